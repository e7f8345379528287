"""The one object the flight and its background tasks share (docs/design.md §7).

The measurement pipeline, the estimator worker, the safety monitor and the status line read and
write a :class:`FlightState`, and nothing else of each other: a request to return home, the
survey's normal end, the link and gNB conditions, the leg being flown, the metres flown, the
measurements and the latest estimate. Everything runs in one event loop, so there is no locking;
every change that ends the survey wakes the flight through `wake`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from estimator.types import Estimate
from mission.control.config import CONNECT
from mission.control.loop import Pulse

log = logging.getLogger(__name__)


@dataclass
class FlightState:
    """See the module docstring. Times are mission seconds.

    phase: CONNECT … LANDED / ABORT; return_reason: why the survey is cut short (first reason wins);
    stop: (status, reason) of a normal end of the survey; on_leg: a survey leg is being flown (the
    Δ-trigger is armed); link_lost_since / gnb_down_since: when the vehicle link / the gNB was
    lost (None: fine); gnb_problem: what the gNB said or did, in its own words; flown_m: survey
    metres; measurements: rtt records logged; estimate: the latest estimate; event: the mission
    log's event writer (message, **fields); wake: pulsed on every fix and every end request.
    """

    event: Callable[..., None]
    phase: str = CONNECT
    return_reason: str | None = None
    stop: tuple[str, str] | None = None
    on_leg: bool = False
    link_lost_since: float | None = None
    gnb_down_since: float | None = None
    gnb_problem: str | None = None
    flown_m: float = 0.0
    measurements: int = 0
    estimate: Estimate | None = None
    wake: Pulse = field(default_factory=Pulse)

    @property
    def ending(self) -> bool:
        """The survey is over (a return was requested or the stop rule was met)."""
        return self.return_reason is not None or self.stop is not None

    def set_phase(self, phase: str) -> None:
        if phase != self.phase:
            log.info("mission state %s -> %s", self.phase, phase)
            self.phase = phase

    def request_return(self, reason: str) -> None:
        """End the survey and return home (the first reason wins)."""
        if self.return_reason is None:
            self.return_reason = reason
            log.warning("returning home: %s", reason)
            self.event(f"return requested: {reason}", kind="return")
            self.wake.pulse()

    def finish_survey(self, status: str, reason: str) -> None:
        """A normal end of the survey (the stop rule); ignored once the survey is ending."""
        if not self.ending:
            self.stop = (status, reason)
            self.event(f"survey done: {reason}", kind="stop")
            self.wake.pulse()

    def gnb_failed(self, now_s: float, problem: str) -> None:
        """A measurement round failed for the gNB as a whole (lost, or answering what nobody can use)."""
        self.gnb_problem = problem
        if self.gnb_down_since is None:
            self.gnb_down_since = now_s
            log.warning("gNB lost: %s", problem)
            self.event(f"gNB lost: {problem}", kind="gnb_lost")

    def gnb_answered(self, now_s: float) -> None:
        """A measurement round went through."""
        if self.gnb_down_since is not None:
            self.event(f"gNB restored after {now_s - self.gnb_down_since:.1f} s", kind="gnb_restored")
            log.info("gNB restored")
            self.gnb_down_since = None
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
