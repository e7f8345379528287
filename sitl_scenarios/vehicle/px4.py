"""What makes the built-in vehicle look like PX4 on the wire (docs/design.md §9): custom-mode encoding,
autopilot capabilities and version. Pure data and pure functions; no sockets, no clocks.

The numbers come from pymavlink: PX4's main and sub modes from `pymavlink.mavutil`
(`PX4_CUSTOM_MAIN_MODE_*`, `PX4_CUSTOM_SUB_MODE_*`, and its mode table `mavutil.px4_map`:
name -> (base_mode, main_mode, sub_mode)), flags and capability bits from `common.xml`.

PX4 custom mode (PX4 `px4_custom_mode.h`): HEARTBEAT.custom_mode is a little-endian union
`{uint16 reserved; uint8 main_mode; uint8 sub_mode}`, so

    custom_mode = (sub_mode << 24) | (main_mode << 16)
"""

from __future__ import annotations

import enum

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

# --- PX4 custom modes (pymavlink's copy of px4_custom_mode.h) ------------------------------------
MAIN_MANUAL = mavutil.PX4_CUSTOM_MAIN_MODE_MANUAL
MAIN_ALTCTL = mavutil.PX4_CUSTOM_MAIN_MODE_ALTCTL
MAIN_POSCTL = mavutil.PX4_CUSTOM_MAIN_MODE_POSCTL
MAIN_AUTO = mavutil.PX4_CUSTOM_MAIN_MODE_AUTO
MAIN_ACRO = mavutil.PX4_CUSTOM_MAIN_MODE_ACRO
MAIN_OFFBOARD = mavutil.PX4_CUSTOM_MAIN_MODE_OFFBOARD
MAIN_STABILIZED = mavutil.PX4_CUSTOM_MAIN_MODE_STABILIZED

SUB_AUTO_READY = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_READY
SUB_AUTO_TAKEOFF = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_TAKEOFF
SUB_AUTO_LOITER = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LOITER
SUB_AUTO_MISSION = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_MISSION
SUB_AUTO_RTL = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_RTL
SUB_AUTO_LAND = mavutil.PX4_CUSTOM_SUB_MODE_AUTO_LAND

# MAV_MODE_FLAG bits (common.xml)
MODE_FLAG_CUSTOM_MODE_ENABLED = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
MODE_FLAG_AUTO_ENABLED = mavlink.MAV_MODE_FLAG_AUTO_ENABLED
MODE_FLAG_GUIDED_ENABLED = mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
MODE_FLAG_STABILIZE_ENABLED = mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
MODE_FLAG_MANUAL_INPUT_ENABLED = mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
MODE_FLAG_SAFETY_ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED


class FlightMode(enum.Enum):
    """The flight modes the built-in vehicle flies, named like MAVSDK's `FlightMode`."""

    HOLD = "hold"  # AUTO.LOITER; also where POSCTL/ALTCTL land without sticks
    TAKEOFF = "takeoff"
    LAND = "land"
    RTL = "return_to_launch"
    MISSION = "mission"
    OFFBOARD = "offboard"
    POSCTL = "posctl"


#: the name of each flight mode in pymavlink's PX4 mode table (`mavutil.px4_map`)
_PX4_MAP_NAME: dict[FlightMode, str] = {
    FlightMode.HOLD: "LOITER",
    FlightMode.TAKEOFF: "TAKEOFF",
    FlightMode.LAND: "LAND",
    FlightMode.RTL: "RTL",
    FlightMode.MISSION: "MISSION",
    FlightMode.OFFBOARD: "OFFBOARD",
    FlightMode.POSCTL: "POSCTL",
}
#: FlightMode -> (base_mode without the armed flag, main_mode, sub_mode), from pymavlink's table
_MODE_TO_PX4: dict[FlightMode, tuple[int, int, int]] = {
    mode: tuple(mavutil.px4_map[name]) for mode, name in _PX4_MAP_NAME.items()
}
_PX4_TO_MODE = {(main, sub): mode for mode, (_, main, sub) in _MODE_TO_PX4.items()}


def px4_custom_mode(mode: FlightMode) -> int:
    """HEARTBEAT.custom_mode of a flight mode: (sub << 24) | (main << 16)."""
    _, main, sub = _MODE_TO_PX4[mode]
    return (sub << 24) | (main << 16)


def px4_main_sub(custom_mode: int) -> tuple[int, int]:
    """(main_mode, sub_mode) of a PX4 custom_mode word."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def mode_from_px4(main: int, sub: int) -> FlightMode | None:
    """The flight mode of a PX4 (main, sub) pair, or None when the simulator does not fly it.

    An AUTO main mode with sub mode 0 is taken as Hold (PX4 does the same when a GCS sets AUTO
    without a sub mode). ALTCTL is flown as POSCTL: neither has sticks here, both hold position.
    """
    if main == MAIN_AUTO and sub == 0:
        return FlightMode.HOLD
    if main == MAIN_ALTCTL:
        return FlightMode.POSCTL
    if main in (MAIN_POSCTL, MAIN_OFFBOARD):
        sub = 0
    return _PX4_TO_MODE.get((main, sub))


def px4_base_mode(mode: FlightMode, armed: bool) -> int:
    """HEARTBEAT.base_mode PX4 sends for a mode: pymavlink's table (custom mode enabled plus the
    classic flags: stabilize, guided and auto, or manual input for POSCTL), armed flag added."""
    flags = _MODE_TO_PX4[mode][0]
    if armed:
        flags |= MODE_FLAG_SAFETY_ARMED
    return flags


# --- AUTOPILOT_VERSION --------------------------------------------------------------------------
# MAV_PROTOCOL_CAPABILITY bits PX4 sets, minus the ones the simulator does not implement
# (FTP, SET_ATTITUDE_TARGET, SET_ACTUATOR_TARGET, FLIGHT_TERMINATION, COMPASS_CALIBRATION).
CAP_MISSION_FLOAT = mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
CAP_PARAM_FLOAT = mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
CAP_MISSION_INT = mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
CAP_COMMAND_INT = mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
CAP_PARAM_ENCODE_BYTEWISE = mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
CAP_SET_POSITION_TARGET_LOCAL_NED = mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
CAP_SET_POSITION_TARGET_GLOBAL_INT = mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
CAP_MAVLINK2 = mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
CAP_MISSION_FENCE = mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
CAP_MISSION_RALLY = mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY

PX4_CAPABILITIES = (
    CAP_MISSION_FLOAT
    | CAP_PARAM_FLOAT
    | CAP_MISSION_INT
    | CAP_COMMAND_INT
    | CAP_PARAM_ENCODE_BYTEWISE
    | CAP_SET_POSITION_TARGET_LOCAL_NED
    | CAP_SET_POSITION_TARGET_GLOBAL_INT
    | CAP_MAVLINK2
    | CAP_MISSION_FENCE
    | CAP_MISSION_RALLY
)

FIRMWARE_VERSION_TYPE_OFFICIAL = mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL


def px4_sw_version(major: int, minor: int, patch: int) -> int:
    """AUTOPILOT_VERSION.flight_sw_version: (major << 24) | (minor << 16) | (patch << 8) | type."""
    return (major << 24) | (minor << 16) | (patch << 8) | FIRMWARE_VERSION_TYPE_OFFICIAL


PX4_VERSION = (1, 15, 4)
