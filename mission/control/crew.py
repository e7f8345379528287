"""What one vehicle of a mission owns (docs/fleet.md): its link, telemetry, gNB rounds, legs and safety.

A mission flies V ≥ 1 vehicles (`[[vehicles]]`; one without). The mission
(mission.control.flight.MissionController) owns what there is once: the mission log, the
estimator, the fleet's planner, the stop rule and the final answer. Each vehicle's
:class:`VehicleCrew` owns the rest:

- its :class:`Vehicle` (MAVSDK) and :class:`GatedVehicle` (its own safety gate: fence, altitude
  band, and the separation from the other vehicles' legs);
- its clock (:class:`VehicleClock`: mission seconds on its own boot time, all crews sharing the
  mission's start instant), its telemetry buffer and the `telemetry` records it logs;
- its :class:`FlightState` (phase, a return request, its link and gNB conditions, metres flown),
  its measurement pipeline (its gNB; every keyframe into the mission's one queue, with
  `Keyframe.vehicle`) and its survey legs;
- its safety monitor, RTL and landing.

A crew's fault (link lost, battery low, refused commands, an error of its own) sends that
vehicle home; the others go on. In a fleet every record a crew writes names its vehicle
(`"vehicle": index`); a one-vehicle mission writes no such field, so its log is as before.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from mission.control.config import (
    RETURN,
    SURVEY,
    TAKEOFF,
    ControllerConfig,
    MissionUser,
)
from mission.control.journal import MissionJournal
from mission.control.pipeline import MeasurementPipeline
from mission.control.state import FlightState, spacing_m
from mission.gnb import GnbClient
from mission.safety import GatedVehicle, SafetyGate
from mission.vehicle import PositionFix, Vehicle
from mission.vehicle.telemetry import TelemetryBuffer, VehicleClock
from uavloc.errors import GnbPreflightError, SafetyError, VehicleError

log = logging.getLogger(__name__)


class VehicleCrew:
    """One vehicle's part of a mission. See the module docstring.

    index, vehicle_id: its number (0..V−1, the log's `vehicle`) and name; vehicle, gnb: its adapters;
    users: the mission's users; config: the controller settings as this vehicle flies them (its
    cruise altitude and band); journal: the mission log; t0_mono_s: the mission's start (monotonic);
    fleet: V > 1 (records name their vehicle); keyframes_out / keyframes: the mission's keyframe
    queue and list, which every crew's pipeline fills; serving: (K,) the vehicle whose gNB last
    measured each user (−1: none), shared by the crews; origin: () -> the mission's ENU origin;
    on_fix: called after each fix is buffered (the mission's separation watch).
    """

    def __init__(self, index: int, vehicle_id: str, vehicle: Vehicle, gnb: GnbClient, users: list[MissionUser],
                 config: ControllerConfig, journal: MissionJournal, t0_mono_s: float, *, fleet: bool,
                 keyframes_out: asyncio.Queue, keyframes: list, serving: np.ndarray,
                 origin: Callable[[], Origin | None], on_fix: Callable[[VehicleCrew], None] | None = None,
                 collect_tau: bool = False):
        self.index, self.id = index, vehicle_id
        self.vehicle, self.gnb = vehicle, gnb
        self.users, self.config, self.journal = users, config, journal
        self.fleet = fleet
        #: the fields naming this vehicle in its records (none in a one-vehicle mission)
        self.tag: dict[str, Any] = {"vehicle": index} if fleet else {}
        self.clock = VehicleClock(t0_mono_s, config.time_scale)
        self.buffer = TelemetryBuffer(4096)
        self._origin = origin
        self._on_fix_hook = on_fix
        self._last_tel_log_t = -math.inf
        #: the telemetry records as logged (t [s], ENU [m], velocity ENU [m/s]) until the take-off is
        #: over, for the GPS correlation time when the noise model leaves it unknown
        self.tau_records: list[tuple[float, np.ndarray, np.ndarray]] | None = [] if collect_tau else None
        self.takeoff_over = asyncio.Event()
        self.flight = FlightState(event=self.event, name=vehicle_id if fleet else None)
        self.pipeline = MeasurementPipeline(gnb, users, config.flight.delta_m, config.gnb_timeout_s, self.flight,
                                            self.buffer, origin, journal.writer, self.now, self.mission_t,
                                            vehicle=index, tag=self.tag, keyframes_out=keyframes_out,
                                            keyframes=keyframes, serving=serving)
        self.home: Origin | None = None  # this vehicle's own home (its RTL point)
        self.home_enu_m: np.ndarray | None = None  # … in the mission's ENU frame
        self.gate: SafetyGate | None = None
        self.gated: GatedVehicle | None = None
        self.legs = None  # SurveyLegs, once home is known
        self.connected = False
        self.rtl_sent = self.landed = self.rtl_gave_up = False
        self.autopilot_landing = False  # RTL not sent: the autopilot was already landing on its own
        #: how this vehicle's part ended: (status, reason), once it did
        self.outcome: tuple[str, str] | None = None

    # -- records --------------------------------------------------------------------------------

    def event(self, message: str, **fields: Any) -> None:
        """An `event` record of this vehicle (in a fleet: naming it, and the message prefixed with its id)."""
        if self.fleet:
            message = f"{self.id}: {message}"
        self.journal.event(message, state=self.flight.phase, **self.tag, **fields)

    # -- clock ----------------------------------------------------------------------------------

    def now(self) -> float:
        """Mission seconds now, on this vehicle's clock."""
        return self.clock.mission_t(time.monotonic())

    def mission_t(self, t_mono_s: float) -> float:
        return self.clock.mission_t(t_mono_s)

    def wall(self, mission_s: float) -> float:
        """Mission seconds → wall seconds (at this vehicle's clock's current rate)."""
        return mission_s / self.clock.rate

    # -- telemetry ------------------------------------------------------------------------------

    def pos_enu(self) -> np.ndarray | None:
        latest = self.buffer.latest()
        return None if latest is None else latest[1]

    def pos_enu_smoothed(self) -> np.ndarray | None:
        """Mean of the fixes over the last config.position_smooth_s (mission), or None."""
        latest = self.buffer.latest()
        return None if latest is None else self.buffer.mean_since(latest[0] - self.config.position_smooth_s)

    def on_fix(self, fix: PositionFix) -> None:
        origin = self._origin()
        if origin is None:
            return
        t = self.mission_t(fix.t_mono_s)
        pos = origin.lla_to_enu(fix.lat_deg, fix.lon_deg, fix.alt_amsl_m)
        self.buffer.append(t, pos)
        if fix.vel_ned_mps is not None:
            self.flight.clock.fix(t, float(np.linalg.norm(fix.vel_ned_mps)))
            self.flight.check_pace(self.config.time_scale, t, time.monotonic())
        if t - self._last_tel_log_t >= 1.0 / self.config.telemetry_log_hz and self.journal.is_open:
            self._last_tel_log_t = t
            extra = {"vel_ned_mps": list(fix.vel_ned_mps)} if fix.vel_ned_mps is not None else {}
            state = getattr(self.vehicle, "state", None)
            if state is not None:
                extra.update(state.status().record_fields())
            rec = self.journal.writer.write("telemetry", t, lat_deg=fix.lat_deg, lon_deg=fix.lon_deg,
                                            alt_m=fix.alt_amsl_m, **self.tag, **extra)
            if self.tau_records is not None and fix.vel_ned_mps is not None:
                # the numbers as logged, so that replay's estimate from the same records agrees
                vn, ve, vd = rec["vel_ned_mps"]
                enu = origin.lla_to_enu(rec["lat_deg"], rec["lon_deg"], rec["alt_m"])
                self.tau_records.append((rec["t"], np.asarray(enu, float), np.array([ve, vn, -vd])))
        if self._on_fix_hook is not None:
            self._on_fix_hook(self)
        self.flight.wake.pulse()

    # -- what the other vehicles keep clear of ----------------------------------------------------

    def committed_leg(self) -> np.ndarray | None:
        """(2, 3) [m, ENU] the leg this vehicle flies or holds: from its position to its leg's end
        while surveying, to its home at its altitude while returning, its position while taking off;
        None on the ground or unknown (planner.fleet: the other vehicles' legs keep clear of it)."""
        pos = self.pos_enu()
        phase = self.flight.phase
        if pos is None or phase not in (TAKEOFF, SURVEY, RETURN):
            return None
        if phase == RETURN and self.home_enu_m is not None:
            home = np.array([self.home_enu_m[0], self.home_enu_m[1], pos[2]])
            return np.array([pos, home])
        wp = getattr(self.legs, "current_wp", None) if phase == SURVEY else None
        return np.array([pos, pos if wp is None else wp], float)

    @property
    def airborne(self) -> bool:
        st = getattr(self.vehicle, "state", None)
        return self.flight.phase in (TAKEOFF, SURVEY, RETURN) and not (
            st is not None and st.landed_state == "ON_GROUND" and st.armed is False)

    # -- preflight ------------------------------------------------------------------------------

    def home_problems(self) -> list[str]:
        """What keeps this vehicle on the ground where it stands (empty: nothing): its home outside
        the fence, inside a no-fly zone or beyond max_distance_m of the mission's origin (vehicle 0's
        home, a simulated fleet's scenario origin)."""
        return self.gate.home_violations(self.home_enu_m)

    def preflight_home(self) -> None:
        """No take-off from a home outside the fence, inside a no-fly zone or too far from the origin."""
        problems = self.home_problems()
        if problems:
            raise SafetyError(f"not taking off{self._of()}: {'; '.join(problems)}")

    def preflight_battery(self) -> None:
        """No take-off below battery_takeoff_min_pct (when the vehicle reports its charge)."""
        pct, floor = self.vehicle.state.battery_pct, self.config.safety.battery_takeoff_min_pct
        if pct is None:
            self.event("battery charge unknown before take-off", kind="battery_unknown")
        elif pct < floor:
            raise SafetyError(f"not taking off{self._of()}: battery at {pct:g} % is below battery_takeoff_min_pct "
                              f"{floor:g} %")

    async def preflight_gnb(self) -> None:
        """A one-vehicle mission's gNB check: no take-off unless every configured user is among the
        gNB's UEs and answers one measurement (passive stock mode: is among them); GnbPreflightError
        names the RNTIs the gNB has and what it answered. A fleet's gNBs are checked together
        (MissionController._preflight_gnb over :meth:`probe_gnb`)."""
        probe, ok = await self.probe_gnb()
        if not ok:
            raise GnbPreflightError(f"not taking off{self._of()}: {probe.message()}")

    async def probe_gnb(self):
        """(probe, ok): the gNB's preflight probe of the mission's users, logged as a `preflight_gnb` event."""
        from mission.gnb.probe import RETRY_PAUSES_S, TIMEOUT_TRIES, probe_gnb

        rntis = [u.rnti for u in self.users]
        gcfg = getattr(self.gnb, "config", None)
        passive = getattr(gcfg, "mode", None) == "stock" and getattr(gcfg, "stock_mode", None) == "passive"
        # a timed-out request is asked again (mission.gnb.probe.TIMEOUT_TRIES): the discovery and each user's
        bound_s = (self.config.gnb_timeout_s * TIMEOUT_TRIES + sum(RETRY_PAUSES_S)) * (1 + len(rntis))
        try:
            async with asyncio.timeout(bound_s):
                probe = await probe_gnb(self.gnb, rntis=rntis, count=1)
        except TimeoutError as exc:
            raise GnbPreflightError(f"not taking off{self._of()}: the gNB did not finish the preflight probe within "
                                    f"{bound_s:g} s") from exc
        have = probe.gnb_rntis or []
        ok = probe.ok or (passive and probe.gnb_rntis is not None and all(r in have for r in rntis))
        message = probe.message()
        if self.fleet:
            # a fleet's gNB serves the UEs attached to its cell: those must answer (the mission
            # checks that every user is on some cell)
            present = [u for u in probe.ues if u.present]
            failed = [u for u in present if not u.ok]
            ok = probe.gnb_rntis is not None and (passive or not failed)
            served = ", ".join(f"{u.rnti:04x}" for u in present)
            message = (f"gNB {'ready' if ok else 'not ready'} ({getattr(probe, 'mode', '?')}): its cell serves "
                       f"{len(present)} of the mission's {len(rntis)} UEs [{served}]"
                       + "".join(f"; UE {u.rnti:04x}: no measurement ({u.errors[-1] if u.errors else 'no answer'})"
                                 for u in failed)
                       + ("" if probe.gnb_rntis is not None else f"; {probe.message()}"))
        self.event(message, kind="preflight_gnb", ok=ok, rntis=[f"{r:04x}" for r in have], probe=probe.to_dict())
        return probe, ok

    def _of(self) -> str:
        return f" ({self.id})" if self.fleet else ""

    async def set_return_layer(self) -> None:
        """A fleet's vehicle returns home at its own cruise altitude (its layer: vehicles in disjoint
        bands stay apart on the way home too); a vehicle that refuses returns at its autopilot's own
        (an event says so)."""
        height_m = self.config.flight.altitude_m
        try:
            await self.vehicle.set_return_altitude(height_m)
        except VehicleError as exc:
            self.event(f"return altitude {height_m:g} m not set ({exc}): it returns at its autopilot's own",
                       kind="return_alt_refused")
            return
        self.event(f"returns home at {height_m:g} m above home", kind="return_alt", height_m=height_m)

    # -- the survey's record ----------------------------------------------------------------------

    def survey_ended(self) -> None:
        """Log how this vehicle's survey spent its time and what it measured (`survey_time`)."""
        c = self.flight.clock
        c.end(self.now(), time.monotonic(), self.flight.stop_s)
        share = 100.0 * c.hover_s / c.survey_s if c.survey_s > 0 else 0.0
        flown_m, n_users = self.flight.flown_m, len(self.users)
        round_m = spacing_m(flown_m, c.rounds)
        # each user's ranges: the survey's ranges shared among the users
        user_m = spacing_m(flown_m * n_users, c.ranges)
        per_min = c.rounds_per_min()
        measured = (f"{c.rounds} gNB rounds ({c.ranges} ranges), one every {round_m:.1f} m (Δ = "
                    f"{self.config.flight.delta_m:g} m), {per_min:.1f} per minute, each user ranged every "
                    f"{user_m:.1f} m" if round_m is not None and per_min is not None and user_m is not None
                    else "no gNB round")
        planned_ahead = self.legs.planned_ahead if self.legs is not None else 0
        self.event(f"survey {c.survey_s:.0f} s: hovering {c.hover_s:.1f} s ({share:.1f} %), longest without "
                   f"a range {c.largest_gap_s:.1f} s; {measured}; {planned_ahead} legs planned "
                   f"ahead", kind="survey_time", survey_s=round(c.survey_s, 2), hover_s=round(c.hover_s, 2),
                   largest_gap_s=round(c.largest_gap_s, 2), planned_ahead=planned_ahead,
                   flown_m=round(flown_m, 2), rounds=c.rounds, ranges=c.ranges,
                   spacing_m=None if round_m is None else round(round_m, 2),
                   user_spacing_m=None if user_m is None else round(user_m, 2),
                   rounds_per_min=None if per_min is None else round(per_min, 2), ranges_dropped_late=c.late_dropped)

    # -- the safe commands ------------------------------------------------------------------------

    async def send_rtl(self, reason: str, retry_s: float = 60.0) -> bool:
        """Send RTL, retrying (e.g. while the link is down) for up to `retry_s` wall seconds;
        True when the vehicle accepted it."""
        t_end = time.monotonic() + retry_s
        attempt = 0
        while True:
            attempt += 1
            if self.vehicle.state.flight_mode == "LAND":
                # the autopilot's own failsafe is landing the vehicle (PX4 after a GPS loss): that is
                # a safe command already, and RTL would be refused without a position
                self.autopilot_landing = True
                self.event(f"RTL not sent: the autopilot is already landing ({reason})", kind="autopilot_land")
                return True
            try:
                await self.gated.return_to_launch()
            except VehicleError as exc:
                if attempt == 1 or attempt % 10 == 0:
                    log.warning("RTL attempt %d%s failed: %s", attempt, self._of(), exc)
                    self.event(f"RTL attempt {attempt} failed: {exc}", kind="rtl_failed")
                if time.monotonic() >= t_end:
                    self.rtl_gave_up = True
                    return False
                await asyncio.sleep(0.5)
                continue
            self.rtl_sent = True
            self.event(f"RTL: {reason}", kind="rtl", attempts=attempt)
            return True

    async def wait_landed(self, timeout_s: float) -> bool:
        st = self.vehicle.state
        deadline = time.monotonic() + self.wall(timeout_s)
        while time.monotonic() < deadline:
            if st.landed_state == "ON_GROUND" and st.armed is False:
                return True
            await self.flight.wake.wait(0.2)
        return False

    async def safe_end(self, reason: str, timeout_s: float) -> None:
        """Never leave the vehicle without a safe command: RTL when it may be airborne (trying
        for at most timeout_s wall seconds)."""
        if not self.connected or self.gated is None or self.rtl_sent or self.rtl_gave_up:
            return
        st = self.vehicle.state
        if st.armed is False and st.landed_state in ("ON_GROUND", "UNKNOWN"):
            return
        try:
            async with asyncio.timeout(timeout_s):
                sent = await self.send_rtl(reason, retry_s=timeout_s)
        except TimeoutError:
            sent = False
        if not sent:
            log.error("RTL%s could not be sent: the vehicle is left to its own failsafe", self._of())
            self.event("RTL could not be sent: the vehicle is left to its own failsafe", kind="rtl_failed")
