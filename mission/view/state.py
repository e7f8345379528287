"""What the live view shows, as a pure model fed with mission-log records (docs/design.md §10).

:class:`ViewState` takes the records a :class:`mission.log.MissionLogWriter` writes (live, as a
listener) or a recorded log holds (`uavloc view LOG`), one by one, and keeps what the page draws in
the ENU frame of the header's origin (east, north, up; metres):

- static: geofence, no-fly zones, buildings, altitude band, max distance, the users, and the true
  users (simulation only);
- the GPS track (telemetry) and the estimated track (the estimator's corrected keyframes);
- per vehicle (:class:`VehicleView`): its id and home, its position, the next waypoint and the leg
  to it, its health (:class:`VehicleHealth`, from its newest `telemetry` record: altitudes,
  speeds, heading, battery, flight mode, armed, GPS), the age of its newest vehicle and gNB
  records and its measurements of the last minute (all in mission seconds), and whether it lost
  its link, is returning or has landed;
- each user's estimate with its 95 % ellipse, σ, ambiguity flag and measurement count;
- mission state, metres flown, measurements, keyframes, the events (RTL reasons, gNB lost, ...).

A fleet (docs/fleet.md): the header's optional `vehicles` list names each vehicle (index = vehicle
number) and its home; `telemetry`, `rtt`, `waypoint` and `event` records name their vehicle
(`"vehicle": k`, absent: 0), an estimate's `uav_vehicle` the vehicle of each `uav_lla` row. A
record naming a vehicle the header did not list adds it. A track item carries its vehicle as a
last element when it is not vehicle 0, so a one-vehicle mission's frames are those of before
fleets, with `vehicles` added (tests/data/view_one_vehicle.json).

:meth:`ViewState.frame` turns it into a JSON-able document. Long series (tracks, events) are sent
incrementally: a frame carries only what a client's :class:`Cursor` has not seen, so a client
that skipped frames still ends with the whole picture. No I/O, no clock, no asyncio.

95 % ellipse of a user with east-north covariance Σ (2×2), eigenpairs (λ₁ ≤ λ₂, v₁, v₂):

    semi-axes a = √(χ²₂(0.95)·λ₂), b = √(χ²₂(0.95)·λ₁), major axis along v₂

so `a` is the same r95 as :meth:`estimator.types.Estimate.error_bound_95_m` and the JSON result's
`error_bound_95_m`.
"""

from __future__ import annotations

import bisect
import copy
import math
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pymap3d

from estimator.geodesy import Origin
from estimator.types import CHI2_2DOF_95
from mission.vehicle.telemetry import GPS_FIX_NAMES, Odometer, VehicleStatus
from uavloc.errors import MissionError

_WGS84 = pymap3d.Ellipsoid.from_name("wgs84")

#: metres flown without a `flown_m` field in the log: odometer dead band [m]
FALLBACK_DEAD_BAND_M = 5.0
#: the newest vehicle record is stale after the controller's link timeout (safety.link_timeout_s),
#: this when the header has none [mission s]
VEHICLE_STALE_S = 3.0
#: the newest gNB measurement is stale after this [mission s] (the simulated and OAI gNBs range
#: several times a second while the UE is attached)
GNB_STALE_S = 5.0
#: window of the measurement rate [mission s]
RATE_WINDOW_S = 60.0
#: the most vehicles a log can name (MAVLink system ids are 1..255); a record naming a higher
#: index is skipped
MAX_VEHICLES = 255


@dataclass(frozen=True)
class VehicleHealth:
    """The instrument strip: the newest `telemetry` record's numbers (None where the record has
    none: an autopilot that does not send it, or a log written before the field).

    rel_alt_m: above home (the autopilot's relative altitude; the ENU up of the fix in a log
    without it); alt_amsl_m: the fix's altitude; groundspeed_mps, climb_mps (up positive): from
    vel_ned_mps; gps_fix: GPS_FIX_NAMES of gps_fix_type."""

    t_s: float
    alt_amsl_m: float
    rel_alt_m: float | None
    groundspeed_mps: float | None
    climb_mps: float | None
    heading_deg: float | None
    battery_pct: float | None
    battery_voltage_v: float | None
    flight_mode: str | None
    armed: bool | None
    gps_fix_type: int | None
    gps_fix: str | None
    gps_satellites: int | None

    @classmethod
    def of(cls, rec: dict, up_m: float) -> VehicleHealth:
        """From a telemetry record (VehicleStatus fields checked) and the fix's ENU up [m]."""
        st = VehicleStatus.from_record(rec)
        vel = rec.get("vel_ned_mps")
        ok = isinstance(vel, list) and len(vel) == 3 and all(isinstance(v, int | float) for v in vel)
        fix = st.gps_fix_type
        return cls(t_s=float(rec["t"]), alt_amsl_m=float(rec["alt_m"]),
                   rel_alt_m=st.rel_alt_m if st.rel_alt_m is not None else up_m,
                   groundspeed_mps=math.hypot(vel[0], vel[1]) if ok else None, climb_mps=0.0 - vel[2] if ok else None,
                   heading_deg=st.heading_deg, battery_pct=st.battery_pct, battery_voltage_v=st.battery_voltage_v,
                   flight_mode=st.flight_mode, armed=st.armed, gps_fix_type=fix,
                   gps_fix=None if fix is None else GPS_FIX_NAMES.get(fix, str(fix)), gps_satellites=st.gps_satellites)


def ellipse_95(cov_en_m2) -> dict:
    """The 95 % error ellipse of a (2, 2) east-north covariance [m²].

    Returns {"a_m": semi-major, "b_m": semi-minor, "angle_deg": major axis from east towards north,
    "sigma_major_m": √λ₂, "sigma_minor_m": √λ₁}.
    """
    cov = np.asarray(cov_en_m2, float).reshape(2, 2)
    cov = 0.5 * (cov + cov.T)
    lam, vec = np.linalg.eigh(cov)
    lam = np.maximum(lam, 0.0)
    # a = √(χ²·λ₂), b = √(χ²·λ₁); major axis v₂ = vec[:, 1]
    major = vec[:, 1]
    return {"a_m": math.sqrt(CHI2_2DOF_95 * lam[1]), "b_m": math.sqrt(CHI2_2DOF_95 * lam[0]),
            "angle_deg": math.degrees(math.atan2(major[1], major[0])),
            "sigma_major_m": math.sqrt(lam[1]), "sigma_minor_m": math.sqrt(lam[0])}


class Series:
    """An append-only list that may be replaced as a whole (then its generation changes)."""

    def __init__(self, max_len: int | None = None):
        self.items: list = []
        self.generation = 0
        self.max_len = max_len

    def append(self, item: Any) -> None:
        self.items.append(item)
        if self.max_len is not None and len(self.items) > self.max_len:
            # drop the oldest half at once (a new generation: clients take the whole list again)
            self.items = self.items[len(self.items) - self.max_len // 2:]
            self.generation += 1

    def copy(self) -> Series:
        """An independent copy (the items themselves are never changed once appended)."""
        new = Series(self.max_len)
        new.items, new.generation = list(self.items), self.generation
        return new

    def replace(self, items: list) -> None:
        self.items = list(items)
        self.generation += 1

    def since(self, seen: tuple[int, int] | None) -> tuple[dict, tuple[int, int]]:
        """({"gen", "from", "items"}, new cursor) with what a client that saw `seen` lacks."""
        start = 0
        if seen is not None and seen[0] == self.generation and seen[1] <= len(self.items):
            start = seen[1]
        return ({"gen": self.generation, "from": start, "items": self.items[start:]},
                (self.generation, len(self.items)))


@dataclass
class Cursor:
    """What one client has seen: the static part's version and each series' (generation, length)."""

    static: int = -1
    series: dict[str, tuple[int, int]] = field(default_factory=dict)

    def key(self) -> tuple:
        """Hashable: clients with equal keys need the same frame."""
        return (self.static, tuple(sorted(self.series.items())))


def _r(x: float, nd: int = 2) -> float:
    return round(float(x), nd)


def vehicle_index(rec: dict, key: str = "vehicle") -> int:
    """The vehicle a record names (`rec[key]`, absent: 0); ValueError for anything but an integer
    in [0, MAX_VEHICLES)."""
    v = rec.get(key, 0)
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < MAX_VEHICLES:
        raise ValueError(f"{key} must be an integer in [0, {MAX_VEHICLES}), got {v!r}")
    return v


class VehicleView:
    """One vehicle's part of the view: what its own records say.

    index: its number in the log; id: the header's name for it (`vehicle K` when the header names
    none); home_enu_m: its home [m] (the origin for a one-vehicle mission; None when unknown);
    vehicle: {"t", "enu_m", "vel_en_mps"} of its newest fix; health: its newest status;
    waypoint: its next waypoint and leg; returning, landed, link_lost: from its events (`rtl` or
    `return`, `landed`, `link_lost` until `link_restored`)."""

    def __init__(self, index: int, vid: str | None = None, home_enu_m: list[float] | None = None):
        self.index = index
        self.id = vid if vid else f"vehicle {index}"
        self.home_enu_m = home_enu_m
        self.vehicle: dict | None = None
        self.health: VehicleHealth | None = None
        self.waypoint: dict | None = None
        self.last_rtt_t_s: float | None = None
        self.rtt_times: deque[float] = deque()  # measurement times of the last RATE_WINDOW_S
        self.odometer = Odometer(FALLBACK_DEAD_BAND_M)
        self.returning = False
        self.landed = False
        self.link_lost = False

    def copy(self) -> VehicleView:
        new = copy.copy(self)
        new.rtt_times = deque(self.rtt_times)
        new.odometer = copy.copy(self.odometer)
        return new

    def ranged(self, t_s: float) -> None:
        """A range measured by this vehicle's gNB at t_s [mission s]."""
        self.last_rtt_t_s = t_s if self.last_rtt_t_s is None else max(self.last_rtt_t_s, t_s)
        self.rtt_times.append(t_s)
        while self.rtt_times and self.rtt_times[0] <= self.last_rtt_t_s - RATE_WINDOW_S:
            self.rtt_times.popleft()

    def health_frame(self, t_s: float, vehicle_stale_s: float) -> dict | None:
        """The instrument strip at mission time t_s: VehicleHealth, the ages of the newest vehicle
        and gNB records [mission s] (and whether they are stale), measurements in the last minute."""
        if self.health is None and self.last_rtt_t_s is None:
            return None
        out: dict[str, Any] = asdict(self.health) if self.health is not None else {}
        for k, v in list(out.items()):
            if isinstance(v, float):
                out[k] = _r(v, 3)
        veh_age = None if self.health is None else max(0.0, t_s - self.health.t_s)
        gnb_age = None if self.last_rtt_t_s is None else max(0.0, t_s - self.last_rtt_t_s)
        t0 = t_s - RATE_WINDOW_S
        out.update({
            "vehicle_age_s": None if veh_age is None else _r(veh_age, 2),
            "vehicle_stale": veh_age is None or veh_age > vehicle_stale_s,
            "vehicle_stale_after_s": vehicle_stale_s,
            "gnb_age_s": None if gnb_age is None else _r(gnb_age, 2),
            "gnb_stale": gnb_age is None or gnb_age > GNB_STALE_S,
            "gnb_stale_after_s": GNB_STALE_S,
            "measurements_per_min": sum(1 for t in self.rtt_times if t > t0),
        })
        return out

    def frame(self, t_s: float, vehicle_stale_s: float) -> dict:
        return {"index": self.index, "id": self.id, "home_enu_m": self.home_enu_m, "vehicle": self.vehicle,
                "waypoint": self.waypoint, "health": self.health_frame(t_s, vehicle_stale_s),
                "returning": self.returning, "landed": self.landed, "link_lost": self.link_lost}


class ViewState:
    """See the module docstring. Feed records with :meth:`apply`; read with :meth:`frame`.

    Records that do not fit (no header yet, unknown user, missing numbers) are skipped: the view
    shows what it can and never stops the mission log (the log reader is the strict judge).
    """

    def __init__(self, max_events: int = 500):
        self.origin: Origin | None = None
        self.static: dict = {}
        self.static_version = 0
        self.t_s = 0.0
        self.track = Series()  # [t, e, n, u] GPS track, [t, e, n, u, k] of vehicle k > 0
        self.est_track = Series()  # [e, n, u] corrected keyframes, [e, n, u, k] of vehicle k > 0
        self.events = Series(max_events)  # {"t", "message", "kind", "state"[, "vehicle"]}
        self.fleet: list[VehicleView] = []  # by vehicle index; one once the header is read
        self.vehicle_stale_s = VEHICLE_STALE_S
        self.stop_bounds: dict | None = None  # {"t", "r95_m": {user: r95}} when the stop rule fired
        self.users: dict[str, dict] = {}
        self.user_ids: list[str] = []
        self.meas_per_user: dict[str, int] = {}
        self.measurements = 0
        self.keyframes = 0
        self.state = "CONNECT"
        self.status: str | None = None
        self.reason: str | None = None  # why the mission ended (the `end` event's reason)
        self.final = False
        self.flown_m = 0.0
        self._flown_from_log = False
        self.records = 0
        self.version = 0  # bumps with every record applied

    def copy(self) -> ViewState:
        """An independent copy. Cheap: records replace the model's values rather than change them,
        so only the containers are copied."""
        new = copy.copy(self)
        new.static = dict(self.static)
        new.track, new.est_track, new.events = self.track.copy(), self.est_track.copy(), self.events.copy()
        new.users, new.meas_per_user = dict(self.users), dict(self.meas_per_user)
        new.fleet = [v.copy() for v in self.fleet]
        return new

    # vehicle 0's, as the state held them before fleets
    @property
    def vehicle(self) -> dict | None:
        return self.fleet[0].vehicle if self.fleet else None

    @property
    def health(self) -> VehicleHealth | None:
        return self.fleet[0].health if self.fleet else None

    @property
    def waypoint(self) -> dict | None:
        return self.fleet[0].waypoint if self.fleet else None

    def vehicle_view(self, index: int) -> VehicleView:
        """Vehicle `index`'s part, added (with those below it) when no record named it yet."""
        if not 0 <= index < MAX_VEHICLES:
            raise ValueError(f"vehicle {index!r} is out of [0, {MAX_VEHICLES})")
        while len(self.fleet) <= index:
            self.fleet.append(VehicleView(len(self.fleet)))
        return self.fleet[index]

    # -- records --------------------------------------------------------------------------------

    def apply(self, rec: dict) -> None:
        """Take one mission-log record (a dict as in docs/design.md §10)."""
        rtype = rec.get("type")
        t = rec.get("t")
        if isinstance(t, int | float) and math.isfinite(t):
            self.t_s = max(self.t_s, float(t))
        handler = getattr(self, f"_on_{rtype}", None) if isinstance(rtype, str) else None
        if handler is None or (rtype != "header" and self.origin is None):
            return
        try:
            handler(rec)
        except (KeyError, TypeError, ValueError, IndexError):
            return  # a malformed record: shown as far as it goes (the log reader reports it)
        self.records += 1
        self.version += 1

    def _enu(self, d: dict) -> list[float]:
        # pymap3d.geodetic2enu's own two steps (geodetic → ECEF, ECEF offset → ENU) on plain floats,
        # with the origin's ECEF computed once (one record at a time, this is 3x faster)
        o, (x0, y0, z0) = self.origin, self._origin_ecef
        x, y, z = pymap3d.geodetic2ecef(float(d["lat_deg"]), float(d["lon_deg"]), float(d["alt_m"]),
                                        ell=_WGS84, deg=True)
        e, n, u = pymap3d.uvw2enu(x - x0, y - y0, z - z0, o.lat_deg, o.lon_deg, deg=True)
        return [_r(e), _r(n), _r(u)]

    def _ring(self, ring: list) -> list[list[float]]:
        pts = np.asarray(ring, float).reshape(-1, 2)
        enu = self.origin.lla_to_enu(pts[:, 0], pts[:, 1], np.full(len(pts), self.origin.alt_m))
        return [[_r(e), _r(n)] for e, n in enu[:, :2]]

    def _on_header(self, rec: dict) -> None:
        o = rec["origin"]
        self.origin = Origin(float(o["lat_deg"]), float(o["lon_deg"]), float(o["alt_m"]))
        self._origin_ecef = pymap3d.geodetic2ecef(self.origin.lat_deg, self.origin.lon_deg, self.origin.alt_m,
                                                  ell=_WGS84, deg=True)
        cfg = rec.get("config") if isinstance(rec.get("config"), dict) else {}
        ctl = cfg.get("controller") if isinstance(cfg.get("controller"), dict) else {}
        # the controller's flight table (a log before it was nested held its keys at the top)
        ctl = ctl.get("flight") if isinstance(ctl.get("flight"), dict) else ctl
        safety = cfg.get("controller", {}).get("safety") if isinstance(cfg.get("controller"), dict) else None
        link_s = safety.get("link_timeout_s") if isinstance(safety, dict) else None
        if isinstance(link_s, int | float) and not isinstance(link_s, bool) and 0 < link_s < 1e6:
            self.vehicle_stale_s = float(link_s)
        self.user_ids = [str(u["id"]) for u in rec["users"]]
        self._header_vehicles(rec.get("vehicles"))
        self.meas_per_user = dict.fromkeys(self.user_ids, 0)
        self.static = {
            "origin": {"lat_deg": self.origin.lat_deg, "lon_deg": self.origin.lon_deg, "alt_m": self.origin.alt_m},
            "start_utc": rec.get("start_utc"),
            "users": [{"id": str(u["id"]), "rnti": u.get("rnti")} for u in rec["users"]],
            "geofence": self._ring(rec["geofence"]) if rec.get("geofence") else None,
            "no_fly_zones": [self._ring(z) for z in rec.get("no_fly_zones") or []],
            "buildings": [{"footprint": self._ring(b["footprint"]), "height_m": float(b["height_m"])}
                          for b in rec.get("buildings") or []],
            "altitude_band_m": rec.get("altitude_band_m"),
            "max_distance_m": rec.get("max_distance_m"),
            "truth": {},
            "scenario": cfg.get("scenario"),
            "planner": cfg.get("planner"),
            "command": cfg.get("command"),
            "target_radius_m": ctl.get("target_radius_m"),
        }
        self.static_version += 1

    def _header_vehicles(self, listed: Any) -> None:
        """The header's `vehicles` (a fleet: [{"id", "home": {lat_deg, lon_deg, alt_m}}, ...]), or
        one vehicle at home (the origin) without it. What does not fit is left out, not raised."""
        if not isinstance(listed, list) or not listed:
            self.vehicle_view(0).home_enu_m = [0.0, 0.0, 0.0]
            return
        for k, entry in enumerate(listed[:MAX_VEHICLES]):
            v = self.vehicle_view(k)
            if not isinstance(entry, dict):
                continue
            if isinstance(entry.get("id"), str | int) and not isinstance(entry.get("id"), bool):
                v.id = str(entry["id"])
            try:
                v.home_enu_m = self._enu(entry["home"])
            except (KeyError, TypeError, ValueError):
                v.home_enu_m = None

    def _on_truth(self, rec: dict) -> None:
        self.static["truth"] = {str(u["id"]): self._enu(u) for u in rec["users"] if u.get("id") in self.meas_per_user}
        self.static_version += 1

    def _on_telemetry(self, rec: dict) -> None:
        k = vehicle_index(rec)
        p = self._enu(rec)
        t = _r(rec["t"], 3)
        v = self.vehicle_view(k)
        self.track.append([t, *p, k] if k else [t, *p])
        vel = rec.get("vel_ned_mps")
        vel_en = [_r(vel[1]), _r(vel[0])] if isinstance(vel, list) and len(vel) >= 2 else None
        v.vehicle = {"t": t, "enu_m": p, "vel_en_mps": vel_en}
        try:
            v.health = VehicleHealth.of(rec, p[2])
        except MissionError:
            v.health = None  # a malformed status: the strip shows nothing rather than a wrong number
        if not self._flown_from_log and self.state == "SURVEY":
            v.odometer.update(np.asarray(p))
            # the fleet's metres: every vehicle's odometer together
            self.flown_m = sum(u.odometer.total_m for u in self.fleet)

    def _on_rtt(self, rec: dict) -> None:
        uid = rec["user"]
        if uid in self.meas_per_user:
            t = float(rec["t"])
            v = self.vehicle_view(vehicle_index(rec))
            self.meas_per_user[uid] += 1
            self.measurements += 1
            v.ranged(t)

    def _on_estimate(self, rec: dict) -> None:
        for u in rec["users"]:
            uid = str(u["id"])
            if uid not in self.meas_per_user:
                continue
            ell = ellipse_95(u["cov_en_m2"])
            self.users[uid] = {
                "id": uid, "t": _r(rec["t"], 3), "enu_m": self._enu(u),
                "cov_en_m2": [[float(x) for x in row] for row in u["cov_en_m2"]],
                "r95_m": ell["a_m"], "ellipse": {k: ell[k] for k in ("a_m", "b_m", "angle_deg")},
                "sigma_m": ell["sigma_major_m"], "ambiguous": bool(u.get("ambiguous", False)),
            }
        if isinstance(rec.get("keyframes"), int):
            self.keyframes = rec["keyframes"]
        if isinstance(rec.get("flown_m"), int | float):
            self.flown_m = float(rec["flown_m"])
            self._flown_from_log = True
        uav = rec.get("uav_lla")
        if isinstance(uav, list) and uav:
            pts = np.asarray(uav, float).reshape(-1, 3)
            enu = self.origin.lla_to_enu(pts[:, 0], pts[:, 1], pts[:, 2])
            of = rec.get("uav_vehicle")
            if of is None:
                of = [0] * len(pts)
            if not isinstance(of, list) or len(of) != len(pts):
                raise ValueError(f"uav_vehicle must list one vehicle per uav_lla row, got {of!r}")
            ks = [vehicle_index({"k": k}, "k") for k in of]
            for k in set(ks):
                self.vehicle_view(k)
            items = [[_r(e), _r(n), _r(up), k] if k else [_r(e), _r(n), _r(up)]
                     for (e, n, up), k in zip(enu, ks, strict=True)]
            if rec.get("final") or len(items) > 1:
                self.est_track.replace(items)  # the whole smoothed track
            else:
                self.est_track.append(items[0])
        if rec.get("final"):
            self.final = True

    def _on_waypoint(self, rec: dict) -> None:
        k = vehicle_index(rec)
        p = self._enu(rec)
        v = self.vehicle_view(k)
        start = v.vehicle["enu_m"] if v.vehicle is not None else None
        v.waypoint = {"t": _r(rec["t"], 3), "leg": rec.get("leg"), "enu_m": p, "from_enu_m": start,
                      "planner": rec.get("planner"), "status": rec.get("status")}
        if self.state in ("CONNECT", "PREFLIGHT", "TAKEOFF"):
            self.state = "SURVEY"
        if self.state == "SURVEY" and start is not None and not self._flown_from_log:
            v.odometer.start(np.asarray(start))

    def _on_event(self, rec: dict) -> None:
        msg = str(rec.get("message", ""))
        kind = rec.get("kind")
        state = rec.get("state")
        v = self.vehicle_view(vehicle_index(rec))
        # an event naming its vehicle is that vehicle's: its state is not the mission's
        if isinstance(state, str) and state and "vehicle" not in rec:
            self.state = state
        if kind == "end":
            self.status = rec.get("status")
            reason = rec.get("reason")
            self.reason = reason if isinstance(reason, str) and reason else None
        if kind == "stop" and self.stop_bounds is None:
            # the bounds the stop rule judged: the estimate the survey ended on
            self.stop_bounds = {"t": _r(rec["t"], 3), "r95_m": {u: v["r95_m"] for u, v in self.users.items()}}
        if kind in ("rtl", "return"):
            v.returning, v.landed = True, False
        elif kind == "landed":
            v.returning, v.landed = False, True
        elif kind in ("link_lost", "link_restored"):
            v.link_lost = kind == "link_lost"
        if kind in ("rtl", "landed"):
            v.waypoint = None
            # the mission returns once every vehicle does, and has landed once every one has
            if all(u.landed for u in self.fleet):
                self.state = "LANDED"
            elif all(u.returning or u.landed for u in self.fleet):
                self.state = "RETURN"
        item = {"t": _r(rec["t"], 3), "message": msg, "kind": kind, "state": state}
        if "vehicle" in rec:
            item["vehicle"] = v.index
        self.events.append(item)

    # -- output ---------------------------------------------------------------------------------

    def users_frame(self) -> list[dict]:
        out = []
        for uid in self.user_ids:
            u = self.users.get(uid)
            entry = {"id": uid, "measurements": self.meas_per_user.get(uid, 0), "located": u is not None}
            if u is not None:
                entry.update(u)
                truth = self.static.get("truth", {}).get(uid)
                if truth is not None:
                    entry["error_m"] = math.hypot(u["enu_m"][0] - truth[0], u["enu_m"][1] - truth[1])
            out.append(entry)
        return out

    def health_frame(self, index: int = 0) -> dict | None:
        """Vehicle `index`'s instrument strip at the state's time (:meth:`VehicleView.health_frame`)."""
        if index >= len(self.fleet):
            return None
        return self.fleet[index].health_frame(self.t_s, self.vehicle_stale_s)

    def target_frame(self) -> dict | None:
        """The target line: the stop rule's radius and each located user's printed r95 judged
        against it (r95 ≤ target, planner.stop.targets_reached), and the bounds the stop judged."""
        target = self.static.get("target_radius_m")
        if not isinstance(target, int | float) or isinstance(target, bool):
            return None
        within = [uid for uid in self.user_ids if uid in self.users and self.users[uid]["r95_m"] <= target
                  and not self.users[uid]["ambiguous"]]
        return {"radius_m": float(target), "within": within, "users": len(self.user_ids),
                "stop": self.stop_bounds}

    def frame(self, cursor: Cursor | None = None) -> tuple[dict, Cursor]:
        """A JSON-able frame with everything `cursor` has not seen (all of it for None), and the
        client's new cursor.

        vehicles: each vehicle's :meth:`VehicleView.frame`; vehicle, waypoint, health: vehicle 0's
        (as in the frames of before fleets)."""
        cursor = cursor or Cursor()
        new = Cursor(static=self.static_version)
        vehicles = [v.frame(self.t_s, self.vehicle_stale_s) for v in self.fleet]
        first = vehicles[0] if vehicles else {}
        doc: dict[str, Any] = {
            "t": _r(self.t_s, 3), "version": self.version, "state": self.state, "status": self.status,
            "reason": self.reason, "final": self.final, "flown_m": _r(self.flown_m, 1),
            "measurements": self.measurements, "keyframes": self.keyframes,
            "vehicle": first.get("vehicle"), "waypoint": first.get("waypoint"),
            "users": self.users_frame(), "health": first.get("health"), "target": self.target_frame(),
            "vehicles": vehicles,
        }
        if cursor.static != self.static_version and self.static:
            doc["static"] = self.static
        elif not self.static:
            new.static = cursor.static
        for name in ("track", "est_track", "events"):
            part, new.series[name] = getattr(self, name).since(cursor.series.get(name))
            doc[name] = part
        return doc, new


class Timeline:
    """A recorded mission for the time slider: the state after the records up to a mission time.

    records: the log's records in file order. Records are taken as a prefix of the file: those up
    to the last one whose running maximum of `t` is ≤ the chosen time (an `rtt` record carries its
    measurement time, which can be slightly before the record written just ahead of it).
    Moving forward applies only the new records; moving back restarts from the nearest checkpoint
    (a copy of the state kept every `checkpoint_every` records).
    """

    def __init__(self, records: list[dict], checkpoint_every: int = 2000):
        self.records = list(records)
        t_run = -math.inf
        self._t_max: list[float] = []
        for rec in self.records:
            t = rec.get("t")
            if isinstance(t, int | float) and math.isfinite(t):
                t_run = max(t_run, float(t))
            self._t_max.append(t_run)
        self.t_end_s = max(0.0, t_run) if self.records else 0.0
        self._state = ViewState()
        self._applied = 0
        self.checkpoint_every = max(1, int(checkpoint_every))
        self._checkpoints: dict[int, ViewState] = {0: ViewState()}

    def prefix_len(self, t_s: float) -> int:
        """How many records (from the start) belong to time t_s."""
        return bisect.bisect_right(self._t_max, float(t_s))

    def state_at(self, t_s: float) -> ViewState:
        """The ViewState after the records up to t_s (moves forward incrementally, restarts when
        asked for an earlier time)."""
        n = self.prefix_len(t_s)
        start = max(k for k in self._checkpoints if k <= n)
        if n < self._applied or start > self._applied:  # back in time, or a checkpoint ahead
            self._state, self._applied = self._checkpoints[start].copy(), start
        for i in range(self._applied, n):
            self._state.apply(self.records[i])
            if (i + 1) % self.checkpoint_every == 0 and (i + 1) not in self._checkpoints:
                self._checkpoints[i + 1] = self._state.copy()
        self._applied = n
        self._state.t_s = min(max(self._state.t_s, float(t_s)), self.t_end_s) if n else 0.0
        return self._state
