"""Campaign specs over the bundled scenario files: each loads, with the scenario's own figures."""

from __future__ import annotations

import pytest

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
