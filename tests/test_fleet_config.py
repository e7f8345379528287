"""A mission file that names a fleet (issue 41: several UAVs, each carrying its own gNB): the
`[[vehicles]]` table, the fleet's `[safety]` separation, the checks across them, and the same table
in scenario files and the log header. Nothing here flies."""

from __future__ import annotations

import copy
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from estimator.geodesy import Origin
from mission.addresses import fleet_address_problem
from mission.config import (
    MissionConfig,
    SafetyConfig,
    VehicleEntryConfig,
    example_mission_path,
    load_mission,
    mission_from_dict,
    with_settings,
)
from mission.log import MissionLogWriter, read_mission_log
from sitl_scenarios.scenario import SCENARIO_DIR, load_scenario, scenario_from_dict
from uavloc.errors import MissionConfigError, ScenarioError

EXAMPLE = example_mission_path()
HOME = Origin(47.397742, 8.545594, 488.0)
REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "config-files.md"
#: the example mission's [flight] band is [20, 80] m, its altitude 40 m
FLEET = [
    {"id": "uav-a", "connect": "udpin://0.0.0.0:14541", "gnb": "10.0.0.11:9090", "alt_max_m": 35.0},
    {"id": "uav_B2", "connect": "udpin://0.0.0.0:14542", "gnb": "10.0.0.12:9090", "gnb_mode": "trace",
     "alt_min_m": 50.0, "alt_max_m": 70.0},
]


def example_dict(vehicles: list[dict] | None = None) -> dict:
    d = tomllib.loads(EXAMPLE.read_text(encoding="utf-8"))
    if vehicles is not None:
        d["vehicles"] = copy.deepcopy(vehicles)
    return d


def fleet_text(vehicles: list[dict]) -> str:
    """The example mission file with `[[vehicles]]` entries appended, as an operator writes them."""
    def value(v):
        return f'"{v}"' if isinstance(v, str) else repr(v)

    entries = ["[[vehicles]]\n" + "".join(f"{k} = {value(v)}\n" for k, v in e.items()) for e in vehicles]
    return EXAMPLE.read_text(encoding="utf-8") + "\n" + "\n".join(entries)


def test_a_two_vehicle_mission_loads_with_each_vehicles_band(tmp_path):
    f = tmp_path / "fleet.toml"
    f.write_text(fleet_text(FLEET), encoding="utf-8")
    mc = load_mission(f)
    assert [v.id for v in mc.vehicles] == ["uav-a", "uav_B2"] and mc.fleet_size == 2
    assert mc.vehicles[0] == VehicleEntryConfig("uav-a", "udpin://0.0.0.0:14541", "10.0.0.11:9090", alt_max_m=35.0)
    assert mc.vehicles[1].gnb_mode == "trace" and mc.vehicles[0].gnb_mode == ""
    # a side left out is the mission's; the cruise altitude is the mission's clipped into the band
    assert mc.vehicle_band_m(0) == (20.0, 35.0) and mc.vehicle_band_m(1) == (50.0, 70.0)
    assert mc.vehicle_cruise_alt_m(0) == 35.0 and mc.vehicle_cruise_alt_m(1) == 50.0
    with pytest.raises(IndexError):
        mc.vehicle_band_m(2)
    pc = mc.planning_constraints(HOME, vehicle=1)
    assert (pc.alt_min_m, pc.alt_max_m, pc.cruise_alt_m) == (50.0, 70.0, 50.0)
    # without vehicle=, and with overrides, the mission's as before
    pc = mc.planning_constraints(HOME, margin_m=3.0)
    assert (pc.alt_min_m, pc.alt_max_m, pc.cruise_alt_m, pc.margin_m) == (20.0, 80.0, 40.0, 3.0)
    assert mc.planning_constraints(HOME, vehicle=0, cruise_alt_m=30.0).cruise_alt_m == 30.0
    assert fleet_address_problem(mc) is None


def test_a_mission_without_vehicles_is_one_vehicle_with_the_missions_band():
    mc = load_mission(EXAMPLE)
    assert mc.vehicles == () and mc.fleet_size == 1
    assert mc.vehicle_band_m(0) == (20.0, 80.0) and mc.vehicle_cruise_alt_m(0) == 40.0
    with pytest.raises(IndexError):
        mc.vehicle_band_m(1)
    a, b = mc.planning_constraints(HOME), mc.planning_constraints(HOME, vehicle=0)
    assert (a.alt_min_m, a.alt_max_m, a.cruise_alt_m) == (b.alt_min_m, b.alt_max_m, b.cruise_alt_m)
    assert mc.safety.separation_m == SafetyConfig.separation_m == 15.0
    assert mc.safety.separation_vertical_m == SafetyConfig.separation_vertical_m == 10.0
    # the separation settings are [safety]'s by their key alone (campaign families, overrides)
    assert with_settings(mc, {"separation_m": 30.0, "separation_vertical_m": 0.0}).safety.separation_m == 30.0


def test_a_band_with_one_side_given_takes_the_other_from_the_mission():
    mc = mission_from_dict(example_dict([{"id": "low", "alt_max_m": 30.0}, {"id": "high", "alt_min_m": 60.0}]))
    assert mc.vehicle_band_m(0) == (20.0, 30.0) and mc.vehicle_band_m(1) == (60.0, 80.0)
    assert mc.vehicle_cruise_alt_m(0) == 30.0 and mc.vehicle_cruise_alt_m(1) == 60.0
    # a vehicle without a band flies the mission's
    mc = mission_from_dict(example_dict([{"id": "x"}, {"id": "y", "alt_min_m": 20.0, "alt_max_m": 80.0}]))
    assert mc.vehicle_band_m(0) == mc.vehicle_band_m(1) == (20.0, 80.0)


def _vehicle(i: int, **kv) -> list[dict]:
    """FLEET with vehicle i's keys set (None deletes)."""
    out = copy.deepcopy(FLEET)
    for k, v in kv.items():
        if v is None:
            out[i].pop(k, None)
        else:
            out[i][k] = v
    return out


# (id, vehicles, [safety] keys, words the message must contain)
BAD = [
    ("duplicate-id", _vehicle(1, id="uav-a"), {}, ["vehicles[1].id", "'uav-a'", "duplicate vehicle id"]),
    ("id-with-a-space", _vehicle(0, id="uav a"), {}, ["vehicles[0].id", "'uav a'", "letters, digits"]),
    ("id-with-a-dot", _vehicle(1, id="uav.b"), {}, ["vehicles[1].id", "'uav.b'", "letters, digits"]),
    ("id-empty", _vehicle(0, id=""), {}, ["vehicles[0].id", "1 to 32"]),
    ("id-33-chars", _vehicle(0, id="u" * 33), {}, ["vehicles[0].id", "1 to 32"]),
    ("id-missing", _vehicle(0, id=None), {}, ["missing required key", "'id'", "vehicles[0]"]),
    ("id-a-number", _vehicle(0, id=7), {}, ["vehicles[0].id", "expected a string"]),
    ("band-below-the-mission", _vehicle(0, alt_min_m=10.0), {},
     ["vehicles[0].alt_min_m", "10.0", "flight.alt_min_m (20)", "inside the mission"]),
    ("band-above-the-mission", _vehicle(1, alt_max_m=90.0), {},
     ["vehicles[1].alt_max_m", "90.0", "flight.alt_max_m (80)", "inside the mission"]),
    ("band-too-thin", _vehicle(1, alt_min_m=67.0), {}, ["vehicles[1].alt_max_m", "[67, 70]", "3 m thick", "5 m"]),
    ("band-too-thin-with-the-missions-side", _vehicle(1, alt_min_m=77.0, alt_max_m=None), {},
     ["vehicles[1].alt_min_m", "77.0", "[77, 80]", "mission's", "5 m"]),
    ("band-upside-down", _vehicle(1, alt_min_m=70.0, alt_max_m=50.0), {},
     ["vehicles[1].alt_max_m", "empty", "alt_min_m < alt_max_m"]),
    ("band-negative", _vehicle(0, alt_min_m=-5.0), {}, ["vehicles[0].alt_min_m", "-5.0", ">= 0"]),
    ("band-nan", _vehicle(0, alt_max_m=float("nan")), {}, ["vehicles[0].alt_max_m", "finite"]),
    ("band-in-feet", _vehicle(0, alt_max_ft=100), {}, ["vehicles[0].alt_max_ft", "wrong unit", "alt_max_m"]),
    ("unknown-key", _vehicle(1, colour="red"), {}, ["vehicles[1].colour", "unknown key", "connect", "gnb_mode"]),
    ("a-position", _vehicle(0, alt_m=30.0), {}, ["vehicles[0].alt_m", "unknown key", "alt_max_m"]),
    ("unknown-gnb-mode", _vehicle(1, gnb_mode="magic"), {}, ["vehicles[1].gnb_mode", "'magic'", "'trace'"]),
    ("stock-gnb-without-log", _vehicle(0, gnb_mode="stock"), {}, ["vehicles[0].gnb_mode", "log_path"]),
    ("vehicles-a-table", {"id": "x"}, {}, ["'vehicles'", "expected a list"]),
    ("separation-zero", FLEET, {"separation_m": 0.0}, ["safety.separation_m", "[1, 500]"]),
    ("separation-far", FLEET, {"separation_m": 1000.0}, ["safety.separation_m", "[1, 500]"]),
    ("vertical-separation-negative", FLEET, {"separation_vertical_m": -1.0}, ["safety.separation_vertical_m", ">= 0"]),
    ("separation-in-km", FLEET, {"separation_km": 0.02}, ["safety.separation_km", "wrong unit", "separation_m"]),
]


@pytest.mark.parametrize(("vehicles", "safety", "words"), [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_a_bad_fleet_is_refused_naming_file_key_and_value(tmp_path, vehicles, safety, words):
    f = str(tmp_path / "fleet.toml")
    data = example_dict()
    data["vehicles"] = copy.deepcopy(vehicles)
    data["safety"].update(safety)
    with pytest.raises(MissionConfigError) as info:
        mission_from_dict(data, f)
    msg = str(info.value)
    assert msg.startswith(f), msg
    for w in words:
        assert w in msg, (w, msg)


def test_a_bad_fleet_is_refused_from_disk(tmp_path):
    f = tmp_path / "fleet.toml"
    f.write_text(fleet_text(_vehicle(1, id="uav-a")), encoding="utf-8")
    with pytest.raises(MissionConfigError, match=re.escape(f"{f}: key 'vehicles[1].id' = 'uav-a': duplicate")):
        load_mission(f)


def test_missing_addresses_load_and_fleet_address_problem_says_what_a_flight_lacks():
    # a simulation gives every vehicle its addresses: the file loads
    mc = mission_from_dict(example_dict(_vehicle(1, connect=None, gnb=None)))
    problem = fleet_address_problem(mc)
    assert problem is not None
    assert "vehicles[1].connect (uav_B2)" in problem and "vehicles[1].gnb (uav_B2)" in problem
    assert "vehicles[0]" not in problem and "--connect" in problem
    mc = mission_from_dict(example_dict(_vehicle(1, gnb=FLEET[0]["gnb"])))
    problem = fleet_address_problem(mc)
    assert problem is not None and "vehicles[1].gnb = '10.0.0.11:9090' reaches the same endpoint as vehicles[0].gnb" \
        in problem
    mc = mission_from_dict(example_dict(_vehicle(1, connect=FLEET[0]["connect"])))
    assert "vehicles[1].connect" in (fleet_address_problem(mc) or "")
    # one vehicle, or none: the command line's --connect and --gnb address it
    assert fleet_address_problem(mission_from_dict(example_dict([{"id": "solo"}]))) is None
    assert fleet_address_problem(load_mission(EXAMPLE)) is None
    assert fleet_address_problem(mission_from_dict(example_dict(FLEET))) is None


def _scenario_doc(vehicles: list[dict] | None = None) -> dict:
    d = tomllib.loads((SCENARIO_DIR / "paper.toml").read_text(encoding="utf-8"))
    if vehicles is not None:
        d["vehicles"] = copy.deepcopy(vehicles)
    return d


#: FLEET as a scenario names it: the simulator gives every vehicle its addresses
SIM_FLEET = [{k: v for k, v in e.items() if k not in ("connect", "gnb")} for e in FLEET]


def test_a_scenarios_vehicles_are_its_missions_as_in_a_mission_file():
    sc = scenario_from_dict(_scenario_doc(SIM_FLEET), "fleet_scenario.toml")
    mission_only = {k: v for k, v in _scenario_doc(SIM_FLEET).items()
                    if k in {f for f in MissionConfig.__dataclass_fields__}}
    assert sc.mission.vehicles == mission_from_dict(mission_only).vehicles
    assert sc.mission.fleet_size == 2 and sc.mission.vehicle_band_m(1) == (50.0, 70.0)
    assert sc.mission_config().vehicles == sc.mission.vehicles
    # the world's [vehicle] (the built-in vehicle's model) is not the mission's [[vehicles]]
    assert sc.vehicle == load_scenario("paper").vehicle
    assert load_scenario("paper").mission.vehicles == ()


@pytest.mark.parametrize(("vehicles", "words"), [
    (_vehicle(1, colour="red"), ["vehicles[1].colour", "unknown key", "gnb_mode"]),
    (_vehicle(0, east_m=10.0), ["vehicles[0].east_m", "unknown key"]),
    (_vehicle(1, id="uav-a"), ["vehicles[1].id", "duplicate vehicle id"]),
    (_vehicle(0, alt_min_m=5.0), ["vehicles[0].alt_min_m", "inside the mission"]),
], ids=["unknown-key", "a-position", "duplicate-id", "band-outside"])
def test_a_bad_fleet_in_a_scenario_is_refused_naming_file_and_key(vehicles, words):
    with pytest.raises(ScenarioError) as info:
        scenario_from_dict(_scenario_doc(vehicles), "fleet_scenario.toml")
    msg = str(info.value)
    assert msg.startswith("fleet_scenario.toml: key "), msg
    for w in words:
        assert w in msg, (w, msg)


def test_the_header_records_the_fleet_and_reads_back(tmp_path):
    assert "vehicles" not in load_mission(EXAMPLE).header_fields(HOME)  # one vehicle: as before
    mc = mission_from_dict(example_dict(FLEET))
    fields = mc.header_fields(HOME)
    assert fields["vehicles"] == [{"id": "uav-a", "alt_min_m": 20.0, "alt_max_m": 35.0},
                                  {"id": "uav_B2", "alt_min_m": 50.0, "alt_max_m": 70.0}]
    assert {k: v for k, v in fields.items() if k != "vehicles"} == load_mission(EXAMPLE).header_fields(HOME)
    p = tmp_path / "mission.jsonl"
    with MissionLogWriter(p) as w:
        w.write_header(HOME, [{"id": u.id, "rnti": u.rnti, "ground_alt_m": HOME.alt_m} for u in mc.users],
                       {"mu": 1, "fs_hz": 46.08e6}, area=fields)
    log = read_mission_log(p)  # the reader does not refuse the field
    assert log.header.altitude_band_m == {"min_m": 20.0, "max_m": 80.0}
    np.testing.assert_allclose(np.asarray(log.header.geofence), np.asarray(fields["geofence"]), atol=1e-9)


def test_the_documented_example_loads():
    """The `[[vehicles]]` example of docs/config-files.md is a valid fleet of the example mission."""
    blocks = re.findall(r"```toml\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)
    fleet = [b for b in blocks if "[[vehicles]]" in b]
    assert len(fleet) == 1
    data = example_dict()
    data.update(tomllib.loads(fleet[0]))
    mc = mission_from_dict(data, str(DOC))
    assert mc.fleet_size == 2 and fleet_address_problem(mc) is None
    assert mc.vehicle_band_m(0) == (20.0, 45.0) and mc.vehicle_band_m(1) == (55.0, 80.0)


# ---------------------------------------------------------------------------------------------
# the fleet as a whole (issue 49): addresses as endpoints, keys a command would ignore, launch points


def _with_addresses(key: str, a: str, b: str) -> list[dict]:
    out = copy.deepcopy(FLEET)
    out[0][key], out[1][key] = a, b
    return out


# (key, address of vehicle 0, of vehicle 1): one endpoint spelt two ways
SAME = [
    ("connect", "udpin://0.0.0.0:14541", "udpin://127.0.0.1:14541"),
    ("connect", "udpin://0.0.0.0:14541", "udp://:14541"),
    ("connect", "udpin://localhost:14541", "udpin://0.0.0.0:14541"),
    ("connect", "udpin://192.0.2.7:14541", "udpin://0.0.0.0:14541"),  # a wildcard takes the port on every address
    ("connect", "tcp://127.0.0.1:5760", "tcpout://localhost:5760"),
    ("connect", "serial:///dev/ttyACM0:57600", "serial:///dev/ttyACM0:115200"),
    ("gnb", "telnet://10.0.0.11:9090", "10.0.0.11:9090"),
    ("gnb", "10.0.0.11", "10.0.0.11:9090"),
    ("gnb", "0.0.0.0:9090", "127.0.0.1:9090"),
    ("gnb", "localhost:9090", "127.0.0.1:9090"),
    ("gnb", "http://10.0.0.11:8090/", "10.0.0.11:8090"),
]
# two endpoints
APART = [
    ("connect", "udpin://0.0.0.0:14541", "udpin://0.0.0.0:14542"),
    ("connect", "udpin://0.0.0.0:14541", "udpout://127.0.0.1:14541"),
    ("connect", "udpout://10.0.0.1:14541", "udpout://10.0.0.2:14541"),
    ("connect", "udpin://192.0.2.7:14541", "udpin://192.0.2.8:14541"),
    ("connect", "serial:///dev/ttyACM0:57600", "serial:///dev/ttyACM1:57600"),
    ("gnb", "10.0.0.11:9090", "10.0.0.11:9091"),
    ("gnb", "http://10.0.0.11", "10.0.0.11"),  # 8090 and 9090
]


@pytest.mark.parametrize(("key", "a", "b"), SAME, ids=[f"{k}-{b}" for k, _, b in SAME])
def test_one_endpoint_spelt_two_ways_is_a_duplicate_address(key, a, b):
    problem = fleet_address_problem(mission_from_dict(example_dict(_with_addresses(key, a, b))))
    assert problem is not None, (a, b)
    assert f"vehicles[1].{key} = {b!r} reaches the same endpoint as vehicles[0].{key}" in problem, problem


@pytest.mark.parametrize(("key", "a", "b"), APART, ids=[f"{k}-{b}" for k, _, b in APART])
def test_two_endpoints_are_not_a_duplicate(key, a, b):
    assert fleet_address_problem(mission_from_dict(example_dict(_with_addresses(key, a, b)))) is None


@pytest.mark.parametrize("key", ["connect", "gnb"])
def test_an_empty_address_is_refused_not_taken_for_absent(tmp_path, key):
    f = tmp_path / "fleet.toml"
    f.write_text(fleet_text(_vehicle(1, **{key: ""})), encoding="utf-8")
    with pytest.raises(MissionConfigError, match=re.escape(f"{f}: key 'vehicles[1].{key}' = '': empty")) as info:
        load_mission(f)
    assert f"--{key}" in str(info.value)


def test_a_malformed_gnb_address_is_what_a_flight_lacks():
    problem = fleet_address_problem(mission_from_dict(example_dict(_vehicle(0, gnb="10.0.0.11:abc")), "fleet.toml"))
    assert problem is not None and problem.startswith("vehicles[0].gnb = '10.0.0.11:abc': ") and "'abc'" in problem


@pytest.mark.parametrize("key", ["connect", "gnb"])
def test_an_address_in_a_scenarios_vehicles_is_refused_naming_the_key(key):
    vehicles = copy.deepcopy(SIM_FLEET)
    vehicles[1][key] = FLEET[1][key]
    with pytest.raises(ScenarioError) as info:
        scenario_from_dict(_scenario_doc(vehicles), "fleet_scenario.toml")
    msg = str(info.value)
    assert msg.startswith(f"fleet_scenario.toml: key 'vehicles[1].{key}'"), msg
    assert "ignored" in msg and "--connect" in msg


def _two_uavs_doc() -> dict:
    return tomllib.loads((SCENARIO_DIR / "two_uavs.toml").read_text(encoding="utf-8"))


def test_launch_points_outside_the_fence_are_refused_at_load_naming_each_vehicle():
    """two_uavs with separation_m = 500 and a third vehicle: a ring of 291.6 m, uav2 and uav3 at
    (-145.8, ±252.5) outside the ±250 m fence."""
    d = _two_uavs_doc()
    d["vehicles"].append({"id": "uav3"})
    d["safety"]["separation_m"] = 500.0
    with pytest.raises(ScenarioError) as info:
        scenario_from_dict(d, "three.toml")
    msg = str(info.value)
    assert msg.startswith("three.toml: key 'safety.separation_m' = 500.0"), msg
    for w in ["291.6 m", "uav2's home (-145.8, 252.5) m is outside the geofence polygon",
              "uav3's home (-145.8, -252.5) m is outside the geofence polygon"]:
        assert w in msg, (w, msg)
    assert "uav1" not in msg
    # inside a no-fly zone, or beyond max_distance_m, as well
    d = _two_uavs_doc()
    d["geofence"]["no_fly_enu_m"] = [[[5.0, -5.0], [20.0, -5.0], [20.0, 5.0], [5.0, 5.0]]]
    with pytest.raises(ScenarioError, match=r"uav1's home \(10\.0, 0\.0\) m is inside no-fly zone 0"):
        scenario_from_dict(d, "nofly.toml")
    d = _two_uavs_doc()
    d["geofence"]["max_distance_m"] = 8.0
    with pytest.raises(ScenarioError, match="10.0 m from the mission's origin exceeds max_distance_m 8"):
        scenario_from_dict(d, "near.toml")
    scenario_from_dict(_two_uavs_doc(), "two_uavs.toml")  # as shipped: inside


def test_a_fleet_larger_than_the_machine_carries_is_refused_with_the_figure():
    from sitl_scenarios.scenario import MAX_BUILTIN_VEHICLES, MAX_VEHICLE_SPEEDUP, check_fleet_load
    from uavloc.errors import MissionError

    d = _two_uavs_doc()
    two = scenario_from_dict(d, "two_uavs.toml")
    check_fleet_load(two, MAX_VEHICLE_SPEEDUP / 2)  # the limit itself flies
    with pytest.raises(MissionError) as info:
        check_fleet_load(two, MAX_VEHICLE_SPEEDUP)
    msg = str(info.value)
    assert f"2 vehicles × speed-up {MAX_VEHICLE_SPEEDUP:g} = {2 * MAX_VEHICLE_SPEEDUP:g}" in msg
    assert f"--speedup {MAX_VEHICLE_SPEEDUP / 2:g} or less" in msg
    d["vehicles"] = [{"id": f"uav{i}"} for i in range(MAX_BUILTIN_VEHICLES + 1)]
    many = scenario_from_dict(d, "many.toml")
    with pytest.raises(MissionError, match=f"more than the {MAX_BUILTIN_VEHICLES} built-in vehicles"):
        check_fleet_load(many, 0.1)


# ---------------------------------------------------------------------------------------------
# the commands: refused before anything connects or starts


def _cli(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "mission", *argv], cwd=cwd, capture_output=True, text=True,
                          timeout=120, env=env)


def _no_traceback(proc: subprocess.CompletedProcess) -> str:
    assert "Traceback" not in proc.stderr, proc.stderr
    return proc.stderr


def test_sim_of_a_50_vehicle_fleet_is_refused_at_once_with_the_figure(tmp_path):
    from sitl_scenarios.scenario import MAX_BUILTIN_VEHICLES

    text = (SCENARIO_DIR / "two_uavs.toml").read_text(encoding="utf-8")
    text = text.replace('[[vehicles]]\nid = "uav1"\n\n[[vehicles]]\nid = "uav2"\n',
                        "".join(f'[[vehicles]]\nid = "uav{i}"\n\n' for i in range(1, 51)))
    (tmp_path / "fifty.toml").write_text(text, encoding="utf-8")
    proc = _cli(["sim", str(tmp_path / "fifty.toml"), "--speedup", "20", "--out", str(tmp_path / "out")], tmp_path)
    err = _no_traceback(proc)
    assert proc.returncode == 1, err
    for w in ["'two_uavs'", "50 built-in vehicles at ×20", f"more than the {MAX_BUILTIN_VEHICLES}",
              "vehicles × speed-up <="]:
        assert w in err, (w, err)
    assert not (tmp_path / "out" / "mission.jsonl").exists()


def test_sim_with_one_autopilot_given_twice_is_refused(tmp_path):
    proc = _cli(["sim", "two_uavs", "--connect", "udpin://0.0.0.0:14541,udpin://127.0.0.1:14541", "--out",
                 str(tmp_path / "out")], tmp_path)
    err = _no_traceback(proc)
    assert proc.returncode == 1, err
    assert "--connect" in err and "URL 2 ('udpin://127.0.0.1:14541') reaches the same MAVLink endpoint as URL 1" in err


@pytest.mark.parametrize(("option", "value"), [("--connect", "udpin://0.0.0.0:14540"), ("--gnb", "127.0.0.1:9")])
def test_fly_refuses_an_address_option_beside_a_fleet_file(tmp_path, option, value):
    f = tmp_path / "fleet.toml"
    f.write_text(fleet_text(FLEET), encoding="utf-8")
    proc = _cli(["fly", "--mission", str(f), option, value, "--out", str(tmp_path / "out")], tmp_path)
    err = _no_traceback(proc)
    assert proc.returncode == 2, err
    assert f"{option} (the file gives each of its 2 vehicles' {option[2:]}) would be ignored" in err, err


def test_fly_refuses_one_gnb_spelt_two_ways(tmp_path):
    f = tmp_path / "fleet.toml"
    f.write_text(fleet_text(_with_addresses("gnb", "telnet://127.0.0.1:9", "localhost:9")), encoding="utf-8")
    proc = _cli(["fly", "--mission", str(f), "--out", str(tmp_path / "out")], tmp_path)
    err = _no_traceback(proc)
    assert proc.returncode == 1, err
    assert "vehicles[1].gnb = 'localhost:9' reaches the same endpoint as vehicles[0].gnb" in err, err


def test_fly_refuses_an_option_a_one_vehicle_entry_overrides(tmp_path):
    f = tmp_path / "solo.toml"
    f.write_text(fleet_text([{"id": "solo", "connect": "udpin://0.0.0.0:14540"}]), encoding="utf-8")
    proc = _cli(["fly", "--mission", str(f), "--connect", "udpin://0.0.0.0:14541", "--gnb", "127.0.0.1:9", "--out",
                 str(tmp_path / "out")], tmp_path)
    err = _no_traceback(proc)
    assert proc.returncode == 2, err
    assert "--connect (the file gives vehicles[0].connect) would be ignored" in err and "--gnb (" not in err


def test_one_vehicle_is_not_bounded_by_the_fleet_load():
    """The fleet's limit is vehicles × speed-up; one vehicle flies at x200 (test_sim_at_x200_takes_off)."""
    from sitl_scenarios.scenario import check_fleet_load, load_scenario

    check_fleet_load(load_scenario("paper"), 200.0)
