"""Issue 39: a campaign whose target lies below the GPS floor ends its runs "floor reached" within
half their budget instead of flying the budget out."""

from __future__ import annotations

from pathlib import Path

import pytest

from sitl_scenarios.campaign.spec import load_spec
from sitl_scenarios.campaign.task import run_one

SPEC = """
[campaign]
name = "floor"
mode = "fast"
seeds = [0]
planners = ["lawnmower", "casadi"]
targets_m = [1.5]

[[families]]
name = "gps_drift_slow"
count = 1
seed = 7
users = [1, 4]
fence_half_m = [100.0, 150.0]
buildings = [0, 2]
range_s0_m = 3.0
gps_sigma_m = 1.0
gps_tau_s = [600.0, 1200.0]
sawtooth_amplitude_m = [0.0, 12.0]
sawtooth_period_s = [10.0, 30.0]
speed_mps = 10.0

[families.mission]
budget_m = 2500.0
"""


@pytest.mark.parametrize("planner", ["lawnmower", "casadi"])
def test_a_target_below_the_gps_floor_ends_floor_reached_within_half_the_budget(planner, tmp_path: Path):
    (tmp_path / "spec.toml").write_text(SPEC)
    (run,) = [r for r in load_spec(tmp_path / "spec.toml").runs if r.planner == planner]
    rec = run_one(run)
    assert rec["floor_m"] > 1.4 * 1.5, "the spec's GPS drift puts the floor well above the target"
    assert rec["status"] == "ok" and rec["end"] == "floor_reached: floor reached", rec
    assert rec["flown_m"] <= 0.5 * rec["budget_m"]
