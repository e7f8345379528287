"""`uavloc fly --mission`: the controller configured from a mission file (no simulator schema)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.geodesy import Origin
from mission.config import example_mission_path, load_mission, mission_from_dict
from mission.control.config import ControllerConfig
from mission.controller import controller_from_mission
from mission.gnb.config import GnbConfig
from mission.safety import SafetyLimits
from sitl_scenarios.scenario import load_scenario
from uavloc.errors import MissionConfigError


def test_controller_config_from_the_example_mission_file():
    m = load_mission(example_mission_path())
    cfg = ControllerConfig.from_mission(m, time_scale=2.0)
    assert cfg.flight is m.flight and cfg.safety is m.safety
    assert cfg.gnb_timeout_s == m.gnb.measure_timeout_s() and cfg.time_scale == 2.0


def test_scenario_config_is_its_mission_parts():
    sc = load_scenario("three_users_nlos")
    assert ControllerConfig.from_mission(sc.mission_config()).flight.cruise_speed_mps == sc.vehicle.speed_mps


def test_active_stock_mode_waits_longer_per_measurement_than_for_the_msg2():
    m = load_mission(example_mission_path())
    rtt = m.gnb
    active = dataclasses.replace(rtt, mode="stock", stock_mode="active", log_path="gnb.log")
    passive = dataclasses.replace(active, stock_mode="passive")
    assert active.msg2_timeout_s == 15.0  # real OAI: ~5 s of log time, the rfsimulator at 0.4x
    assert active.measure_timeout_s() > active.msg2_timeout_s + active.request_timeout_s
    assert rtt.measure_timeout_s() < rtt.msg2_timeout_s  # the Msg2 wait is not part of an RTT request
    assert passive.measure_timeout_s() == rtt.measure_timeout_s()
    c = GnbConfig.of(active, "10.0.0.2", 9090, retries=1)
    assert (c.host, c.port, c.retries) == ("10.0.0.2", 9090, 1)
    # the rest of the adapter's settings are the mission file's, field for field
    assert all(getattr(c, f.name) == getattr(active, f.name) for f in dataclasses.fields(active) if f.name != "retries")


def test_stock_mode_is_checked():
    base = {"name": "m", "users": [{"id": "a", "rnti": "0x4601"}]}
    with pytest.raises(MissionConfigError, match=r"gnb.stock_mode.*'active', 'passive'"):
        mission_from_dict({**base, "gnb": {"mode": "stock", "stock_mode": "sometimes", "log_path": "g.log"}}, "f.toml")
    m = mission_from_dict({**base, "gnb": {"mode": "stock", "stock_mode": "passive", "log_path": "g.log"}}, "f.toml")
    assert m.gnb.stock_mode == "passive"


def test_geodetic_fence_is_placed_once_home_is_known(tmp_path):
    """A fence given in degrees cannot be turned into home-ENU before home is known: the controller
    gets a planner and limits as functions of home (built in PREFLIGHT)."""
    home = Origin(43.6143, 7.0716, 150.0)
    ring = [[-100.0, -100.0], [150.0, -100.0], [150.0, 150.0], [-100.0, 150.0]]
    lla = np.array([home.enu_to_lla([e, n, 0.0]) for e, n in ring])
    m = mission_from_dict({"name": "geo", "users": [{"id": "a", "rnti": "0x4601"}],
                           "geofence": {"polygon_lat_lon_deg": lla[:, :2].tolist()},
                           "flight": {"planner": "lawnmower"}}, "geo.toml")
    ctl = controller_from_mission(m, None, None, tmp_path / "m.jsonl")
    assert ctl.planner is None and ctl.gate is None  # not before home
    ctl._at_home(type("Home", (), {"lat_deg": home.lat_deg, "lon_deg": home.lon_deg,
                                   "alt_amsl_m": home.alt_m})())
    assert ctl.planner is not None and ctl.planner.constraints.fence_enu_m == pytest.approx(np.array(ring), abs=1e-6)
    want = SafetyLimits.from_mission(m, home)
    assert ctl.gate.limits.fence_enu_m == pytest.approx(want.fence_enu_m)
    ctl.journal.close()


def test_controller_overrides_of_mission_settings_fly_the_mission_with_them(tmp_path):
    """A mission file setting given as an override reaches the controller and the safety limits
    alike (one configuration); an override that is no setting is refused by its key."""
    m = load_mission(example_mission_path())
    ctl = controller_from_mission(m, None, None, tmp_path / "m.jsonl", time_limit_s=600.0, battery_rtl_pct=40.0,
                                  gnb_timeout_s=7.0)
    assert ctl.config.flight.time_limit_s == 600.0 and ctl.config.gnb_timeout_s == 7.0
    assert ctl.config.safety.battery_rtl_pct == 40.0 and ctl.gate.limits.battery_rtl_pct == 40.0
    assert ctl.config.flight.budget_m == m.flight.budget_m
    ctl.journal.close()
    with pytest.raises(MissionConfigError, match="time_limit_min"):
        controller_from_mission(m, None, None, tmp_path / "n.jsonl", time_limit_min=10)
    with pytest.raises(MissionConfigError, match="time_limit_s"):
        controller_from_mission(m, None, None, tmp_path / "o.jsonl", time_limit_s=-1.0)
    # the controller's own settings have bounds too (a 0 Hz telemetry log would divide by zero)
    with pytest.raises(MissionConfigError, match="controller settings: key 'telemetry_log_hz' = 0.0"):
        controller_from_mission(m, None, None, tmp_path / "p.jsonl", telemetry_log_hz=0.0)


def test_fly_refuses_the_oracle_planner_before_connecting(capsys):
    """Issue 21 #10: the oracle plans at the true positions, which a flight never has: refused
    with the reason and the planners it may use, before anything connects (nothing listens)."""
    from mission.cli import main
    from mission.config import example_mission_path

    code = main(["fly", "--mission", str(example_mission_path()), "--connect", "udpin://127.0.0.1:9",
                 "--gnb", "127.0.0.1:9", "--planner", "oracle"])
    err = capsys.readouterr().err
    assert code == 1
    assert "oracle planner plans at the users' true positions" in err and "lawnmower" in err, err
    assert "waiting for an autopilot" not in err
