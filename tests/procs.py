"""Starting and stopping the subprocesses the tests start (a launcher, a simulator, `uavloc view`)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path


def stop_process(proc: subprocess.Popen, grace_s: float, kill_wait_s: float | None = None) -> None:
    """SIGTERM to a running `proc`, SIGKILL if it has not exited after grace_s [s]; then wait for
    it (at most kill_wait_s [s], None: as long as it takes)."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=kill_wait_s)


@contextlib.contextmanager
def standalone_trace_gnb(scenario: str, cwd: Path, *extra: str) -> Iterator[tuple[str, str]]:
    """`python -m sitl_scenarios.gnb --scenario SCENARIO` with a T tracer, on free loopback ports, its
    UAV held 40 m above the origin (and `extra` arguments): yields (telnet port, T port) as text,
    read from its start-up line."""
    srv = subprocess.Popen([sys.executable, "-m", "sitl_scenarios.gnb", "--scenario", scenario, "--host", "127.0.0.1",
                            "--port", "0", "--t-port", "0", "--static-enu", "0", "0", "40", *extra],
                           cwd=cwd, stderr=subprocess.PIPE, text=True)
    try:
        line = ""
        while "T tracer on" not in line:
            line = srv.stderr.readline()
            assert line, "the simulated gNB did not start"
        yield line.split(" on 127.0.0.1:")[1].split(",")[0], line.rsplit(":", 1)[1].strip()
    finally:
        srv.terminate()
        srv.wait(10)
