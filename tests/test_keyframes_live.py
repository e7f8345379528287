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


def _records(rng, n: int, messy: bool) -> VelocityRecords:
    """n telemetry records about 0.2 s apart, some without velocity, some stretches 2 s apart.
    Strictly increasing times, as the flight logs them (one record per 1/telemetry_log_hz at
    most); `messy`: also records at equal times and three neighbours swapped (another tool's log)."""
    steps = [0.0, 0.2, 0.2, 0.2, 0.23, 2.0] if messy else [0.17, 0.2, 0.2, 0.2, 0.23, 2.0]
    t = np.round(np.cumsum(rng.choice(steps, size=n, p=[0.05, 0.5, 0.2, 0.1, 0.1, 0.05])), 6)
    v = rng.normal(size=(n, 3)) * 3.0
    v[rng.random(n) < 0.1] = np.nan
    if messy:
        swap = rng.integers(0, n - 1, size=3)
        t[swap], t[swap + 1] = t[swap + 1].copy(), t[swap].copy()
    return VelocityRecords(t, v)


def test_the_records_at_hand_give_the_whole_logs_bits():
    """velocity_odometry over all records == estimator.motion.integrate_velocity over them as
    logged; and, for records logged as the flight logs them, each gap alone from the first prefix
    of the records that holds one strictly after it (what the flight has when it places a
    keyframe) == that gap among all the position times over every record (what replay computes)."""
    rng = np.random.default_rng(7)
    noise = NoiseModel(vel_sigma_mps=0.05, vel_tau_s=0.7)
    checked = linked = 0
    for i in range(300):
        messy = i % 3 == 0
        rec = _records(rng, int(rng.integers(5, 80)), messy)
        times = np.sort(rng.uniform(rec.t_s.min() - 0.5, rec.t_s.max() + 0.5, size=int(rng.integers(2, 7))))
        times[rng.random(times.size) < 0.2] = rng.choice(rec.t_s)  # at a record's time exactly
        times = np.sort(times)
        disp, sigma, ok = velocity_odometry(rec, times, noise)
        ref, ref_ok, disc = integrate_velocity(rec.t_s, rec.vel_enu_mps, times)
        np.testing.assert_array_equal(ok, ref_ok)
        np.testing.assert_array_equal(disp[ok], ref[ref_ok])
        np.testing.assert_array_equal(sigma[ok], motion_sigma_m(np.diff(times, prepend=times[:1]), noise, disc)[ok])
        linked += int(ok[1:].sum())
        if messy:
            continue
        for n in range(1, times.size):
            prefix = next((p for p in (VelocityRecords(rec.t_s[:m], rec.vel_enu_mps[:m])
                                       for m in range(1, rec.t_s.size + 1)) if velocity_covers(p, times[n])), None)
            if prefix is None:
                continue
            d1, s1, ok1 = velocity_odometry(prefix, times[n - 1:n + 1], noise)
            assert ok1[1] == ok[n]
            if ok[n]:
                np.testing.assert_array_equal(d1[1], disp[n])
                assert s1[1] == sigma[n]
            checked += 1
    assert linked > 100 and checked > 200, (linked, checked)


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
