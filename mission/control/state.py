"""The one object the flight and its background tasks share (docs/design.md §7).

The measurement pipeline, the estimator worker, the safety monitor and the status line read and
write a :class:`FlightState`, and nothing else of each other: a request to return home, the
survey's normal end, the link and gNB conditions, the leg being flown, the metres flown, the
measurements and the latest estimate. Everything runs in one event loop, so there is no locking;
every change that ends the survey wakes the flight through `wake`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from estimator.types import Estimate
from mission.control.config import CONNECT, SURVEY, SurveyPace
from mission.control.loop import Pulse

log = logging.getLogger(__name__)

#: slower than this [m/s, 3-D speed], a surveying vehicle hovers (issue 39: a survey that waits for
#: the planner); a leg that mostly climbs or descends is flown, not hovered
HOVER_SPEED_MPS = 0.5
#: the survey's pace is judged while it runs once it has lasted this long [mission s]: its first
#: seconds wait for the first plan
PACE_JUDGE_AFTER_S = 60.0


@dataclass
class SurveyClock:
    """How the survey spent its time, in mission seconds: t0_s, t1_s its start and end; hover_s the
    time slower than HOVER_SPEED_MPS; largest_gap_s the longest time without a range (from the
    start, between rounds, to the end); rounds / ranges: gNB rounds placed (one keyframe each) and
    the ranges in them during the survey; late_dropped: ranges dropped during the survey as timed
    too loosely to place (mission.control.timing); wall0_s, wall1_s: the wall instants (monotonic)
    of its start and end (:meth:`pace`).
    Pure: the caller passes the instants.
    """

    t0_s: float | None = None
    t1_s: float | None = None
    hover_s: float = 0.0
    largest_gap_s: float = 0.0
    rounds: int = 0
    ranges: int = 0
    late_dropped: int = 0
    wall0_s: float | None = None
    wall1_s: float | None = None
    _last_fix_s: float | None = None
    _last_range_s: float | None = None

    def start(self, t_s: float, wall_s: float | None = None) -> None:
        """The survey starts at mission time t_s (wall instant wall_s)."""
        self.t0_s, self.wall0_s = t_s, wall_s

    def fix(self, t_s: float, speed_mps: float | None) -> None:
        """A fix during the survey: Δt since the latest fix so far counts as hover when slower than
        the threshold. A fix stamped before the latest one (two streams' stamps interleaved, seen
        under load) adds nothing, so hover time never exceeds the survey's time."""
        if self.t0_s is None or self.t1_s is not None:
            return
        if self._last_fix_s is not None and speed_mps is not None and speed_mps < HOVER_SPEED_MPS:
            self.hover_s += max(0.0, t_s - self._last_fix_s)
        self._last_fix_s = t_s if self._last_fix_s is None else max(self._last_fix_s, t_s)

    def range_at(self, t_s: float, ranges: int = 1) -> None:
        """A round of `ranges` ranges measured at t_s."""
        if self.t0_s is None or self.t1_s is not None:
            return
        self.rounds += 1
        self.ranges += ranges
        self._gap_to(t_s)

    def dropped_late(self, ranges: int = 1) -> None:
        """`ranges` ranges dropped as timed too loosely (counted during the survey only)."""
        if self.t0_s is not None and self.t1_s is None:
            self.late_dropped += ranges

    def _gap_to(self, t_s: float) -> None:
        prev = self._last_range_s if self._last_range_s is not None else self.t0_s
        self.largest_gap_s = max(self.largest_gap_s, t_s - prev)
        self._last_range_s = max(t_s, prev)

    def end(self, t_s: float, wall_s: float | None = None, measured_until_s: float | None = None) -> None:
        """The survey ends at mission time t_s (wall instant wall_s). measured_until_s: when the
        stop rule ended the ranging, if it did (the seconds the flight then takes to confirm the
        final answer and command the return are no gap between ranges)."""
        if self.t0_s is None or self.t1_s is not None:
            return
        self._gap_to(t_s if measured_until_s is None else min(t_s, measured_until_s))
        self.t1_s, self.wall1_s = t_s, wall_s

    @property
    def survey_s(self) -> float:
        if self.t0_s is None:
            return 0.0
        return (self.t1_s if self.t1_s is not None else self._last_fix_s or self.t0_s) - self.t0_s

    def rounds_per_min(self) -> float | None:
        """gNB rounds placed per mission minute of the survey (None: no survey time)."""
        return 60.0 * self.rounds / self.survey_s if self.survey_s > 0 else None

    def pace(self, requested_speedup: float) -> SurveyPace | None:
        """The survey's :class:`SurveyPace` once it ended with wall instants (None before, or
        when it lasted no wall time)."""
        if self.t1_s is None or self.wall0_s is None or self.wall1_s is None or self.wall1_s <= self.wall0_s:
            return None
        return SurveyPace(requested_speedup, self.survey_s, self.wall1_s - self.wall0_s, self.hover_s,
                          self.largest_gap_s, self.ranges, self.late_dropped)

    def pace_now(self, requested_speedup: float, t_s: float, wall_s: float) -> SurveyPace | None:
        """The survey's pace so far, at mission time t_s and wall instant wall_s, once it has run
        PACE_JUDGE_AFTER_S mission seconds (None before, after its end, or without wall instants):
        what the flight checks while surveying, to say at once that it falls behind."""
        if self.t0_s is None or self.t1_s is not None or self.wall0_s is None:
            return None
        survey_s = t_s - self.t0_s
        if survey_s < PACE_JUDGE_AFTER_S or wall_s <= self.wall0_s:
            return None
        # the stretch since the last range is a gap too, so far
        gap_s = max(self.largest_gap_s, t_s - (self._last_range_s if self._last_range_s is not None else self.t0_s))
        return SurveyPace(requested_speedup, survey_s, wall_s - self.wall0_s, self.hover_s, gap_s, self.ranges,
                          self.late_dropped)


def spacing_m(flown_m: float, count: int) -> float | None:
    """Metres flown per event (gNB round, or range of one user) over the survey; None when none."""
    return flown_m / count if count > 0 else None


@dataclass
class FlightState:
    """See the module docstring. Times are mission seconds.

    phase: CONNECT … LANDED / ABORT; return_reason: why the survey is cut short (first reason wins);
    stop: (status, reason) of a normal end of the survey, stop_s its mission time; on_leg: a survey
    leg is being flown (the Δ-trigger is armed); link_lost_since / gnb_down_since: when the vehicle
    link / the gNB was lost (None: fine); gnb_problem: what the gNB said or did, in its own words;
    flown_m: survey metres; measurements: rtt records logged; estimate: the latest estimate; event:
    the mission log's event writer (message, **fields); wake: pulsed on every fix and every end
    request; clock: the survey's hover time and largest gap between ranges.
    """

    event: Callable[..., None]
    phase: str = CONNECT
    return_reason: str | None = None
    stop: tuple[str, str] | None = None
    stop_s: float | None = None
    on_leg: bool = False
    link_lost_since: float | None = None
    gnb_down_since: float | None = None
    #: the monotonic wall instant of gnb_down_since [s] (the gNB's silence is judged in wall time too)
    gnb_down_since_wall: float | None = None
    gnb_problem: str | None = None
    flown_m: float = 0.0
    measurements: int = 0
    estimate: Estimate | None = None
    wake: Pulse = field(default_factory=Pulse)
    #: hover time and the longest time without a range, over the survey
    clock: SurveyClock = field(default_factory=SurveyClock)
    #: whose state this is in log lines: a fleet's vehicle id (None: the mission's one vehicle)
    name: str | None = None
    #: why the survey was seen falling behind its speed-up (SurveyPace.reasons, said once:
    #: :meth:`check_pace`; empty: not seen)
    pace_said: tuple[str, ...] = ()
    #: a requested return whose `return` event waits for the end of the survey (request_return)
    _return_unlogged: bool = False

    def check_pace(self, requested_speedup: float, t_s: float, wall_s: float) -> SurveyPace | None:
        """While surveying: the moment the survey's pace so far (SurveyClock.pace_now at mission
        time t_s, wall instant wall_s) falls behind its speed-up, say so on the console (a warning)
        and in the log (event `falling_behind`), once. The pace when it was said now, else None."""
        if self.pace_said:
            return None
        pace = self.clock.pace_now(requested_speedup, t_s, wall_s)
        if pace is None or not pace.fell_behind:
            return None
        self.pace_said = tuple(pace.reasons())
        who = f"{self.name}: " if self.name else ""
        log.warning("falling behind: %s%s", who, pace.message())
        self.event(f"falling behind: {pace.message()}", kind="falling_behind", **pace.to_dict())
        return pace

    @property
    def ending(self) -> bool:
        """The survey is over (a return was requested or the stop rule was met)."""
        return self.return_reason is not None or self.stop is not None

    def set_phase(self, phase: str) -> None:
        if phase != self.phase:
            log.info("%s state %s -> %s", self.name or "mission", self.phase, phase)
            self.phase = phase

    def request_return(self, reason: str) -> None:
        """End the survey and return home (the first reason wins). During the survey its `return`
        event is logged once the survey has ended, after its `survey_time` (:meth:`log_return`),
        so that a vehicle's log reads survey, then return; otherwise at once."""
        if self.return_reason is None:
            self.return_reason = reason
            log.warning("%sreturning home: %s", f"{self.name}: " if self.name else "", reason)
            self._return_unlogged = True
            if self.phase != SURVEY:
                self.log_return()
            self.wake.pulse()

    def log_return(self) -> None:
        """The `return` event of a return requested and not logged yet (in_survey: requested during
        the survey, logged after its `survey_time`)."""
        if self.return_reason is not None and self._return_unlogged:
            self._return_unlogged = False
            self.event(f"return requested: {self.return_reason}", kind="return", reason=self.return_reason,
                       **({"in_survey": True} if self.phase == SURVEY else {}))

    def finish_survey(self, status: str, reason: str, now_s: float) -> None:
        """A normal end of the survey (the stop rule) at mission time now_s; ignored once the
        survey is ending."""
        if not self.ending:
            self.stop, self.stop_s = (status, reason), now_s
            self.event(f"survey done: {reason}", kind="stop", reason=reason)
            self.wake.pulse()

    def resume_survey(self) -> None:
        """The stop rule's end is withdrawn (the final answer did not confirm the target)."""
        self.stop = self.stop_s = None

    def gnb_failed(self, now_s: float, problem: str) -> None:
        """A measurement round failed for the gNB as a whole (lost, or answering what nobody can use)."""
        self.gnb_problem = problem
        if self.gnb_down_since is None:
            self.gnb_down_since = now_s
            self.gnb_down_since_wall = time.monotonic()
            log.warning("gNB lost: %s", problem)
            self.event(f"gNB lost: {problem}", kind="gnb_lost")

    def gnb_answered(self, now_s: float) -> None:
        """A measurement round went through."""
        if self.gnb_down_since is not None:
            self.event(f"gNB restored after {now_s - self.gnb_down_since:.1f} s", kind="gnb_restored")
            log.info("gNB restored")
            self.gnb_down_since = self.gnb_down_since_wall = None
            self.gnb_problem = None

    def link(self, now_s: float, lost: bool) -> None:
        """The vehicle link's condition now."""
        if lost and self.link_lost_since is None:
            self.link_lost_since = now_s
            self.event("vehicle link lost", kind="link_lost")
        elif not lost and self.link_lost_since is not None:
            self.event(f"vehicle link restored after {now_s - self.link_lost_since:.1f} s", kind="link_restored")
            self.link_lost_since = None

    def summary(self) -> dict[str, Any]:
        return {"phase": self.phase, "return_reason": self.return_reason, "stop": self.stop,
                "flown_m": self.flown_m, "measurements": self.measurements}
