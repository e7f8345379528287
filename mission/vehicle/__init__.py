"""The vehicle adapter: one MAVSDK ``System`` per autopilot, and what it reads and sends.

- :mod:`mission.vehicle.mavsdk_vehicle`: :class:`MavsdkVehicle` (the adapter, PX4 and ArduPilot
  through MAVSDK), the :class:`Vehicle` protocol the controller flies, and its state;
- :mod:`mission.vehicle.ardupilot`: what MAVSDK does not do on ArduPilot (pymavlink messages
  through MavlinkDirect);
- :mod:`mission.vehicle.telemetry`: the telemetry ring buffer, odometer, clock and status;
- :mod:`mission.vehicle.types`: the command errors and a geodetic point.
"""

from mission.vehicle.mavsdk_vehicle import (
    MavsdkVehicle,
    PositionFix,
    Vehicle,
    VehicleState,
    vehicle_library_wedged,
)
from mission.vehicle.types import GeoFix, VehicleCommandError, VehicleTimeoutError

__all__ = ["GeoFix", "MavsdkVehicle", "PositionFix", "Vehicle", "VehicleCommandError", "VehicleState",
           "VehicleTimeoutError", "vehicle_library_wedged"]
