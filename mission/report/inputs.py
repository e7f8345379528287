"""What a report draws: :class:`ReportInputs`, plain arrays independent of how replay or the
mission controller store their results, and :class:`MissionShapes`, the geofence, no-fly zones,
altitude band and buildings a log header may carry (docs/design.md §10, optional fields):

    geofence         [[lat_deg, lon_deg], ...]            open ring (inclusion)
    no_fly_zones     [[[lat_deg, lon_deg], ...], ...]     open rings (exclusion)
    altitude_band_m  {"min_m", "max_m"}                   above home
    buildings        [{"footprint": ring, "height_m"}]    simulations only

Absent fields are fine; a malformed one is left out with a warning naming it (the report of a
flight is not lost to a bad decoration).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from mission.result import Result, error_bound_95_m
from uavloc.errors import MissionError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Building:
    """A building: footprint (P, 2) [lat_deg, lon_deg] (open ring) and height above ground [m]."""

    footprint_lat_lon_deg: np.ndarray
    height_m: float


@dataclass(frozen=True)
class MissionShapes:
    """The mission's areas in geodetic coordinates. geofence_lat_lon_deg (P, 2) or None;
    no_fly_lat_lon_deg: tuple of (Q, 2); altitude_band_m: (min_m, max_m) above home or None;
    buildings: tuple of :class:`Building`."""

    geofence_lat_lon_deg: np.ndarray | None = None
    no_fly_lat_lon_deg: tuple[np.ndarray, ...] = ()
    altitude_band_m: tuple[float, float] | None = None
    buildings: tuple[Building, ...] = ()


def _ring(value: Any, what: str) -> np.ndarray:
    ring = np.asarray(value, dtype=float)
    if ring.ndim != 2 or ring.shape[1] != 2 or len(ring) < 3 or not np.all(np.isfinite(ring)):
        raise ValueError(f"{what} must be >= 3 [lat_deg, lon_deg] pairs, got {value!r}")
    if np.any(np.abs(ring[:, 0]) > 90) or np.any(np.abs(ring[:, 1]) > 180):
        raise ValueError(f"{what} has a latitude beyond 90 or a longitude beyond 180 degrees: {value!r}")
    if len(ring) > 3 and np.array_equal(ring[0], ring[-1]):
        ring = ring[:-1]  # tolerate a closed ring
    return ring


def shapes_from_header(header: dict) -> MissionShapes:
    """:class:`MissionShapes` of a raw log header object (see the module docstring)."""

    def field_or_none(key: str, parse):
        if header.get(key) is None:
            return None
        try:
            return parse(header[key])
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            log.warning("log header field %r left out of the report: %s", key, exc)
            return None

    def band(v: dict) -> tuple[float, float]:
        lo, hi = float(v["min_m"]), float(v["max_m"])
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ValueError(f"need finite min_m <= max_m, got {v!r}")
        return lo, hi

    def buildings(v: list) -> tuple[Building, ...]:
        out = []
        for i, b in enumerate(v):
            h = float(b["height_m"])
            if not (math.isfinite(h) and h > 0):
                raise ValueError(f"buildings[{i}].height_m must be positive, got {b['height_m']!r}")
            out.append(Building(_ring(b["footprint"], f"buildings[{i}].footprint"), h))
        return tuple(out)

    return MissionShapes(
        geofence_lat_lon_deg=field_or_none("geofence", lambda v: _ring(v, "geofence")),
        no_fly_lat_lon_deg=field_or_none("no_fly_zones", lambda v: tuple(
            _ring(z, f"no_fly_zones[{i}]") for i, z in enumerate(v))) or (),
        altitude_band_m=field_or_none("altitude_band_m", band),
        buildings=field_or_none("buildings", buildings) or (),
    )


def shapes_from_log(mlog: Any) -> MissionShapes:
    """The shapes of a parsed log's header: its raw header object when the parser keeps one
    (`header.raw`), else the log file's first line, read again; empty when neither is there."""
    raw = getattr(mlog.header, "raw", None)
    if not isinstance(raw, dict):
        try:
            with open(Path(str(mlog.path)), encoding="utf-8") as f:
                raw = json.loads(f.readline())
        except (OSError, ValueError, TypeError):
            return MissionShapes()
    return shapes_from_header(raw) if isinstance(raw, dict) else MissionShapes()


def uavloc_version() -> str:
    """The installed uavloc's version (package metadata), or "unknown" when it is not installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("uavloc")
    except PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class MissionFacts:
    """What mission the report is of, from the log header (None where an older log or another
    tool's does not say): command ("sim", "fly", ...), command_line (as typed), scenario, mission
    (the mission's name), mission_file, seed, planner, start_utc (the header's start time), the
    log's file name and the uavloc version that wrote the report."""

    log_file: str
    uavloc_version: str
    command: str | None = None
    command_line: str | None = None
    scenario: str | None = None
    mission: str | None = None
    mission_file: str | None = None
    seed: int | None = None
    planner: str | None = None
    start_utc: str | None = None

    def title(self) -> str:
        """"uavloc sim three_users_nlos, seed 3, casadi"; a log without a command is named after its
        scenario or mission ("paper, seed 1"), a log that says nothing after its file."""
        subject = self.scenario or self.mission_file or self.mission
        if self.command is not None:
            head = " ".join(x for x in ("uavloc", self.command, subject) if x)
        else:
            head = subject or f"mission log {self.log_file}"
        parts = [head]
        if self.seed is not None:
            parts.append(f"seed {self.seed}")
        if self.planner is not None:
            parts.append(self.planner)
        return ", ".join(parts)

    def to_dict(self) -> dict[str, Any]:
        return {"command": self.command, "command_line": self.command_line, "scenario": self.scenario,
                "mission": self.mission, "mission_file": self.mission_file, "seed": self.seed,
                "planner": self.planner, "start_utc": self.start_utc, "log_file": self.log_file,
                "uavloc_version": self.uavloc_version}


def facts_from_header(config: dict, start_utc: str | None, log_file: str, version: str) -> MissionFacts:
    """:class:`MissionFacts` of a log header's `config` section and start time; a field of the
    wrong type is left out (None), as an older log's absent field."""

    def text(key: str) -> str | None:
        v = config.get(key)
        return v if isinstance(v, str) and v else None

    seed = config.get("seed")
    return MissionFacts(
        log_file=log_file, uavloc_version=version, command=text("command"), command_line=text("command_line"),
        scenario=text("scenario"), mission=text("mission"), mission_file=text("mission_file"),
        seed=seed if isinstance(seed, int) and not isinstance(seed, bool) else None,
        planner=text("planner"), start_utc=start_utc or None)


@dataclass(frozen=True)
class ReportInputs:
    """Everything a report or an export draws. Shapes: K users, N keyframes, M range measurements,
    T telemetry fixes, H history steps, W waypoints. Positions are ENU [m] about the result's origin.

    result: the mission's :class:`mission.result.Result` (status, users, flown metres, counts,
    origin: what the report summarizes; never re-derived here); its origin must be known.
    noise: the noise model the estimator used.
    kf_t_s (N,), kf_gps_enu_m (N, 3): keyframe times and GPS positions; uav_enu_m (N, 3) the
    estimator's corrected track (or None).
    tel_t_s (T,), tel_enu_m (T, 3): telemetry track (or None: the keyframes are the track).
    meas_t_s (M,), meas_user (M,), meas_range_m (M,), meas_uav_enu_m (M, 3): every range used, with
    the GPS position it was taken at.
    hist_flown_m (H,), hist_bound_95_m (H, K), hist_error_m (H, K) or None: how the estimate evolved.
    waypoints_enu_m (W, 3) or None: the planner's waypoints, if the mission logged them.
    kf_vehicle (N,), tel_vehicle (T,), waypoints_vehicle (W,): each keyframe's, telemetry fix's and
    waypoint's vehicle in a fleet (docs/fleet.md; None: one vehicle, vehicle 0). Each vehicle's
    track is its own: draw it with :meth:`tracks_enu_m` and :meth:`vehicle_rows`, never as one line.
    title: the report's title; extra: report-only facts for report.json's `extra`.
    facts: what mission this is (:class:`MissionFacts`, the log header's), or None (not from a log).
    shapes: the geofence, no-fly zones, altitude band and buildings of the log header (empty when
    the header has none).
    """

    result: Result
    noise: NoiseModel
    kf_t_s: np.ndarray
    kf_gps_enu_m: np.ndarray
    meas_t_s: np.ndarray
    meas_user: np.ndarray
    meas_range_m: np.ndarray
    meas_uav_enu_m: np.ndarray
    uav_enu_m: np.ndarray | None = None
    tel_t_s: np.ndarray | None = None
    tel_enu_m: np.ndarray | None = None
    hist_flown_m: np.ndarray | None = None
    hist_bound_95_m: np.ndarray | None = None
    hist_error_m: np.ndarray | None = None
    waypoints_enu_m: np.ndarray | None = None
    title: str = "uavloc mission"
    extra: dict = field(default_factory=dict)
    shapes: MissionShapes = field(default_factory=lambda: MissionShapes())
    facts: MissionFacts | None = None
    kf_vehicle: np.ndarray | None = None
    tel_vehicle: np.ndarray | None = None
    waypoints_vehicle: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.result.origin is None:
            raise MissionError("a report needs the result's origin (the log header's)")

    # the result's facts, as the figures draw them
    @property
    def origin(self) -> Origin:
        return self.result.origin

    @property
    def user_ids(self) -> list[str]:
        return self.result.user_ids

    @property
    def n_users(self) -> int:
        return len(self.result.users)

    @property
    def users_enu_m(self) -> np.ndarray:
        """(K, 3) estimated users [m] (NaN rows: not located)."""
        return self.result.users_enu_m()

    @property
    def cov_en_m2(self) -> np.ndarray:
        """(K, 2, 2) their east-north covariance [m²]."""
        return self.result.cov_en_m2()

    @property
    def truth_enu_m(self) -> np.ndarray | None:
        """(K, 3) true users [m], or None."""
        return self.result.truth_enu_m()

    def vehicles(self) -> list[int]:
        """The vehicles that flew (keyframes' and telemetry's), ascending; [0] for one vehicle."""
        seen = [np.asarray(v, int) for v in (self.kf_vehicle, self.tel_vehicle) if v is not None]
        found = sorted({int(v) for a in seen for v in a})
        return found or [0]

    @staticmethod
    def vehicle_rows(vehicle_of_rows: np.ndarray | None, n: int, vehicle: int) -> np.ndarray:
        """(n,) bool: the rows of an array whose rows' vehicles are vehicle_of_rows (None: all 0)
        that are `vehicle`'s."""
        if vehicle_of_rows is None:
            return np.full(n, vehicle == 0)
        return np.asarray(vehicle_of_rows, int) == vehicle

    def track_enu_m(self, vehicle: int | None = None) -> np.ndarray:
        """(T, 3) the flown GPS track of `vehicle`: its telemetry when it has two fixes or more,
        else its keyframes' GPS positions. None: every vehicle's points (one vehicle: its track as
        before; a fleet's: the vehicles' tracks one after the other, points to fit a view, not a line)."""
        if vehicle is None:
            vs = self.vehicles()
            if len(vs) == 1:
                return self.track_enu_m(vs[0])
            return np.vstack([self.track_enu_m(v) for v in vs])
        if self.tel_enu_m is not None:
            tel = self.tel_enu_m[self.vehicle_rows(self.tel_vehicle, len(self.tel_enu_m), vehicle)]
            if len(tel) >= 2:
                return tel
        return self.kf_gps_enu_m[self.vehicle_rows(self.kf_vehicle, len(self.kf_gps_enu_m), vehicle)]

    def tracks_enu_m(self) -> list[tuple[int, np.ndarray]]:
        """[(vehicle, its GPS track (T_v, 3))] for every vehicle (:meth:`track_enu_m`)."""
        return [(v, self.track_enu_m(v)) for v in self.vehicles()]

    def uav_track_enu_m(self, vehicle: int) -> np.ndarray | None:
        """(N_v, 3) the estimator's corrected track at `vehicle`'s keyframes, or None."""
        if self.uav_enu_m is None:
            return None
        return self.uav_enu_m[self.vehicle_rows(self.kf_vehicle, len(self.uav_enu_m), vehicle)]

    def waypoints_of(self, vehicle: int) -> np.ndarray | None:
        """(W_v, 3) `vehicle`'s waypoints, or None when the mission logged none."""
        if self.waypoints_enu_m is None:
            return None
        return self.waypoints_enu_m[self.vehicle_rows(self.waypoints_vehicle, len(self.waypoints_enu_m), vehicle)]

    def error_bound_95_m(self) -> np.ndarray:
        """(K,) semi-major axis of each user's 95 % ellipse [m]; inf where unknown."""
        return error_bound_95_m(self.cov_en_m2)

    def error_m(self) -> np.ndarray | None:
        """(K,) horizontal error of each estimated user [m] when the truth is known."""
        return self.result.error_m()


def inputs_from_replay(result: Any, title: str | None = None) -> ReportInputs:
    """Build :class:`ReportInputs` from a `mission.replay.ReplayResult` (keyframes, estimate, log,
    noise, flown_m, history) and its :class:`mission.result.Result` (mission.replay.result_of_replay)."""
    from mission.replay import result_of_replay

    mlog = result.log
    origin = mlog.header.origin
    est = result.estimate
    kfs = list(result.keyframes)
    meas_t = np.concatenate([np.full(len(kf.range_m), kf.t_s) for kf in kfs]) if kfs else np.zeros(0)
    meas_user = np.concatenate([np.asarray(kf.user_idx, int) for kf in kfs]) if kfs else np.zeros(0, int)
    meas_r = np.concatenate([np.asarray(kf.range_m, float) for kf in kfs]) if kfs else np.zeros(0)
    meas_uav = (np.concatenate([np.repeat(np.asarray(kf.gps_enu_m, float)[None], len(kf.range_m), 0) for kf in kfs])
                if kfs else np.zeros((0, 3)))
    tel_t = tel_enu = tel_vehicle = None
    if len(mlog.tel_t_s) >= 2:
        tel_t = mlog.tel_t_s
        tel_enu = origin.lla_to_enu(mlog.tel_lla[:, 0], mlog.tel_lla[:, 1], mlog.tel_lla[:, 2])
        tel_vehicle = getattr(mlog, "tel_vehicle", None)
    kf_vehicle = np.array([getattr(kf, "vehicle", 0) for kf in kfs], int)
    fleet = bool(kf_vehicle.any()) or (tel_vehicle is not None and bool(np.asarray(tel_vehicle).any()))
    waypoints, waypoints_vehicle = waypoints_from_log(mlog, with_vehicle=True)
    uav = np.asarray(est.uav_enu_m, float)
    if uav.shape != result.kf_gps_enu_m.shape:
        uav = None  # a fixed-lag estimator keeps only the last keyframes: nothing to draw against
    hist = getattr(result, "history", None)
    facts = facts_from_header(mlog.header.config, mlog.header.start_utc, Path(str(mlog.path)).name,
                              uavloc_version())
    extra = {}
    if getattr(mlog, "channel", None):
        from mission.channel import channel_residuals

        # a real gNB behind a bridge (uavloc sim --oai): its ranges against the channel's distance
        res = channel_residuals(mlog.rtt_t_s, mlog.rtt_user, mlog.rtt_toa_s, mlog.channel, mlog.header.user_index())
        extra["channel_residuals"] = res.to_dict()
    return ReportInputs(
        result=result_of_replay(result),
        noise=result.noise,
        kf_t_s=np.asarray(result.kf_t_s, float),
        kf_gps_enu_m=np.asarray(result.kf_gps_enu_m, float),
        meas_t_s=meas_t, meas_user=meas_user, meas_range_m=meas_r, meas_uav_enu_m=meas_uav,
        uav_enu_m=uav,
        tel_t_s=tel_t, tel_enu_m=tel_enu,
        hist_flown_m=None if hist is None else np.asarray(hist.flown_m, float),
        hist_bound_95_m=None if hist is None else np.asarray(hist.bound_95_m, float),
        hist_error_m=None if hist is None or hist.error_m is None else np.asarray(hist.error_m, float),
        waypoints_enu_m=waypoints,
        kf_vehicle=kf_vehicle if fleet else None,
        tel_vehicle=tel_vehicle if fleet else None,
        waypoints_vehicle=waypoints_vehicle if fleet else None,
        shapes=shapes_from_log(mlog),
        title=title or facts.title(),
        facts=facts,
        extra=extra,
    )


def waypoints_from_log(mlog: Any, with_vehicle: bool = False):
    """(W, 3) ENU of the log's `waypoint` records that carry lat_deg/lon_deg/alt_m, or None.
    with_vehicle: (that, (W,) each one's vehicle (the record's `vehicle`, 0 when absent) or None)."""
    pts, vehicles = [], []
    for w in getattr(mlog, "waypoints", []) or []:
        try:
            pts.append((float(w["lat_deg"]), float(w["lon_deg"]), float(w["alt_m"])))
        except (KeyError, TypeError, ValueError):
            continue
        vehicles.append(int(w.get("vehicle", 0)))
    if not pts:
        return (None, None) if with_vehicle else None
    a = np.asarray(pts)
    enu = mlog.header.origin.lla_to_enu(a[:, 0], a[:, 1], a[:, 2])
    return (enu, np.asarray(vehicles, int)) if with_vehicle else enu
