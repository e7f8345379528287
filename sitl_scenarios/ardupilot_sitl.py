"""The user's own ArduCopter SITL, started and stopped from Python (the `ardupilot` tests).

`UAVLOC_ARDUPILOT` names an ArduCopter SITL binary (`ardupilot/build/sitl/bin/arducopter`, made
by `./waf configure --board sitl && ./waf copter` in ArduPilot's source); nothing of ArduPilot
ships with uavloc. It is started as the recording of ../shared/data/ardupilot-4.7-sitl/ was made:
frame `+`, speed-up, home 43.6143, 7.0716, 150 m, heading 0, ArduPilot's autotest `copter.parm`
defaults (found beside the build, `Tools/autotest/default_params/copter.parm`, or named by
`UAVLOC_ARDUPILOT_DEFAULTS`), a wiped EEPROM in a fresh working directory; SERIAL0 and SERIAL1 sent
to local UDP ports (`--serialN udpclient:127.0.0.1:PORT`, MAVSDK: `udpin://127.0.0.1:PORT`). Its
own process group, its output written to a file, stopped with SIGTERM (SIGKILL after a grace time).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
from pathlib import Path

from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

#: environment variables: the ArduCopter SITL binary, and (optional) its defaults file
BINARY_ENV = "UAVLOC_ARDUPILOT"
DEFAULTS_ENV = "UAVLOC_ARDUPILOT_DEFAULTS"
#: the recording's home: lat, lon [deg], alt AMSL [m], heading [deg]
HOME = (43.6143, 7.0716, 150.0, 0.0)


def binary_from_env(env: dict[str, str] | None = None) -> Path | None:
    value = (os.environ if env is None else env).get(BINARY_ENV, "").strip()
    return Path(value).expanduser() if value else None


def defaults_file(binary: Path, env: dict[str, str] | None = None) -> Path | None:
    """copter.parm: UAVLOC_ARDUPILOT_DEFAULTS, else beside a build of the source tree
    (build/sitl/bin/arducopter → Tools/autotest/default_params/copter.parm)."""
    value = (os.environ if env is None else env).get(DEFAULTS_ENV, "").strip()
    if value:
        return Path(value).expanduser()
    for parent in Path(binary).resolve().parents:
        candidate = parent / "Tools" / "autotest" / "default_params" / "copter.parm"
        if candidate.is_file():
            return candidate
    return None


def missing_requirement(binary: Path | None, env: dict[str, str] | None = None) -> str | None:
    """Why ArduCopter SITL cannot start (unset, not executable, no copter.parm), or None. The
    sentence names UAVLOC_ARDUPILOT and what it must point to."""
    if binary is None:
        return (f"{BINARY_ENV} is not set: set it to your ArduCopter SITL binary (ardupilot/build/sitl/bin/"
                "arducopter, made by `./waf configure --board sitl && ./waf copter`) to run the ArduPilot tests")
    if not (Path(binary).is_file() and os.access(binary, os.X_OK)):
        return f"{BINARY_ENV}={binary} is not an executable ArduCopter SITL binary"
    parm = defaults_file(binary, env)
    if parm is None or not parm.is_file():
        return (f"{BINARY_ENV}={binary}: ArduPilot's Tools/autotest/default_params/copter.parm not found beside "
                f"it; name it with {DEFAULTS_ENV}")
    return None


class ArduCopterSitl:
    """One ArduCopter SITL instance (module docstring); `serial_ports`: the UDP ports SERIAL0,
    SERIAL1, ... send to. A context manager."""

    def __init__(self, binary: Path, instance: int, speedup: float, workdir: Path, serial_ports: list[int],
                 output: Path, defaults: Path | None = None):
        self.binary = Path(binary)
        self.instance = int(instance)
        self.speedup = float(speedup)
        self.workdir = Path(workdir)
        self.serial_ports = list(serial_ports)
        self.output = Path(output)
        self.defaults = defaults or defaults_file(self.binary)
        self._proc: subprocess.Popen | None = None
        self._out = None

    def command(self) -> list[str]:
        home = ",".join(f"{v:g}" for v in HOME)
        cmd = [str(self.binary), "-S", "-w", "--model", "+", "--speedup", f"{self.speedup:g}", "--home", home,
               "-I", str(self.instance)]
        if self.defaults is not None:
            cmd += ["--defaults", str(self.defaults)]
        for k, port in enumerate(self.serial_ports):
            cmd += [f"--serial{k}", f"udpclient:127.0.0.1:{port}"]
        return cmd

    def start(self) -> None:
        if self._proc is not None:
            raise SimulatorError("ArduCopter SITL already started")
        self.workdir.mkdir(parents=True, exist_ok=True)
        self._out = open(self.output, "wb")  # noqa: SIM115 (closed in stop)
        log.info("starting ArduCopter SITL: %s", " ".join(self.command()))
        try:
            self._proc = subprocess.Popen(self.command(), cwd=self.workdir, stdout=self._out,
                                          stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        except OSError as exc:
            self._out.close()
            raise SimulatorError(f"cannot start ArduCopter SITL {self.binary}: {exc}") from exc

    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self, grace_s: float = 5.0) -> None:
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=grace_s)
        if self._out is not None:
            self._out.close()
            self._out = None

    def __enter__(self) -> ArduCopterSitl:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
