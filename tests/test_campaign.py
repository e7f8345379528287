"""Campaigns on Dask: same records as one by one, failures recorded, resume, strict specs (issue 15)."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest

from estimator.types import CHI2_2DOF_95, CHI2_2DOF_999
from sitl_scenarios.campaign import (
    TIMING_FIELDS,
    ResultsStore,
    load_spec,
    run_campaign,
    run_one,
    same_value,
    spec_from_dict,
)
from sitl_scenarios.campaign.families import FamilySpec, generate_scenario
from sitl_scenarios.campaign.summary import format_table, summary_rows
from tests.bench_module import load_benchmark
from uavloc.errors import CampaignError

REPO = Path(__file__).resolve().parents[1]

# small fast-mode runs: 1–2 users in a small fence, a 400 m budget, a 3 m target; the channel has a
# drifting GPS, UE clock sawtooths and NLoS excess behind buildings
SPEC = {
    "campaign": {"name": "t", "mode": "fast", "seeds": [0], "planners": ["lawnmower", "greedy"],
                 "targets_m": [4.0, 3.0]},
    "estimators": {"default": {"window": 30}},
    "families": [{"name": "small", "count": 3, "seed": 7, "users": [1, 2], "fence_half_m": [70.0, 90.0],
                  "no_fly": 0, "buildings": [0, 1], "gps_tau_s": [30.0, 120.0], "sawtooth_amplitude_m": [0.0, 4.0],
                  "nlos_excess_mean_m": 10.0, "mission": {"budget_m": 400.0}}],
}

# a scenario whose fence leaves out home: the planner raises when asked to route from there
# home under a building too tall to overfly (a no-fly zone of the planner's, not of the mission
# file: a home outside the fence or inside a no-fly zone is refused when the scenario loads)
OUTSIDE = """
name = "home_under_tall_building"
[[users]]
id = "ue1"
rnti = 17921
[truth.ue1]
east_m = 150.0
north_m = 150.0
[[buildings]]
footprint_enu_m = [[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]
height_m = 200.0
"""


def deterministic(rec: dict) -> dict:
    return {k: v for k, v in rec.items() if k not in TIMING_FIELDS}


def assert_same_records(a: list[dict], b: list[dict]) -> None:
    assert [r["key"] for r in a] == [r["key"] for r in b]
    for ra, rb in zip(a, b, strict=True):
        da, db = deterministic(ra), deterministic(rb)
        assert da.keys() == db.keys()
        # to the last bits: Dask's workers run BLAS on one thread (its nanny sets OMP_NUM_THREADS=1),
        # this process on every core, and LAPACK's blocked sums round differently
        bad = [k for k in da if not same_value(da[k], db[k], rel=1e-12)]
        assert not bad, f"{ra['key']}: {[(k, da[k], db[k]) for k in bad]}"


@pytest.fixture(scope="module")
def cluster():
    """A LocalCluster of 2 single-threaded worker processes, reached by address like an external one."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, scheduler_port=0, dashboard_address=None,
                      scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                      worker_dashboard_address="127.0.0.1:0") as c:
        yield c


def test_six_runs_on_a_local_cluster_of_two_workers_equal_the_runs_one_by_one(tmp_path):
    campaign = spec_from_dict(copy.deepcopy(SPEC))
    assert len(campaign.runs) == 6
    one_by_one = [run_one(r) for r in campaign.runs]
    done = run_campaign(campaign, tmp_path, workers=2, progress=False)
    assert done.where == "LocalCluster(2)" and done.workers == 2
    assert done.ran == 6 and done.failed == 0
    assert all(r["status"] == "ok" for r in one_by_one), [r["error"] for r in one_by_one]
    assert_same_records(one_by_one, done.records)
    # and what was written to Parquet is what came back
    order = [r.key for r in campaign.runs]
    assert_same_records(one_by_one, sorted(ResultsStore(tmp_path).read_records(), key=lambda r: order.index(r["key"])))
    # the runs measured something: every run located its users to the first target within the budget
    assert all(r["metres_to_m"][0] > 0 for r in one_by_one)
    assert all(len(r["final_error_m"]) == r["users"] for r in one_by_one)
    # each user's final NEES eᵀΣ⁻¹e is at least |e|²/λmax = χ²₂(0.95)·(error / 95 % bound)²
    for r in one_by_one:
        err, bound, nees = (np.array(r[k]) for k in ("final_error_m", "final_bound95_m", "final_nees"))
        assert np.all(np.isfinite(nees) == np.isfinite(err)), r["key"]
        ok = np.isfinite(err)
        assert np.all(nees[ok] >= CHI2_2DOF_95 * (err[ok] / bound[ok]) ** 2 * (1 - 1e-9)), r["key"]


def test_a_run_that_raises_is_recorded_and_the_others_finish(tmp_path, cluster):
    (tmp_path / "outside.toml").write_text(OUTSIDE)
    data = copy.deepcopy(SPEC)
    data["families"][0]["count"] = 1
    data["scenarios"] = [{"file": "outside.toml", "condition": "broken"}]
    (tmp_path / "spec.toml").write_text(_toml(data))
    campaign = load_spec(tmp_path / "spec.toml")
    done = run_campaign(campaign, tmp_path / "out", scheduler=cluster.scheduler_address, progress=False)
    assert done.ran == 4 and done.failed == 2
    by_status = {r["condition"]: r["status"] for r in done.records}
    assert by_status == {"broken": "error", "small": "ok"}
    for r in done.records:
        if r["condition"] == "broken":
            assert r["error"].startswith("PlannerError: ") and "outside the fence" in r["error"]
            assert "Traceback" in r["traceback"]
        else:
            assert r["error"] == "" and r["replans"] > 0
    stored = ResultsStore(tmp_path / "out").read_records()
    assert sorted(r["status"] for r in stored) == ["error", "error", "ok", "ok"]
    assert (tmp_path / "out" / "summary.csv").exists() is False  # the summary is the command's job


def test_a_second_run_of_the_same_spec_skips_what_is_done(tmp_path, cluster):
    data = copy.deepcopy(SPEC)
    data["families"][0]["count"] = 1
    first = run_campaign(spec_from_dict(data), tmp_path, scheduler=cluster.scheduler_address, progress=False)
    assert (first.ran, first.skipped) == (2, 0)
    again = run_campaign(spec_from_dict(data), tmp_path, scheduler=cluster.scheduler_address, progress=False)
    assert (again.ran, again.skipped) == (0, 2)
    assert_same_records(first.records, again.records)
    # a torn write (a part never renamed into place) is not a result
    (tmp_path / "results" / "part-9.tmp").write_bytes(b"PAR1 torn")
    # one more seed: only its runs are new; a changed run definition is a new run
    data["campaign"]["seeds"] = [0, 1]
    more = run_campaign(spec_from_dict(data), tmp_path, scheduler=cluster.scheduler_address, progress=False)
    assert (more.ran, more.skipped) == (2, 2)
    assert sorted(r["seed"] for r in more.records) == [0, 0, 1, 1]
    data["estimators"]["default"]["window"] = 31
    changed = run_campaign(spec_from_dict(data), tmp_path, workers=0, progress=False)
    assert (changed.ran, changed.skipped) == (4, 0)
    assert len(ResultsStore(tmp_path).parts()) == 1  # merged once complete


def _toml(data: dict) -> str:
    """A minimal TOML writer for the specs of these tests (tables, arrays of tables, scalars, lists)."""
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return '"' + v + '"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines = []

    def table(name, d):
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict)}
        lines.extend([f"[{name}]"] + [f"{k} = {value(v)}" for k, v in scalars.items()])
        for k, v in d.items():
            if isinstance(v, dict):
                table(f"{name}.{k}", v)

    for key, v in data.items():
        if isinstance(v, list):
            for item in v:
                lines.append(f"[[{key}]]")
                lines.extend(f"{k} = {value(x)}" for k, x in item.items() if not isinstance(x, dict))
                for k, x in item.items():
                    if isinstance(x, dict):
                        lines.append(f"[{key}.{k}]")
                        lines.extend(f"{kk} = {value(xx)}" for kk, xx in x.items())
        else:
            table(key, v)
    text = "\n".join(lines) + "\n"
    assert tomllib.loads(text) == data  # the writer is only trusted where it round-trips
    return text


def _with(path: tuple, value) -> dict:
    data = copy.deepcopy(SPEC)
    d = data
    for p in path[:-1]:
        d = d[p]
    if value is _DELETE:
        del d[path[-1]]
    else:
        d[path[-1]] = value
    return data


_DELETE = object()


@pytest.mark.parametrize("path, value, named", [
    (("campaign", "colour"), "red", "'colour'"),
    (("extra",), {}, "'extra'"),
    (("campaign", "mode"), "slow", "campaign.mode"),
    (("campaign", "planners"), ["lawnmower", "teleport"], "campaign.planners"),
    (("campaign", "seeds"), [0, 0], "campaign.seeds"),
    (("campaign", "seeds"), "0", "campaign.seeds"),
    (("campaign", "targets_m"), [1.0, float("nan")], "campaign.targets_m"),
    (("campaign", "name"), _DELETE, "'name'"),
    (("estimators", "default", "windw"), 40, "estimators.default"),
    (("estimators", "default", "loss"), "l1", "estimators.default.loss"),
    (("estimators", "default", "window"), 4.5, "estimators.default.window"),
    (("planner_options",), {"casadi": {"horizon": 2}}, "planner_options.casadi"),
    (("planner_options",), {"greedy": {"no_such_option": 1}}, "planner_options.greedy"),
    (("families", 0, "users"), [3, 1], "families[0].users"),
    (("families", 0, "gps_tau_s"), [0.0, 1.0, 2.0], "families[0].gps_tau_s"),
    (("families", 0, "sawtooth_amplitude_m"), -1.0, "families[0].sawtooth_amplitude_m"),
    (("families", 0, "buidlings"), 2, "'buidlings'"),
    (("families", 0, "mission"), {"budget_m": -5.0}, "mission.budget_m"),
    (("families", 0, "mission"), {"budgt_m": 5.0}, "'budgt_m'"),
    (("scenarios",), [{"file": "no_such_scenario"}], "scenarios[0].file"),
])
def test_a_bad_spec_is_a_clear_error_naming_the_key(path, value, named):
    with pytest.raises(CampaignError) as err:
        spec_from_dict(_with(path, value), "spec.toml")
    assert named in str(err.value) and str(err.value).startswith("spec.toml: ")


def test_a_spec_file_that_is_not_toml_names_the_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[campaign\nname = 1\n")
    with pytest.raises(CampaignError, match="bad.toml: not valid TOML"):
        load_spec(bad)


def test_conditions_never_move_a_family_s_geometry():
    plain = FamilySpec(name="f", seed=3)
    drifting = FamilySpec(name="f", seed=3, gps_tau_s=[60.0, 300.0], sawtooth_amplitude_m=[2.0, 8.0],
                          nlos_excess_mean_m=[5.0, 20.0])
    for j in range(4):
        a, b = generate_scenario(plain, j), generate_scenario(drifting, j)
        assert a.geofence == b.geofence and a.buildings == b.buildings
        assert [(u.east_m, u.north_m) for u in a.users] == [(u.east_m, u.north_m) for u in b.users]
        assert a.vehicle.gps_tau_s == 0.0 and 60.0 <= b.vehicle.gps_tau_s <= 300.0
        assert all(2.0 <= u.sawtooth_amplitude_m <= 8.0 for u in b.users)


def test_the_planner_benchmark_spec_loads():
    campaign = load_spec(REPO / "benchmarks" / "planner_campaign.toml")
    # two conditions on the same geometry (the hardware world by default, the ideal one labelled)
    assert len(campaign.runs) == 2 * 30 * 7 and campaign.targets_m == (3.0, 1.0, 0.6)
    assert [r.condition for r in campaign.runs][::210] == ["hardware", "ideal"]
    assert {r.params.window for r in campaign.runs} == {40}


@pytest.mark.parametrize("planners", [("lawnmower", "greedy", "casadi"), ("lawnmower",), ("oracle", "random")])
def test_the_benchmarks_campaign_takes_any_planners_of_it(planners):
    """benchmarks/planner.py --planners and benchmarks/campaign_scaling.py (lawnmower, greedy,
    casadi by default) pick planners of the spec; the options of the others go with them."""
    campaign = _planner_bench().benchmark_campaign(2, planners)
    assert {r.planner for r in campaign.runs} == set(planners) and len(campaign.runs) == 2 * 2 * len(planners)


def _planner_bench():
    return load_benchmark("planner")


def test_the_worlds_benchmark_changes_one_effect_of_the_same_scenarios():
    """benchmarks/planner.py --worlds: the hardware scenarios with one effect changed each, and the
    ideal world flown to the last target; the same geometry in every world."""
    bench = _planner_bench()
    campaign = bench.worlds_campaign(2)
    worlds = [w for w, _ in bench.WORLDS] + ["ideal"]
    assert list(dict.fromkeys(r.condition for r in campaign.runs)) == worlds
    assert len(campaign.runs) == len(worlds) * 2 * 3 and campaign.targets_m == (3.0, 2.0, 1.5)
    sc = {(r.condition, r.scenario.name[-2:]): r.scenario for r in campaign.runs}
    for i in ("00", "01"):
        hw = sc[("hardware", i)]
        assert hw.vehicle.gps_tau_s > 0 and hw.mission.flight.target_radius_m == 3.0
        assert sc[("no-gps-drift", i)].vehicle.gps_tau_s == 0.0
        assert sc[("gps-constant", i)].vehicle.gps_tau_s == 1e5
        assert all(u.sawtooth_amplitude_m == 0.0 for u in sc[("no-sawtooth", i)].users)
        assert sc[("ideal", i)].mission.flight.target_radius_m == 1.5
        for w in worlds:
            assert [(u.east_m, u.north_m) for u in sc[(w, i)].users] == [(u.east_m, u.north_m) for u in hw.users]


def test_the_worlds_table_gives_each_planner_its_metres_and_ratios():
    bench = _planner_bench()

    def rec(world, planner, metres, err=1.0, bound=2.0):
        return {"status": "ok", "condition": world, "planner": planner, "metres_to_m": metres,
                "budget_m": 3000.0, "final_error_m": [err], "final_bound95_m": [bound]}

    records = [rec("hardware", "lawnmower", [600.0, None, None]), rec("hardware", "casadi", [450.0, None, None]),
               rec("hardware", "oracle", [300.0, None, None], err=3.0),
               rec("ideal", "lawnmower", [300.0, 400.0, 500.0]), rec("ideal", "casadi", [150.0, 300.0, float("nan")]),
               rec("ideal", "oracle", [150.0, 200.0, 250.0])]
    rows = bench.summarise_worlds(records).splitlines()
    hw = next(r for r in rows if r.startswith("hardware")).split()
    assert hw[3:11] == ["600", "450", "300", "0.75", "0.50", "1.00", "1.00", "0.00"]
    ideal = [r.split() for r in rows if r.startswith("ideal")]
    # the hardware worlds stop at the first target; the ideal one reads all three (the budget when never)
    assert [r[1] for r in ideal] == ["3", "2", "1.5"] and ideal[2][3:8] == ["500", "3000", "250", "6.00", "0.50"]


def test_the_planner_table_gives_mission_seconds_hover_and_the_floor_and_checks_casadis_seconds():
    """Issue 39: per planner and condition the metres and mission seconds to each target (the whole
    survey when never), hover seconds, the GPS floor beside each target (runs whose floor is above
    it), and the check of casadi's mission seconds against 0.75 x lawnmower's in the hardware world."""
    bench = _planner_bench()

    def rec(planner, metres, seconds, survey_s, hover_s, floor_m, flown_m):
        return {"status": "ok", "condition": "hardware", "planner": planner, "metres_to_m": metres,
                "seconds_to_s": seconds, "survey_s": survey_s, "hover_s": hover_s, "floor_m": floor_m,
                "flown_m": flown_m, "budget_m": 3000.0, "error_at_m": [1.0, float("nan")], "final_error_m": [1.0],
                "final_bound95_m": [2.0], "plan_times_s": [0.01], "violations": 0}

    nan = float("nan")
    # the lawnmower flew its budget; casadi ended at its floor after 1500 and 1950 m
    records = [rec("lawnmower", [600.0, nan], [100.0, nan], 300.0, 0.0, 1.2, 3000.0),
               rec("lawnmower", [800.0, nan], [140.0, nan], 400.0, 0.0, 2.5, 3000.0),
               rec("casadi", [300.0, nan], [80.0, nan], 200.0, 6.0, 1.2, 1500.0),
               rec("casadi", [500.0, nan], [100.0, nan], 260.0, 2.0, 2.5, 1950.0)]

    def table(recs):
        text, ok = bench.summarise(recs, ("lawnmower", "casadi"), (3.0, 1.0))
        rows = {ln.split()[1]: ln.split() for ln in text.splitlines() if ln.startswith("hardware")}
        return text, ok, rows

    text, ok, rows = table(records)
    # reach, m@3, /lawn /ref /orac, s@3, s/lawn, flr>3 | reach, m@1, ..., s@1 (never: the budget's seconds at the
    # run's pace, survey_s · budget / flown: 400 s each for casadi, 300 and 400 s for lawnmower), s/lawn, flr>1 |
    # hover s, floor m
    assert rows["lawnmower"][2:10] == ["2/2", "700", "1.00", "nan", "nan", "120", "1.00", "0/2"]
    assert rows["casadi"][2:10] == ["2/2", "400", "0.57", "nan", "nan", "90", "0.75", "0/2"]
    assert rows["casadi"][10:18] == ["0/2", "3000", "1.00", "nan", "nan", "400", "1.14", "2/2"]
    assert rows["casadi"][18:20] == ["4.0", "1.85"] and rows["lawnmower"][18:20] == ["0.0", "1.85"]
    assert "PASS  hardware: casadi's mission seconds <= 0.75 x lawnmower's at 3 m: ratio 0.75 (90 s / 120 s)" in text
    assert ok
    records[3]["seconds_to_s"] = [104.0, nan]
    text, ok, _ = table(records)
    assert "FAIL  hardware: casadi's mission seconds <= 0.75 x lawnmower's at 3 m: ratio 0.77" in text and not ok


def test_the_command_writes_results_summary_and_figures_and_exits_non_zero_on_failed_runs(tmp_path, capsys):
    from mission.cli import main

    (tmp_path / "outside.toml").write_text(OUTSIDE)
    data = copy.deepcopy(SPEC)
    data["campaign"]["planners"] = ["lawnmower"]
    data["families"][0]["count"] = 1
    (tmp_path / "spec.toml").write_text(_toml(data))
    out = tmp_path / "out"
    assert main(["campaign", str(tmp_path / "spec.toml"), "--workers", "0", "--out", str(out), "--no-progress"]) == 0
    for name in ("summary.csv", "summary.txt", "metres_to_target.png", "error_vs_bound.png"):
        assert (out / name).stat().st_size > 0, name
    printed = capsys.readouterr().out
    assert "small" in printed and "lawnmower" in printed and "1 run now on local" in printed
    data["scenarios"] = [{"file": "outside.toml"}]
    (tmp_path / "spec.toml").write_text(_toml(data))
    assert main(["campaign", str(tmp_path / "spec.toml"), "--workers", "0", "--out", str(out), "--no-progress"]) == 1
    assert "1 already done, 1 failed" in capsys.readouterr().out


def test_the_summary_counts_users_inside_their_final_95_and_beyond_their_99_9_ellipse():
    """end95 and >99.9 come from every located user's final NEES; records written before final_nees
    (no such column) and users never located (NaN) count in neither."""
    def rec(seed, nees):
        return {"key": f"k{seed}", "condition": "c", "planner": "p", "estimator": "e", "status": "ok",
                "metres_to_m": [100.0], "budget_m": 400.0, "mean_error_m": 1.0, "inside95": 0.5,
                "plan_times_s": [0.01], "violations": 0, "final_nees": nees}

    old = rec(0, None)
    records = [rec(1, [1.0, CHI2_2DOF_95 + 0.01, float("nan")]), rec(2, [CHI2_2DOF_999 + 0.01, 0.2]), old]
    (row,) = summary_rows(records, (4.0,))
    assert row["final_users"] == 4
    assert row["final_inside95"] == pytest.approx(2 / 4)
    assert row["final_beyond999"] == 1
    table = format_table([row], (4.0,))
    assert "end95" in table and " 0.50     1 " in table


@pytest.mark.parametrize("doc", ["README.md", "docs/campaigns.md"])
def test_the_documented_campaign_example_loads_as_written(doc):
    """The spec shown in the README's "Campaigns" section (and in docs/campaigns.md) is a valid
    spec: the bundled scenario and 20 generated worlds, 3 seeds, 2 planners, fleets of 1 and 2 UAVs."""
    text = (REPO / doc).read_text()
    block = text.split("```toml\n[campaign]", 1)[1].split("```", 1)[0]
    campaign = spec_from_dict(tomllib.loads("[campaign]" + block), where=doc)
    assert len(campaign.runs) == (1 + 20) * 3 * 2 * 2
    assert sorted({r.n_vehicles for r in campaign.runs}) == [1, 2]
    assert campaign.targets_m == (3.0, 2.0)


def test_the_final_nees_is_the_last_estimate_s_even_when_it_lost_every_user():
    """final_nees follows final_error_m: an estimate that locates nobody leaves NaN in both."""
    from sitl_scenarios.campaign.outcome import AccuracyTrack, Outcome

    track = AccuracyTrack(np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]), (4.0,))
    track.update(np.array([[1.0, 0.0], [10.0, 2.0]]), np.array([np.eye(2), 4.0 * np.eye(2)]), 1.0)
    out = track.fill(Outcome())
    assert out.final_nees == pytest.approx([1.0, 1.0])
    track.update(np.full((2, 2), np.nan), np.full((2, 2, 2), np.inf), 2.0)
    out = track.fill(Outcome())
    assert np.all(np.isnan(out.final_error_m)) and np.all(np.isnan(out.final_nees))
