"""Exports: GeoJSON structure and coordinates, KML parses, and the real mavsdk library loads the plan."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from estimator.types import CHI2_2DOF_95
from mission.report.exports import (
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
    geojson_document,
    kml_document,
    plan_from_inputs,
    qgc_plan,
    simplify_track_m,
    write_exports,
)
from tests.test_report import ORIGIN, make_inputs


def test_geojson_is_a_feature_collection_with_lon_lat_order(tmp_path):
    inp = make_inputs()
    paths = write_exports(inp, tmp_path)
    doc = json.loads(paths["geojson"].read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON number {c}"))
    assert doc["type"] == "FeatureCollection"
    kinds = [f["properties"]["kind"] for f in doc["features"]]
    assert kinds.count("user_estimate") == 2
    assert kinds.count("error_ellipse_95") == 2
    assert kinds.count("user_truth") == 2
    assert {"gps_track", "estimated_uav_track"} <= set(kinds)
    for f in doc["features"]:
        assert f["type"] == "Feature"
        assert f["geometry"]["type"] in ("Point", "LineString", "Polygon")
    est = [f for f in doc["features"] if f["properties"]["kind"] == "user_estimate"]
    lat, lon, alt = ORIGIN.enu_to_lla(inp.users_enu_m)
    for k, f in enumerate(est):
        lo, la, al = f["geometry"]["coordinates"]  # RFC 7946: longitude first
        assert lo == pytest.approx(float(lon[k]), abs=1e-8)
        assert la == pytest.approx(float(lat[k]), abs=1e-8)
        assert al == pytest.approx(float(alt[k]), abs=1e-3)
        assert f["properties"]["sigma_east_m"] == pytest.approx(np.sqrt(inp.cov_en_m2[k][0, 0]), abs=1e-4)
        assert f["properties"]["sigma_north_m"] == pytest.approx(np.sqrt(inp.cov_en_m2[k][1, 1]), abs=1e-4)
    # user 1 is 40 m east and 10 m north of the origin: a longitude east of it, a latitude a bit north
    lo, la, _ = est[0]["geometry"]["coordinates"]
    assert lo > ORIGIN.lon_deg and la > ORIGIN.lat_deg
    track = next(f for f in doc["features"] if f["properties"]["kind"] == "gps_track")
    assert len(track["geometry"]["coordinates"]) == len(inp.kf_gps_enu_m)


def test_geojson_ellipses_are_closed_ccw_95_percent_rings():
    inp = make_inputs()
    doc = geojson_document(inp)
    rings = [f for f in doc["features"] if f["properties"]["kind"] == "error_ellipse_95"]
    for k, f in enumerate(rings):
        (ring,) = f["geometry"]["coordinates"]
        assert ring[0] == ring[-1] and len(ring) >= 4
        a = np.array(ring)
        lo, la = a[:, 0], a[:, 1]
        assert 0.5 * np.sum(lo[:-1] * la[1:] - lo[1:] * la[:-1]) > 0  # counter-clockwise (RFC 7946 §3.1.6)
        enu = ORIGIN.lla_to_enu(a[:, 1], a[:, 0], a[:, 2])
        rel = enu[:, :2] - inp.users_enu_m[k, :2]
        m2 = np.einsum("ij,jk,ik->i", rel, np.linalg.inv(inp.cov_en_m2[k]), rel)
        np.testing.assert_allclose(m2, CHI2_2DOF_95, rtol=1e-3)


def test_kml_parses_and_has_placemarks_with_lon_lat_alt(tmp_path):
    inp = make_inputs()
    paths = write_exports(inp, tmp_path)
    root = ET.parse(paths["kml"]).getroot()
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    assert root.tag == "{http://www.opengis.net/kml/2.2}kml"
    names = [p.findtext("k:name", namespaces=ns) for p in root.iter("{http://www.opengis.net/kml/2.2}Placemark")]
    assert "ue1 (estimate)" in names and "ue2 95 % ellipse" in names and "GPS track" in names
    pm = next(p for p in root.iter("{http://www.opengis.net/kml/2.2}Placemark")
              if p.findtext("k:name", namespaces=ns) == "ue1 (estimate)")
    lo, la, al = (float(x) for x in pm.find(".//k:coordinates", ns).text.split(","))
    lat, lon, alt = ORIGIN.enu_to_lla(inp.users_enu_m[0])
    assert (lo, la) == pytest.approx((float(lon), float(lat)), abs=1e-8)
    assert al == pytest.approx(float(alt), abs=1e-3)
    assert kml_document(inp) == paths["kml"].read_text()


def test_simplify_keeps_every_dropped_point_within_tolerance():
    rng = np.random.default_rng(5)
    track = np.cumsum(rng.normal(0, 3, (400, 3)), axis=0)
    kept = simplify_track_m(track, 2.0)
    assert 2 < len(kept) < len(track)
    assert np.array_equal(kept[0], track[0]) and np.array_equal(kept[-1], track[-1])
    # every original point lies within 2 m of the kept polyline
    seg_a, seg_b = kept[:-1], kept[1:]
    for p in track:
        v = seg_b - seg_a
        s = np.clip(np.einsum("ij,ij->i", p - seg_a, v) / np.maximum(np.einsum("ij,ij->i", v, v), 1e-12), 0, 1)
        assert np.min(np.linalg.norm(p - (seg_a + s[:, None] * v), axis=1)) <= 2.0 + 1e-9
    line = np.c_[np.linspace(0, 100, 50), np.zeros(50), np.full(50, 30.0)]
    assert len(simplify_track_m(line, 0.1)) == 2


def test_plan_has_the_qgc_structure():
    plan = qgc_plan(np.array([[47.4, 8.55, 520.0], [47.401, 8.551, 525.0]]), (47.3977, 8.5456, 488.0),
                    geofence_circle=(47.3977, 8.5456, 300.0))
    assert plan["fileType"] == "Plan" and plan["version"] == 1
    assert plan["mission"]["version"] == 2
    assert set(plan["geoFence"]) >= {"circles", "polygons", "version"}
    assert set(plan["rallyPoints"]) >= {"points", "version"}
    cmds = [it["command"] for it in plan["mission"]["items"]]
    assert cmds == [MAV_CMD_NAV_TAKEOFF, MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_RETURN_TO_LAUNCH]
    wp = plan["mission"]["items"][1]
    assert wp["frame"] == 0 and wp["AltitudeMode"] == 2 and wp["Altitude"] == 520.0 and wp["params"][6] == 520.0


def _mavsdk_import(plan_text: str):
    """Import a plan with the real MAVSDK library: a raw:// connection fed one PX4 heartbeat gives
    a System offline (no vehicle, no socket) on which MissionRaw can import."""
    mavsdk = pytest.importorskip("mavsdk")
    from mavsdk.component_type import ComponentType
    from mavsdk.mavsdk import Configuration, Mavsdk
    from mavsdk.plugins.mission_raw import MissionRaw
    from pymavlink.dialects.v20 import common as mav

    del mavsdk
    m = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        m.add_any_connection("raw://")
        link = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        hb = link.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 0, 0, mav.MAV_STATE_STANDBY)
        m.pass_received_raw_bytes(bytes(hb.pack(link)))
        system = m.first_autopilot(5.0)
        assert system is not None, "MAVSDK did not see the heartbeat"
        return MissionRaw(system).import_qgroundcontrol_mission_from_string(plan_text)
    finally:
        m.destroy()


def test_mavsdk_imports_the_plan_of_a_flown_track_with_amsl_altitudes(tmp_path):
    inp = make_inputs()
    paths = write_exports(inp, tmp_path)
    text = paths["plan"].read_text()
    plan = json.loads(text)
    data = _mavsdk_import(text)
    items = data.mission_items
    assert len(items) == len(plan["mission"]["items"]) >= 4
    assert items[0].command == MAV_CMD_NAV_TAKEOFF and items[-1].command == MAV_CMD_NAV_RETURN_TO_LAUNCH
    wps = [it for it in items if it.command == MAV_CMD_NAV_WAYPOINT]
    for it, src in zip(wps, [i for i in plan["mission"]["items"] if i["command"] == MAV_CMD_NAV_WAYPOINT], strict=True):
        assert it.frame == 0  # MAV_FRAME_GLOBAL: altitude AMSL
        assert abs(it.x - src["params"][4] * 1e7) <= 1 and abs(it.y - src["params"][5] * 1e7) <= 1  # 1e-7 deg
        assert it.z == pytest.approx(src["params"][6], abs=1e-3)
    # the flown circle is 30 m above an origin at 488 m AMSL: 518 m AMSL in the plan
    assert np.median([it.z for it in wps]) == pytest.approx(ORIGIN.alt_m + 30.0, abs=0.5)
    assert [it.seq for it in items] == list(range(len(items)))


def test_mavsdk_rejects_a_broken_plan():
    from mavsdk.plugins.mission_raw import MissionRawError

    with pytest.raises(MissionRawError):
        _mavsdk_import('{"fileType": "Plan", "version": 1}')


def test_plan_prefers_logged_waypoints():
    from dataclasses import replace

    wps = np.array([[10.0, 0.0, 30.0], [10.0, 20.0, 35.0], [-5.0, 20.0, 40.0]])
    plan = plan_from_inputs(replace(make_inputs(), waypoints_enu_m=wps), takeoff=False, return_to_launch=False)
    items = plan["mission"]["items"]
    assert len(items) == 3
    lat, lon, alt = ORIGIN.enu_to_lla(wps)
    assert [it["params"][6] for it in items] == pytest.approx(list(alt), abs=0.01)
    assert [it["params"][4] for it in items] == pytest.approx(list(lat), abs=1e-8)
    assert [it["params"][5] for it in items] == pytest.approx(list(lon), abs=1e-8)
