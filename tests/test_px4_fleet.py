"""A fleet of two real PX4 SITL instances (SIH quadrotors, the `px4_pair` fixture: the second 20 m
east of the first), each carrying a simulated gNB, flown by one uavloc mission (docs/fleet.md).

The scenario (tests/data/px4_two_uavs.toml) is two_uavs made small enough for PX4 at the tests'
speed factor: two groups of three UEs 300 m apart, 250 m cells. A second MAVLink client on each
instance's GCS link (tests.px4.GcsClient) watches what PX4 does, so landing, disarming and the
vehicles' separation are checked from PX4's own reports, not from uavloc's.
"""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

import numpy as np
import pytest

from estimator.geodesy import Origin
from mission.control.config import STATUS_TARGET
from mission.log import read_mission_log
from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission
from tests.px4 import GcsClient
from tests.test_mission_e2e import assert_log_replays_to_the_result

pytestmark = pytest.mark.px4

SCENARIO = Path(__file__).parent / "data" / "px4_two_uavs.toml"
#: wall seconds the mission may take at speed factor 4 before the test fails (about 90 s on a
#: 2-core machine running a test suite beside it)
MISSION_TIMEOUT_S = 240.0
#: metres from its own home each PX4 may land after RTL (its landing accuracy plus EKF2's error)
LANDING_RADIUS_M = 5.0


async def _sample(gcss: list[GcsClient], origin: Origin, out: list[np.ndarray], period_s: float = 0.05) -> None:
    """Both vehicles' positions as PX4 reports them on its GCS link, (2, 3) ENU of `origin` [m],
    every period_s wall seconds while both are known."""
    while True:
        fixes = [g.seen.lat_lon_alt for g in gcss]
        if all(f is not None for f in fixes):
            out.append(np.array([origin.lla_to_enu(*f) for f in fixes], float))
        await asyncio.sleep(period_s)


def _apart(pos: np.ndarray, sep_h: float, sep_v: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """pos (S, 2, 3): (apart (S,) bool, horizontal (S,), vertical (S,) distances [m])."""
    d_h = np.linalg.norm(pos[:, 0, :2] - pos[:, 1, :2], axis=1)
    d_v = np.abs(pos[:, 0, 2] - pos[:, 1, 2])
    return (d_h >= sep_h) | (d_v >= sep_v), d_h, d_v


def _logged_tracks(mlog) -> np.ndarray:
    """(S, 2, 3) both vehicles' logged telemetry [m, ENU of the log's origin], each interpolated at
    every telemetry time of either vehicle within both tracks."""
    enu = mlog.header.origin.lla_to_enu(mlog.tel_lla[:, 0], mlog.tel_lla[:, 1], mlog.tel_lla[:, 2])
    t = mlog.tel_t_s
    tracks = [(t[mlog.tel_vehicle == v], enu[mlog.tel_vehicle == v]) for v in (0, 1)]
    lo, hi = max(tr[0][0] for tr in tracks), min(tr[0][-1] for tr in tracks)
    grid = np.unique(t[(t >= lo) & (t <= hi)])
    return np.stack([np.column_stack([np.interp(grid, tv, pv[:, i]) for i in range(3)]) for tv, pv in tracks],
                    axis=1)


def test_two_px4_vehicles_reach_the_target_apart_and_both_land(px4_pair, tmp_path):
    sc = load_scenario(SCENARIO)
    log_path = tmp_path / "mission.jsonl"
    sep_h, sep_v = sc.mission.safety.separation_m, sc.mission.safety.separation_vertical_m
    reported: list[np.ndarray] = []

    async def fly():
        async with contextlib.AsyncExitStack() as stack:
            gcss = [await stack.enter_async_context(GcsClient(p.gcs_url)) for p in px4_pair]
            async with SimulatedMission(sc, log_path, connect=[p.api_url for p in px4_pair]) as sim:
                async def sample_once_home_known() -> None:
                    while sim.controller.origin is None:
                        await asyncio.sleep(0.05)
                    await _sample(gcss, sim.controller.origin, reported)

                sampler = asyncio.create_task(sample_once_home_known())
                try:
                    result = await asyncio.wait_for(sim.run(), MISSION_TIMEOUT_S)
                    await asyncio.gather(*(g.wait_for(lambda s: s.landed_disarmed(), 60, "PX4 landed and disarmed")
                                           for g in gcss))
                finally:
                    sampler.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await sampler
            return result, [g.seen for g in gcss], [g.describe() for g in gcss]

    result, seen, described = asyncio.run(fly())
    assert result.status == STATUS_TARGET, (result.reason, result.events[-12:])
    err = result.error_m()
    bound = np.array([u.error_bound_95_m for u in result.result.users])
    assert err is not None and np.all(err <= sc.mission.flight.target_radius_m), err
    # the final answer is the cold batch over every keyframe: its bound may come out a few per
    # cent either side of the stop rule's (tests/test_px4_mission.py)
    assert np.all(bound <= 1.1 * sc.mission.flight.target_radius_m), bound

    # PX4's side: each vehicle flew RTL home, landed there and disarmed
    assert result.rtl_sent and result.landed
    assert [v.id for v in result.result.vehicles] == ["uav1", "uav2"]
    assert all(v.rtl_sent and v.landed for v in result.result.vehicles), result.result.vehicles
    for s, d in zip(seen, described, strict=True):
        assert s.landed_disarmed(), d
        assert "RETURN_TO_LAUNCH" in s.modes, d
        assert s.home_offset_m() < LANDING_RADIUS_M, d

    # never closer than the separation: PX4's own reports on the GCS links, and the log's telemetry
    # of each vehicle (uavloc's view) interpolated at a common time
    assert result.result.separation_breaches == 0
    pos = np.array(reported)
    assert len(pos) > 200, len(pos)
    apart, d_h, d_v = _apart(pos, sep_h, sep_v)
    assert apart.all(), f"PX4 reports {d_h[~apart].min():.1f} m apart (vertical {d_v[~apart].min():.1f} m)"
    mlog = read_mission_log(log_path)
    apart, d_h, d_v = _apart(_logged_tracks(mlog), sep_h, sep_v)
    assert apart.all(), f"logged {d_h[~apart].min():.1f} m apart (vertical {d_v[~apart].min():.1f} m)"

    # one log naming both vehicles: header, telemetry, ranges; it replays to the result
    assert [v.id for v in mlog.header.vehicles] == ["uav1", "uav2"]
    assert set(np.unique(mlog.tel_vehicle)) == {0, 1}
    assert set(np.unique(mlog.rtt_vehicle)) == {0, 1}
    homes = {e.get("vehicle") for e in mlog.events if e.get("kind") == "home"}
    assert homes == {0, 1}, homes
    assert_log_replays_to_the_result(log_path, result)
