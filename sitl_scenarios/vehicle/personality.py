"""Which autopilot the built-in vehicle is on the wire and in flight (`VehicleConfig.autopilot`):
the classes of its flight logic, streams and command answers, and its default stream intervals."""

from __future__ import annotations

from dataclasses import dataclass

from sitl_scenarios.vehicle.autopilot import Autopilot
from sitl_scenarios.vehicle.commands import CommandProtocol
from sitl_scenarios.vehicle.streams import DEFAULT_INTERVALS_S, StreamEncoder
from uavloc.errors import SimulatorError


@dataclass(frozen=True)
class Personality:
    autopilot: type[Autopilot]
    streams: type[StreamEncoder]
    commands: type[CommandProtocol]
    intervals_s: dict[int, float | None]


def personality(name: str) -> Personality:
    """"px4" (the default) or "ardupilot" (ArduCopter, sitl_scenarios.vehicle.ardupilot)."""
    if name == "px4":
        return Personality(Autopilot, StreamEncoder, CommandProtocol, DEFAULT_INTERVALS_S)
    if name == "ardupilot":
        from sitl_scenarios.vehicle import ardupilot

        return Personality(ardupilot.ArduCopter, ardupilot.ArduPilotStreams, ardupilot.ArduPilotCommands,
                           ardupilot.DEFAULT_INTERVALS_S)
    raise SimulatorError(f"unknown autopilot personality {name!r} (px4, ardupilot)")
