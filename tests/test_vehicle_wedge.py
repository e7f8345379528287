"""A vehicle library that wedges must not hang uavloc (issue 10).

The built-in vehicle's `reposition_refused` fault answers COMMAND_INT DO_REPOSITION with MAV_RESULT 9,
as the PX4 build before PX4 #26626 did: real MAVSDK 4.1 then reports UNKNOWN, stops delivering
telemetry and never returns from its shutdown. `uavloc sim` must still print its result, close its log
and exit with its code; the only time limit is a generous "it returned at all".
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from sitl_scenarios.scenario import SCENARIO_DIR
from sitl_scenarios.vehicle import FaultEvent, faults_from_scenario

REPO = Path(__file__).resolve().parents[1]


def test_reposition_refused_fault_is_parsed() -> None:
    assert faults_from_scenario({"vehicle": [{"kind": "reposition_refused", "at_s": 0}]}) == [
        FaultEvent("reposition_refused", 0.0, None, None)]


@pytest.mark.sim
@pytest.mark.slow
def test_uavloc_sim_exits_with_its_result_when_mavsdk_wedges(tmp_path: Path) -> None:
    text = (SCENARIO_DIR / "three_users_nlos.toml").read_text()
    assert "[[faults.vehicle]]" not in text
    scenario = tmp_path / "wedge.toml"
    scenario.write_text(text + '\n[[faults.vehicle]]\nkind = "reposition_refused"\nat_s = 0.0\n')
    out = tmp_path / "out"
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "mission", "sim", str(scenario), "--planner", "lawnmower", "--out", str(out),
             "--json"], cwd=REPO, capture_output=True, text=True, timeout=400)
    except subprocess.TimeoutExpired as exc:
        raise AssertionError(f"uavloc sim did not return: {str(exc.stderr)[-3000:]}") from exc
    assert proc.returncode == 1, proc.stderr[-3000:]
    doc = json.loads(proc.stdout)
    assert doc["status"] == "aborted", doc
    lines = (out / "mission.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]  # every line complete
    events = [r for r in records if r["type"] == "event"]
    assert any(e.get("kind") == "goto_failed" and "UNKNOWN" in e["message"] for e in events), events
    assert events[-1]["kind"] == "end" and events[-1]["status"] == "aborted"
