"""Faults of the built-in vehicle: the scenario's `[[faults.vehicle]]` events and the fault state
the simulator consults (link paused, GPS lost until, DO_REPOSITION refused until). Times are
simulated seconds."""

from __future__ import annotations

import logging
import math

from sitl_scenarios.vehicle.autopilot import Autopilot
from sitl_scenarios.vehicle.fault_events import FAULT_KINDS, FaultEvent, faults_from_scenario

__all__ = ["FAULT_KINDS", "FaultEvent", "VehicleFaults", "faults_from_scenario"]

log = logging.getLogger(__name__)

class VehicleFaults:
    """The faults in effect and those scheduled. Not thread-safe: the simulator serializes calls."""

    def __init__(self, events: list[FaultEvent] | tuple[FaultEvent, ...] = ()) -> None:
        self.scheduled = sorted(events, key=lambda f: f.at_s)
        self.link_down_until_s: float | None = None
        self.gps_back_at_s: float | None = None
        self.refuse_reposition_until_s = -math.inf

    def link_down(self, t_s: float) -> bool:
        """Whether the link is paused at simulated time t_s."""
        return self.link_down_until_s is not None and t_s < self.link_down_until_s

    def link_resumed(self, t_s: float) -> bool:
        """True once, at the first call after a pause ended (the pause is then forgotten)."""
        if self.link_down_until_s is None or self.link_down(t_s):
            return False
        self.link_down_until_s = None
        return True

    def pause_link(self, t_s: float, duration_s: float) -> None:
        self.link_down_until_s = t_s + duration_s

    def resume_link(self) -> None:
        self.link_down_until_s = None

    def lose_gps(self, ap: Autopilot, duration_s: float | None) -> None:
        ap.set_gps_lost(True)
        self.gps_back_at_s = None if duration_s is None else ap.t_s + duration_s

    def restore_gps(self, ap: Autopilot) -> None:
        ap.set_gps_lost(False)
        self.gps_back_at_s = None

    def refuse_reposition(self, t_s: float, duration_s: float | None) -> None:
        self.refuse_reposition_until_s = math.inf if duration_s is None else t_s + duration_s

    def refusing_reposition(self, t_s: float) -> bool:
        return t_s < self.refuse_reposition_until_s

    def apply(self, ap: Autopilot) -> None:
        """Start the scheduled faults that are due at the autopilot's time; end a timed GPS loss."""
        while self.scheduled and self.scheduled[0].at_s <= ap.t_s:
            f = self.scheduled.pop(0)
            log.info("vehicle: scheduled fault %s at %.1f s", f.kind, ap.t_s)
            if f.kind == "link_pause":
                self.pause_link(ap.t_s, f.duration_s or 0.0)
            elif f.kind == "gps_loss":
                self.lose_gps(ap, f.duration_s)
            elif f.kind == "low_battery":
                ap.set_battery_pct(f.battery_pct if f.battery_pct is not None else 10.0)
            elif f.kind == "reposition_refused":
                self.refuse_reposition(ap.t_s, f.duration_s)
        if self.gps_back_at_s is not None and ap.t_s >= self.gps_back_at_s:
            self.restore_gps(ap)
