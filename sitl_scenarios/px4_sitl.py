"""The user's own PX4 SITL build, started and stopped from Python.

Used by the `px4` tests (tests/conftest.py), `benchmarks/px4.py` and `benchmarks/px4_legs.py`.
`UAVLOC_PX4` names a PX4-Autopilot build folder (`.../PX4-Autopilot/build/px4_sitl_default`, made
by `make px4_sitl`); nothing of PX4 ships with uavloc. Two parts:

- :class:`Px4Sitl`: one PX4 instance started the way `make px4_sitl sihsim_quadx` starts it (PX4's
  `simulator_sih/CMakeLists.txt`: ``PX4_SIM_MODEL=sihsim_quadx PX4_SIMULATOR=sihsim bin/px4``), the
  way PX4's own MAVSDK tests run it unattended (`-d`, no interactive shell): ``bin/px4 -d -i
  INSTANCE -w WORKDIR BUILD/etc`` with ``PX4_SIM_SPEED_FACTOR``. PX4 links `WORKDIR/etc` to the
  build's ROMFS (`BUILD/etc`), keeps its parameters, dataman and logs in WORKDIR, runs
  `etc/init.d-posix/rcS INSTANCE`, which picks airframe 10040_sihsim_quadx (SYS_AUTOSTART) from
  PX4_SIM_MODEL. Its own process group, its output kept (and written to a file), ready when it
  prints `Ready for takeoff!`, stopped with SIGTERM (SIGKILL after a grace time).
- :class:`UdpRelay`: a UDP relay between PX4's API link and a MAVLink client that can stop
  relaying for a while (a paused vehicle link), in both directions.

Ports (PX4's stock `px4-rc.mavlink`, unchanged): instance i sends its API link to UDP 14540+i
(MAVSDK: ``udpin://127.0.0.1:14540+i``) for i <= 9; every instance above 9 sends it to 14549, so
the tests use instances 1-8 only. Its GCS link listens on 18570+i and answers whoever talks to it
first (MAVSDK: ``udpout://127.0.0.1:18570+i``), so no two instances' GCS links collide.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

#: environment variable naming the user's PX4 build folder (build/px4_sitl_default)
BUILD_ENV = "UAVLOC_PX4"
#: what PX4 prints when it can fly
READY_TEXT = "Ready for takeoff!"
#: the SIH quadrotor, PX4's simulator without Gazebo (airframe 10040_sihsim_quadx)
SIM_MODEL = "sihsim_quadx"


def api_port(instance: int) -> int:
    """UDP port PX4 instance `instance` sends its API (offboard) link to (stock px4-rc.mavlink)."""
    return 14540 + int(instance) if int(instance) <= 9 else 14549


def gcs_port(instance: int) -> int:
    """UDP port PX4 instance `instance` listens on for its GCS link."""
    return 18570 + int(instance)


def build_from_env(env: dict[str, str] | None = None) -> Path | None:
    """The PX4 build folder `UAVLOC_PX4` names (None when unset or empty)."""
    value = (os.environ if env is None else env).get(BUILD_ENV, "").strip()
    return Path(value).expanduser() if value else None


def missing_requirement(build: Path | None) -> str | None:
    """Why PX4 SITL cannot start from `build` (unset, not a px4_sitl build, `bc` missing), or None.

    The sentence names UAVLOC_PX4 and what it must point to.
    """
    if build is None:
        return (f"{BUILD_ENV} is not set: set it to your PX4-Autopilot build folder "
                "(PX4-Autopilot/build/px4_sitl_default, made by `make px4_sitl`) to run the PX4 tests")
    build = Path(build)
    px4, rcs = build / "bin" / "px4", build / "etc" / "init.d-posix" / "rcS"
    if not (px4.is_file() and os.access(px4, os.X_OK)):
        return f"{BUILD_ENV}={build} has no executable bin/px4 (build it with `make px4_sitl` in PX4-Autopilot)"
    if not rcs.is_file():
        return f"{BUILD_ENV}={build} has no etc/init.d-posix/rcS (PX4's ROMFS of a px4_sitl build)"
    airframes = build / "etc" / "init.d-posix" / "airframes"
    if airframes.is_dir() and not any(airframes.glob(f"*_{SIM_MODEL}")):
        return f"{BUILD_ENV}={build} has no {SIM_MODEL} airframe in etc/init.d-posix/airframes"
    if shutil.which("bc") is None and _scripts_use_bc(build / "etc" / "init.d-posix"):
        return "PX4's start-up script needs `bc` (apt-get install bc)"
    return None


def _scripts_use_bc(init_dir: Path) -> bool:
    pipe_to_bc = re.compile(r"\|\s*bc\b")
    return any(pipe_to_bc.search(f.read_text(errors="replace")) for f in init_dir.glob("*rc*") if f.is_file())


def instance_busy(instance: int) -> bool:
    """True when a PX4 server already runs as `instance` on this machine (PX4 holds an exclusive
    lock on /tmp/px4_lock-<instance> while it runs) or one of its UDP ports is taken."""
    lock = Path(f"/tmp/px4_lock-{int(instance)}")
    if lock.exists():
        try:
            with open(lock, "rb") as fh:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                fcntl.flock(fh, fcntl.LOCK_UN)
        except OSError:
            return True
    for port in (api_port(instance), 14580 + int(instance), gcs_port(instance)):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return True
    return False


class Px4Sitl:
    """One PX4 SITL instance of the user's build. See the module docstring.

    build: the PX4 build folder (`build/px4_sitl_default`, :func:`build_from_env`); instance: PX4
    instance (ports above); speed: PX4_SIM_SPEED_FACTOR; workdir: a fresh directory for parameters,
    dataman and logs; home: (lat_deg, lon_deg, alt_amsl_m) or None for PX4's default (SIH: near
    Zurich); output: file that gets PX4's console output.
    """

    def __init__(self, build: Path, instance: int, speed: float, workdir: Path,
                 home: tuple[float, float, float] | None = None, output: Path | None = None):
        self.build = Path(build).resolve()
        self.instance = int(instance)
        self.speed = float(speed)
        self.workdir = Path(workdir)
        self.home = home
        self.output = Path(output) if output is not None else self.workdir.with_suffix(".log")
        self.lines: list[str] = []
        self._ready = threading.Event()
        self._proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None

    @property
    def api_port(self) -> int:
        return api_port(self.instance)

    @property
    def gcs_port(self) -> int:
        return gcs_port(self.instance)

    @property
    def api_url(self) -> str:
        """MAVSDK URL of the API link (what `uavloc sim --connect` is given)."""
        return f"udpin://127.0.0.1:{self.api_port}"

    @property
    def gcs_url(self) -> str:
        """MAVSDK URL of the GCS link (a second client: observer, parameters, failure injection).
        The client talks first; PX4 then answers to where the client's datagrams came from."""
        return f"udpout://127.0.0.1:{self.gcs_port}"

    def text(self) -> str:
        return "".join(self.lines)

    def command_line(self) -> tuple[list[str], dict[str, str]]:
        """(argv, the environment variables PX4 is given on top of this process's)."""
        env = {"PX4_SIM_MODEL": SIM_MODEL, "PX4_SIMULATOR": "sihsim", "PX4_SIM_SPEED_FACTOR": f"{self.speed:g}"}
        if self.home is not None:
            env.update(PX4_HOME_LAT=repr(self.home[0]), PX4_HOME_LON=repr(self.home[1]),
                       PX4_HOME_ALT=repr(self.home[2]))
        argv = [str(self.build / "bin" / "px4"), "-d", "-i", str(self.instance), "-w", str(self.workdir.resolve()),
                str(self.build / "etc")]
        return argv, env

    def start(self) -> None:
        why = missing_requirement(self.build)
        if why is not None:
            raise SimulatorError(why)
        self.workdir.mkdir(parents=True, exist_ok=True)
        argv, extra = self.command_line()
        log.info("starting PX4 SITL: %s %s", " ".join(f"{k}={v}" for k, v in extra.items()), " ".join(argv))
        self._proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                      env=dict(os.environ, **extra), cwd=self.workdir, start_new_session=True,
                                      preexec_fn=terminate_with_parent)
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
        exe = self.build / "bin" / f"px4-{module}"
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
        # a module command PX4 started may outlive it for a moment
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


def terminate_with_parent() -> None:
    """In a simulator's process (Linux; Popen's preexec_fn): SIGTERM when the Python thread that
    started it dies, even without running its cleanup (PX4 and OAI then shut down), so an aborted
    run leaves no simulator behind. Start it from a thread that lives as long as it (the event
    loop's, not a worker's)."""
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
