"""Faults of the built-in vehicle: the scenario's `[[faults.vehicle]]` events and the fault state
the simulator consults (link paused, GPS lost until, DO_REPOSITION refused until). Times are
simulated seconds."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from sitl_scenarios.vehicle.autopilot import Autopilot
from uavloc.errors import ScenarioError

log = logging.getLogger(__name__)

FAULT_KINDS = ("link_pause", "gps_loss", "low_battery", "reposition_refused")


@dataclass(frozen=True)
class FaultEvent:
    """A scheduled fault (scenario `[[faults.vehicle]]`): kind, simulated start time [s], duration
    [simulated s] (link_pause, gps_loss, reposition_refused; the last two last for ever without a
    duration), battery_pct (low_battery).

    reposition_refused: COMMAND_INT DO_REPOSITION is answered with MAV_RESULT 9 (unsupported frame),
    as the PX4 build before PX4 #26626 did; MAVSDK 4.1 reports UNKNOWN and then wedges."""

    kind: str
    at_s: float
    duration_s: float | None = None
    battery_pct: float | None = None


def faults_from_scenario(faults: dict[str, Any], where: str = "faults") -> list[FaultEvent]:
    """The vehicle's fault events from a scenario's free-form `[faults]` table (key `vehicle`).

    Other keys of `[faults]` belong to other simulators and are ignored here; inside `vehicle`
    every table is checked strictly.
    """
    raw = faults.get("vehicle", [])
    if not isinstance(raw, list):
        raise ScenarioError(f"{where}.vehicle: expected a list of tables ([[faults.vehicle]]), got {raw!r}")
    events = []
    allowed = {"kind", "at_s", "duration_s", "battery_pct"}
    for i, item in enumerate(raw):
        w = f"{where}.vehicle[{i}]"
        if not isinstance(item, dict):
            raise ScenarioError(f"{w}: expected a table, got {item!r}")
        unknown = sorted(set(item) - allowed)
        if unknown:
            raise ScenarioError(f"{w}: unknown key(s) {', '.join(map(repr, unknown))}; allowed: {sorted(allowed)}")
        kind = item.get("kind")
        if kind not in FAULT_KINDS:
            raise ScenarioError(f"{w}.kind must be one of {', '.join(FAULT_KINDS)}, got {kind!r}")
        nums = {}
        for key in ("at_s", "duration_s", "battery_pct"):
            v = item.get(key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)):
                raise ScenarioError(f"{w}.{key}: expected a finite number, got {v!r}")
            nums[key] = None if v is None else float(v)
        if nums["at_s"] is None or nums["at_s"] < 0:
            raise ScenarioError(f"{w}.at_s: a start time >= 0 [s] is required, got {nums['at_s']!r}")
        if kind == "link_pause" and not (nums["duration_s"] or 0) > 0:
            raise ScenarioError(f"{w}.duration_s: link_pause needs a positive duration, got {nums['duration_s']!r}")
        if nums["duration_s"] is not None and nums["duration_s"] <= 0:
            raise ScenarioError(f"{w}.duration_s must be positive, got {nums['duration_s']!r}")
        if kind == "low_battery" and (nums["battery_pct"] is None or not 0 <= nums["battery_pct"] <= 100):
            raise ScenarioError(f"{w}.battery_pct: low_battery needs a value in [0, 100], got {nums['battery_pct']!r}")
        events.append(FaultEvent(kind, nums["at_s"], nums["duration_s"], nums["battery_pct"]))
    return events


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
