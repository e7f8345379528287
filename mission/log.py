"""The mission log, `uavloc-mission/1`: JSON Lines, appended and flushed line by line (docs/design.md §10).

Writer: :class:`MissionLogWriter` appends one JSON object per line and flushes each, so a crash loses
at most the line being written. Reader: :func:`read_mission_log` accepts any file that follows the
table in docs/design.md §10; a torn last line (no newline, not JSON) is skipped with a warning; anything
else malformed raises :class:`MissionLogError` naming the line number and the reason, also
telemetry records out of time order (a shuffled or spliced log: refused, not sorted).

A fleet's log (docs/fleet.md) lists its vehicles in the header (`vehicles`, index = vehicle number)
and names the vehicle of each `telemetry`, `rtt`, `waypoint` and `event` record (`"vehicle"`; absent:
vehicle 0). The reader keeps each rtt and telemetry record's vehicle (:attr:`MissionLog.rtt_vehicle`,
:attr:`MissionLog.tel_vehicle`) and checks every time order per vehicle.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from estimator.ranging import toa_s_from_raw
from mission.channel import check_channel_record
from mission.log_checks import LineError as _LineError
from mission.log_checks import RangeRecords
from mission.vehicle.telemetry import VehicleStatus
from uavloc.errors import MissionLogError, UavlocError

log = logging.getLogger(__name__)

FORMAT = "uavloc-mission/1"
RECORD_TYPES = ("header", "telemetry", "rtt", "estimate", "waypoint", "event", "truth", "channel")


class MissionLogWriter:
    """Append-only writer of a mission log. Use as a context manager.

    Every record is one line, written and flushed at once (one unbuffered write of the whole
    line). NaN or infinite numbers are refused (JSON has none) with a :class:`MissionLogError`, and
    nothing is written for that record.

    A line the file system refuses (a full disk, a file size limit, an I/O error) is cut off
    again, so the log stays whole up to the last record written; that write raises a
    :class:`MissionLogError` naming the file and the reason, and the writer is then
    :attr:`failed`: later records are dropped (counted in :attr:`dropped`) instead of raising, so
    that a failing log never stops the mission's safe end (RTL) on its way.

    Listeners (:meth:`subscribe`, e.g. the live view) get each record as written (a dict of plain
    JSON types) right after its line is flushed; they must be quick and not raise: an exception in
    a listener is logged and the listener dropped, the mission log goes on.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._fd: int | None = None
        self._size = 0  # bytes of whole lines in the file
        self._lines = 0  # lines this writer wrote
        self._listeners: list[Callable[[dict], None]] = []
        #: the error that stopped the log (None while it is written)
        self.failed: MissionLogError | None = None
        #: records dropped since the log failed
        self.dropped = 0

    def subscribe(self, listener: Callable[[dict], None]) -> None:
        """Call `listener(record)` with every record written from now on."""
        self._listeners.append(listener)

    def __enter__(self) -> MissionLogWriter:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._fd is not None

    def open(self) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        except OSError as exc:
            raise MissionLogError(f"cannot open mission log {self.path}: {exc.strerror or exc}") from None
        self._size = os.fstat(self._fd).st_size

    def close(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            with contextlib.suppress(OSError):  # nothing is buffered: every line was written whole
                os.close(fd)

    def write(self, record_type: str, t_s: float, **fields: Any) -> dict:
        """Append one record `{"type": record_type, "t": t_s, **fields}` and flush it."""
        if self._fd is None:
            raise MissionLogError(f"mission log {self.path} is not open")
        if record_type not in RECORD_TYPES:
            raise MissionLogError(f"unknown record type {record_type!r}; known: {', '.join(RECORD_TYPES)}")
        obj = {"type": record_type, "t": round(float(t_s), 6), **fields}
        plain = _plain(obj)
        try:
            line = json.dumps(plain, allow_nan=False, separators=(",", ":"))
        except ValueError as exc:
            raise MissionLogError(f"{record_type} record has a NaN or infinite number: {obj!r}") from exc
        if self.failed is not None:
            self.dropped += 1
            return obj
        self._append((line + "\n").encode("utf-8"))
        for listener in list(self._listeners):
            try:
                listener(plain)
            except Exception:
                log.exception("mission log listener %r failed; it gets no more records", listener)
                self._listeners.remove(listener)
        return obj

    def _append(self, data: bytes) -> None:
        """Write `data` (whole lines) at the end; on a refused write cut the file back to its last
        whole line and fail (see the class docstring)."""
        view = memoryview(data)
        try:
            while view:
                n = os.write(self._fd, view)
                view = view[n:]
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, self._size)
            self.failed = MissionLogError(
                f"cannot write the mission log {self.path}: {exc.strerror or exc}; it holds the "
                f"{self._lines} record(s) written before, whole, and no more are written")
            raise self.failed from None
        self._size += len(data)
        self._lines += 1

    def write_header(
        self,
        origin: Origin,
        users: list[dict],
        radio: dict,
        noise: NoiseModel | None = None,
        config: dict | None = None,
        start_utc: str | None = None,
        area: dict | None = None,
        vehicles: list[dict] | None = None,
    ) -> dict:
        """Write the header line: users as [{"id", "rnti", "ground_alt_m"}], radio {"mu", "fs_hz"};
        `area`: the optional geofence / no-fly / altitude-band / buildings fields (:func:`area_fields`,
        or mission.config's `header_fields`, whose fleet `vehicles` carry each one's altitude band).

        `vehicles` (a fleet only; None or empty for one vehicle): [{"id", "home"}, ...], index =
        vehicle number, `home` an :class:`Origin` or {"lat_deg", "lon_deg", "alt_m"}: the vehicle's
        own home (the header's `origin` stays the mission's ENU origin, vehicle 0's home). Merged
        by index with the `vehicles` of `area` when both are given (their ids must agree and their
        counts match), so each entry holds id, home and band."""
        fields: dict[str, Any] = {
            "format": FORMAT,
            "start_utc": start_utc or datetime.now(UTC).isoformat(timespec="milliseconds"),
            "origin": origin.to_dict(),
            "users": users,
            "radio": radio,
        }
        if noise is not None:
            fields["noise"] = noise.to_log_dict()
        if config is not None:
            fields["config"] = config
        if area:
            fields.update(area)
        if vehicles:
            fields["vehicles"] = _merge_vehicles(vehicles, fields.get("vehicles"))
        return self.write("header", 0.0, **fields)


def _merge_vehicles(vehicles: list[dict], banded: list[dict] | None) -> list[dict]:
    """The header's `vehicles`: write_header's [{"id", "home"}] merged by index with the area's
    [{"id", "alt_min_m", "alt_max_m"}] (None: none). Raises MissionLogError when they disagree."""
    out = []
    if banded is not None and len(banded) != len(vehicles):
        raise MissionLogError(f"header vehicles: {len(vehicles)} given, but the area fields list {len(banded)}")
    for i, v in enumerate(vehicles):
        if not isinstance(v, dict) or not isinstance(v.get("id"), str) or not v["id"]:
            raise MissionLogError(f"header vehicles[{i}] needs a string 'id', got {v!r}")
        entry: dict[str, Any] = dict(banded[i]) if banded is not None else {}
        if entry.get("id", v["id"]) != v["id"]:
            raise MissionLogError(f"header vehicles[{i}] is {v['id']!r} here and {entry['id']!r} in the area fields")
        entry.update(v)
        home = entry.get("home")
        if isinstance(home, Origin):
            entry["home"] = home.to_dict()
        out.append(entry)
    return out


def _ring_lat_lon(origin: Origin, ring_en_m) -> list[list[float]]:
    """(P, 2) east/north ring [m] → [[lat_deg, lon_deg], ...] (open ring, as given)."""
    ring = np.asarray(ring_en_m, float).reshape(-1, 2)
    lat, lon, _ = origin.enu_to_lla(np.column_stack([ring, np.zeros(len(ring))]))
    return [[round(float(a), 9), round(float(b), 9)] for a, b in zip(np.atleast_1d(lat), np.atleast_1d(lon),
                                                                       strict=True)]


def area_fields(origin: Origin, fence_en_m=None, no_fly_en_m=(), alt_min_m: float | None = None,
                alt_max_m: float | None = None, max_distance_m: float | None = None,
                buildings: list | None = None) -> dict:
    """The header's optional area fields from shapes in the ENU frame of `origin`:

    `geofence` [[lat_deg, lon_deg], ...] (open ring) from fence_en_m (P, 2); `no_fly_zones` a list
    of such rings; `altitude_band_m` {"min_m", "max_m"} above home; `max_distance_m` from home;
    `buildings` [{"footprint": ring, "height_m"}] from (footprint (Q, 2), height_m) pairs
    (simulations). Absent inputs give absent fields.
    """
    out: dict[str, Any] = {}
    if fence_en_m is not None and len(fence_en_m):
        out["geofence"] = _ring_lat_lon(origin, fence_en_m)
    if no_fly_en_m is not None and len(no_fly_en_m):
        out["no_fly_zones"] = [_ring_lat_lon(origin, z) for z in no_fly_en_m]
    if alt_min_m is not None and alt_max_m is not None:
        out["altitude_band_m"] = {"min_m": float(alt_min_m), "max_m": float(alt_max_m)}
    if max_distance_m is not None:
        out["max_distance_m"] = float(max_distance_m)
    if buildings:
        out["buildings"] = [{"footprint": _ring_lat_lon(origin, fp), "height_m": float(h)} for fp, h in buildings]
    return out


def _plain(obj: Any) -> Any:
    """numpy scalars and arrays -> plain JSON types."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


# ---------------------------------------------------------------------------------------------
# reader


@dataclass(frozen=True)
class LogUser:
    id: str
    rnti: int
    ground_alt_m: float


@dataclass(frozen=True)
class LogVehicle:
    """A fleet's vehicle as its log header lists it: its id, its own home (None when not logged)
    and its altitude band above the mission's home [m] (None when not logged)."""

    id: str
    home: Origin | None = None
    alt_min_m: float | None = None
    alt_max_m: float | None = None


@dataclass(frozen=True)
class LogHeader:
    start_utc: str
    origin: Origin
    users: list[LogUser]
    mu: int | None
    fs_hz: float | None
    noise: NoiseModel
    has_noise: bool
    config: dict
    #: optional area fields (docs/design.md §10 header; absent in older logs): geofence and each no-fly
    #: zone as open rings [[lat_deg, lon_deg], ...]; altitude band {"min_m", "max_m"} above home;
    #: max distance from home [m]; buildings [{"footprint": ring, "height_m"}] (simulations)
    geofence: list[list[float]] | None = None
    no_fly_zones: list[list[list[float]]] = field(default_factory=list)
    altitude_band_m: dict | None = None
    max_distance_m: float | None = None
    buildings: list[dict] = field(default_factory=list)
    #: a fleet's vehicles, index = vehicle number (empty: one vehicle, vehicle 0)
    vehicles: list[LogVehicle] = field(default_factory=list)

    def user_index(self) -> dict[str, int]:
        return {u.id: i for i, u in enumerate(self.users)}

    @property
    def n_vehicles(self) -> int:
        """How many vehicles the mission flew: the header's `vehicles`, or 1 without them."""
        return max(1, len(self.vehicles))


@dataclass
class MissionLog:
    """A parsed mission log.

    rtt_*: one entry per `rtt` record, in file order: rtt_t_s (M,), rtt_user (M,) user indices,
    rtt_uav_lla (M, 3) lat_deg/lon_deg/alt_m, rtt_toa_s (M,), rtt_raw: list of the raw-field dicts.
    rtt_vehicle (M,): each rtt record's vehicle (0 where a record names none).
    tel_t_s (T,), tel_lla (T, 3): telemetry; tel_vehicle (T,): its vehicle (0 where it names none),
    each vehicle's records a track of their own (:meth:`vehicle_telemetry`); tel_vel_ned_mps (T, 3):
    the autopilot's velocity (north, east, down) [m/s], NaN rows where a record has none;
    tel_status: the vehicle's health each telemetry record carries (all fields None in a log
    written before them). truth_lla: (K, 3) or None (NaN rows for users absent). t_start_s: the
    header's time; t_last_s: the last record's time [s].
    """

    path: Path
    header: LogHeader
    rtt_t_s: np.ndarray
    rtt_user: np.ndarray
    rtt_uav_lla: np.ndarray
    rtt_toa_s: np.ndarray
    rtt_raw: list[dict]
    tel_t_s: np.ndarray
    tel_lla: np.ndarray
    truth_lla: np.ndarray | None
    tel_vel_ned_mps: np.ndarray | None = None
    tel_status: list[VehicleStatus] = field(default_factory=list)
    estimates: list[dict] = field(default_factory=list)
    waypoints: list[dict] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)
    skipped_torn_line: int | None = None
    t_start_s: float = 0.0
    t_last_s: float = 0.0
    rtt_vehicle: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    tel_vehicle: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    #: the GPS error's correlation time [s] the flight's estimator used (its last `gps_tau` event's
    #: `gps_tau_s`), None when the log holds none (replay then estimates it: mission.replay.resolve_gps_tau)
    gps_tau_s: float | None = None
    #: rtt records dropped as exact repeats of an earlier one (same user, vehicle, time and values),
    #: and the line of the first one dropped (None: none)
    duplicate_rtt: int = 0
    duplicate_rtt_line: int | None = None
    #: `channel` records (`sim --oai`: each rfsim distance set; mission.channel.check_channel_record)
    channel: list[dict] = field(default_factory=list)

    @property
    def n_vehicles(self) -> int:
        """How many vehicles the mission flew (LogHeader.n_vehicles)."""
        return self.header.n_vehicles

    def vehicle_telemetry(self, vehicle: int) -> np.ndarray:
        """(T_v,) indices of vehicle `vehicle`'s telemetry records, in file (= its time) order."""
        return np.flatnonzero(self.tel_vehicle == vehicle)

    def last_event(self, kind: str) -> dict | None:
        """The last `event` record of this kind, or None."""
        return next((e for e in reversed(self.events) if e.get("kind") == kind), None)

    @property
    def n_users(self) -> int:
        return len(self.header.users)

    def user_up_m(self) -> np.ndarray:
        """(K,) ENU up of each user's ground [m] (ground_alt_m − origin altitude)."""
        return np.array([u.ground_alt_m - self.header.origin.alt_m for u in self.header.users])


def _num(obj: dict, key: str, lo: float = -math.inf, hi: float = math.inf, required: bool = True):
    if key not in obj:
        if required:
            raise _LineError(f"missing field {key!r}")
        return None
    v = obj[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise _LineError(f"field {key!r} must be a number, got {v!r}")
    if not math.isfinite(v):
        raise _LineError(f"field {key!r} must be finite, got {v!r}")
    if not lo <= v <= hi:
        raise _LineError(f"field {key!r} = {v!r} is outside [{lo}, {hi}]")
    return float(v)


def _table(obj: dict, key: str) -> dict:
    v = obj.get(key)
    if not isinstance(v, dict):
        raise _LineError(f"field {key!r} must be an object, got {v!r}")
    return v


#: the altitudes [m AMSL] a log's positions may hold (the writer's estimate records keep to them too)
ALT_MIN_M, ALT_MAX_M = -1000.0, 100_000.0


def _lla(d: dict, what: str) -> tuple[float, float, float]:
    try:
        return (_num(d, "lat_deg", -90, 90), _num(d, "lon_deg", -180, 180), _num(d, "alt_m", ALT_MIN_M, ALT_MAX_M))
    except _LineError as exc:
        raise _LineError(f"{what}: {exc}") from None


def _parse_header(obj: dict) -> LogHeader:
    fmt = obj.get("format")
    if fmt != FORMAT:
        raise _LineError(f"format is {fmt!r}, this reader reads {FORMAT!r}")
    origin_d = _table(obj, "origin")
    lat, lon, alt = _lla(origin_d, "origin")
    users_d = obj.get("users")
    if not isinstance(users_d, list) or not users_d:
        raise _LineError(f"field 'users' must be a non-empty list, got {users_d!r}")
    users: list[LogUser] = []
    for i, u in enumerate(users_d):
        if not isinstance(u, dict) or not isinstance(u.get("id"), str) or not u["id"]:
            raise _LineError(f"users[{i}] needs a string 'id', got {u!r}")
        rnti = u.get("rnti")
        if isinstance(rnti, str):
            try:
                rnti = int(rnti, 16 if not rnti.lower().startswith("0x") else 0)
            except ValueError:
                raise _LineError(f"users[{i}].rnti is not a number: {u.get('rnti')!r}") from None
        if isinstance(rnti, bool) or not isinstance(rnti, int) or not 0 <= rnti <= 0xFFFF:
            raise _LineError(f"users[{i}].rnti must be an integer 0..0xFFFF, got {u.get('rnti')!r}")
        try:
            ground = _num(u, "ground_alt_m", -1000, 100_000)
        except _LineError as exc:
            raise _LineError(f"users[{i}]: {exc}") from None
        users.append(LogUser(u["id"], rnti, ground))
    if len({u.id for u in users}) != len(users):
        raise _LineError("user ids in the header are not unique")
    radio = obj.get("radio", {})
    if not isinstance(radio, dict):
        raise _LineError(f"field 'radio' must be an object, got {radio!r}")
    mu = radio.get("mu")
    if mu is not None and (isinstance(mu, bool) or mu not in (0, 1, 2, 3)):
        raise _LineError(f"radio.mu must be 0..3, got {mu!r}")
    fs = _num(radio, "fs_hz", 1.0, 1e12, required=False)
    noise_d = obj.get("noise")
    if noise_d is not None and not isinstance(noise_d, dict):
        raise _LineError(f"field 'noise' must be an object, got {noise_d!r}")
    try:
        noise = NoiseModel.from_log_dict(noise_d)
    except UavlocError as exc:
        raise _LineError(str(exc)) from None
    config = obj.get("config", {})
    start = obj.get("start_utc", "")
    if not isinstance(start, str):
        raise _LineError(f"start_utc must be a string, got {start!r}")
    return LogHeader(start, Origin(lat, lon, alt), users, mu, fs, noise, noise_d is not None,
                     config if isinstance(config, dict) else {"value": config}, **_parse_area(obj),
                     vehicles=_parse_vehicles(obj))


def _parse_vehicles(obj: dict) -> list[LogVehicle]:
    """The header's optional fleet `vehicles` [{"id", "home"?, "alt_min_m"?, "alt_max_m"?}]."""
    if "vehicles" not in obj:
        return []
    vs = obj["vehicles"]
    if not isinstance(vs, list) or not vs:
        raise _LineError(f"field 'vehicles' must be a non-empty list, got {vs!r}")
    out = []
    for i, v in enumerate(vs):
        if not isinstance(v, dict) or not isinstance(v.get("id"), str) or not v["id"]:
            raise _LineError(f"vehicles[{i}] needs a string 'id', got {v!r}")
        home = None
        if "home" in v:
            home = Origin(*_lla(_table(v, "home"), f"vehicles[{i}].home"))
        try:
            lo = _num(v, "alt_min_m", -1000, 100_000, required=False)
            hi = _num(v, "alt_max_m", -1000, 100_000, required=False)
        except _LineError as exc:
            raise _LineError(f"vehicles[{i}]: {exc}") from None
        if lo is not None and hi is not None and lo > hi:
            raise _LineError(f"vehicles[{i}]: alt_min_m {lo} is above alt_max_m {hi}")
        out.append(LogVehicle(v["id"], home, lo, hi))
    if len({v.id for v in out}) != len(out):
        raise _LineError("vehicle ids in the header are not unique")
    return out


#: record types that name their vehicle in a fleet's log (`"vehicle": <index>`; absent: 0)
VEHICLE_RECORD_TYPES = ("telemetry", "rtt", "waypoint", "event")


#: record types a fleet's log must name the vehicle of (a range or fix of no vehicle has no track)
VEHICLE_REQUIRED_TYPES = ("telemetry", "rtt")


def _vehicle(obj: dict, header: LogHeader) -> int:
    """The record's vehicle index: its `vehicle` field, 0 when absent; an integer within the
    header's vehicles (0 alone without them). A fleet's telemetry and rtt records must name theirs."""
    if "vehicle" not in obj and header.vehicles and obj.get("type") in VEHICLE_REQUIRED_TYPES:
        raise _LineError(f"{obj['type']} record names no 'vehicle', but the header lists {len(header.vehicles)} "
                         f"vehicles ({', '.join(v.id for v in header.vehicles)}): a fleet's {obj['type']} records each "
                         "name their vehicle (refused: its track cannot be told)")
    v = obj.get("vehicle", 0)
    if isinstance(v, bool) or not isinstance(v, int):
        raise _LineError(f"field 'vehicle' must be an integer vehicle index, got {v!r}")
    n = header.n_vehicles
    if not 0 <= v < n:
        listed = (f"the header lists {n} vehicles (0..{n - 1})" if header.vehicles
                  else "the header lists no vehicles (one vehicle: 0)")
        raise _LineError(f"field 'vehicle' = {v!r} is out of range: {listed}")
    return v


def _ring(v: Any, what: str) -> list[list[float]]:
    if not isinstance(v, list) or len(v) < 3:
        raise _LineError(f"{what} must be a list of >= 3 [lat_deg, lon_deg] points, got {v!r}")
    out = []
    for i, p in enumerate(v):
        if not isinstance(p, list) or len(p) != 2:
            raise _LineError(f"{what}[{i}] must be [lat_deg, lon_deg], got {p!r}")
        try:
            out.append([_num({"lat_deg": p[0]}, "lat_deg", -90, 90), _num({"lon_deg": p[1]}, "lon_deg", -180, 180)])
        except _LineError as exc:
            raise _LineError(f"{what}[{i}]: {exc}") from None
    return out


def _parse_area(obj: dict) -> dict:
    """The header's optional area fields, checked (see LogHeader)."""
    out: dict[str, Any] = {}
    if "geofence" in obj:
        out["geofence"] = _ring(obj["geofence"], "geofence")
    zones = obj.get("no_fly_zones", [])
    if not isinstance(zones, list):
        raise _LineError(f"no_fly_zones must be a list of rings, got {zones!r}")
    out["no_fly_zones"] = [_ring(z, f"no_fly_zones[{i}]") for i, z in enumerate(zones)]
    if "altitude_band_m" in obj:
        band = _table(obj, "altitude_band_m")
        lo, hi = _num(band, "min_m", -1000, 100_000), _num(band, "max_m", -1000, 100_000)
        if lo > hi:
            raise _LineError(f"altitude_band_m min_m {lo} is above max_m {hi}")
        out["altitude_band_m"] = {"min_m": lo, "max_m": hi}
    if "max_distance_m" in obj:
        out["max_distance_m"] = _num(obj, "max_distance_m", 0.0, 1e7)
    blds = obj.get("buildings", [])
    if not isinstance(blds, list):
        raise _LineError(f"buildings must be a list, got {blds!r}")
    out["buildings"] = []
    for i, b in enumerate(blds):
        if not isinstance(b, dict):
            raise _LineError(f"buildings[{i}] must be an object, got {b!r}")
        try:
            h = _num(b, "height_m", 0.0, 10_000)
        except _LineError as exc:
            raise _LineError(f"buildings[{i}]: {exc}") from None
        out["buildings"].append({"footprint": _ring(b.get("footprint"), f"buildings[{i}].footprint"), "height_m": h})
    return out


#: record types whose times must not go back: the track and the odometer are built from them in
#: file order; uavloc and `uavloc import` write them in time order, and a shuffled or spliced log
#: shows there. (rtt records are not checked: a trigger's records carry each measurement's own
#: time, which in stock mode is the user's random access and may precede the one logged before it.)
TIME_ORDERED_TYPES = ("telemetry",)
#: how far an rtt record may go back in time from the latest one before it [s]: a trigger's records
#: carry each measurement's own time (a stock random access read seconds late from a block-buffered
#: gNB log, a trace mode SRS occasion, records of a slow trigger on a loaded machine), so some
#: disorder is real; half a minute is a shuffled or spliced log, whose ranges would sit on a track
#: never flown (refused, not sorted)
RTT_DISORDER_MAX_S = 30.0

#: largest speed a telemetry velocity may claim [m/s]
MAX_SPEED_MPS = 200.0


def _velocity(obj: dict) -> tuple[float, float, float]:
    """Optional `vel_ned_mps` [north, east, down] of a telemetry record; NaNs when absent."""
    v = obj.get("vel_ned_mps")
    if v is None:
        return (math.nan, math.nan, math.nan)
    if (not isinstance(v, list) or len(v) != 3
            or not all(isinstance(c, int | float) and not isinstance(c, bool) for c in v)
            or not all(math.isfinite(c) and abs(c) <= MAX_SPEED_MPS for c in v)):
        raise _LineError(f"vel_ned_mps must be 3 finite numbers within ±{MAX_SPEED_MPS:g} m/s, got {v!r}")
    return (float(v[0]), float(v[1]), float(v[2]))


def _rtt_toa(obj: dict, header: LogHeader) -> tuple[float, dict]:
    raw = {k: obj[k] for k in ("ta", "mu", "srs_peak", "fs_hz", "snr_db") if k in obj}
    if "toa_s" in obj:
        return _num(obj, "toa_s", 0.0, 1e-3), raw
    if "ta" not in obj:
        raise _LineError("rtt record has neither 'toa_s' nor the raw 'ta' field")
    mu = obj.get("mu", header.mu)
    fs = obj.get("fs_hz", header.fs_hz)
    peak = obj.get("srs_peak", 0.0)
    if mu is None:
        raise _LineError("rtt record has raw 'ta' but no 'mu' (neither in the record nor the header radio)")
    if fs is None and peak:
        raise _LineError("rtt record has 'srs_peak' but no 'fs_hz' (neither in the record nor the header)")
    try:
        return toa_s_from_raw(obj["ta"], mu, peak, fs if fs is not None else 1.0), raw
    except UavlocError as exc:
        raise _LineError(f"raw ranging fields are unusable: {exc}") from None


def iter_log_objects(fh: TextIO, path: Path) -> Iterator[tuple[int, dict | None, str]]:
    """Yield (line_number, object, line) for each non-empty line; object None for a torn last line."""
    lines = fh.readlines()
    last = len(lines)
    while last > 0 and not lines[last - 1].strip():
        last -= 1
    for i, line in enumerate(lines[:last], start=1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            if i == last and not line.endswith("\n"):
                yield i, None, line
                continue
            raise MissionLogError(f"{path}:{i}: not valid JSON ({exc.msg} at column {exc.colno})") from None
        except RecursionError:
            # json's parser recurses once per nesting level; a record is a few levels deep
            raise MissionLogError(f"{path}:{i}: JSON nested too deeply to be a record (Python's JSON reader "
                                  f"gives up after about {sys.getrecursionlimit()} levels)") from None
        if not isinstance(obj, dict):
            raise MissionLogError(f"{path}:{i}: a record must be a JSON object, got {type(obj).__name__}")
        yield i, obj, line


def read_mission_log(path: str | Path) -> MissionLog:
    """Parse a `uavloc-mission/1` log strictly (see the module docstring)."""
    path = Path(path)
    try:
        fh = path.open("r", encoding="utf-8")
    except OSError as exc:
        raise MissionLogError(f"cannot open mission log {path}: {exc}") from exc

    header: LogHeader | None = None
    user_ix: dict[str, int] = {}
    rtt_t, rtt_user, rtt_lla, rtt_toa, rtt_raw, rtt_veh = [], [], [], [], [], []
    tel_t, tel_lla, tel_vel, tel_status, tel_veh = [], [], [], [], []
    truth: np.ndarray | None = None
    estimates, waypoints, events, channel = [], [], [], []
    torn: int | None = None
    t_start = t_last = 0.0
    # (record type, vehicle) -> (time, line) of the latest one
    last_t: dict[tuple[str, int], tuple[float, int]] = {}
    ranges = RangeRecords(path)
    gps_tau: float | None = None
    with fh:
        try:
            for lineno, obj, _line in iter_log_objects(fh, path):
                if obj is None:
                    log.warning("%s:%d: skipping a torn last line (no newline, not JSON)", path, lineno)
                    torn = lineno
                    continue
                try:
                    rtype = obj.get("type")
                    if rtype not in RECORD_TYPES:
                        raise _LineError(f"unknown record type {rtype!r}; known: {', '.join(RECORD_TYPES)}")
                    t = _num(obj, "t", 0.0, 1e9)
                    if header is None:
                        if rtype != "header":
                            raise _LineError(f"the first record must be the header, got type {rtype!r}")
                        header = _parse_header(obj)
                        user_ix = header.user_index()
                        t_start = t_last = t
                        continue
                    if rtype == "header":
                        raise _LineError("a second header")
                    vehicle = _vehicle(obj, header) if rtype in VEHICLE_RECORD_TYPES else 0
                    if rtype in TIME_ORDERED_TYPES:
                        prev = last_t.get((rtype, vehicle))
                        if prev is not None and t < prev[0]:
                            whose = f" of vehicle {vehicle}" if header.vehicles else ""
                            raise _LineError(f"{rtype} record{whose} at t = {t:g} s is earlier than the one on line "
                                             f"{prev[1]} (t = {prev[0]:g} s): the log is out of time order "
                                             "(refused, not sorted: its track would be one never flown)")
                        last_t[(rtype, vehicle)] = (t, lineno)
                    if rtype == "rtt":
                        prev = last_t.get(("rtt", vehicle))
                        if prev is not None and t < prev[0] - RTT_DISORDER_MAX_S:
                            raise _LineError(
                                f"rtt record at t = {t:g} s is {prev[0] - t:.1f} s earlier than the one on line "
                                f"{prev[1]} (t = {prev[0]:g} s): range records out of time order by more than "
                                f"{RTT_DISORDER_MAX_S:g} s (refused, not sorted: a shuffled or spliced log)")
                        if prev is None or t > prev[0]:
                            last_t[("rtt", vehicle)] = (t, lineno)
                        uid = obj.get("user")
                        if uid not in user_ix:
                            raise _LineError(f"rtt for unknown user {uid!r}; header users: {sorted(user_ix)}")
                        uav = _lla(_table(obj, "uav"), "uav")
                        toa, raw = _rtt_toa(obj, header)
                        if not ranges.first(lineno, (vehicle, user_ix[uid], t), (toa, uav)):
                            continue
                        rtt_t.append(t)
                        rtt_user.append(user_ix[uid])
                        rtt_lla.append(uav)
                        rtt_toa.append(toa)
                        rtt_raw.append(raw)
                        rtt_veh.append(vehicle)
                    elif rtype == "telemetry":
                        tel_t.append(t)
                        tel_lla.append(_lla(obj, "telemetry"))
                        tel_vel.append(_velocity(obj))
                        try:
                            tel_status.append(VehicleStatus.from_record(obj))
                        except UavlocError as exc:
                            raise _LineError(str(exc)) from None
                        tel_veh.append(vehicle)
                    elif rtype == "truth":
                        truth = _parse_truth(obj, user_ix) if truth is None else truth
                    elif rtype == "estimate":
                        _check_estimate(obj, user_ix, header)
                        estimates.append(obj)
                    elif rtype == "waypoint":
                        waypoints.append(obj)
                    elif rtype == "channel":
                        channel.append(check_channel_record(obj, user_ix))
                    elif rtype == "event":
                        if not isinstance(obj.get("message", ""), str):
                            raise _LineError(f"event message must be a string, got {obj.get('message')!r}")
                        if obj.get("kind") == "gps_tau" and "gps_tau_s" in obj:
                            gps_tau = _num(obj, "gps_tau_s", 0.0, 1e5)
                        events.append(obj)
                    t_last = t
                except _LineError as exc:
                    raise MissionLogError(f"{path}:{lineno}: {exc}") from None
        except UnicodeDecodeError as exc:
            raise MissionLogError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    if header is None:
        raise MissionLogError(f"{path}: empty log, no header line")
    ranges.warn()
    return MissionLog(
        path=path,
        header=header,
        rtt_t_s=np.asarray(rtt_t, float),
        rtt_user=np.asarray(rtt_user, int),
        rtt_uav_lla=np.asarray(rtt_lla, float).reshape(-1, 3),
        rtt_toa_s=np.asarray(rtt_toa, float),
        rtt_raw=rtt_raw,
        tel_t_s=np.asarray(tel_t, float),
        tel_lla=np.asarray(tel_lla, float).reshape(-1, 3),
        truth_lla=truth,
        tel_vel_ned_mps=np.asarray(tel_vel, float).reshape(-1, 3),
        tel_status=tel_status,
        estimates=estimates,
        waypoints=waypoints,
        events=events,
        skipped_torn_line=torn,
        t_start_s=t_start,
        t_last_s=t_last,
        rtt_vehicle=np.asarray(rtt_veh, int),
        tel_vehicle=np.asarray(tel_veh, int),
        gps_tau_s=gps_tau,
        duplicate_rtt=ranges.dropped,
        duplicate_rtt_line=ranges.first_dropped_line,
        channel=channel,
    )


def _parse_truth(obj: dict, user_ix: dict[str, int]) -> np.ndarray:
    users = obj.get("users")
    if not isinstance(users, list):
        raise _LineError(f"truth 'users' must be a list, got {users!r}")
    out = np.full((len(user_ix), 3), np.nan)
    for i, u in enumerate(users):
        if not isinstance(u, dict) or u.get("id") not in user_ix:
            raise _LineError(f"truth users[{i}] names an unknown user: {u!r}")
        out[user_ix[u["id"]]] = _lla(u, f"truth users[{i}]")
    return out


def _check_estimate(obj: dict, user_ix: dict[str, int], header: LogHeader) -> None:
    users = obj.get("users")
    if not isinstance(users, list):
        raise _LineError(f"estimate 'users' must be a list, got {users!r}")
    for i, u in enumerate(users):
        if not isinstance(u, dict) or u.get("id") not in user_ix:
            raise _LineError(f"estimate users[{i}] names an unknown user: {u!r}")
        _lla(u, f"estimate users[{i}]")
        cov = u.get("cov_en_m2")
        ok = (isinstance(cov, list) and len(cov) == 2
              and all(isinstance(r, list) and len(r) == 2 for r in cov)
              and all(isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
                      for r in cov for x in r))
        if not ok:
            raise _LineError(f"estimate users[{i}].cov_en_m2 must be a 2x2 list of finite numbers, got {cov!r}")
        shift = u.get("nlos_shift_m", 0.0)
        if isinstance(shift, bool) or not isinstance(shift, int | float) or not (math.isfinite(shift) and shift >= 0):
            raise _LineError(f"estimate users[{i}].nlos_shift_m must be a finite number >= 0, got {shift!r}")
    if "uav_vehicle" in obj:
        uv = obj["uav_vehicle"]
        if not isinstance(uv, list):
            raise _LineError(f"estimate uav_vehicle must be a list of vehicle indices, got {uv!r}")
        uav = obj.get("uav_lla")
        if not isinstance(uav, list) or len(uav) != len(uv):
            n_uav = len(uav) if isinstance(uav, list) else "no"
            raise _LineError(f"estimate uav_vehicle has {len(uv)} entries but uav_lla has {n_uav}: they are parallel")
        for i, v in enumerate(uv):
            try:
                _vehicle({"vehicle": v}, header)
            except _LineError as exc:
                raise _LineError(f"estimate uav_vehicle[{i}]: {exc}") from None
