"""`uavloc replay LOG --out DIR`: the report and the exports agree with the replay's own answer."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mission.cli import main
from mission.report import FIG_DPI, FIG_SIZE_IN, FIGURES
from tests.test_export import _mavsdk_import

EXAMPLE = Path(__file__).resolve().parents[1] / "sitl_scenarios" / "data" / "example_paper.jsonl"


def test_replay_out_writes_a_report_that_matches_the_replay(tmp_path, capsys):
    from PIL import Image

    out = tmp_path / "report"
    assert main(["replay", str(EXAMPLE), "--json", "--out", str(out)]) == 0
    doc = json.loads(capsys.readouterr().out)
    rep = json.loads((out / "report.json").read_text())
    # report.json is the replay's document and the report's own sections beside it
    assert {k: rep[k] for k in doc} == doc
    assert set(rep) - set(doc) >= {"title", "noise", "range_statistics", "figures"}
    # the log ends without an `end` record: the status is the estimate's
    assert doc["status"] == "ok" and doc["reason"] == "the log has no end record"
    for name in FIGURES:
        with Image.open(out / f"{name}.png") as im:
            im.load()
            assert im.size == (int(FIG_SIZE_IN[0] * FIG_DPI), int(FIG_SIZE_IN[1] * FIG_DPI))
    gj = json.loads((out / "mission.geojson").read_text())
    est = [f for f in gj["features"] if f["properties"]["kind"] == "user_estimate"]
    assert [f["properties"]["id"] for f in est] == [u["id"] for u in doc["users"]]
    lon, lat, _ = est[0]["geometry"]["coordinates"]
    assert (lat, lon) == pytest.approx((doc["users"][0]["lat_deg"], doc["users"][0]["lon_deg"]), abs=1e-8)
    items = _mavsdk_import((out / "mission.plan").read_text()).mission_items
    assert len(items) >= 4
    assert (out / "report.html").is_file()
