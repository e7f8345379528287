"""A fleet flies over MAVLink (docs/fleet.md): `two_uavs`, two built-in vehicles each carrying a
simulated gNB, one mission controller, one log.

The vehicles' true positions are sampled from the simulators while the mission flies, so the
separation and the fence are checked on what the vehicles did, not on what the controller saw.
"""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mission.control.config import STATUS_TARGET
from mission.geometry import contains_point
from mission.log import read_mission_log
from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission
from tests.test_mission_e2e import _wait, assert_log_replays_to_the_result

#: one fleet flight at a time (the README's run has two workers): two at once are four vehicles,
#: four gNBs and two controllers on 2 cores, and in a clean-clone run both missed their target
pytestmark = pytest.mark.xdist_group("fleet-flights")

#: the built-in vehicles' speed factor (two vehicles, two gNBs and the controller share 2 cores)
SPEEDUP = 20.0
#: … with a link cut: MAVSDK and the monitor notice a lost link after link_timeout_s wall seconds,
#: SPEEDUP times as many mission seconds, in which the other vehicle must not have finished its users
#: and gone home
FAULT_SPEEDUP = 10.0
#: wall seconds a mission may take (about 30 s on an idle machine)
TIMEOUT_S = 240.0


async def _sample_truth(sim: SimulatedMission, out: list[np.ndarray], period_s: float = 0.02) -> None:
    """Every vehicle's true position [m, scenario ENU] every period_s wall seconds, into `out`."""
    while True:
        out.append(sim._fleet_positions())
        await asyncio.sleep(period_s)


def _fly(sc, log_path: Path, during=None, speedup: float = SPEEDUP, **kw):
    """Fly `sc`; during(sim) runs alongside (a fault). (result, true positions (S, V, 3), sims' final states)."""
    samples: list[np.ndarray] = []

    async def main():
        async with SimulatedMission(sc, log_path, speedup=speedup, **kw) as sim:
            sampler = asyncio.create_task(_sample_truth(sim, samples))
            fault = asyncio.create_task(during(sim)) if during is not None else None
            try:
                result = await asyncio.wait_for(sim.run(), TIMEOUT_S)
            finally:
                sampler.cancel()
                if fault is not None:
                    fault.cancel()
            return result, [s.state() for s in sim.vehicle_sims]

    result, finals = asyncio.run(main())
    return result, np.array(samples), finals


def _assert_apart_and_fenced(sc, truth: np.ndarray) -> None:
    sep_h, sep_v = sc.mission.safety.separation_m, sc.mission.safety.separation_vertical_m
    d_h = np.linalg.norm(truth[:, 0, :2] - truth[:, 1, :2], axis=1)
    d_v = np.abs(truth[:, 0, 2] - truth[:, 1, 2])
    apart = (d_h >= sep_h) | (d_v >= sep_v)
    assert apart.all(), f"closest {d_h[~apart].min():.1f} m apart (vertical {d_v[~apart].min():.1f} m)"
    fence = np.asarray(sc.mission.geofence.polygon_enu_m, float)
    outside = [p for p in truth.reshape(-1, 3) if not contains_point(fence, p[:2])]
    assert not outside, outside[:3]


@pytest.mark.slow
def test_two_uavs_reach_the_target_apart_inside_the_fence_and_both_land(tmp_path):
    sc = load_scenario("two_uavs")
    log_path = tmp_path / "mission.jsonl"
    result, truth, finals = _fly(sc, log_path)
    assert result.status == STATUS_TARGET, (result.reason, result.events[-12:])
    # every user's 95 % bound inside the target (the stop rule, judged on the final answer); the true
    # errors within twice it (a 95 % bound leaves one user in twenty outside it: not all six every time)
    err = result.error_m()
    bound = np.array([u.error_bound_95_m for u in result.result.users])
    target_m = sc.mission.flight.target_radius_m
    assert np.all(bound <= target_m) and np.all(err <= 2.0 * target_m), (err, bound)
    # both home: RTL accepted, landed and disarmed, on the ground at their launch points
    assert result.rtl_sent and result.landed and result.refusals == 0
    assert all(not s.armed and not s.in_air for s in finals)
    assert [v.id for v in result.result.vehicles] == ["uav1", "uav2"]
    assert all(v.rtl_sent and v.landed for v in result.result.vehicles)
    assert result.result.separation_breaches == 0
    assert len(truth) > 100
    _assert_apart_and_fenced(sc, truth)
    # one log, each record naming its vehicle; both vehicles ranged users; it replays to the result
    mlog = read_mission_log(log_path)
    assert [v.id for v in mlog.header.vehicles] == ["uav1", "uav2"]
    assert set(np.unique(mlog.rtt_vehicle)) == {0, 1} and set(np.unique(mlog.tel_vehicle)) == {0, 1}
    assert_log_replays_to_the_result(log_path, result)
    # each vehicle took the users of its own side (the groups lie 700 m apart)
    east = np.array([u.east_m for u in sc.users]) > 0
    users_of = [set(mlog.rtt_user[mlog.rtt_vehicle == v]) for v in (0, 1)]
    assert users_of[0] & set(np.flatnonzero(east)) and users_of[1] & set(np.flatnonzero(~east))


@pytest.mark.slow
def test_a_vehicle_that_loses_its_link_returns_and_the_other_finishes_its_users(tmp_path):
    """uav2 (the west group's) loses its MAVLink link at its first range: after link_lost_wait_s it is
    sent home and lands; its cell, on the ground, no longer reaches the west group, whose UEs attach
    to uav1's cell as uav1 comes within reach, and uav1 locates every user. The log says which."""
    sc = load_scenario("two_uavs")
    # the mission's 1200 s time limit counts from its start: beside two busy processes the planner's
    # preparation alone took 310-410 mission seconds at ×10 before take-off, and the rest 350-490
    flight = dataclasses.replace(sc.mission.flight, time_limit_s=3000.0)
    sc = dataclasses.replace(sc, mission=dataclasses.replace(sc.mission, flight=flight))
    log_path = tmp_path / "mission.jsonl"
    west = [k for k, u in enumerate(sc.users) if u.east_m < 0]

    async def cut_uav2(sim: SimulatedMission) -> None:
        ctl = sim.controller
        await _wait(lambda: ctl.crews[1].flight.measurements >= 1, 120, "uav2's first range")
        # 5 wall seconds: the link is lost after link_timeout_s, the return requested link_lost_wait_s
        # later, and RTL goes through once the link is back. uav1 must not have finished its own
        # users and gone home by then (it takes about 80 mission seconds): the link is judged lost
        # after 1.5 wall seconds, 15 mission seconds at ×10, not the 3 s default
        sim.vehicle_sims[1].pause_link(5.0 * FAULT_SPEEDUP)

    result, truth, finals = _fly(sc, log_path, during=cut_uav2, speedup=FAULT_SPEEDUP,
                                 controller_overrides={"link_lost_wait_s": 5.0, "link_timeout_s": 1.5})
    assert result.status == STATUS_TARGET, (result.reason, result.events[-12:])
    bound = np.array([u.error_bound_95_m for u in result.result.users])
    assert np.all(bound <= sc.mission.flight.target_radius_m), bound
    uav1, uav2 = result.result.vehicles
    assert "link lost" in uav2.ended and uav2.rtl_sent and uav2.landed, uav2
    # uav1 located every user (the status and bounds above); on a busy machine it may spend its
    # budget before the mission's answer reaches the target, which is still its survey's end
    assert uav1.ended.startswith("survey done: ") and uav1.landed, uav1
    assert all(not s.armed and not s.in_air for s in finals)
    mlog = read_mission_log(log_path)
    by_kind = {}
    for e in mlog.events:
        by_kind.setdefault(e.get("kind"), []).append(e)
    assert [e["vehicle"] for e in by_kind["link_lost"]] == [1]
    assert [e.get("vehicle") for e in by_kind["return"]] == [1]
    t_return = by_kind["return"][0]["t"]
    # after uav2 left, uav1 ranged the west group's users
    late = (mlog.rtt_t_s > t_return) & (mlog.rtt_vehicle == 0)
    assert set(mlog.rtt_user[late]) & set(west), "uav1 never ranged the west group"
    _assert_apart_and_fenced(sc, truth)
    assert_log_replays_to_the_result(log_path, result)


@pytest.mark.slow
def test_cancelling_a_fleet_mission_sends_every_vehicle_home(tmp_path):
    """Ctrl-C, SIGTERM and SIGHUP cancel the mission (mission.runtime): every vehicle gets RTL."""
    sc = load_scenario("two_uavs")
    log_path = tmp_path / "mission.jsonl"

    async def main():
        async with SimulatedMission(sc, log_path, speedup=SPEEDUP) as sim:
            task = asyncio.create_task(sim.run())
            await _wait(lambda: sim.controller.measurements >= 20, 120, "20 ranges")
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            return sim.controller, [s.state() for s in sim.vehicle_sims]

    ctl, states = asyncio.run(main())
    assert [c.rtl_sent for c in ctl.crews] == [True, True]
    assert all(s.mode == "return_to_launch" or not s.in_air for s in states), [s.mode for s in states]
    mlog = read_mission_log(log_path)
    assert sorted(e.get("vehicle") for e in mlog.events if e.get("kind") == "rtl") == [0, 1]
    assert mlog.last_event("end")["status"] == "interrupted"
