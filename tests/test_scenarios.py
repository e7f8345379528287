"""Smoke test of every bundled scenario: it loads strictly, its users and home lie inside its own
limits, and the planner, the safety gate and the radio model all accept it."""

from __future__ import annotations

import numpy as np
import pytest

from mission.safety import SafetyGate, SafetyLimits
from sitl_scenarios.radio import RadioModel, line_of_sight_blocked
from sitl_scenarios.scenario import bundled_scenarios, load_scenario

SCENARIOS = bundled_scenarios()


def test_the_issue_asks_for_these_scenarios():
    names = {p.stem for p in SCENARIOS}
    assert {"paper", "three_users_nlos", "edge_of_coverage", "clock_sawtooth"} <= names


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_bundled_scenario_is_consistent(path):
    sc = load_scenario(path)
    gate = SafetyGate(SafetyLimits.from_mission(sc.mission_config(), sc.origin_geo))
    cruise = np.array([0.0, 0.0, sc.mission.altitude_m])
    assert gate.position_violations(cruise) == []
    for u in sc.users:
        # every user lies inside the fence, so the UAV may fly over it
        assert gate.position_violations(np.array([u.east_m, u.north_m, sc.mission.altitude_m])) == [], u.id
    constraints = sc.planning_constraints()
    assert constraints.alt_min_m <= constraints.cruise_alt_m <= constraints.alt_max_m
    radio = RadioModel(sc, np.random.default_rng(sc.seed))
    # the user closest to home answers from overhead
    k = int(np.argmin([np.hypot(u.east_m, u.north_m) for u in sc.users]))
    u = sc.users[k]
    assert radio.measure(k, np.array([u.east_m, u.north_m, sc.mission.altitude_m]), 0.0) is not None


def test_three_users_scenario_has_nlos_from_some_directions_only():
    sc = load_scenario("three_users_nlos")
    alt = sc.mission.altitude_m
    for u in sc.users:
        user = np.array([u.east_m, u.north_m, u.up_m])
        ring = [np.array([u.east_m + 60 * np.cos(a), u.north_m + 60 * np.sin(a), alt])
                for a in np.linspace(0, 2 * np.pi, 36, endpoint=False)]
        blocked = [line_of_sight_blocked(p, user, sc.buildings) for p in ring]
        assert 0 < sum(blocked) < len(blocked), u.id


def test_edge_of_coverage_user_is_out_of_reach_from_part_of_the_fence():
    sc = load_scenario("edge_of_coverage")
    u = sc.users[0]
    corners = np.asarray(sc.geofence.polygon_enu_m)
    d = np.hypot(corners[:, 0] - u.east_m, corners[:, 1] - u.north_m)
    assert d.max() > sc.radio.coverage_m > np.hypot(u.east_m, u.north_m)
    assert sc.noise_model().range_sigma_m(330.0) > 1.8 * sc.noise_model().range_sigma_m(0.0)


def test_sawtooth_scenario_has_a_strong_clock_drift():
    sc = load_scenario("clock_sawtooth")
    assert max(u.sawtooth_amplitude_m for u in sc.users) >= 3 * sc.radio.s0_m
