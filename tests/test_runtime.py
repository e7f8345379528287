"""mission.runtime.BoundedRun: the event loop of `uavloc sim`/`fly` ends even when a blocking call
of the vehicle library never returns (the MAVSDK 4.1 wedge), and reports it."""

from __future__ import annotations

import asyncio
import threading

import pytest

from mission.runtime import BoundedRun
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
