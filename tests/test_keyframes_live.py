"""One keyframe builder: the keyframes a whole simulated mission hands its estimator are the
keyframes replay rebuilds from the mission's log, bit for bit (mission.keyframes)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from estimator.motion import integrate_velocity, motion_sigma_m
from estimator.noise import NoiseModel
from mission.keyframes import TriggerRecords, VelocityRecords, build_keyframe, velocity_covers, velocity_odometry
from mission.log import read_mission_log
from mission.replay import build_keyframes
from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission
from uavloc.errors import MissionLogError


def _fly(name: str, log_path, speedup: float):
    async def fly():
        async with asyncio.timeout(120.0):
            async with SimulatedMission(load_scenario(name), log_path, speedup=speedup) as sim:
                result = await sim.run()
                return result, list(sim.controller.keyframes)

    return asyncio.run(fly())


@pytest.mark.sim
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


# --- the velocity window ------------------------------------------------------------------------


def _records(rng, n: int, shuffle: bool) -> VelocityRecords:
    """n telemetry records 0.2 s apart (jittered, some at equal times, some without velocity,
    one stretch 2 s apart); with `shuffle` three neighbours swapped."""
    t = np.cumsum(rng.choice([0.0, 0.2, 0.2, 0.2, 0.23, 2.0], size=n, p=[0.05, 0.5, 0.2, 0.1, 0.1, 0.05]))
    t = np.round(t, 6)
    v = rng.normal(size=(n, 3)) * 3.0
    v[rng.random(n) < 0.1] = np.nan
    if shuffle:
        swap = rng.integers(0, n - 1, size=3)
        t[swap], t[swap + 1] = t[swap + 1].copy(), t[swap].copy()
    return VelocityRecords(t, v)


def test_the_window_gives_the_whole_logs_bits():
    """velocity_odometry over [a, b] == estimator.motion.integrate_velocity over every record, and
    == velocity_odometry over any prefix of the records that holds one strictly after b (what the
    flight has when it places a keyframe), records logged in time order."""
    rng = np.random.default_rng(7)
    noise = NoiseModel(vel_sigma_mps=0.05, vel_tau_s=0.7)
    checked = linked = 0
    for i in range(300):
        shuffle = i % 3 == 0
        rec = _records(rng, int(rng.integers(5, 80)), shuffle)
        a = float(rng.uniform(rec.t_s.min() - 0.5, rec.t_s.max()))
        b = a + float(rng.choice([0.0, 0.4, rng.uniform(0.0, 6.0)]))
        if rng.random() < 0.2:  # at a record's time exactly
            b = float(rng.choice(rec.t_s))
            a = min(a, b)
        got = velocity_odometry(rec, a, b, noise)
        disp, ok, disc = integrate_velocity(rec.t_s, rec.vel_enu_mps, np.array([a, b]))
        assert (got[0] is not None) == bool(ok[1])
        if ok[1]:
            np.testing.assert_array_equal(got[0], disp[1])
            assert got[1] == float(motion_sigma_m(b - a, noise, disc[1]))
            linked += 1
        for m in range(1, 0 if shuffle else len(rec.t_s) + 1):
            prefix = VelocityRecords(rec.t_s[:m], rec.vel_enu_mps[:m])
            if velocity_covers(prefix, b):
                early = velocity_odometry(prefix, a, b, noise)
                assert (early[0] is None) == (got[0] is None)
                if got[0] is not None and early[0] is not None:
                    np.testing.assert_array_equal(early[0], got[0])
                    assert early[1] == got[1]
                checked += 1
                break
    assert linked > 50 and checked > 50


def test_a_trigger_with_one_logged_position_keeps_it_exactly():
    from estimator.geodesy import Origin

    origin = Origin(43.6143, 7.0716, 150.0)
    recs = [{"t": 10.0 + 0.01 * k, "user": u, "uav": {"lat_deg": 43.6149, "lon_deg": 7.0721, "alt_m": 185.0},
             "toa_s": 1e-7 * (k + 1)} for k, u in enumerate(["b", "a"])]
    trig = TriggerRecords.from_records(recs, {"a": 0, "b": 1})
    kf = build_keyframe(trig, origin, None, None, NoiseModel())
    np.testing.assert_array_equal(kf.gps_enu_m, origin.lla_to_enu(43.6149, 7.0721, 185.0))
    np.testing.assert_array_equal(kf.user_idx, [1, 0])
    assert kf.t_s == 10.0 and trig.position_t_s == pytest.approx(10.005) and kf.odom_enu_m is None
    with pytest.raises(MissionLogError, match="'toa_s'"):
        TriggerRecords.from_records([{k: v for k, v in recs[0].items() if k != "toa_s"}], {"a": 0, "b": 1})
