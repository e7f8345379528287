"""What a mission writes down: the mission log's header, events, truth and estimate records
(docs/design.md §10), and the status line on stderr."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from estimator.types import Estimate
from mission.control.config import MissionUser
from mission.log import ALT_MAX_M, ALT_MIN_M, MissionLogWriter

log = logging.getLogger(__name__)


class MissionJournal:
    """The mission log of one flight. Events before the header (home unknown yet) are kept and
    written right after it. now: mission seconds; phase: the flight's phase now."""

    def __init__(self, writer: MissionLogWriter, users: list[MissionUser], now: Callable[[], float],
                 phase: Callable[[], str]):
        self.writer = writer
        self.users = users
        self.now, self.phase = now, phase
        self.messages: list[str] = []
        #: the end record is written (the controller's close, or mission.control.last_resort)
        self.ended = False
        self._pending: list[tuple[float, dict]] = []
        self._last_event_t = -float("inf")

    @property
    def is_open(self) -> bool:
        return self.writer.is_open

    def event(self, message: str, **fields: Any) -> None:
        """An `event` record (kept until the header is written)."""
        # mission time comes from the vehicle clock's mapping of the monotonic clock, refitted as
        # fixes arrive: a refit can put "now" a few ms before the previous event's time. Events are
        # written in the order they happened, so none is stamped before the one written before it
        t = max(self.now(), self._last_event_t)
        self._last_event_t = t
        rec = {"message": message, "state": self.phase(), **fields}
        self.messages.append(message)
        self.ended = self.ended or fields.get("kind") == "end"
        log.debug("event: %s", message)
        if self.is_open:
            self.writer.write("event", t, **rec)
        else:
            self._pending.append((t, rec))

    def open(self, origin: Origin, radio: dict, noise: NoiseModel, config: dict, start_utc: str,
             area: dict | None = None, vehicles: list[dict] | None = None) -> None:
        """The header (origin = home; area: its geofence / no-fly / altitude-band / buildings
        fields, mission.log.area_fields; vehicles: a fleet's [{id, home {lat_deg, lon_deg, alt_m},
        alt_min_m, alt_max_m}], docs/fleet.md), then the events so far."""
        users = [{"id": u.id, "rnti": u.rnti, "ground_alt_m": origin.alt_m + u.up_m} for u in self.users]
        self.writer.open()
        self.writer.write_header(origin, users, radio, noise=noise, config=config, start_utc=start_utc,
                                 area=area, vehicles=vehicles or None)
        for t, rec in self._pending:
            self.writer.write("event", t, **rec)
        self._pending.clear()

    def truth(self, origin: Origin, truth_enu_m: np.ndarray) -> None:
        """Simulation only: the `truth` record of the users' true positions (K, 3) ENU [m]."""
        lat, lon, alt = origin.enu_to_lla(truth_enu_m)
        self.writer.write("truth", self.now(), users=[
            {"id": u.id, "lat_deg": float(lat[k]), "lon_deg": float(lon[k]), "alt_m": float(alt[k])}
            for k, u in enumerate(self.users)])

    def estimate(self, origin: Origin, est: Estimate, keyframes: int, flown_m: float, final: bool = False,
                 vehicles: list[int] | None = None) -> None:
        """An `estimate` record of the located users (with their ambiguity), the metres flown and
        the corrected UAV track (the live view's estimated track): the newest keyframe, all at the end.
        vehicles: a fleet's vehicle of each keyframe (the track's `uav_vehicle`, parallel to `uav_lla`)."""
        if not self.is_open:
            return
        lat, lon, alt = origin.enu_to_lla(est.users_enu_m)
        shift = None if est.state is None else est.state.nlos_shift_m
        users = []
        for k, u in enumerate(self.users):
            cov = est.cov_en_m2(k)
            if not (np.all(np.isfinite(est.users_enu_m[k])) and np.all(np.isfinite(cov))):
                continue
            if not (-90.0 <= lat[k] <= 90.0 and -180.0 <= lon[k] <= 180.0 and ALT_MIN_M <= alt[k] <= ALT_MAX_M):
                # a diverged online estimate (seen: 2e11 m up) locates nobody, and a record the log's
                # reader refuses would cost the mission its replayed final answer
                continue
            entry = {"id": u.id, "lat_deg": float(lat[k]), "lon_deg": float(lon[k]),
                     "alt_m": float(alt[k]), "cov_en_m2": cov.tolist(), "ambiguous": bool(est.ambiguous[k])}
            if shift is not None and shift[k] > 0.0:
                # the part of cov_en_m2 that no survey shrinks (estimator.nlos_shift)
                entry["nlos_shift_m"] = round(float(shift[k]), 4)
            users.append(entry)
        extra: dict[str, Any] = {"final": True} if final else {}
        uav = np.asarray(est.uav_enu_m, float).reshape(-1, 3)
        uav = uav[np.all(np.isfinite(uav), axis=1)]
        if len(uav):
            ulat, ulon, ualt = (np.atleast_1d(a) for a in origin.enu_to_lla(uav if final else uav[-1:]))
            extra["uav_lla"] = np.round(np.column_stack([ulat, ulon, ualt]), 8).tolist()
            if vehicles:
                # the track's rows are the keyframes' (the newest last), those with a finite position
                rows = np.all(np.isfinite(np.asarray(est.uav_enu_m, float).reshape(-1, 3)), axis=1)
                if not final:
                    extra["uav_vehicle"] = [int(vehicles[-1])]
                elif len(rows) == len(vehicles):
                    extra["uav_vehicle"] = np.asarray(vehicles, int)[rows].tolist()
        self.writer.write("estimate", self.now(), users=users, keyframes=keyframes, flown_m=round(flown_m, 2),
                          **extra)

    def close(self) -> None:
        self.writer.close()


def status_line(phase: str, now_s: float, flown_m: float, measurements: int, users: list[MissionUser],
                est: Estimate | None, gnb_problem: str | None = None, gnb_home_in_s: float | None = None) -> str:
    """Phase, metres flown, measurements, a lost gNB and each user's estimate and 95 % bound."""
    parts = [f"{phase:<9} t={now_s:6.1f} s  flown {flown_m:6.1f} m  {measurements} meas"]
    if gnb_problem is not None:
        then = f"; home in {gnb_home_in_s:.0f} s" if gnb_home_in_s is not None else ""
        parts.append(f"gNB LOST: {gnb_problem}{then}")
    if est is not None:
        bound = est.error_bound_95_m()
        for k, u in enumerate(users):
            p = est.users_enu_m[k]
            if np.all(np.isfinite(p)) and bool(est.ambiguous[k]):
                # a mirror position explains the ranges as well: its small r95 means nothing yet
                m = est.mirror_enu_m[k]
                mirror = f" or ({m[0]:.1f}, {m[1]:.1f})" if np.all(np.isfinite(m[:2])) else ""
                parts.append(f"{u.id} AMBIGUOUS ({p[0]:.1f}, {p[1]:.1f}){mirror}")
            elif np.all(np.isfinite(p)):
                parts.append(f"{u.id} ({p[0]:.1f}, {p[1]:.1f}) r95 {bound[k]:.2f} m")
            else:
                parts.append(f"{u.id} -")
    return " | ".join(parts)
