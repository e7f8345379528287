"""Take-off and the survey's legs (docs/design.md §7): plan a waypoint, pass it through the safety
gate, command the cruise speed, fly it until arrival, a stop or return request, or its timeout.

Refused waypoints: max_refusals in a row (by the gate or the vehicle) request a return home;
MAVSDK's UNKNOWN answer (the 4.1 wedge after PX4's MAV_RESULT 9) requests it at once, so nothing
but RTL is sent afterwards.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import numpy as np

from estimator.geodesy import Origin
from mission.control.config import (
    PX4_DEFAULT_CRUISE_MPS,
    STATUS_BUDGET,
    TAKEOFF,
    ControllerConfig,
)
from mission.control.journal import MissionJournal
from mission.control.safety_monitor import energy_remaining_m
from mission.control.state import FlightState
from mission.result import status_of_planner_reason
from mission.safety import GatedVehicle
from mission.vehicle.telemetry import Odometer, odometer_dead_band_m
from planner.types import Planner, PlanningState, PlanResult
from uavloc.errors import PlannerError, SafetyError, VehicleError

log = logging.getLogger(__name__)


#: how long [mission s] the UAV hovers at most before a plan, for the estimator to solve the
#: measurements so far: a hover costs battery in mission time, so the bound is in mission time (at
#: a simulator's speedup, wall seconds would cost the battery speedup times as much)
PLAN_DRAIN_MAX_S = 10.0
#: the next leg is planned while this one is flown, from its end, once the vehicle is this many
#: mission seconds of flight from it (the plan, and the estimator's drain before it, then cost no
#: hover); at least the acceptance radius away
PLAN_AHEAD_S = 5.0


#: the take-off's wait never ends sooner than this [wall s] (Legs.takeoff)
TAKEOFF_WALL_FLOOR_S = 10.0


def disarm_text(texts: list[tuple[float, str, str]], since_mono_s: float) -> str | None:
    """The first status text since `since_mono_s` saying the vehicle disarmed ("Disarmed: no
    takeoff" on PX4, "Disarming motors" on ArduPilot), or None. texts: (t_mono_s, severity, text)."""
    for t_mono_s, _severity, text in texts:
        if t_mono_s >= since_mono_s and "disarm" in text.lower() and "denied" not in text.lower():
            return text
    return None


@dataclass(frozen=True)
class LegsDeps:
    """What the survey legs use of the flight, once home is known.

    config, flight: the mission's settings and the shared state; gated: every command that moves
    the vehicle, through the safety gate; set_speed(m/s): the cruise speed (no motion of its
    own); battery_pct(): the vehicle's charge now [%] or None; battery_rtl_pct: the gate's RTL
    threshold [%]; planner; origin: home (ENU frame of the planner and the gate); journal: the
    mission log; pos_enu(): the latest fix [m, ENU] or None; now(): mission seconds; wall(s):
    mission → wall seconds; drain(timeout_s): wait until the measurements so far are solved;
    sigma_gps_m: the GPS σ (the odometer's dead band); event: this vehicle's event writer; tag:
    the fields naming the vehicle in its records (a fleet's).
    """

    config: ControllerConfig
    flight: FlightState
    gated: GatedVehicle
    set_speed: Callable[[float], Awaitable[None]]
    battery_pct: Callable[[], float | None]
    battery_rtl_pct: float
    planner: Planner
    origin: Origin
    journal: MissionJournal
    pos_enu: Callable[[], np.ndarray | None]
    now: Callable[[], float]
    wall: Callable[[float], float]
    drain: Callable[[float], Awaitable[None]]
    sigma_gps_m: float
    event: Callable[..., None] | None = None
    tag: dict = dataclasses.field(default_factory=dict)

    def log_event(self, message: str, **fields) -> None:
        (self.event or self.journal.event)(message, **fields)


class SurveyLegs:
    """Take-off and the survey's legs of one flight (module docstring), on :class:`LegsDeps`."""

    def __init__(self, deps: LegsDeps):
        self.deps = deps
        self.odometer = Odometer(odometer_dead_band_m(deps.sigma_gps_m))
        self.leg_speed_mps = PX4_DEFAULT_CRUISE_MPS  # what the vehicle flies legs at (commanded or default)
        self.speed_refusals = 0
        self.battery_start_pct: float | None = None
        self.battery_start_s = 0.0  # mission seconds at battery_start_pct's reading
        #: the next leg, being planned from this leg's end while it is flown: (end [m, ENU], task)
        self._ahead: tuple[np.ndarray, asyncio.Task[PlanResult]] | None = None
        #: legs whose plan was ready (or being made) when the vehicle arrived
        self.planned_ahead = 0
        #: legs started so far (numbered on in a resumed survey)
        self.legs_flown = 0
        #: the end [m, ENU] of the leg being flown (None between legs): the other vehicles keep clear of it
        self.current_wp: np.ndarray | None = None
        self._plan_wall_s = 1.0  # how long the last plan took, drain included [wall s]

    async def takeoff(self) -> None:
        dep, cfg, f = self.deps, self.deps.config, self.deps.flight
        f.set_phase(TAKEOFF)
        st = dep.gated.vehicle.state
        t_arm_mono_s = time.monotonic()
        await dep.gated.arm()
        dep.log_event("armed", kind="arm")
        seen_armed = bool(st.armed)
        await dep.gated.takeoff(cfg.flight.altitude_m)
        dep.log_event(f"takeoff to {cfg.flight.altitude_m:g} m above home", kind="takeoff")
        # the climb's time in mission seconds, on the wall clock at the simulation's rate, but never
        # less than TAKEOFF_WALL_FLOOR_S: at x200 the climb is a fraction of a wall second, less
        # than the telemetry's own latency
        deadline = time.monotonic() + max(dep.wall(2.0 * cfg.flight.altitude_m / cfg.flight.climb_mps + 30.0),
                                          TAKEOFF_WALL_FLOOR_S)
        while f.return_reason is None:
            pos = dep.pos_enu()
            if pos is not None and pos[2] >= cfg.flight.altitude_m - max(1.5, cfg.flight.acceptance_m):
                return
            seen_armed = seen_armed or bool(st.armed)
            said = disarm_text(st.texts, t_arm_mono_s)
            if said is not None or (seen_armed and st.armed is False and pos is not None and pos[2] < 1.0):
                raise VehicleError(f"the vehicle disarmed before take-off ({said or 'it reports disarmed'})")
            if time.monotonic() > deadline:
                raise VehicleError(f"takeoff to {cfg.flight.altitude_m:g} m not reached in time (at "
                                   f"{'?' if pos is None else f'{pos[2]:.1f}'} m)")
            await f.wake.wait(0.2)

    def energy_remaining_m(self) -> float:
        """Metres the battery still allows (down to the RTL threshold), from the drain so far."""
        dep = self.deps
        return energy_remaining_m(dep.now() - self.battery_start_s, self.leg_speed_mps, self.battery_start_pct,
                                  dep.battery_pct(), dep.battery_rtl_pct)

    async def plan(self, pos: np.ndarray, drain_max_s: float = PLAN_DRAIN_MAX_S, ahead_m: float = 0.0) -> PlanResult:
        """The planner's next leg from `pos`, with the estimate of every keyframe measured so far
        (waiting at most drain_max_s mission seconds for the estimator to solve them). ahead_m: the
        metres still to fly before `pos` is reached (a plan made ahead, from the current leg's end):
        counted as flown and taken off the energy left, so that the budget and the way home are
        judged at `pos`, as they will be there."""
        dep = self.deps
        w0 = time.perf_counter()
        await dep.drain(dep.wall(drain_max_s))
        state = PlanningState(uav_enu_m=pos, estimate=dep.flight.estimate, flown_m=dep.flight.flown_m + ahead_m,
                              energy_remaining_m=self.energy_remaining_m() - ahead_m)
        t0 = time.perf_counter()
        plan = await asyncio.to_thread(dep.planner.plan, state)
        t1 = time.perf_counter()
        # how long a plan takes on this machine, in wall seconds (the plan-ahead's lead follows it)
        self._plan_wall_s = max(t1 - w0, 0.5 * self._plan_wall_s)
        # the planner's compute time, for the log (the planner itself has no clock)
        return dataclasses.replace(plan, solve_time_s=t1 - t0)

    async def survey(self) -> None:
        try:
            await self._survey()
        finally:
            self._drop_ahead()

    def _drop_ahead(self) -> None:
        if self._ahead is not None:
            self._ahead[1].cancel()
            self._ahead = None

    async def _next_plan(self, pos: np.ndarray) -> PlanResult:
        """The leg from `pos`: the one planned ahead from this leg's end when the vehicle is there
        (within twice the acceptance radius), else a plan now."""
        ahead, self._ahead = self._ahead, None
        if ahead is not None:
            end, task = ahead
            if float(np.linalg.norm(pos - end)) <= 2.0 * self.deps.config.flight.acceptance_m:
                self.planned_ahead += 1
                return await task
            task.cancel()
        return await self.plan(pos)

    def _plan_ahead(self, pos: np.ndarray, wp: np.ndarray) -> None:
        """Start planning the leg after `wp` once the vehicle is PLAN_AHEAD_S of flight from it."""
        dep = self.deps
        if self._ahead is not None or dep.flight.ending:
            return
        # lead [mission s] = PLAN_AHEAD_S + twice the last plan's wall time at this clock's speed
        lead_s = PLAN_AHEAD_S + 2.0 * self._plan_wall_s / dep.wall(1.0)
        near_m = max(dep.config.flight.acceptance_m, self.leg_speed_mps * lead_s)
        if float(np.linalg.norm(pos - wp)) <= near_m:
            end = np.asarray(wp, float).copy()
            # no long drain: ranges keep coming while the leg is flown; the estimate of now is the one
            ahead_m = float(np.linalg.norm(end - pos))
            self._ahead = (end, asyncio.create_task(self.plan(end, drain_max_s=1.0, ahead_m=ahead_m),
                                                    name="plan-ahead"))

    async def _survey(self) -> None:
        dep, cfg, f = self.deps, self.deps.config, self.deps.flight
        if self.battery_start_pct is None:  # a survey resumed keeps the charge it started with
            self.battery_start_pct, self.battery_start_s = dep.battery_pct(), dep.now()
        refusals = 0
        while not f.ending:
            # while the vehicle link is lost, wait (the safety monitor returns home after
            # link_lost_wait_s) rather than plan from a stale fix and command into the void
            await self.wait_link()
            if f.ending:
                break
            pos = dep.pos_enu()
            try:
                plan = await self._next_plan(pos)
            except PlannerError as exc:
                f.request_return(f"planner failed: {exc}")
                break
            if plan.done:
                f.finish_survey(status_of_planner_reason(plan.reason), plan.reason or "planner done", dep.now())
                break
            if f.ending:
                break
            wp = np.asarray(plan.waypoint_enu_m, float)
            lat, lon, alt = (float(x) for x in dep.origin.enu_to_lla(wp))
            self.legs_flown += 1
            dep.journal.writer.write(
                "waypoint", dep.now(), **dep.tag, leg=self.legs_flown, lat_deg=lat, lon_deg=lon, alt_m=alt,
                enu_m=wp.tolist(),
                planner=getattr(dep.planner, "name", "?"), status=plan.status,
                objective=plan.objective if math.isfinite(plan.objective) else None, solve_time_s=plan.solve_time_s)
            await self.command_speed()
            try:
                await dep.gated.goto_enu(wp)
            except SafetyError:
                refusals += 1
                if refusals >= cfg.safety.max_refusals:
                    f.request_return(f"{refusals} waypoints in a row refused by the safety gate")
                continue
            except VehicleError as exc:
                # a lost link or a refusal: the safety monitor decides about the link; here wait for
                # it and replan from wherever the vehicle is then
                refusals += 1
                dep.log_event(f"goto failed: {exc}", kind="goto_failed")
                if getattr(exc, "result", None) == "UNKNOWN":
                    # MAVSDK 4.1's answer to a MAV_RESULT it does not know (PX4's 9 to a reposition):
                    # it stops delivering telemetry and may crash on later calls, so send nothing but RTL
                    f.request_return(f"the vehicle library answered UNKNOWN: {exc}")
                elif refusals >= cfg.safety.max_refusals:
                    f.request_return(f"{refusals} gotos in a row failed: {exc}")
                await self.wait_link()
                continue
            refusals = 0
            self.current_wp = wp
            try:
                await self.fly_leg(pos, wp)
            finally:
                self.current_wp = None
        if self.budget_spent():
            f.finish_survey(STATUS_BUDGET, "budget spent", dep.now())

    async def command_speed(self) -> None:
        """Command the mission's cruise speed before every leg (PX4 keeps it over repositions, but a
        mode change resets it); the leg timeouts follow what the vehicle then flies."""
        dep, speed_mps = self.deps, self.deps.config.flight.cruise_speed_mps
        try:
            await dep.set_speed(speed_mps)
        except VehicleError as exc:
            self.speed_refusals += 1
            self.leg_speed_mps = min(speed_mps, PX4_DEFAULT_CRUISE_MPS)
            if self.speed_refusals == 1:
                dep.log_event(f"speed {speed_mps:g} m/s not accepted ({exc}): legs timed for "
                                  f"{self.leg_speed_mps:g} m/s", kind="speed_refused")
            return
        if self.leg_speed_mps != speed_mps:
            dep.log_event(f"cruise speed {speed_mps:g} m/s commanded", kind="speed", speed_mps=speed_mps)
        self.leg_speed_mps = speed_mps

    async def wait_link(self) -> None:
        """While the vehicle link is lost (and the survey goes on), wait."""
        f = self.deps.flight
        while f.link_lost_since is not None and not f.ending:
            await asyncio.sleep(0.05)

    def budget_spent(self) -> bool:
        return self.deps.flight.flown_m >= self.deps.config.flight.budget_m

    async def fly_leg(self, start: np.ndarray, wp: np.ndarray) -> None:
        """Wait for arrival within the acceptance radius, a stop/return request, or the leg timeout;
        the Δ-trigger measures while the leg is flown."""
        f = self.deps.flight
        f.on_leg = True
        try:
            await self._fly_leg_until_done(start, wp)
        finally:
            f.on_leg = False

    async def _fly_leg_until_done(self, start: np.ndarray, wp: np.ndarray) -> None:
        dep, cfg, f = self.deps, self.deps.config, self.deps.flight
        deadline = time.monotonic() + dep.wall(2.0 * self.leg_time_s(start, wp) + 20.0)
        # metres flown: an odometer whose dead band (max(5 m, 8 σ_gps)) GPS noise does not cross
        self.odometer.start(start)
        while True:
            pos = dep.pos_enu()
            f.flown_m = self.odometer.update(pos)
            if np.linalg.norm(pos - wp) <= cfg.flight.acceptance_m:
                f.flown_m = self.odometer.finish(pos)
                return
            self._plan_ahead(pos, wp)
            if f.ending:
                return
            if self.budget_spent():
                f.finish_survey(STATUS_BUDGET, "budget spent", dep.now())
                return
            if time.monotonic() > deadline:
                dep.log_event(f"leg to ({wp[0]:.1f}, {wp[1]:.1f}, {wp[2]:.1f}) m timed out", kind="leg_timeout")
                return
            await f.wake.wait(0.2)

    def leg_time_s(self, start: np.ndarray, wp: np.ndarray) -> float:
        """Mission seconds a leg from `start` to `wp` [m, ENU] takes at the vehicle's speeds: an
        autopilot flies the horizontal and the vertical at once, each at its own limit,

            t = max(|Δ_en| / v_leg,  Δ_up / v_climb if Δ_up > 0 else −Δ_up / v_descent)

        (a live PX4 leg from 80 m down to 30 m over 57 m horizontally takes 33 s at a 1.5 m/s
        descent: 3-D metres at cruise speed gave 7.6 s, and the leg timed out after 35 s)."""
        fl = self.deps.config.flight
        d = np.asarray(wp, float) - np.asarray(start, float)
        vertical_s = d[2] / fl.climb_mps if d[2] > 0.0 else -d[2] / fl.descent_mps
        return max(float(np.hypot(d[0], d[1])) / self.leg_speed_mps, float(vertical_s))

    def return_timeout_s(self) -> float:
        """Mission seconds the return home and landing may take: twice the flight at the vehicle's
        return speed (PX4: MPC_XY_CRUISE unless changed) and descent, plus 60 s."""
        dep = self.deps
        pos = dep.pos_enu()
        dist = 0.0 if pos is None else float(np.hypot(pos[0], pos[1]))
        height = dep.config.flight.altitude_m if pos is None else max(float(pos[2]), 0.0)
        return 2.0 * (dist / min(self.leg_speed_mps, PX4_DEFAULT_CRUISE_MPS)
                      + height / dep.config.flight.descent_mps) + 60.0
