"""Real PX4 SITL (the shared bundle `../shared/px4-sitl/`) started and stopped from Python.

Used by the `px4` tests (tests/conftest.py) and `benchmarks/px4.py`. Three parts:

- :func:`materialize`: a working copy of the bundle. The bundle as shipped is read-only and its
  `bin/px4-<module>` commands are 3-byte plain files containing ``px4`` where PX4's build makes
  symbolic links to `px4` (PX4's start-up script runs them: `px4-param: Permission denied`, `no
  autostart file found`). The copy replaces each such file by a link to `px4`; every other file
  (`px4-alias.sh`, the binary, `etc/`) is copied as it is, except one line of PX4's
  `px4-rc.mavlink`, see :data:`API_PORT_RULE`.
- :class:`Px4Sitl`: one PX4 instance (`px4-sitl -i INSTANCE -s SPEED -w WORKDIR`) in its own
  process group, its output kept (and written to a file), ready when it prints `Ready for
  takeoff!`, stopped with SIGTERM (SIGKILL after a grace time).
- :class:`UdpRelay`: a UDP relay between PX4's API link and a MAVLink client that can stop
  relaying for a while (a paused vehicle link), in both directions.

Ports (PX4's `px4-rc.mavlink`): instance i sends its API link to UDP 14540+i (MAVSDK:
``udpin://127.0.0.1:14540+i``) and listens on 14580+i; its GCS link listens on 18570+i and sends
to ``PX4_GCS_REMOTE_PORT``, which must then differ from 18570+i (the bundle's default, 18570+i,
is PX4's own port: nobody else can listen there); here 14690+i unless given.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

#: where the shared bundle sits beside a checkout (../shared/px4-sitl)
DEFAULT_BUNDLE = Path(__file__).resolve().parents[2] / "shared" / "px4-sitl"
#: what PX4 prints when it can fly
READY_TEXT = "Ready for takeoff!"
#: PX4's `px4-rc.mavlink` sends the API link of every instance above 9 to the same UDP port 14549
#: (PX4's multi-vehicle convention). Two test runs (or a colleague's instance 9) would then share
#: one port, so the working copy drops that rule: instance i always sends to 14540+i.
API_PORT_RULE = '[ "$px4_instance" -gt 9 ] && udp_offboard_port_remote=14549'


def api_port(instance: int) -> int:
    """UDP port PX4 instance `instance` sends its API (offboard) link to."""
    return 14540 + int(instance)


def default_gcs_port(instance: int) -> int:
    """UDP port PX4 instance `instance` is told to send its GCS link to (PX4_GCS_REMOTE_PORT)."""
    return 14690 + int(instance)


def missing_requirement(bundle: Path = DEFAULT_BUNDLE) -> str | None:
    """Why PX4 SITL cannot start here (bundle absent, `bc` missing), or None."""
    bundle = Path(bundle)
    if not (bundle / "px4-sitl").is_file() or not (bundle / "bin" / "px4").is_file():
        return f"PX4 SITL bundle not found at {bundle}"
    if shutil.which("bc") is None:
        return "PX4's start-up script needs `bc` (apt-get install bc)"
    return None


def instance_busy(instance: int) -> bool:
    """True when a PX4 server already runs as `instance` on this machine (PX4 holds an exclusive
    `flock` on /tmp/px4_lock-<instance> while it runs) or one of its UDP ports is taken."""
    lock = Path(f"/tmp/px4_lock-{int(instance)}")
    if lock.exists():
        try:
            with open(lock, "rb") as fh:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                fcntl.flock(fh, fcntl.LOCK_UN)
        except OSError:
            return True
    for port in (api_port(instance), 14580 + int(instance), 18570 + int(instance), default_gcs_port(instance)):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return True
    return False


def _is_module_stub(path: Path) -> bool:
    """A `bin/px4-<module>` that should be a link to `px4` but is a plain file saying `px4`."""
    if path.is_symlink() or not path.is_file() or not path.name.startswith("px4-"):
        return False
    if path.stat().st_size > 16:
        return False
    return path.read_bytes().strip() == b"px4"


def materialize(bundle: Path, dest: Path) -> Path:
    """A working copy of the PX4 SITL bundle in `dest` (created; reused when already complete).

    Returns the launcher `dest/px4-sitl`. Module stubs become symbolic links to `px4`; the copy is
    writable by its owner so it can be removed.
    """
    bundle, dest = Path(bundle), Path(dest)
    launcher = dest / "px4-sitl"
    done = dest / ".materialized"
    if done.is_file():
        return launcher
    why = missing_requirement(bundle)
    if why is not None and "bundle" in why:
        raise SimulatorError(why)
    if dest.exists():
        _make_writable(dest)
        shutil.rmtree(dest)
    shutil.copytree(bundle, dest, symlinks=True)
    _make_writable(dest)
    linked = 0
    for f in sorted((dest / "bin").iterdir()):
        if _is_module_stub(f):
            f.unlink()
            f.symlink_to("px4")
            linked += 1
    rc = dest / "etc" / "init.d-posix" / "px4-rc.mavlink"
    if rc.is_file():
        text = rc.read_text()
        if API_PORT_RULE in text:
            rc.write_text(text.replace(API_PORT_RULE, "# (uavloc test copy) " + API_PORT_RULE))
    done.write_text(f"{linked} module links\n")
    log.info("PX4 SITL working copy in %s (%d module commands linked to px4)", dest, linked)
    return launcher


def _make_writable(root: Path) -> None:
    for dirpath, _dirnames, filenames in os.walk(root):
        os.chmod(dirpath, 0o755)
        for name in filenames:
            p = Path(dirpath) / name
            if not p.is_symlink():
                p.chmod(p.stat().st_mode | 0o200)


class Px4Sitl:
    """One PX4 SITL instance. See the module docstring.

    launcher: a working copy's `px4-sitl` (:func:`materialize`); instance: PX4 instance (ports
    above); speed: PX4_SIM_SPEED_FACTOR; workdir: a fresh directory for parameters, dataman and
    logs; home: (lat_deg, lon_deg, alt_amsl_m) or None for the bundle's; output: file that gets
    PX4's console output; gcs_port: where PX4 sends its GCS link (default :func:`default_gcs_port`).
    """

    def __init__(self, launcher: Path, instance: int, speed: float, workdir: Path,
                 home: tuple[float, float, float] | None = None, output: Path | None = None,
                 gcs_port: int | None = None):
        self.launcher = Path(launcher)
        self.instance = int(instance)
        self.speed = float(speed)
        self.workdir = Path(workdir)
        self.home = home
        self.output = Path(output) if output is not None else self.workdir.with_suffix(".log")
        self.gcs_port = default_gcs_port(self.instance) if gcs_port is None else int(gcs_port)
        self.lines: list[str] = []
        self._ready = threading.Event()
        self._proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None

    @property
    def api_port(self) -> int:
        return api_port(self.instance)

    @property
    def api_url(self) -> str:
        """MAVSDK URL of the API link (what `uavloc sim --connect` is given)."""
        return f"udpin://127.0.0.1:{self.api_port}"

    @property
    def gcs_url(self) -> str:
        """MAVSDK URL of the GCS link (a second client: observer, parameters, failure injection)."""
        return f"udpin://127.0.0.1:{self.gcs_port}"

    def text(self) -> str:
        return "".join(self.lines)

    def start(self) -> None:
        self.workdir.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ, PX4_GCS_REMOTE_PORT=str(self.gcs_port))
        if self.home is not None:
            env.update(PX4_HOME_LAT=repr(self.home[0]), PX4_HOME_LON=repr(self.home[1]),
                       PX4_HOME_ALT=repr(self.home[2]))
        cmd = [str(self.launcher), "-i", str(self.instance), "-s", f"{self.speed:g}", "-w", str(self.workdir)]
        log.info("starting PX4 SITL: %s", " ".join(cmd))
        self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                      env=env, cwd=self.workdir, start_new_session=True,
                                      preexec_fn=_terminate_with_parent)
        self._reader = threading.Thread(target=self._read, name=f"px4-{self.instance}-out", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        with open(self.output, "w") as fh:
            for raw in self._proc.stdout:
                line = raw.decode("utf-8", "replace")
                self.lines.append(line)
                fh.write(line)
                fh.flush()
                if READY_TEXT in line:
                    self._ready.set()

    def wait_ready(self, timeout_s: float) -> bool:
        """True once PX4 printed `Ready for takeoff!` (False after timeout_s wall seconds or when
        PX4 exited first)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._ready.wait(0.2):
                return True
            if self._proc is None or self._proc.poll() is not None:
                return False
        return self._ready.is_set()

    def command(self, module: str, *args: str, timeout_s: float = 10.0) -> str:
        """Run a command on this PX4's console (`bin/px4-<module> --instance N ARGS`, PX4's own
        client, e.g. `command("sensor_gps_sim", "stop")`); returns its output."""
        exe = self.launcher.parent / "bin" / f"px4-{module}"
        if not exe.exists():
            raise SimulatorError(f"PX4 has no module command {exe.name}")
        r = subprocess.run([str(exe), "--instance", str(self.instance), *args], capture_output=True, text=True,
                           timeout=timeout_s, cwd=self.workdir)
        return (r.stdout + r.stderr).strip()

    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self, grace_s: float = 10.0) -> int | None:
        """SIGTERM to PX4's process group, SIGKILL after grace_s; returns the exit code."""
        proc, self._proc = self._proc, None
        if proc is None:
            return None
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                log.warning("PX4 instance %d ignored SIGTERM: killed", self.instance)
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5.0)
        # PX4's daemon may outlive the launcher's shell for a moment
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
        if self._reader is not None:
            self._reader.join(2.0)
        return proc.returncode

    def __enter__(self) -> Px4Sitl:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _terminate_with_parent() -> None:
    """In the launcher's child process (Linux): SIGTERM when the Python process that started it
    dies, even without running its cleanup (the launcher then stops PX4), so an aborted test run
    leaves no PX4 behind."""
    with contextlib.suppress(Exception):
        import ctypes

        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


class UdpRelay:
    """Relays UDP datagrams between PX4's API link and a client, and can pause.

    PX4 sends to `listen_port` (its API port); the relay forwards to the client at
    `client_port` on 127.0.0.1 (MAVSDK ``udpin://127.0.0.1:client_port``) and sends the
    client's answers back to where PX4's datagrams came from. While paused, datagrams in both
    directions are dropped (a vehicle link that goes silent).
    """

    def __init__(self, listen_port: int, client_port: int, host: str = "127.0.0.1"):
        self.host = host
        self.listen_port = int(listen_port)
        self.client_port = int(client_port)
        self.paused = threading.Event()
        self.dropped = 0
        self.relayed = 0
        self._stop = threading.Event()
        self._px4_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._px4_side.bind((host, self.listen_port))
        self._client_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._client_side.bind((host, 0))
        self._px4_addr: tuple[str, int] | None = None
        self._threads = [threading.Thread(target=self._pump, args=(self._px4_side, True), daemon=True,
                                          name="relay-px4"),
                         threading.Thread(target=self._pump, args=(self._client_side, False), daemon=True,
                                          name="relay-client")]

    def _pump(self, sock: socket.socket, from_px4: bool) -> None:
        sock.settimeout(0.2)
        while not self._stop.is_set():
            try:
                data, addr = sock.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if from_px4:
                self._px4_addr = addr
            if self.paused.is_set():
                self.dropped += 1
                continue
            try:
                if from_px4:
                    self._client_side.sendto(data, (self.host, self.client_port))
                elif self._px4_addr is not None:
                    self._px4_side.sendto(data, self._px4_addr)
                self.relayed += 1
            except OSError as exc:  # client not listening yet: ICMP port unreachable
                log.debug("relay: %s", exc)

    def pause(self) -> None:
        self.paused.set()

    def resume(self) -> None:
        self.paused.clear()

    def __enter__(self) -> UdpRelay:
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(1.0)
        self._px4_side.close()
        self._client_side.close()
