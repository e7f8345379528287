"""Fleet size as a campaign dimension (issue 41): the spec's `fleet`, the runs and keys it expands to,
the results' n_vehicles column and the summary's fleet speed-up. No flights: specs are expanded and
the summary reads hand-made records."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math

import pyarrow.parquet as pq
import pytest

from sitl_scenarios.campaign import ResultsStore, run_one, spec_from_dict
from sitl_scenarios.campaign.outcome import Outcome
from sitl_scenarios.campaign.results import records_to_table
from sitl_scenarios.campaign.spec import _run_key
from sitl_scenarios.campaign.summary import (
    fleet_size,
    fleet_speedup_rows,
    format_fleet_speedup,
    format_table,
    series_label,
    summary_rows,
    summary_text,
    write_summary,
)
from uavloc.errors import CampaignError

# a bundled scenario file and two generated worlds; two planners, two estimators, two seeds
SPEC = {
    "campaign": {"name": "fleet", "mode": "fast", "seeds": [0, 3], "planners": ["lawnmower", "greedy"],
                 "targets_m": [4.0, 2.0]},
    "estimators": {"default": {"window": 30}, "w40": {"window": 40}},
    "scenarios": [{"file": "three_users_nlos"}],
    "families": [{"name": "small", "count": 2, "seed": 7, "users": [1, 2], "mission": {"budget_m": 400.0}}],
}


def _spec(**campaign) -> dict:
    data = copy.deepcopy(SPEC)
    data["campaign"].update(campaign)
    return data


def _key_before_fleets(run) -> str:
    """The run key as it was made before fleets existed (a fast-mode run over telnet/rtt): a
    one-vehicle run must keep it, so a resumed campaign still skips its done runs."""
    definition = {
        "scenario": dataclasses.asdict(run.scenario), "planner": run.planner, "planner_opts": run.planner_opts,
        "params": dataclasses.asdict(run.params), "seed": run.seed, "mode": run.mode,
        "targets_m": list(run.targets_m), "speedup": run.speedup if run.mode == "full" else None,
    }
    digest = hashlib.sha1(json.dumps(definition, sort_keys=True, default=repr).encode()).hexdigest()[:12]
    return f"{run.condition}/{run.scenario.name}/{run.planner}/{run.estimator}/s{run.seed}#{digest}"


# --- the spec -----------------------------------------------------------------------------------


def test_without_fleet_every_run_flies_one_vehicle():
    campaign = spec_from_dict(copy.deepcopy(SPEC))
    assert campaign.section.fleet == [1]
    assert len(campaign.runs) == 3 * 2 * 2 * 2
    assert {r.n_vehicles for r in campaign.runs} == {1}


def test_fleet_sizes_multiply_the_runs_and_one_vehicle_runs_keep_their_keys():
    plain = spec_from_dict(copy.deepcopy(SPEC)).runs
    runs = spec_from_dict(_spec(fleet=[1, 2, 3])).runs
    # scenarios × planners × estimators × fleet sizes × seeds, fleet sizes inside estimators, seeds inside fleets
    assert len(runs) == 3 * 2 * 2 * 3 * 2
    assert [(r.n_vehicles, r.seed) for r in runs[:6]] == [(1, 0), (1, 3), (2, 0), (2, 3), (3, 0), (3, 3)]
    assert len({r.key for r in runs}) == len(runs)
    ones = [r for r in runs if r.n_vehicles == 1]
    # a one-vehicle run is the run it was before fleets: same key, same definition
    assert [r.key for r in ones] == [r.key for r in plain]
    assert [r.key for r in ones] == [_key_before_fleets(r) for r in ones]
    for r in ones:
        assert r.key == _run_key(r.condition, r.scenario, r.planner, r.planner_opts, r.estimator, r.params, r.seed,
                                 r.mode, r.targets_m, r.speedup)
    # a fleet is another run: its fleet size is in the key's digest and its readable part
    by_def = {(r.condition, r.scenario.name, r.planner, r.estimator, r.seed): r.key for r in ones}
    for r in runs:
        if r.n_vehicles != 1:
            solo = by_def[(r.condition, r.scenario.name, r.planner, r.estimator, r.seed)]
            assert r.key != solo and f"/{r.estimator}/x{r.n_vehicles}/s{r.seed}#" in r.key
            assert r.key.split("#")[1] != solo.split("#")[1]


def test_a_fleet_without_one_vehicle_has_only_fleet_runs():
    runs = spec_from_dict(_spec(fleet=[4], seeds=[0])).runs
    assert len(runs) == 3 * 2 * 2 and {r.n_vehicles for r in runs} == {4}


@pytest.mark.parametrize("value, named", [
    ([], "campaign.fleet must be distinct fleet sizes from 1 to 8 (vehicles per run), got []"),
    ([0, 2], "campaign.fleet must be distinct fleet sizes from 1 to 8 (vehicles per run), got [0, 2]"),
    ([1, 9], "got [1, 9]"),
    ([-1], "got [-1]"),
    ([2, 2], "got [2, 2]"),
    ([1.5], "key 'campaign.fleet[0]' = 1.5: expected an integer"),
    ([True], "key 'campaign.fleet[0]' = True: expected an integer"),
    (2, "key 'campaign.fleet' = 2: expected a list"),
    ("1,2", "key 'campaign.fleet' = '1,2': expected a list"),
])
def test_a_bad_fleet_is_a_clear_error_naming_the_file_key_and_value(value, named):
    with pytest.raises(CampaignError) as err:
        spec_from_dict(_spec(fleet=value), "spec.toml")
    assert str(err.value).startswith("spec.toml: ") and named in str(err.value)


def test_full_mode_refuses_fleets_of_more_than_one_vehicle():
    data = _spec(mode="full", fleet=[1, 2], planners=["lawnmower"])
    data["estimators"] = {"default": {}}
    with pytest.raises(CampaignError) as err:
        spec_from_dict(data, "spec.toml")
    assert str(err.value) == ('spec.toml: campaign.fleet [1, 2]: full mode flies one vehicle; fleet sizes > 1 need '
                              'mode = "fast"')
    data["campaign"]["fleet"] = [1]
    assert {r.n_vehicles for r in spec_from_dict(data, "spec.toml").runs} == {1}


# --- the task and the results -------------------------------------------------------------------


def test_run_one_flies_the_runs_fleet_and_records_its_size(monkeypatch):
    import sitl_scenarios.campaign.fast as fast

    asked = []

    def fake_fly_fast(*args, n_vehicles: int = 1, **kwargs):
        asked.append(n_vehicles)
        return Outcome(end="budget: budget spent")

    monkeypatch.setattr(fast, "fly_fast", fake_fly_fast)
    run = next(r for r in spec_from_dict(_spec(fleet=[1, 3])).runs if r.n_vehicles == 3)
    rec = run_one(run)
    assert asked == [3]
    assert rec["status"] == "ok" and rec["n_vehicles"] == 3
    assert records_to_table([rec]).column("n_vehicles").to_pylist() == [3]


def test_results_written_before_fleets_read_as_one_vehicle(tmp_path):
    rec = {"key": "c/w/p/e/s0#0", "condition": "c", "scenario": "w", "planner": "p", "estimator": "e", "seed": 0,
           "status": "ok"}
    old = records_to_table([rec]).drop_columns(["n_vehicles"])
    (tmp_path / "results").mkdir()
    pq.write_table(old, tmp_path / "results" / "part-0.parquet")
    (back,) = ResultsStore(tmp_path).read_records()
    assert back["n_vehicles"] is None and fleet_size(back) == 1


# --- the summary --------------------------------------------------------------------------------

NAN = math.nan
TARGETS = (3.0, 1.0)


def rec(scenario, seed, n, seconds, planner="casadi", status="ok", condition="drift"):
    r = {"key": f"{condition}/{scenario}/{planner}/default/x{n}/s{seed}", "condition": condition,
         "scenario": scenario, "planner": planner, "estimator": "default", "seed": seed, "n_vehicles": n,
         "status": status, "metres_to_m": [10.0 * s for s in seconds], "seconds_to_s": list(seconds),
         "budget_m": 3000.0, "survey_s": 500.0, "flown_m": 3000.0, "mean_error_m": 1.0, "inside95": 0.9,
         "plan_times_s": [0.01], "violations": 0, "final_error_m": [1.0], "final_bound95_m": [2.0],
         "wall_s": 1.0}
    if n is None:
        del r["n_vehicles"]  # a record written before n_vehicles
    return r


def fleet_records() -> list[dict]:
    return [
        # one vehicle
        rec("w0", 0, 1, [100.0, 300.0]),
        rec("w0", 1, 1, [200.0, NAN]),      # never reached 1 m
        rec("w0", 2, 1, [50.0, 150.0]),
        rec("w1", 0, None, [80.0, 400.0]),  # written before n_vehicles: one vehicle
        rec("w0", 3, 1, [NAN, NAN], status="error"),
        # two vehicles
        rec("w0", 0, 2, [60.0, 120.0]),     # 0.6, 0.4
        rec("w0", 1, 2, [100.0, 200.0]),    # 0.5, (one vehicle never reached 1 m)
        rec("w0", 2, 2, [40.0, NAN]),       # 0.8, (never reached 1 m)
        rec("w1", 0, 2, [20.0, 200.0]),     # 0.25, 0.5
        rec("w0", 3, 2, [10.0, 10.0]),      # its one-vehicle run failed: no pair
        rec("w0", 4, 2, [10.0, 10.0]),      # no one-vehicle run of seed 4: no pair
        rec("w0", 0, 2, [50.0, 100.0], planner="lawnmower"),  # no one-vehicle lawnmower run: no pair
        rec("w0", 0, 2, [50.0, 100.0], condition="ideal"),    # nor one in its condition
        # three vehicles
        rec("w0", 0, 3, [30.0, 60.0]),      # 0.3, 0.2
    ]


def test_the_fleet_speed_up_pairs_runs_by_scenario_seed_and_planner():
    rows = fleet_speedup_rows(fleet_records(), TARGETS)
    got = [(r["condition"], r["planner"], r["n_vehicles"], r["target_m"], r["pairs"], r["both_reached"],
            r["ratio_median"], r["ratio_max"]) for r in rows]
    assert got == [
        ("drift", "casadi", 2, 3.0, 4, 4, pytest.approx(0.55), pytest.approx(0.8)),
        ("drift", "casadi", 2, 1.0, 4, 2, pytest.approx(0.45), pytest.approx(0.5)),
        ("drift", "casadi", 3, 3.0, 1, 1, pytest.approx(0.3), pytest.approx(0.3)),
        ("drift", "casadi", 3, 1.0, 1, 1, pytest.approx(0.2), pytest.approx(0.2)),
    ]
    lines = format_fleet_speedup(rows).splitlines()
    assert lines[0].startswith("fleet speed-up")
    table = [ln.split() for ln in lines if ln.startswith("drift")]
    assert table == [["drift", "casadi", "default", "2", "3", "4/4", "0.55", "0.80"],
                     ["drift", "casadi", "default", "2", "1", "2/4", "0.45", "0.50"],
                     ["drift", "casadi", "default", "3", "3", "1/1", "0.30", "0.30"],
                     ["drift", "casadi", "default", "3", "1", "1/1", "0.20", "0.20"]]


def test_the_speed_up_table_is_printed_only_with_more_than_one_fleet_size():
    records = fleet_records()
    assert "fleet speed-up" in summary_text(records, TARGETS)
    solo = [r for r in records if fleet_size(r) == 1]
    assert fleet_speedup_rows(solo, TARGETS) == [] and "fleet speed-up" not in summary_text(solo, TARGETS)
    twos = [r for r in records if fleet_size(r) == 2]
    assert fleet_speedup_rows(twos, TARGETS) == [] and "fleet speed-up" not in summary_text(twos, TARGETS)
    # more than one size but none to pair with: the table says so
    no_solo = [r for r in records if fleet_size(r) in (2, 3)]
    assert "(no pairs:" in summary_text(no_solo, TARGETS)


def test_the_summary_groups_by_fleet_size_and_shows_it_only_for_fleets():
    records = fleet_records()
    rows = summary_rows(records, TARGETS)
    keys = [(r["condition"], r["planner"], r["n_vehicles"]) for r in rows]
    assert keys == [("drift", "casadi", 1), ("drift", "casadi", 2), ("drift", "lawnmower", 2),
                    ("ideal", "casadi", 2), ("drift", "casadi", 3)]
    assert [r["runs"] for r in rows] == [5, 6, 1, 1, 1] and rows[0]["failed"] == 1
    table = format_table(rows, TARGETS).splitlines()
    assert table[0].split()[:4] == ["condition", "planner", "fleet", "estimator"]
    assert [ln.split()[:3] for ln in table[2:7]] == [["drift", "casadi", "1"], ["drift", "casadi", "2"],
                                                     ["drift", "lawnmower", "2"], ["ideal", "casadi", "2"],
                                                     ["drift", "casadi", "3"]]
    # one vehicle everywhere: the table as it was (no fleet column), whether or not the records have n_vehicles
    solo = summary_rows([r for r in records if fleet_size(r) == 1], TARGETS)
    assert len(solo) == 1 and solo[0]["n_vehicles"] == 1 and solo[0]["runs"] == 5
    text = format_table(solo, TARGETS)
    assert text.startswith(f"{'condition':<14} {'planner':<10} {'estimator':<10} {'runs':>4} {'fail':>4}")
    assert "fleet" not in text
    assert text == format_table([{k: v for k, v in solo[0].items() if k != "n_vehicles"}], TARGETS)


def test_the_figures_series_name_the_fleet_size():
    assert series_label(rec("w0", 0, 2, [1.0, 1.0]), fleets=True) == "casadi ×2"
    assert series_label(rec("w0", 0, None, [1.0, 1.0]), fleets=True) == "casadi ×1"
    assert series_label(rec("w0", 0, 1, [1.0, 1.0]), fleets=False) == "casadi"


def test_write_summary_writes_the_speed_up_beside_the_table(tmp_path):
    paths = write_summary(fleet_records(), TARGETS, tmp_path)
    text = (tmp_path / "summary.txt").read_text(encoding="utf-8")
    assert "fleet speed-up" in text and " fleet " in text.splitlines()[0]
    lines = (tmp_path / "fleet_speedup.csv").read_text(encoding="utf-8").splitlines()
    assert lines[0] == "condition,planner,estimator,n_vehicles,target_m,pairs,both_reached,ratio_median,ratio_max"
    assert len(lines) == 5 and paths["fleet_speedup"] == tmp_path / "fleet_speedup.csv"
    assert (tmp_path / "summary.csv").read_text(encoding="utf-8").startswith("condition,planner,n_vehicles,")
    for name in ("metres_to_target", "error_vs_bound"):
        assert paths[name].stat().st_size > 0
