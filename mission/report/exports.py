"""Exports of a mission result for GIS tools and ground stations.

- GeoJSON (RFC 7946): a FeatureCollection in WGS-84 with positions [lon, lat, alt] (longitude
  first). Users are Points carrying σ_east, σ_north, the 95 % bound and the covariance; their 95 %
  error ellipses are Polygons (closed, counter-clockwise exterior rings, RFC 7946 §3.1.6); the GPS
  track, the estimated UAV track and the waypoints are LineStrings; true users (simulation) are
  Points too. Every feature has a `kind` property.
- KML 2.2: the same as Placemarks (tracks with altitudeMode absolute, ellipses clamped to ground).
- QGroundControl `.plan` (JSON, fileType "Plan", version 1, mission version 2, with geoFence and
  rallyPoints): waypoints as SimpleItems in MAV_FRAME_GLOBAL (altitude AMSL) with QGC's
  AltitudeMode 2 (absolute), which MAVSDK's `import_qgroundcontrol_mission` accepts; the log's
  geofence as a geoFence polygon with `inclusion: true`, its no-fly zones with `inclusion: false`.

The log header's shapes (:class:`mission.report.inputs.MissionShapes`: geofence, no-fly zones,
altitude band, buildings) appear in all three when present: GeoJSON Polygons of kind `geofence`,
`no_fly_zone`, `building` (with `height_m`; the altitude band is a property of the fence and of
the collection), KML Placemarks (buildings extruded to their height). MAVLink numbers are
pymavlink's enums.

Input is a :class:`mission.report.ReportInputs` (ENU about its origin) or plain arrays.
"""

from __future__ import annotations

import json
import logging
import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from estimator.geodesy import Origin
from mission.report.inputs import MissionShapes, ReportInputs
from mission.report.statistics import ellipse_en_m
from uavloc.errors import MissionError

log = logging.getLogger(__name__)

#: decimals of degrees written (1e-8 deg ≈ 1.1 mm) and of metres
DEG_DECIMALS = 8
M_DECIMALS = 3

# MAVLink numbers used in a plan (pymavlink's common dialect)
MAV_CMD_NAV_WAYPOINT = mavlink.MAV_CMD_NAV_WAYPOINT
MAV_CMD_NAV_RETURN_TO_LAUNCH = mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH
MAV_CMD_NAV_TAKEOFF = mavlink.MAV_CMD_NAV_TAKEOFF
MAV_FRAME_GLOBAL = mavlink.MAV_FRAME_GLOBAL  # altitude AMSL
MAV_FRAME_MISSION = mavlink.MAV_FRAME_MISSION
MAV_AUTOPILOT_PX4 = mavlink.MAV_AUTOPILOT_PX4
MAV_TYPE_QUADROTOR = mavlink.MAV_TYPE_QUADROTOR
#: QGroundControl's AltMode enum: 0 mixed, 1 relative, 2 absolute (AMSL), 3 calc. above terrain, 4 terrain frame
QGC_ALT_MODE_ABSOLUTE = 2


def _lonlatalt(origin: Origin, enu_m: np.ndarray) -> list[list[float]]:
    """(P, 3) ENU -> [[lon, lat, alt], ...] rounded (RFC 7946 order)."""
    lat, lon, alt = origin.enu_to_lla(np.asarray(enu_m, float).reshape(-1, 3))
    return [[round(float(lo), DEG_DECIMALS), round(float(la), DEG_DECIMALS), round(float(al), M_DECIMALS)]
            for la, lo, al in zip(np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(alt), strict=True)]


def _num(x: Any, nd: int = 4) -> float | None:
    v = float(x)
    return round(v, nd) if math.isfinite(v) else None


def _ellipse_ring_enu(center: np.ndarray, cov: np.ndarray, n: int = 72) -> np.ndarray:
    """(n + 1, 3) closed ring of the 95 % ellipse at the centre's height."""
    ring = ellipse_en_m(center, cov, n=n)
    return np.c_[ring, np.full(len(ring), float(center[2]))]


def _user_stats(inp: ReportInputs, k: int) -> dict:
    """The export properties of user k: the result's entry (mission.result.UserResult), rounded."""
    u = inp.result.users[k]
    cov = u.cov_en_m2
    props = {
        "id": u.id,
        "sigma_east_m": _num_or_none(u.sigma_east_m),
        "sigma_north_m": _num_or_none(u.sigma_north_m),
        "cov_en_m2": None if cov is None else [[_num(cov[i][j], 6) for j in range(2)] for i in range(2)],
        "error_bound_95_m": _num_or_none(u.error_bound_95_m),
    }
    if u.bias_m is not None:
        props["bias_m"] = _num_or_none(u.bias_m)
    if u.ambiguous is not None:
        props["ambiguous"] = u.ambiguous
    if u.truth is not None:
        props["error_m"] = _num_or_none(u.error_m)
    return props


def _num_or_none(x: float | None, nd: int = 4) -> float | None:
    return None if x is None else _num(x, nd)


def _ring_lonlat(ring_lat_lon_deg: np.ndarray, ccw: bool = True) -> list[list[float]]:
    """Closed [[lon, lat], ...] ring of an open (P, 2) lat/lon ring, counter-clockwise (RFC 7946
    §3.1.6 exterior) when `ccw`."""
    lonlat = [[round(float(lo), DEG_DECIMALS), round(float(la), DEG_DECIMALS)] for la, lo in ring_lat_lon_deg]
    a = np.asarray(lonlat)
    # shoelace: twice the signed area, > 0 for counter-clockwise (lon east, lat north)
    area2 = float(np.sum(a[:, 0] * np.roll(a[:, 1], -1) - np.roll(a[:, 0], -1) * a[:, 1]))
    if ccw and area2 < 0:
        lonlat = lonlat[::-1]
    return [*lonlat, lonlat[0]]


def _shape_features(shapes: MissionShapes) -> list[dict]:
    """GeoJSON Features of the geofence, the no-fly zones and the buildings."""
    feats = []
    band = shapes.altitude_band_m
    band_props = {} if band is None else {"altitude_band_m": {"min_m": band[0], "max_m": band[1]}}
    if shapes.geofence_lat_lon_deg is not None:
        feats.append({"type": "Feature",
                      "geometry": {"type": "Polygon", "coordinates": [_ring_lonlat(shapes.geofence_lat_lon_deg)]},
                      "properties": {"kind": "geofence", "inclusion": True, **band_props}})
    for i, zone in enumerate(shapes.no_fly_lat_lon_deg):
        feats.append({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [_ring_lonlat(zone)]},
                      "properties": {"kind": "no_fly_zone", "index": i, "inclusion": False}})
    for i, b in enumerate(shapes.buildings):
        feats.append({"type": "Feature",
                      "geometry": {"type": "Polygon", "coordinates": [_ring_lonlat(b.footprint_lat_lon_deg)]},
                      "properties": {"kind": "building", "index": i, "height_m": b.height_m}})
    return feats


# ---------------------------------------------------------------------------------------------
# GeoJSON


def geojson_document(inp: ReportInputs) -> dict:
    """RFC 7946 FeatureCollection of the users (estimate, 95 % ellipse, truth) and the tracks."""
    feats: list[dict] = []
    for k, uid in enumerate(inp.user_ids):
        u = inp.users_enu_m[k]
        if not np.all(np.isfinite(u)):
            continue
        stats = _user_stats(inp, k)
        feats.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": _lonlatalt(inp.origin, u)[0]},
                      "properties": {"kind": "user_estimate", **stats}})
        if stats["cov_en_m2"] is not None:
            ring = _lonlatalt(inp.origin, _ellipse_ring_enu(u, inp.cov_en_m2[k]))
            ring[-1] = ring[0]
            feats.append({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [ring]},
                          "properties": {"kind": "error_ellipse_95", "id": uid,
                                         "error_bound_95_m": stats["error_bound_95_m"]}})
    if inp.truth_enu_m is not None:
        for k, uid in enumerate(inp.user_ids):
            t = inp.truth_enu_m[k]
            if np.all(np.isfinite(t)):
                geom = {"type": "Point", "coordinates": _lonlatalt(inp.origin, t)[0]}
                feats.append({"type": "Feature", "geometry": geom, "properties": {"kind": "user_truth", "id": uid}})
    fleet = len(inp.vehicles()) > 1
    for v in inp.vehicles():  # a fleet's tracks: one line per vehicle, each naming its vehicle
        tracks = [("gps_track", inp.track_enu_m(v)), ("estimated_uav_track", inp.uav_track_enu_m(v)),
                  ("waypoints", inp.waypoints_of(v))]
        for kind, pts in tracks:
            if pts is not None and len(pts) >= 2:
                geom = {"type": "LineString", "coordinates": _lonlatalt(inp.origin, pts)}
                props = {"kind": kind, "points": len(pts), **({"vehicle": v} if fleet else {})}
                feats.append({"type": "Feature", "geometry": geom, "properties": props})
    feats += _shape_features(inp.shapes)
    props = {"title": inp.title, "status": inp.result.status, "flown_m": _num(inp.result.flown_m, 1)}
    if inp.shapes.altitude_band_m is not None:
        props["altitude_band_m"] = {"min_m": inp.shapes.altitude_band_m[0], "max_m": inp.shapes.altitude_band_m[1]}
    return {"type": "FeatureCollection", "features": feats, "properties": props}


def write_geojson(inp: ReportInputs, path: str | Path) -> Path:
    """Write :func:`geojson_document` to `path`."""
    return _write_text(path, json.dumps(geojson_document(inp), allow_nan=False) + "\n")


# ---------------------------------------------------------------------------------------------
# KML

KML_NS = "http://www.opengis.net/kml/2.2"


def _kml_coords(coords: list[list[float]]) -> str:
    return " ".join(f"{lo:.{DEG_DECIMALS}f},{la:.{DEG_DECIMALS}f},{al:.{M_DECIMALS}f}" for lo, la, al in coords)


def kml_document(inp: ReportInputs) -> str:
    """KML 2.2 text: a Document with users, ellipses (clamped to ground) and tracks (absolute)."""
    ET.register_namespace("", KML_NS)
    kml = ET.Element(f"{{{KML_NS}}}kml")
    doc = ET.SubElement(kml, "Document")
    ET.SubElement(doc, "name").text = inp.title
    for sid, color, width in (("track", "ff999999", "2"), ("estimate", "ffff7f00", "2"), ("ellipse", "ff0000ff", "2"),
                              ("waypoints", "ff000000", "1"), ("geofence", "ff00aa00", "3"),
                              ("no_fly", "ff0000cc", "3"), ("building", "ff555555", "1")):
        st = ET.SubElement(doc, "Style", id=sid)
        ls = ET.SubElement(st, "LineStyle")
        ET.SubElement(ls, "color").text = color
        ET.SubElement(ls, "width").text = width
        ps = ET.SubElement(st, "PolyStyle")
        ET.SubElement(ps, "fill").text = "0"

    def placemark(name: str, style: str | None, description: str = "") -> ET.Element:
        pm = ET.SubElement(doc, "Placemark")
        ET.SubElement(pm, "name").text = name
        if description:
            ET.SubElement(pm, "description").text = description
        if style:
            ET.SubElement(pm, "styleUrl").text = f"#{style}"
        return pm

    for k, uid in enumerate(inp.user_ids):
        u = inp.users_enu_m[k]
        if not np.all(np.isfinite(u)):
            continue
        stats = _user_stats(inp, k)
        desc = ", ".join(f"{key} = {val}" for key, val in stats.items() if key not in ("id", "cov_en_m2"))
        pm = placemark(f"{uid} (estimate)", None, desc)
        pt = ET.SubElement(pm, "Point")
        ET.SubElement(pt, "altitudeMode").text = "absolute"
        ET.SubElement(pt, "coordinates").text = _kml_coords(_lonlatalt(inp.origin, u))
        if stats["cov_en_m2"] is not None:
            pm = placemark(f"{uid} 95 % ellipse", "ellipse", f"error_bound_95_m = {stats['error_bound_95_m']}")
            poly = ET.SubElement(pm, "Polygon")
            ET.SubElement(poly, "altitudeMode").text = "clampToGround"
            ring = ET.SubElement(ET.SubElement(poly, "outerBoundaryIs"), "LinearRing")
            coords = _lonlatalt(inp.origin, _ellipse_ring_enu(u, inp.cov_en_m2[k]))
            coords[-1] = coords[0]
            ET.SubElement(ring, "coordinates").text = _kml_coords(coords)
    if inp.truth_enu_m is not None:
        for k, uid in enumerate(inp.user_ids):
            t = inp.truth_enu_m[k]
            if np.all(np.isfinite(t)):
                pm = placemark(f"{uid} (true)", None)
                pt = ET.SubElement(pm, "Point")
                ET.SubElement(pt, "altitudeMode").text = "absolute"
                ET.SubElement(pt, "coordinates").text = _kml_coords(_lonlatalt(inp.origin, t))
    fleet = len(inp.vehicles()) > 1
    lines = [(f"{name} (vehicle {v})" if fleet else name, style, pts) for v in inp.vehicles()
             for name, style, pts in (("GPS track", "track", inp.track_enu_m(v)),
                                      ("estimated UAV track", "estimate", inp.uav_track_enu_m(v)),
                                      ("waypoints", "waypoints", inp.waypoints_of(v)))]
    for name, style, pts in lines:
        if pts is None or len(pts) < 2:
            continue
        pm = placemark(name, style)
        ls = ET.SubElement(pm, "LineString")
        ET.SubElement(ls, "altitudeMode").text = "absolute"
        ET.SubElement(ls, "coordinates").text = _kml_coords(_lonlatalt(inp.origin, pts))
    _kml_shapes(inp.shapes, placemark)
    ET.indent(kml)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(kml, encoding="unicode") + "\n"


def _kml_shapes(shapes: MissionShapes, placemark) -> None:
    """Placemarks of the geofence and no-fly zones (on the ground) and the buildings (extruded)."""

    def polygon(pm: ET.Element, ring_lat_lon: np.ndarray, height_m: float | None) -> None:
        poly = ET.SubElement(pm, "Polygon")
        if height_m is None:
            ET.SubElement(poly, "altitudeMode").text = "clampToGround"
        else:
            ET.SubElement(poly, "extrude").text = "1"
            ET.SubElement(poly, "altitudeMode").text = "relativeToGround"
        ring = ET.SubElement(ET.SubElement(poly, "outerBoundaryIs"), "LinearRing")
        h = 0.0 if height_m is None else height_m
        ET.SubElement(ring, "coordinates").text = _kml_coords([[lo, la, h] for lo, la in _ring_lonlat(ring_lat_lon)])

    band = shapes.altitude_band_m
    if shapes.geofence_lat_lon_deg is not None:
        desc = "inclusion" + ("" if band is None else f"; altitude band {band[0]:g}..{band[1]:g} m above home")
        polygon(placemark("geofence", "geofence", desc), shapes.geofence_lat_lon_deg, None)
    for i, zone in enumerate(shapes.no_fly_lat_lon_deg):
        polygon(placemark(f"no-fly zone {i}", "no_fly", "exclusion"), zone, None)
    for i, b in enumerate(shapes.buildings):
        polygon(placemark(f"building {i}", "building", f"height_m = {b.height_m:g}"), b.footprint_lat_lon_deg,
                b.height_m)


def write_kml(inp: ReportInputs, path: str | Path) -> Path:
    """Write :func:`kml_document` to `path`."""
    return _write_text(path, kml_document(inp))


# ---------------------------------------------------------------------------------------------
# QGroundControl plan


def simplify_track_m(track_enu_m: np.ndarray, tolerance_m: float) -> np.ndarray:
    """Ramer–Douglas–Peucker: the fewest points of a (P, 3) polyline such that no dropped point is
    farther than `tolerance_m` (3-D) from the kept polyline. Keeps the first and last points."""
    pts = np.asarray(track_enu_m, float).reshape(-1, 3)
    if len(pts) <= 2:
        return pts.copy()
    keep = np.zeros(len(pts), bool)
    keep[0] = keep[-1] = True
    stack = [(0, len(pts) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        a, b = pts[i], pts[j]
        seg = b - a
        inner = pts[i + 1:j]
        L2 = float(seg @ seg)
        if L2 < 1e-12:
            dist = np.linalg.norm(inner - a, axis=1)
        else:
            # distance from p to the segment a→b: clamp s = (p−a)·(b−a)/|b−a|² to [0, 1]
            s = np.clip((inner - a) @ seg / L2, 0.0, 1.0)
            dist = np.linalg.norm(inner - (a + s[:, None] * seg), axis=1)
        m = int(np.argmax(dist))
        if dist[m] > tolerance_m:
            keep[i + 1 + m] = True
            stack.append((i, i + 1 + m))
            stack.append((i + 1 + m, j))
    return pts[keep]


def _simple_item(seq: int, command: int, frame: int, params: list, alt_amsl_m: float | None = None) -> dict:
    item = {"type": "SimpleItem", "autoContinue": True, "command": command, "doJumpId": seq + 1,
            "frame": frame, "params": params}
    if alt_amsl_m is not None:
        item.update({"AltitudeMode": QGC_ALT_MODE_ABSOLUTE, "Altitude": alt_amsl_m, "AMSLAltAboveTerrain": None})
    return item


def qgc_plan(
    waypoints_lla: np.ndarray,
    home_lla: tuple[float, float, float],
    takeoff: bool = True,
    return_to_launch: bool = True,
    geofence_polygons_latlon: list[np.ndarray] | None = None,
    exclusion_polygons_latlon: list[np.ndarray] | None = None,
    geofence_circle: tuple[float, float, float] | None = None,
    rally_lla: np.ndarray | None = None,
    cruise_speed_mps: float = 10.0,
    hover_speed_mps: float = 5.0,
) -> dict:
    """A QGroundControl plan (dict, ready for json.dumps).

    waypoints_lla: (W, 3) lat_deg, lon_deg, alt_m AMSL; home_lla: planned home (lat, lon, alt AMSL).
    takeoff: first item NAV_TAKEOFF to the first waypoint's altitude above home; return_to_launch:
    last item RTL. geofence_polygons_latlon: inclusion polygons, each (P, 2) lat/lon (open ring);
    exclusion_polygons_latlon: exclusion (no-fly) polygons, the same way; geofence_circle:
    (lat, lon, radius_m) inclusion circle; rally_lla: (R, 3) rally points.
    """
    wps = np.asarray(waypoints_lla, float).reshape(-1, 3)
    if len(wps) == 0:
        raise MissionError("a plan needs at least one waypoint")
    if not np.all(np.isfinite(wps)):
        raise MissionError("plan waypoints must be finite lat/lon/alt")
    items: list[dict] = []
    if takeoff:
        alt = round(float(wps[0, 2]), 2)
        hla, hlo = round(home_lla[0], DEG_DECIMALS), round(home_lla[1], DEG_DECIMALS)
        # NAV_TAKEOFF: params [pitch, empty, empty, yaw, lat, lon, alt]; at home, climbing to the first altitude
        items.append(_simple_item(len(items), MAV_CMD_NAV_TAKEOFF, MAV_FRAME_GLOBAL,
                                  [0, 0, 0, None, hla, hlo, alt], alt))
    for lat, lon, alt in wps:
        # NAV_WAYPOINT: params [hold s, acceptance radius m, pass radius m, yaw, lat, lon, alt AMSL]
        a = round(float(alt), 2)
        la, lo = round(float(lat), DEG_DECIMALS), round(float(lon), DEG_DECIMALS)
        items.append(_simple_item(len(items), MAV_CMD_NAV_WAYPOINT, MAV_FRAME_GLOBAL, [0, 0, 0, None, la, lo, a], a))
    if return_to_launch:
        items.append(_simple_item(len(items), MAV_CMD_NAV_RETURN_TO_LAUNCH, MAV_FRAME_MISSION, [0, 0, 0, 0, 0, 0, 0]))
    polygons = []
    for inclusion, polys in ((True, geofence_polygons_latlon), (False, exclusion_polygons_latlon)):
        for poly in polys or []:
            p = np.asarray(poly, float).reshape(-1, 2)
            if len(p) < 3 or not np.all(np.isfinite(p)):
                raise MissionError(f"a geofence polygon needs >= 3 finite lat/lon vertices, got {p.tolist()!r}")
            polygons.append({"inclusion": inclusion, "version": 1,
                             "polygon": [[round(float(a), DEG_DECIMALS), round(float(b), DEG_DECIMALS)] for a, b in p]})
    circles = []
    if geofence_circle is not None:
        la, lo, r = geofence_circle
        circles.append({"inclusion": True, "version": 1,
                        "circle": {"center": [round(la, DEG_DECIMALS), round(lo, DEG_DECIMALS)], "radius": float(r)}})
    rally = [] if rally_lla is None else [
        [round(float(a), DEG_DECIMALS), round(float(b), DEG_DECIMALS), round(float(c), 2)]
        for a, b, c in np.asarray(rally_lla, float).reshape(-1, 3)]
    return {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "QGroundControl",
        "geoFence": {"version": 2, "circles": circles, "polygons": polygons},
        "rallyPoints": {"version": 2, "points": rally},
        "mission": {
            "version": 2,
            "firmwareType": MAV_AUTOPILOT_PX4,
            "vehicleType": MAV_TYPE_QUADROTOR,
            "cruiseSpeed": float(cruise_speed_mps),
            "hoverSpeed": float(hover_speed_mps),
            "globalPlanAltitudeMode": QGC_ALT_MODE_ABSOLUTE,
            "plannedHomePosition": [round(home_lla[0], DEG_DECIMALS), round(home_lla[1], DEG_DECIMALS),
                                    round(home_lla[2], 2)],
            "items": items,
        },
    }


def plan_from_inputs(inp: ReportInputs, tolerance_m: float = 2.0, max_waypoints: int = 500,
                     min_height_m: float = 2.0, vehicle: int = 0, **kwargs: Any) -> dict:
    """Plan of the mission's waypoints when it logged any, else of the flown GPS track simplified
    to within `tolerance_m` (points less than `min_height_m` above home — take-off and landing —
    are left out; the tolerance doubles until at most `max_waypoints` remain). The log's geofence
    and no-fly zones become the plan's inclusion and exclusion polygons. A plan is one vehicle's:
    `vehicle`'s waypoints or track (a fleet gets one plan per vehicle, :func:`write_exports`)."""
    waypoints = inp.waypoints_of(vehicle)
    if waypoints is not None and len(waypoints):
        pts = waypoints
    else:
        track = inp.track_enu_m(vehicle)
        track = track[track[:, 2] >= min_height_m] if np.any(track[:, 2] >= min_height_m) else track
        tol = tolerance_m
        pts = simplify_track_m(track, tol)
        while len(pts) > max_waypoints:
            tol *= 2
            pts = simplify_track_m(track, tol)
    lat, lon, alt = inp.origin.enu_to_lla(pts)
    o = inp.origin
    shapes = inp.shapes
    kwargs.setdefault("geofence_polygons_latlon",
                      [] if shapes.geofence_lat_lon_deg is None else [shapes.geofence_lat_lon_deg])
    kwargs.setdefault("exclusion_polygons_latlon", list(shapes.no_fly_lat_lon_deg))
    return qgc_plan(np.c_[lat, lon, alt], (o.lat_deg, o.lon_deg, o.alt_m), **kwargs)


def write_plan(plan: dict, path: str | Path) -> Path:
    """Write a plan dict as a `.plan` file."""
    return _write_text(path, json.dumps(plan, indent=2, allow_nan=False) + "\n")


def _write_text(path: str | Path, text: str) -> Path:
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise MissionError(f"cannot write {p}: {exc}") from exc
    return p


def write_exports(inp: ReportInputs, out_dir: str | Path, stem: str = "mission") -> dict[str, Path]:
    """Write `<stem>.geojson`, `<stem>.kml` and `<stem>.plan` into `out_dir`; a fleet's plans are
    one per vehicle, `<stem>.plan` vehicle 0's and `<stem>.vehicle<v>.plan` (key `plan_vehicle<v>`)
    each other one's."""
    out = Path(out_dir)
    paths = {
        "geojson": write_geojson(inp, out / f"{stem}.geojson"),
        "kml": write_kml(inp, out / f"{stem}.kml"),
        "plan": write_plan(plan_from_inputs(inp), out / f"{stem}.plan"),
    }
    for v in inp.vehicles():
        if v != 0:
            paths[f"plan_vehicle{v}"] = write_plan(plan_from_inputs(inp, vehicle=v), out / f"{stem}.vehicle{v}.plan")
    return paths
