"""mission.runtime.BoundedRun: the event loop of `uavloc sim`/`fly` ends even when a blocking call
of the vehicle library never returns (the MAVSDK 4.1 wedge), and reports it."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import threading
import time

import numpy as np
import pytest

from mission.runtime import EXIT_INTERRUPTED, BoundedRun
from uavloc.errors import VehicleError


def test_a_call_stuck_in_the_executor_does_not_hold_the_loop_and_is_reported() -> None:
    release = threading.Event()

    async def mission() -> str:
        loop = asyncio.get_running_loop()
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(0.2):
                await loop.run_in_executor(None, release.wait)  # a MAVSDK call that never returns
        return "result"

    runner = BoundedRun(shutdown_timeout_s=0.5)
    try:
        assert runner.run(mission()) == "result"
        assert runner.stuck
    finally:
        release.set()


def test_a_clean_run_is_not_stuck_and_errors_propagate() -> None:
    async def ok() -> int:
        await asyncio.to_thread(lambda: None)
        return 3

    runner = BoundedRun(shutdown_timeout_s=2.0)
    assert runner.run(ok()) == 3 and not runner.stuck

    async def fails() -> None:
        raise VehicleError("refused")

    with pytest.raises(VehicleError, match="refused"):
        BoundedRun().run(fails())


@pytest.mark.sim
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_sigterm_or_sighup_during_the_survey_sends_the_vehicle_home(tmp_path, signum) -> None:
    """Issue 21 #1: a `kill` or a dropped terminal during `uavloc fly`'s survey ends the mission as
    Ctrl-C does: RTL (the vehicle seen returning home), the log closed with its end record, exit 130."""
    from mission.log import read_mission_log
    from tests.fly_rig import REPO, external_fly_rig, rtt_lines, wait_for

    out = tmp_path / "out"
    log_path = out / "mission.jsonl"
    with external_fly_rig(tmp_path, speedup=20.0) as rig:
        proc = subprocess.Popen(rig.fly_args("--out", str(out)), cwd=REPO, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            wait_for(lambda: rtt_lines(log_path) >= 5, 90, "5 measurements", proc)
            home = np.asarray(rig.vehicle.state().home_enu_m)
            proc.send_signal(signum)
            _out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        state = rig.vehicle.state()
        d0_m = float(np.linalg.norm((state.pos_enu_m - home)[:2]))
        time.sleep(1.0)
        d1_m = float(np.linalg.norm((rig.vehicle.state().pos_enu_m - home)[:2]))
    assert proc.returncode == EXIT_INTERRUPTED, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    # returning home, or (when uavloc took longer to exit than the 20x-speed return: a loaded
    # machine) already landed there; a vehicle left alone would hover in Hold where it was
    landed_home = not state.in_air and d0_m < 5.0
    assert state.mode == "return_to_launch" or landed_home, (state.mode, state.in_air, d0_m)
    # closing in on home, or over it already (descending: the true position then wanders by the GPS
    # error around the home the vehicle's estimate holds)
    assert d1_m < d0_m or not state.in_air or d0_m < 5.0, (d0_m, d1_m)
    kinds = [e.get("kind", "") for e in read_mission_log(log_path).events]
    assert kinds[-3:] == ["interrupted", "rtl", "end"], kinds[-5:]
    last = log_path.read_bytes().rstrip(b"\n").rsplit(b"\n", 1)[-1]
    assert b'"kind":"end"' in last, last
