"""The mission controller (DESIGN.md §1, §7): fly, measure every Δ, estimate, replan, stay safe.

States CONNECT → PREFLIGHT → TAKEOFF → SURVEY → RETURN → LANDED, and ABORT from anywhere. One
`asyncio.TaskGroup` owns the concurrent parts:

- telemetry: the vehicle's streams; each position fix goes into a :class:`TelemetryBuffer` (mission
  time, ENU from home) and, rate-limited, into the mission log;
- Δ-trigger: while a survey leg is flown, when the UAV has moved Δ since the last keyframe
  (`KeyframeSelector`), measure every user through the gNB (not while hovering to replan, where
  GPS noise alone would move the fix by Δ); the UAV position of a trigger is the telemetry interpolated to the mean
  time of its measurements (DESIGN.md §3) and is shared by the trigger's `rtt` records, which is
  how replay groups them back into the same keyframe;
- estimator worker: `OnlineEstimator.add_keyframe` in a thread (`asyncio.to_thread`), so the event
  loop never waits on numpy;
- safety monitor: battery, geofence, altitude band, vehicle link (lost → wait, then RTL), gNB
  (lost → keep flying without measurements for a while, then RTL), mission time limit;
- status: a progress line on stderr through `logging`.

The main flow (in the TaskGroup's body) asks the planner for a waypoint at each leg end, passes it
through the safety gate (:class:`GatedVehicle`: nothing reaches the vehicle that the gate did not
pass) and flies it until arrival within the acceptance radius or the leg timeout. The stop rule
(every user's 95 % ellipse within the target radius, or the budget spent) leads to RETURN. An
exception, a cancellation (Ctrl-C) or a safety condition ends in RTL and a flushed log.

Time: the log's `t` is mission seconds since start on the vehicle's clock (MAVLink boot time,
:class:`mission.telemetry.VehicleClock`), so logs of SITL at any speed factor and of real flights
are in vehicle seconds; before the vehicle's time is known (and with a vehicle that sends none) it
is `(monotonic − start) · time_scale` (time_scale = the simulator's speedup; 1 for real flights).
Request timeouts stay in wall seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from estimator.keyframes import KeyframeSelector
from estimator.noise import NoiseModel
from estimator.ranging import C_MPS
from estimator.slam import OnlineEstimator, solve_batch
from estimator.types import Estimate, Keyframe, SolverParams
from mission.gnb import GnbClient
from mission.log import MissionLogWriter
from mission.safety import BreachWatch, GatedVehicle, SafetyGate, SafetyLimits
from mission.telemetry import Odometer, TelemetryBuffer, VehicleClock, odometer_dead_band_m
from mission.vehicle import PositionFix, Vehicle
from planner.stop import targets_reached
from planner.types import Planner, PlanningState, PlanResult
from uavloc.errors import (
    EstimatorError,
    GnbError,
    GnbNoMeasurementError,
    GnbPreflightError,
    GnbProtocolError,
    GnbUnknownCommandError,
    MissionError,
    PlannerError,
    SafetyError,
    UavlocError,
    VehicleError,
)

log = logging.getLogger(__name__)

CONNECT, PREFLIGHT, TAKEOFF, SURVEY, RETURN, LANDED, ABORT = (
    "CONNECT", "PREFLIGHT", "TAKEOFF", "SURVEY", "RETURN", "LANDED", "ABORT")

#: MissionResult.status values
STATUS_TARGET = "target_reached"
STATUS_BUDGET = "budget_spent"
STATUS_NO_LEG = "no_feasible_leg"
STATUS_RETURNED = "returned"  # a safety condition ended the survey early
STATUS_ABORTED = "aborted"  # an error ended the mission (RTL sent when airborne)
STATUS_INTERRUPTED = "interrupted"  # cancelled / Ctrl-C (RTL sent when airborne)

#: PX4's default horizontal cruise speed (MPC_XY_CRUISE): what the vehicle flies when a speed
#: command was refused, so the leg timeouts follow it then
PX4_DEFAULT_CRUISE_MPS = 5.0

#: consecutive measurement rounds answered with nothing but protocol errors that count as a lost gNB
PROTOCOL_ERROR_STREAK = 3

#: wall seconds the safe end may spend getting RTL accepted after an error
SAFE_END_TIMEOUT_S = 60.0
#: ... and after Ctrl-C (the user waits; a second Ctrl-C exits at once, mission.runtime)
INTERRUPT_SAFE_END_TIMEOUT_S = 20.0


@dataclass(frozen=True)
class MissionUser:
    """A user to locate: id, RNTI and ground height `up_m` in the home ENU frame [m]."""

    id: str
    rnti: int
    up_m: float = 0.0


@dataclass(frozen=True)
class ControllerConfig:
    """Mission settings. Times marked (mission) are mission seconds; (wall) are real seconds.

    delta_m: keyframe spacing Δ; altitude_m: survey height above home; target_radius_m: stop rule;
    budget_m: survey metres; time_limit_s (mission); acceptance_m: arrival radius; speed_mps,
    climb_mps, descent_mps: vehicle speeds used for leg and landing timeouts.
    time_scale: mission seconds per wall second (simulator speedup).
    link_timeout_s (wall): no vehicle data for this long counts as a lost link;
    link_lost_wait_s (mission): wait this long for the link before returning home;
    gnb_lost_wait_s (mission): keep flying without measurements this long before returning home;
    gnb_timeout_s (wall): per measurement request; telemetry_log_hz (mission): telemetry records;
    status_interval_s (wall): progress lines; max_refusals: consecutive refused waypoints before
    returning home; alt_margin_m: tolerance of the altitude-band check while surveying;
    breach_confirm_fixes: consecutive fixes outside a position limit before returning home (one
    noisy fix near the fence is not a breach, mission.safety.BreachWatch);
    position_smooth_s (mission): the position a waypoint's leg is checked from is the mean of
    the fixes over this long (the vehicle hovers when a leg is planned);
    estimator_mode: "process" (estimator in a child process) or "thread" (see EstimatorWorker).
    """

    delta_m: float = 2.0
    altitude_m: float = 30.0
    target_radius_m: float = 2.0
    budget_m: float = 2000.0
    time_limit_s: float = 1200.0
    acceptance_m: float = 2.0
    speed_mps: float = 10.0
    climb_mps: float = 3.0
    descent_mps: float = 1.5
    time_scale: float = 1.0
    connect_timeout_s: float = 30.0
    ready_timeout_s: float = 60.0
    link_timeout_s: float = 3.0
    link_lost_wait_s: float = 10.0
    gnb_lost_wait_s: float = 20.0
    gnb_timeout_s: float = 2.0
    telemetry_log_hz: float = 5.0
    status_interval_s: float = 2.0
    max_refusals: int = 3
    alt_margin_m: float = 5.0
    breach_confirm_fixes: int = 3
    position_smooth_s: float = 1.0
    estimator_mode: str = "process"

    @classmethod
    def from_mission(cls, mission, **overrides) -> ControllerConfig:
        """From a :class:`mission.config.MissionConfig` (its flight, safety and gNB sections; the
        per-measurement timeout is `mission.gnb.measure_timeout_s()`); overrides: any field."""
        f, s = mission.flight, mission.safety
        kw = dict(delta_m=f.delta_m, altitude_m=f.altitude_m, target_radius_m=f.target_radius_m,
                  budget_m=f.budget_m, time_limit_s=f.time_limit_s, acceptance_m=f.acceptance_m,
                  speed_mps=f.cruise_speed_mps, climb_mps=f.climb_mps, descent_mps=f.descent_mps,
                  link_timeout_s=s.link_timeout_s, link_lost_wait_s=s.link_lost_wait_s,
                  gnb_lost_wait_s=s.gnb_lost_wait_s, max_refusals=s.max_refusals,
                  alt_margin_m=s.alt_margin_m, breach_confirm_fixes=s.breach_confirm_fixes,
                  gnb_timeout_s=mission.gnb.measure_timeout_s())
        kw.update(overrides)
        return cls(**kw)

    @classmethod
    def from_scenario(cls, sc, **overrides) -> ControllerConfig:
        """A simulation scenario's: `from_mission(sc.mission_config())`."""
        return cls.from_mission(sc.mission_config(), **overrides)


@dataclass
class MissionResult:
    """How a mission ended, and what it found.

    status: one of the STATUS_* values; reason: why; estimate: final (batch) estimate or None;
    origin: home (the log's ENU origin) or None if never known; truth_enu_m (K, 3) when known;
    flown_m: survey metres flown; measurements: rtt records logged; keyframes: keyframes used.
    """

    status: str
    reason: str
    user_ids: list[str]
    estimate: Estimate | None = None
    origin: Origin | None = None
    truth_enu_m: np.ndarray | None = None
    flown_m: float = 0.0
    measurements: int = 0
    keyframes: int = 0
    log_path: Path | None = None
    mission_s: float = 0.0
    wall_s: float = 0.0
    rtl_sent: bool = False
    landed: bool = False
    refusals: int = 0
    events: list[str] = field(default_factory=list)
    loop_lag: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """The mission ended normally and located every user (else the command exits non-zero)."""
        return self.status in (STATUS_TARGET, STATUS_BUDGET, STATUS_NO_LEG, STATUS_RETURNED) and not self.not_located()

    def not_located(self) -> list[str]:
        """Ids of the users without a position estimate, or with one a mirror position explains as
        well (ambiguous)."""
        est = self.estimate
        if est is None:
            return list(self.user_ids)
        return [u for k, u in enumerate(self.user_ids)
                if not np.all(np.isfinite(est.users_enu_m[k])) or bool(est.ambiguous[k])]

    def error_m(self) -> np.ndarray | None:
        """(K,) horizontal error of each user [m] when truth is known."""
        if self.estimate is None or self.truth_enu_m is None:
            return None
        return np.linalg.norm(self.estimate.users_enu_m[:, :2] - self.truth_enu_m[:, :2], axis=1)

    def to_document(self) -> dict:
        """The DESIGN.md §11 JSON document (plus `reason`)."""
        users: list[dict] = []
        if self.estimate is not None and self.origin is not None:
            from mission.replay import users_document

            users = users_document(self.estimate, self.origin, self.user_ids, self.error_m())
        else:
            users = [{"id": u, "lat_deg": None, "lon_deg": None, "alt_m": None, "enu_m": None,
                      "cov_en_m2": None} for u in self.user_ids]
        return {"status": self.status, "reason": self.reason, "users": users,
                "flown_m": round(self.flown_m, 3), "measurements": self.measurements}


class _Pulse:
    """Wake every waiter on the next `pulse()` (a new Event per generation)."""

    def __init__(self) -> None:
        self._event = asyncio.Event()

    def pulse(self) -> None:
        self._event.set()
        self._event = asyncio.Event()

    async def wait(self, timeout_s: float) -> bool:
        try:
            async with asyncio.timeout(timeout_s):
                await self._event.wait()
            return True
        except TimeoutError:
            return False


class LoopLagMonitor:
    """Measures event-loop lag: how late a `sleep(period)` wakes up [s]. Kept as a sample list."""

    def __init__(self, period_s: float = 0.01):
        self.period_s = period_s
        self.lags_s: list[float] = []

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            t = loop.time()
            await asyncio.sleep(self.period_s)
            self.lags_s.append(max(0.0, loop.time() - t - self.period_s))

    def summary(self) -> dict:
        """{"samples", "max_s", "p99_s", "median_s"} (zeros before the first sample)."""
        if not self.lags_s:
            return {"samples": 0, "max_s": 0.0, "p99_s": 0.0, "median_s": 0.0}
        a = np.asarray(self.lags_s)
        return {"samples": len(a), "max_s": float(a.max()), "p99_s": float(np.percentile(a, 99)),
                "median_s": float(np.median(a))}


#: the child process's estimator (EstimatorWorker in process mode)
_CHILD_ONLINE: OnlineEstimator | None = None


def _child_init(n_users: int, user_up_m: np.ndarray, noise: NoiseModel, params: SolverParams) -> None:
    global _CHILD_ONLINE
    _die_with_parent()
    _CHILD_ONLINE = OnlineEstimator(n_users, user_up_m, noise, params)


def _die_with_parent() -> None:
    """Linux: SIGTERM this process when its parent dies (a crashed or hard-exited uavloc must not
    leave the estimator child behind holding its stdout). Elsewhere a no-op."""
    import ctypes
    import signal
    import sys

    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
        if os.getppid() == 1:  # the parent is already gone
            os._exit(0)


def _child_ping() -> int:
    return os.getpid()


def _child_add(kf: Keyframe) -> Estimate:
    return _CHILD_ONLINE.add_keyframe(kf)


class EstimatorWorker:
    """Feeds keyframes from a queue to an online estimator that runs off the event loop.

    `OnlineEstimator.add_keyframe` is numpy work of milliseconds (up to a few hundred when it
    (re)initializes users). mode "process" (default) runs the estimator in a child process (spawn),
    so the event loop neither waits on it nor competes with it for the GIL; mode "thread" runs it
    through `asyncio.to_thread`. Keyframes are solved one at a time in arrival order.
    """

    def __init__(self, n_users: int, user_up_m: np.ndarray, noise: NoiseModel, params: SolverParams,
                 queue: asyncio.Queue | None = None, mode: str = "process"):
        if mode not in ("process", "thread"):
            raise MissionError(f"estimator worker mode must be 'process' or 'thread', got {mode!r}")
        self.args = (int(n_users), np.asarray(user_up_m, float), noise, params)
        self.mode = mode
        self.queue: asyncio.Queue[Keyframe] = queue if queue is not None else asyncio.Queue()
        self.solve_s: list[float] = []
        self.ready = asyncio.Event()

    async def run(self, on_estimate: Callable[[Estimate], None],
                  on_error: Callable[[EstimatorError], None] | None = None) -> None:
        """Until cancelled: take a keyframe, solve it off the loop, hand the estimate over.

        If the child process cannot start or dies (e.g. a caller's unguarded `__main__` under
        spawn), the worker falls back to thread mode and re-feeds the keyframes seen so far."""
        from concurrent.futures.process import BrokenProcessPool

        loop = asyncio.get_running_loop()
        pool = None
        fed: list[Keyframe] = []

        def thread_solver(history: list[Keyframe]):
            online = OnlineEstimator(*self.args)

            def replay_then_add(kf: Keyframe) -> Estimate:
                while history:
                    online.add_keyframe(history.pop(0))
                return online.add_keyframe(kf)

            return functools.partial(asyncio.to_thread, replay_then_add)

        if self.mode == "process":
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                       initializer=_child_init, initargs=self.args)
            solve = functools.partial(loop.run_in_executor, pool, _child_add)
        else:
            solve = thread_solver([])
        try:
            if pool is not None:
                try:
                    await loop.run_in_executor(pool, _child_ping)  # start the child now, not at the 1st keyframe
                except BrokenProcessPool:
                    log.warning("estimator child process did not start; solving in a thread instead")
                    pool.shutdown(wait=False, cancel_futures=True)
                    pool, solve, self.mode = None, thread_solver([]), "thread"
            self.ready.set()
            while True:
                kf = await self.queue.get()
                try:
                    t0 = time.perf_counter()
                    try:
                        est = await solve(kf)
                    except BrokenProcessPool:
                        log.warning("estimator child process died; solving in a thread from now on")
                        pool.shutdown(wait=False, cancel_futures=True)
                        pool, solve, self.mode = None, thread_solver(list(fed)), "thread"
                        est = await solve(kf)
                    fed.append(kf)
                    self.solve_s.append(time.perf_counter() - t0)
                except EstimatorError as exc:
                    if on_error is None:
                        raise
                    on_error(exc)
                    continue
                finally:
                    self.queue.task_done()
                on_estimate(est)
        finally:
            if pool is not None:
                # never block the loop on the child: it finishes its keyframe and exits by itself
                pool.shutdown(wait=False, cancel_futures=True)


class MissionController:
    """Runs one mission. See the module docstring.

    vehicle: a :class:`Vehicle` (connected by the controller); gnb: a connected :class:`GnbClient`;
    planner: a :class:`planner.types.Planner` whose constraints are in the home ENU frame;
    users: the users to locate; noise/params: the estimator's model and settings; limits: the
    safety gate's limits (home ENU frame); log_path: where the mission log goes;
    truth: simulation only: home Origin -> (K, 3) true user positions in the home ENU frame [m]
    (written as the `truth` record once home is known);
    header_config: the header's `config` section (scenario, planner, …).
    """

    def __init__(self, vehicle: Vehicle, gnb: GnbClient, planner: Planner | Callable[[Origin], Planner],
                 users: list[MissionUser], noise: NoiseModel,
                 limits: SafetyLimits | Callable[[Origin], SafetyLimits], config: ControllerConfig,
                 log_path: str | Path,
                 params: SolverParams | None = None, truth: Callable[[Origin], np.ndarray] | None = None,
                 header_config: dict | None = None, radio: dict | None = None):
        if not users:
            raise MissionError("a mission needs at least one user")
        self.vehicle = vehicle
        self.gnb = gnb
        self.planner = planner
        self.users = list(users)
        self.noise = noise
        self.config = config
        self.params = params or SolverParams(delta_m=config.delta_m)
        # a planner or limits given as a function of home are built once home is known (PREFLIGHT)
        self._planner_at = None if hasattr(planner, "plan") else planner
        self._limits_at = None if isinstance(limits, SafetyLimits) else limits
        self.gate: SafetyGate | None = None if self._limits_at is not None else SafetyGate(limits)
        self._truth = truth
        self.truth_enu_m: np.ndarray | None = None
        self.header_config = header_config or {}
        self.radio = radio or {}
        self.log_path = Path(log_path)
        self._writer = MissionLogWriter(self.log_path)
        self._pending_events: list[tuple[float, dict]] = []
        self.state = CONNECT
        self.origin: Origin | None = None
        self.estimate: Estimate | None = None
        self.keyframes: list[Keyframe] = []
        self.flown_m = 0.0
        self._odometer = Odometer(odometer_dead_band_m(noise.sigma_gps_m))
        self.measurements = 0
        self.event_messages: list[str] = []
        self._t0_mono = time.monotonic()
        self._clock = VehicleClock(self._t0_mono, config.time_scale)
        self._start_utc = datetime.now(UTC).isoformat(timespec="milliseconds")
        self._buffer = TelemetryBuffer(4096)
        self._fix_pulse: _Pulse | None = None
        self._last_tel_log_t = -math.inf
        self._kf_queue: asyncio.Queue[Keyframe] | None = None
        self._place_queue: asyncio.Queue[list] | None = None
        self._return_reason: str | None = None
        self._stop_status: tuple[str, str] | None = None
        self._link_lost_since: float | None = None
        self._gnb_down_since: float | None = None
        self._gnb_failures = 0
        self._gnb_problem: str | None = None  # why the gNB is lost, in its own words (status line)
        self._protocol_streak = 0  # consecutive measurement rounds with nothing but protocol errors
        self._rtl_sent = False
        self._landed = False
        self._gated: GatedVehicle | None = None
        self._connected = False
        self._user_misses = np.zeros(len(self.users), int)
        self._battery_start_pct: float | None = None
        self.loop_lag = LoopLagMonitor()
        self._on_leg = False  # flying a survey leg: the Δ-trigger is armed (not while hovering to plan)
        self.result: MissionResult | None = None  # set when the mission ends (also when cancelled)
        self._rtl_gave_up = False  # RTL retried for its whole time without being accepted
        self._leg_speed_mps = PX4_DEFAULT_CRUISE_MPS  # the speed the vehicle flies legs at (commanded or default)
        self._speed_refusals = 0

    # -- clock ----------------------------------------------------------------------------------

    def now(self) -> float:
        """Mission seconds since start (vehicle seconds once the vehicle's clock is known)."""
        return self._clock.mission_t(time.monotonic())

    def mission_t(self, t_mono_s: float) -> float:
        return self._clock.mission_t(t_mono_s)

    def wall(self, mission_s: float) -> float:
        """Mission seconds → wall seconds (at the vehicle clock's current rate)."""
        return mission_s / self._clock.rate

    # -- log ------------------------------------------------------------------------------------

    def _event(self, message: str, **fields: Any) -> None:
        """An `event` record (buffered until the header is written)."""
        t = self.now()
        rec = {"message": message, "state": self.state, **fields}
        self.event_messages.append(message)
        log.debug("event: %s", message)
        if self._writer._fh is None:
            self._pending_events.append((t, rec))
        else:
            self._writer.write("event", t, **rec)

    def _open_log(self) -> None:
        users = [{"id": u.id, "rnti": u.rnti, "ground_alt_m": self.origin.alt_m + u.up_m} for u in self.users]
        cfg = dict(self.header_config)
        cfg.setdefault("controller", asdict(self.config))
        cfg.setdefault("solver", asdict(self.params))
        self._writer.open()
        self._writer.write_header(self.origin, users, self.radio, noise=self.noise, config=cfg,
                                  start_utc=self._start_utc)
        for t, rec in self._pending_events:
            self._writer.write("event", t, **rec)
        self._pending_events.clear()
        if self._truth is not None:
            self.truth_enu_m = np.asarray(self._truth(self.origin), float).reshape(len(self.users), 3)
            lat, lon, alt = self.origin.enu_to_lla(self.truth_enu_m)
            self._writer.write("truth", self.now(), users=[
                {"id": u.id, "lat_deg": float(lat[k]), "lon_deg": float(lon[k]), "alt_m": float(alt[k])}
                for k, u in enumerate(self.users)])

    def _log_estimate(self, est: Estimate, final: bool = False) -> None:
        if self._writer._fh is None:
            return
        lat, lon, alt = self.origin.enu_to_lla(est.users_enu_m)
        users = []
        for k, u in enumerate(self.users):
            cov = est.cov_en_m2(k)
            if not (np.all(np.isfinite(est.users_enu_m[k])) and np.all(np.isfinite(cov))):
                continue
            users.append({"id": u.id, "lat_deg": float(lat[k]), "lon_deg": float(lon[k]),
                          "alt_m": float(alt[k]), "cov_en_m2": cov.tolist()})
        extra = {"final": True} if final else {}
        self._writer.write("estimate", self.now(), users=users, keyframes=len(self.keyframes), **extra)

    # -- state ----------------------------------------------------------------------------------

    def _set_state(self, state: str) -> None:
        if state != self.state:
            log.info("mission state %s -> %s", self.state, state)
            self.state = state

    def _pos_enu(self) -> np.ndarray | None:
        latest = self._buffer.latest()
        return None if latest is None else latest[1]

    def _pos_enu_smoothed(self) -> np.ndarray | None:
        """Mean of the fixes over the last config.position_smooth_s (mission), or None."""
        latest = self._buffer.latest()
        return None if latest is None else self._buffer.mean_since(latest[0] - self.config.position_smooth_s)

    def request_return(self, reason: str) -> None:
        """Ask the main flow to end the survey and return home (first reason wins)."""
        if self._return_reason is None:
            self._return_reason = reason
            log.warning("returning home: %s", reason)
            self._event(f"return requested: {reason}", kind="return")
            if self._fix_pulse is not None:
                self._fix_pulse.pulse()

    def _finish_survey(self, status: str, reason: str) -> None:
        """A normal end of the survey (stop rule); the main flow returns home."""
        if self._stop_status is None and self._return_reason is None:
            self._stop_status = (status, reason)
            self._event(f"survey done: {reason}", kind="stop")
            if self._fix_pulse is not None:
                self._fix_pulse.pulse()

    # -- telemetry ------------------------------------------------------------------------------

    def _on_fix(self, fix: PositionFix) -> None:
        if self.origin is None:
            return
        t = self.mission_t(fix.t_mono_s)
        pos = self.origin.lla_to_enu(fix.lat_deg, fix.lon_deg, fix.alt_amsl_m)
        self._buffer.append(t, pos)
        if t - self._last_tel_log_t >= 1.0 / self.config.telemetry_log_hz and self._writer._fh is not None:
            self._last_tel_log_t = t
            extra = {"vel_ned_mps": list(fix.vel_ned_mps)} if fix.vel_ned_mps is not None else {}
            self._writer.write("telemetry", t, lat_deg=fix.lat_deg, lon_deg=fix.lon_deg,
                               alt_m=fix.alt_amsl_m, **extra)
        if self._fix_pulse is not None:
            self._fix_pulse.pulse()

    async def _position_at(self, t_s: float) -> np.ndarray:
        """UAV position at mission time t_s: waits briefly for the fix after it, then interpolates."""
        deadline = time.monotonic() + 1.0
        while not self._buffer.covers(t_s) and time.monotonic() < deadline:
            await self._fix_pulse.wait(0.2)
        return self._buffer.at(t_s, max_extrapolate_s=0.5)

    # -- tasks ----------------------------------------------------------------------------------

    async def _trigger_task(self) -> None:
        selector = KeyframeSelector(self.config.delta_m)
        while True:
            pos = self._pos_enu()
            if (self._on_leg and not self._return_reason and not self._stop_status and pos is not None
                    and selector.accept(pos)):
                await self._measure_all()
                continue  # check the newest fix at once: fixes arrived while measuring
            await self._fix_pulse.wait(1.0)

    async def _measure_all(self) -> None:
        """One trigger: measure every user, log the rtt records, queue one keyframe."""
        samples = []
        gnb_failed: str | None = None
        protocol_errors: list[str] = []
        for k, u in enumerate(self.users):
            t_req = time.monotonic()
            try:
                async with asyncio.timeout(self.config.gnb_timeout_s):
                    s = await self.gnb.measure(u.rnti)
            except GnbUnknownCommandError as exc:
                # the measurement command is gone (module not loaded, gNB restarted without it)
                gnb_failed = " ".join(str(exc).split())
                break
            except GnbProtocolError as exc:
                self._user_misses[k] += 1
                protocol_errors.append(f"{u.id}: {' '.join(str(exc).split())}")
                log.debug("unreadable answer for %s: %s", u.id, exc)
                continue
            except GnbNoMeasurementError as exc:
                self._user_misses[k] += 1
                log.debug("no measurement for %s: %s", u.id, exc)
                continue
            except TimeoutError:
                gnb_failed = f"gNB did not answer within {self.config.gnb_timeout_s:g} s"
                break
            except GnbError as exc:
                gnb_failed = str(exc)
                break
            t_mono = s.t_mono_s if (s.t_mono_s and math.isfinite(s.t_mono_s)) else 0.5 * (t_req + time.monotonic())
            samples.append((k, s, t_mono))
        now = self.now()
        # answers nobody can read, trigger after trigger, are a lost gNB too
        self._protocol_streak = self._protocol_streak + 1 if protocol_errors and not samples else 0
        if gnb_failed is None and self._protocol_streak >= PROTOCOL_ERROR_STREAK:
            gnb_failed = (f"{self._protocol_streak} measurement rounds in a row answered with protocol errors, "
                          f"last: {protocol_errors[-1]}")
        if gnb_failed is not None:
            self._gnb_failures += 1
            self._gnb_problem = gnb_failed
            if self._gnb_down_since is None:
                self._gnb_down_since = now
                log.warning("gNB lost: %s", gnb_failed)
                self._event(f"gNB lost: {gnb_failed}", kind="gnb_lost")
        elif self._gnb_down_since is not None:
            self._event(f"gNB restored after {now - self._gnb_down_since:.1f} s", kind="gnb_restored")
            log.info("gNB restored")
            self._gnb_down_since = None
            self._gnb_problem = None
        if not samples:
            return
        # placing the trigger on the track waits for the next fix: hand it to the placer task so
        # the trigger is ready for the next Δ at once
        self._place_queue.put_nowait(samples)

    async def _placer_task(self) -> None:
        """Place each trigger at the telemetry interpolated to its mean measurement time, log its
        rtt records and queue its keyframe (in trigger order)."""
        while True:
            samples = await self._place_queue.get()
            try:
                await self._place(samples)
            finally:
                self._place_queue.task_done()

    async def _place(self, samples: list) -> None:
        t_meas = float(np.mean([self.mission_t(tm) for _, _, tm in samples]))
        try:
            pos = await self._position_at(t_meas)
        except MissionError as exc:
            self._event(f"measurements dropped: {exc}", kind="dropped")
            return
        lat, lon, alt = (float(x) for x in self.origin.enu_to_lla(pos))
        uav = {"lat_deg": lat, "lon_deg": lon, "alt_m": alt}
        for k, s, tm in samples:
            self._writer.write("rtt", self.mission_t(tm), user=self.users[k].id, uav=uav, **s.log_fields())
        self.measurements += len(samples)
        # the keyframe from the logged numbers, exactly as replay rebuilds it
        gps = self.origin.lla_to_enu(lat, lon, alt)
        kf = Keyframe(gps_enu_m=np.asarray(gps, float), user_idx=np.array([k for k, _, _ in samples]),
                      range_m=np.array([C_MPS * s.toa_s for _, s, _ in samples]),
                      t_s=self.mission_t(samples[0][2]))
        self.keyframes.append(kf)
        self._kf_queue.put_nowait(kf)

    async def _estimator_task(self) -> None:
        up = np.array([u.up_m for u in self.users])
        worker = EstimatorWorker(len(self.users), up, self.noise, self.params, self._kf_queue,
                                 mode=self.config.estimator_mode)

        def on_estimate(est: Estimate) -> None:
            self.estimate = est
            self._log_estimate(est)
            if self.state == SURVEY and targets_reached(est, self.config.target_radius_m):
                self._finish_survey(STATUS_TARGET, "target reached")

        def on_error(exc: EstimatorError) -> None:
            self._event(f"estimator: {exc}", kind="estimator_error")

        await worker.run(on_estimate, on_error)

    async def _safety_task(self) -> None:
        cfg = self.config
        st = self.vehicle.state
        breach = BreachWatch(self.gate, cfg.breach_confirm_fixes)
        while True:
            await asyncio.sleep(0.05)
            now = self.now()
            lost = (not st.connected) or st.age_s() > cfg.link_timeout_s
            if lost and self._link_lost_since is None:
                self._link_lost_since = now
                self._event("vehicle link lost", kind="link_lost")
            elif not lost and self._link_lost_since is not None:
                self._event(f"vehicle link restored after {now - self._link_lost_since:.1f} s",
                            kind="link_restored")
                self._link_lost_since = None
            if self.state not in (TAKEOFF, SURVEY):
                continue
            if self._link_lost_since is not None and now - self._link_lost_since > cfg.link_lost_wait_s:
                self.request_return(f"vehicle link lost for more than {cfg.link_lost_wait_s:g} s")
            reason = self.gate.return_reason(None, st.battery_pct)
            latest = None if lost else self._buffer.latest()
            if reason is None and latest is not None:
                reason = breach.update(latest[0], latest[1], check_altitude=self.state == SURVEY,
                                       alt_margin_m=cfg.alt_margin_m)
            if reason:
                self.request_return(reason)
            if self._gnb_down_since is not None and now - self._gnb_down_since > cfg.gnb_lost_wait_s:
                self.request_return(f"gNB lost for more than {cfg.gnb_lost_wait_s:g} s: {self._gnb_problem}")
            if now > cfg.time_limit_s:
                self.request_return(f"mission time limit {cfg.time_limit_s:g} s reached")

    async def _status_task(self) -> None:
        while True:
            await asyncio.sleep(self.config.status_interval_s)
            log.info("%s", self.status_line())

    def status_line(self) -> str:
        """State, metres flown, measurements and each user's estimate and 95 % bound."""
        parts = [f"{self.state:<9} t={self.now():6.1f} s  flown {self.flown_m:6.1f} m  {self.measurements} meas"]
        if self._gnb_down_since is not None:
            left = self.config.gnb_lost_wait_s - (self.now() - self._gnb_down_since)
            then = f"; home in {left:.0f} s" if self.state in (TAKEOFF, SURVEY) and left > 0 else ""
            parts.append(f"gNB LOST: {self._gnb_problem}{then}")
        est = self.estimate
        if est is not None:
            bound = est.error_bound_95_m()
            for k, u in enumerate(self.users):
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

    # -- vehicle helpers ------------------------------------------------------------------------

    async def _send_rtl(self, reason: str, retry_s: float = 60.0) -> bool:
        """Send RTL, retrying (e.g. while the link is down) for up to `retry_s` wall seconds;
        True when the vehicle accepted it."""
        t_end = time.monotonic() + retry_s
        attempt = 0
        while True:
            attempt += 1
            try:
                await self._gated.return_to_launch()
            except VehicleError as exc:
                if attempt == 1 or attempt % 10 == 0:
                    log.warning("RTL attempt %d failed: %s", attempt, exc)
                    self._event(f"RTL attempt {attempt} failed: {exc}", kind="rtl_failed")
                if time.monotonic() >= t_end:
                    self._rtl_gave_up = True
                    return False
                await asyncio.sleep(0.5)
                continue
            self._rtl_sent = True
            self._event(f"RTL: {reason}", kind="rtl", attempts=attempt)
            return True

    async def _wait_landed(self, timeout_s: float) -> bool:
        st = self.vehicle.state
        deadline = time.monotonic() + self.wall(timeout_s)
        while time.monotonic() < deadline:
            if st.landed_state == "ON_GROUND" and st.armed is False:
                return True
            await self._fix_pulse.wait(0.2)
        return False

    def _return_timeout_s(self) -> float:
        pos = self._pos_enu()
        dist = 0.0 if pos is None else float(np.hypot(pos[0], pos[1]))
        height = self.config.altitude_m if pos is None else max(float(pos[2]), 0.0)
        cfg = self.config
        # RTL flies at the vehicle's own return speed (PX4: MPC_XY_CRUISE unless changed)
        return 2.0 * (dist / min(self._leg_speed_mps, PX4_DEFAULT_CRUISE_MPS) + height / cfg.descent_mps) + 60.0

    # -- main flow ------------------------------------------------------------------------------

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
        except asyncio.CancelledError:
            self._set_state(ABORT)
            self._event("mission interrupted (cancelled): returning home", kind="interrupted")
            await self._safe_end("interrupted", INTERRUPT_SAFE_END_TIMEOUT_S)
            self._close(STATUS_INTERRUPTED, "interrupted", t_wall)
            raise
        except KeyboardInterrupt:
            self._set_state(ABORT)
            self._event("mission interrupted (Ctrl-C): returning home", kind="interrupted")
            await self._safe_end("interrupted", INTERRUPT_SAFE_END_TIMEOUT_S)
            self._close(STATUS_INTERRUPTED, "interrupted", t_wall)
            raise
        except UavlocError as exc:
            self._set_state(ABORT)
            log.error("mission aborted: %s", exc)
            self._event(f"mission aborted: {exc}", kind="abort", error=type(exc).__name__)
            await self._safe_end(str(exc))
            return self._close(STATUS_ABORTED, str(exc), t_wall)
        except Exception as exc:
            self._set_state(ABORT)
            log.exception("mission aborted by an unexpected error")
            self._event(f"mission aborted: unexpected {type(exc).__name__}: {exc}", kind="abort",
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
            self._event("RTL could not be sent: the vehicle is left to its own failsafe", kind="rtl_failed")

    def _close(self, status: str, reason: str, t_wall: float) -> MissionResult:
        est = self.estimate
        if self.keyframes:
            # the final answer is the batch solution over every keyframe (what replay computes)
            try:
                est = self._final_estimate_sync()
            except EstimatorError as exc:
                self._event(f"final batch estimate failed: {exc}", kind="estimator_error")
        if est is not None and self._writer._fh is not None:
            self.estimate = est
            self._log_estimate(est, final=True)
        self._event(f"mission end: {status} ({reason})", kind="end", status=status)
        self._writer.close()
        self.result = MissionResult(
            status=status, reason=reason, user_ids=[u.id for u in self.users], estimate=est,
            origin=self.origin, truth_enu_m=self.truth_enu_m, flown_m=self.flown_m,
            measurements=self.measurements, keyframes=len(self.keyframes),
            log_path=self.log_path if self.origin is not None else None, mission_s=self.now(),
            wall_s=time.monotonic() - t_wall, rtl_sent=self._rtl_sent, landed=self._landed,
            refusals=self._gated.refusals if self._gated else 0, events=list(self.event_messages),
            loop_lag=self.loop_lag.summary())
        return self.result

    def _final_estimate_sync(self) -> Estimate:
        up = np.array([u.up_m for u in self.users])
        return solve_batch(self.keyframes, len(self.users), up, self.noise, self.params)

    async def _flow(self, tg: asyncio.TaskGroup) -> tuple[str, str]:
        cfg = self.config
        self._fix_pulse = _Pulse()
        self._kf_queue = asyncio.Queue()
        self._place_queue = asyncio.Queue()
        background: list[asyncio.Task] = []

        # CONNECT
        self._set_state(CONNECT)
        await self.vehicle.connect(cfg.connect_timeout_s)
        self._connected = True
        background.append(tg.create_task(self.vehicle.run_telemetry(self._on_fix, self._clock.update),
                                         name="telemetry"))
        # PREFLIGHT: global position and home ok; home is the ENU origin
        self._set_state(PREFLIGHT)
        home = await self.vehicle.wait_ready(cfg.ready_timeout_s)
        self.origin = Origin(home.lat_deg, home.lon_deg, home.alt_amsl_m)
        if self._planner_at is not None:
            self.planner = self._planner_at(self.origin)
        if self._limits_at is not None:
            self.gate = SafetyGate(self._limits_at(self.origin))
        self._gated = GatedVehicle(self.vehicle, self.gate, self.origin, self._event, self._pos_enu_smoothed)
        self._open_log()
        self._event(f"home {home.lat_deg:.7f}, {home.lon_deg:.7f}, {home.alt_amsl_m:.1f} m AMSL", kind="home")
        await self._preflight_gnb()
        for coro, name in ((self._estimator_task(), "estimator"), (self._trigger_task(), "trigger"),
                           (self._placer_task(), "placer"),
                           (self._safety_task(), "safety"), (self._status_task(), "status"),
                           (self.loop_lag.run(), "loop-lag")):
            background.append(tg.create_task(coro, name=name))
        try:
            await self._takeoff()
            if self._return_reason is None:
                self._set_state(SURVEY)
                await self._survey()
            self._set_state(RETURN)
            if not await self._send_rtl(self._return_reason or (self._stop_status or ("", "survey done"))[1]):
                raise VehicleError("the vehicle did not accept RTL")
            self._landed = await self._wait_landed(self._return_timeout_s())
            if not self._landed:
                self._event("landing not confirmed before the timeout", kind="landing_timeout")
            else:
                self._event("landed and disarmed", kind="landed")
            self._set_state(LANDED)
            # let the estimator finish the last keyframes before the final batch solve
            await self._drain(30.0)
        finally:
            for task in background:
                task.cancel()
        if self._return_reason is not None:
            return STATUS_RETURNED, self._return_reason
        if self._stop_status is not None:
            return self._stop_status
        return STATUS_RETURNED, "survey ended"

    async def _preflight_gnb(self) -> None:
        """No take-off unless every configured user is among the gNB's UEs and answers one
        measurement (passive stock mode: is among them; its random accesses come when they come).
        The event and the error say which RNTIs the gNB has and what it answered."""
        from mission.probe import probe_gnb

        rntis = [u.rnti for u in self.users]
        passive = getattr(getattr(self.gnb, "config", None), "stock_mode", None) == "passive" and (
            getattr(self.gnb.config, "mode", None) == "stock")
        try:
            async with asyncio.timeout(self.config.gnb_timeout_s * (2 + len(rntis))):
                probe = await probe_gnb(self.gnb, rntis=rntis, count=1)
        except TimeoutError as exc:
            raise GnbPreflightError(f"not taking off: the gNB did not finish the preflight probe within "
                                    f"{self.config.gnb_timeout_s * (2 + len(rntis)):g} s") from exc
        have = probe.gnb_rntis or []
        ok = probe.ok or (passive and probe.gnb_rntis is not None and all(r in have for r in rntis))
        self._event(probe.message(), kind="preflight_gnb", ok=ok, rntis=[f"{r:04x}" for r in have],
                    probe=probe.to_dict())
        if not ok:
            raise GnbPreflightError(f"not taking off: {probe.message()}")

    async def _takeoff(self) -> None:
        cfg = self.config
        self._set_state(TAKEOFF)
        await self._gated.arm()
        self._event("armed", kind="arm")
        await self._gated.takeoff(cfg.altitude_m)
        self._event(f"takeoff to {cfg.altitude_m:g} m above home", kind="takeoff")
        deadline = time.monotonic() + self.wall(2.0 * cfg.altitude_m / cfg.climb_mps + 30.0)
        while self._return_reason is None:
            pos = self._pos_enu()
            if pos is not None and pos[2] >= cfg.altitude_m - max(1.5, cfg.acceptance_m):
                return
            if time.monotonic() > deadline:
                raise VehicleError(f"takeoff to {cfg.altitude_m:g} m not reached in time (at "
                                   f"{'?' if pos is None else f'{pos[2]:.1f}'} m)")
            await self._fix_pulse.wait(0.2)

    def _energy_remaining_m(self) -> float:
        """Metres the battery still allows (down to the RTL threshold), from the drain so far."""
        st = self.vehicle.state
        if st.battery_pct is None or self._battery_start_pct is None or self.flown_m < 50.0:
            return math.inf
        used = self._battery_start_pct - st.battery_pct
        if used < 1.0:
            return math.inf
        per_pct = self.flown_m / used
        return max(0.0, (st.battery_pct - self.gate.limits.battery_rtl_pct) * per_pct)

    async def _drain(self, timeout_s: float) -> None:
        """Wait until every trigger so far is placed and solved (bounded)."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                await self._place_queue.join()
                await self._kf_queue.join()

    async def _plan(self, pos: np.ndarray) -> PlanResult:
        # plan with the estimate of every keyframe measured so far
        await self._drain(10.0)
        state = PlanningState(uav_enu_m=pos, estimate=self.estimate, flown_m=self.flown_m,
                              energy_remaining_m=self._energy_remaining_m())
        return await asyncio.to_thread(self.planner.plan, state)

    async def _survey(self) -> None:
        cfg = self.config
        self._battery_start_pct = self.vehicle.state.battery_pct
        refusals = 0
        leg = 0
        while self._return_reason is None and self._stop_status is None:
            pos = self._pos_enu()
            try:
                plan = await self._plan(pos)
            except PlannerError as exc:
                self.request_return(f"planner failed: {exc}")
                break
            if plan.done:
                status = {"target reached": STATUS_TARGET, "budget spent": STATUS_BUDGET}.get(
                    plan.reason, STATUS_NO_LEG)
                self._finish_survey(status, plan.reason or "planner done")
                break
            if self._return_reason is not None or self._stop_status is not None:
                break
            wp = np.asarray(plan.waypoint_enu_m, float)
            lat, lon, alt = (float(x) for x in self.origin.enu_to_lla(wp))
            leg += 1
            self._writer.write("waypoint", self.now(), leg=leg, lat_deg=lat, lon_deg=lon, alt_m=alt,
                               enu_m=wp.tolist(), planner=getattr(self.planner, "name", "?"),
                               status=plan.status, objective=plan.objective if math.isfinite(plan.objective)
                               else None, solve_time_s=plan.solve_time_s)
            await self._command_speed()
            try:
                await self._gated.goto_enu(wp)
            except SafetyError:
                refusals += 1
                if refusals >= cfg.max_refusals:
                    self.request_return(f"{refusals} waypoints in a row refused by the safety gate")
                continue
            except VehicleError as exc:
                # a lost link or a refusal: the safety monitor decides about the link; here wait for
                # it and replan from wherever the vehicle is then
                refusals += 1
                self._event(f"goto failed: {exc}", kind="goto_failed")
                if getattr(exc, "result", None) == "UNKNOWN":
                    # MAVSDK 4.1's answer to a MAV_RESULT it does not know (PX4's 9 to a reposition):
                    # it stops delivering telemetry and may crash on later calls, so send nothing but RTL
                    self.request_return(f"the vehicle library answered UNKNOWN: {exc}")
                elif refusals >= cfg.max_refusals:
                    self.request_return(f"{refusals} gotos in a row failed: {exc}")
                await self._wait_link()
                continue
            refusals = 0
            await self._fly_leg(pos, wp)
        if self._budget_spent():
            self._finish_survey(STATUS_BUDGET, "budget spent")

    async def _command_speed(self) -> None:
        """Command the mission's cruise speed before every leg (PX4 keeps it over repositions, but a
        mode change resets it); the leg timeouts follow what the vehicle then flies."""
        cfg = self.config
        try:
            await self.vehicle.set_speed(cfg.speed_mps)
        except VehicleError as exc:
            self._speed_refusals += 1
            self._leg_speed_mps = min(cfg.speed_mps, PX4_DEFAULT_CRUISE_MPS)
            if self._speed_refusals == 1:
                self._event(f"speed {cfg.speed_mps:g} m/s not accepted ({exc}): legs timed for "
                            f"{self._leg_speed_mps:g} m/s", kind="speed_refused")
            return
        if self._leg_speed_mps != cfg.speed_mps:
            self._event(f"cruise speed {cfg.speed_mps:g} m/s commanded", kind="speed", speed_mps=cfg.speed_mps)
        self._leg_speed_mps = cfg.speed_mps

    async def _wait_link(self) -> None:
        """While the vehicle link is lost (and no return is requested), wait."""
        while (self._link_lost_since is not None and self._return_reason is None
               and self._stop_status is None):
            await asyncio.sleep(0.05)

    def _budget_spent(self) -> bool:
        return self.flown_m >= self.config.budget_m

    async def _fly_leg(self, start: np.ndarray, wp: np.ndarray) -> None:
        """Wait for arrival within the acceptance radius, a stop/return request, or the leg timeout;
        the Δ-trigger measures while the leg is flown."""
        self._on_leg = True
        try:
            await self._fly_leg_until_done(start, wp)
        finally:
            self._on_leg = False

    async def _fly_leg_until_done(self, start: np.ndarray, wp: np.ndarray) -> None:
        cfg = self.config
        dist = float(np.linalg.norm(wp - start))
        deadline = time.monotonic() + self.wall(2.0 * dist / self._leg_speed_mps + 20.0)
        # metres flown: an odometer whose dead band (max(5 m, 8 σ_gps)) GPS noise does not cross
        self._odometer.start(start)
        while True:
            pos = self._pos_enu()
            self.flown_m = self._odometer.update(pos)
            if np.linalg.norm(pos - wp) <= cfg.acceptance_m:
                self.flown_m = self._odometer.finish(pos)
                return
            if self._return_reason is not None or self._stop_status is not None:
                return
            if self._budget_spent():
                self._finish_survey(STATUS_BUDGET, "budget spent")
                return
            if time.monotonic() > deadline:
                self._event(f"leg to ({wp[0]:.1f}, {wp[1]:.1f}, {wp[2]:.1f}) m timed out", kind="leg_timeout")
                return
            await self._fix_pulse.wait(0.2)


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


# ---------------------------------------------------------------------------------------------
# building a controller from a scenario file


def resolve_planner_name(name: str) -> str:
    """The planner to use: `name`, except "casadi" falls back to "lawnmower" when CasADi's planner
    is not available."""
    from planner import planner_names

    names = planner_names()
    if name == "casadi" and name not in names:
        log.warning("the casadi planner is not available; planning with the lawnmower baseline")
        return "lawnmower"
    if name not in names:
        raise PlannerError(f"unknown planner {name!r}; choose one of {', '.join(names)}")
    return name


def controller_from_mission(mission, vehicle: Vehicle, gnb: GnbClient, log_path: str | Path, *,
                            planner: str | None = None, seed: int = 0, time_scale: float = 1.0,
                            truth: Callable[[Origin], np.ndarray] | None = None,
                            header_config: dict | None = None, params: SolverParams | None = None,
                            constraints: Callable[[Origin], Any] | None = None,
                            **overrides: Any) -> MissionController:
    """A :class:`MissionController` flying a :class:`mission.config.MissionConfig` (a mission file).

    planner: planner name (default: the mission's `flight.planner`); seed: planner seed;
    time_scale: simulator speedup; truth: simulation only (see MissionController); constraints:
    home -> PlanningConstraints (default `mission.planning_constraints(home)`); overrides:
    ControllerConfig fields. Geodetic polygons of the mission file become home-ENU once the
    vehicle's home is known (the planner and the safety limits are built then).
    """
    from planner import make_planner

    name = resolve_planner_name(planner or mission.flight.planner)
    noise = mission.noise_model()
    make_constraints = constraints or mission.planning_constraints

    def planner_at(home: Origin) -> Planner:
        return make_planner(name, make_constraints(home), noise, rng_seed=seed)

    def limits_at(home: Origin) -> SafetyLimits:
        return SafetyLimits.from_mission(mission, home)

    g = mission.geofence
    if not (g.polygon_lat_lon_deg or g.no_fly_lat_lon_deg):
        # ENU polygons do not depend on home: build now (a caller may wrap the planner before run)
        here = Origin(0.0, 0.0, 0.0)
        planner_obj, limits = planner_at(here), limits_at(here)
    else:
        planner_obj, limits = planner_at, limits_at
    config = ControllerConfig.from_mission(mission, time_scale=time_scale, **overrides)
    users = [MissionUser(u.id, u.rnti, u.ground_height_m) for u in mission.users]
    cfg = {"mission": mission.name, "planner": name, "seed": seed, **(header_config or {})}
    radio = {"mu": mission.gnb.mu, "fs_hz": mission.gnb.fs_hz}
    if params is None:
        params = SolverParams(delta_m=mission.flight.delta_m, estimate_bias=mission.noise.estimate_bias,
                              bias_prior_sigma_m=mission.noise.bias_prior_sigma_m)
    return MissionController(vehicle, gnb, planner_obj, users, noise, limits, config, log_path,
                             params=params, truth=truth, header_config=cfg, radio=radio)


def controller_from_scenario(scenario, vehicle: Vehicle, gnb: GnbClient, log_path: str | Path, *,
                             planner: str | None = None, seed: int | None = None, time_scale: float = 1.0,
                             truth: Callable[[Origin], np.ndarray] | None = None,
                             header_config: dict | None = None, params: SolverParams | None = None,
                             **overrides: Any) -> MissionController:
    """A :class:`MissionController` for a simulation scenario: its mission
    (`scenario.mission_config()`) flown by :func:`controller_from_mission`, with the planning
    constraints that also keep clear of the scenario's buildings. seed: default the scenario's."""
    from planner import PlanningConstraints

    return controller_from_mission(
        scenario.mission_config(), vehicle, gnb, log_path, planner=planner,
        seed=scenario.seed if seed is None else seed, time_scale=time_scale, truth=truth,
        header_config={"scenario": scenario.name, **(header_config or {})}, params=params,
        constraints=lambda home: PlanningConstraints.from_scenario(scenario), **overrides)
