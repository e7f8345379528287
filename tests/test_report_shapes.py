"""The log header's geofence, no-fly zones, altitude band and buildings in the report's exports:
GeoJSON, KML, and a QGroundControl `.plan` whose fence MAVSDK reads and the real PX4 SITL accepts."""

from __future__ import annotations

import asyncio
import json
import logging
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from mission.report import MissionShapes, inputs_from_replay, shapes_from_header, write_report
from mission.report.exports import geojson_document, kml_document, plan_from_inputs
from mission.report.inputs import shapes_from_log
from tests.test_export import _mavsdk_import
from tests.test_report import ORIGIN, make_inputs

KML = "{http://www.opengis.net/kml/2.2}"


def _ring(en_m) -> list[list[float]]:
    """[[lat, lon], ...] of east-north offsets [m] from ORIGIN."""
    en = np.asarray(en_m, float)
    lat, lon, _ = ORIGIN.enu_to_lla(np.c_[en, np.zeros(len(en))])
    return [[float(a), float(o)] for a, o in zip(lat, lon, strict=True)]


# a clockwise fence (the exports must turn it counter-clockwise for GeoJSON), a no-fly zone, a building
FENCE_EN = [[-150, -150], [-150, 200], [200, 200], [200, -150]]
ZONE_EN = [[60, -40], [90, -40], [90, -10], [60, -10]]
BUILDING_EN = [[-80, 105], [-45, 105], [-45, 118], [-80, 118]]
HEADER = {
    "geofence": _ring(FENCE_EN),
    "no_fly_zones": [_ring(ZONE_EN)],
    "altitude_band_m": {"min_m": 20.0, "max_m": 80.0},
    "buildings": [{"footprint": _ring(BUILDING_EN), "height_m": 14.0}],
}


def inputs_with_shapes():
    return replace(make_inputs(), shapes=shapes_from_header(HEADER))


def test_header_shapes_are_read_and_absent_ones_are_fine():
    sh = shapes_from_header(HEADER)
    np.testing.assert_allclose(sh.geofence_lat_lon_deg, HEADER["geofence"])
    assert len(sh.no_fly_lat_lon_deg) == 1 and sh.altitude_band_m == (20.0, 80.0)
    assert sh.buildings[0].height_m == 14.0
    assert shapes_from_header({}) == MissionShapes()


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("geofence", [[43.6, 7.0], [43.7, 7.0]], ">= 3"),
        ("geofence", [[143.6, 7.0], [43.7, 7.0], [43.7, 7.1]], "latitude beyond 90"),
        ("no_fly_zones", [[[1, 2], [1, "x"], [2, 2]]], "could not convert"),
        ("altitude_band_m", {"min_m": 80, "max_m": 20}, "min_m <= max_m"),
        ("altitude_band_m", {"min_m": 20}, "max_m"),
        ("buildings", [{"footprint": _ring(BUILDING_EN), "height_m": -3}], "height_m must be positive"),
    ],
)
def test_a_malformed_header_shape_is_left_out_with_a_warning_naming_it(caplog, field, value, words):
    with caplog.at_level(logging.WARNING, logger="mission.report.inputs"):
        sh = shapes_from_header({**HEADER, field: value})
    assert any(field in r.getMessage() and words in r.getMessage() for r in caplog.records), caplog.text
    assert sh.altitude_band_m is None if field == "altitude_band_m" else sh.altitude_band_m == (20.0, 80.0)


def test_shapes_come_from_the_log_file_header(tmp_path):
    from mission.log import read_mission_log

    path = tmp_path / "m.jsonl"
    header = {"type": "header", "t": 0, "format": "uavloc-mission/1", "start_utc": "2026-12-01T00:00:00Z",
              "origin": ORIGIN.to_dict(), "users": [{"id": "ue1", "rnti": 17921, "ground_alt_m": 488.0}],
              "radio": {"mu": 1, "fs_hz": 46.08e6}, **HEADER}
    path.write_text(json.dumps(header) + "\n", encoding="utf-8")
    sh = shapes_from_log(read_mission_log(path))
    np.testing.assert_allclose(sh.no_fly_lat_lon_deg[0], HEADER["no_fly_zones"][0])
    assert sh.altitude_band_m == (20.0, 80.0)


def test_geojson_carries_fence_zones_buildings_as_closed_ccw_polygons():
    doc = geojson_document(inputs_with_shapes())
    by_kind = {}
    for f in doc["features"]:
        by_kind.setdefault(f["properties"]["kind"], []).append(f)
    assert len(by_kind["geofence"]) == len(by_kind["no_fly_zone"]) == len(by_kind["building"]) == 1
    assert by_kind["geofence"][0]["properties"]["altitude_band_m"] == {"min_m": 20.0, "max_m": 80.0}
    assert doc["properties"]["altitude_band_m"] == {"min_m": 20.0, "max_m": 80.0}
    assert by_kind["building"][0]["properties"]["height_m"] == 14.0
    assert by_kind["no_fly_zone"][0]["properties"]["inclusion"] is False
    for kind, src in (("geofence", FENCE_EN), ("no_fly_zone", ZONE_EN), ("building", BUILDING_EN)):
        (ring,) = by_kind[kind][0]["geometry"]["coordinates"]
        a = np.asarray(ring)
        assert ring[0] == ring[-1] and len(ring) == len(src) + 1
        assert 0.5 * np.sum(a[:-1, 0] * a[1:, 1] - a[1:, 0] * a[:-1, 1]) > 0  # counter-clockwise
        en = ORIGIN.lla_to_enu(a[:, 1], a[:, 0], np.full(len(a), ORIGIN.alt_m))[:-1, :2]
        assert {tuple(np.round(p, 2)) for p in en} == {tuple(map(float, p)) for p in src}


def test_geojson_without_shapes_has_none():
    kinds = {f["properties"]["kind"] for f in geojson_document(make_inputs())["features"]}
    assert not kinds & {"geofence", "no_fly_zone", "building"}


def test_kml_has_the_fence_the_zone_and_an_extruded_building():
    root = ET.fromstring(kml_document(inputs_with_shapes()))
    marks = {p.findtext(f"{KML}name"): p for p in root.iter(f"{KML}Placemark")}
    assert {"geofence", "no-fly zone 0", "building 0"} <= set(marks)
    assert "20..80 m above home" in marks["geofence"].findtext(f"{KML}description")
    b = marks["building 0"].find(f"{KML}Polygon")
    assert b.findtext(f"{KML}extrude") == "1" and b.findtext(f"{KML}altitudeMode") == "relativeToGround"
    heights = {float(c.split(",")[2]) for c in b.find(f".//{KML}coordinates").text.split()}
    assert heights == {14.0}


def test_plan_fence_is_inclusion_and_no_fly_is_exclusion_and_mavsdk_reads_both():
    plan = plan_from_inputs(inputs_with_shapes())
    polys = plan["geoFence"]["polygons"]
    assert [p["inclusion"] for p in polys] == [True, False]
    np.testing.assert_allclose(polys[0]["polygon"], HEADER["geofence"], atol=1e-8)
    np.testing.assert_allclose(polys[1]["polygon"], HEADER["no_fly_zones"][0], atol=1e-8)
    data = _mavsdk_import(json.dumps(plan))
    fence = data.geofence_items
    cmds = [it.command for it in fence]
    assert cmds == ([mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION] * 4
                    + [mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION] * 4)
    assert all(it.param1 == 4 for it in fence)  # vertex count of its polygon
    got = np.array([[it.x / 1e7, it.y / 1e7] for it in fence])
    np.testing.assert_allclose(got, HEADER["geofence"] + HEADER["no_fly_zones"][0], atol=2e-7)


def test_report_of_a_replayed_log_exports_the_header_fence(tmp_path):
    """End to end through replay: a log whose header carries the shapes → mission.plan with them."""
    from mission.log import read_mission_log
    from mission.replay import ReplayOptions, replay

    rng = np.random.default_rng(4)
    user = np.array([40.0, 30.0, 0.0])
    lines = [{"type": "header", "t": 0, "format": "uavloc-mission/1", "start_utc": "2026-12-01T00:00:00Z",
              "origin": ORIGIN.to_dict(), "users": [{"id": "ue1", "rnti": 17921, "ground_alt_m": ORIGIN.alt_m}],
              "radio": {"mu": 1, "fs_hz": 46.08e6}, **HEADER}]
    for i, a in enumerate(np.linspace(0, 2 * np.pi, 120)):
        p = np.array([80 * np.cos(a), 80 * np.sin(a), 40.0])
        lat, lon, alt = ORIGIN.enu_to_lla(p + rng.normal(0, 1, 3))
        uav = {"lat_deg": float(lat), "lon_deg": float(lon), "alt_m": float(alt)}
        lines.append({"type": "telemetry", "t": i * 0.5, **uav})
        d = np.linalg.norm(p - user) + rng.normal(0, 3)
        lines.append({"type": "rtt", "t": i * 0.5, "user": "ue1", "uav": uav, "toa_s": d / 299_792_458.0})
    path = tmp_path / "m.jsonl"
    path.write_text("".join(json.dumps(x) + "\n" for x in lines), encoding="utf-8")
    inp = inputs_from_replay(replay(read_mission_log(path), ReplayOptions(history=False)))
    assert inp.shapes.altitude_band_m == (20.0, 80.0)
    paths = write_report(inp, tmp_path / "out", figures=("top_view",))
    plan = json.loads(Path(paths["plan"]).read_text())
    assert [p["inclusion"] for p in plan["geoFence"]["polygons"]] == [True, False]


# ---------------------------------------------------------------------------------------------
# the real PX4 SITL takes the exported fence through MAVSDK's Geofence plugin

@pytest.mark.px4
def test_exported_plan_fence_uploads_to_px4_as_inclusion_and_exclusion_polygons(px4):
    """The `px4` fixture (tests/conftest.py) starts a working copy of ../shared/px4-sitl."""
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.geofence import GeofenceAsync
    from mavsdk.plugins.geofence.geofence import FenceType, GeofenceData, Point, Polygon

    # PX4's home is near Zurich: the plan's fence is drawn about that origin
    plan = plan_from_inputs(inputs_with_shapes())
    polygons = [Polygon([Point(lat, lon) for lat, lon in p["polygon"]],
                        FenceType.INCLUSION if p["inclusion"] else FenceType.EXCLUSION)
                for p in plan["geoFence"]["polygons"]]

    async def run():
        async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as m:
            await m.add_any_connection(px4.api_url)
            system = await m.first_autopilot(timeout_s=30.0)
            assert system is not None, "no autopilot on " + px4.api_url
            fence = GeofenceAsync(system)
            await fence.upload_geofence(GeofenceData(polygons, []))
            return await fence.download_geofence()

    back = asyncio.run(run())
    assert [p.fence_type for p in back.polygons] == [FenceType.INCLUSION, FenceType.EXCLUSION]
    for sent, got in zip(plan["geoFence"]["polygons"], back.polygons, strict=True):
        pts = np.array([[q.latitude_deg, q.longitude_deg] for q in got.points])
        np.testing.assert_allclose(pts, sent["polygon"], atol=2e-7)  # MAVLink carries 1e-7 deg
