"""The mission controller (docs/design.md §1, §7; docs/fleet.md): fly, measure every Δ, estimate, replan, stay safe.

States CONNECT → PREFLIGHT → TAKEOFF → SURVEY → RETURN → LANDED, and ABORT from anywhere. The
flight (:meth:`MissionController._flow`) reads top to bottom: connect, wait for home, open the log,
check the gNB (every user present and answering, else no take-off), start the background tasks,
take off, survey, return, land. One `asyncio.TaskGroup` owns the background tasks, which share
nothing but the :class:`FlightState`:

- telemetry: each position fix into a :class:`TelemetryBuffer` (mission time, ENU from home) and,
  rate-limited, into the mission log;
- the measurement pipeline (mission.control.pipeline): Δ-trigger and placer;
- the estimator worker (mission.control.estimator_worker): keyframes solved off the event loop;
- the safety monitor (mission.control.safety_monitor): link, battery, position, gNB, time limit;
- status: a progress line on stderr through `logging`.

A mission flies one vehicle or a fleet (`[[vehicles]]`), and one vehicle is a fleet of one: the
mission owns the log, the estimator, the planner (planner.fleet.FleetPlanner), the stop rule and
the final answer; each vehicle's :class:`mission.control.crew.VehicleCrew` owns its link,
telemetry, gNB rounds, legs, safety monitor and its FlightState, and flies its own states in the
same task group. A vehicle's fault (its link lost, its battery low, its commands refused, an
error of its own) sends that vehicle home and the others go on; the stop rule, Ctrl-C or a
cancellation ends every vehicle's survey. The mission's ENU origin is vehicle 0's home.

The survey asks the planner for a waypoint at each leg end, passes it through the safety gate
(:class:`GatedVehicle`: nothing reaches the vehicle that the gate did not pass) and flies it
until arrival within the acceptance radius or the leg timeout. The stop rule (every user's 95 %
ellipse within the target radius, or the budget spent) leads to RETURN. An exception, a
cancellation (Ctrl-C) or a safety condition ends in RTL and a flushed log.

Time: the log's `t` is mission seconds since start on the vehicle's clock (MAVLink boot time,
:class:`mission.vehicle.telemetry.VehicleClock`); before the vehicle's time is known (and with a vehicle
that sends none) it is `(monotonic − start) · time_scale` (the simulator's speedup; 1 for real
flights). Request timeouts stay in wall seconds. A fleet's vehicles each keep their own clock
from the mission's one start, so their mission seconds agree.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import asdict, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

import numpy as np

from estimator.geodesy import Origin
from estimator.gps import estimate_gps_tau_s
from estimator.noise import NoiseModel
from estimator.types import Estimate, Keyframe, SolverParams
from mission.control.answer import FinalAnswer
from mission.control.config import (
    ABORT,
    CONNECT,
    INTERRUPT_SAFE_END_TIMEOUT_S,
    LANDED,
    PREFLIGHT,
    PREPARE_TIMEOUT_S,
    RETURN,
    SAFE_END_TIMEOUT_S,
    STATUS_ABORTED,
    STATUS_BUDGET,
    STATUS_FLOOR,
    STATUS_INTERRUPTED,
    STATUS_RETURNED,
    STATUS_TARGET,
    SURVEY,
    TAKEOFF,
    ControllerConfig,
    MissionResult,
    MissionUser,
)
from mission.control.crew import VehicleCrew
from mission.control.estimator_worker import EstimatorWorker
from mission.control.journal import MissionJournal, status_line
from mission.control.legs import LegsDeps, SurveyLegs
from mission.control.loop import LoopLagMonitor
from mission.control.safety_monitor import SafetyMonitor
from mission.control.state import SurveyPace
from mission.estimation import MissionEstimator, solver_params_header
from mission.gnb import GnbClient
from mission.log import MissionLogWriter, area_fields
from mission.safety import GatedVehicle, SafetyGate, SafetyLimits
from mission.vehicle import Vehicle, VehicleTimeoutError
from planner.fleet import FleetPlanner, Separation, vehicles_apart
from planner.types import Planner, PlanningState, PlanResult
from uavloc.errors import (
    EstimatorError,
    GnbPreflightError,
    MissionError,
    PlannerError,
    SafetyError,
    UavlocError,
    VehicleError,
)

log = logging.getLogger(__name__)

T = TypeVar("T")

#: how a fleet's mission ended, from its vehicles' ends: the first of these any vehicle reached
_FLEET_STATUS_ORDER = (STATUS_TARGET, STATUS_FLOOR, STATUS_BUDGET)


class _VehiclePlanner:
    """Vehicle v's view of the fleet's planner: what its legs ask (`plan(state)`, `name`), answered
    by FleetPlanner.plan with the users' serving cells and the other vehicles' legs now. Plans run
    in threads (SurveyLegs.plan), one at a time: the vehicles' planners may share compiled kernels."""

    def __init__(self, fleet: FleetPlanner, vehicle: int, serving: Callable[[], np.ndarray],
                 committed: Callable[[], list[np.ndarray | None]], lock: threading.Lock):
        self.fleet, self.vehicle = fleet, vehicle
        self._serving, self._committed, self._lock = serving, committed, lock
        self.name = fleet.name

    def plan(self, state: PlanningState) -> PlanResult:
        serving, committed = self._serving(), self._committed()
        with self._lock:
            return self.fleet.plan(self.vehicle, state, serving, committed)


class MissionController(FinalAnswer):
    """Runs one mission of one vehicle or a fleet. See the module docstring.

    vehicle, gnb: a :class:`Vehicle` and a connected :class:`GnbClient`, or a fleet's sequences of
    them (one each per vehicle, in the mission's `[[vehicles]]` order); planner: a
    :class:`planner.types.Planner` whose constraints are in the home ENU frame, or
    (home, vehicle) -> Planner; users: the users to locate; noise/params: the estimator's model and
    settings; limits: the safety gate's limits (home ENU frame), or (home, vehicle) -> SafetyLimits;
    log_path: the mission log; truth: simulation only: home -> (K, 3) true user positions in the
    home ENU frame [m] (the `truth` record); header_config: the header's `config` section; radio: its
    `radio`; buildings: simulation only: home -> [(footprint (Q, 2) [m, ENU from home], height_m)]
    for the header's `buildings`; vehicle_ids: the vehicles' names (a fleet's `[[vehicles]]` ids);
    vehicle_config: vehicle -> the ControllerConfig that vehicle flies (its cruise altitude);
    separation: how far apart a fleet's vehicles stay; origin: the vehicles' homes (GeoFix each)
    -> the mission's ENU origin (default: vehicle 0's home; a simulated fleet's: the scenario's
    origin, the centre of its launch points).
    """

    def __init__(self, vehicle: Vehicle | Sequence[Vehicle], gnb: GnbClient | Sequence[GnbClient],
                 planner: Planner | Callable[[Origin, int], Planner],
                 users: list[MissionUser], noise: NoiseModel,
                 limits: SafetyLimits | Callable[[Origin, int], SafetyLimits], config: ControllerConfig,
                 log_path: str | Path, params: SolverParams | None = None,
                 truth: Callable[[Origin], np.ndarray] | None = None,
                 header_config: dict | None = None, radio: dict | None = None,
                 buildings: Callable[[Origin], list] | None = None,
                 vehicle_ids: Sequence[str] | None = None,
                 vehicle_config: Callable[[int], ControllerConfig] | None = None,
                 separation: Separation | None = None,
                 origin: Callable[[Sequence], Origin] | None = None):
        if not users:
            raise MissionError("a mission needs at least one user")
        vehicles = list(vehicle) if isinstance(vehicle, list | tuple) else [vehicle]
        gnbs = list(gnb) if isinstance(gnb, list | tuple) else [gnb]
        if not vehicles or len(gnbs) != len(vehicles):
            raise MissionError(f"a mission needs one gNB per vehicle: {len(vehicles)} vehicles, {len(gnbs)} gNBs")
        n = len(vehicles)
        ids = list(vehicle_ids) if vehicle_ids is not None else [f"uav{i + 1}" for i in range(n)]
        if len(ids) != n:
            raise MissionError(f"{len(ids)} vehicle ids for {n} vehicles")
        self.users = list(users)
        self.noise, self.config = noise, config
        self.params = params or SolverParams(delta_m=config.flight.delta_m)
        # a planner or limits given as a function of home are built once home is known (PREFLIGHT)
        self._planner_at = None if hasattr(planner, "plan") else planner
        #: vehicle 0's planner (a one-vehicle mission's; callers may wrap it before run); the
        #: fleet's planner is built from every vehicle's once home is known
        self.planner = planner if self._planner_at is None else None
        self.fleet_planner: FleetPlanner | None = None
        self._limits_at = None if isinstance(limits, SafetyLimits) else limits
        self._limits = limits if isinstance(limits, SafetyLimits) else None
        self.separation = separation or Separation()
        self._truth = truth
        self._buildings = buildings
        self.truth_enu_m: np.ndarray | None = None
        self.header_config = header_config or {}
        self.radio = radio or {}
        self.log_path = Path(log_path)
        self.origin: Origin | None = None
        self._origin_at = origin
        self._t0_mono = time.monotonic()
        self._start_utc = datetime.now(UTC).isoformat(timespec="milliseconds")
        self._estimator: MissionEstimator | None = None  # the flight's estimator setup, once it runs
        self.journal = MissionJournal(MissionLogWriter(self.log_path), self.users, self.now, lambda: self.state)
        # what the vehicles share: one keyframe queue and list, the serving cell of each user
        self.keyframes_out: asyncio.Queue[Keyframe] = asyncio.Queue()
        self._keyframes: list[Keyframe] = []
        self.serving = np.full(len(self.users), -1, int)
        fleet = n > 1
        self.crews = [VehicleCrew(i, ids[i], vehicles[i], gnbs[i], self.users,
                                  vehicle_config(i) if vehicle_config is not None else config, self.journal,
                                  self._t0_mono, fleet=fleet, keyframes_out=self.keyframes_out,
                                  keyframes=self._keyframes, serving=self.serving, origin=lambda: self.origin,
                                  on_fix=self._watch_separation if fleet else None,
                                  collect_tau=noise.gps_tau_s is None)
                      for i in range(n)]
        if self._limits is not None:  # limits that do not depend on home: a gate now
            for c in self.crews:
                c.gate = SafetyGate(self._limits)
        self._plan_lock = threading.Lock()
        self._confirm_lock = asyncio.Lock()
        self.loop_lag = LoopLagMonitor()
        self.result: MissionResult | None = None  # set when the mission ends (also when cancelled)
        #: how fast the survey really ran against the wall clock (once it ended; vehicle 0's)
        self.pace: SurveyPace | None = None
        #: a fleet's vehicles closer than the separation: (mission t [s], least distance [m]) of each breach
        self.separation_breaches: list[tuple[float, float]] = []
        self._apart = True
        #: PREFLIGHT: what each vehicle (or the mission) is still waiting for, named if it runs out of time
        self._pending: dict[str, str] = {}

    # -- what the flight knows, for callers and tests --------------------------------------------

    @property
    def fleet(self) -> bool:
        return len(self.crews) > 1

    @property
    def vehicle(self) -> Vehicle:
        """Vehicle 0 (a one-vehicle mission's vehicle)."""
        return self.crews[0].vehicle

    @property
    def gnb(self) -> GnbClient:
        return self.crews[0].gnb

    @property
    def flight(self):
        """Vehicle 0's FlightState (a one-vehicle mission's)."""
        return self.crews[0].flight

    @property
    def pipeline(self):
        return self.crews[0].pipeline

    @property
    def legs(self) -> SurveyLegs | None:
        return self.crews[0].legs

    @property
    def gate(self) -> SafetyGate | None:
        return self.crews[0].gate

    @property
    def log_writer(self) -> MissionLogWriter:
        """The mission log's writer; the live view subscribes to its records."""
        return self.journal.writer

    @property
    def state(self) -> str:
        """The mission's phase: its one vehicle's; a fleet's, the first vehicle's still flying (else vehicle 0's)."""
        for c in self.crews:
            if c.flight.phase not in (LANDED, ABORT):
                return c.flight.phase
        return self.crews[0].flight.phase

    @property
    def estimate(self) -> Estimate | None:
        return self.crews[0].flight.estimate

    @estimate.setter
    def estimate(self, est: Estimate | None) -> None:
        for c in self.crews:
            c.flight.estimate = est

    @property
    def measurements(self) -> int:
        return sum(c.flight.measurements for c in self.crews)

    @property
    def flown_m(self) -> float:
        return sum(c.flight.flown_m for c in self.crews)

    @property
    def keyframes(self) -> list[Keyframe]:
        return self._keyframes

    @property
    def event_messages(self) -> list[str]:
        return self.journal.messages

    def request_return(self, reason: str) -> None:
        """Ask every vehicle to end its survey and return home (first reason wins)."""
        for c in self.crews:
            c.flight.request_return(reason)

    # -- clock ----------------------------------------------------------------------------------

    def now(self) -> float:
        """Mission seconds since start (vehicle 0's seconds once its clock is known)."""
        return self.crews[0].now()

    def mission_t(self, t_mono_s: float) -> float:
        return self.crews[0].mission_t(t_mono_s)

    def wall(self, mission_s: float) -> float:
        """Mission seconds → wall seconds (at vehicle 0's clock's current rate)."""
        return self.crews[0].wall(mission_s)

    def pos_enu(self) -> np.ndarray | None:
        return self.crews[0].pos_enu()

    # -- the flight -----------------------------------------------------------------------------

    async def _flow(self, tg: asyncio.TaskGroup) -> tuple[str, str]:
        cfg = self.config
        background: list[asyncio.Task] = []
        await asyncio.gather(*(self._connect(c) for c in self.crews))
        for c in self.crews:
            background.append(tg.create_task(c.vehicle.run_telemetry(c.on_fix, c.clock.update),
                                             name=f"telemetry{self._suffix(c)}"))
            c.flight.set_phase(PREFLIGHT)
        homes = await asyncio.gather(*(self._named(c, PREFLIGHT, c.vehicle.wait_ready(cfg.ready_timeout_s))
                                       for c in self.crews))
        self._at_home(homes)
        # the planner's kernels compile (seconds of CPU) while the gNB is probed, not after it
        prepared = tg.create_task(self._prepare_planner(), name="prepare-planner")
        background.append(prepared)
        self._preflight_home()
        # the rest of PREFLIGHT has a wall bound (each vehicle's wait for its home has its own)
        self._pending = {c.id: "its gNB's probe" for c in self.crews}
        bound = asyncio.timeout(cfg.preflight_timeout_s)
        try:
            async with bound:
                await self._preflight_gnb()
                for c in self.crews:
                    c.preflight_battery()
                self._pending = {"mission": "the planner's preparation"}
                try:
                    async with asyncio.timeout(PREPARE_TIMEOUT_S):
                        await prepared
                except TimeoutError as exc:
                    raise PlannerError(f"PREFLIGHT: the planner {self.fleet_planner.name} was not prepared within "
                                       f"{PREPARE_TIMEOUT_S:g} s (its kernels compile before take-off); not taking "
                                       "off") from exc
        except TimeoutError as exc:
            if not bound.expired():
                raise
            raise MissionError(f"PREFLIGHT not done within {cfg.preflight_timeout_s:g} s (wall): still waiting for "
                               + ", ".join(f"{k}: {v}" for k, v in self._pending.items())) from exc
        for coro, name in ((self._estimator_task(), "estimator"), (self._status_task(), "status"),
                           (self.loop_lag.run(), "loop-lag")):
            background.append(tg.create_task(coro, name=name))
        for c in self.crews:
            safety = SafetyMonitor(c.flight, c.config, c.gate, c.vehicle.state, c.buffer.latest, c.now)
            for coro, name in ((c.pipeline.run_trigger(), "trigger"), (c.pipeline.run_placer(), "placer"),
                               (safety.run(), "safety")):
                background.append(tg.create_task(coro, name=f"{name}{self._suffix(c)}"))
        try:
            ends = await asyncio.gather(*(self._fly_vehicle(c) for c in self.crews), return_exceptions=True)
        finally:
            for task in background:
                task.cancel()
        for end in ends:
            if isinstance(end, BaseException) and not isinstance(end, UavlocError | Exception):
                raise end  # a cancellation or interrupt
        errors = [e for e in ends if isinstance(e, BaseException)]
        if len(errors) == len(ends):
            raise errors[0]  # every vehicle failed: the mission aborts (a one-vehicle mission: its error)
        return self._mission_end([e for e in ends if not isinstance(e, BaseException)])

    async def _probed(self, crew: VehicleCrew):
        """crew's gNB probe (VehicleCrew.probe_gnb); PREFLIGHT no longer waits for it once done."""
        out = await crew.probe_gnb()
        self._pending.pop(crew.id, None)
        return out

    def _suffix(self, crew: VehicleCrew) -> str:
        return f"-{crew.id}" if self.fleet else ""

    async def _connect(self, crew: VehicleCrew) -> None:
        crew.flight.set_phase(CONNECT)
        await self._named(crew, CONNECT, crew.vehicle.connect(self.config.connect_timeout_s))
        crew.connected = True

    async def _named(self, crew: VehicleCrew, state: str, wait: Awaitable[T]) -> T:
        """`wait` (bounded by its own timeout); its timeout error names the state and, in a fleet, the vehicle."""
        try:
            return await wait
        except VehicleTimeoutError as exc:
            raise VehicleTimeoutError(f"{state}{f' ({crew.id})' if self.fleet else ''}: {exc}") from exc

    async def _fly_vehicle(self, crew: VehicleCrew) -> tuple[str, str]:
        """One vehicle's take-off, survey, return and landing; its (status, reason). In a fleet a
        vehicle's own error sends it home (its safe end) and is returned for the mission to weigh;
        alone, the error is the mission's."""
        try:
            crew.outcome = await self._fly(crew)
            return crew.outcome
        except UavlocError as exc:
            if not self.fleet:
                raise
            crew.flight.set_phase(ABORT)
            log.error("%s aborted: %s", crew.id, exc)
            crew.event(f"vehicle aborted: {exc}", kind="abort", error=type(exc).__name__, reason=str(exc))
            await crew.safe_end(str(exc), SAFE_END_TIMEOUT_S)
            crew.outcome = (STATUS_ABORTED, str(exc))
            raise

    async def _fly(self, crew: VehicleCrew) -> tuple[str, str]:
        f, legs = crew.flight, crew.legs
        if self.fleet:
            await crew.set_return_layer()
        await legs.takeoff()
        crew.takeoff_over.set()
        if f.return_reason is None:
            f.set_phase(SURVEY)
            f.clock.start(crew.now(), time.monotonic())
            try:
                await legs.survey()
                while not await self._target_confirmed(crew):
                    await legs.survey()
            finally:
                crew.survey_ended()
                f.log_return()  # a return requested during the survey: after its survey_time
                if crew.index == 0:
                    self._note_pace(crew)
                crew.pipeline.release_users()
        f.set_phase(RETURN)
        if not await crew.send_rtl(f.return_reason or (f.stop or ("", "survey done"))[1]):
            raise VehicleError("the vehicle did not accept RTL")
        crew.landed = await crew.wait_landed(legs.return_timeout_s())
        crew.event("landed and disarmed" if crew.landed else "landing not confirmed before the timeout",
                   kind="landed" if crew.landed else "landing_timeout")
        f.set_phase(LANDED)
        await crew.pipeline.drain(30.0)  # the last keyframes before the final batch solve
        if f.return_reason is not None:
            return STATUS_RETURNED, f.return_reason
        return f.stop or (STATUS_RETURNED, "survey ended")

    def _mission_end(self, ends: list[tuple[str, str]]) -> tuple[str, str]:
        """The mission's (status, reason) from its vehicles' ends: its one vehicle's; a fleet's, the
        first of target, floor, budget any vehicle reached, else vehicle 0's (or the first vehicle's
        that ended without an error)."""
        if len(ends) == 1:
            return ends[0]
        for status in _FLEET_STATUS_ORDER:
            for end in ends:
                if end[0] == status:
                    return end
        return ends[0]

    def _finish_all(self, status: str, reason: str) -> None:
        """The stop rule ends every vehicle's survey (those taking off or surveying)."""
        for c in self.crews:
            if c.flight.phase in (TAKEOFF, SURVEY):
                c.flight.finish_survey(status, reason, c.now())

    def _at_home(self, homes: Sequence) -> None:
        """Every home is known: the ENU origin (vehicle 0's home by default), the home-dependent planner and
        limits, each vehicle's gate and legs, the log header. homes: each vehicle's (a GeoFix:
        lat_deg, lon_deg, alt_amsl_m), or a one-vehicle mission's home alone."""
        if not isinstance(homes, list | tuple):
            homes = [homes]
        home = homes[0]
        self.origin = (self._origin_at(homes) if self._origin_at is not None
                       else Origin(home.lat_deg, home.lon_deg, home.alt_amsl_m))
        if self._planner_at is not None:
            self.planner = self._planner_at(self.origin, 0)
        planners = [self.planner] + [self._planner_at(self.origin, i) for i in range(1, len(self.crews))]
        self.fleet_planner = FleetPlanner(planners, self.separation)
        for c, h in zip(self.crews, homes, strict=True):
            c.home = Origin(h.lat_deg, h.lon_deg, h.alt_amsl_m)
            c.home_enu_m = np.asarray(self.origin.lla_to_enu(h.lat_deg, h.lon_deg, h.alt_amsl_m), float)
            if self._limits_at is not None:
                c.gate = SafetyGate(self._limits_at(self.origin, c.index))
            others = (lambda me=c: [leg for o in self.crews if o is not me
                                    for leg in [o.committed_leg()] if leg is not None]) if self.fleet else None
            c.gated = GatedVehicle(c.vehicle, c.gate, self.origin, c.event, c.pos_enu_smoothed, others=others)
            vplanner = _VehiclePlanner(self.fleet_planner, c.index, self._serving_now, self._committed,
                                       self._plan_lock)
            c.legs = SurveyLegs(LegsDeps(
                config=c.config, flight=c.flight, gated=c.gated, set_speed=lambda mps, c=c: c.vehicle.set_speed(mps),
                battery_pct=lambda c=c: c.vehicle.state.battery_pct, battery_rtl_pct=c.gate.limits.battery_rtl_pct,
                planner=vplanner, origin=self.origin, journal=self.journal, pos_enu=c.pos_enu, now=c.now,
                wall=c.wall, drain=c.pipeline.drain, sigma_gps_m=self.noise.sigma_gps_m, event=c.event, tag=c.tag))
        cfg = dict(self.header_config)
        cfg.setdefault("controller", asdict(self.config))
        cfg.setdefault("solver", solver_params_header(self.params))
        lim = self.crews[0].gate.limits
        area = area_fields(self.origin, lim.fence_enu_m, lim.no_fly_enu_m, lim.alt_min_m, lim.alt_max_m,
                           lim.max_distance_m, self._buildings(self.origin) if self._buildings else None)
        vehicles = None
        if self.fleet:
            vehicles = [{"id": c.id, "home": {"lat_deg": c.home.lat_deg,
                                              "lon_deg": c.home.lon_deg, "alt_m": c.home.alt_m},
                         "alt_min_m": c.gate.limits.alt_min_m, "alt_max_m": c.gate.limits.alt_max_m}
                        for c in self.crews]
        self.journal.open(self.origin, self.radio, self.noise, cfg, self._start_utc, area=area, vehicles=vehicles)
        if self._truth is not None:
            self.truth_enu_m = np.asarray(self._truth(self.origin), float).reshape(len(self.users), 3)
            self.journal.truth(self.origin, self.truth_enu_m)
        for c, h in zip(self.crews, homes, strict=True):
            c.event(f"home {h.lat_deg:.7f}, {h.lon_deg:.7f}, {h.alt_amsl_m:.1f} m AMSL", kind="home")

    def _serving_now(self) -> np.ndarray:
        """(K,) whose user is whose, for planning: `serving`, with the users of a vehicle asked to
        return home nobody's (the others plan for them at once, before its survey has wound down)."""
        s = self.serving.copy()
        for c in self.crews:
            if c.flight.return_reason is not None:
                s[s == c.index] = -1
        return s

    def _committed(self) -> list[np.ndarray | None]:
        """Each vehicle's committed leg now (VehicleCrew.committed_leg), for the fleet's planner."""
        return [c.committed_leg() for c in self.crews]

    def _watch_separation(self, crew: VehicleCrew) -> None:
        """A fleet's vehicles in the air closer than the separation (horizontally and in altitude):
        an event when it starts (`separation_lost`, with the least distance) and when it ends."""
        airborne = [c for c in self.crews if c.airborne and c.pos_enu() is not None]
        if len(airborne) < 2:
            apart, least = True, float("inf")
        else:
            apart, least = vehicles_apart(np.array([c.pos_enu() for c in airborne]), self.separation)
        if apart == self._apart:
            return
        self._apart = apart
        if not apart:
            self.separation_breaches.append((self.now(), least))
            log.warning("vehicles closer than the separation: %.1f m", least)
            self.journal.event(f"vehicles {', '.join(c.id for c in airborne)} closer than the separation: "
                               f"{least:.1f} m", kind="separation_lost", least_m=round(least, 2))
        else:
            self.journal.event("vehicles apart again", kind="separation_restored")

    async def _prepare_planner(self) -> None:
        """The planner's one-time work (CasADi kernels) before take-off, in a thread, so that the
        first plan with an estimate does not hold the vehicle in a hover (planner.types.Planner.prepare)."""
        t0 = time.perf_counter()
        await asyncio.to_thread(self.fleet_planner.prepare)
        took_s = time.perf_counter() - t0
        if took_s > 0.05:
            self.journal.event(f"planner {self.fleet_planner.name} prepared in {took_s:.2f} s (before take-off)",
                               kind="planner_prepared", took_s=round(took_s, 3))

    def _preflight_home(self) -> None:
        """No take-off from a home outside the fence, inside a no-fly zone or beyond max_distance_m
        of the origin (geodetic polygons are known in the home frame only now; mission.config
        refuses ENU ones at load): a fleet's every vehicle is held to it, and none arms when one fails."""
        if not self.fleet:
            self.crews[0].preflight_home()
            return
        bad = [(c, p) for c in self.crews for p in [c.home_problems()] if p]
        if bad:
            raise SafetyError("not taking off: no vehicle of the fleet arms: " + "; ".join(
                f"{c.id}'s {'; '.join(p)}" for c, p in bad))

    async def _preflight_gnb(self) -> None:
        """No take-off unless every configured user is among the gNB's UEs and answers one
        measurement (passive stock mode: is among them; its random accesses come when they come).
        The event and the error say which RNTIs the gNB has and what it answered.

        A fleet's gNBs each serve the UEs attached to their cells, and a fleet flies users spread
        wider than one cell's reach (a gNB on the ground reaches less far than one in the air:
        sitl_scenarios.radio.reach_m): every gNB must answer, and every UE on its cell must answer
        a measurement; users no gNB has yet are logged (`users_unserved`) and attach as the vehicles
        come within reach."""
        if not self.fleet:
            await self.crews[0].preflight_gnb()
            return
        probes = await asyncio.gather(*(self._probed(c) for c in self.crews))
        for c, (probe, ok) in zip(self.crews, probes, strict=True):
            if not ok:
                raise GnbPreflightError(f"not taking off: {c.id}'s gNB: {probe.message()}")
            for r in probe.gnb_rntis or []:
                k = next((k for k, u in enumerate(self.users) if u.rnti == r), None)
                if k is not None and self.serving[k] < 0:
                    self.serving[k] = c.index
        unserved = [u.id for k, u in enumerate(self.users) if self.serving[k] < 0]
        if unserved:
            self.journal.event(f"no vehicle's gNB serves {', '.join(unserved)} yet: they attach as the vehicles come "
                               "within reach", kind="users_unserved", users=unserved)

    def _note_pace(self, crew: VehicleCrew) -> None:
        self.pace = crew.flight.clock.pace(self.config.time_scale)
        if self.pace is not None and crew.flight.pace_said:
            self.pace = replace(self.pace, said_while_flying=crew.flight.pace_said)
        if self.pace is not None and self.pace.fell_behind:
            log.warning("%s", self.pace.message())
            self.journal.event(self.pace.message(), kind="fell_behind", **self.pace.to_dict())

    # -- background tasks -----------------------------------------------------------------------

    def _flight_noise(self) -> NoiseModel:
        """The noise model the flight's estimator uses: the mission's, with the GPS error's
        correlation time estimated from the telemetry logged so far (the take-off; a fleet's vehicles
        each a series of their own) when the mission leaves it unknown (an external autopilot: PX4's
        EKF output drifts with τ of minutes); the estimator's default when too little was logged.
        The τ used is logged (event gps_tau): replay's final answer uses it (resolve_gps_tau)."""
        if self.crews[0].tau_records is None:
            return self.noise
        records, series = [], []
        for c in self.crews:
            mine, c.tau_records = c.tau_records or [], None
            records += mine
            series += [c.index] * len(mine)
        tau = None
        if len(records) > 1:
            t, pos, vel = (np.array(c) for c in zip(*records, strict=True))
            tau = estimate_gps_tau_s(t, pos, vel, self.noise.sigma_gps_m, series=np.array(series))
        if tau is None:
            self.journal.event(f"GPS error correlation time unknown and too little telemetry to estimate it "
                               f"({len(records)} records): assuming {self.noise.gps_tau_used_s:g} s", kind="gps_tau",
                               gps_tau_s=self.noise.gps_tau_used_s, estimated=False)
            return self.noise
        self.journal.event(f"GPS error correlation time estimated from {len(records)} telemetry records: "
                           f"{tau:.0f} s", kind="gps_tau", gps_tau_s=tau, estimated=True)
        return replace(self.noise, gps_tau_s=tau)

    def estimator_setup(self, noise: NoiseModel | None = None) -> MissionEstimator:
        """The mission's estimator (mission.estimation) for these users, settings and stop rule."""
        return MissionEstimator(len(self.users), np.array([u.up_m for u in self.users], float),
                                self.noise if noise is None else noise, self.params, self.config.flight.target_radius_m)

    async def _estimator_task(self) -> None:
        if self.crews[0].tau_records is not None:
            # the first keyframe comes with the survey: estimate τ from the take-off's telemetry
            await self.crews[0].takeoff_over.wait()
        # the stop rule is judged on batch estimates only: a target the online estimate reaches
        # asks the worker for a batch refresh first (mission.estimation)
        setup = self._estimator = self.estimator_setup(self._flight_noise())
        worker = EstimatorWorker(setup, self.keyframes_out, mode=self.config.estimator_mode)

        def on_estimate(est: Estimate) -> None:
            self.estimate = est
            self.journal.estimate(self.origin, est, len(self._keyframes), self.flown_m,
                                  vehicles=self._kf_vehicles() if self.fleet else None)
            if any(c.flight.phase == SURVEY for c in self.crews) and setup.stops(est):
                self._finish_all(STATUS_TARGET, "target reached")

        def on_error(exc: EstimatorError) -> None:
            self.journal.event(f"estimator: {exc}", kind="estimator_error")

        await worker.run(on_estimate, on_error)

    def _kf_vehicles(self) -> list[int]:
        return [kf.vehicle for kf in self._keyframes]

    async def _status_task(self) -> None:
        while True:
            await asyncio.sleep(self.config.status_interval_s)
            log.info("%s", self.status_line())

    def status_line(self) -> str:
        def line(c: VehicleCrew, prefix: str = "") -> str:
            f = c.flight
            home_in = None
            if f.gnb_down_since is not None and f.phase in (TAKEOFF, SURVEY):
                home_in = max(0.0, self.config.safety.gnb_lost_wait_s - (c.now() - f.gnb_down_since))
            return prefix + status_line(f.phase, c.now(), f.flown_m, f.measurements, self.users if not prefix else [],
                                        f.estimate if not prefix else None,
                                        f.gnb_problem if f.gnb_down_since is not None else None, home_in)

        if not self.fleet:
            return line(self.crews[0])
        head = status_line(self.state, self.now(), self.flown_m, self.measurements, self.users, self.estimate)
        return " || ".join([head] + [line(c, f"{c.id} ") for c in self.crews])

    # -- start and end --------------------------------------------------------------------------

    async def run(self) -> MissionResult:
        """Fly the mission and return its result. Cancellation (Ctrl-C) sends RTL, then re-raises."""
        t_wall = time.monotonic()
        status, reason = STATUS_ABORTED, ""
        try:
            try:
                async with asyncio.TaskGroup() as tg:
                    status, reason = await self._flow(tg)
            except BaseExceptionGroup as eg:
                raise _first_error(eg) from eg
        except (asyncio.CancelledError, KeyboardInterrupt) as exc:
            self._set_phase(ABORT)
            how = "cancelled" if isinstance(exc, asyncio.CancelledError) else "Ctrl-C"
            self.journal.event(f"mission interrupted ({how}): returning home", kind="interrupted")
            await self._safe_end("interrupted", INTERRUPT_SAFE_END_TIMEOUT_S)
            self._close(STATUS_INTERRUPTED, "interrupted", t_wall)
            raise
        except UavlocError as exc:
            self._set_phase(ABORT)
            log.error("mission aborted: %s", exc)
            self.journal.event(f"mission aborted: {exc}", kind="abort", error=type(exc).__name__)
            await self._safe_end(str(exc))
            return self._close(STATUS_ABORTED, str(exc), t_wall)
        except Exception as exc:
            self._set_phase(ABORT)
            log.exception("mission aborted by an unexpected error")
            self.journal.event(f"mission aborted: unexpected {type(exc).__name__}: {exc}", kind="abort",
                               error=type(exc).__name__)
            await self._safe_end(str(exc))
            self._close(STATUS_ABORTED, str(exc), t_wall)
            raise
        return self._close(status, reason, t_wall)

    def _set_phase(self, phase: str) -> None:
        for c in self.crews:
            c.flight.set_phase(phase)

    async def _safe_end(self, reason: str, timeout_s: float = SAFE_END_TIMEOUT_S) -> None:
        """Never leave a vehicle without a safe command: RTL to every one that may be airborne (trying
        for at most timeout_s wall seconds, all at once)."""
        await asyncio.gather(*(c.safe_end(reason, timeout_s) for c in self.crews))

    def last_resort(self, why: str, timeout_s: float = 4.0) -> None:
        """RTL to every vehicle that may be airborne and the log's end record, from a thread other
        than the event loop's, which does not answer (mission.runtime's signal watchdog)."""
        from mission.control.last_resort import end_from_outside

        end_from_outside(self.crews, self.journal, why, timeout_s)

def _first_error(eg: BaseExceptionGroup) -> BaseException:
    """The exception to act on from a TaskGroup's group: a cancellation/interrupt first, then a
    project error, then anything else."""
    flat: list[BaseException] = []

    def walk(e: BaseException) -> None:
        if isinstance(e, BaseExceptionGroup):
            for sub in e.exceptions:
                walk(sub)
        else:
            flat.append(e)

    walk(eg)
    for kind in (KeyboardInterrupt, asyncio.CancelledError, UavlocError):
        for e in flat:
            if isinstance(e, kind):
                return e
    return flat[0]
