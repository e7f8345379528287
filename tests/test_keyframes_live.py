"""One keyframe builder: the keyframes a whole simulated mission hands its estimator are the
keyframes replay rebuilds from the mission's log, bit for bit (mission.keyframes)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from mission.log import read_mission_log
from mission.replay import build_keyframes
from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission

pytestmark = pytest.mark.sim


def _fly(name: str, log_path, speedup: float):
    async def fly():
        async with asyncio.timeout(120.0):
            async with SimulatedMission(load_scenario(name), log_path, speedup=speedup) as sim:
                result = await sim.run()
                return result, list(sim.controller.keyframes)

    return asyncio.run(fly())


def test_live_keyframes_are_replays_bit_for_bit(tmp_path):
    log_path = tmp_path / "mission.jsonl"
    result, live = _fly("paper", log_path, speedup=20.0)
    replayed = build_keyframes(read_mission_log(log_path))
    assert result.keyframes == len(live) >= 20
    assert len(replayed) == len(live)
    with_motion = 0
    for n, (a, b) in enumerate(zip(live, replayed, strict=True)):
        assert a.t_s == b.t_s, n
        np.testing.assert_array_equal(a.gps_enu_m, b.gps_enu_m, err_msg=f"keyframe {n}")
        np.testing.assert_array_equal(a.user_idx, b.user_idx, err_msg=f"keyframe {n}")
        np.testing.assert_array_equal(a.range_m, b.range_m, err_msg=f"keyframe {n}")
        assert (a.odom_enu_m is None) == (b.odom_enu_m is None), n
        if a.odom_enu_m is not None:
            np.testing.assert_array_equal(a.odom_enu_m, b.odom_enu_m, err_msg=f"keyframe {n}")
            assert a.odom_sigma_m == b.odom_sigma_m, n
            with_motion += 1
    # the built-in vehicle logs its velocity: keyframes are linked where the logged records cover
    # the gap (how many depends on the machine's load: telemetry logged > 1 s apart links none)
    assert with_motion >= 1
