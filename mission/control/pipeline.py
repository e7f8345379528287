"""The measurement pipeline (docs/design.md §3, §7): Δ-trigger → placer → keyframe queue.

- the **trigger** (:meth:`MeasurementPipeline.run_trigger`): while a survey leg is flown, when the
  UAV has moved Δ since the last keyframe (`KeyframeSelector`), or MAX_RANGE_GAP_S mission seconds
  have passed since the last round (a turn: braking to a leg's end and accelerating into the next
  one moves less than Δ for seconds), measure the users through the gNB (not while hovering to
  replan, where GPS noise alone would move the fix by Δ) and put the round on the place queue.
  A round ends when every user is measured or when the UAV has moved
  Δ since it began, whichever comes first; the next round goes on with the next user (in turn),
  so many users share the gNB's answers without stretching the keyframe spacing (one position
  per round, within Δ of every measurement in it). The first round cut short logs how many users
  the gNB served in that Δ (event `gnb_rounds`; the spacing achieved is measured over the survey,
  `survey_time`); a round that fails for the gNB as a whole (no answer, an unknown
  command, or PROTOCOL_ERROR_STREAK rounds of nothing but unreadable answers) marks the gNB lost
  in the :class:`FlightState`, in the gNB's own words;
- the **placer** (:meth:`MeasurementPipeline.run_placer`): places each round at the telemetry
  interpolated to the mean time of its measurements, logs its `rtt` records (one UAV position per
  round: how replay groups them back into the same keyframe) and puts its keyframe on the
  keyframe queue, in trigger order. Placing waits for the next fix, so the trigger is ready for
  the next Δ at once;
- the **keyframe** is built from the round's `rtt` records as logged by the one builder replay
  uses too (mission.keyframes.build_keyframe), with the displacement from the previous keyframe
  integrated from the telemetry velocity *as logged* (the pipeline listens to the mission log)
  under the header's noise model: the keyframes replay rebuilds from the log, bit for bit. Placing
  waits briefly for the logged velocity record after the round; without one (or without velocity)
  the keyframe has no motion factor.

The pipeline owns its place queue; the estimator worker reads `keyframes_out`, which in a fleet
(docs/fleet.md) every vehicle's pipeline fills, each keyframe naming its vehicle. A fleet's gNB
serves the users attached to its cell: a round asks it for the users it served last and those
no vehicle's gNB has (`serving`), and a user its gNB stops answering for is nobody's again, for
every gNB to try.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
import time
from collections.abc import Callable

import numpy as np

from estimator.geodesy import Origin
from estimator.keyframes import KeyframeSelector
from estimator.motion import MAX_VEL_GAP_S
from estimator.noise import NoiseModel
from estimator.types import Keyframe
from mission.control.config import MissionUser
from mission.control.state import FlightState
from mission.control.timing import judge_range_timing, speed_around_mps
from mission.gnb import GnbClient
from mission.keyframes import TriggerRecords, VelocityRecords, build_keyframe, velocity_covers
from mission.log import MissionLogWriter
from mission.vehicle.telemetry import TelemetryBuffer
from uavloc.errors import GnbError, GnbNoMeasurementError, GnbProtocolError, GnbUnknownCommandError, MissionError

log = logging.getLogger(__name__)

#: consecutive measurement rounds answered with nothing but protocol errors that count as a lost gNB
PROTOCOL_ERROR_STREAK = 3
#: how long placing waits (wall) at most for the logged velocity record after a round [s] (the
#: record is due within 1/telemetry_log_hz of mission time; the bound only matters when telemetry stops)
VELOCITY_WAIT_S = 5.0
#: on a leg, a round at least this often [mission s] however little the UAV moved: a reversal at a
#: leg's end moved less than Δ for 3.5 s in a `paper` survey, a gap without ranges. Longer than
#: replay's GROUP_WINDOW_S (1 s), so that replay never merges two such rounds into one keyframe
MAX_RANGE_GAP_S = 1.5
#: logged velocity records kept for judging a range's timing (at 5 Hz: 13 minutes)
SPEED_HISTORY = 4096
#: a `range_timing_dropped` event for the first range dropped and then for every this many
TIMING_EVENT_EVERY = 50
#: the gNB clock offset is logged again when it moved by more than this [s]
OFFSET_LOG_STEP_S = 0.05


class MeasurementPipeline:
    """See the module docstring.

    gnb, users: whom to measure; delta_m: keyframe spacing; gnb_timeout_s: bound of one measurement
    (wall) [s]; flight: the shared state; buffer: the telemetry (mission time, ENU); origin: () ->
    home; writer: the mission log; now / mission_t: mission seconds now / of a monotonic time.
    In a fleet: vehicle: this pipeline's vehicle (Keyframe.vehicle); tag: the fields naming it in
    its records; keyframes_out / keyframes: the mission's queue and list, shared by the vehicles;
    serving: (K,) the vehicle whose gNB last measured each user (−1: none), shared.
    """

    def __init__(self, gnb: GnbClient, users: list[MissionUser], delta_m: float, gnb_timeout_s: float,
                 flight: FlightState, buffer: TelemetryBuffer, origin: Callable[[], Origin | None],
                 writer: MissionLogWriter, now: Callable[[], float], mission_t: Callable[[float], float],
                 *, vehicle: int = 0, tag: dict | None = None, keyframes_out: asyncio.Queue | None = None,
                 keyframes: list | None = None, serving: np.ndarray | None = None):
        self.gnb, self.users = gnb, users
        self.delta_m, self.gnb_timeout_s = delta_m, gnb_timeout_s
        self.flight, self.buffer, self.origin, self.writer = flight, buffer, origin, writer
        self.now, self.mission_t = now, mission_t
        self.vehicle = int(vehicle)
        self.tag = dict(tag or {})
        self.place_queue: asyncio.Queue[list] = asyncio.Queue()
        self.keyframes_out: asyncio.Queue[Keyframe] = asyncio.Queue() if keyframes_out is None else keyframes_out
        self.keyframes: list[Keyframe] = [] if keyframes is None else keyframes
        self.serving = np.full(len(users), -1, int) if serving is None else serving
        self.user_misses = np.zeros(len(users), int)
        #: the survey is over (release_users): this vehicle's gNB claims no user any more
        self.released = False
        self.protocol_streak = 0
        self._next_user = 0  # whom the next round measures first (rounds take the users in turn)
        self._rounds_reported = False
        # logged telemetry velocity (mission t [s], ENU [m/s]) since shortly before the last keyframe,
        # the header's noise model, and the last keyframe's position time
        self._vel_t: list[float] = []
        self._vel_enu: list[tuple[float, float, float]] = []
        #: (mission t [s], speed [m/s]) of the logged velocity, the last SPEED_HISTORY records (the
        #: velocity lists above are trimmed to the keyframes' needs; a range's interval may be longer)
        self._speed_hist: collections.deque[tuple[float, float]] = collections.deque(maxlen=SPEED_HISTORY)
        self._noise = NoiseModel()
        self._last_pos_t: float | None = None
        self._tel_last_t = -np.inf  # the last telemetry record's t, with or without velocity
        self._user_index = {u.id: k for k, u in enumerate(users)}
        #: ranges dropped as timed too loosely for where they would be placed (mission.control.timing)
        self.timing_dropped = 0
        #: stamped ranges the gNB refused for an unbounded clock offset, and the offset last logged [s]
        self.clock_refused = 0
        self._offset_logged: float | None = None
        writer.subscribe(self._on_record)

    # -- the log, as written --------------------------------------------------------------------

    def _on_record(self, rec: dict) -> None:
        """Keep the velocity of each telemetry record as logged, and the header's noise model."""
        kind = rec.get("type")
        if kind == "telemetry" and rec.get("vehicle", 0) == self.vehicle:
            self._tel_last_t = float(rec["t"])
            v = rec.get("vel_ned_mps")
            if v is not None:
                self._vel_t.append(float(rec["t"]))
                self._vel_enu.append((float(v[1]), float(v[0]), -float(v[2])))
                self._speed_hist.append((float(rec["t"]), float(np.linalg.norm(np.asarray(v, float)))))
        elif kind == "header" and isinstance(rec.get("noise"), dict):
            self._noise = NoiseModel.from_log_dict(rec["noise"])

    def _velocity(self) -> VelocityRecords:
        return VelocityRecords(np.asarray(self._vel_t, float), np.asarray(self._vel_enu, float).reshape(-1, 3))

    async def _velocity_covers(self, t_s: float) -> bool:
        """Wait for a logged velocity record strictly after t_s (mission.keyframes: then the records
        at hand give the displacement the whole log gives). False at once without velocity, and as
        soon as the log shows the gap replay would refuse (a telemetry record MAX_VEL_GAP_S after the
        last velocity record, none after t_s); at most VELOCITY_WAIT_S wall."""
        deadline = time.monotonic() + VELOCITY_WAIT_S
        while not velocity_covers(self._velocity(), t_s):
            if (not self._vel_t or self._tel_last_t > self._vel_t[-1] + MAX_VEL_GAP_S
                    or time.monotonic() >= deadline):
                return False
            await self.flight.wake.wait(0.05)
        return True

    def _forget_velocity_before(self, t_s: float) -> None:
        """Drop velocity records no longer needed: those before the last one at or before t_s − MAX_VEL_GAP_S."""
        i = int(np.searchsorted(np.asarray(self._vel_t), t_s - MAX_VEL_GAP_S, side="right")) - 1
        if i > 0:
            del self._vel_t[:i]
            del self._vel_enu[:i]

    # -- trigger --------------------------------------------------------------------------------

    async def run_trigger(self) -> None:
        f = self.flight
        selector = KeyframeSelector(self.delta_m)
        last_round_t = -float("inf")
        while True:
            latest = self.buffer.latest()
            now = self.now()
            if f.on_leg and not f.ending and latest is not None and (
                    selector.accept(latest[1], force=now - last_round_t >= MAX_RANGE_GAP_S)):
                last_round_t = now
                await self.measure_round()
                continue  # check the newest fix at once: fixes arrived while measuring
            await f.wake.wait(1.0)

    def release_users(self) -> None:
        """The survey is over: the users this vehicle's gNB served are nobody's now, for the
        vehicles still surveying to plan for and every gNB to try (its cell may still serve them
        until it is out of reach); a round still under way claims none of them back."""
        self.released = True
        self.serving[self.serving == self.vehicle] = -1

    def _moved_since_m(self, start: tuple[float, np.ndarray] | None) -> float:
        """How far [m] the UAV's newest fix is from `start` (buffer.latest() when the round began)."""
        latest = self.buffer.latest()
        if start is None or latest is None:
            return 0.0
        return float(np.linalg.norm(latest[1] - start[1]))

    async def measure_round(self) -> None:
        """One trigger: measure the users in turn, from the one after the last round's, until all
        are measured or the UAV has moved Δ; queue the round for placing."""
        samples = []
        gnb_failed: str | None = None
        protocol_errors: list[str] = []
        n_users = len(self.users)
        start = self.buffer.latest()
        first, tried = self._next_user, 0
        for k in [(first + i) % n_users for i in range(n_users)]:
            if self.flight.ending or self.released:
                break  # the survey is over: its users are for the vehicles still surveying
            if self.serving[k] not in (-1, self.vehicle):
                continue  # another vehicle's gNB serves this user
            if tried and self._moved_since_m(start) >= self.delta_m:
                self._report_rounds(tried, start)
                break
            u = self.users[k]
            self._next_user = k  # a failing gNB: this user is measured first next time
            tried += 1
            t_req = time.monotonic()
            try:
                async with asyncio.timeout(self.gnb_timeout_s):
                    s = await self.gnb.measure(u.rnti)
            except GnbUnknownCommandError as exc:
                # the measurement command is gone (module not loaded, gNB restarted without it)
                gnb_failed = " ".join(str(exc).split())
                break
            except GnbProtocolError as exc:
                self.user_misses[k] += 1
                protocol_errors.append(f"{u.id}: {' '.join(str(exc).split())}")
                log.debug("unreadable answer for %s: %s", u.id, exc)
                continue
            except GnbNoMeasurementError as exc:
                self.user_misses[k] += 1
                log.debug("no measurement for %s: %s", u.id, exc)
                self._note_trace_orders()
                if self.serving[k] == self.vehicle:
                    self.serving[k] = -1  # not (or no longer) on this cell: every gNB may try it
                continue
            except TimeoutError:
                gnb_failed = f"gNB did not answer within {self.gnb_timeout_s:g} s"
                break
            except GnbError as exc:
                gnb_failed = str(exc)
                break
            finally:
                if gnb_failed is None:
                    self._next_user = (k + 1) % n_users
            if s.t_mono_s and math.isfinite(s.t_mono_s):
                t_mono, t_unc = s.t_mono_s, float(getattr(s, "t_unc_s", 0.0))
            else:  # a client without a time: somewhere between asking and being answered
                t_end = time.monotonic()
                t_mono, t_unc = 0.5 * (t_req + t_end), 0.5 * (t_end - t_req)
            samples.append((k, s, t_mono, t_unc))
            # an answer that arrives after the survey ended claims nobody: its users were released
            # (release_users), and a claim now would keep every other vehicle's gNB from asking for
            # them for the rest of the mission
            if not (self.flight.ending or self.released):
                self.serving[k] = self.vehicle
            self._note_trace_orders()
        now = self.now()
        # answers nobody can read, round after round, are a lost gNB too
        self.protocol_streak = self.protocol_streak + 1 if protocol_errors and not samples else 0
        if gnb_failed is None and self.protocol_streak >= PROTOCOL_ERROR_STREAK:
            gnb_failed = (f"{self.protocol_streak} measurement rounds in a row answered with protocol errors, "
                          f"last: {protocol_errors[-1]}")
        if gnb_failed is not None:
            self.flight.gnb_failed(now, gnb_failed)
        else:
            self.flight.gnb_answered(now)
        self._note_clock_offset()
        self._note_trace_gaps()
        if samples:
            self.place_queue.put_nowait(samples)

    def _note_clock_offset(self) -> None:
        """Log the gNB host's clock offset (trace and stock modes: mission.gnb.clock_offset) when it
        is first bounded and whenever it moves by more than OFFSET_LOG_STEP_S; count the stamped
        ranges refused while it was not."""
        estimate = getattr(self.gnb, "clock_offset", None)
        est = estimate() if callable(estimate) else None
        refused = int(getattr(self.gnb, "clock_refused", 0) or 0)
        if refused > self.clock_refused:
            if self.clock_refused == 0:
                self.flight.event(f"ranges refused: the gNB host's clock offset is not bounded yet ({refused} so far)",
                                  kind="gnb_clock_unbounded", refused=refused)
            self.clock_refused = refused
        if est is None or not est.bounded:
            return
        last = self._offset_logged
        if last is None or abs(est.offset_s - last) > OFFSET_LOG_STEP_S:
            self._offset_logged = est.offset_s
            self.flight.event(f"the gNB host's clock is {est.offset_s:+.3f} s behind ours (±{est.spread_s:.3f} s, "
                              f"{est.samples} stamps): its stamps are corrected by it", kind="gnb_clock_offset",
                              **est.to_dict())

    def _note_trace_gaps(self) -> None:
        """Log what each UE's first SRS after a dropped T connection proved (trace mode:
        mission.gnb.trace_rtt.GapOutcome): its TA checked (and re-based by the missed steps), or
        unknown and its ranges withheld."""
        drain = getattr(self.gnb, "trace_gaps", None)
        for g in (drain() if callable(drain) else []):
            self.flight.event(g.message, kind="gnb_trace_gap", **g.fields())

    def _report_rounds(self, served: int, start: tuple[float, np.ndarray] | None) -> None:
        """Once per mission: the first round cut short says how many users the gNB served while the
        UAV flew Δ, and no more (the spacing achieved is the survey's `survey_time` event's, measured)."""
        if self._rounds_reported:
            return
        self._rounds_reported = True
        n_users = len(self.users)
        latest = self.buffer.latest()
        took = f" in {latest[0] - start[0]:.2f} s" if start is not None and latest is not None else ""
        self.flight.event(f"the gNB served {served} of {n_users} users{took} while the UAV flew Δ = "
                          f"{self.delta_m:g} m: rounds take the users in turn", kind="gnb_rounds", served=served,
                          users=n_users)

    # -- placer ---------------------------------------------------------------------------------

    async def run_placer(self) -> None:
        while True:
            samples = await self.place_queue.get()
            try:
                await self.place(samples)
            finally:
                self.place_queue.task_done()

    async def position_at(self, t_s: float) -> np.ndarray:
        """UAV position at mission time t_s: waits briefly for the fix after it, then interpolates."""
        deadline = time.monotonic() + 1.0
        while not self.buffer.covers(t_s) and time.monotonic() < deadline:
            await self.flight.wake.wait(0.2)
        return self.buffer.at(t_s, max_extrapolate_s=0.5)

    def _note_trace_orders(self) -> None:
        """Log what the trace mode's PDCCH orders did (a UE that attached before the T client
        connected: mission.gnb.trace_order), as `gnb_trace_order` events."""
        drain = getattr(self.gnb, "drain_trace_orders", None)
        for o in (drain() if callable(drain) else []):
            self.flight.event(o.message, kind="gnb_trace_order", **o.fields())

    def _speed_mps(self, t0_s: float, t1_s: float) -> float:
        """The UAV's speed [m/s] around [t0_s, t1_s] (mission s): the logged velocity's
        (mission.control.timing.speed_around_mps), else the fixes' mean speed over it, else 0."""
        hist = np.asarray(self._speed_hist, float).reshape(-1, 2)
        speed = np.zeros((hist.shape[0], 3))
        speed[:, 0] = hist[:, 1]
        v = speed_around_mps(hist[:, 0], speed, t0_s, t1_s)
        if v is not None:
            return v
        if t1_s > t0_s:
            with contextlib.suppress(MissionError):
                return float(np.linalg.norm(self.buffer.at(t1_s, max_extrapolate_s=0.5)
                                            - self.buffer.at(t0_s, max_extrapolate_s=0.5))) / (t1_s - t0_s)
        return 0.0

    def _timed(self, samples: list) -> list[tuple[int, object, float, float]]:
        """The round's samples whose timing is good enough to place them (mission.control.timing),
        as (user, sample, mission t [s], half-interval [mission s]); the others counted and dropped."""
        kept = []
        for k, s, tm, unc in samples:
            t = self.mission_t(tm)
            half = 0.5 * (self.mission_t(tm + unc) - self.mission_t(tm - unc)) if unc > 0 else 0.0
            verdict = judge_range_timing(s.range_m, half, self._speed_mps(t - half, t + half), self._noise)
            if verdict.keep:
                kept.append((k, s, t, half))
                continue
            self.timing_dropped += 1
            self.flight.clock.dropped_late()
            if self.timing_dropped == 1 or self.timing_dropped % TIMING_EVENT_EVERY == 0:
                self.flight.event(f"range of {self.users[k].id} dropped: {verdict.describe()} ({self.timing_dropped} "
                                  f"dropped so far)", kind="range_timing_dropped", user=self.users[k].id,
                                  half_s=round(verdict.half_s, 4), speed_mps=round(verdict.speed_mps, 2),
                                  error_m=round(verdict.error_m, 2), sigma_m=round(verdict.sigma_m, 2),
                                  dropped=self.timing_dropped)
        return kept

    async def place(self, samples: list) -> None:
        origin = self.origin()
        timed = self._timed(samples)
        if not timed:
            return
        t_meas = float(np.mean([t for _, _, t, _ in timed]))
        try:
            pos = await self.position_at(t_meas)
        except MissionError as exc:
            self.flight.event(f"measurements dropped: {exc}", kind="dropped")
            return
        lat, lon, alt = (float(x) for x in origin.enu_to_lla(pos))
        uav = {"lat_deg": lat, "lon_deg": lon, "alt_m": alt}
        records = [self.writer.write("rtt", t, user=self.users[k].id, uav=uav, **self.tag, **s.log_fields(),
                                     **({"t_unc_s": round(half, 6)} if half > 0 else {}))
                   for k, s, t, half in timed]
        self.flight.measurements += len(timed)
        self.flight.clock.range_at(t_meas, len(timed))
        # the keyframe of the records as logged, by replay's builder (mission.keyframes)
        trigger = TriggerRecords.from_records(records, self._user_index)
        t_pos = trigger.position_t_s
        velocity = None
        if self._last_pos_t is not None and await self._velocity_covers(t_pos):
            velocity = self._velocity()
        kf = build_keyframe(trigger, origin, self._last_pos_t, velocity, self._noise, vehicle=self.vehicle)
        self._last_pos_t = t_pos
        self._forget_velocity_before(t_pos)
        self.keyframes.append(kf)
        self.keyframes_out.put_nowait(kf)

    async def drain(self, timeout_s: float) -> None:
        """Wait until every round so far is placed and solved (bounded; in a fleet, every vehicle's
        keyframes queued so far)."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                await self.place_queue.join()
                await self.keyframes_out.join()
