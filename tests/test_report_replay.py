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
    assert rep["status"] == doc["status"]
    assert rep["measurements"] == doc["measurements"] and rep["keyframes"] == doc["keyframes"]
    assert rep["flown_m"] == pytest.approx(doc["flown_m"])
    for u_rep, u_doc in zip(rep["users"], doc["users"], strict=True):
        assert u_rep["id"] == u_doc["id"]
        assert u_rep["lat_deg"] == pytest.approx(u_doc["lat_deg"], abs=1e-10)
        assert u_rep["lon_deg"] == pytest.approx(u_doc["lon_deg"], abs=1e-10)
        assert u_rep["error_bound_95_m"] == pytest.approx(u_doc["error_bound_95_m"], rel=1e-9)
        assert u_rep["error_m"] == pytest.approx(u_doc["error_m"], rel=1e-9)
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
    assert "report.html" in doc["report"] or any("report.html" in str(v) for v in doc["report"].values())
