"""Issue 40, the report of one simulated mission (three_users_nlos, seed 1, speedup 20, `--out D`):
report.html shows every figure, titled after the mission with each user's error as the mission's
Result prints it, and names the command, scenario, seed, planner, date and uavloc's version."""

from __future__ import annotations

import contextlib
import html
import io
import json
import re
from importlib.metadata import version

import pytest

from mission.cli import main
from mission.log import read_mission_log

#: the figures the paper shows, by file name
VIEWS = ("top_view", "side_view_east", "side_view_north", "view_3d")
FIGURES = (*VIEWS, "range_error")


@pytest.fixture(scope="module")
def mission_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("report-mission")
    mp = pytest.MonkeyPatch()
    mp.setenv("UAVLOC_RUNS", str(out / "runs"))
    stdout = io.StringIO()
    try:
        with contextlib.redirect_stdout(stdout):
            code = main(["-q", "sim", "three_users_nlos", "--speedup", "20", "--seed", "1", "--json",
                         "--out", str(out)])
    finally:
        mp.undo()
    assert code in (0, 1)
    page = (out / "report.html").read_text(encoding="utf-8")
    return out, json.loads(stdout.getvalue()), page


def _figures(page: str) -> dict[str, tuple[str, str]]:
    """{figure id: (alt text, caption)} of report.html."""
    found = re.findall(r'<figure id="([^"]+)"><img alt="([^"]*)" src="data:image/png;base64,[^"]+">'
                       r"<figcaption>(.*?)</figcaption></figure>", page)
    return {name: (html.unescape(alt), html.unescape(cap)) for name, alt, cap in found}


@pytest.mark.sim
def test_every_figure_is_in_the_page_and_the_views_carry_each_users_error(mission_run):
    out, doc, page = mission_run
    figs = _figures(page)
    assert set(FIGURES) <= set(figs), sorted(figs)
    errors = [f"{u['id']} {u['error_m']:.2f} m" for u in doc["users"]]  # as the summary prints them
    assert len(errors) == 3
    for name in VIEWS:
        alt, caption = figs[name]
        assert (out / f"{name}.png").stat().st_size > 0
        assert caption.startswith(f"{name}.png: ")
        for text in errors:
            assert text in alt and text in caption, (name, text, alt)
    # the range error figure writes the model readably: three_users_nlos has σ(d) = 3 m, no exp term
    assert "σ(d) = 3.00 m" in figs["range_error"][0] and "exp" not in figs["range_error"][0]


@pytest.mark.sim
def test_the_page_names_command_scenario_seed_planner_date_and_version(mission_run):
    out, _doc, page = mission_run
    header = read_mission_log(out / "mission.jsonl").header
    cfg = header.config
    assert cfg["command_line"].startswith("uavloc -q sim three_users_nlos --speedup 20 --seed 1")
    assert cfg["seed"] == 1 and cfg["scenario"] == "three_users_nlos" and cfg["planner"]
    title = f"uavloc sim three_users_nlos, seed 1, {cfg['planner']}"
    assert f"<h1>{title}</h1>" in page and f"<title>{title}</title>" in page
    rows = {html.unescape(k): html.unescape(v)
            for k, v in re.findall(r'<tr><th>([^<]+)</th><td class="l">([^<]*)</td></tr>', page)}
    assert rows["command"] == cfg["command_line"]
    assert rows["scenario"] == "three_users_nlos"
    assert rows["seed"] == "1"
    assert rows["planner"] == cfg["planner"]
    assert rows["date (UTC)"] == header.start_utc != ""
    assert rows["uavloc version"] == version("uavloc")
    rep = json.loads((out / "report.json").read_text())
    assert rep["title"] == title and rep["mission"]["start_utc"] == header.start_utc
