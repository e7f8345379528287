"""The built-in vehicle's scheduled faults, a scenario's `[[faults.vehicle]]` tables (read by the one
strict loader when the scenario is; the simulator's fault state is sitl_scenarios.vehicle.faults).
Times are simulated seconds."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal, get_args

from mission import schema
from mission.schema import bounded
from uavloc.errors import ScenarioError

FaultKind = Literal["link_pause", "gps_loss", "low_battery", "reposition_refused"]
FAULT_KINDS: tuple[str, ...] = get_args(FaultKind)
#: the latest start and the longest duration of a fault [simulated s]
MAX_FAULT_TIME_S = 1e6


@dataclass(frozen=True)
class FaultEvent:
    """A scheduled fault (scenario `[[faults.vehicle]]`): kind, simulated start time [s], duration
    [simulated s] (link_pause, gps_loss, reposition_refused; the last two last for ever without a
    duration), battery_pct (low_battery).

    reposition_refused: COMMAND_INT DO_REPOSITION is answered with MAV_RESULT 9 (unsupported frame),
    as the PX4 build before PX4 #26626 did; MAVSDK 4.1 reports UNKNOWN and then wedges.
    vehicle: the id (`[[vehicles]]`) of the fleet's vehicle it strikes; empty: the first (or only)."""

    kind: FaultKind
    at_s: float = bounded(dataclasses.MISSING, 0.0, MAX_FAULT_TIME_S)
    duration_s: float | None = bounded(None, 0.0, MAX_FAULT_TIME_S, lo_open=True)
    battery_pct: float | None = bounded(None, 0.0, 100.0)
    vehicle: str = ""


def check_fault_event(ev: FaultEvent, where: str, key: str) -> None:
    """Raise ScenarioError unless the event's fields fit its kind (key: its key path, for messages)."""
    if ev.kind == "link_pause" and ev.duration_s is None:
        raise schema.fail(where, f"{key}.duration_s", None, "link_pause needs a positive duration", ScenarioError)
    if ev.kind == "low_battery" and ev.battery_pct is None:
        raise schema.fail(where, f"{key}.battery_pct", None, "low_battery needs a value in [0, 100]", ScenarioError)


def faults_from_scenario(faults: dict[str, Any], where: str = "faults") -> list[FaultEvent]:
    """The vehicle's fault events of a parsed `[faults]` table (key `vehicle`; other keys belong to
    other simulators), strictly."""
    raw = faults.get("vehicle", [])
    if not isinstance(raw, list):
        raise schema.fail(where, "vehicle", raw, "expected a list of tables ([[faults.vehicle]])", ScenarioError)
    events = []
    for i, item in enumerate(raw):
        ev = schema.build(FaultEvent, item, where, f"vehicle[{i}]", error=ScenarioError)
        check_fault_event(ev, where, f"vehicle[{i}]")
        events.append(ev)
    return events
