"""The mission controller's configuration and result: what a flight is asked to do and what it
found (docs/design.md §7, §11). Plain data, no I/O."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from estimator.geodesy import Origin
from estimator.types import Estimate
from mission.config import FlightConfig, SafetyConfig
from mission.result import horizontal_error_m, user_entries_of_estimate
from mission.schema import bounded, check_bounds, positive

if TYPE_CHECKING:
    from mission.control.state import SurveyPace

CONNECT, PREFLIGHT, TAKEOFF, SURVEY, RETURN, LANDED, ABORT = (
    "CONNECT", "PREFLIGHT", "TAKEOFF", "SURVEY", "RETURN", "LANDED", "ABORT")

#: MissionResult.status values
STATUS_TARGET = "target_reached"
STATUS_BUDGET = "budget_spent"
STATUS_NO_LEG = "no_feasible_leg"
STATUS_FLOOR = "floor_reached"  # the bounds stopped shrinking above the target (GPS floor)
STATUS_RETURNED = "returned"  # a safety condition ended the survey early
STATUS_ABORTED = "aborted"  # an error ended the mission (RTL sent when airborne)
STATUS_INTERRUPTED = "interrupted"  # cancelled / Ctrl-C (RTL sent when airborne)

#: PX4's default horizontal cruise speed (MPC_XY_CRUISE): what the vehicle flies when a speed
#: command was refused, so the leg timeouts follow it then
PX4_DEFAULT_CRUISE_MPS = 5.0

#: the largest simulator speedup (mission seconds per wall second) and controller wait [s]
MAX_TIME_SCALE = 1000.0
MAX_WAIT_S = 3600.0

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
    """Mission settings: the mission file's flight and safety tables as they are
    (:class:`mission.config.FlightConfig`, :class:`mission.config.SafetyConfig`: survey height,
    Δ, stop rule, budget, time limit, speeds, lost-link and lost-gNB waits, refusals, breach
    confirmation, battery floor), and the controller's own settings, which a mission file does not
    hold. Times marked (mission) are mission seconds; (wall) are real seconds.

    time_scale: mission seconds per wall second (simulator speedup);
    connect_timeout_s, ready_timeout_s (wall): the vehicle's connection and readiness;
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


@dataclass
class MissionResult:
    """How a mission ended, and what it found.

    status: one of the STATUS_* values; reason: why; estimate: final (batch) estimate or None;
    origin: home (the log's ENU origin) or None if never known; truth_enu_m (K, 3) when known;
    flown_m: survey metres flown; measurements: rtt records logged; keyframes: keyframes used;
    pace: how fast the survey really ran against its speed-up (None: no survey).
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
    pace: SurveyPace | None = None

    @property
    def ok(self) -> bool:
        """The mission ended normally and located every user (else the command exits non-zero)."""
        ended = (STATUS_TARGET, STATUS_FLOOR, STATUS_BUDGET, STATUS_NO_LEG, STATUS_RETURNED)
        return self.status in ended and not self.not_located()

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
        return horizontal_error_m(self.estimate.users_enu_m, self.truth_enu_m)

    def to_document(self) -> dict:
        """The docs/design.md §11 JSON document (plus `reason`)."""
        users = user_entries_of_estimate(self.estimate if self.origin is not None else None, self.origin,
                                         self.user_ids, self.truth_enu_m)
        return {"status": self.status, "reason": self.reason, "users": users,
                "flown_m": round(self.flown_m, 3), "measurements": self.measurements}
