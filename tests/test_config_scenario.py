"""A scenario file is a mission file plus world sections, read by the one loader."""

from __future__ import annotations

import dataclasses
import tomllib

import pytest

from mission.config import MissionConfig, mission_from_dict
from sitl_scenarios.campaign.families import FamilySpec, generate_scenario
from sitl_scenarios.scenario import (
    MISSION_DEFAULTS_FROM_WORLD,
    WORLD_KEYS,
    bundled_scenarios,
    load_scenario,
    scenario_from_dict,
)
from uavloc.errors import MissionConfigError, ScenarioError

PATHS = bundled_scenarios()


@pytest.mark.parametrize("path", PATHS, ids=lambda p: p.stem)
def test_a_scenario_file_without_its_world_is_a_mission_file(path):
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    mission = mission_from_dict({k: v for k, v in data.items() if k not in WORLD_KEYS}, str(path))
    sc = load_scenario(path)
    assert isinstance(sc.mission, MissionConfig)
    assert (mission.users, mission.geofence, mission.safety) == (sc.mission.users, sc.mission.geofence,
                                                                 sc.mission.safety)
    # the flight's speeds come from the world when the file leaves them out, the rest is the file's
    world_keys = {key for (table, key), _ in MISSION_DEFAULTS_FROM_WORLD if table == "flight"}
    assert dataclasses.replace(mission.flight, **{k: getattr(sc.mission.flight, k) for k in world_keys}) \
        == sc.mission.flight
    assert sc.mission.flight.cruise_speed_mps == sc.vehicle.speed_mps
    assert sc.mission.noise.range_s0_m == sc.radio.s0_m or "range_s0_m" in data.get("noise", {})


@pytest.mark.parametrize("path", PATHS, ids=lambda p: p.stem)
def test_a_mission_file_refuses_the_world_sections(path):
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    with pytest.raises(MissionConfigError, match="simulated world"):
        mission_from_dict(data, str(path))


def test_the_old_layout_says_where_its_keys_went():
    old = {"name": "o", "users": [{"id": "a", "rnti": 1, "east_m": 1.0, "north_m": 2.0}],
           "mission": {"delta_m": 2.0}}
    with pytest.raises(ScenarioError, match=r"o.toml: key 'mission'.*\[flight\]"):
        scenario_from_dict(old, "o.toml")


def test_family_members_are_the_same_objects():
    sc = generate_scenario(FamilySpec(name="f", seed=3, users=[2, 4]), 0)
    assert isinstance(sc.mission, MissionConfig) and type(sc) is type(load_scenario("paper"))
    assert [u.id for u in sc.users] == [u.id for u in sc.mission.users] == sorted(sc.world.truth)
    assert sc.mission.flight.target_radius_m == 0.6 and sc.mission.noise.estimate_bias is True


def test_a_scenarios_held_bias_follows_the_kind_of_its_ues():
    """Commercial UEs (a clock sawtooth, the radio's default) hold an insignificant bias at an
    untracked sawtooth's mean; a world of ideal UEs at 0; the file's own [noise] key wins."""
    assert load_scenario("three_users_nlos").mission.noise.bias_held == "sawtooth"
    ideal = generate_scenario(FamilySpec(name="f", seed=3, users=[2, 4], sawtooth_amplitude_m=0.0), 0)
    assert ideal.mission.noise.bias_held == "zero"
    commercial = generate_scenario(FamilySpec(name="f", seed=3, users=[2, 4], sawtooth_amplitude_m=[1.0, 12.0]), 0)
    assert commercial.mission.noise.bias_held == "sawtooth"
    path = next(p for p in PATHS if p.stem == "three_users_nlos")
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    data.setdefault("noise", {})["bias_held"] = "zero"
    assert scenario_from_dict(data, str(path)).mission.noise.bias_held == "zero"
    data["noise"]["bias_held"] = "always"
    with pytest.raises(ScenarioError, match="bias_held"):
        scenario_from_dict(data, str(path))


def test_sim_refuses_a_target_below_the_gps_floor_of_the_built_in_vehicles_gps(tmp_path, capsys):
    """Issue 48: the floor check of a mission file also judges a scenario, with the world's τ."""
    from mission.cli import main
    from sitl_scenarios.scenario import SCENARIO_DIR

    text = (SCENARIO_DIR / "five_commercial_ues.toml").read_text()
    assert "target_radius_m = 4.0" in text
    path = tmp_path / "five_1m.toml"
    path.write_text(text.replace("target_radius_m = 4.0", "target_radius_m = 1.0"))
    assert main(["sim", str(path), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert str(path) in err and "flight.target_radius_m = 1" in err and "below the GPS floor of 1.92 m" in err
    assert "gps_tau_s = 120 s" in err and not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", ["paper", "three_users_nlos", "five_commercial_ues", "two_uavs", "clock_sawtooth",
                                  "edge_of_coverage"])
def test_every_bundled_scenarios_target_lies_above_its_gps_floor(name):
    from mission.config import gps_floor_problem
    from sitl_scenarios.scenario import load_scenario

    assert gps_floor_problem(load_scenario(name).mission_config()) is None
