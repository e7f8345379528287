"""What makes the built-in vehicle look like PX4 on the wire (DESIGN.md §9): custom-mode encoding,
autopilot capabilities and version, the parameter table and its byte-wise encoding.

Pure data and pure functions; no sockets, no clocks.

PX4 custom mode (PX4 `px4_custom_mode.h`): HEARTBEAT.custom_mode is a little-endian union
`{uint16 reserved; uint8 main_mode; uint8 sub_mode}`, so

    custom_mode = (sub_mode << 24) | (main_mode << 16)

main modes MANUAL=1, ALTCTL=2, POSCTL=3, AUTO=4, ACRO=5, OFFBOARD=6, STABILIZED=7; AUTO sub modes
READY=1, TAKEOFF=2, LOITER=3 (MAVSDK "Hold"), MISSION=4, RTL=5, LAND=6.
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass

from uavloc.errors import SimulatorError

# --- PX4 custom modes -------------------------------------------------------------------------
MAIN_MANUAL = 1
MAIN_ALTCTL = 2
MAIN_POSCTL = 3
MAIN_AUTO = 4
MAIN_ACRO = 5
MAIN_OFFBOARD = 6
MAIN_STABILIZED = 7

SUB_AUTO_READY = 1
SUB_AUTO_TAKEOFF = 2
SUB_AUTO_LOITER = 3
SUB_AUTO_MISSION = 4
SUB_AUTO_RTL = 5
SUB_AUTO_LAND = 6

# MAV_MODE_FLAG bits (common.xml)
MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MODE_FLAG_AUTO_ENABLED = 4
MODE_FLAG_GUIDED_ENABLED = 8
MODE_FLAG_STABILIZE_ENABLED = 16
MODE_FLAG_MANUAL_INPUT_ENABLED = 64
MODE_FLAG_SAFETY_ARMED = 128


class FlightMode(enum.Enum):
    """The flight modes the built-in vehicle flies, named like MAVSDK's `FlightMode`."""

    HOLD = "hold"  # AUTO.LOITER; also where POSCTL/ALTCTL land without sticks
    TAKEOFF = "takeoff"
    LAND = "land"
    RTL = "return_to_launch"
    MISSION = "mission"
    OFFBOARD = "offboard"
    POSCTL = "posctl"


_MODE_TO_PX4: dict[FlightMode, tuple[int, int]] = {
    FlightMode.HOLD: (MAIN_AUTO, SUB_AUTO_LOITER),
    FlightMode.TAKEOFF: (MAIN_AUTO, SUB_AUTO_TAKEOFF),
    FlightMode.LAND: (MAIN_AUTO, SUB_AUTO_LAND),
    FlightMode.RTL: (MAIN_AUTO, SUB_AUTO_RTL),
    FlightMode.MISSION: (MAIN_AUTO, SUB_AUTO_MISSION),
    FlightMode.OFFBOARD: (MAIN_OFFBOARD, 0),
    FlightMode.POSCTL: (MAIN_POSCTL, 0),
}
_PX4_TO_MODE = {v: k for k, v in _MODE_TO_PX4.items()}


def px4_custom_mode(mode: FlightMode) -> int:
    """HEARTBEAT.custom_mode of a flight mode: (sub << 24) | (main << 16)."""
    main, sub = _MODE_TO_PX4[mode]
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
    """HEARTBEAT.base_mode PX4 sends for a mode (custom mode enabled plus the classic flags)."""
    flags = MODE_FLAG_CUSTOM_MODE_ENABLED | MODE_FLAG_STABILIZE_ENABLED
    if mode is FlightMode.POSCTL:
        flags |= MODE_FLAG_MANUAL_INPUT_ENABLED
    else:
        flags |= MODE_FLAG_GUIDED_ENABLED | MODE_FLAG_AUTO_ENABLED
    if armed:
        flags |= MODE_FLAG_SAFETY_ARMED
    return flags


# --- AUTOPILOT_VERSION --------------------------------------------------------------------------
# MAV_PROTOCOL_CAPABILITY bits PX4 sets, minus the ones the simulator does not implement
# (FTP, SET_ATTITUDE_TARGET, SET_ACTUATOR_TARGET, FLIGHT_TERMINATION, COMPASS_CALIBRATION).
CAP_MISSION_FLOAT = 1
CAP_PARAM_FLOAT = 2
CAP_MISSION_INT = 4
CAP_COMMAND_INT = 8
CAP_PARAM_ENCODE_BYTEWISE = 16
CAP_SET_POSITION_TARGET_LOCAL_NED = 128
CAP_SET_POSITION_TARGET_GLOBAL_INT = 256
CAP_MAVLINK2 = 8192
CAP_MISSION_FENCE = 16384
CAP_MISSION_RALLY = 32768

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

FIRMWARE_VERSION_TYPE_OFFICIAL = 255


def px4_sw_version(major: int, minor: int, patch: int) -> int:
    """AUTOPILOT_VERSION.flight_sw_version: (major << 24) | (minor << 16) | (patch << 8) | type."""
    return (major << 24) | (minor << 16) | (patch << 8) | FIRMWARE_VERSION_TYPE_OFFICIAL


PX4_VERSION = (1, 15, 4)


# --- parameters ---------------------------------------------------------------------------------
PARAM_TYPE_INT32 = 6  # MAV_PARAM_TYPE_INT32
PARAM_TYPE_REAL32 = 9  # MAV_PARAM_TYPE_REAL32


@dataclass(frozen=True)
class ParamSpec:
    """One autopilot parameter: name (≤ 16 chars), MAV_PARAM_TYPE, PX4 default, meaning here."""

    name: str
    type: int
    default: float
    doc: str


def encode_param_value(value: float, param_type: int) -> float:
    """PARAM_VALUE.param_value with PX4's byte-wise encoding: an INT32 travels as the float whose
    four bytes are the integer's bytes (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE)."""
    if param_type == PARAM_TYPE_INT32:
        return struct.unpack("<f", struct.pack("<i", int(value)))[0]
    if param_type == PARAM_TYPE_REAL32:
        return float(value)
    raise SimulatorError(f"unsupported MAV_PARAM_TYPE {param_type} (only INT32 and REAL32)")


def decode_param_value(wire_value: float, param_type: int) -> float:
    """Inverse of :func:`encode_param_value`."""
    if param_type == PARAM_TYPE_INT32:
        return float(struct.unpack("<i", struct.pack("<f", wire_value))[0])
    if param_type == PARAM_TYPE_REAL32:
        return float(wire_value)
    raise SimulatorError(f"unsupported MAV_PARAM_TYPE {param_type} (only INT32 and REAL32)")


def px4_params(speed_mps: float, climb_mps: float, descent_mps: float, accel_mps2: float) -> list[ParamSpec]:
    """The parameters the built-in vehicle has, PX4 names and defaults; speeds from the scenario.

    Every REAL32/INT32 listed here is read by the simulator (changing it changes the flight) except
    the identity ones at the end, which exist because ground stations read them.
    """
    f, i = PARAM_TYPE_REAL32, PARAM_TYPE_INT32
    return [
        ParamSpec("MIS_TAKEOFF_ALT", f, 2.5, "takeoff height above home when the command gives none [m]"),
        # RTL defaults of PX4 SITL (v1.18-dev, SIH quadrotor; read from the real bundle): return at
        # max(current height, RTL_RETURN_ALT), lower only inside the cone near home (rtl_return_height_m)
        ParamSpec("RTL_RETURN_ALT", f, 30.0, "RTL: climb to at least this height above home [m]"),
        ParamSpec("RTL_DESCEND_ALT", f, 10.0, "RTL: descend to this height above home before landing [m]"),
        ParamSpec("RTL_CONE_ANG", i, 45, "RTL: half angle of the return cone above home, 0 off [deg]"),
        ParamSpec("RTL_MIN_DIST", f, 10.0, "RTL: the cone applies within this distance of home [m]"),
        ParamSpec("RTL_LAND_DELAY", f, 0.0, "RTL: hover this long at RTL_DESCEND_ALT, < 0 forever [s]"),
        # PX4's default cruise: the mission's speed reaches the vehicle as DO_CHANGE_SPEED, as on PX4
        ParamSpec("MPC_XY_CRUISE", f, 5.0, "horizontal speed in auto modes [m/s]"),
        ParamSpec("MPC_XY_VEL_MAX", f, max(12.0, speed_mps), "horizontal speed limit [m/s]"),
        ParamSpec("MPC_Z_V_AUTO_UP", f, climb_mps, "climb rate in auto modes [m/s]"),
        ParamSpec("MPC_Z_V_AUTO_DN", f, descent_mps, "descent rate in auto modes [m/s]"),
        ParamSpec("MPC_TKO_SPEED", f, min(1.5, climb_mps), "takeoff climb rate [m/s]"),
        ParamSpec("MPC_LAND_SPEED", f, min(0.7, descent_mps), "descent rate close to the ground [m/s]"),
        ParamSpec("MPC_LAND_ALT1", f, 10.0, "below this height the descent slows down [m]"),
        ParamSpec("MPC_LAND_ALT2", f, 5.0, "below this height descend at MPC_LAND_SPEED [m]"),
        ParamSpec("MPC_ACC_HOR", f, accel_mps2, "horizontal acceleration limit [m/s²]"),
        ParamSpec("MPC_ACC_UP_MAX", f, 4.0, "upward acceleration limit [m/s²]"),
        ParamSpec("MPC_ACC_DOWN_MAX", f, 3.0, "downward acceleration limit [m/s²]"),
        ParamSpec("NAV_ACC_RAD", f, 2.0, "mission waypoint acceptance radius [m]"),
        ParamSpec("NAV_MC_ALT_RAD", f, 0.8, "mission waypoint altitude acceptance [m]"),
        ParamSpec("COM_DISARM_LAND", f, 2.0, "disarm this long after landing, < 0 never [s]"),
        ParamSpec("COM_DISARM_PRFLT", f, 10.0, "disarm when armed on the ground without takeoff [s]"),
        ParamSpec("COM_OF_LOSS_T", f, 1.0, "offboard setpoints older than this are lost (wall) [s]"),
        ParamSpec("COM_LOW_BAT_ACT", i, 0, "0 warn, 1 RTL at critical, 2 land at emergency, 3 both"),
        ParamSpec("BAT_LOW_THR", f, 0.15, "low battery threshold [fraction]"),
        ParamSpec("BAT_CRIT_THR", f, 0.07, "critical battery threshold [fraction]"),
        ParamSpec("BAT_EMERGEN_THR", f, 0.05, "emergency battery threshold [fraction]"),
        ParamSpec("BAT1_N_CELLS", i, 4, "battery cells in series (voltage only)"),
        ParamSpec("NAV_DLL_ACT", i, 0, "data link loss action: 0 none (the only one simulated)"),
        ParamSpec("COM_RC_IN_MODE", i, 4, "4: no RC (the simulator has none)"),
        ParamSpec("MAV_SYS_ID", i, 1, "MAVLink system id (identity only)"),
        ParamSpec("MAV_COMP_ID", i, 1, "MAVLink component id (identity only)"),
        ParamSpec("MAV_TYPE", i, 2, "MAV_TYPE_QUADROTOR (identity only)"),
        ParamSpec("SYS_AUTOSTART", i, 4001, "airframe: generic quadcopter (identity only)"),
        ParamSpec("SYS_HITL", i, 0, "not hardware-in-the-loop (identity only)"),
        ParamSpec("CAL_GYRO0_ID", i, 1310988, "calibrated gyro id (identity only)"),
        ParamSpec("CAL_ACC0_ID", i, 1310988, "calibrated accelerometer id (identity only)"),
        ParamSpec("CAL_MAG0_ID", i, 197388, "calibrated magnetometer id (identity only)"),
    ]


class ParamStore:
    """The parameter table: ordered (PARAM_VALUE.param_index), typed, values kept as floats."""

    def __init__(self, specs: list[ParamSpec]) -> None:
        self._specs = list(specs)
        self._index = {s.name: k for k, s in enumerate(self._specs)}
        self._values = [float(s.default) for s in self._specs]
        for s in self._specs:
            if len(s.name) > 16:
                raise SimulatorError(f"parameter name longer than 16 characters: {s.name!r}")

    def __len__(self) -> int:
        return len(self._specs)

    def __contains__(self, name: str) -> bool:
        return name in self._index

    def __getitem__(self, name: str) -> float:
        try:
            return self._values[self._index[name]]
        except KeyError as exc:
            raise SimulatorError(f"no parameter {name!r}") from exc

    def set(self, name: str, value: float) -> float:
        """Set a parameter (INT32 ones are rounded); returns the stored value."""
        k = self._index.get(name)
        if k is None:
            raise SimulatorError(f"no parameter {name!r}")
        if not math.isfinite(value):
            raise SimulatorError(f"parameter {name} must be finite, got {value!r}")
        spec = self._specs[k]
        self._values[k] = float(round(value)) if spec.type == PARAM_TYPE_INT32 else float(value)
        return self._values[k]

    def index_of(self, name: str) -> int | None:
        return self._index.get(name)

    def entry(self, index: int) -> tuple[ParamSpec, float]:
        """(spec, value) of the parameter at `index`; SimulatorError when out of range."""
        if not 0 <= index < len(self._specs):
            raise SimulatorError(f"parameter index {index} out of range 0..{len(self._specs) - 1}")
        return self._specs[index], self._values[index]
