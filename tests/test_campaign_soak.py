"""The soak in the suite (issue 21): a few seeded fast-mode runs of benchmarks/soak.toml's wide family
(`python benchmarks/soak.py` flies 300 of them and full-mode runs): nothing raises, neither the run
nor the estimator inside it, and every leg keeps to the constraints."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

from sitl_scenarios.campaign import run_campaign, spec_from_dict

SOAK = Path(__file__).resolve().parents[1] / "benchmarks" / "soak.toml"


def test_a_small_soak_of_the_wide_family_raises_nothing(tmp_path):
    data = tomllib.loads(SOAK.read_text(encoding="utf-8"))
    fam = data["families"][0]
    assert (fam["users"], fam["buildings"], fam["nlos_excess_mean_m"]) == ([1, 12], [0, 5], [0.0, 40.0])
    # two worlds of the same family, drawn from another seed than the benchmark's, on a shorter budget
    fam.update(count=2, seed=7100)
    fam["mission"]["budget_m"] = 300.0
    campaign = spec_from_dict(data, str(SOAK))
    assert len(campaign.runs) == 6 and {r.planner for r in campaign.runs} == {"lawnmower", "greedy", "casadi"}
    done = run_campaign(campaign, tmp_path, workers=0, progress=False)
    assert [r["error"] for r in done.records if r["status"] != "ok"] == []
    assert [r["first_estimator_error"] for r in done.records if r["estimator_errors"]] == []
    assert sum(r["violations"] for r in done.records) == 0
    for r in done.records:
        assert r["keyframes"] > 20 and len(r["final_error_m"]) == r["users"]
        assert any(math.isfinite(e) for e in r["final_error_m"]), r["key"]
