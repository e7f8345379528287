"""The built-in vehicle's scheduled faults as a scenario's `[[faults.vehicle]]` tables give them
(read strictly when the scenario loads; the simulator's fault state is sitl_scenarios.vehicle.faults)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from uavloc.errors import ScenarioError

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
