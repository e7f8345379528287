"""The mission controller (docs/design.md §1, §7): fly, measure every Δ, estimate, replan, stay safe.

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

The survey asks the planner for a waypoint at each leg end, passes it through the safety gate
(:class:`GatedVehicle`: nothing reaches the vehicle that the gate did not pass) and flies it
until arrival within the acceptance radius or the leg timeout. The stop rule (every user's 95 %
ellipse within the target radius, or the budget spent) leads to RETURN. An exception, a
cancellation (Ctrl-C) or a safety condition ends in RTL and a flushed log.

Time: the log's `t` is mission seconds since start on the vehicle's clock (MAVLink boot time,
:class:`mission.vehicle.telemetry.VehicleClock`); before the vehicle's time is known (and with a vehicle
that sends none) it is `(monotonic − start) · time_scale` (the simulator's speedup; 1 for real
flights). Request timeouts stay in wall seconds.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from estimator.geodesy import Origin
from estimator.gps import estimate_gps_tau_s
from estimator.noise import NoiseModel
from estimator.types import Estimate, Keyframe, SolverParams
from mission.control.config import (
    ABORT,
    CONNECT,
    INTERRUPT_SAFE_END_TIMEOUT_S,
    LANDED,
    PREFLIGHT,
    RETURN,
    SAFE_END_TIMEOUT_S,
    STATUS_ABORTED,
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
from mission.control.estimator_worker import EstimatorWorker
from mission.control.journal import MissionJournal, status_line
from mission.control.legs import PLAN_DRAIN_MAX_S, LegsDeps, SurveyLegs
from mission.control.loop import LoopLagMonitor
from mission.control.pipeline import MeasurementPipeline
from mission.control.safety_monitor import SafetyMonitor
from mission.control.state import FlightState, SurveyPace, spacing_m
from mission.estimation import MissionEstimator, solver_params_header
from mission.gnb import GnbClient
from mission.log import MissionLogWriter, area_fields, read_mission_log
from mission.replay import ReplayOptions, ReplayResult, replay, result_of_log
from mission.result import Result, build_result
from mission.safety import GatedVehicle, SafetyGate, SafetyLimits
from mission.vehicle import PositionFix, Vehicle
from mission.vehicle.telemetry import TelemetryBuffer, VehicleClock
from planner.types import Planner
from uavloc.errors import (
    EstimatorError,
    GnbPreflightError,
    MissionError,
    MissionLogError,
    SafetyError,
    UavlocError,
    VehicleError,
)

log = logging.getLogger(__name__)


class MissionController:
    """Runs one mission. See the module docstring.

    vehicle: a :class:`Vehicle` (connected by the controller); gnb: a connected :class:`GnbClient`;
    planner: a :class:`planner.types.Planner` whose constraints are in the home ENU frame, or
    home -> Planner; users: the users to locate; noise/params: the estimator's model and settings;
    limits: the safety gate's limits (home ENU frame), or home -> SafetyLimits; log_path: the
    mission log; truth: simulation only: home -> (K, 3) true user positions in the home ENU frame
    [m] (the `truth` record); header_config: the header's `config` section; radio: its `radio`;
    buildings: simulation only: home -> [(footprint (Q, 2) [m, ENU from home], height_m)] for the
    header's `buildings` (the live view and the exports draw them).
    """

    def __init__(self, vehicle: Vehicle, gnb: GnbClient, planner: Planner | Callable[[Origin], Planner],
                 users: list[MissionUser], noise: NoiseModel,
                 limits: SafetyLimits | Callable[[Origin], SafetyLimits], config: ControllerConfig,
                 log_path: str | Path, params: SolverParams | None = None,
                 truth: Callable[[Origin], np.ndarray] | None = None,
                 header_config: dict | None = None, radio: dict | None = None,
                 buildings: Callable[[Origin], list] | None = None):
        if not users:
            raise MissionError("a mission needs at least one user")
        self.vehicle, self.gnb = vehicle, gnb
        self.users = list(users)
        self.noise, self.config = noise, config
        self.params = params or SolverParams(delta_m=config.flight.delta_m)
        # a planner or limits given as a function of home are built once home is known (PREFLIGHT)
        self._planner_at = None if hasattr(planner, "plan") else planner
        self.planner = planner if self._planner_at is None else None
        self._limits_at = None if isinstance(limits, SafetyLimits) else limits
        self.gate: SafetyGate | None = None if self._limits_at is not None else SafetyGate(limits)
        self._truth = truth
        self._buildings = buildings
        self.truth_enu_m: np.ndarray | None = None
        self.header_config = header_config or {}
        self.radio = radio or {}
        self.log_path = Path(log_path)
        self.origin: Origin | None = None
        self._t0_mono = time.monotonic()
        self._clock = VehicleClock(self._t0_mono, config.time_scale)
        self._start_utc = datetime.now(UTC).isoformat(timespec="milliseconds")
        self._buffer = TelemetryBuffer(4096)
        self._last_tel_log_t = -math.inf
        # the telemetry records as logged (t [s], ENU [m], velocity ENU [m/s]) until the take-off is
        # over, for the GPS correlation time when the noise model leaves it unknown (_flight_noise)
        self._tau_records: list[tuple[float, np.ndarray, np.ndarray]] | None = (
            [] if noise.gps_tau_s is None else None)
        self._takeoff_over = asyncio.Event()
        self._estimator: MissionEstimator | None = None  # the flight's estimator setup, once it runs
        self.journal = MissionJournal(MissionLogWriter(self.log_path), self.users, self.now, lambda: self.flight.phase)
        self.flight = FlightState(event=self.journal.event)
        self.pipeline = MeasurementPipeline(gnb, self.users, config.flight.delta_m, config.gnb_timeout_s, self.flight,
                                            self._buffer, lambda: self.origin, self.journal.writer, self.now,
                                            self.mission_t)
        self.legs: SurveyLegs | None = None  # once home is known (_at_home)
        self._gated: GatedVehicle | None = None
        self._connected = False
        self.loop_lag = LoopLagMonitor()
        self.result: MissionResult | None = None  # set when the mission ends (also when cancelled)
        #: how fast the survey really ran against the wall clock (once it ended)
        self.pace: SurveyPace | None = None
        self._rtl_sent = self._landed = self._rtl_gave_up = False
        self._autopilot_landing = False  # RTL not sent: the autopilot was already landing on its own

    # -- what the flight knows, for callers and tests --------------------------------------------

    @property
    def log_writer(self) -> MissionLogWriter:
        """The mission log's writer; the live view subscribes to its records."""
        return self.journal.writer

    @property
    def state(self) -> str:
        return self.flight.phase

    @property
    def estimate(self) -> Estimate | None:
        return self.flight.estimate

    @estimate.setter
    def estimate(self, est: Estimate | None) -> None:
        self.flight.estimate = est

    @property
    def measurements(self) -> int:
        return self.flight.measurements

    @property
    def flown_m(self) -> float:
        return self.flight.flown_m

    @property
    def keyframes(self) -> list[Keyframe]:
        return self.pipeline.keyframes

    @property
    def event_messages(self) -> list[str]:
        return self.journal.messages

    def request_return(self, reason: str) -> None:
        """Ask the flight to end the survey and return home (first reason wins)."""
        self.flight.request_return(reason)

    # -- clock ----------------------------------------------------------------------------------

    def now(self) -> float:
        """Mission seconds since start (vehicle seconds once the vehicle's clock is known)."""
        return self._clock.mission_t(time.monotonic())

    def mission_t(self, t_mono_s: float) -> float:
        return self._clock.mission_t(t_mono_s)

    def wall(self, mission_s: float) -> float:
        """Mission seconds → wall seconds (at the vehicle clock's current rate)."""
        return mission_s / self._clock.rate

    # -- telemetry ------------------------------------------------------------------------------

    def pos_enu(self) -> np.ndarray | None:
        latest = self._buffer.latest()
        return None if latest is None else latest[1]

    def _pos_enu_smoothed(self) -> np.ndarray | None:
        """Mean of the fixes over the last config.position_smooth_s (mission), or None."""
        latest = self._buffer.latest()
        return None if latest is None else self._buffer.mean_since(latest[0] - self.config.position_smooth_s)

    def _on_fix(self, fix: PositionFix) -> None:
        if self.origin is None:
            return
        t = self.mission_t(fix.t_mono_s)
        pos = self.origin.lla_to_enu(fix.lat_deg, fix.lon_deg, fix.alt_amsl_m)
        self._buffer.append(t, pos)
        if fix.vel_ned_mps is not None:
            self.flight.clock.fix(t, float(np.linalg.norm(fix.vel_ned_mps)))
        if t - self._last_tel_log_t >= 1.0 / self.config.telemetry_log_hz and self.journal.is_open:
            self._last_tel_log_t = t
            extra = {"vel_ned_mps": list(fix.vel_ned_mps)} if fix.vel_ned_mps is not None else {}
            state = getattr(self.vehicle, "state", None)
            if state is not None:
                extra.update(state.status().record_fields())
            rec = self.journal.writer.write("telemetry", t, lat_deg=fix.lat_deg, lon_deg=fix.lon_deg,
                                            alt_m=fix.alt_amsl_m, **extra)
            if self._tau_records is not None and fix.vel_ned_mps is not None:
                # the numbers as logged, so that replay's estimate from the same records agrees
                vn, ve, vd = rec["vel_ned_mps"]
                enu = self.origin.lla_to_enu(rec["lat_deg"], rec["lon_deg"], rec["alt_m"])
                self._tau_records.append((rec["t"], np.asarray(enu, float), np.array([ve, vn, -vd])))
        self.flight.wake.pulse()

    # -- the flight -----------------------------------------------------------------------------

    async def _flow(self, tg: asyncio.TaskGroup) -> tuple[str, str]:
        cfg, f = self.config, self.flight
        background: list[asyncio.Task] = []
        f.set_phase(CONNECT)
        await self.vehicle.connect(cfg.connect_timeout_s)
        self._connected = True
        background.append(tg.create_task(self.vehicle.run_telemetry(self._on_fix, self._clock.update),
                                         name="telemetry"))
        f.set_phase(PREFLIGHT)
        self._at_home(await self.vehicle.wait_ready(cfg.ready_timeout_s))
        # the planner's kernels compile (seconds of CPU) while the gNB is probed, not after it
        prepared = tg.create_task(self._prepare_planner(), name="prepare-planner")
        background.append(prepared)
        self._preflight_home()
        await self._preflight_gnb()
        self._preflight_battery()
        await prepared
        safety = SafetyMonitor(f, cfg, self.gate, self.vehicle.state, self._buffer.latest, self.now)
        for coro, name in ((self._estimator_task(), "estimator"), (self.pipeline.run_trigger(), "trigger"),
                           (self.pipeline.run_placer(), "placer"), (safety.run(), "safety"),
                           (self._status_task(), "status"), (self.loop_lag.run(), "loop-lag")):
            background.append(tg.create_task(coro, name=name))
        try:
            await self.legs.takeoff()
            self._takeoff_over.set()
            if f.return_reason is None:
                f.set_phase(SURVEY)
                f.clock.start(self.now(), time.monotonic())
                try:
                    await self.legs.survey()
                    while not await self._target_confirmed():
                        await self.legs.survey()
                finally:
                    self._survey_ended()
            f.set_phase(RETURN)
            if not await self._send_rtl(f.return_reason or (f.stop or ("", "survey done"))[1]):
                raise VehicleError("the vehicle did not accept RTL")
            self._landed = await self._wait_landed(self.legs.return_timeout_s())
            self.journal.event("landed and disarmed" if self._landed else "landing not confirmed before the timeout",
                               kind="landed" if self._landed else "landing_timeout")
            f.set_phase(LANDED)
            await self.pipeline.drain(30.0)  # the last keyframes before the final batch solve
        finally:
            for task in background:
                task.cancel()
        if f.return_reason is not None:
            return STATUS_RETURNED, f.return_reason
        return f.stop or (STATUS_RETURNED, "survey ended")

    async def _target_confirmed(self) -> bool:
        """After a survey that ended "target reached" or "floor reached": the mission's final
        answer (the batch over every keyframe, the last rounds placed first) decides. "Target
        reached" must hold for the answer the mission prints: a last range can widen a bound by a
        metre (seen: 3.86 to 4.84 m against 4 m), and then the survey goes on (False). A floor the
        survey's estimate saw may be within the target in the final answer (seen: 3.57 m against
        4 m after "floor reached"): then the target is reached."""
        f = self.flight
        if (f.stop is None or f.stop[0] not in (STATUS_TARGET, STATUS_FLOOR) or f.return_reason is not None
                or self._estimator is None):
            return True
        await self.pipeline.drain(self.wall(PLAN_DRAIN_MAX_S))
        final = await asyncio.to_thread(self._estimator.final, list(self.pipeline.keyframes))
        reached = self._estimator.within_target(final)
        if f.stop[0] == STATUS_FLOOR:
            if reached:
                f.stop = (STATUS_TARGET, "target reached")
                self.journal.event(f"the final answer over {len(self.pipeline.keyframes)} keyframes bounds every "
                                   f"user within the {self.config.flight.target_radius_m:g} m target: target reached",
                                   kind="target_in_final_answer")
            return True
        if reached:
            return True
        worst = float(np.max(final.error_bound_95_m()))
        f.resume_survey()
        self.journal.event(f"the final answer over {len(self.pipeline.keyframes)} keyframes bounds a user at "
                           f"{worst:.2f} m, beyond the {self.config.flight.target_radius_m:g} m target the "
                           f"survey's estimate reached: surveying on", kind="target_unconfirmed", bound_95_m=worst)
        f.estimate = final
        return False

    def _at_home(self, home) -> None:
        """Home is known: the ENU origin, the home-dependent planner and limits, the log header."""
        self.origin = Origin(home.lat_deg, home.lon_deg, home.alt_amsl_m)
        if self._planner_at is not None:
            self.planner = self._planner_at(self.origin)
        if self._limits_at is not None:
            self.gate = SafetyGate(self._limits_at(self.origin))
        self._gated = GatedVehicle(self.vehicle, self.gate, self.origin, self.journal.event, self._pos_enu_smoothed)
        self.legs = SurveyLegs(LegsDeps(
            config=self.config, flight=self.flight, gated=self._gated,
            set_speed=lambda mps: self.vehicle.set_speed(mps), battery_pct=lambda: self.vehicle.state.battery_pct,
            battery_rtl_pct=self.gate.limits.battery_rtl_pct, planner=self.planner, origin=self.origin,
            journal=self.journal, pos_enu=self.pos_enu, now=self.now, wall=self.wall, drain=self.pipeline.drain,
            sigma_gps_m=self.noise.sigma_gps_m))
        cfg = dict(self.header_config)
        cfg.setdefault("controller", asdict(self.config))
        cfg.setdefault("solver", solver_params_header(self.params))
        lim = self.gate.limits
        area = area_fields(self.origin, lim.fence_enu_m, lim.no_fly_enu_m, lim.alt_min_m, lim.alt_max_m,
                           lim.max_distance_m, self._buildings(self.origin) if self._buildings else None)
        self.journal.open(self.origin, self.radio, self.noise, cfg, self._start_utc, area=area)
        if self._truth is not None:
            self.truth_enu_m = np.asarray(self._truth(self.origin), float).reshape(len(self.users), 3)
            self.journal.truth(self.origin, self.truth_enu_m)
        self.journal.event(f"home {home.lat_deg:.7f}, {home.lon_deg:.7f}, {home.alt_amsl_m:.1f} m AMSL", kind="home")

    async def _preflight_gnb(self) -> None:
        """No take-off unless every configured user is among the gNB's UEs and answers one
        measurement (passive stock mode: is among them; its random accesses come when they come).
        The event and the error say which RNTIs the gNB has and what it answered."""
        from mission.gnb.probe import probe_gnb

        rntis = [u.rnti for u in self.users]
        gcfg = getattr(self.gnb, "config", None)
        passive = getattr(gcfg, "mode", None) == "stock" and getattr(gcfg, "stock_mode", None) == "passive"
        bound_s = self.config.gnb_timeout_s * (2 + len(rntis))
        try:
            async with asyncio.timeout(bound_s):
                probe = await probe_gnb(self.gnb, rntis=rntis, count=1)
        except TimeoutError as exc:
            raise GnbPreflightError(f"not taking off: the gNB did not finish the preflight probe within "
                                    f"{bound_s:g} s") from exc
        have = probe.gnb_rntis or []
        ok = probe.ok or (passive and probe.gnb_rntis is not None and all(r in have for r in rntis))
        self.journal.event(probe.message(), kind="preflight_gnb", ok=ok, rntis=[f"{r:04x}" for r in have],
                           probe=probe.to_dict())
        if not ok:
            raise GnbPreflightError(f"not taking off: {probe.message()}")

    def _survey_ended(self) -> None:
        """Log how the survey spent its time and what it measured, as it happened: hover (slower than
        HOVER_SPEED_MPS), the longest time without a range, the gNB rounds placed (metres flown per
        round and per range of each user, rounds per minute); and, when it ran materially slower
        than its speed-up (SurveyPace), a `fell_behind` event and a warning."""
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
        self.journal.event(f"survey {c.survey_s:.0f} s: hovering {c.hover_s:.1f} s ({share:.1f} %), longest without "
                           f"a range {c.largest_gap_s:.1f} s; {measured}; {self.legs.planned_ahead} legs planned "
                           f"ahead", kind="survey_time", survey_s=round(c.survey_s, 2), hover_s=round(c.hover_s, 2),
                           largest_gap_s=round(c.largest_gap_s, 2), planned_ahead=self.legs.planned_ahead,
                           flown_m=round(flown_m, 2), rounds=c.rounds, ranges=c.ranges,
                           spacing_m=None if round_m is None else round(round_m, 2),
                           user_spacing_m=None if user_m is None else round(user_m, 2),
                           rounds_per_min=None if per_min is None else round(per_min, 2))
        self.pace = c.pace(self.config.time_scale)
        if self.pace is not None and self.pace.fell_behind:
            log.warning("%s", self.pace.message())
            self.journal.event(self.pace.message(), kind="fell_behind", **self.pace.to_dict())

    async def _prepare_planner(self) -> None:
        """The planner's one-time work (CasADi kernels) before take-off, in a thread, so that the
        first plan with an estimate does not hold the vehicle in a hover (planner.types.Planner.prepare)."""
        t0 = time.perf_counter()
        await asyncio.to_thread(self.planner.prepare)
        took_s = time.perf_counter() - t0
        if took_s > 0.05:
            self.journal.event(f"planner {self.planner.name} prepared in {took_s:.2f} s (before take-off)",
                               kind="planner_prepared", took_s=round(took_s, 3))

    def _preflight_home(self) -> None:
        """No take-off from a home outside the fence or inside a no-fly zone (geodetic polygons
        are known in the home frame only now; mission.config refuses ENU ones at load)."""
        problems = self.gate.home_violations()
        if problems:
            raise SafetyError(f"not taking off: {'; '.join(problems)}")

    def _preflight_battery(self) -> None:
        """No take-off below battery_takeoff_min_pct (when the vehicle reports its charge)."""
        pct, floor = self.vehicle.state.battery_pct, self.config.safety.battery_takeoff_min_pct
        if pct is None:
            self.journal.event("battery charge unknown before take-off", kind="battery_unknown")
        elif pct < floor:
            raise SafetyError(f"not taking off: battery at {pct:g} % is below battery_takeoff_min_pct {floor:g} %")

    # -- background tasks -----------------------------------------------------------------------

    def _flight_noise(self) -> NoiseModel:
        """The noise model the flight's estimator uses: the mission's, with the GPS error's
        correlation time estimated from the telemetry logged so far (take-off) when the mission
        leaves it unknown (an external autopilot: PX4's EKF output drifts with τ of minutes), as
        replay estimates it from the whole log; the estimator's default when too little was logged."""
        records, self._tau_records = self._tau_records, None
        if records is None:
            return self.noise
        tau = None
        if len(records) > 1:
            t, pos, vel = (np.array(c) for c in zip(*records, strict=True))
            tau = estimate_gps_tau_s(t, pos, vel, self.noise.sigma_gps_m)
        if tau is None:
            self.journal.event(f"GPS error correlation time unknown and too little telemetry to estimate it "
                               f"({len(records)} records): assuming {self.noise.gps_tau_used_s:g} s", kind="gps_tau")
            return self.noise
        self.journal.event(f"GPS error correlation time estimated from {len(records)} telemetry records: "
                           f"{tau:.0f} s", kind="gps_tau", gps_tau_s=tau)
        return replace(self.noise, gps_tau_s=tau)

    def estimator_setup(self, noise: NoiseModel | None = None) -> MissionEstimator:
        """The mission's estimator (mission.estimation) for these users, settings and stop rule."""
        return MissionEstimator(len(self.users), np.array([u.up_m for u in self.users], float),
                                self.noise if noise is None else noise, self.params, self.config.flight.target_radius_m)

    async def _estimator_task(self) -> None:
        f = self.flight
        if self._tau_records is not None:
            # the first keyframe comes with the survey: estimate τ from the take-off's telemetry
            await self._takeoff_over.wait()
        # the stop rule is judged on batch estimates only: a target the online estimate reaches
        # asks the worker for a batch refresh first (mission.estimation)
        setup = self._estimator = self.estimator_setup(self._flight_noise())
        worker = EstimatorWorker(setup, self.pipeline.keyframes_out, mode=self.config.estimator_mode)

        def on_estimate(est: Estimate) -> None:
            f.estimate = est
            self.journal.estimate(self.origin, est, len(self.pipeline.keyframes), f.flown_m)
            if f.phase == SURVEY and setup.stops(est):
                f.finish_survey(STATUS_TARGET, "target reached", self.now())

        def on_error(exc: EstimatorError) -> None:
            self.journal.event(f"estimator: {exc}", kind="estimator_error")

        await worker.run(on_estimate, on_error)

    async def _status_task(self) -> None:
        while True:
            await asyncio.sleep(self.config.status_interval_s)
            log.info("%s", self.status_line())

    def status_line(self) -> str:
        f = self.flight
        home_in = None
        if f.gnb_down_since is not None and f.phase in (TAKEOFF, SURVEY):
            home_in = max(0.0, self.config.safety.gnb_lost_wait_s - (self.now() - f.gnb_down_since))
        return status_line(f.phase, self.now(), f.flown_m, f.measurements, self.users, f.estimate,
                           f.gnb_problem if f.gnb_down_since is not None else None, home_in)

    # -- vehicle helpers ------------------------------------------------------------------------

    async def _send_rtl(self, reason: str, retry_s: float = 60.0) -> bool:
        """Send RTL, retrying (e.g. while the link is down) for up to `retry_s` wall seconds;
        True when the vehicle accepted it."""
        t_end = time.monotonic() + retry_s
        attempt = 0
        while True:
            attempt += 1
            if self.vehicle.state.flight_mode == "LAND":
                # the autopilot's own failsafe is landing the vehicle (PX4 after a GPS loss): that is
                # a safe command already, and RTL would be refused without a position
                self._autopilot_landing = True
                self.journal.event(f"RTL not sent: the autopilot is already landing ({reason})", kind="autopilot_land")
                return True
            try:
                await self._gated.return_to_launch()
            except VehicleError as exc:
                if attempt == 1 or attempt % 10 == 0:
                    log.warning("RTL attempt %d failed: %s", attempt, exc)
                    self.journal.event(f"RTL attempt {attempt} failed: {exc}", kind="rtl_failed")
                if time.monotonic() >= t_end:
                    self._rtl_gave_up = True
                    return False
                await asyncio.sleep(0.5)
                continue
            self._rtl_sent = True
            self.journal.event(f"RTL: {reason}", kind="rtl", attempts=attempt)
            return True

    async def _wait_landed(self, timeout_s: float) -> bool:
        st = self.vehicle.state
        deadline = time.monotonic() + self.wall(timeout_s)
        while time.monotonic() < deadline:
            if st.landed_state == "ON_GROUND" and st.armed is False:
                return True
            await self.flight.wake.wait(0.2)
        return False

    # -- start and end --------------------------------------------------------------------------

    async def run(self) -> MissionResult:
        """Fly the mission and return its result. Cancellation (Ctrl-C) sends RTL, then re-raises."""
        t_wall = time.monotonic()
        status, reason = STATUS_ABORTED, ""
        f = self.flight
        try:
            try:
                async with asyncio.TaskGroup() as tg:
                    status, reason = await self._flow(tg)
            except BaseExceptionGroup as eg:
                raise _first_error(eg) from eg
        except (asyncio.CancelledError, KeyboardInterrupt) as exc:
            f.set_phase(ABORT)
            how = "cancelled" if isinstance(exc, asyncio.CancelledError) else "Ctrl-C"
            self.journal.event(f"mission interrupted ({how}): returning home", kind="interrupted")
            await self._safe_end("interrupted", INTERRUPT_SAFE_END_TIMEOUT_S)
            self._close(STATUS_INTERRUPTED, "interrupted", t_wall)
            raise
        except UavlocError as exc:
            f.set_phase(ABORT)
            log.error("mission aborted: %s", exc)
            self.journal.event(f"mission aborted: {exc}", kind="abort", error=type(exc).__name__)
            await self._safe_end(str(exc))
            return self._close(STATUS_ABORTED, str(exc), t_wall)
        except Exception as exc:
            f.set_phase(ABORT)
            log.exception("mission aborted by an unexpected error")
            self.journal.event(f"mission aborted: unexpected {type(exc).__name__}: {exc}", kind="abort",
                               error=type(exc).__name__)
            await self._safe_end(str(exc))
            self._close(STATUS_ABORTED, str(exc), t_wall)
            raise
        return self._close(status, reason, t_wall)

    async def _safe_end(self, reason: str, timeout_s: float = SAFE_END_TIMEOUT_S) -> None:
        """Never leave the vehicle without a safe command: RTL when it may be airborne (trying
        for at most timeout_s wall seconds)."""
        if not self._connected or self._gated is None or self._rtl_sent or self._rtl_gave_up:
            return
        st = self.vehicle.state
        if st.armed is False and st.landed_state in ("ON_GROUND", "UNKNOWN"):
            return
        try:
            async with asyncio.timeout(timeout_s):
                sent = await self._send_rtl(reason, retry_s=timeout_s)
        except TimeoutError:
            sent = False
        if not sent:
            log.error("RTL could not be sent: the vehicle is left to its own failsafe")
            self.journal.event("RTL could not be sent: the vehicle is left to its own failsafe", kind="rtl_failed")

    def _replay_log(self) -> ReplayResult:
        """What `uavloc replay LOG` computes, from the log as written so far (the header holds the
        mission's noise model and solver settings)."""
        mlog = read_mission_log(self.journal.writer.path)  # flushed line by line
        if mlog.skipped_torn_line is not None:
            raise MissionLogError(f"{self.journal.writer.path}: a torn line ({mlog.skipped_torn_line})")
        return replay(mlog, ReplayOptions(history=False))

    def _close(self, status: str, reason: str, t_wall: float) -> MissionResult:
        est = self.flight.estimate
        keyframes = self.pipeline.keyframes
        replayed: ReplayResult | None = None
        if keyframes:
            # the final answer is the batch solution over every keyframe, as `uavloc replay`
            # computes it from the log: the same keyframes (one builder, mission.keyframes) under
            # replay's noise model and solver settings, the GPS error's τ estimated from the whole
            # log's telemetry when the mission leaves it unknown; the pipeline's keyframes under
            # the mission's noise model if the log cannot be read back
            try:
                replayed = self._replay_log()
                est = replayed.estimate
            except Exception as exc:  # also a bug in replay: fall back, never lose the result
                log.warning("final estimate from the pipeline's keyframes: the log could not be replayed: %s", exc)
                try:
                    est = self.estimator_setup().final(keyframes)
                except Exception as exc2:  # a bug must not cost the mission its log or its last estimate
                    log.exception("final batch estimate failed")
                    self.journal.event(f"final batch estimate failed: {type(exc2).__name__}: {exc2}",
                                       kind="estimator_error")
        if est is not None and self.journal.is_open:
            self.flight.estimate = est
            self.journal.estimate(self.origin, est, len(keyframes), self.flight.flown_m, final=True)
        self.journal.event(f"mission end: {status} ({reason})", kind="end", status=status, reason=reason)
        self.journal.close()
        self.result = MissionResult(
            result=self._result(status, reason, est, replayed), estimate=est, wall_s=time.monotonic() - t_wall,
            rtl_sent=self._rtl_sent, landed=self._landed, refusals=self._gated.refusals if self._gated else 0,
            events=list(self.journal.messages), loop_lag=self.loop_lag.summary(), pace=self.pace)
        return self.result

    def _result(self, status: str, reason: str, est: Estimate | None, replayed: ReplayResult | None) -> Result:
        """The mission's Result: from its closed log and the replay of it (mission.replay.result_of_log,
        as `uavloc replay` builds it; the final estimate and end records change no replayed number);
        when there is no replay (no range measured, or the log could not be replayed) or the closed
        log cannot be read back whole, from the flight's own counts and estimate."""
        writer = self.journal.writer
        if replayed is not None and writer.failed is None:
            try:
                closed = read_mission_log(writer.path)
                result = result_of_log(closed, replace(replayed, log=closed))
                if (result.status, result.reason) == (status, reason):
                    return result
                log.warning("the mission log does not end as the mission did: the result from the flight's counts")
            except UavlocError as exc:
                log.warning("the mission log could not be read back: the result from the flight's counts: %s", exc)
        c = self.flight.clock
        surveyed = c.survey_s > 0
        return build_result(
            status=status, reason=reason, user_ids=[u.id for u in self.users], estimate=est, origin=self.origin,
            truth_enu_m=self.truth_enu_m, flown_m=self.flight.flown_m, measurements=self.flight.measurements,
            keyframes=len(self.pipeline.keyframes), duration_s=self.now(),
            survey_s=c.survey_s if surveyed else None, hover_s=c.hover_s if surveyed else None,
            largest_gap_s=c.largest_gap_s if surveyed else None,
            log_path=self.log_path if self.origin is not None else None)


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
