"""Missions flown without --out are kept: their log and report go under $UAVLOC_RUNS."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_a_sim_without_out_keeps_its_log_and_says_where(tmp_path):
    """Issue 39: `uavloc sim` without --out kept no log. It goes to $UAVLOC_RUNS/<UTC>-sim-<name>/,
    said on stderr, with the report."""
    import os

    env = dict(os.environ, UAVLOC_RUNS=str(tmp_path / "runs"))
    proc = subprocess.run([sys.executable, "-m", "mission", "sim", "paper", "--planner", "lawnmower", "--speedup", "20",
                           "--json"], cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode in (0, 1), proc.stderr[-2000:]
    (run,) = (tmp_path / "runs").iterdir()
    assert run.name.endswith("-sim-paper") and str(run) in proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["log"] == str(run / "mission.jsonl") and (run / "report.json").is_file()
    events = [json.loads(line) for line in (run / "mission.jsonl").read_text().splitlines() if '"survey_time"' in line]
    (ev,) = events
    assert ev["survey_s"] > 0 and 0 <= ev["hover_s"] <= ev["survey_s"] and ev["largest_gap_s"] > 0
