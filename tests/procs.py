"""Stopping the subprocesses the tests start (a launcher, a simulator, `uavloc view`)."""

from __future__ import annotations

import subprocess


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
