"""A full-mode campaign run: the built-in MAVLink vehicle and the simulated gNB on their own ports."""

from __future__ import annotations

import math

import pytest

from sitl_scenarios.campaign import run_campaign, spec_from_dict


@pytest.mark.sim
def test_a_full_mode_run_flies_the_mission_and_reads_its_log(tmp_path):
    # ×20, not more: at ×40 beside two busy processes (the suite's other worker and its subprocesses)
    # the controller kept up with neither the vehicle nor the gNB and, honestly, hovered to the
    # mission's 1200 s time limit ("returned"); ×20 takes the same wall time idle and holds loaded
    spec = {
        "campaign": {"name": "full", "mode": "full", "planners": ["greedy"], "targets_m": [4.0], "speedup": 20.0},
        "families": [{"name": "f", "count": 1, "users": 1, "fence_half_m": 80.0, "buildings": 0, "no_fly": 0,
                      "mission": {"budget_m": 250.0, "target_radius_m": 2.0}}],
    }
    done = run_campaign(spec_from_dict(spec), tmp_path, workers=0, progress=False)
    (rec,) = done.records
    assert rec["status"] == "ok", rec["error"]
    assert rec["end"].split(":")[0] in ("target_reached", "budget_spent"), rec["end"]
    assert rec["keyframes"] > 20 and rec["replans"] >= 1 and 0 < rec["flown_m"] <= 250.0 + 20.0
    assert len(rec["final_error_m"]) == 1 and math.isfinite(rec["final_error_m"][0])
    # the 4 m target is met long before the 250 m budget in this open field
    assert 0 < rec["metres_to_m"][0] < rec["flown_m"] + 1.0
