"""A vehicle library that wedges must not hang uavloc (issue 10).

The built-in vehicle's `reposition_refused` fault answers COMMAND_INT DO_REPOSITION with MAV_RESULT 9,
as the PX4 build before PX4 #26626 did: real MAVSDK 4.1 then reports UNKNOWN, stops delivering
telemetry and never returns from its shutdown. `uavloc sim` must still print its result, close its log
and exit with its code; the only time limit is a generous "it returned at all". The controller sends
nothing but RTL after MAVSDK's UNKNOWN (later calls into a wedged MAVSDK may crash the process).
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
    # the controller sends nothing but RTL after MAVSDK's UNKNOWN; the vehicle returns home
    # ... and exits 1: it came home without locating anyone (issue 12: a mission that ends without
    # locating a user exits non-zero), after printing its result
    assert proc.returncode == 1, proc.stderr[-3000:]
    doc = json.loads(proc.stdout)
    assert doc["status"] == "returned" and "UNKNOWN" in doc["reason"], doc
    assert "not located" in proc.stderr
    lines = (out / "mission.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]  # every line complete
    events = [r for r in records if r["type"] == "event"]
    kinds = [e.get("kind") for e in events]
    assert any(e.get("kind") == "goto_failed" and "UNKNOWN" in e["message"] for e in events), events
    assert "rtl" in kinds and kinds.count("goto_failed") == 1, kinds
    assert events[-1]["kind"] == "end" and events[-1]["status"] == "returned"


@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.parametrize("ctrl_c", [1, 2])
def test_ctrl_c_ends_uavloc_sim_when_mavsdk_wedges(tmp_path: Path, ctrl_c: int) -> None:
    """One Ctrl-C: RTL tried for a bounded time, result printed, exit 130. A second Ctrl-C: exit 130 at once."""
    import os
    import signal
    import time

    text = (SCENARIO_DIR / "three_users_nlos.toml").read_text()
    scenario = tmp_path / "wedge.toml"
    scenario.write_text(text + '\n[[faults.vehicle]]\nkind = "reposition_refused"\nat_s = 0.0\n')
    out = tmp_path / "out"
    log_path = out / "mission.jsonl"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mission", "sim", str(scenario), "--planner", "lawnmower", "--out", str(out), "--json"],
        cwd=REPO, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)

    def wait_log(needle: str) -> None:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if log_path.exists() and needle in log_path.read_text():
                return
            # the safe end after the first Ctrl-C takes about 30 ms on an idle machine: a coarser
            # poll sends the second one after the loop ended, into the interpreter's finalization
            time.sleep(0.002)
        raise AssertionError(f"{needle!r} never logged")

    try:
        wait_log('"kind":"goto_failed"')
        proc.send_signal(signal.SIGINT)
        if ctrl_c == 2:
            wait_log('"kind":"interrupted"')
            proc.send_signal(signal.SIGINT)
        try:
            stdout, stderr = proc.communicate(timeout=300)
        except subprocess.TimeoutExpired as exc:
            raise AssertionError("uavloc sim did not return after Ctrl-C") from exc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, stderr[-3000:]
    records = [json.loads(line) for line in log_path.read_text().splitlines()]  # every line complete
    kinds = [r.get("kind") for r in records if r["type"] == "event"]
    assert "interrupted" in kinds
    if ctrl_c == 1:
        assert json.loads(stdout)["status"] == "interrupted"
        assert kinds[-1] == "end"
