"""Bad configuration input (issue 21, 3-6 and 12): each refused with a message naming the file, the
key and the value (or the limit), exit 1 for a bad file and 2 for bad usage, never a traceback."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from estimator.geodesy import Origin
from mission.cli import main
from mission.config import example_mission_path, load_mission, mission_from_dict
from mission.controller import controller_from_mission
from sitl_scenarios.campaign import load_spec, spec_from_dict
from sitl_scenarios.scenario import load_scenario, resolve_scenario_path, scenario_from_dict
from uavloc.errors import CampaignError, MissionConfigError, SafetyError, ScenarioError

MISSION = {"name": "m", "users": [{"id": "a", "rnti": "0x4601"}],
           "geofence": {"polygon_enu_m": [[-100.0, -100.0], [100.0, -100.0], [100.0, 100.0], [-100.0, 100.0]]},
           "flight": {"planner": "lawnmower"}}
SCENARIO = {"name": "s", "users": [{"id": "a", "rnti": "0x4601", "east_m": 20.0, "north_m": 10.0}],
            "geofence": {"polygon_enu_m": [[-100.0, -100.0], [100.0, -100.0], [100.0, 100.0], [-100.0, 100.0]]}}
SQUARE_OFF_HOME = [[50.0, 50.0], [90.0, 50.0], [90.0, 90.0], [50.0, 90.0]]
SQUARE_AT_HOME = [[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]


def _with(base: dict, section: str, key: str, value) -> dict:
    d = copy.deepcopy(base)
    d.setdefault(section, {})[key] = value
    return d


# -- 3: home outside the geofence or under a no-fly zone --------------------------------------


@pytest.mark.parametrize(("key", "value", "words"), [
    ("polygon_enu_m", SQUARE_OFF_HOME, "outside the geofence"),
    ("no_fly_enu_m", [SQUARE_AT_HOME], "inside no-fly zone 0"),
])
def test_a_home_outside_the_fence_or_in_a_no_fly_zone_is_refused(key, value, words):
    with pytest.raises(MissionConfigError, match=f"m.toml: key 'geofence'.*home is {words}"):
        mission_from_dict(_with(MISSION, "geofence", key, value), "m.toml")
    with pytest.raises(ScenarioError, match=f"s.toml: key 'geofence'.*home is {words}"):
        scenario_from_dict(_with(SCENARIO, "geofence", key, value), "s.toml")


def test_the_cli_refuses_such_a_mission_file_before_connecting(tmp_path, capsys):
    text = example_mission_path().read_text().replace(
        "no_fly_enu_m = [[[60.0, -40.0], [90.0, -40.0], [90.0, -10.0], [60.0, -10.0]]]",
        "no_fly_enu_m = [[[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]]]")
    (tmp_path / "m.toml").write_text(text)
    # nothing listens there: a mission that got as far as connecting would fail differently
    code = main(["fly", "--mission", str(tmp_path / "m.toml"), "--connect", "udpin://127.0.0.1:20290",
                 "--gnb", "127.0.0.1:20291"])
    err = capsys.readouterr().err
    assert code == 1 and "home is inside no-fly zone 0" in err and "Traceback" not in err


def test_a_geodetic_fence_leaving_home_out_stops_the_mission_before_take_off(tmp_path):
    home = Origin(43.6143, 7.0716, 150.0)
    lla = np.array([home.enu_to_lla([e, n, 0.0]) for e, n in SQUARE_OFF_HOME])
    m = mission_from_dict({**MISSION, "geofence": {"polygon_lat_lon_deg": lla[:, :2].tolist()}}, "geo.toml")
    ctl = controller_from_mission(m, None, None, tmp_path / "m.jsonl")
    ctl._at_home(type("Home", (), {"lat_deg": home.lat_deg, "lon_deg": home.lon_deg, "alt_amsl_m": home.alt_m})())
    with pytest.raises(SafetyError, match="not taking off: home is outside the geofence"):
        ctl._preflight_home()
    ctl.journal.close()


# -- 4: upper bounds ----------------------------------------------------------------------------


@pytest.mark.parametrize(("section", "key", "value", "limit"), [
    ("flight", "altitude_m", 1e6, "500"),
    ("flight", "alt_max_m", 1e6, "500"),
    ("flight", "cruise_speed_mps", 1e9, "30"),
    ("flight", "time_limit_s", 1e300, "7200"),
    ("flight", "budget_m", 1e9, "100000"),
    ("flight", "delta_m", 1e4, "100"),
    ("gnb", "retries", 1_000_000_000, "100"),
    ("gnb", "request_timeout_s", 1e6, "120"),
    ("safety", "gnb_lost_wait_s", 1e9, "7200"),
    ("safety", "max_refusals", 10**9, "1000"),
    ("geofence", "max_distance_m", 1e9, "20000"),
])
def test_every_number_has_an_upper_bound_named_in_the_message(section, key, value, limit):
    with pytest.raises(MissionConfigError) as info:
        mission_from_dict(_with(MISSION, section, key, value), "m.toml")
    msg = str(info.value)
    assert msg.startswith("m.toml: ") and f"{section}.{key}" in msg and limit in msg, msg


@pytest.mark.parametrize(("section", "key", "value"), [
    ("mission", "altitude_m", 1e6), ("mission", "time_limit_s", 1e300), ("vehicle", "speed_mps", 1e9),
    ("radio", "coverage_m", 1e12),
])
def test_a_scenario_has_the_same_bounds(section, key, value):
    with pytest.raises(ScenarioError, match=f"s.toml: key '{section}.{key}'.*at most"):
        scenario_from_dict(_with(SCENARIO, section, key, value), "s.toml")


# -- 5: a missing scenario path is an error -------------------------------------------------------


def test_a_missing_scenario_path_is_never_the_bundled_file_of_that_name(tmp_path, capsys):
    assert resolve_scenario_path("paper").name == "paper.toml"  # a bare name is a bundled file
    for missing in ("nonexistent/paper.toml", "paper.toml", str(tmp_path / "paper.toml"), "nodir/paper"):
        with pytest.raises(ScenarioError, match="no such scenario file"):
            resolve_scenario_path(missing)
    assert main(["sim", "nonexistent/paper.toml"]) == 1
    assert "no such scenario file" in capsys.readouterr().err
    spec = {"campaign": {"name": "c", "planners": ["lawnmower"]}, "scenarios": [{"file": "nodir/paper.toml"}]}
    with pytest.raises(CampaignError, match="scenarios.0..file.*no such scenario file"):
        spec_from_dict(spec, "spec.toml", base_dir=tmp_path)
    code = main(["fly", "--scenario", "nonexistent/paper.toml", "--connect", "udpin://127.0.0.1:20292",
                 "--gnb", "127.0.0.1:20293"])
    assert code == 1 and "no such scenario file" in capsys.readouterr().err


# -- 6: files that are not UTF-8; a negative seed ------------------------------------------------


def test_a_file_that_is_not_utf8_is_an_error_naming_the_file(tmp_path, capsys):
    bad = tmp_path / "latin1.toml"
    bad.write_bytes('name = "caf\u00e9"\n'.encode("latin-1"))
    for loader, error in ((load_mission, MissionConfigError), (load_scenario, ScenarioError),
                          (load_spec, CampaignError)):
        with pytest.raises(error, match=f"{bad}: .*not UTF-8"):
            loader(bad)
    for argv in (["sim", str(bad)], ["campaign", str(bad)]):
        assert main(argv) == 1, argv
        err = capsys.readouterr().err
        assert "not UTF-8" in err and "Traceback" not in err and "UnicodeDecodeError" not in err


@pytest.mark.parametrize("seed", ["-1", "4294967296", "x"])
def test_a_bad_seed_is_a_usage_error(seed, capsys):
    with pytest.raises(SystemExit) as info:
        main(["sim", "paper", "--seed", seed])
    assert info.value.code == 2 and "--seed" in capsys.readouterr().err


def test_a_negative_scenario_seed_is_refused():
    with pytest.raises(ScenarioError, match="s.toml: key 'seed' = -1"):
        scenario_from_dict({**SCENARIO, "seed": -1}, "s.toml")


# -- 12: scenario schema errors name the file; [faults]; RNTI rule; campaign names -----------------


def test_a_scenario_schema_error_names_the_file(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('name = "s"\n[[users]]\nid = "a"\nrnti = 1\neast_m = 1.0\nnorth_m = 1.0\n[radio]\nmuu = 1\n')
    with pytest.raises(ScenarioError, match=f"^{p}: key 'radio.muu'"):
        load_scenario(p)


@pytest.mark.parametrize("faults", [{"gnbb": {}}, {"gnb": {"drop_rat": 0.1}}, {"vehicle": [{"kind": "warp"}]}])
def test_faults_refuse_unknown_keys(faults):
    with pytest.raises(ScenarioError, match="s.toml: .*faults"):
        scenario_from_dict({**SCENARIO, "faults": faults}, "s.toml")


def test_an_rnti_string_follows_one_rule_in_mission_files_and_scenarios():
    for value in ("4601", "17921"):
        with pytest.raises(MissionConfigError, match="hex with 0x"):
            mission_from_dict({**MISSION, "users": [{"id": "a", "rnti": value}]}, "m.toml")
        with pytest.raises(ScenarioError, match="hex with 0x"):
            scenario_from_dict({**SCENARIO, "users": [{**SCENARIO["users"][0], "rnti": value}]}, "s.toml")
    assert scenario_from_dict(SCENARIO).users[0].rnti == load_mission(example_mission_path()).users[0].rnti == 0x4601


@pytest.mark.parametrize("name", ["../escape", "a/b", "..", ".", "x\\y", ""])
def test_a_campaign_name_never_names_a_folder(name):
    spec = {"campaign": {"name": name, "planners": ["lawnmower"]}, "scenarios": [{"file": "paper"}]}
    with pytest.raises(CampaignError, match="campaign.name"):
        spec_from_dict(spec, "spec.toml")
