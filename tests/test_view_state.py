"""The live view's state model (mission/view/state.py) and the mission-log parts it relies on:
the writer's listeners and the header's optional area fields. Pure: no server, no browser."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from estimator.geodesy import Origin
from estimator.types import CHI2_2DOF_95, Estimate
from mission.config import FlightConfig
from mission.control.config import ControllerConfig
from mission.log import MissionLogWriter, area_fields, read_mission_log
from mission.vehicle.telemetry import VehicleStatus
from mission.view.state import GNB_STALE_S, Cursor, Timeline, ViewState, ellipse_95
from uavloc.errors import MissionLogError

ORIGIN = Origin(43.6143, 7.0716, 150.0)
USERS = [{"id": "ue1", "rnti": 17921, "ground_alt_m": 150.0}, {"id": "ue2", "rnti": 17922, "ground_alt_m": 150.0}]
FENCE_EN_M = np.array([[-100.0, -100.0], [200.0, -100.0], [200.0, 150.0], [-100.0, 150.0]])
NOFLY_EN_M = [np.array([[50.0, 50.0], [80.0, 50.0], [65.0, 90.0]])]
BUILDING_EN_M = np.array([[10.0, 10.0], [30.0, 10.0], [30.0, 25.0], [10.0, 25.0]])


def lla(e, n, u=0.0) -> dict:
    lat, lon, alt = ORIGIN.enu_to_lla(np.array([e, n, u], float))
    return {"lat_deg": float(lat), "lon_deg": float(lon), "alt_m": float(alt)}


def write_mission(path, listener=None, n_tel: int = 50, controller: dict | None = None) -> list[dict]:
    """A small mission log written by the real writer; returns the records as written.
    controller: the header's controller settings (default: those the controller writes)."""
    seen: list[dict] = []
    with MissionLogWriter(path) as w:
        w.subscribe(seen.append)
        if listener is not None:
            w.subscribe(listener)
        w.write_header(ORIGIN, USERS, {"mu": 1, "fs_hz": 46.08e6},
                       config={"scenario": "t",
                               "controller": controller or asdict(ControllerConfig(FlightConfig(target_radius_m=2.5)))},
                       area=area_fields(ORIGIN, FENCE_EN_M, NOFLY_EN_M, 10.0, 120.0, 500.0,
                                        [(BUILDING_EN_M, 12.0)]))
        w.write("truth", 0.1, users=[{"id": "ue1", **lla(40, 30)}, {"id": "ue2", **lla(-20, 60)}])
        w.write("event", 0.2, message="armed", kind="arm", state="TAKEOFF")
        for i in range(n_tel):
            w.write("telemetry", 1.0 + 0.2 * i, **lla(0.5 * i, 0.1 * i, 30.0), vel_ned_mps=[0.5, 2.5, -0.4],
                    **VehicleStatus(rel_alt_m=30.0 - 0.01 * i, heading_deg=(350.0 + 2 * i) % 360,
                                    battery_pct=95.0 - 0.5 * i, battery_voltage_v=16.4 - 0.01 * i,
                                    flight_mode="HOLD" if i < 5 else "OFFBOARD", armed=True, gps_fix_type=3,
                                    gps_satellites=10 + i % 3).record_fields())
            if i == 5:
                w.write("waypoint", 2.05, leg=1, **lla(60, 10, 30), enu_m=[60, 10, 30], planner="casadi",
                        status="ok")
            if i % 5 == 4:
                w.write("rtt", 1.0 + 0.2 * i - 0.05, user="ue1", uav=lla(0.5 * i, 0.1 * i, 30.0), toa_s=2e-7)
                if i > 20:
                    w.write("rtt", 1.0 + 0.2 * i - 0.05, user="ue2", uav=lla(0.5 * i, 0.1 * i, 30.0), toa_s=2e-7)
            if i in (10, 30):
                s = 1.0 if i == 10 else 0.5
                users = [{"id": "ue1", **lla(40 + s, 30 - s), "cov_en_m2": [[4 * s, s], [s, 2 * s]],
                          "ambiguous": i == 10}]
                if i == 30:
                    users.append({"id": "ue2", **lla(-19, 61), "cov_en_m2": [[9.0, 0.0], [0.0, 1.0]]})
                w.write("estimate", 1.0 + 0.2 * i + 0.01, users=users, keyframes=i // 5, flown_m=float(i),
                        uav_lla=[list(lla(0.5 * i, 0.1 * i, 30).values())])
        w.write("event", 12.0, message="RTL: target reached", kind="rtl", state="RETURN")
        w.write("estimate", 12.5, users=[{"id": "ue1", **lla(40.2, 29.9), "cov_en_m2": [[0.5, 0.1], [0.1, 0.4]]}],
                keyframes=9, flown_m=55.0, final=True,
                uav_lla=[list(lla(0.5 * i, 0.1 * i, 30).values()) for i in range(0, n_tel, 5)])
        w.write("event", 13.0, message="mission end: target_reached (target reached)", kind="end",
                status="target_reached", reason="target reached", state="LANDED")
    return seen


# -- the ellipse ------------------------------------------------------------------------------------


@pytest.mark.parametrize("cov", [
    [[4.0, 0.0], [0.0, 1.0]],
    [[1.0, 0.0], [0.0, 4.0]],
    [[2.0, 1.2], [1.2, 1.0]],
    [[0.3, -0.2], [-0.2, 0.9]],
    [[1.0, 0.0], [0.0, 1.0]],
])
def test_ellipse_semi_major_is_the_estimates_r95_and_its_boundary_is_the_chi2_contour(cov):
    cov = np.array(cov)
    ell = ellipse_95(cov)
    est = Estimate(users_enu_m=np.zeros((1, 3)), cov_users_m2=cov[None], info_users=np.eye(2),
                   bias_m=None, uav_enu_m=np.zeros((0, 3)), ambiguous=np.zeros(1, bool),
                   mirror_enu_m=np.full((1, 3), np.nan), n_ranges=np.zeros(1, int))
    assert ell["a_m"] == pytest.approx(est.error_bound_95_m()[0], rel=1e-12)
    assert ell["a_m"] >= ell["b_m"]
    # points on the drawn ellipse (axes a, b, rotated by angle) have Mahalanobis d² = χ²₂(0.95)
    th = math.radians(ell["angle_deg"])
    rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    for phi in np.linspace(0, 2 * np.pi, 7):
        p = rot @ np.array([ell["a_m"] * math.cos(phi), ell["b_m"] * math.sin(phi)])
        assert p @ np.linalg.solve(cov, p) == pytest.approx(CHI2_2DOF_95, rel=1e-9)


# -- the model ----------------------------------------------------------------------------------


def test_a_log_with_the_flat_controller_settings_of_older_uavloc_shows_its_target(tmp_path):
    state = ViewState()
    write_mission(tmp_path / "m.jsonl", state.apply, n_tel=2, controller={"target_radius_m": 3.5})
    assert state.frame()[0]["static"]["target_radius_m"] == 3.5


def test_state_from_the_records_the_writer_hands_its_listeners(tmp_path):
    state = ViewState()
    write_mission(tmp_path / "m.jsonl", state.apply)
    doc, _ = state.frame()
    st = doc["static"]
    assert [u["id"] for u in st["users"]] == ["ue1", "ue2"]
    np.testing.assert_allclose(st["geofence"], FENCE_EN_M, atol=0.01)
    np.testing.assert_allclose(st["no_fly_zones"][0], NOFLY_EN_M[0], atol=0.01)
    np.testing.assert_allclose(st["buildings"][0]["footprint"], BUILDING_EN_M, atol=0.01)
    assert st["buildings"][0]["height_m"] == 12.0
    assert st["altitude_band_m"] == {"min_m": 10.0, "max_m": 120.0}
    assert st["target_radius_m"] == 2.5
    np.testing.assert_allclose(st["truth"]["ue2"], [-20, 60, 0], atol=0.01)
    assert len(doc["track"]["items"]) == 50
    np.testing.assert_allclose(doc["track"]["items"][-1][1:], [24.5, 4.9, 30.0], atol=0.01)
    assert doc["vehicle"]["vel_en_mps"] == [2.5, 0.5]
    u1, u2 = doc["users"]
    assert u1["measurements"] == 10 and u2["measurements"] == 6 and doc["measurements"] == 16
    np.testing.assert_allclose(u1["enu_m"][:2], [40.2, 29.9], atol=0.01)
    assert u1["r95_m"] == pytest.approx(ellipse_95([[0.5, 0.1], [0.1, 0.4]])["a_m"])
    assert u1["error_m"] == pytest.approx(math.hypot(0.2, 0.1), abs=0.02)
    assert u2["r95_m"] == pytest.approx(3.0 * math.sqrt(CHI2_2DOF_95))
    assert not u1["ambiguous"]
    assert doc["state"] == "LANDED" and doc["status"] == "target_reached" and doc["final"]
    assert doc["flown_m"] == 55.0 and doc["keyframes"] == 9
    assert doc["waypoint"] is None  # cleared at RTL
    # the final estimate replaces the estimated track with the whole smoothed one
    assert len(doc["est_track"]["items"]) == 10
    assert [e["kind"] for e in doc["events"]["items"]] == ["arm", "rtl", "end"]


def test_waypoint_leg_starts_where_the_vehicle_was_and_ambiguity_is_shown(tmp_path):
    records = write_mission(tmp_path / "m.jsonl")
    state = ViewState()
    for rec in records:
        state.apply(rec)
        if rec["type"] == "estimate":
            break
    doc, _ = state.frame()
    assert doc["state"] == "SURVEY"
    assert doc["waypoint"]["leg"] == 1
    np.testing.assert_allclose(doc["waypoint"]["from_enu_m"], [2.5, 0.5, 30.0], atol=0.01)
    np.testing.assert_allclose(doc["waypoint"]["enu_m"], [60, 10, 30], atol=0.01)
    assert doc["users"][0]["ambiguous"] is True
    assert doc["users"][1]["located"] is False


def test_flown_metres_without_the_field_come_from_the_survey_track():
    state = ViewState()
    state.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS[:1]})
    state.apply({"type": "waypoint", "t": 1, "leg": 1, **lla(100, 0, 30)})
    for i in range(11):
        state.apply({"type": "telemetry", "t": 1 + i, **lla(10.0 * i, 0, 30)})
    assert state.frame()[0]["flown_m"] == pytest.approx(100.0, abs=0.1)


def test_incremental_frames_add_up_to_the_whole_picture_whichever_frames_a_client_skips(tmp_path):
    records = write_mission(tmp_path / "m.jsonl")
    rng = np.random.default_rng(3)
    for _trial in range(5):
        state = ViewState()
        cursor: Cursor | None = None
        local: dict[str, list] = {}
        for rec in records:
            state.apply(rec)
            if rng.random() < 0.2:  # this client took a frame now; it skipped the others
                doc, cursor = state.frame(cursor)
                for name in ("track", "est_track", "events"):
                    part = doc[name]
                    if part["from"] == 0:
                        local[name] = list(part["items"])
                    else:
                        assert len(local[name]) == part["from"]
                        local[name] += part["items"]
        doc, cursor = state.frame(cursor)
        full, _ = state.frame(None)
        for name in ("track", "est_track", "events"):
            part = doc[name]
            merged = list(part["items"]) if part["from"] == 0 else local[name] + part["items"]
            assert merged == full[name]["items"]
        assert "static" not in state.frame(cursor)[0]  # seen already


def test_events_beyond_the_cap_drop_the_oldest_and_clients_start_over():
    state = ViewState(max_events=10)
    state.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS[:1]})
    _, cur = state.frame()
    for i in range(25):
        state.apply({"type": "event", "t": i, "message": f"e{i}", "kind": "x"})
    doc, _ = state.frame(cur)
    assert doc["events"]["from"] == 0 and doc["events"]["items"][-1]["message"] == "e24"
    assert len(doc["events"]["items"]) <= 10


def test_malformed_records_are_skipped_not_raised():
    state = ViewState()
    state.apply({"type": "telemetry", "t": 1, **lla(1, 1)})  # before the header: ignored
    state.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS})
    state.apply({"type": "telemetry", "t": 2, "lat_deg": "x"})
    state.apply({"type": "estimate", "t": 3, "users": [{"id": "nobody", **lla(0, 0), "cov_en_m2": [[1, 0], [0, 1]]}]})
    state.apply({"type": "rtt", "t": 4, "user": "nobody"})
    state.apply({"type": "bogus", "t": 5})
    doc, _ = state.frame()
    assert doc["track"]["items"] == [] and doc["measurements"] == 0
    assert not any(u["located"] for u in doc["users"])


def test_timeline_shows_the_estimate_of_the_chosen_time_forwards_and_backwards(tmp_path):
    records = write_mission(tmp_path / "m.jsonl")
    tl = Timeline(records)
    assert tl.t_end_s == 13.0
    est_t = [r["t"] for r in records if r["type"] == "estimate"]
    # just after the first estimate: its numbers; before it: nothing located
    for t, expect in ((est_t[1] + 0.01, 0.5), (est_t[0] + 0.01, 1.0), (est_t[0] - 0.01, None),
                      (est_t[1] + 0.01, 0.5)):
        u1 = tl.state_at(t).frame()[0]["users"][0]
        if expect is None:
            assert not u1["located"]
        else:
            np.testing.assert_allclose(u1["enu_m"][:2], [40 + expect, 30 - expect], atol=0.01)
            assert u1["r95_m"] == pytest.approx(ellipse_95([[4 * expect, expect], [expect, 2 * expect]])["a_m"])
    assert tl.state_at(1e9).frame()[0]["final"]


def test_timeline_checkpoints_give_the_same_state_as_a_fresh_replay(tmp_path):
    records = write_mission(tmp_path / "m.jsonl")
    tl = Timeline(records, checkpoint_every=7)
    rng = np.random.default_rng(5)
    for t in [13.0, *rng.uniform(0, 13.5, 12)]:
        got = tl.state_at(t).frame()[0]
        fresh = Timeline(records).state_at(t).frame()[0]
        assert json.dumps(got, sort_keys=True) == json.dumps(fresh, sort_keys=True)


# -- the mission log's parts ----------------------------------------------------------------------


def test_a_failing_listener_is_dropped_and_the_log_goes_on(tmp_path, caplog):
    calls = []

    def bad(rec):
        calls.append(rec["type"])
        raise RuntimeError("boom")

    p = tmp_path / "m.jsonl"
    with MissionLogWriter(p) as w:
        w.subscribe(bad)
        w.write_header(ORIGIN, USERS, {"mu": 1})
        w.write("telemetry", 1.0, **lla(0, 0))
    assert calls == ["header"]
    assert len(p.read_text().splitlines()) == 2
    assert "listener" in caplog.text


def test_header_area_fields_round_trip_and_old_logs_still_read(tmp_path):
    p = tmp_path / "m.jsonl"
    write_mission(p)
    h = read_mission_log(p).header
    assert len(h.geofence) == 4 and len(h.no_fly_zones) == 1 and len(h.buildings) == 1
    back = ORIGIN.lla_to_enu(np.array(h.geofence)[:, 0], np.array(h.geofence)[:, 1], ORIGIN.alt_m)[:, :2]
    np.testing.assert_allclose(back, FENCE_EN_M, atol=1e-3)
    assert h.altitude_band_m == {"min_m": 10.0, "max_m": 120.0} and h.max_distance_m == 500.0
    assert h.buildings[0]["height_m"] == 12.0
    # a header without them (older logs, other tools)
    lines = p.read_text().splitlines()
    head = json.loads(lines[0])
    for k in ("geofence", "no_fly_zones", "buildings", "altitude_band_m", "max_distance_m"):
        head.pop(k)
    p2 = tmp_path / "old.jsonl"
    p2.write_text(json.dumps(head) + "\n" + "\n".join(lines[1:]) + "\n")
    h2 = read_mission_log(p2).header
    assert h2.geofence is None and h2.no_fly_zones == [] and h2.buildings == [] and h2.altitude_band_m is None


@pytest.mark.parametrize("field, value, match", [
    ("geofence", [[43.6, 7.0], [43.7, 7.0]], "geofence must be a list of >= 3"),
    ("geofence", [[43.6, 7.0], [43.7, 7.0], [95.0, 7.1]], r"geofence\[2\]"),
    ("no_fly_zones", [[[43.6, 7.0], [43.7, 7.0], [43.7, "x"]]], r"no_fly_zones\[0\]\[2\]"),
    ("altitude_band_m", {"min_m": 50, "max_m": 10}, "above max_m"),
    ("buildings", [{"footprint": [[43.6, 7.0], [43.7, 7.0], [43.7, 7.1]]}], r"buildings\[0\].*height_m"),
])
def test_bad_area_fields_name_the_line_and_the_field(tmp_path, field, value, match):
    head = {"type": "header", "t": 0, "format": "uavloc-mission/1", "origin": ORIGIN.to_dict(), "users": USERS,
            field: value}
    p = tmp_path / "bad.jsonl"
    p.write_text(json.dumps(head) + "\n")
    with pytest.raises(MissionLogError, match=rf"bad.jsonl:1: .*{match}"):
        read_mission_log(p)


def test_simulated_buildings_reach_the_header_in_the_home_frame(tmp_path):
    """The built-in vehicle's world is the scenario origin; the log's frame is the reported home
    (a little off): the buildings land at the same geodetic place either way."""
    from sitl_scenarios.scenario import load_scenario
    from sitl_scenarios.sim_runner import SimulatedMission

    sc = load_scenario("three_users_nlos")
    sim = SimulatedMission(sc, tmp_path / "m.jsonl")
    world = sc.origin_geo
    home = Origin(*world.enu_to_lla(np.array([3.0, -2.0, 0.5])))
    blds = sim._buildings(home)
    assert len(blds) == len(sc.buildings) == 3
    area = area_fields(home, buildings=blds)
    for b, cfg in zip(area["buildings"], sc.buildings, strict=True):
        ring = np.array(b["footprint"])
        back = world.lla_to_enu(ring[:, 0], ring[:, 1], world.alt_m)[:, :2]
        np.testing.assert_allclose(back, cfg.footprint_enu_m, atol=0.01)
        assert b["height_m"] == cfg.height_m


# -- the instrument strip ---------------------------------------------------------------------------


def test_health_strip_is_the_newest_telemetry_records_numbers_and_the_log_reads_them(tmp_path):
    recs = write_mission(tmp_path / "m.jsonl")
    tel = [r for r in recs if r["type"] == "telemetry"]
    st = ViewState()
    for rec in recs:
        st.apply(rec)
    h = st.frame()[0]["health"]
    last = tel[-1]
    assert h["t_s"] == last["t"] and h["rel_alt_m"] == last["rel_alt_m"]
    assert h["alt_amsl_m"] == pytest.approx(last["alt_m"], abs=1e-3)  # the frame's numbers: 3 decimals
    assert h["groundspeed_mps"] == pytest.approx(math.hypot(0.5, 2.5), abs=1e-3)
    assert h["climb_mps"] == pytest.approx(0.4)
    for k in ("heading_deg", "battery_pct", "battery_voltage_v", "flight_mode", "armed", "gps_fix_type",
              "gps_satellites"):
        assert h[k] == last[k], k
    assert h["flight_mode"] == "OFFBOARD" and h["gps_fix"] == "3D fix"
    # ages at the state's time (the end event at 13 s): the vehicle's 2.2 s, stale after the
    # controller's link timeout (3 s); rtt records up to 10.75 s
    assert h["vehicle_age_s"] == pytest.approx(13.0 - last["t"], abs=0.01) and not h["vehicle_stale"]
    rtt = [r for r in recs if r["type"] == "rtt"]
    assert h["gnb_age_s"] == pytest.approx(13.0 - max(r["t"] for r in rtt), abs=0.01)
    assert h["gnb_stale"] is (h["gnb_age_s"] > GNB_STALE_S)
    assert h["measurements_per_min"] == sum(1 for r in rtt if r["t"] > 13.0 - 60.0) == len(rtt)
    # the reader keeps the same numbers, typed
    log = read_mission_log(tmp_path / "m.jsonl")
    assert len(log.tel_status) == len(tel)
    assert log.tel_status[-1] == VehicleStatus.from_record(last)
    assert log.tel_status[-1].flight_mode == "OFFBOARD" and log.tel_status[-1].gps_satellites == last["gps_satellites"]


def test_health_strip_ages_turn_stale_and_the_rate_counts_the_last_minute():
    st = ViewState()
    st.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS[:1]})
    st.apply({"type": "telemetry", "t": 1.0, **lla(0, 0, 10)})
    for k in range(90):  # one range a second from 2 s to 91 s
        st.apply({"type": "rtt", "t": 2.0 + k, "user": "ue1", "uav": lla(0, 0, 10), "toa_s": 2e-7})
    h = st.frame()[0]["health"]
    assert h["measurements_per_min"] == 60  # 32..91 s
    assert h["vehicle_stale"] and h["vehicle_age_s"] == pytest.approx(90.0)
    assert not h["gnb_stale"] and h["gnb_age_s"] == 0.0
    st.apply({"type": "event", "t": 91.0 + GNB_STALE_S + 0.5, "message": "x"})
    h = st.frame()[0]["health"]
    assert h["gnb_stale"] and h["measurements_per_min"] == 55  # 37..91 s: the last minute of the state's time
    # an old log's telemetry (no status fields): altitude above home from the fix, the rest unknown
    assert h["rel_alt_m"] == pytest.approx(10.0, abs=0.01) and h["groundspeed_mps"] is None
    assert h["battery_pct"] is None and h["flight_mode"] is None and h["gps_fix"] is None


@pytest.mark.parametrize("field, value, match", [
    ("battery_pct", 120.0, "battery_pct"), ("gps_satellites", 3.5, "gps_satellites.*integer"),
    ("armed", 1, "armed.*true or false"), ("heading_deg", "N", "heading_deg"), ("flight_mode", 3, "flight_mode")])
def test_a_bad_status_field_names_the_line_and_the_field_and_the_view_skips_it(tmp_path, field, value, match):
    path = tmp_path / "m.jsonl"
    with MissionLogWriter(path) as w:
        w.write_header(ORIGIN, USERS, {"mu": 1})
        w.write("telemetry", 1.0, **lla(0, 0, 10), **{field: value})
    with pytest.raises(MissionLogError, match=f"m.jsonl:2: .*{match}"):
        read_mission_log(path)
    st = ViewState()
    for line in path.read_text().splitlines():
        st.apply(json.loads(line))
    assert st.vehicle is not None and st.health is None


def test_the_recorded_logs_still_read_and_show_a_strip():
    from pathlib import Path

    for path in [Path(__file__).resolve().parents[2] / "shared/data/px4-v1.18-sih/mission.jsonl"]:
        if not path.exists():
            pytest.skip(f"{path} is not here")
        log = read_mission_log(path)
        assert len(log.tel_status) == len(log.tel_t_s) > 0
        st = ViewState()
        for line in path.read_text().splitlines():
            st.apply(json.loads(line))
        h = st.frame()[0]["health"]
        assert h["alt_amsl_m"] == pytest.approx(log.tel_lla[-1, 2])


def test_the_target_line_judges_the_printed_bound_and_keeps_what_the_stop_judged(tmp_path):
    recs = write_mission(tmp_path / "m.jsonl")
    st = ViewState()
    for rec in recs:
        st.apply(rec)
        if rec["type"] == "event" and rec.get("kind") == "rtl":
            st.apply({"type": "event", "t": rec["t"], "message": "survey done: target reached", "kind": "stop"})
    f = st.frame()[0]
    target = f["target"]
    assert target["radius_m"] == 2.5 and target["users"] == 2
    # the same r95 the users table prints, judged r95 <= radius
    assert target["within"] == [u["id"] for u in f["users"] if u["located"] and u["r95_m"] <= 2.5]
    # the stop judged the estimate the survey ended on, not the final one shown after landing
    assert target["stop"]["r95_m"] == {"ue1": pytest.approx(ellipse_95([[2.0, 0.5], [0.5, 1.0]])["a_m"]),
                                       "ue2": pytest.approx(3.0 * math.sqrt(CHI2_2DOF_95))}
    assert f["users"][0]["r95_m"] == pytest.approx(ellipse_95([[0.5, 0.1], [0.1, 0.4]])["a_m"])


# -- a fleet ----------------------------------------------------------------------------------------

GOLDEN = Path(__file__).resolve().parent / "data" / "view_one_vehicle.json"


def _digest(frame: dict) -> str:
    return hashlib.sha256(json.dumps(frame, sort_keys=True).encode()).hexdigest()[:16]


@pytest.mark.parametrize("stream", ["mission", "no_flown_field"])
def test_a_one_vehicle_stream_gives_the_frames_of_before_fleets_with_its_vehicle_added(stream):
    """tests/data/view_one_vehicle.json: the frames the view of before fleets made after each record
    (events of every kind the fleet reads, a malformed status, the odometer without `flown_m`).
    Now: the same frames with `vehicles`, whose one entry is what the frame's vehicle fields say."""
    data = json.loads(GOLDEN.read_text())["streams"][stream]
    state = ViewState()
    for i, rec in enumerate(data["records"]):
        state.apply(rec)
        doc = state.frame()[0]
        (veh,) = doc.pop("vehicles")
        if str(i) in data["frames"]:
            assert doc == data["frames"][str(i)], i
        assert _digest(doc) == data["frame_sha256_16"][i], (i, rec)
        assert veh["vehicle"] == doc["vehicle"] and veh["waypoint"] == doc["waypoint"]
        assert veh["health"] == doc["health"]
        assert veh["index"] == 0 and veh["id"] == "vehicle 0" and veh["home_enu_m"] == [0.0, 0.0, 0.0]


FLEET = [{"id": "uav1", "home": lla(0, 0)}, {"id": "uav2", "home": lla(50, -20)}]


def fleet_records() -> list[dict]:
    """Two vehicles flying east and north from their homes, each ranging its own user, then uav2
    loses its link, returns and lands while uav1 surveys on; then uav1 returns and lands."""
    recs: list[dict] = [
        {"type": "header", "t": 0.0, "origin": ORIGIN.to_dict(), "users": USERS, "vehicles": FLEET,
         "config": {"controller": {"flight": {"target_radius_m": 3.0}, "safety": {"link_timeout_s": 2.0}}}},
        {"type": "event", "t": 0.5, "message": "armed", "kind": "arm", "state": "TAKEOFF"},
    ]
    for i in range(20):
        t = 1.0 + i
        recs.append({"type": "telemetry", "t": t, "vehicle": 0, **lla(2.0 * i, 0, 30),
                     **VehicleStatus(battery_pct=90.0 - i, flight_mode="OFFBOARD", armed=True).record_fields()})
        if i < 12:  # uav2's telemetry: none after its landing; absent vehicle field on none of these
            recs.append({"type": "telemetry", "t": t + 0.1, "vehicle": 1, **lla(50, -20 + 3.0 * i, 40),
                         **VehicleStatus(battery_pct=60.0 - 2 * i, flight_mode="OFFBOARD",
                                         armed=True).record_fields()})
        if i == 2:
            recs.append({"type": "waypoint", "t": t + 0.2, "vehicle": 0, "leg": 1, **lla(40, 0, 30)})
            recs.append({"type": "waypoint", "t": t + 0.3, "vehicle": 1, "leg": 1, **lla(50, 40, 40)})
        if i % 2 == 0:
            recs.append({"type": "rtt", "t": t + 0.05, "vehicle": 0, "user": "ue1", "uav": lla(0, 0, 30),
                         "toa_s": 2e-7})
            if i < 8:
                recs.append({"type": "rtt", "t": t + 0.06, "vehicle": 1, "user": "ue2", "uav": lla(0, 0, 30),
                             "toa_s": 2e-7})
        if i == 8:
            recs.append({"type": "event", "t": t + 0.4, "message": "vehicle link lost", "kind": "link_lost",
                         "vehicle": 1, "state": "RETURN"})
            recs.append({"type": "event", "t": t + 0.5, "message": "RTL: link lost", "kind": "rtl", "vehicle": 1,
                         "state": "RETURN"})
        if i == 9:
            recs.append({"type": "event", "t": t + 0.5, "message": "vehicle link restored", "kind": "link_restored",
                         "vehicle": 1})
        if i == 10:
            recs.append({"type": "estimate", "t": t + 0.5, "keyframes": 6, "users": [
                {"id": "ue1", **lla(40, 30), "cov_en_m2": [[4.0, 0.0], [0.0, 1.0]]}],
                "uav_lla": [list(lla(2.0 * j, 0, 30).values()) for j in range(3)]
                + [list(lla(50, -20 + 3.0 * j, 40).values()) for j in range(2)],
                "uav_vehicle": [0, 0, 0, 1, 1]})
        if i == 12:
            recs.append({"type": "event", "t": t + 0.5, "message": "landed", "kind": "landed", "vehicle": 1})
    recs += [{"type": "event", "t": 21.5, "message": "RTL: target reached", "kind": "rtl", "vehicle": 0},
             {"type": "event", "t": 25.0, "message": "landed", "kind": "landed", "vehicle": 0}]
    return recs


def _state_until(recs: list[dict], stop) -> ViewState:
    state = ViewState()
    for rec in recs:
        state.apply(rec)
        if stop(rec):
            break
    return state


def test_a_two_vehicle_stream_keeps_each_vehicles_track_leg_home_and_health():
    recs = fleet_records()
    state = _state_until(recs, lambda r: r["type"] == "rtt" and r["t"] > 8.0)  # t = 9.05, both surveying
    doc = state.frame()[0]
    assert doc["state"] == "SURVEY"
    v0, v1 = doc["vehicles"]
    assert (v0["id"], v1["id"]) == ("uav1", "uav2")
    np.testing.assert_allclose(v0["home_enu_m"], [0, 0, 0], atol=0.01)
    np.testing.assert_allclose(v1["home_enu_m"], [50, -20, 0], atol=0.01)
    # tracks: vehicle 1's items carry its index, vehicle 0's are as before
    track = doc["track"]["items"]
    mine = [p for p in track if len(p) == 4]
    theirs = [p for p in track if len(p) == 5]
    assert len(mine) == len(theirs) == 9 and {p[4] for p in theirs} == {1}
    np.testing.assert_allclose([p[1:4] for p in mine], [[2.0 * i, 0, 30] for i in range(9)], atol=0.01)
    np.testing.assert_allclose([p[1:4] for p in theirs], [[50, -20 + 3.0 * i, 40] for i in range(9)], atol=0.01)
    np.testing.assert_allclose(v0["vehicle"]["enu_m"], [16, 0, 30], atol=0.01)
    np.testing.assert_allclose(v1["vehicle"]["enu_m"], [50, 4, 40], atol=0.01)
    # each leg starts where its own vehicle was
    np.testing.assert_allclose(v0["waypoint"]["from_enu_m"], [4, 0, 30], atol=0.01)
    np.testing.assert_allclose(v0["waypoint"]["enu_m"], [40, 0, 30], atol=0.01)
    np.testing.assert_allclose(v1["waypoint"]["from_enu_m"], [50, -14, 40], atol=0.01)
    np.testing.assert_allclose(v1["waypoint"]["enu_m"], [50, 40, 40], atol=0.01)
    # health: each vehicle's own battery and its own gNB's measurements
    assert v0["health"]["battery_pct"] == 82.0 and v1["health"]["battery_pct"] == 44.0
    assert v0["health"]["measurements_per_min"] == 5 and v1["health"]["measurements_per_min"] == 4
    assert doc["measurements"] == 9
    assert [u["measurements"] for u in doc["users"]] == [5, 4]
    assert not any(v["returning"] or v["landed"] or v["link_lost"] for v in (v0, v1))
    # the frame's own vehicle fields are vehicle 0's
    assert doc["vehicle"] == v0["vehicle"] and doc["health"] == v0["health"] and doc["waypoint"] == v0["waypoint"]


def test_one_vehicle_returning_and_landing_leaves_the_mission_surveying_until_every_one_does():
    recs = fleet_records()
    after = lambda kind, k: lambda r: r.get("kind") == kind and r.get("vehicle") == k  # noqa: E731
    doc = _state_until(recs, after("link_lost", 1)).frame()[0]
    assert doc["vehicles"][1]["link_lost"] and doc["state"] == "SURVEY"  # the vehicle's state is not the mission's
    doc = _state_until(recs, after("rtl", 1)).frame()[0]
    v0, v1 = doc["vehicles"]
    assert v1["returning"] and v1["link_lost"] and v1["waypoint"] is None
    assert not v0["returning"] and v0["waypoint"] is not None and doc["state"] == "SURVEY"
    assert doc["events"]["items"][-1]["vehicle"] == 1
    doc = _state_until(recs, after("landed", 1)).frame()[0]
    v0, v1 = doc["vehicles"]
    assert v1["landed"] and not v1["returning"] and not v1["link_lost"] and doc["state"] == "SURVEY"
    doc = _state_until(recs, after("rtl", 0)).frame()[0]
    assert doc["state"] == "RETURN" and doc["vehicles"][0]["returning"]
    doc = _state_until(recs, lambda r: False).frame()[0]
    assert doc["state"] == "LANDED" and all(v["landed"] for v in doc["vehicles"])
    # uav2 went silent at its landing (12.1 s): stale at the end, uav1 fresh until 20 s
    v0, v1 = doc["vehicles"]
    assert v1["health"]["vehicle_stale"] and v1["health"]["vehicle_age_s"] == pytest.approx(25.0 - 12.1)
    assert v0["health"]["vehicle_age_s"] == pytest.approx(5.0)


def test_the_estimated_track_names_each_keyframes_vehicle():
    recs = fleet_records()
    doc = _state_until(recs, lambda r: r["type"] == "estimate").frame()[0]
    items = doc["est_track"]["items"]
    assert [len(p) for p in items] == [3, 3, 3, 4, 4] and items[3][3] == items[4][3] == 1
    np.testing.assert_allclose(items[4][:3], [50, -17, 40], atol=0.01)


def test_the_fleets_metres_without_the_field_are_every_vehicles_odometer():
    recs = [r for r in fleet_records() if r["type"] != "estimate"]
    doc = _state_until(recs, lambda r: r["type"] == "telemetry" and r["t"] == 11.0).frame()[0]
    # from their legs' starts, in steps of at least the 5 m dead band: uav1 4 -> 16 m east in 2 m
    # fixes (12 m counted), uav2 -14 -> 4 m north in 3 m fixes (18 m counted)
    assert doc["flown_m"] == pytest.approx(12.0 + 18.0, abs=0.01)


@pytest.mark.parametrize("odd", [
    {"type": "telemetry", "t": 2.0, "vehicle": 3, **lla(5, 5, 10)},
    {"type": "rtt", "t": 2.0, "vehicle": 2, "user": "ue1", "uav": lla(0, 0), "toa_s": 2e-7},
    {"type": "event", "t": 2.0, "vehicle": 4, "message": "vehicle link lost", "kind": "link_lost"},
    {"type": "waypoint", "t": 2.0, "vehicle": 2, "leg": 1, **lla(5, 5, 10)},
    {"type": "estimate", "t": 2.0, "users": [], "uav_lla": [list(lla(0, 0).values())], "uav_vehicle": [5]},
])
def test_a_vehicle_the_header_did_not_list_is_added_not_raised(odd):
    state = ViewState()
    state.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS, "vehicles": FLEET})
    state.apply(odd)
    doc = state.frame()[0]
    k = max(odd.get("vehicle", 0), *odd.get("uav_vehicle", [0]))
    assert [v["id"] for v in doc["vehicles"]] == ["uav1", "uav2"] + [f"vehicle {j}" for j in range(2, k + 1)]
    assert doc["vehicles"][-1]["home_enu_m"] is None and state.records == 2
    json.dumps(doc)


@pytest.mark.parametrize("odd", [
    {"type": "telemetry", "t": 2.0, "vehicle": -1, **lla(5, 5, 10)},
    {"type": "telemetry", "t": 2.0, "vehicle": "1", **lla(5, 5, 10)},
    {"type": "telemetry", "t": 2.0, "vehicle": True, **lla(5, 5, 10)},
    {"type": "telemetry", "t": 2.0, "vehicle": 10**9, **lla(5, 5, 10)},
    {"type": "rtt", "t": 2.0, "vehicle": 1.5, "user": "ue1"},
    {"type": "event", "t": 2.0, "vehicle": None, "message": "x", "kind": "rtl"},
    {"type": "estimate", "t": 2.0, "users": [], "uav_lla": [list(lla(0, 0).values())], "uav_vehicle": [0, 1]},
    {"type": "estimate", "t": 2.0, "users": [], "uav_lla": [list(lla(0, 0).values())], "uav_vehicle": ["a"]},
    {"type": "estimate", "t": 2.0, "users": [], "uav_lla": [list(lla(0, 0).values())], "uav_vehicle": 3},
])
def test_a_vehicle_that_is_no_index_skips_the_record(odd):
    state = ViewState()
    state.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS, "vehicles": FLEET})
    state.apply(odd)
    doc = state.frame()[0]
    assert len(doc["vehicles"]) == 2 and doc["track"]["items"] == [] and doc["est_track"]["items"] == []
    assert doc["measurements"] == 0 and doc["events"]["items"] == [] and state.records == 1


@pytest.mark.parametrize("vehicles", [
    "uav1", [], [None, {"id": "b"}], [{"id": "a", "home": {"lat_deg": "x"}}, {"home": lla(1, 1)}], [{"id": True}]])
def test_an_odd_vehicles_list_in_the_header_names_what_it_can(vehicles):
    state = ViewState()
    state.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS, "vehicles": vehicles})
    state.apply({"type": "telemetry", "t": 1.0, **lla(1, 1, 10)})
    doc = state.frame()[0]
    assert doc["vehicles"] and doc["vehicles"][0]["vehicle"] is not None and len(doc["track"]["items"]) == 1
    json.dumps(doc)


def test_the_timeline_of_a_fleet_gives_the_same_state_from_any_checkpoint():
    recs = fleet_records()
    tl = Timeline(recs, checkpoint_every=5)
    for t in [25.0, 3.0, 9.5, 13.7, 2.0, 25.0]:
        got = tl.state_at(t).frame()[0]
        fresh = Timeline(recs).state_at(t).frame()[0]
        assert json.dumps(got, sort_keys=True) == json.dumps(fresh, sort_keys=True)
