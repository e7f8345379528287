"""A real OAI gNB (`nr-softmodem`) and its nrUE(s) (`nr-uesoftmodem`) over rfsim, started and stopped
by `uavloc sim --oai` (docs/oai-in-the-loop.md). Each gets SIGTERM when the thread that started it
ends, however the Python process died (PR_SET_PDEATHSIG).

:class:`OaiPair` writes the configuration files (sitl_scenarios.oai.conf) into its run folder,
starts the gNB (its T server on a free port), and — when asked, after uavloc's T client is
connected, the only time a UE's absolute TA (its RAR) can be seen — each nrUE at rfsim offset 0,
waiting for the gNB's `CFRA procedure succeeded` line that names the UE's C-RNTI. Each process runs
without CAP_SYS_NICE at nice 19 in a session of its own; closing sends SIGTERM to the UEs then the
gNB, then SIGKILL to what is left of each process group (with `--T_stdout 2` nr-softmodem forks a
T process that outlives it).

:class:`UeTelnet` is the nrUE's own telnet server (module rfsimu): `setdistance` on its
`rfsimu_channel_enB0` (the downlink) and `vtime`. Nobody else uses it, so the connection is held.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import os
import re
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

from sitl_scenarios.oai.channel import parse_set_offset, parse_vtime
from sitl_scenarios.oai.conf import NRUE_ORDER_ENV, OaiPorts, gnb_command, gnb_conf, ue_command, ue_conf
from sitl_scenarios.px4_sitl import terminate_with_parent
from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

#: the nrUE's channel: on the rfsim client (the UE) the model is named after the gNB (simulator.c)
UE_CHANNEL = "rfsimu_channel_enB0"
#: the gNB's line when a --do-ra UE is attached ("(rnti 0x6940) CFRA procedure succeeded!")
CFRA_DONE = re.compile(r"\(rnti 0x([0-9a-f]{4})\) CFRA procedure succeeded")
#: the gNB's pre-configured UE (--do-ra: the only one it will take), and its removal
CFRA_ADDED = re.compile(r"Added new CFRA process for UE RNTI ([0-9a-f]{4})")
RNTI_REMOVED = "Remove NR rnti 0x{rnti}"
SET_ANSWER = re.compile(r"new_offset \d+, new \(exact\) distance [0-9.]+ m, new delay")
VERSION_LINE = re.compile(r"\[HW\] I (Version: [^\n]*)")
GNB_START_TIMEOUT_S = 180.0
ATTACH_TIMEOUT_S = 240.0


class AttachLost(SimulatorError):
    """The gNB removed its one pre-configured UE before it attached (a loaded machine's MAC missed
    the RA window: "exceeded RA window ... cannot schedule Msg2"); in --do-ra mode no other UE is
    taken, so only a new gNB can attach one."""


def attach_state(gnb_log: str, known: set[int]) -> tuple[int | None, str | None]:
    """(the C-RNTI of a UE the gNB says is attached and not in `known`, or None; why the attach can
    no longer happen, or None) from the gNB's log text."""
    for m in CFRA_DONE.finditer(gnb_log):
        rnti = int(m.group(1), 16)
        if rnti not in known:
            return rnti, None
    for m in CFRA_ADDED.finditer(gnb_log):
        removed = gnb_log.find(RNTI_REMOVED.format(rnti=m.group(1)), m.end())
        if removed >= 0:
            late = "exceeded RA window" in gnb_log[m.end():removed]
            return None, (f"the OAI gNB removed its pre-configured UE {m.group(1)} before it attached"
                          + (" (its MAC missed the RA window: the machine is loaded)" if late else ""))
    return None, None


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def binary_id(path: Path) -> str:
    """sha256 of a binary, first 16 hex digits (names the exact build in the log)."""
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:16]


def _port_open(port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
        return True
    return False


@dataclass
class OaiPair:
    """See the module docstring. build: the OAI build folder; run_dir: this run's folder (confs,
    logs, the gNB's raw files); n_ues: how many nrUEs; rtt: the build is patched
    (conf.rtt_missing) and the `rtt` mode measures: the gNB loads the telnet module rtt, the nrUEs
    run with NRUE_PDCCH_ORDER_CSS=1."""

    build: Path
    run_dir: Path
    n_ues: int = 1
    rtt: bool = False
    ports: OaiPorts | None = None
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    #: every command line started, in order (the mission log's header names them)
    command_lines: list[list[str]] = field(default_factory=list)
    _t_start: float | None = None

    @property
    def gnb_log(self) -> Path:
        return self.run_dir / "gnb.log"

    def start_gnb(self) -> None:
        """:meth:`spawn_gnb` then :meth:`wait_gnb`."""
        self.spawn_gnb()
        self.wait_gnb()

    def spawn_gnb(self) -> None:
        """Write the confs and start nr-softmodem (from the thread that lives as long as it: it gets
        SIGTERM when that thread ends)."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.ports = OaiPorts(free_tcp_port(), free_tcp_port(), free_tcp_port(),
                              tuple(free_tcp_port() for _ in range(self.n_ues)))
        (self.run_dir / "gnb.conf").write_text(gnb_conf(self.ports))
        for i in range(self.n_ues):
            (self.run_dir / f"ue{i}.conf").write_text(ue_conf(self.ports, i))
        self._start("gnb", gnb_command(self.build, self.run_dir / "gnb.conf", self.ports, rtt=self.rtt))

    def wait_gnb(self) -> None:
        """Wait until the gNB's telnet listens and it wrote the UE's rbconfig.raw (SimulatorError,
        naming the log, when it exits or takes GNB_START_TIMEOUT_S). Blocking: run it in a thread."""
        deadline = time.monotonic() + GNB_START_TIMEOUT_S
        # never probe the T port with a bare connect: OAI's T server takes a client that leaves
        # without its event mask as fatal
        while not (_port_open(self.ports.gnb_telnet) and (self.run_dir / "rbconfig.raw").is_file()):
            self._check_alive("gnb")
            if time.monotonic() > deadline:
                raise SimulatorError(f"the OAI gNB did not start within {GNB_START_TIMEOUT_S:g} s ({self.gnb_log})")
            time.sleep(0.2)

    def start_ue(self, index: int) -> None:
        """Start nrUE `index` at rfsim offset 0 (attach near; the bridge walks it out)."""
        self._start(f"ue{index}", ue_command(self.build, self.run_dir / f"ue{index}.conf"),
                    NRUE_ORDER_ENV if self.rtt else {})

    async def wait_attached(self, known: set[int], timeout_s: float = ATTACH_TIMEOUT_S) -> int:
        """The C-RNTI of the next UE the gNB says is attached (not in `known`); AttachLost when the
        gNB dropped its pre-configured UE first, SimulatorError when an OAI process exits or
        timeout_s passes."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for name in self.procs:
                self._check_alive(name)
            text = self.gnb_log.read_text(errors="replace") if self.gnb_log.is_file() else ""
            rnti, lost = attach_state(text, known)
            if rnti is not None:
                return rnti
            if lost is not None:
                raise AttachLost(lost)
            await asyncio.sleep(0.5)
        raise SimulatorError(f"no nrUE attached to the OAI gNB within {timeout_s:g} s ({self.gnb_log})")

    def version(self) -> dict:
        """What names this gNB: the `Version:` line of its log (empty fields when built outside
        git), the build folder and the binaries' sha256."""
        line = None
        if self.gnb_log.is_file():
            m = VERSION_LINE.search(self.gnb_log.read_text(errors="replace")[:200_000])
            line = m.group(1).strip() if m else None
        return {"version_line": line, "build": str(self.build),
                "nr_softmodem_sha256": binary_id(self.build / "nr-softmodem"),
                "nr_uesoftmodem_sha256": binary_id(self.build / "nr-uesoftmodem")}

    def _start(self, name: str, cmd: list[str], extra_env: dict[str, str] | None = None) -> None:
        env = dict(os.environ, **(extra_env or {}), LD_LIBRARY_PATH=os.pathsep.join(
            p for p in (str(self.build), os.environ.get("LD_LIBRARY_PATH", "")) if p))
        for _ in range(20):  # another build may relink a binary in place: briefly missing
            if Path(cmd[cmd.index("-O") - 1]).is_file():
                break
            time.sleep(0.5)
        with (self.run_dir / f"{name}.log").open("w") as fh:
            self.procs[name] = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                                cwd=self.run_dir, env=env, start_new_session=True,
                                                preexec_fn=terminate_with_parent)
        self.command_lines.append([f"{k}={v}" for k, v in (extra_env or {}).items()] + cmd)
        if self._t_start is None:
            self._t_start = time.monotonic()
        log.info("OAI %s started (pid %d): %s", name, self.procs[name].pid, " ".join(self.command_lines[-1]))

    def _check_alive(self, name: str) -> None:
        proc = self.procs[name]
        if proc.poll() is not None:
            raise SimulatorError(f"OAI's {name} exited with status {proc.returncode} (log {self.run_dir / name}.log)")

    def exited(self) -> list[str]:
        """The OAI processes that have exited."""
        return [n for n, p in self.procs.items() if p.poll() is not None]

    def cpu_s(self) -> dict[str, float]:
        """CPU seconds (user + system) used so far by each OAI process group ("gnb", "ue0", ...: the
        process and what it forked, e.g. the gNB's T process), from /proc."""
        tick = os.sysconf("SC_CLK_TCK")
        out = dict.fromkeys(self.procs, 0.0)
        groups = {p.pid: n for n, p in self.procs.items()}
        for _pid, fields in _proc_stats():
            name = groups.get(int(fields[2]))  # field 5: the process group
            if name is not None:
                out[name] += (int(fields[11]) + int(fields[12])) / tick  # fields 14, 15: utime, stime
        return out

    def close(self) -> None:
        """SIGTERM to the UEs, then the gNB (SIGKILL after 10 s), then SIGKILL to each process group."""
        if self.procs and self._t_start is not None:
            cpu, wall = self.cpu_s(), time.monotonic() - self._t_start
            log.info("OAI used %.0f CPU-s in %.0f s of wall time: %.2f cores (%s)", sum(cpu.values()), wall,
                     sum(cpu.values()) / max(wall, 1e-9), ", ".join(f"{n} {c:.0f} s" for n, c in cpu.items()))
        order = [n for n in self.procs if n != "gnb"] + (["gnb"] if "gnb" in self.procs else [])
        for name in order:
            proc = self.procs[name]
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.terminate()
                try:
                    proc.wait(timeout=10.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=5.0)
        for proc in self.procs.values():
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGKILL)  # each in a session of its own: its T fork too
        # SIGKILL is not instant (a gNB frees some GB): return when no member is left but zombies
        deadline = time.monotonic() + 10.0
        while self._group_members() and time.monotonic() < deadline:
            time.sleep(0.1)
        left = self._group_members()
        if left:
            log.warning("OAI processes %s did not end within 10 s of SIGKILL", left)

    def _group_members(self) -> list[int]:
        """The live (not zombie) processes of the pairs' process groups, from /proc."""
        groups = {p.pid for p in self.procs.values()}
        return [pid for pid, fields in _proc_stats() if int(fields[2]) in groups and fields[0] not in ("Z", "X")]


def _proc_stats():
    """(pid, the fields of /proc/<pid>/stat after the command name: state first) of every process."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            yield int(stat.parent.name), stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue


class UeTelnet:
    """An nrUE's telnet server (see the module docstring); request_timeout_s bounds each answer."""

    def __init__(self, port: int, request_timeout_s: float = 3.0) -> None:
        self.port = port
        self.request_timeout_s = request_timeout_s
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._buf = ""

    async def __aenter__(self) -> UeTelnet:
        deadline = time.monotonic() + 30.0  # the nrUE opens its telnet soon after it starts
        while True:
            try:
                self._reader, self._writer = await asyncio.wait_for(
                    asyncio.open_connection("127.0.0.1", self.port), self.request_timeout_s)
                return self
            except (OSError, TimeoutError) as exc:
                if time.monotonic() > deadline:
                    raise SimulatorError(f"the nrUE's telnet on port {self.port} did not open: {exc}") from exc
                await asyncio.sleep(0.5)

    async def __aexit__(self, *exc: object) -> None:
        if self._writer is not None:
            with contextlib.suppress(OSError, ConnectionError):
                self._writer.write(b"exit\n")
                self._writer.close()
            self._writer = None

    async def _ask(self, line: str, answer: re.Pattern) -> str:
        """Send `line`, read until `answer` matches what came after it (rfsimu prints after the prompt)."""
        if self._writer is None or self._reader is None:
            raise SimulatorError("the nrUE's telnet is not connected")
        self._buf = ""
        self._writer.write(line.encode() + b"\n")
        await self._writer.drain()
        deadline = time.monotonic() + self.request_timeout_s
        while not answer.search(self._buf):
            left = deadline - time.monotonic()
            if left <= 0:
                raise SimulatorError(f"the nrUE's telnet (port {self.port}) did not answer {line!r} within "
                                     f"{self.request_timeout_s:g} s (got {self._buf[-200:]!r})")
            try:
                chunk = await asyncio.wait_for(self._reader.read(4096), left)
            except TimeoutError:
                continue
            if not chunk:
                raise SimulatorError(f"the nrUE's telnet (port {self.port}) closed the connection")
            self._buf += chunk.decode(errors="replace")
        return self._buf

    async def set_distance(self, metres: int) -> int:
        """`rfsimu setdistance rfsimu_channel_enB0 <metres>` -> the offset OAI set [samples]."""
        text = await self._ask(f"rfsimu setdistance {UE_CHANNEL} {int(metres)}", SET_ANSWER)
        return parse_set_offset(text)

    async def vtime_s(self) -> float:
        """rfsim's virtual time on this nrUE [s] (`rfsimu vtime`)."""
        return parse_vtime(await self._ask("rfsimu vtime", re.compile(r"sample_rate [0-9.]+")))
