"""A campaign prints what a run costs, and keeps Dask's INFO lines out of the terminal unless asked (issue 23)."""

from __future__ import annotations

import re

import pytest

from sitl_scenarios.campaign import run_campaign, spec_from_dict

SPEC = """
[campaign]
name = "cost"
planners = ["lawnmower", "greedy"]
targets_m = [4.0]
[[families]]
name = "small"
count = 1
seed = 7
users = [1, 2]
fence_half_m = [70.0, 90.0]
no_fly = 0
buildings = 0
[families.mission]
budget_m = 300.0
target_radius_m = 3.0
"""

DASK_INFO = ("Nanny", "Register worker", "Scheduler at", "Remove client")


def test_a_campaign_s_cost_is_its_runs_wall_times(tmp_path):
    import tomllib

    done = run_campaign(spec_from_dict(tomllib.loads(SPEC)), tmp_path, workers=0, progress=False)
    walls = [r["wall_s"] for r in done.records]
    assert done.ran == 2 and done.run_s == pytest.approx(sum(walls))
    assert done.runs_per_min_per_worker == pytest.approx(60.0 * 2 / sum(walls))
    assert done.runs_per_min == pytest.approx(60.0 * 2 / done.wall_s)
    assert re.search(r"cost: [\d.]+ runs/min per worker \(a run takes [\d.]+ s\), [\d.]+ runs/min on 1 worker",
                     done.cost_line())


def test_the_command_prints_the_cost_and_dask_stays_quiet_unless_asked(tmp_path, capsys):
    from mission.cli import main

    (tmp_path / "spec.toml").write_text(SPEC)
    args = ["campaign", str(tmp_path / "spec.toml"), "--workers", "2", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    cap = capsys.readouterr()
    assert re.search(r"cost: [\d.]+ runs/min per worker .* on 2 worker\(s\), 2 runs", cap.out), cap.out
    assert not [w for w in DASK_INFO if w in cap.err], cap.err
    assert main(["-v", *args, "--out", str(tmp_path / "b")]) == 0
    assert [w for w in DASK_INFO if w in capsys.readouterr().err]
