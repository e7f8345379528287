"""The built-in vehicle's parameter table: PX4 names and defaults, MAV_PARAM_TYPE, PX4's
byte-wise encoding of INT32 values on the wire. Pure data and pure functions."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from uavloc.errors import SimulatorError

PARAM_TYPE_INT32 = mavlink.MAV_PARAM_TYPE_INT32
PARAM_TYPE_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32


@dataclass(frozen=True)
class ParamSpec:
    """One autopilot parameter: name (≤ 16 chars), MAV_PARAM_TYPE, PX4 default, meaning here."""

    name: str
    type: int
    default: float
    doc: str


def encode_param_value(value: float, param_type: int, bytewise: bool = True) -> float:
    """PARAM_VALUE.param_value with PX4's byte-wise encoding: an INT32 travels as the float whose
    four bytes are the integer's bytes (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE); without
    `bytewise`, ArduPilot's C cast: the integer's value as a float (PARAM_ENCODE_C_CAST)."""
    if param_type == PARAM_TYPE_INT32 and bytewise:
        return struct.unpack("<f", struct.pack("<i", int(value)))[0]
    if param_type in (PARAM_TYPE_REAL32, PARAM_TYPE_INT32):
        return float(value)
    raise SimulatorError(f"unsupported MAV_PARAM_TYPE {param_type} (only INT32 and REAL32)")


def decode_param_value(wire_value: float, param_type: int, bytewise: bool = True) -> float:
    """Inverse of :func:`encode_param_value`."""
    if param_type == PARAM_TYPE_INT32 and not bytewise:
        return float(round(wire_value))
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
        ParamSpec("MPC_JERK_AUTO", f, 4.0, "jerk limit of the auto-mode trajectory (horizontal) [m/s³]"),
        ParamSpec("MPC_XY_ERR_MAX", f, 2.0, "the trajectory slows down when the vehicle lags it by this [m]"),
        ParamSpec("MPC_XY_P", f, 0.95, "horizontal position gain [1/s]"),
        ParamSpec("MPC_XY_VEL_P_ACC", f, 1.8, "horizontal velocity gain [m/s² per m/s]"),
        ParamSpec("MPC_XY_VEL_I_ACC", f, 0.4, "horizontal velocity integral gain [m/s² per m]"),
        ParamSpec("MPC_XY_VEL_D_ACC", f, 0.2, "horizontal velocity derivative gain [m/s² per m/s²]"),
        ParamSpec("MPC_TILTMAX_AIR", f, 45.0, "largest tilt in the air [deg]"),
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
        ParamSpec("MAV_TYPE", i, mavlink.MAV_TYPE_QUADROTOR, "MAV_TYPE_QUADROTOR (identity only)"),
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
