"""The mission file of real flights (mission/config.py): strict, and never a true position."""

from __future__ import annotations

import copy
import dataclasses
import tomllib

import numpy as np
import pytest

from estimator.geodesy import Origin
from mission.config import (
    MissionConfig,
    example_mission_path,
    load_mission,
    mission_from_dict,
)
from sitl_scenarios.scenario import bundled_scenarios, load_scenario
from uavloc.errors import MissionConfigError, MissionError

EXAMPLE = example_mission_path()


def example_dict() -> dict:
    return tomllib.loads(EXAMPLE.read_text(encoding="utf-8"))


def test_example_mission_file_loads_with_its_values():
    mc = load_mission(EXAMPLE)
    assert isinstance(mc, MissionConfig)
    assert [(u.id, u.rnti, u.ground_height_m) for u in mc.users] == [("ue1", 0x4601, 0.0), ("ue2", 0x4602, -1.5)]
    assert mc.flight.altitude_m == 40.0 and mc.flight.cruise_speed_mps == 8.0
    assert mc.noise.noise_model().range_sigma_m(100.0) == pytest.approx(3.0)
    assert mc.gnb.mode == "rtt" and mc.safety.gnb_lost_wait_s == 20.0
    assert mc.noise.header_noise() == {"sigma_gps_m": 1.0, "gps_tau_s": 5.0,
                                       "range_sigma_m": {"range_s0_m": 3.0, "range_a_m": 0.0,
                                                                         "range_b_per_m": 0.0}}
    with pytest.raises(dataclasses.FrozenInstanceError):
        mc.flight.budget_m = 1.0  # type: ignore[misc]


def test_example_mission_file_is_package_data():
    assert EXAMPLE.is_file() and EXAMPLE.parent.name == "examples" and EXAMPLE.parent.parent.name == "mission"


def _set(d: dict, path: str, value) -> dict:
    """Copy of d with the dotted key path set (`users.0.east_m`); value None deletes it."""
    out = copy.deepcopy(d)
    node = out
    *parents, last = path.split(".")
    for p in parents:
        node = node[int(p)] if p.isdigit() else node.setdefault(p, {})
    if value is None:
        del node[last]
    else:
        node[last] = value
    return out


# (key path, value, words the message must contain)
BAD = [
    ("users.0.east_m", 60.0, ["users[0].east_m", "60.0", "never holds true positions"]),
    ("users.1.lat_deg", 43.6, ["users[1].lat_deg", "never holds true positions"]),
    ("buildings", [], ["'buildings'", "simulated world"]),
    ("radio", {"mu": 1}, ["'radio'", "simulated world"]),
    ("flight.budget_km", 1.2, ["flight.budget_km", "1.2", "wrong unit", "budget_m"]),
    ("flight.altitude_ft", 120, ["flight.altitude_ft", "wrong unit", "altitude_m"]),
    ("flight.speed", 8.0, ["flight.speed", "unknown key", "cruise_speed_mps"]),
    ("flight.budget_m", "1200 m", ["flight.budget_m", "'1200 m'", "expected a number", "unit is in the key"]),
    ("flight.budget_m", float("nan"), ["flight.budget_m", "nan", "finite"]),
    ("flight.budget_m", -5.0, ["flight.budget_m", "-5.0", "positive"]),
    ("flight.altitude_m", 100.0, ["flight.altitude_m", "100.0", "alt_max_m"]),
    ("flight.planner", "rrt", ["flight.planner", "'rrt'", "'casadi'"]),
    ("users.0.rnti", "0xZZ", ["users[0].rnti", "'0xZZ'", "integer"]),
    ("users.0.rnti", "4601", ["users[0].rnti", "'4601'", "hex with 0x", '"0x4601"']),
    ("users.0.rnti", 0, ["users[0].rnti", "0x0001..0xFFEF"]),
    ("users.1.rnti", "0x4601", ["users[1].rnti", "duplicate RNTI"]),
    ("users.0.id", None, ["missing required key", "id"]),
    ("users", [], ["'users'", "at least one user"]),
    ("geofence.polygon_enu_m", [[0.0, 0.0], [1.0, 0.0]], ["geofence.polygon_enu_m", "3 vertices"]),
    ("geofence.polygon_enu_m", [[0.0, 0.0, 5.0], [1.0, 0.0], [1, 1]], ["geofence.polygon_enu_m[0]", "2 numbers"]),
    ("geofence.polygon_lat_lon_deg", [[43.6, 7.0], [43.7, 7.0], [43.7, 7.1]],
     ["geofence.polygon_lat_lon_deg", "give the fence once"]),
    ("geofence.no_fly_lat_lon_deg", [[[95.0, 7.0], [43.7, 7.0], [43.7, 7.1]]],
     ["geofence.no_fly_lat_lon_deg[0]", "latitude"]),
    ("noise.range_a_m", -1.0, ["noise.range_a_m", "-1.0", ">= 0"]),
    ("noise.sigma_gps_m", 0, ["noise.sigma_gps_m", "positive"]),
    ("noise.estimate_bias", "yes", ["noise.estimate_bias", "'yes'", "true or false"]),
    ("gnb.mode", "magic", ["gnb.mode", "'magic'", "'rtt'", "'stock'"]),
    ("gnb.mode", "stock", ["gnb.mode", "log_path"]),
    ("gnb.rtt_command", "pdcch order", ["gnb.rtt_command", "one word"]),
    ("gnb.mu", 5, ["gnb.mu", "5", "0..3"]),
    ("gnb.timeout_s", 1.0, ["gnb.timeout_s", "unknown key", "request_timeout_s"]),
    ("safety.battery_rtl_pct", 100.0, ["safety.battery_rtl_pct", "at most 99"]),
    ("safety.battery_takeoff_min_pct", 10.0, ["safety.battery_takeoff_min_pct", "battery_rtl_pct"]),
    ("safety.gnb_lost_wait_ms", 20000, ["safety.gnb_lost_wait_ms", "wrong unit", "gnb_lost_wait_s"]),
    ("safety.link_lost_wait_s", -1.0, ["safety.link_lost_wait_s", "positive"]),
]


@pytest.mark.parametrize(("path", "value", "words"), BAD, ids=[f"{p}={v!r}" for p, v, _ in BAD])
def test_bad_mission_file_is_refused_naming_file_key_and_value(tmp_path, path, value, words):
    f = tmp_path / "bad.toml"
    data = _set(example_dict(), path, value)
    with pytest.raises(MissionConfigError) as info:
        mission_from_dict(data, str(f))
    msg = str(info.value)
    assert msg.startswith(str(f)), msg
    for w in words:
        assert w in msg, (w, msg)
    assert isinstance(info.value, MissionError)


def test_a_file_with_a_true_position_is_refused_from_disk(tmp_path):
    text = EXAMPLE.read_text(encoding="utf-8").replace('ground_height_m = 0.0', 'east_m = 60.0\nnorth_m = 45.0', 1)
    f = tmp_path / "with_truth.toml"
    f.write_text(text, encoding="utf-8")
    with pytest.raises(MissionConfigError, match=r"with_truth\.toml: key 'users\[0\]\.east_m' = 60\.0: .*never holds "
                       r"true positions"):
        load_mission(f)


def test_not_toml_and_missing_file_name_the_file(tmp_path):
    f = tmp_path / "broken.toml"
    f.write_text("[flight\n", encoding="utf-8")
    with pytest.raises(MissionConfigError, match="broken.toml: not valid TOML"):
        load_mission(f)
    with pytest.raises(MissionConfigError, match="nope.toml: cannot read"):
        load_mission(tmp_path / "nope.toml")


def test_geodetic_fence_becomes_the_same_enu_polygon():
    home = Origin(43.6143, 7.0716, 150.0)
    fence_enu = np.array([[-150.0, -150.0], [200.0, -150.0], [200.0, 200.0], [-150.0, 200.0]])
    lat, lon, _ = home.enu_to_lla(np.column_stack([fence_enu, np.zeros(4)]))
    data = _set(example_dict(), "geofence.polygon_enu_m", None)
    data = _set(data, "geofence.polygon_lat_lon_deg", [[float(a), float(o)] for a, o in zip(lat, lon, strict=True)])
    fence, zones = mission_from_dict(data).geofence.polygons_enu_m(home)
    np.testing.assert_allclose(fence, fence_enu, atol=1e-3)
    np.testing.assert_allclose(zones[0], [[60, -40], [90, -40], [90, -10], [60, -10]])


@pytest.mark.parametrize("path", bundled_scenarios(), ids=lambda p: p.stem)
def test_every_bundled_scenario_has_a_valid_mission_part(path):
    sc = load_scenario(path)
    mc = sc.mission_config()
    assert [u.rnti for u in mc.users] == [u.rnti for u in sc.users]
    assert mc.flight.budget_m == sc.mission.flight.budget_m
    assert mc.noise_model() == sc.noise_model()
    assert not any(hasattr(u, "east_m") for u in mc.users)


def test_header_fields_round_trip_to_the_report_and_the_safety_gate():
    """mission file → log header fields → the report's shapes, and → the safety gate's limits."""
    from mission.report import shapes_from_header
    from mission.safety import SafetyGate, SafetyLimits

    home = Origin(47.397742, 8.545594, 488.0)
    mc = load_mission(EXAMPLE)
    fields = mc.header_fields(home)
    assert set(fields) == {"geofence", "no_fly_zones", "altitude_band_m"}
    sh = shapes_from_header(fields)
    back = home.lla_to_enu(sh.geofence_lat_lon_deg[:, 0], sh.geofence_lat_lon_deg[:, 1], np.full(4, home.alt_m))
    np.testing.assert_allclose(back[:, :2], mc.geofence.polygon_enu_m, atol=1e-6)
    assert sh.altitude_band_m == (20.0, 80.0) and len(sh.no_fly_lat_lon_deg) == 1
    gate = SafetyGate(SafetyLimits.from_mission(mc, home))
    assert gate.position_violations(np.array([0.0, 0.0, 40.0])) == []
    assert any("no-fly zone 0" in v for v in gate.position_violations(np.array([75.0, -25.0, 40.0])))
    assert any("band" in v for v in gate.position_violations(np.array([0.0, 0.0, 90.0])))


@pytest.mark.parametrize("path", bundled_scenarios(), ids=lambda p: p.stem)
def test_planning_constraints_of_the_mission_part_equal_the_scenarios_without_buildings(path):
    """The mission file gives the planner what the scenario gave it (buildings are the world's:
    a scenario turns them into an altitude floor or no-fly zones, a mission file names no-fly zones)."""
    from planner.types import PlanningConstraints

    sc = load_scenario(path)
    if sc.buildings:
        sc = dataclasses.replace(sc, world=dataclasses.replace(sc.world, buildings=[]))
    want = sc.planning_constraints()
    got = sc.mission_config().planning_constraints(Origin(sc.origin.lat_deg, sc.origin.lon_deg, sc.origin.alt_m))
    for f in dataclasses.fields(PlanningConstraints):
        a, b = getattr(got, f.name), getattr(want, f.name)
        if f.name == "no_fly_enu_m":
            assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
        elif isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
        else:
            assert a == b, f.name


def test_the_gps_floor_is_the_drifting_errors_mean_over_the_survey():
    """Var[(1/T)∫β] / σ² of a Gauss–Markov error against a seeded simulation of one; the floor's
    limits: a constant offset (τ ≫ T) keeps all of σ, a white error none."""
    from estimator.gps import gps_floor_bound_95_m, gps_mean_var_factor, gps_tau_for_floor_s
    from estimator.types import CHI2_2DOF_95

    rng = np.random.default_rng(7)
    tau_s, survey_s, dt = 30.0, 150.0, 0.1
    phi = np.exp(-dt / tau_s)
    e = rng.normal(size=4000)
    total = np.zeros(4000)
    n = round(survey_s / dt)
    for _ in range(n):
        total += e
        e = phi * e + np.sqrt(1 - phi**2) * rng.normal(size=4000)
    assert np.var(total / n) == pytest.approx(gps_mean_var_factor(tau_s, survey_s), rel=0.08)
    assert gps_floor_bound_95_m(1.0, 1e12, 150.0) == pytest.approx(np.sqrt(CHI2_2DOF_95), rel=1e-6)
    assert gps_floor_bound_95_m(1.0, 0.0, 150.0) == 0.0
    tau = gps_tau_for_floor_s(1.0, 150.0, 1.5)
    assert gps_floor_bound_95_m(1.0, tau, 150.0) == pytest.approx(1.5, abs=1e-6)


def test_a_target_below_the_gps_floor_is_refused_with_both_numbers(tmp_path, capsys):
    """Issue 39: σ_gps 1 m drifting with τ of minutes leaves ~2.4 m no flight removes; a 1.5 m
    target is refused at load, naming the floor, the target and what would allow it."""
    from mission.cli import main
    from mission.config import gps_floor_m

    text = EXAMPLE.read_text().replace("target_radius_m = 3.0", "target_radius_m = 1.5").replace(
        "gps_tau_s = 5.0", "gps_tau_s = 600.0")
    path = tmp_path / "tight.toml"
    path.write_text(text)
    with pytest.raises(MissionConfigError, match=r"target_radius_m.*1\.5.*below the GPS floor of 2\.\d\d m"):
        load_mission(path)
    rc = main(["fly", "--mission", str(path), "--connect", "udpin://127.0.0.1:1", "--gnb", "127.0.0.1:1"])
    err = capsys.readouterr().err
    assert rc == 1 and "below the GPS floor" in err and "sigma_gps_m <=" in err and "gps_tau_s <=" in err
    # the example's own target stands above its floor
    assert gps_floor_m(load_mission(EXAMPLE)) < 3.0
