"""`uavloc replay`: keyframes from a log, the estimate, the JSON document, and the CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mission.cli import main
from mission.log import read_mission_log
from mission.replay import ReplayOptions, build_keyframes, replay, result_of_replay
from sitl_scenarios.example_log import generate
from sitl_scenarios.scenario import load_scenario, scenario_from_dict, user_tables

EXAMPLE = Path(__file__).resolve().parents[1] / "sitl_scenarios" / "data" / "example_paper.jsonl"

THREE_USERS = {
    "name": "three",
    "seed": 7,
    **user_tables([
        {"id": "a", "rnti": 0x4601, "east_m": 40.0, "north_m": 10.0},
        {"id": "b", "rnti": 0x4602, "east_m": -20.0, "north_m": 50.0},
        {"id": "c", "rnti": 0x4603, "east_m": 10.0, "north_m": -45.0, "up_m": 2.0},
    ]),
    "flight": {"altitude_m": 35.0},
}


def _same_record(a, b) -> bool:
    """Equal JSON values, floats to 1e-12 relative or 1e-8 absolute (the last digit of a double's
    repr depends on the platform's libm and numpy build, and the bundled log was written on another
    machine; an altitude comes back from ECEF, where a double's step at the Earth's radius is
    ~1e-9 m: one such altitude was 6.4e-10 m apart on another CPU)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same_record(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same_record(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) or isinstance(b, float):
        return (isinstance(a, int | float) and isinstance(b, int | float)
                and math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-8))
    return a == b


def test_bundled_example_is_what_the_generator_writes(tmp_path):
    out = tmp_path / "ex.jsonl"
    generate(load_scenario("paper"), out)
    ours, bundled = out.read_text().splitlines(), EXAMPLE.read_text().splitlines()
    assert len(ours) == len(bundled)
    for k, (a, b) in enumerate(zip(ours, bundled, strict=True)):
        assert _same_record(json.loads(a), json.loads(b)), (k, a, b)


def test_one_keyframe_per_trigger_and_delta_thins_them():
    mlog = read_mission_log(EXAMPLE)
    kfs = build_keyframes(mlog)
    assert len(kfs) == len(mlog.rtt_t_s)  # one user: one record per trigger
    thinned = build_keyframes(mlog, delta_m=10.0)
    assert len(kfs) / 6 < len(thinned) < len(kfs) / 4
    gaps = np.linalg.norm(np.diff([k.gps_enu_m for k in thinned], axis=0), axis=1)
    assert np.all(gaps >= 10.0)


def test_triggers_group_all_users_at_one_position(tmp_path):
    sc = scenario_from_dict(THREE_USERS)
    out = tmp_path / "three.jsonl"
    counts = generate(sc, out, radius_m=40.0)
    mlog = read_mission_log(out)
    kfs = build_keyframes(mlog)
    assert sum(len(k.range_m) for k in kfs) == counts["rtt"]
    assert max(len(k.user_idx) for k in kfs) == 3
    assert all(len(set(k.user_idx.tolist())) == len(k.user_idx) for k in kfs)


def test_a_trigger_slower_than_the_group_window_is_one_keyframe_at_its_logged_position(tmp_path):
    """uavloc writes one UAV position per trigger; on a loaded machine at a high speedup its records
    can span several vehicle seconds. They are still one keyframe, at exactly the logged position
    (the controller's keyframe), so replay reproduces the mission's estimate to the bit."""
    sc = scenario_from_dict(THREE_USERS)
    src = tmp_path / "three.jsonl"
    generate(sc, src, radius_m=40.0)
    out = [json.loads(line) for line in src.read_text().splitlines()]
    # space the records of a trigger 2.5 s apart (more than GROUP_WINDOW_S), keeping their order
    seen: dict[str, int] = {}
    for obj in out:
        if obj["type"] == "rtt":
            key = json.dumps(obj["uav"], sort_keys=True)
            seen[key] = seen.get(key, -1) + 1
            obj["t"] = round(obj["t"] + 2.5 * seen[key], 6)
    stretched = tmp_path / "stretched.jsonl"
    stretched.write_text("".join(json.dumps(o) + "\n" for o in out))
    mlog = read_mission_log(stretched)
    kfs = build_keyframes(mlog)
    assert len(kfs) == len(build_keyframes(read_mission_log(src)))
    assert max(len(k.user_idx) for k in kfs) == 3
    origin = mlog.header.origin
    logged = origin.lla_to_enu(mlog.rtt_uav_lla[:, 0], mlog.rtt_uav_lla[:, 1], mlog.rtt_uav_lla[:, 2])
    starts = np.cumsum([0] + [len(k.user_idx) for k in kfs[:-1]])
    for k, i in zip(kfs, starts, strict=True):
        assert np.array_equal(k.gps_enu_m, logged[i])  # bit for bit, not a mean of equal numbers


def test_replay_localizes_every_user_near_truth(tmp_path):
    sc = scenario_from_dict(THREE_USERS)
    out = tmp_path / "three.jsonl"
    generate(sc, out, radius_m=40.0)
    result = replay(read_mission_log(out))
    assert result.error_m is not None
    assert np.all(result.error_m < 3.0), result.error_m
    doc = result_of_replay(result).to_document()
    assert doc["status"] == "ok"
    assert [u["id"] for u in doc["users"]] == ["a", "b", "c"]
    for u, k in zip(doc["users"], range(3), strict=True):
        assert np.allclose(u["enu_m"][:2], [sc.users[k].east_m, sc.users[k].north_m], atol=3.0)
        assert np.asarray(u["cov_en_m2"]).shape == (2, 2)
    # the online history ends near the batch answer and its bound shrinks as the UAV flies
    h = result.history
    assert h is not None and h.bound_95_m.shape == (len(result.keyframes), 3)
    assert np.all(h.bound_95_m[-1] < h.bound_95_m[len(h.bound_95_m) // 4])
    assert np.all(np.diff(h.flown_m) >= 0)


def test_cli_json_document(capsys):
    assert main(["replay", str(EXAMPLE), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) >= {"status", "users", "flown_m", "measurements"}
    (u,) = doc["users"]
    assert set(u) >= {"id", "lat_deg", "lon_deg", "alt_m", "enu_m", "cov_en_m2", "error_m"}
    assert u["error_m"] < 3.0
    assert doc["measurements"] == 295


def test_cli_human_output(capsys):
    assert main(["replay", str(EXAMPLE), "--loss", "cauchy", "--delta", "4"]) == 0
    out = capsys.readouterr().out
    assert "ue1: lat 43.61" in out


def test_cli_torn_log_still_replays(tmp_path, capsys):
    p = tmp_path / "torn.jsonl"
    text = EXAMPLE.read_text()
    p.write_text(text[: len(text) - 40])  # cut the last line in half
    assert main(["replay", str(p), "--json", "--no-history"]) == 0
    assert json.loads(capsys.readouterr().out)["status"] == "ok"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--delta", "-1"], "--delta must be a positive number"),
        (["--sigma-gps", "nan"], "--sigma-gps must be a positive number"),
    ],
)
def test_cli_bad_flags_are_errors(args, message, caplog):
    assert main(["replay", str(EXAMPLE), *args]) == 1
    assert message in caplog.text


def test_cli_bad_log_names_the_line(tmp_path, caplog):
    p = tmp_path / "bad.jsonl"
    lines = EXAMPLE.read_text().splitlines(keepends=True)
    lines[5] = lines[5].replace('"user":"ue1"', '"user":"ue7"')
    p.write_text("".join(lines))
    assert main(["replay", str(p)]) == 1
    assert "bad.jsonl:6: rtt for unknown user 'ue7'" in caplog.text


def test_replay_without_rtt_is_an_error(tmp_path):
    p = tmp_path / "h.jsonl"
    p.write_text(EXAMPLE.read_text().splitlines(keepends=True)[0])
    from uavloc.errors import MissionLogError

    with pytest.raises(MissionLogError, match="no rtt records"):
        replay(read_mission_log(p), ReplayOptions())


def _with_solver_config(tmp_path, solver) -> Path:
    lines = EXAMPLE.read_text().splitlines(keepends=True)
    head = json.loads(lines[0])
    head["config"]["solver"] = solver
    p = tmp_path / "solver.jsonl"
    p.write_text(json.dumps(head) + "\n" + "".join(lines[1:]))
    return p


def test_replay_uses_the_solver_settings_logged_in_the_header(tmp_path, caplog):
    from mission.replay import solver_params_from_header

    p = _with_solver_config(tmp_path, {"loss": "cauchy", "estimate_bias": True, "from_the_future": 1})
    params = solver_params_from_header(read_mission_log(p))
    assert params.loss == "cauchy" and params.estimate_bias
    assert "from_the_future" in caplog.text
    result = replay(read_mission_log(p), ReplayOptions(history=False))
    assert result.params.estimate_bias and result.estimate.bias_m is not None


def test_cli_flags_override_the_logged_solver_settings(tmp_path, capsys):
    p = _with_solver_config(tmp_path, {"estimate_bias": True})
    assert main(["replay", str(p), "--json", "--no-bias", "--no-history"]) == 0
    assert json.loads(capsys.readouterr().out)["status"] == "ok"


@pytest.mark.parametrize(("solver", "match"), [("fast", "must be an object"), ({"estimate_bias": "yes"}, "wrong type")])
def test_malformed_logged_solver_settings_are_errors(tmp_path, solver, match):
    from mission.replay import solver_params_from_header
    from uavloc.errors import MissionLogError

    with pytest.raises(MissionLogError, match=match):
        solver_params_from_header(read_mission_log(_with_solver_config(tmp_path, solver)))


def test_cli_unknown_loss_is_an_error(caplog):
    assert main(["replay", str(EXAMPLE), "--loss", "bogus"]) == 1
    assert "unknown robust loss 'bogus'" in caplog.text


def test_metres_flown_are_the_survey_s_own_count_when_the_log_closes_it(tmp_path):
    """The controller counts metres from every fix of its legs and logs the total in the
    `survey_time` event; the log's telemetry is a sample of those fixes, and the survey flies on
    for the seconds the final answer takes to confirm (a three_users_nlos run: 374.3 m live, 362 m
    replayed from the telemetry up to the last range). A log that closes its survey replays to its
    own count; one without (another tool's) to the odometer over its telemetry."""
    sc = scenario_from_dict(THREE_USERS)
    out = tmp_path / "three.jsonl"
    generate(sc, out, radius_m=40.0)
    odometer_m = replay(read_mission_log(out), ReplayOptions(history=False)).flown_m
    assert odometer_m > 100.0
    lines = out.read_text().splitlines()
    t_last = max(json.loads(line)["t"] for line in lines)
    closed = {"type": "event", "t": t_last, "message": "survey ...", "kind": "survey_time",
              "survey_s": 60.0, "flown_m": round(odometer_m + 12.3, 2)}
    out.write_text("\n".join([*lines, json.dumps(closed)]) + "\n")
    assert replay(read_mission_log(out), ReplayOptions(history=False)).flown_m == round(odometer_m + 12.3, 2)
