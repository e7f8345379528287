"""Scenario files: strict keys, types and values; every bundled scenario loads."""

from __future__ import annotations

import copy
import tomllib

import pytest

from sitl_scenarios.scenario import (
    bundled_scenarios,
    load_scenario,
    resolve_scenario_path,
    scenario_from_dict,
)
from uavloc.errors import ScenarioError

BASE = {
    "name": "t",
    "users": [{"id": "a", "rnti": "0x4601"}],
    "truth": {"a": {"east_m": 10.0, "north_m": 5.0}},
    "radio": {"mu": 1},
}


def with_(path: list, value):
    d = copy.deepcopy(BASE)
    node = d
    for key in path[:-1]:
        node = node.setdefault(key, {}) if isinstance(key, str) else node[key]
    node[path[-1]] = value
    return d


@pytest.mark.parametrize("path", sorted(p.stem for p in bundled_scenarios()))
def test_every_bundled_scenario_loads(path):
    sc = load_scenario(path)
    assert sc.users and sc.name


def test_hex_rnti_and_defaults():
    sc = scenario_from_dict(BASE)
    assert sc.users[0].rnti == 0x4601
    assert sc.mission.flight.delta_m == 2.0
    assert sc.noise_model().range_s0_m == sc.radio.s0_m


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (with_(["bogus"], 1), "unknown key.*'bogus'"),
        (with_(["radio", "muu"], 1), r"'radio.muu'.*unknown key"),
        (with_(["users", 0, "colour"], "red"), r"users\[0\].colour'.*unknown key"),
        (with_(["radio", "mu"], 7), "radio.mu"),
        (with_(["radio", "fs_hz"], "fast"), "radio.fs_hz' = 'fast': expected a number"),
        (with_(["radio", "fs_hz"], float("nan")), "finite"),
        (with_(["users", 0, "rnti"], "zz"), "expected an integer"),
        (with_(["flight", "altitude_m"], 500.0), "alt_max_m"),
        (with_(["mission"], {"delta_m": 2.0}), r"'mission'.*a mission file plus world sections.*\[flight\]"),
        (with_(["users", 0, "east_m"], 1.0), r"'users\[0\].east_m'.*truth"),
        (with_(["truth", "b"], {"east_m": 1.0, "north_m": 1.0}), r"'truth.b'.*no \[\[users\]\] entry"),
        (with_(["truth"], {}), r"user 'a' has no \[truth.a\]"),
        (with_(["users"], []), "at least one user"),
        ({"name": "x", "truth": {}}, "missing required key 'users'"),
        ({"name": "x", "users": [{"id": "a", "rnti": 1}]}, "missing required key 'truth'"),
        (with_(["buildings"], [{"footprint_enu_m": [[0, 0], [1, 1]], "height_m": 5.0}]), ">= 3"),
    ],
)
def test_bad_scenarios_name_the_key(data, match):
    with pytest.raises(ScenarioError, match=match):
        scenario_from_dict(data)


def test_duplicate_users_rejected():
    d = copy.deepcopy(BASE)
    d["users"].append(dict(d["users"][0]))
    with pytest.raises(ScenarioError, match="duplicate"):
        scenario_from_dict(d)


def test_unknown_scenario_name_lists_bundled(tmp_path):
    with pytest.raises(ScenarioError, match="bundled scenarios: .*paper"):
        resolve_scenario_path(tmp_path / "nope.toml")


def test_invalid_toml_is_a_scenario_error(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("name = \n")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(p)


def test_file_round_trip(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('name = "s"\n[[users]]\nid = "u"\nrnti = 17921\n[truth.u]\neast_m = 1\nnorth_m = 2\n')
    assert tomllib.loads(p.read_text())["name"] == "s"
    assert load_scenario(p).users[0].east_m == 1.0


def test_estimator_noise_can_differ_from_the_radio_truth():
    sc = scenario_from_dict(with_(["noise", "range_s0_m"], 4.6))
    assert sc.noise_model().range_s0_m == 4.6
    assert sc.radio_noise_model().range_s0_m == sc.radio.s0_m == 3.0
    assert scenario_from_dict(BASE).noise_model().range_s0_m == 3.0
    with pytest.raises(ScenarioError, match="range_s0_m' = 0.0: must be positive"):
        scenario_from_dict(with_(["noise", "range_s0_m"], 0.0))


def test_an_external_autopilot_does_not_get_the_builtin_vehicles_gps_drift():
    """The built-in vehicle's GPS error (Gauss–Markov, τ = vehicle.gps_tau_s) is what the estimator
    assumes when that vehicle flies; PX4 SITL's EKF output drifts far slower (its increments give
    τ ≈ 120–220 s at σ 1 m), so with an external autopilot τ is unknown (the log omits it; replay
    estimates it from the telemetry) unless the mission section sets it."""
    sc = scenario_from_dict(BASE)
    assert sc.noise_model().gps_tau_s == sc.vehicle.gps_tau_s == 3.0
    assert sc.noise_model(external_vehicle=True).gps_tau_s is None
    assert sc.mission_config(external_vehicle=True).noise.gps_tau_s is None
    assert "gps_tau_s" not in sc.mission_config(external_vehicle=True).noise.header_noise()
    given = scenario_from_dict(with_(["noise", "gps_tau_s"], 60.0))
    assert given.noise_model(external_vehicle=True).gps_tau_s == given.noise_model().gps_tau_s == 60.0
