"""The fleet's planner and cells (docs/fleet.md): separation geometry against brute force, UEs
attaching as OAI's do, each vehicle planning for its own cell's users, and a fleet flown in fast mode."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.noise import NoiseModel
from mission.estimation import mission_solver_params
from planner import PlanningConstraints, PlanningState, make_planner
from planner.fleet import (
    REASON_USERS_DONE,
    FleetPlanner,
    Separation,
    legs_separated,
    segment_distance_m,
    vehicles_apart,
)
from planner.information import track_points_en_m, unsearched_point
from sitl_scenarios.campaign.fast import fly_fast
from sitl_scenarios.radio import CellAttachment
from sitl_scenarios.scenario import load_scenario
from tests.test_planner import fake_estimate

NOISE = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0)


def _constraints(**kw) -> PlanningConstraints:
    base = dict(home_enu_m=np.zeros(3), fence_enu_m=np.array([[-300, -300], [300, -300], [300, 300], [-300, 300]]),
                no_fly_enu_m=(), alt_min_m=20.0, alt_max_m=60.0, cruise_alt_m=30.0, leg_max_m=60.0,
                max_distance_m=400.0, budget_m=3000.0, target_radius_m=3.0)
    base.update(kw)
    return PlanningConstraints(**base)


def test_segment_distance_is_the_least_distance_of_densely_sampled_points():
    rng = np.random.default_rng(5)
    t = np.linspace(0.0, 1.0, 801)[:, None]
    for _ in range(60):
        a0, a1, b0, b1 = rng.uniform(-50, 50, size=(4, 2))
        pa, pb = a0 + t * (a1 - a0), b0 + t * (b1 - b0)
        brute = np.min(np.linalg.norm(pa[:, None] - pb[None], axis=2))
        got = segment_distance_m(a0, a1, b0, b1)
        # the samples' least distance is at most one sample step above the true one
        step = max(np.linalg.norm(a1 - a0), np.linalg.norm(b1 - b0)) / 800
        assert got <= brute + 1e-9 and brute - got <= step + 1e-9


def test_legs_apart_horizontally_or_by_altitude_layer():
    sep = Separation(15.0, 10.0)
    a = np.array([[0.0, 0.0, 30.0], [100.0, 0.0, 30.0]])
    crossing = np.array([[50.0, -50.0, 30.0], [50.0, 50.0, 30.0]])
    assert not legs_separated(a, crossing, sep)
    assert legs_separated(a, crossing + np.array([0.0, 0.0, 10.0]), sep)  # a layer 10 m up
    assert not legs_separated(a, crossing + np.array([0.0, 0.0, 9.0]), sep)
    assert not legs_separated(a, crossing + np.array([0.0, 0.0, 10.0]), Separation(15.0, 0.0))  # no layers
    parallel = a + np.array([0.0, 15.0, 0.0])
    assert legs_separated(a, parallel, sep) and not legs_separated(a, a + np.array([0.0, 14.9, 0.0]), sep)
    ok, least = vehicles_apart(np.array([[0.0, 0.0, 30.0], [10.0, 0.0, 45.0], [0.0, 12.0, 30.0]]), sep)
    assert not ok and least == pytest.approx(12.0)


def test_ues_attach_to_the_nearest_cell_and_stay_until_it_is_out_of_reach():
    users = np.array([[0.0, 0.0, 0.0], [300.0, 0.0, 0.0], [900.0, 0.0, 0.0]])
    cells = CellAttachment(users, coverage_m=400.0)
    s = cells.update(np.array([[50.0, 0.0, 30.0], [250.0, 0.0, 30.0]]))
    assert s.tolist() == [0, 1, -1]  # the third hears no cell
    # cell 0 flies over user 1: user 1 stays on cell 1, which still reaches it
    s = cells.update(np.array([[300.0, 0.0, 30.0], [0.0, 0.0, 30.0]]))
    assert s.tolist() == [0, 1, 1 if np.hypot(900, 30) <= 400 else -1]
    # cell 1 flies off to the east: user 1 is out of its reach and attaches to cell 0 (a new random access)
    s = cells.update(np.array([[300.0, 0.0, 30.0], [800.0, 0.0, 30.0]]))
    assert s.tolist() == [0, 0, 1] and cells.attaches.tolist() == [1, 2, 1]
    # cell 0 goes off the air: its UEs find cell 1 if they hear it, or no cell
    s = cells.update(np.array([[300.0, 0.0, 30.0], [800.0, 0.0, 30.0]]), on_air=np.array([False, True]))
    assert s.tolist() == [-1, -1, 1]


def test_each_vehicle_plans_for_its_own_cells_users_and_keeps_apart():
    c = _constraints()
    est = fake_estimate([[150.0, 0.0, 0.0], [-150.0, 0.0, 0.0]], np.eye(2) * 100.0)
    fleet = FleetPlanner([make_planner("casadi", c, NOISE, rng_seed=v) for v in range(2)], Separation(15.0, 10.0))
    serving = np.array([1, 0])  # user 0 (east) is cell 1's, user 1 (west) cell 0's
    x0, x1 = np.array([0.0, 0.0, 30.0]), np.array([20.0, 0.0, 30.0])
    r0 = fleet.plan(0, PlanningState(x0, est), serving, [None, np.array([x1, x1])])
    r1 = fleet.plan(1, PlanningState(x1, est), serving, [np.array([x0, r0.waypoint_enu_m]), None])
    assert not r0.done and not r1.done
    assert r0.waypoint_enu_m[0] < x0[0] and r1.waypoint_enu_m[0] > x1[0]  # each toward its own users
    assert legs_separated(np.array([x0, r0.waypoint_enu_m]), np.array([x1, r1.waypoint_enu_m]), fleet.separation)
    # boxed in: every leg comes near the other vehicle, which holds on a ring around this one
    ring = np.array([[x0[0] + 12 * np.cos(a), x0[1] + 12 * np.sin(a), 30.0] for a in np.linspace(0, 2 * np.pi, 13)])
    held = fleet.plan(0, PlanningState(x0, est), serving, [None, np.array([ring[0], ring[6]])])
    assert held.status.endswith("+hold") or legs_separated(np.array([x0, held.waypoint_enu_m]),
                                                           np.array([ring[0], ring[6]]), fleet.separation)
    # its users within the target while the other cell serves the rest: this vehicle's part is done
    done_est = fake_estimate([[150.0, 0.0, 0.0], [-150.0, 0.0, 0.0]], np.array([np.eye(2) * 100.0, np.eye(2) * 0.1]))
    res = fleet.plan(0, PlanningState(x0, done_est), serving, [None, np.array([x1, x1])])
    assert res.done and res.reason == REASON_USERS_DONE


def test_a_vehicle_with_nothing_left_in_reach_searches_the_ground_no_cell_covered():
    c = _constraints(coverage_m=150.0)
    track = track_points_en_m(np.array([[0.0, 0.0, 30.0], [-250.0, 0.0, 30.0], [-250.0, 250.0, 30.0]]))
    here = np.array([-250.0, 250.0])
    assert c.reach_m == pytest.approx(np.sqrt(150.0**2 - 30.0**2))
    near = unsearched_point(c, track, here)
    # the open ground nearest the vehicle: just beyond the reach (≈ 146 m) of the track's nearest point
    d_track = np.min(np.linalg.norm(track - near, axis=1))
    assert d_track > np.sqrt(150.0**2 - 30.0**2)
    grid = np.array([[x, y] for x in np.arange(-300, 301, 25) for y in np.arange(-300, 301, 25)], dtype=float)
    reach = np.sqrt(150.0**2 - 30.0**2)
    open_ground = grid[np.min(np.linalg.norm(grid[:, None] - track[None], axis=2), axis=1) > reach]
    assert np.linalg.norm(near - here) == pytest.approx(np.min(np.linalg.norm(open_ground - here, axis=1)))
    covered = np.array([[x, y] for x in range(-300, 301, 100) for y in range(-300, 301, 100)], dtype=float)
    assert unsearched_point(c, covered, here) is None
    assert unsearched_point(dataclasses.replace(c, coverage_m=np.inf), track, here) is None


def test_a_user_its_cell_lost_is_looked_for_where_that_cell_last_served_it():
    """uav2 served user 0 at (-250, 0) and went home; the user's UE lost its cell. uav1, with
    nothing of its own left to measure, flies toward (-250, 0), not to ground no track covered,
    and forgets the point once it has planned from near it without the user attaching."""
    c = _constraints(coverage_m=150.0)
    # user 1 ranged too little to be placed (no position yet): nothing to plan for
    est = fake_estimate([[200.0, 0.0, 0.0], [np.nan, np.nan, 0.0]], np.array([np.eye(2) * 0.1, np.eye(2) * np.nan]))
    fleet = FleetPlanner([make_planner("casadi", c, NOISE, rng_seed=v) for v in range(2)], Separation(15.0, 10.0))
    x0, west = np.array([200.0, 100.0, 30.0]), np.array([-250.0, 0.0, 30.0])
    fleet.plan(1, PlanningState(west, est), np.array([0, 1]), [np.array([x0, x0]), None])
    assert fleet.heard_en_m[1] == pytest.approx(west[:2])
    # user 1 unserved now; user 0, uav1's, within the target: uav1 explores toward the west point
    res = fleet.plan(0, PlanningState(x0, est), np.array([0, -1]), [None, None])
    assert res.status.startswith("explore+lost"), res.status
    assert np.linalg.norm(res.waypoint_enu_m[:2] - west[:2]) < np.linalg.norm(x0[:2] - west[:2]) - 0.5 * c.leg_max_m
    near = west + np.array([20.0, 0.0, 0.0])
    after = fleet.plan(0, PlanningState(near, est), np.array([0, -1]), [None, None])
    assert 1 not in fleet.heard_en_m and not after.status.startswith("explore+lost"), after.status


def test_a_user_beyond_every_legs_reach_is_flown_to():
    c = _constraints(coverage_m=120.0)
    planner = make_planner("casadi", c, NOISE)
    est = fake_estimate([[250.0, 250.0, 0.0]], np.eye(2) * 50.0)
    res = planner.plan(PlanningState(np.array([-200.0, -200.0, 30.0]), est))
    assert res.status == "transit"
    assert np.linalg.norm(res.waypoint_enu_m[:2] - 250.0) < np.linalg.norm(np.array([-450.0, -450.0]))


@pytest.fixture(scope="module")
def two_uavs():
    sc = load_scenario("two_uavs")
    return sc, mission_solver_params(sc.mission)


def test_two_uavs_in_fast_mode_reach_the_target_sooner_and_apart(two_uavs):
    sc, params = two_uavs
    seen = []
    two = fly_fast(sc, "casadi", params, 1, (4.0,), on_keyframe=lambda kf, est: seen.append(kf.vehicle),
                   n_vehicles=2)
    one = fly_fast(sc, "casadi", params, 1, (4.0,))
    # (a floor whose final answer bounds every user within the target ends as the target reached)
    assert two.end.startswith("target_reached") and one.end.startswith("target_reached")
    assert 4.0 in two.seconds_to and 4.0 in one.seconds_to
    assert not two.violations
    assert set(seen) == {0, 1}
    assert two.seconds_to[4.0] <= 0.6 * one.seconds_to[4.0]
    assert np.all(np.array(two.final_error_m) <= np.array(two.final_bound95_m))


def test_a_vehicle_whose_link_is_lost_returns_and_the_other_finishes_its_users(two_uavs):
    from sitl_scenarios.vehicle_faults import FaultEvent

    sc, params = two_uavs
    lost = dataclasses.replace(sc, world=dataclasses.replace(sc.world, faults=dataclasses.replace(
        sc.world.faults, vehicle=[FaultEvent("link_pause", 15.0, 300.0, vehicle="uav2")])))
    kfs = []
    out = fly_fast(lost, "casadi", params, 1, (4.0,), on_keyframe=lambda kf, est: kfs.append(kf), n_vehicles=2)
    leave_s = 15.0 + sc.mission.safety.link_timeout_s + sc.mission.safety.link_lost_wait_s
    assert out.events == [f"vehicle uav2: link lost at {leave_s:.1f} s: returns home"]
    assert all(kf.vehicle == 0 for kf in kfs if kf.t_s > leave_s + 0.5)
    assert 4.0 in out.seconds_to and not out.violations  # every user within the 4 m target
    # uav1 ranged the east group (uav2's cell's users until it left) after the loss
    east = [k for k, u in enumerate(sc.users) if u.east_m > 0]
    assert any(set(kf.user_idx.tolist()) & set(east) for kf in kfs if kf.vehicle == 0 and kf.t_s > leave_s)
