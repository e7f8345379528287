"""Issue 48 items 3 and 4: one answer, and replay refuses what cannot be.

One answer: the GPS correlation time τ the flight estimated (event `gps_tau`) is the one replay
uses, so the flight's own `--json` result and `uavloc replay` of its log are the same document,
bit for bit; replay judges the status the log recorded against its own answer and says so when
they differ. Refusals: an rtt record repeated is counted once (dropped with a warning naming the
count and the first line), never a smaller bound; a fleet's rtt or telemetry record that names no
vehicle, and a record that contradicts the header, are refused with the file and line.

The flight's log comes from one short simulated mission (paper, seed 1), flown as an external
autopilot's flight is (the mission leaves τ unknown: the flight estimates it from the take-off);
the logs mutated are the bundled sitl_scenarios/data/example_paper.jsonl and
tests/test_fleet_log.py's two-vehicle log.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
from pathlib import Path

import numpy as np
import pytest

import sitl_scenarios.sim_runner as sim_runner
from mission.cli import main
from mission.log import read_mission_log
from mission.replay import ReplayOptions, replay, resolve_gps_tau, result_of_replay
from mission.result import STATUS_BUDGET, STATUS_TARGET, STATUS_TARGET_MISSED
from tests.test_fleet_log import _write_fleet_log
from uavloc.errors import MissionLogError

EXAMPLE = Path(__file__).resolve().parents[1] / "sitl_scenarios" / "data" / "example_paper.jsonl"


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> tuple[Path, dict]:
    """(the mission log, the flight's own `--json` document) of paper, seed 1, at ×20, flown with τ
    unknown to the mission, as with an external autopilot (the built-in vehicle flies it)."""
    out = tmp_path_factory.mktemp("flight")
    mp = pytest.MonkeyPatch()
    made = sim_runner.controller_from_scenario
    mp.setattr(sim_runner, "controller_from_scenario", lambda *a, **kw: made(*a, **{**kw, "external_vehicle": True}))
    mp.setenv("UAVLOC_RUNS", str(out / "runs"))
    stdout = io.StringIO()
    try:
        with contextlib.redirect_stdout(stdout):
            code = main(["-q", "sim", "paper", "--speedup", "20", "--seed", "1", "--planner", "lawnmower", "--json",
                         "--out", str(out)])
    finally:
        mp.undo()
    assert code in (0, 1)  # 1: a user not located (a loaded machine); the log is what is tested
    return out / "mission.jsonl", json.loads(stdout.getvalue())


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in _lines(path)]


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def _replay_json(path: Path, capsys) -> tuple[int, dict | None, str]:
    capsys.readouterr()
    code = main(["-q", "replay", str(path), "--json"])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if code == 0 else None), err


def _bounds(doc: dict) -> list[float]:
    return [u["error_bound_95_m"] for u in doc["users"]]


# -- one answer -----------------------------------------------------------------------------------


@pytest.mark.sim
def test_replay_uses_the_tau_the_flight_estimated(flight):
    path, _ = flight
    mlog = read_mission_log(path)
    assert mlog.header.noise.gps_tau_s is None  # the mission left τ unknown
    (event,) = [e for e in mlog.events if e.get("kind") == "gps_tau"]
    # estimated from the take-off's telemetry, or (too few fixes: a loaded machine) the default assumed
    assert event["gps_tau_s"] >= 0 and isinstance(event["estimated"], bool)
    assert mlog.gps_tau_s == event["gps_tau_s"]
    assert resolve_gps_tau(mlog, mlog.header.noise).gps_tau_s == event["gps_tau_s"]
    # the whole log's telemetry gives another τ: replay no longer estimates it a second time
    without = _write(path.with_name("no-tau-event.jsonl"),
                     [line for line, r in zip(_lines(path), _records(path), strict=True) if r.get("kind") != "gps_tau"])
    other = read_mission_log(without)
    assert other.gps_tau_s is None
    assert resolve_gps_tau(other, other.header.noise).gps_tau_s != event["gps_tau_s"]


@pytest.mark.sim
def test_replay_of_the_flights_log_is_the_flights_own_result(flight, capsys):
    path, doc = flight
    code, replayed, err = _replay_json(path, capsys)
    assert code == 0 and "recorded status" not in err
    # bit-identical: JSON's floats are the doubles' shortest round-trip repr
    assert replayed == {k: v for k, v in doc.items() if k != "speedup"}
    assert replayed["status_logged"] == doc["status"] == replayed["status"]
    # report.json (written by the flight's --out) is the same result
    rep = json.loads((path.parent / "report.json").read_text())
    assert [u["error_bound_95_m"] for u in rep["users"]] == _bounds(doc) and rep["status"] == doc["status"]


@pytest.fixture(scope="module")
def paper(tmp_path_factory) -> tuple[Path, dict]:
    """(the bundled paper log, its replay's document)."""
    path = tmp_path_factory.mktemp("paper") / "paper.jsonl"
    path.write_text(EXAMPLE.read_text())
    return path, result_of_replay(replay(read_mission_log(path), ReplayOptions(history=False))).to_document()


def _ended(path: Path, out: Path, target_m: float, status: str, reason: str) -> Path:
    """The log with a stop rule's target in its header (as the controller logs its settings) and an
    end record of `status`."""
    lines = _lines(path)
    header = json.loads(lines[0])
    header["config"]["controller"] = {"flight": {"target_radius_m": target_m}}
    lines[0] = json.dumps(header)
    end = {"type": "event", "t": json.loads(lines[-1])["t"], "kind": "end", "status": status, "reason": reason,
           "message": f"mission end: {status} ({reason})"}
    return _write(out, [*lines, json.dumps(end)])


def test_a_status_the_answer_does_not_support_is_recomputed_and_said(paper, tmp_path, capsys):
    path, doc = paper
    (bound,) = _bounds(doc)
    # recorded target_reached, but the answer's bound is beyond the target
    missed = _ended(path, tmp_path / "missed.jsonl", 0.5 * bound, STATUS_TARGET, "target reached")
    code, got, err = _replay_json(missed, capsys)
    assert code == 0 and got["status"] == STATUS_TARGET_MISSED and got["status_logged"] == STATUS_TARGET
    assert f"ue1 at {bound:.2f} m" in got["reason"] and _bounds(got) == _bounds(doc)
    assert "recorded status target_reached" in err and "target_missed" in err and "missed.jsonl" in err
    # recorded budget_spent, but the answer bounds every user within the target
    budget = _ended(path, tmp_path / "budget.jsonl", 2.0 * bound, STATUS_BUDGET, "budget spent")
    code, got, err = _replay_json(budget, capsys)
    assert code == 0 and got["status"] == STATUS_TARGET and got["status_logged"] == STATUS_BUDGET
    assert got["reason"] == "target reached in the final answer (the survey ended budget_spent)"
    assert "recorded status budget_spent" in err
    # a status the answer supports: printed as recorded, no warning
    held = _ended(path, tmp_path / "held.jsonl", 2.0 * bound, STATUS_TARGET, "target reached")
    code, got, err = _replay_json(held, capsys)
    assert (got["status"], got["reason"], got["status_logged"]) == (STATUS_TARGET, "target reached", STATUS_TARGET)
    assert "recorded status" not in err
    # the text summary prints the recomputed status
    capsys.readouterr()
    assert main(["-q", "replay", str(missed)]) == 0
    assert capsys.readouterr().out.startswith(f"mission {STATUS_TARGET_MISSED} (")


# -- refusals -------------------------------------------------------------------------------------


def test_an_rtt_line_repeated_100_times_counts_once(paper, tmp_path, capsys, caplog):
    path, doc = paper
    lines, recs = _lines(path), _records(path)
    rtt = [i for i, r in enumerate(recs) if r["type"] == "rtt"]
    i = rtt[len(rtt) // 2]
    dup = _write(tmp_path / "dup.jsonl", lines[:i + 1] + [lines[i]] * 100 + lines[i + 1:])
    with caplog.at_level(logging.WARNING):
        mlog = read_mission_log(dup)
    assert mlog.duplicate_rtt == 100 and mlog.duplicate_rtt_line == i + 2
    assert len(mlog.rtt_t_s) == len(rtt)
    assert f"dropped 100 duplicate rtt record(s), first on line {i + 2}" in caplog.text
    code, got, err = _replay_json(dup, capsys)
    assert code == 0 and "dropped 100 duplicate" in err
    assert min(b - a for a, b in zip(_bounds(doc), _bounds(got), strict=True)) >= 0.0  # never smaller
    assert got["measurements"] == doc["measurements"]


def test_a_repeated_rtt_record_with_another_range_is_refused(paper, tmp_path, capsys):
    path, _ = paper
    lines, recs = _lines(path), _records(path)
    i = next(i for i, r in enumerate(recs) if r["type"] == "rtt")
    other = {k: v for k, v in recs[i].items() if k not in ("ta", "srs_peak")}
    other["toa_s"] = 1.5 * recs[i]["toa_s"]
    bad = _write(tmp_path / "contradicts.jsonl", [*lines[:i + 1], json.dumps(other), *lines[i + 1:]])
    with pytest.raises(MissionLogError, match=rf"contradicts\.jsonl:{i + 2}: .*same time .*line {i + 1}"):
        read_mission_log(bad)
    code, _, err = _replay_json(bad, capsys)
    assert code == 1 and f"contradicts.jsonl:{i + 2}" in err


@pytest.fixture(scope="module")
def fleet_log(tmp_path_factory) -> Path:
    return _write_fleet_log(tmp_path_factory.mktemp("fleet") / "fleet.jsonl")


@pytest.mark.parametrize("rtype", ["rtt", "telemetry"])
def test_a_fleet_record_without_its_vehicle_is_refused_with_its_line(fleet_log, tmp_path, capsys, rtype):
    """Half of the records stripped of `vehicle` (the issue's half-stripped fleet log): refused at
    the first, never replayed onto vehicle 0's track."""
    lines, recs = _lines(fleet_log), _records(fleet_log)
    ix = [i for i, r in enumerate(recs) if r["type"] == rtype][1::2]
    for i in ix:
        lines[i] = json.dumps({k: v for k, v in recs[i].items() if k != "vehicle"})
    bad = _write(tmp_path / f"stripped-{rtype}.jsonl", lines)
    with pytest.raises(MissionLogError) as err:
        read_mission_log(bad)
    msg = str(err.value)
    assert msg.startswith(f"{bad}:{ix[0] + 1}: {rtype} record names no 'vehicle'") and "uav1, uav2" in msg
    code, _, out = _replay_json(bad, capsys)
    assert code == 1 and f"stripped-{rtype}.jsonl:{ix[0] + 1}" in out


def test_the_fleet_log_replays_whole(fleet_log):
    """The unmutated log the refusals above start from is read and replayed."""
    res = replay(read_mission_log(fleet_log), ReplayOptions(history=False))
    assert {kf.vehicle for kf in res.keyframes} == {0, 1} and np.all(np.isfinite(res.estimate.users_enu_m))


@pytest.mark.parametrize(("edit", "words"), [
    (lambda r: {**r, "vehicle": 5}, "'vehicle' = 5 is out of range"),
    (lambda r: {**r, "user": "ue9"}, "rtt for unknown user 'ue9'"),
])
def test_a_record_contradicting_the_header_is_refused_with_its_line(fleet_log, tmp_path, edit, words):
    lines, recs = _lines(fleet_log), _records(fleet_log)
    i = next(i for i, r in enumerate(recs) if r["type"] == "rtt")
    lines[i] = json.dumps(edit(recs[i]))
    bad = _write(tmp_path / "contradicts-header.jsonl", lines)
    with pytest.raises(MissionLogError, match=rf"contradicts-header\.jsonl:{i + 1}: .*{words}"):
        read_mission_log(bad)


def test_result_of_replay_keeps_the_logged_status(fleet_log):
    """A log without a target (another tool's) keeps its recorded status, and says which it was."""
    res = result_of_replay(replay(read_mission_log(fleet_log), ReplayOptions(history=False)))
    assert (res.status, res.status_logged, res.status_note()) == ("ok", "ok", None)
