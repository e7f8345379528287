"""The mission's final answer (docs/design.md §11): the controller's part that judges a survey's
end against it and closes the mission with it.

The final answer is the batch solution over every keyframe, as `uavloc replay` computes it from the
log: before a vehicle turns home, a survey that ended "target reached", "floor reached" or "its
users done" is held to it (:meth:`FinalAnswer._target_confirmed`), and when the mission ends its
log is replayed, the status judged against that replay (mission.replay.status_of_answer) and the
one `Result` built from the closed log (mission.replay.result_of_log), the function `uavloc replay`
uses too.

:class:`FinalAnswer` is a part of :class:`mission.control.flight.MissionController` (a base class:
it reads the controller's crews, keyframes, estimator, journal and settings), kept in a module of
its own so that the flight's states read top to bottom in flight.py.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import replace

import numpy as np

from estimator.types import Estimate
from mission.control.config import STATUS_FLOOR, STATUS_TARGET, MissionResult
from mission.control.crew import VehicleCrew
from mission.control.legs import PLAN_DRAIN_MAX_S
from mission.log import read_mission_log
from mission.replay import ReplayOptions, ReplayResult, replay, result_of_log, status_of_answer
from mission.result import Result, VehicleResult, build_result, vehicles_of_events
from planner.fleet import REASON_USERS_DONE
from uavloc.errors import MissionLogError, UavlocError

log = logging.getLogger(__name__)


class FinalAnswer:
    """The final-answer methods of the mission controller (see the module docstring)."""

    async def _target_confirmed(self, crew: VehicleCrew) -> bool:
        """After a survey that ended "target reached" or "floor reached": the mission's final
        answer (the batch over every keyframe, the last rounds placed first) decides. "Target
        reached" must hold for the answer the mission prints: a last range can widen a bound by a
        metre (seen: 3.86 to 4.84 m against 4 m), and then the survey goes on (False). A floor the
        survey's estimate saw may be within the target in the final answer (seen: 3.57 m against
        4 m after "floor reached"): then the target is reached, for every vehicle of a fleet.

        A fleet's vehicle whose planner found its users within the target ("its users done",
        planner.fleet) judged that on the estimate of the moment, an online one perhaps, narrower
        than a batch answer (seen on PX4: 3.9 m online, 6.0 m in the final answer): the final answer
        decides here too. Every user within the target: the target is reached; this vehicle's users
        within it: its part is done; else it surveys on (:meth:`_users_done_confirmed`)."""
        f = crew.flight
        users_done = f.stop is not None and f.stop[1] == REASON_USERS_DONE
        if (f.stop is None or (f.stop[0] not in (STATUS_TARGET, STATUS_FLOOR) and not users_done)
                or f.return_reason is not None or self._estimator is None):
            return True
        async with self._confirm_lock:  # a fleet's vehicles judge one after the other
            if f.stop is None:
                return False
            await asyncio.gather(*(c.pipeline.drain(c.wall(PLAN_DRAIN_MAX_S)) for c in self.crews))
            final = await asyncio.to_thread(self._estimator.final, list(self._keyframes))
            reached = self._estimator.within_target(final)
            n_kf = len(self._keyframes)
            if users_done:
                return self._users_done_confirmed(crew, final, reached)
            if f.stop[0] == STATUS_FLOOR:
                if reached:
                    f.stop = (STATUS_TARGET, "target reached")
                    crew.event(f"the final answer over {n_kf} keyframes bounds every user within the "
                               f"{self.config.flight.target_radius_m:g} m target: target reached",
                               kind="target_in_final_answer")
                    self._finish_all(STATUS_TARGET, "target reached")
                return True
            if reached:
                return True
            worst = _worst_bound_m(final.error_bound_95_m())
            f.resume_survey()
            crew.event(f"the final answer over {n_kf} keyframes {_bound_words(worst)} of a user, beyond the "
                       f"{self.config.flight.target_radius_m:g} m target the survey's estimate reached: "
                       f"surveying on", kind="target_unconfirmed", bound_95_m=worst)
            f.estimate = final
            return False

    def _users_done_confirmed(self, crew: VehicleCrew, final: Estimate, reached: bool) -> bool:
        """A survey that ended "its users done", against the final answer `final` (reached: every
        user within the target in it): True when the vehicle's part is done (the target reached for
        the fleet, or its own users within the target), False when it surveys on."""
        f, target = crew.flight, self.config.flight.target_radius_m
        n_kf = len(self._keyframes)
        if reached:
            f.stop = (STATUS_TARGET, "target reached")
            crew.event(f"the final answer over {n_kf} keyframes bounds every user within the {target:g} m target: "
                       "target reached", kind="target_in_final_answer")
            self._finish_all(STATUS_TARGET, "target reached")
            return True
        bound = final.error_bound_95_m()
        # its users, and those nobody serves now (a vehicle gone home left them: planner.fleet.has_work)
        serving = self._serving_now()
        mine = ((serving == crew.index) | (serving < 0)) & ~((bound <= target) & ~np.asarray(final.ambiguous, bool))
        if not mine.any():
            return True
        worst = _worst_bound_m(bound[mine])
        f.resume_survey()
        crew.event(f"the final answer over {n_kf} keyframes {_bound_words(worst)} of a user it can measure, beyond the "
                   f"{target:g} m target its survey's estimate reached: surveying on", kind="users_done_unconfirmed",
                   bound_95_m=worst, users=[self.users[k].id for k in np.flatnonzero(mine)])
        f.estimate = final
        return False

    def _replay_log(self) -> ReplayResult:
        """What `uavloc replay LOG` computes, from the log as written so far (the header holds the
        mission's noise model and solver settings)."""
        mlog = read_mission_log(self.journal.writer.path)  # flushed line by line
        if mlog.skipped_torn_line is not None:
            raise MissionLogError(f"{self.journal.writer.path}: a torn line ({mlog.skipped_torn_line})")
        return replay(mlog, ReplayOptions(history=False))

    def _close(self, status: str, reason: str, t_wall: float) -> MissionResult:
        est = self.estimate
        keyframes = self._keyframes
        replayed: ReplayResult | None = None
        if keyframes:
            # the final answer is the batch solution over every keyframe, as `uavloc replay`
            # computes it from the log: the same keyframes (one builder, mission.keyframes) under
            # the header's noise model and solver settings and the τ the flight logged (event
            # gps_tau), and the status it supports (status_of_answer, as replay judges it); the
            # pipeline's keyframes under the flight's noise model if the log cannot be read back
            try:
                replayed = self._replay_log()
                est = replayed.estimate
                if (judged := status_of_answer(status, reason, replayed)) != (status, reason):
                    status, reason = judged
                    self.journal.event(f"the final answer: {status} ({reason})", kind="status_of_answer")
            except Exception as exc:  # also a bug in replay: fall back, never lose the result
                log.warning("final estimate from the pipeline's keyframes: the log could not be replayed: %s", exc)
                try:
                    est = (self._estimator or self.estimator_setup()).final(keyframes)
                except Exception as exc2:  # a bug must not cost the mission its log or its last estimate
                    log.exception("final batch estimate failed")
                    self.journal.event(f"final batch estimate failed: {type(exc2).__name__}: {exc2}",
                                       kind="estimator_error")
        if est is not None and self.journal.is_open:
            self.estimate = est
            self.journal.estimate(self.origin, est, len(keyframes), self.flown_m, final=True,
                                  vehicles=self._kf_vehicles() if self.fleet else None)
        self.journal.event(f"mission end: {status} ({reason})", kind="end", status=status, reason=reason)
        self.journal.close()
        self.result = MissionResult(
            result=self._result(status, reason, est, replayed), estimate=est, wall_s=time.monotonic() - t_wall,
            rtl_sent=all(c.rtl_sent for c in self.crews if c.connected) and any(c.connected for c in self.crews),
            landed=all(c.landed for c in self.crews),
            refusals=sum(c.gated.refusals for c in self.crews if c.gated is not None),
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
        c = self.crews[0].flight.clock
        surveyed = c.survey_s > 0
        vehicles, breaches = self._fleet_parts()
        return build_result(
            status=status, reason=reason, user_ids=[u.id for u in self.users], estimate=est, origin=self.origin,
            truth_enu_m=self.truth_enu_m, flown_m=self.flown_m, measurements=self.measurements,
            keyframes=len(self._keyframes), duration_s=self.now(),
            survey_s=c.survey_s if surveyed else None, hover_s=c.hover_s if surveyed else None,
            largest_gap_s=c.largest_gap_s if surveyed else None,
            log_path=self.log_path if self.origin is not None else None, vehicles=vehicles,
            separation_breaches=breaches)

    def _fleet_parts(self) -> tuple[tuple[VehicleResult, ...], int | None]:
        """A fleet's `vehicles` and `separation_breaches` for a result not replayed (an aborted
        fleet's too, docs/fleet.md): from the closed log's events as replay reads them, or, when
        the log cannot be read back, each vehicle's safe end and the breaches the flight counted."""
        if not self.fleet:
            return (), None
        try:
            return vehicles_of_events([c.id for c in self.crews], read_mission_log(self.journal.writer.path).events)
        except (UavlocError, OSError):
            return (tuple(VehicleResult(c.id, "did not survey", c.rtl_sent, c.landed) for c in self.crews),
                    len(self.separation_breaches))


def _worst_bound_m(bounds_m: np.ndarray) -> float | None:
    """The largest finite 95 % bound [m], None when no user is located (its bound is infinite):
    what an event record can hold (the log refuses NaN and infinities)."""
    b = np.asarray(bounds_m, float)
    if np.any(~np.isfinite(b)) or b.size == 0:
        return None
    return float(np.max(b))


def _bound_words(worst_m: float | None) -> str:
    return "leaves no position" if worst_m is None else f"gives a {worst_m:.2f} m bound"
