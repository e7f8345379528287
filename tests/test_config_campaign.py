"""Campaign specs over the bundled scenario files: each loads, with the scenario's own figures."""

from __future__ import annotations

from dataclasses import replace

import pytest

from mission.estimation import mission_solver_params
from sitl_scenarios.campaign import spec_from_dict
from sitl_scenarios.scenario import bundled_scenarios, load_scenario

NAMES = sorted(p.stem for p in bundled_scenarios())


def test_a_campaign_over_every_bundled_scenario_file_loads():
    spec = {"campaign": {"name": "all", "planners": ["lawnmower"]},
            "scenarios": [{"file": n} for n in NAMES]}
    campaign = spec_from_dict(spec)
    assert sorted({r.scenario.name for r in campaign.runs}) == sorted(load_scenario(n).name for n in NAMES)
    for run in campaign.runs:
        # a commercial UE (no sawtooth of its own in the file) counts with the radio's sawtooth
        want = max(u.sawtooth_amplitude_m for u in load_scenario(run.scenario.name).users)
        assert run.scenario_params["sawtooth_max_m"] == want


@pytest.mark.parametrize("name", NAMES)
def test_a_loaded_user_carries_its_clock_sawtooth(name):
    sc = load_scenario(name)
    for u in sc.users:
        assert u.sawtooth_amplitude_m is not None and u.sawtooth_period_s is not None
        assert u.sawtooth_amplitude_m >= 0 and u.sawtooth_period_s > 0


def test_a_runs_estimator_is_the_missions_under_the_specs_options():
    """A run's SolverParams are those its scenario's mission flies with (mission_solver_params:
    Δ, range bias and its prior), with the spec's [estimators.NAME] options over them."""
    spec = {"campaign": {"name": "est", "planners": ["lawnmower"]},
            "estimators": {"w40": {"window": 40}, "tight": {"bias_prior_sigma_m": 2.0}},
            "families": [{"name": "f", "count": 2, "users": 2,
                          "mission": {"delta_m": 3.0, "bias_prior_sigma_m": 4.0, "estimate_bias": False}}]}
    runs = spec_from_dict(spec).runs
    assert {r.estimator for r in runs} == {"w40", "tight"}
    for run in runs:
        mission = mission_solver_params(run.scenario.mission)
        assert mission.bias_prior_sigma_m == 4.0 and mission.delta_m == 3.0 and not mission.estimate_bias
        want = replace(mission, window=40) if run.estimator == "w40" else replace(mission, bias_prior_sigma_m=2.0)
        assert run.params == want
