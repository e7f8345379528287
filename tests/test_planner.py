"""Planner interface, geometry, exact leg check, stop rule and the fixed-pattern baselines."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.noise import NoiseModel
from estimator.types import Estimate
from planner import (
    REASON_BUDGET,
    REASON_TARGET,
    PlanningConstraints,
    PlanningState,
    make_planner,
    planner_names,
    stop_reason,
)
from planner.geometry import (
    convex_cell,
    leg_violations,
    point_in_polygon,
    segment_segment_distance,
)
from sitl_scenarios.scenario import BuildingConfig, load_scenario
from uavloc.errors import PlannerError

# A non-convex (U-shaped) fence with a no-fly square in the west arm.
U_FENCE = [[-100, -100], [100, -100], [100, 100], [40, 100], [40, -20], [-40, -20], [-40, 100], [-100, 100]]
NO_FLY = [[[-80, 20], [-60, 20], [-60, 40], [-80, 40]]]


def u_constraints(**kw) -> PlanningConstraints:
    args = dict(
        home_enu_m=np.array([0.0, -60.0, 0.0]),
        fence_enu_m=np.array(U_FENCE, dtype=float),
        no_fly_enu_m=tuple(np.array(p, dtype=float) for p in NO_FLY),
        alt_min_m=10.0,
        alt_max_m=60.0,
        cruise_alt_m=30.0,
        leg_max_m=60.0,
        max_distance_m=150.0,
        budget_m=2000.0,
    )
    args.update(kw)
    return PlanningConstraints(**args)


def fake_estimate(users_enu_m, cov_m2, ambiguous=None, mirror=None) -> Estimate:
    users = np.asarray(users_enu_m, dtype=float)
    K = len(users)
    cov = np.broadcast_to(np.asarray(cov_m2, dtype=float), (K, 2, 2)).copy()
    info = np.zeros((2 * K, 2 * K))
    for k in range(K):
        info[2 * k:2 * k + 2, 2 * k:2 * k + 2] = np.linalg.inv(cov[k])
    return Estimate(
        users_enu_m=users,
        cov_users_m2=cov,
        info_users=info,
        bias_m=None,
        uav_enu_m=np.zeros((0, 3)),
        ambiguous=np.zeros(K, bool) if ambiguous is None else np.asarray(ambiguous),
        mirror_enu_m=np.full((K, 3), np.nan) if mirror is None else np.asarray(mirror, dtype=float),
        n_ranges=np.full(K, 10),
    )


@pytest.mark.parametrize(
    ("point", "inside"),
    [((0, -60), True), ((0, 0), False), ((-70, 50), True), ((70, 50), True), ((0, 150), False), ((120, 0), False)],
)
def test_point_in_polygon_non_convex_table(point, inside):
    assert bool(point_in_polygon(np.array(point, dtype=float), np.array(U_FENCE, dtype=float))) is inside


@pytest.mark.parametrize(
    ("a0", "a1", "b0", "b1", "dist"),
    [
        ((0, 0), (10, 0), (5, -5), (5, 5), 0.0),  # crossing
        ((0, 0), (10, 0), (0, 3), (10, 3), 3.0),  # parallel
        ((0, 0), (10, 0), (13, 4), (20, 4), 5.0),  # end to end: (10,0)-(13,4)
        ((0, 0), (10, 0), (5, 2), (5, 9), 2.0),  # T without touching
    ],
)
def test_segment_segment_distance_table(a0, a1, b0, b1, dist):
    got = segment_segment_distance(*(np.array(p, dtype=float) for p in (a0, a1, b0, b1)))
    assert got == pytest.approx(dist, abs=1e-12)


def test_leg_check_refuses_crossing_the_notch_and_the_no_fly_zone():
    c = u_constraints()
    x = np.array([-70.0, -60.0, 30.0])
    # straight into the west arm: fine
    assert leg_violations(c, x, np.array([-70.0, 0.0, 30.0]), 2000.0) == []
    # across the notch of the U (both ends inside the fence, the leg is not)
    assert "free" in leg_violations(c, np.array([-70.0, 50.0, 30.0]), np.array([70.0, 50.0, 30.0]), 2000.0)
    # through the no-fly square
    assert "free" in leg_violations(c, np.array([-70.0, 0.0, 30.0]), np.array([-70.0, 58.0, 30.0]), 2000.0)
    # too long, too low, too far from home, not enough energy
    assert "leg" in leg_violations(c, x, x + np.array([0, 61, 0]), 2000.0)
    assert "altitude" in leg_violations(c, x, x + np.array([0, 20, -25]), 2000.0)
    assert "energy" in leg_violations(c, x, x + np.array([0, 50, 0]), 2000.0, energy_m=60.0)
    far = u_constraints(max_distance_m=60.0)
    assert "distance" in leg_violations(far, x, np.array([-70.0, 0.0, 30.0]), 2000.0)


def test_convex_cell_contains_seed_and_excludes_edges():
    c = u_constraints()
    a, b = np.array([-70.0, -60.0]), np.array([-70.0, 0.0])
    A, off = convex_cell(c, a, b, max_planes=32)
    assert np.all(A @ a <= off + 1e-9) and np.all(A @ b <= off + 1e-9)
    # a random point of the cell is free: sample, keep those inside the cell, check every one
    rng = np.random.default_rng(3)
    pts = rng.uniform(-110, 110, size=(4000, 2))
    inside = np.all(pts @ A.T <= off, axis=1)
    assert inside.sum() > 50
    for p in pts[inside]:
        assert leg_violations(c, np.array([*a, 30.0]), np.array([*p, 30.0]), 1e9) in ([], ["leg"], ["leg", "distance"],
                                                                                  ["distance"])


def test_scenario_constraints_raise_floor_over_buildings_and_makes_tall_ones_no_fly():
    sc = load_scenario("paper")
    low = BuildingConfig(footprint_enu_m=[[0, 0], [10, 0], [10, 10]], height_m=25.0)
    tall = BuildingConfig(footprint_enu_m=[[50, 50], [60, 50], [60, 60]], height_m=200.0)
    from dataclasses import replace

    c = replace(sc, world=replace(sc.world, buildings=[low, tall])).planning_constraints(home_enu_m=(0, 0, 5))
    assert c.alt_min_m == pytest.approx(5 + 30.0)  # 25 m + 5 m clearance above home at up = 5
    assert c.alt_max_m == pytest.approx(5 + sc.mission.flight.alt_max_m)
    assert len(c.no_fly_enu_m) == 1 and c.no_fly_enu_m[0][0].tolist() == [50, 50]


def test_constraints_reject_bad_values():
    with pytest.raises(PlannerError, match="alt_min_m"):
        u_constraints(alt_min_m=40.0)
    with pytest.raises(PlannerError, match="fence_enu_m"):
        u_constraints(fence_enu_m=np.array([[0, 0], [1, 1]], dtype=float))
    with pytest.raises(PlannerError, match="unknown planner"):
        make_planner("spiral", u_constraints(), NoiseModel())


def test_stop_rule_target_budget_and_ambiguity():
    c = u_constraints(target_radius_m=1.0)
    x = np.array([0.0, -60.0, 30.0])
    tight = fake_estimate([[10, 10, 0], [20, -50, 0]], np.eye(2) * 0.01)  # r95 = sqrt(5.99·0.01) ≈ 0.24 m
    loose = fake_estimate([[10, 10, 0], [20, -50, 0]], np.diag([0.01, 1.0]))
    amb = fake_estimate([[10, 10, 0]], np.eye(2) * 0.01, ambiguous=[True], mirror=[[-10, 10, 0]])
    assert stop_reason(c, PlanningState(x, tight, 0.0)) == REASON_TARGET
    assert stop_reason(c, PlanningState(x, loose, 0.0)) is None
    assert stop_reason(c, PlanningState(x, amb, 0.0)) is None
    assert stop_reason(c, PlanningState(x, None, 0.0)) is None
    assert stop_reason(c, PlanningState(x, loose, 1995.0)) == REASON_BUDGET
    assert stop_reason(c, PlanningState(x, loose, 0.0, energy_remaining_m=5.0)) == REASON_BUDGET


def _fly(planner, c, x0, n_legs, estimate=None):
    # a fixed estimate never shrinks, so it would be at its floor (planner.stop.FloorWatch): these
    # tests look at the legs alone
    planner.floor_watch = None
    x, flown, legs = np.asarray(x0, dtype=float), 0.0, []
    for _ in range(n_legs):
        r = planner.plan(PlanningState(x, estimate, flown))
        if r.done:
            break
        assert leg_violations(c, x, r.waypoint_enu_m, c.budget_m - flown) == []
        flown += float(np.linalg.norm(r.waypoint_enu_m - x))
        legs.append(r)
        x = r.waypoint_enu_m
    return x, flown, legs


@pytest.mark.parametrize("name", ["lawnmower", "circle", "random"])
def test_baselines_keep_every_constraint_in_the_u_fence(name):
    c = u_constraints()
    est = fake_estimate([[-70, 60, 0], [70, 60, 0]], np.eye(2) * 25.0)
    _, flown, legs = _fly(make_planner(name, c, NoiseModel(), rng_seed=1), c, [0, -60, 30], 25, est)
    assert len(legs) == 25 and flown > 25 * c.min_leg_m


def test_lawnmower_covers_both_arms_of_the_u():
    c = u_constraints()
    x, visited = np.array([0.0, -60.0, 30.0]), []
    p = make_planner("lawnmower", c, NoiseModel())
    for _ in range(40):
        r = p.plan(PlanningState(x, None, 0.0))
        x = r.waypoint_enu_m
        visited.append(x)
    v = np.array(visited)
    assert np.any((v[:, 0] < -40) & (v[:, 1] > 50)) and np.any((v[:, 0] > 40) & (v[:, 1] > 50))
    assert np.all(v[:, 2] == c.cruise_alt_m)


def test_lawnmower_goes_on_from_a_vertex_reached_within_the_arrival_radius():
    """Issue 21 #11: the flight counts a waypoint reached within 2 m; the lawnmower, asking for
    1 m, sent the UAV to the same corner again and again until the battery was spent hovering.
    Arriving 1.5 m off each vertex, it now follows its lanes."""
    c = u_constraints()
    p = make_planner("lawnmower", c, NoiseModel())
    x = np.array([0.0, -60.0, 30.0])
    seen = []
    for _ in range(12):
        wp = p.plan(PlanningState(x, None, 0.0)).waypoint_enu_m
        assert not any(np.allclose(wp, s) for s in seen[-1:]), f"the same waypoint {wp} twice in a row"
        seen.append(wp)
        x = wp + np.array([1.5, 0.0, 0.0])  # "arrived": within the flight's 2 m radius
    assert len({tuple(np.round(s, 6)) for s in seen}) >= 8


def test_budget_spent_ends_the_survey():
    c = u_constraints(budget_m=100.0)
    _, flown, _ = _fly(make_planner("lawnmower", c, NoiseModel()), c, [0, -60, 30], 20)
    assert flown <= 100.0 + 1e-6
    late = PlanningState([0, -60, 30], None, 95.0)
    assert make_planner("lawnmower", c, NoiseModel()).plan(late).reason == REASON_BUDGET


def test_plan_refuses_a_start_outside_the_fence():
    c = u_constraints()
    with pytest.raises(PlannerError, match="outside the fence"):
        make_planner("random", c, NoiseModel()).plan(PlanningState([0.0, 0.0, 30.0]))


def test_planner_names_include_the_baselines():
    assert {"lawnmower", "circle", "random"} <= set(planner_names())
