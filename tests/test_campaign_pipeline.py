"""One estimator pipeline: the campaigns' fast mode acts on the mission's estimator (issue 22 item 1).

A flight, `uavloc sim`, replay and both campaign modes build their estimator from
mission.estimation.MissionEstimator; these tests hold the fast mode to it: the estimate each
keyframe is acted on is what a fresh mission estimator gives on the same keyframes (batch refreshes,
clock tracking, the stop rule's confirm), the run ends on the mission's stop rule, and its final
figures are the mission's final answer (replay's batch solution).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from estimator.types import SOURCE_BATCH, SolverParams
from mission.controller import controller_from_mission
from mission.estimation import MissionEstimator, mission_solver_params
from mission.result import STATUS_BUDGET, STATUS_FLOOR, STATUS_TARGET
from sitl_scenarios.campaign.fast import fly_fast
from sitl_scenarios.scenario import load_scenario, resolve_scenario_path


def _params(sc) -> SolverParams:
    # what a campaign spec's default estimator variant gives (campaign.spec: the scenario's mission's)
    return mission_solver_params(sc.mission)


@pytest.mark.parametrize(("name", "planner", "seed"), [("paper", "lawnmower", 0), ("three_users_nlos", "greedy", 0)])
def test_the_fast_mode_acts_on_the_mission_s_estimator_and_ends_with_its_final_answer(name, planner, seed):
    sc = load_scenario(resolve_scenario_path(name))
    seen = []
    out = fly_fast(sc, planner, _params(sc), seed, (sc.mission.flight.target_radius_m,),
                   on_keyframe=lambda kf, est: seen.append((kf, est)))
    assert len(seen) == out.keyframes > 10

    setup = MissionEstimator.from_mission(sc.mission_config(), params=_params(sc))
    fresh = setup.estimator()
    sources = []
    for kf, acted_on in seen:
        ref = fresh.add_keyframe(kf, setup.confirm)
        sources.append(acted_on.source)
        assert acted_on.source == ref.source
        np.testing.assert_allclose(acted_on.users_enu_m, ref.users_enu_m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(acted_on.cov_users_m2, ref.cov_users_m2, rtol=0, atol=1e-9)
    assert sources.count(SOURCE_BATCH) >= 3, "the batch refreshes are the estimate acted on"

    # the run ends where the mission would: the stop rule on a batch estimate, the bounds at their
    # floor, or the budget
    # (the row's `end` renders the run's Result, built by the mission's one constructor)
    assert out.end == f"{out.result.status}: {out.result.reason}"
    if out.result.status == STATUS_TARGET:
        assert setup.stops(seen[-1][1])
    else:
        assert out.result.status in (STATUS_BUDGET, STATUS_FLOOR) and not any(setup.stops(est) for _, est in seen)
    assert (out.result.keyframes, out.result.measurements) == (len(seen), sum(len(kf.range_m) for kf, _ in seen))

    # the final figures are the mission's final answer: the batch solution over every keyframe
    final = setup.final([kf for kf, _ in seen])
    truth = np.array([[u.east_m, u.north_m] for u in sc.users])
    np.testing.assert_allclose(out.final_error_m, np.linalg.norm(final.users_enu_m[:, :2] - truth, axis=1),
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.final_bound95_m, final.error_bound_95_m(), rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["paper", "five_commercial_ues", "three_users_nlos"])
def test_the_flight_and_the_fast_mode_build_the_same_estimator(name, tmp_path: Path):
    sc = load_scenario(resolve_scenario_path(name))
    # the controller `uavloc sim` builds for the scenario's mission (its vehicle and gNB are not
    # used before it runs)
    ctl = controller_from_mission(sc.mission_config(), None, None, tmp_path / "mission.jsonl", params=_params(sc))
    flight = ctl.estimator_setup()
    fast = MissionEstimator.from_mission(sc.mission_config(), params=_params(sc))
    assert flight.n_users == fast.n_users == len(sc.users)
    np.testing.assert_array_equal(flight.user_up_m, fast.user_up_m)
    assert flight.noise == fast.noise and flight.params == fast.params
    assert flight.target_radius_m == fast.target_radius_m == sc.mission.flight.target_radius_m
    # and the spec's default estimator variant is the mission file's own settings
    assert fast.params == MissionEstimator.from_mission(sc.mission_config()).params
