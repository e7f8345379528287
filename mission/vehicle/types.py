"""The vehicle adapter's small types that its ArduPilot part shares with it
(mission.vehicle.mavsdk_vehicle, mission.vehicle.ardupilot): the command errors and a geodetic
point. Import them from mission.vehicle."""

from __future__ import annotations

from dataclasses import dataclass

from uavloc.errors import VehicleError


class VehicleCommandError(VehicleError):
    """A vehicle command was refused or failed; `result` is MAVSDK's result-code name."""

    def __init__(self, message: str, result: str = "UNKNOWN"):
        super().__init__(message)
        self.result = result


class VehicleTimeoutError(VehicleError):
    """The vehicle did not answer a request in time."""


@dataclass(frozen=True)
class GeoFix:
    """A geodetic point: latitude, longitude [deg], altitude AMSL [m]."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float


__all__ = ["GeoFix", "VehicleCommandError", "VehicleTimeoutError"]
