"""The mission controller's configuration and result: what a flight is asked to do and what it
found (docs/design.md §7, §11). Plain data, no I/O."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from estimator.types import Estimate
from mission.config import FlightConfig, SafetyConfig

# how a mission ends (Result.status), named once in mission.result and re-exported here
from mission.result import STATUS_ABORTED as STATUS_ABORTED
from mission.result import STATUS_BUDGET as STATUS_BUDGET
from mission.result import STATUS_FLOOR as STATUS_FLOOR
from mission.result import STATUS_INTERRUPTED as STATUS_INTERRUPTED
from mission.result import STATUS_NO_LEG as STATUS_NO_LEG
from mission.result import STATUS_RETURNED as STATUS_RETURNED
from mission.result import STATUS_TARGET as STATUS_TARGET
from mission.result import Result
from mission.schema import bounded, check_bounds, positive

CONNECT, PREFLIGHT, TAKEOFF, SURVEY, RETURN, LANDED, ABORT = (
    "CONNECT", "PREFLIGHT", "TAKEOFF", "SURVEY", "RETURN", "LANDED", "ABORT")

#: PX4's default horizontal cruise speed (MPC_XY_CRUISE): what the vehicle flies when a speed
#: command was refused, so the leg timeouts follow it then
PX4_DEFAULT_CRUISE_MPS = 5.0

#: the largest simulator speedup (mission seconds per wall second) and controller wait [s]
MAX_TIME_SCALE = 1000.0
MAX_WAIT_S = 3600.0

#: wall seconds the safe end may spend getting RTL accepted after an error
SAFE_END_TIMEOUT_S = 60.0
#: ... and after Ctrl-C (the user waits; mission.runtime's watchdog acts alone 15 s after the signal)
INTERRUPT_SAFE_END_TIMEOUT_S = 10.0
#: wall seconds the planner's one-time preparation (its CasADi kernels compiled, ~8 s on an idle
#: machine, 106 s seen on 2 loaded cores) may take before take-off; beyond it the mission aborts
PREPARE_TIMEOUT_S = 300.0


@dataclass(frozen=True)
class MissionUser:
    """A user to locate: id, RNTI and ground height `up_m` in the home ENU frame [m]."""

    id: str
    rnti: int
    up_m: float = 0.0


@dataclass(frozen=True)
class ControllerConfig:
    """Mission settings: the mission file's flight and safety tables as they are
    (:class:`mission.config.FlightConfig`, :class:`mission.config.SafetyConfig`: survey height,
    Δ, stop rule, budget, time limit, speeds, lost-link and lost-gNB waits, refusals, breach
    confirmation, battery floor), and the controller's own settings, which a mission file does not
    hold. Times marked (mission) are mission seconds; (wall) are real seconds.

    time_scale: mission seconds per wall second (simulator speedup);
    connect_timeout_s, ready_timeout_s (wall): the vehicle's connection and readiness;
    preflight_timeout_s (wall): PREFLIGHT once every home is known (the gNB probes, the battery,
    the planner's preparation), beyond which the mission aborts naming what it still waits for;
    gnb_timeout_s (wall): per measurement request; telemetry_log_hz (mission): telemetry records;
    status_interval_s (wall): progress lines;
    position_smooth_s (mission): the position a waypoint's leg is checked from is the mean of
    the fixes over this long (the vehicle hovers when a leg is planned);
    estimator_mode: "process" (estimator in a child process) or "thread" (see EstimatorWorker).
    """

    flight: FlightConfig = field(default_factory=FlightConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    time_scale: float = positive(1.0, MAX_TIME_SCALE)
    connect_timeout_s: float = positive(30.0, MAX_WAIT_S)
    ready_timeout_s: float = positive(60.0, MAX_WAIT_S)
    preflight_timeout_s: float = positive(300.0, MAX_WAIT_S)
    gnb_timeout_s: float = positive(2.0, MAX_WAIT_S)
    telemetry_log_hz: float = positive(5.0, 1000.0)
    status_interval_s: float = positive(2.0, MAX_WAIT_S)
    position_smooth_s: float = bounded(1.0, 0.0, 60.0)
    estimator_mode: Literal["process", "thread"] = "process"

    def __post_init__(self) -> None:
        # set by code and overrides, not read by the strict loader: checked here, with the same bounds
        check_bounds(self, "controller settings")

    @classmethod
    def from_mission(cls, mission, **overrides) -> ControllerConfig:
        """From a :class:`mission.config.MissionConfig`: its flight and safety tables, and the
        per-measurement timeout `mission.gnb.measure_timeout_s()`; overrides: any field."""
        kw = dict(flight=mission.flight, safety=mission.safety, gnb_timeout_s=mission.gnb.measure_timeout_s())
        kw.update(overrides)
        return cls(**kw)


#: below this share of the requested speed-up a simulation fell behind it (issue 39)
FELL_BEHIND_SHARE = 0.8
#: more of the survey than this share hovering: the flight waited for its planner or its estimator
#: (issue 48: `paper --speedup 100` hovered 60 % of its survey and said nothing)
HOVER_SHARE_MAX = 0.25
#: more of the ranges than this share dropped as timed too loosely (mission.control.timing), judged
#: once at least LATE_JUDGE_MIN ranges were measured
LATE_SHARE_MAX = 0.1
LATE_JUDGE_MIN = 10


@dataclass(frozen=True)
class SurveyPace:
    """How fast the survey really ran against the wall clock, and whether it kept the pace its
    speed-up asks (issue 39, issue 48: a simulation that cannot keep its speed-up must say so, and
    by how much).

    requested_speedup: the controller's time_scale (mission seconds per wall second asked for);
    survey_s / survey_wall_s: the survey's mission seconds (the vehicle's clock, as the controller
    reads it) and wall seconds. achieved_speedup = survey_s / survey_wall_s: it falls below the
    requested one when the simulation runs slow (a starved built-in vehicle drops the time it cannot
    work off, its `behind_s`; a PX4 SITL runs below its speed factor). hover_s: survey seconds
    spent hovering (waiting for a plan); largest_gap_s: the longest stretch without a range [s]
    (reported, not judged: a gNB that stopped answering is no slow simulation);
    ranges / late_dropped: the survey's ranges placed, and those dropped as timed too loosely.
    """

    requested_speedup: float
    survey_s: float
    survey_wall_s: float
    hover_s: float = 0.0
    largest_gap_s: float = 0.0
    ranges: int = 0
    late_dropped: int = 0
    #: why the survey was said to fall behind while it flew (FlightState.check_pace): a survey that
    #: caught up by its end still fell behind (its ranges of that stretch are in the answer)
    said_while_flying: tuple[str, ...] = ()

    @property
    def achieved_speedup(self) -> float:
        """Mission seconds per wall second over the survey."""
        return self.survey_s / self.survey_wall_s

    @property
    def hover_share(self) -> float:
        """hover_s / survey_s (0 without survey seconds)."""
        return self.hover_s / self.survey_s if self.survey_s > 0 else 0.0

    def reasons(self) -> list[str]:
        """Why the survey did not keep its pace (empty: it did)."""
        out = []
        achieved = round(self.achieved_speedup, 2)
        if self.achieved_speedup < FELL_BEHIND_SHARE * self.requested_speedup:
            out.append(f"the simulation fell behind its speed-up ({self.survey_s:.0f} mission seconds of survey "
                       f"took {self.survey_wall_s:.1f} wall seconds, {100.0 * achieved / self.requested_speedup:.0f} "
                       f"% of the pace asked)")
        if self.hover_share > HOVER_SHARE_MAX:
            out.append(f"the UAV hovered {100.0 * self.hover_share:.0f} % of the survey ({self.hover_s:.0f} of "
                       f"{self.survey_s:.0f} s) waiting for plans (limit {100.0 * HOVER_SHARE_MAX:.0f} %)")
        total = self.ranges + self.late_dropped
        if total >= LATE_JUDGE_MIN and self.late_dropped > LATE_SHARE_MAX * total:
            out.append(f"{self.late_dropped} of {total} ranges were timed too loosely to place and were dropped")
        if not out and self.said_while_flying:
            out.append(f"while surveying: {'; '.join(self.said_while_flying)}")
        return out

    @property
    def fell_behind(self) -> bool:
        """The survey did not keep the pace its speed-up asks (any of :meth:`reasons`)."""
        return bool(self.reasons())

    def message(self) -> str:
        """One line: "asked ×20, ran ×6.3: ..." (what fell behind, by how much, and what it means).
        It prints the speed-up the log records (to_dict's two decimals), so the line and the field
        never disagree."""
        achieved = round(self.achieved_speedup, 2)
        return (f"asked ×{self.requested_speedup:g}, ran ×{achieved:.1f}: {'; '.join(self.reasons())}; "
                f"the machine is too busy for it, try a smaller --speedup")

    def to_dict(self) -> dict:
        """The mission log's `fell_behind` event fields and the `--json` document's `speedup` entry."""
        return {"requested_speedup": self.requested_speedup, "achieved_speedup": round(self.achieved_speedup, 2),
                "survey_wall_s": round(self.survey_wall_s, 2), "hover_share": round(self.hover_share, 3),
                "largest_gap_s": round(self.largest_gap_s, 2), "ranges_dropped_late": self.late_dropped,
                "fell_behind": self.fell_behind, "why": self.reasons()}


@dataclass
class MissionResult:
    """How a mission ended: its :class:`mission.result.Result` (what the log holds, the one object
    every rendering prints) and the run-time facts a log cannot hold.

    result: the mission's result; estimate: its final (batch) estimate, or None; wall_s: wall
    seconds the run took; rtl_sent, landed: the safe end; refusals: commands the safety gate
    refused; events: the event messages; loop_lag: the event loop's lag summary;
    pace: how fast the survey really ran against its speed-up (None: no survey).
    """

    result: Result
    estimate: Estimate | None = None
    wall_s: float = 0.0
    rtl_sent: bool = False
    landed: bool = False
    refusals: int = 0
    events: list[str] = field(default_factory=list)
    loop_lag: dict = field(default_factory=dict)
    pace: SurveyPace | None = None

    # the result's facts, read through (one object holds them)
    @property
    def status(self) -> str:
        return self.result.status

    @property
    def reason(self) -> str:
        return self.result.reason

    @property
    def flown_m(self) -> float:
        return self.result.flown_m

    @property
    def measurements(self) -> int:
        return self.result.measurements

    @property
    def keyframes(self) -> int:
        return self.result.keyframes

    @property
    def log_path(self) -> Path | None:
        return self.result.log_path

    @property
    def ok(self) -> bool:
        """The mission ended normally and located every user (else the command exits non-zero)."""
        return self.result.ok

    def not_located(self) -> list[str]:
        return self.result.not_located()

    def error_m(self) -> np.ndarray | None:
        """(K,) horizontal error of each user [m] when truth is known."""
        return self.result.error_m()
