"""Issue 39 item 5, "one result": a mission's result is one object (mission.result.Result), and
the CLI's `--json`, report.json and `uavloc replay --json` are renderings of it that agree."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from estimator.geodesy import Origin
from estimator.types import Estimate
from mission.cli import main
from mission.log import MissionLogWriter, read_mission_log
from mission.replay import end_of_log, result_of_log
from mission.result import STATUS_TARGET, build_result

ORIGIN = Origin(43.6143, 7.0716, 150.0)
RESULT_KEYS = ("status", "reason", "flown_m", "measurements", "keyframes", "duration_s", "survey_s", "hover_s",
               "largest_gap_s", "origin", "log")


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory, monkeypatch_module):
    """A short simulated mission (paper, seed 1, speedup 20) with `--json --out D`, in process."""
    import contextlib
    import io

    out_dir = tmp_path_factory.mktemp("one-result")
    monkeypatch_module.setenv("UAVLOC_RUNS", str(out_dir / "runs"))
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["-q", "sim", "paper", "--speedup", "20", "--seed", "1", "--json", "--out", str(out_dir)])
    assert code in (0, 1)
    return out_dir, json.loads(stdout.getvalue())


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


@pytest.mark.sim
def test_json_report_and_replay_give_one_document(sim_run, capsys):
    out_dir, doc = sim_run
    log_path = out_dir / "mission.jsonl"
    rep = json.loads((out_dir / "report.json").read_text())
    # the result's keys, every one, are the same in report.json
    for key in RESULT_KEYS:
        assert rep[key] == doc[key], key
    assert rep["users"] == doc["users"]
    assert doc["status"] == STATUS_TARGET and doc["reason"] == "target reached"
    # report-only sections never redefine a key of the result document
    assert set(rep) - set(doc) == {"title", "mission", "noise", "range_statistics", "figures"}
    assert set(rep["range_statistics"]) == {u["id"] for u in doc["users"]}
    # the mission's seconds: header to the end record, not the keyframes' span
    mlog = read_mission_log(log_path)
    status, reason, t_end = end_of_log(mlog)
    assert (status, reason) == (doc["status"], doc["reason"])
    assert doc["duration_s"] == pytest.approx(t_end) and doc["duration_s"] > mlog.rtt_t_s[-1] - mlog.rtt_t_s[0]
    assert doc["survey_s"] > 0 and 0 <= doc["hover_s"] <= doc["survey_s"]
    # the clock sawtooth's bias, noise scale and NLoS shift are in both (the estimator's, as estimated)
    assert all("bias_m" in u and "noise_scale" in u and "clock_sawtooth" in u for u in rep["users"])
    capsys.readouterr()
    assert main(["-q", "replay", str(log_path), "--json"]) == 0
    # replay prints the same document; only the run's `speedup` (a fact of the run, not of its log) is
    # the mission's alone
    assert "speedup" in doc
    assert json.loads(capsys.readouterr().out) == {k: v for k, v in doc.items() if k != "speedup"}


@pytest.mark.sim
def test_the_text_summary_renders_the_same_result(sim_run, capsys):
    out_dir, doc = sim_run
    assert main(["-q", "replay", str(out_dir / "mission.jsonl")]) == 0
    text = capsys.readouterr().out
    assert text.splitlines()[0] == (f"mission {doc['status']} ({doc['reason']}): {doc['measurements']} ranges, "
                                    f"{doc['keyframes']} keyframes, {doc['flown_m']:.0f} m flown in "
                                    f"{doc['duration_s']:.0f} s")
    for u in doc["users"]:
        assert f"  {u['id']}: lat {u['lat_deg']:.7f}" in text


def _estimate(k: int = 2, clock: bool = False) -> Estimate:
    users = np.array([[10.0, 20.0, 0.0], [-30.0, 5.0, 0.0]])[:k]
    cov = np.tile(np.diag([1.0, 2.0, 1.0]), (k, 1, 1))
    return Estimate(users_enu_m=users, cov_users_m2=cov, info_users=np.eye(3 * k), bias_m=np.array([4.0, 1.0])[:k],
                    uav_enu_m=np.zeros((0, 3)), ambiguous=np.zeros(k, bool), mirror_enu_m=np.full((k, 3), np.nan),
                    n_ranges=np.array([30, 31])[:k])


def test_build_result_is_strict_json_and_reads_back_typed():
    est = _estimate()
    res = build_result(status=STATUS_TARGET, reason="target reached", user_ids=["a", "b"], estimate=est,
                       origin=ORIGIN, truth_enu_m=np.array([[10.0, 21.0, 0.0], [-30.0, 5.0, 0.0]]), flown_m=123.4,
                       measurements=61, keyframes=30, duration_s=99.0)
    doc = res.to_document()
    json.dumps(doc, allow_nan=False)
    assert doc["duration_s"] == 99.0 and doc["survey_s"] is None and doc["origin"] == ORIGIN.to_dict()
    assert [u.error_m for u in res.users] == pytest.approx([1.0, 0.0])
    assert res.users[0].sigma_north_m == pytest.approx(np.sqrt(2.0))
    assert doc["users"][1]["measurements"] == 31 and res.ok
    lost = build_result(status=STATUS_TARGET, reason="x", user_ids=["a", "b"], estimate=None, origin=ORIGIN,
                        flown_m=0.0, measurements=0, keyframes=0)
    assert lost.not_located() == ["a", "b"] and not lost.ok


def _log(path: Path, end: dict | None) -> Path:
    with MissionLogWriter(path) as w:
        w.write_header(ORIGIN, [{"id": "a", "rnti": 1, "ground_alt_m": 150.0}], {"mu": 1, "fs_hz": 46.08e6})
        w.write("telemetry", 5.0, lat_deg=43.6143, lon_deg=7.0716, alt_m=190.0)
        w.write("event", 40.0, message="survey 30 s", kind="survey_time", survey_s=30.0, hover_s=2.5,
                largest_gap_s=1.5)
        w.write("telemetry", 50.0, lat_deg=43.6144, lon_deg=7.0716, alt_m=190.0)
        if end is not None:
            w.write("event", 61.0, **end)
    return path


def test_status_reason_and_duration_come_from_the_end_record(tmp_path):
    new = read_mission_log(_log(tmp_path / "new.jsonl", {"message": "mission end: returned (low battery)",
                                                          "kind": "end", "status": "returned",
                                                          "reason": "battery (low) at 20 %"}))
    res = result_of_log(new, None)
    assert (res.status, res.reason, res.duration_s) == ("returned", "battery (low) at 20 %", 61.0)
    assert (res.survey_s, res.hover_s, res.largest_gap_s) == (30.0, 2.5, 1.5)
    # a log written before the end record carried `reason`: its message names it
    old = read_mission_log(_log(tmp_path / "old.jsonl", {"message": "mission end: budget_spent (budget spent)",
                                                          "kind": "end", "status": "budget_spent"}))
    assert end_of_log(old) == ("budget_spent", "budget spent", 61.0)
    # no end record: the estimate's status, the duration to the last record
    none = result_of_log(read_mission_log(_log(tmp_path / "none.jsonl", None)), None)
    assert none.status == "incomplete" and none.duration_s == 50.0 and none.not_located() == ["a"]
