"""ArduCopter's personality of the built-in vehicle (`[vehicle] autopilot = "ardupilot"`).

What a ground station sees of ArduCopter (V4.7 SITL, recorded in
../shared/data/ardupilot-4.7-sitl/legs.tlog.gz; tests/test_ardupilot_conformance.py holds this
class to it): HEARTBEAT with MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_TYPE_QUADROTOR and ArduCopter's
custom modes (pymavlink `mavutil.mode_mapping_acm`: STABILIZE 0, AUTO 3, GUIDED 4, LOITER 5, RTL 6,
LAND 9), system status STANDBY on the ground and ACTIVE in the air; nothing but HEARTBEAT until a
ground station asks (REQUEST_DATA_STREAM or SET_MESSAGE_INTERVAL); EKF_STATUS_REPORT; GUIDED
take-off (NAV_TAKEOFF, relative altitude, armed only) and SET_POSITION_TARGET_GLOBAL_INT targets;
DO_CHANGE_SPEED; RTL at max(RTL_ALT, current height), a loiter of RTL_LOIT_TIME over home and a
landing at WPNAV_SPEED_DN then LAND_SPEED below LAND_ALT_LOW; disarmed in the mode it landed in; on
a GPS loss in the air the EKF failsafe lands at once (FS_EKF_ACTION 1). Its parameter names and
units (cm, cm/s, ms) on the wire, INT32 values C-cast.

The flight itself is the built-in multicopter's (:class:`~sitl_scenarios.vehicle.autopilot.Autopilot`
and :mod:`~sitl_scenarios.vehicle.kinematics`) driven by ArduCopter's parameters: the PX4 names the
shared flight logic reads are answered from ArduCopter's (:class:`ArduPilotParams`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega
from pymavlink.dialects.v20 import common as mavlink

from sitl_scenarios.scenario import VehicleConfig
from sitl_scenarios.vehicle import kinematics
from sitl_scenarios.vehicle.autopilot import Autopilot
from sitl_scenarios.vehicle.commands import CommandProtocol
from sitl_scenarios.vehicle.mav import (
    ACCEPTED,
    CHARGE_EMERGENCY,
    CMD_DO_REPOSITION,
    CMD_DO_SET_MODE,
    CMD_NAV_LAND,
    CMD_NAV_RETURN_TO_LAUNCH,
    CMD_NAV_TAKEOFF,
    DENIED,
    FAILED,
    FRAME_LOCAL_NED,
    SEV_CRITICAL,
    UNSUPPORTED,
)
from sitl_scenarios.vehicle.params import PARAM_TYPE_INT32, PARAM_TYPE_REAL32, ParamSpec, ParamStore
from sitl_scenarios.vehicle.px4 import FlightMode
from sitl_scenarios.vehicle.streams import StreamEncoder
from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

# --- ArduCopter's custom modes (pymavlink's table of ArduCopter's mode numbers) ------------------
_ACM = {name: number for number, name in mavutil.mode_mapping_acm.items()}
STABILIZE, AUTO, GUIDED, LOITER, RTL, LAND = (_ACM[n] for n in ("STABILIZE", "AUTO", "GUIDED", "LOITER", "RTL",
                                                                 "LAND"))
#: the internal flight mode each ArduCopter mode is flown as (GUIDED and LOITER both hold a target)
_FLOWN_AS = {STABILIZE: FlightMode.POSCTL, AUTO: FlightMode.MISSION, GUIDED: FlightMode.HOLD,
             LOITER: FlightMode.HOLD, RTL: FlightMode.RTL, LAND: FlightMode.LAND}
#: modes ArduCopter arms in (the rest: "Arm: Mode not armable")
_ARMABLE = (STABILIZE, GUIDED, LOITER, AUTO)
#: modes in which ArduCopter's HEARTBEAT sets MAV_MODE_FLAG_GUIDED_ENABLED (ArduCopter's
#: GCS_MAVLINK_Copter::base_mode; the recording: GUIDED and RTL 89/217, STABILIZE 81)
_GUIDED_FLAG_MODES = (AUTO, GUIDED, LOITER, RTL)
BASE_MODE_ALWAYS = (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
                    | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED)

# --- timing of the recorded ArduCopter (simulated seconds) --------------------------------------
#: from the first GPS fix to the EKF origin and home ("EKF3 IMU0 origin set": 10 s after the fix)
ORIGIN_AFTER_FIX_S = 10.0
#: from the first GPS fix to "EKF3 IMU0 is using GPS" (31.4 s in the recording): no global position
#: (EKF_STATUS_REPORT without POS_HORIZ_ABS, arming refused) before
EKF_GPS_AFTER_FIX_S = 31.4
#: from NAV_TAKEOFF to leaving the ground: the motors spool up (3.1 s in the recording)
TAKEOFF_SPOOL_S = 3.1
#: the take-off's approach to its height: v = sqrt(2 · a · height to go), a [m/s²] fitted to the
#: recorded climb (2.5 m/s until about 6 m below, 1.2 m/s 1.3 m below)
TAKEOFF_APPROACH_MPS2 = 0.55
#: from touchdown ("SIM Hit ground") to "land complete" (system status STANDBY, still armed) and on to
#: "Disarming motors": 2.1 s in all in the recording, STANDBY seen 1.6 s after the touchdown
LAND_COMPLETE_S = 1.0
DISARM_AFTER_LAND_S = 1.1
#: ArduCopter approaches a position target on a square-root speed law (AP_Math sqrt_controller),
#: fitted to the recorded legs (2.6 m/s² up to speed, about 1.1 m/s² down from it, and through the
#: target at about 0.8 m/s, overshooting it by 0.5-0.9 m):
#:     v(d) = sqrt(2 · a · (d + BRAKE_THROUGH_M)),   a = BRAKE_FRACTION · WPNAV_ACCEL
#: d the horizontal distance to go [m]
BRAKE_FRACTION = 0.44
BRAKE_THROUGH_M = 0.3
#: the jerk limit [m/s³] of the shared (PX4) trajectory under that law: high, so that the law and
#: not PX4's jerk-limited braking shapes the approach
TRAJECTORY_JERK_MPS3 = 40.0

# EKF_STATUS_REPORT flags (ardupilotmega.xml EKF_STATUS_FLAGS)
EKF_USING_GPS = (ardupilotmega.EKF_ATTITUDE | ardupilotmega.EKF_VELOCITY_HORIZ | ardupilotmega.EKF_VELOCITY_VERT
                 | ardupilotmega.EKF_POS_HORIZ_REL | ardupilotmega.EKF_POS_HORIZ_ABS | ardupilotmega.EKF_POS_VERT_ABS
                 | ardupilotmega.EKF_PRED_POS_HORIZ_REL | ardupilotmega.EKF_PRED_POS_HORIZ_ABS)  # 0x33f
EKF_NO_GPS = (ardupilotmega.EKF_ATTITUDE | ardupilotmega.EKF_VELOCITY_HORIZ | ardupilotmega.EKF_VELOCITY_VERT
              | ardupilotmega.EKF_POS_VERT_ABS | ardupilotmega.EKF_CONST_POS_MODE)  # 0xa7
EKF_BOOT = ardupilotmega.EKF_UNINITIALIZED  # 0x400


def ardupilot_params() -> list[ParamSpec]:
    """ArduCopter's parameters the built-in vehicle flies by, with ArduCopter's names, units and
    defaults (ArduCopter 4.x; the recording's RTL at 20 m, above RTL_ALT, says RTL_ALT ≤ 20 m)."""
    f, i = PARAM_TYPE_REAL32, PARAM_TYPE_INT32
    return [
        ParamSpec("WPNAV_SPEED", f, 1000.0, "horizontal speed in GUIDED, AUTO and RTL [cm/s]"),
        ParamSpec("WPNAV_SPEED_UP", f, 250.0, "climb rate [cm/s]"),
        ParamSpec("WPNAV_SPEED_DN", f, 150.0, "descent rate [cm/s]"),
        ParamSpec("WPNAV_ACCEL", f, 250.0, "horizontal acceleration [cm/s²]"),
        ParamSpec("WPNAV_ACCEL_Z", f, 100.0, "vertical acceleration [cm/s²]"),
        ParamSpec("WPNAV_RADIUS", f, 200.0, "waypoint radius [cm]"),
        ParamSpec("PSC_POSXY_P", f, 1.0, "horizontal position gain [1/s]"),
        ParamSpec("PSC_VELXY_P", f, 2.0, "horizontal velocity gain [1/s]"),
        ParamSpec("PSC_VELXY_I", f, 1.0, "horizontal velocity integral gain [1/s²]"),
        ParamSpec("RTL_ALT", i, 1500, "RTL: return at least this high above home [cm]"),
        ParamSpec("RTL_ALT_FINAL", i, 0, "RTL: final height above home, 0 lands [cm]"),
        ParamSpec("RTL_LOIT_TIME", i, 5000, "RTL: loiter over home before landing [ms]"),
        ParamSpec("RTL_SPEED", i, 0, "RTL: horizontal speed, 0 WPNAV_SPEED [cm/s]"),
        ParamSpec("RTL_CONE_SLOPE", f, 3.0, "RTL: the return height is at most slope x distance, 0 off"),
        ParamSpec("LAND_SPEED", i, 50, "landing descent rate below LAND_ALT_LOW [cm/s]"),
        ParamSpec("LAND_SPEED_HIGH", i, 0, "landing descent rate above LAND_ALT_LOW, 0 WPNAV_SPEED_DN [cm/s]"),
        ParamSpec("LAND_ALT_LOW", i, 1000, "the landing slows to LAND_SPEED below this height [cm]"),
        ParamSpec("PILOT_TKOFF_ALT", f, 0.0, "take-off height of a take-off without one [cm]"),
        ParamSpec("DISARM_DELAY", i, 10, "disarm when armed on the ground without take-off, 0 never [s]"),
        ParamSpec("FS_EKF_ACTION", i, 1, "EKF failsafe: 1 land (the only one simulated)"),
        ParamSpec("BATT_FS_LOW_ACT", i, 0, "battery failsafe action: 0 warn (the only one simulated)"),
        ParamSpec("SYSID_THISMAV", i, 1, "MAVLink system id (identity only)"),
        ParamSpec("FRAME_CLASS", i, 1, "quad (identity only)"),
        ParamSpec("FRAME_TYPE", i, 0, "plus, the recording's model `+` (identity only)"),
    ]


def _cm(name: str) -> Callable[[ParamStore], float]:
    return lambda p: p[name] / 100.0


#: the PX4 parameter names the shared flight logic reads, answered from ArduCopter's parameters
#: (a callable of the store) or a constant where ArduCopter has no parameter for it
_PX4_MODEL: dict[str, float | Callable[[ParamStore], float]] = {
    "MPC_XY_CRUISE": _cm("WPNAV_SPEED"),
    "MPC_XY_VEL_MAX": 20.0,
    "MPC_Z_V_AUTO_UP": _cm("WPNAV_SPEED_UP"),
    "MPC_Z_V_AUTO_DN": _cm("WPNAV_SPEED_DN"),
    "MPC_TKO_SPEED": _cm("WPNAV_SPEED_UP"),
    "MPC_LAND_SPEED": _cm("LAND_SPEED"),
    "MPC_LAND_ALT1": _cm("LAND_ALT_LOW"),
    "MPC_LAND_ALT2": _cm("LAND_ALT_LOW"),
    "MPC_ACC_HOR": _cm("WPNAV_ACCEL"),
    "MPC_ACC_UP_MAX": _cm("WPNAV_ACCEL_Z"),
    "MPC_ACC_DOWN_MAX": _cm("WPNAV_ACCEL_Z"),
    "MIS_TAKEOFF_ALT": lambda p: max(p["PILOT_TKOFF_ALT"] / 100.0, 1.0),
    "NAV_ACC_RAD": _cm("WPNAV_RADIUS"),
    "NAV_MC_ALT_RAD": 0.8,
    # RTL (navigator): ArduCopter loiters RTL_LOIT_TIME at its return height over home, then lands
    "RTL_DESCEND_ALT": math.inf,
    "RTL_LAND_DELAY": lambda p: p["RTL_LOIT_TIME"] / 1000.0,
    "COM_DISARM_LAND": DISARM_AFTER_LAND_S,
    "COM_DISARM_PRFLT": lambda p: p["DISARM_DELAY"] if p["DISARM_DELAY"] > 0 else -1.0,
    "COM_OF_LOSS_T": 1.0,
    "COM_LOW_BAT_ACT": 0,
    "BAT_LOW_THR": 0.15,
    "BAT_CRIT_THR": 0.07,
    "BAT_EMERGEN_THR": 0.05,
    "BAT1_N_CELLS": 3,  # the recording's 12.6 V full
}


class ArduPilotParams(ParamStore):
    """ArduCopter's parameter table on the wire; reading a PX4 name the shared flight logic uses
    gives its value from ArduCopter's (:data:`_PX4_MODEL`)."""

    def __getitem__(self, name: str) -> float:
        if name in self:
            return super().__getitem__(name)
        model = _PX4_MODEL.get(name)
        if model is None:
            raise SimulatorError(f"no parameter {name!r}")
        return float(model(self) if callable(model) else model)


#: what PX4 says that ArduCopter says otherwise (None: says nothing there)
_TEXTS: dict[str, str | None] = {
    "Armed by external command": "Arming motors",
    "Disarmed after landing": "Disarming motors",
    "Disarmed by external command": "Disarming motors",
    "Disarmed: no takeoff": "Disarming motors",
    "Takeoff finished, holding": None,
    "Landing detected": None,
    "Home position set": None,
    "GPS lost: dead reckoning": None,
    "GPS fix regained": None,
    "RTL: landing at home": None,
}


def approach_speed_mps(distance_m: float, accel_mps2: float) -> float:
    """ArduCopter's square-root speed law towards a target [m/s] (see BRAKE_FRACTION)."""
    return math.sqrt(2.0 * accel_mps2 * (max(distance_m, 0.0) + BRAKE_THROUGH_M))


class ArduCopter(Autopilot):
    """ArduCopter's flight logic over the built-in multicopter (module docstring).

    :attr:`custom_mode` is the ArduCopter mode the HEARTBEAT reports; :attr:`mode` the internal
    flight mode it is flown as.
    """

    INITIAL_MODE = FlightMode.POSCTL  # STABILIZE
    MODE_AFTER_LANDING = None  # disarmed in RTL / LAND (the recording)
    LAND_DETECT_S = LAND_COMPLETE_S
    PARAM_BYTEWISE = False

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.custom_mode = STABILIZE
        self.ekf_failsafe = False
        self._takeoff_cmd_s: float | None = None

    @staticmethod
    def _param_store(vehicle: VehicleConfig) -> ParamStore:
        return ArduPilotParams(ardupilot_params())

    # --- derived state ------------------------------------------------------------------------
    @property
    def ekf_using_gps(self) -> bool:
        return self.gps_ok and self.t_s >= self.gps_fix_delay_s + EKF_GPS_AFTER_FIX_S

    @property
    def position_valid(self) -> bool:
        """The EKF has a global position once it uses GPS; after a loss it dead-reckons, except in
        the EKF failsafe: ArduCopter's Copter::position_ok() is false while failsafe.ekf is set,
        so the LAND it switched to cannot be changed to GUIDED, AUTO or RTL."""
        return (not self.ekf_failsafe and super().position_valid
                and self.t_s >= self.gps_fix_delay_s + EKF_GPS_AFTER_FIX_S)

    def _home_ready(self) -> bool:
        return self.gps_ok and self.t_s >= self.gps_fix_delay_s + ORIGIN_AFTER_FIX_S

    def ekf_flags(self) -> int:
        """EKF_STATUS_REPORT.flags: uninitialised at boot, constant-position mode without GPS."""
        if self.t_s < 1.0:
            return EKF_BOOT
        return EKF_USING_GPS if self.ekf_using_gps else EKF_NO_GPS

    def system_status(self) -> int:
        """HEARTBEAT.system_status: CRITICAL in a failsafe, ACTIVE flying, else STANDBY."""
        if self.ekf_failsafe or self.charge_state >= CHARGE_EMERGENCY:
            return mavlink.MAV_STATE_CRITICAL
        return mavlink.MAV_STATE_ACTIVE if self.armed and self.in_air else mavlink.MAV_STATE_STANDBY

    def base_mode(self) -> int:
        flags = BASE_MODE_ALWAYS
        if self.custom_mode in _GUIDED_FLAG_MODES:
            flags |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.armed:
            flags |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        return flags

    def _say(self, severity: int, text: str) -> None:
        if text.startswith("RTL: start return"):
            return
        said = _TEXTS.get(text, text)
        if said is not None:
            super()._say(severity, said)

    # --- modes --------------------------------------------------------------------------------
    def _set_mode(self, mode: FlightMode, keep_hold: bool = False) -> None:
        super()._set_mode(mode, keep_hold)
        if mode is FlightMode.HOLD:
            if self.custom_mode not in (GUIDED, LOITER):
                self.custom_mode = GUIDED
        elif mode in (FlightMode.TAKEOFF, FlightMode.OFFBOARD):
            self.custom_mode = GUIDED
        else:
            self.custom_mode = {FlightMode.POSCTL: STABILIZE, FlightMode.MISSION: AUTO, FlightMode.RTL: RTL,
                                FlightMode.LAND: LAND}[mode]

    def set_custom_mode(self, number: int) -> tuple[int, str]:
        """MAV_CMD_DO_SET_MODE with an ArduCopter mode number (param2)."""
        flown = _FLOWN_AS.get(number)
        if flown is None:
            return self._deny(f"Flight mode change failed: mode {number} not simulated")
        if number == self.custom_mode:
            return ACCEPTED, "mode unchanged"
        if number in (GUIDED, LOITER, AUTO, RTL):
            denied = self._need_position("Flight mode change")
            if denied:
                return denied
        if number == RTL:
            return self.return_to_launch()
        if number == LAND:
            return self.land()
        if number == AUTO:
            return self.set_mode(FlightMode.MISSION)
        was = self.custom_mode
        self._set_mode(flown)
        self.custom_mode = number
        if number == GUIDED and was != GUIDED:
            self._speed_override_mps = None  # a new GUIDED starts at WPNAV_SPEED
        return ACCEPTED, mavutil.mode_mapping_acm[number]

    # --- commands -----------------------------------------------------------------------------
    def arm(self, force: bool = False) -> tuple[int, str]:
        if not self.armed and not force:
            if self.custom_mode not in _ARMABLE:
                return self._deny("Arm: Mode not armable")
            if not self.position_valid:
                return self._deny("PreArm: EKF3 not using GPS")
        return super().arm(force)

    def guided_takeoff(self, height_m: float) -> tuple[int, str]:
        """MAV_CMD_NAV_TAKEOFF in GUIDED, param7 the height above home [m]: armed and on the
        ground only; climbs after the motors spooled up."""
        if self.custom_mode != GUIDED:
            return self._deny("Takeoff: not in GUIDED")
        if not self.armed:
            return self._deny("Takeoff: not armed")
        if self.in_air:
            return FAILED, "already flying"
        if not math.isfinite(height_m) or height_m <= 0:
            height_m = self.params["MIS_TAKEOFF_ALT"]
        self._takeoff_up_m = self.home[2] + height_m
        self._hold = [self.nav_pos[0], self.nav_pos[1], self._takeoff_up_m]
        self._takeoff_cmd_s = self.t_s
        self._set_mode(FlightMode.TAKEOFF)
        return ACCEPTED, f"takeoff to {height_m:.1f} m"

    def guided_target(self, pos_enu_m: list[float]) -> bool:
        """A SET_POSITION_TARGET_* position in GUIDED: fly there (from a take-off too, at once);
        ignored in other modes and on the ground, as ArduCopter does. True when taken."""
        if self.custom_mode != GUIDED or not (self.armed and self.in_air):
            log.debug("vehicle: position target ignored (mode %d, in air %s)", self.custom_mode, self.in_air)
            return False
        self._set_mode(FlightMode.HOLD, keep_hold=True)
        self._hold = [pos_enu_m[0], pos_enu_m[1], max(pos_enu_m[2], 1.0)]
        return True

    def reposition(self, lat_deg: float, lon_deg: float, alt_amsl_m: float,
                   speed_mps: float = -1.0) -> tuple[int, str]:
        """MAV_CMD_DO_REPOSITION: ArduCopter flies it in GUIDED."""
        result = super().reposition(lat_deg, lon_deg, alt_amsl_m, speed_mps)
        if result[0] == ACCEPTED:
            self.custom_mode = GUIDED
        return result

    def set_gps_lost(self, lost: bool) -> None:
        """The fix goes: the EKF loses its global position and, in the air, the EKF failsafe
        (FS_EKF_ACTION 1) lands where the vehicle is, without horizontal position control."""
        was = self.gps_lost
        super().set_gps_lost(lost)
        if lost and not was and self.armed and self.in_air and self.custom_mode != LAND:
            self.ekf_failsafe = True
            self._say(SEV_CRITICAL, "EKF variance")
            self._say(SEV_CRITICAL, "EKF Failsafe: changed to LAND Mode")
            self.land()

    def _position_failsafe(self) -> None:
        """The EKF failsafe landed already (:meth:`set_gps_lost`); nothing more happens later."""

    def _disarm(self, text: str) -> None:
        super()._disarm(text)
        self.ekf_failsafe = False

    # --- flight -------------------------------------------------------------------------------
    def _cruise_mps(self) -> float:
        """RTL at RTL_SPEED (0: WPNAV_SPEED); otherwise DO_CHANGE_SPEED's speed or WPNAV_SPEED."""
        p = self.params
        if self.mode is FlightMode.RTL:
            v = (p["RTL_SPEED"] or p["WPNAV_SPEED"]) / 100.0
        else:
            v = self._speed_override_mps or p["WPNAV_SPEED"] / 100.0
        return max(0.1, min(v, p["MPC_XY_VEL_MAX"]))

    def _takeoff_climb_mps(self) -> float:
        """Nothing while the motors spool up, then WPNAV_SPEED_UP, slowing near the height as
        v = sqrt(2 · TAKEOFF_APPROACH_MPS2 · height to go)."""
        if self._takeoff_cmd_s is not None and self.t_s - self._takeoff_cmd_s < TAKEOFF_SPOOL_S:
            return 0.0
        to_go = max(self._takeoff_up_m - self.pos[2], 0.0)
        return max(0.05, min(self.params["WPNAV_SPEED_UP"] / 100.0, math.sqrt(2 * TAKEOFF_APPROACH_MPS2 * to_go)))

    def _land_speed(self) -> float:
        """LAND_SPEED_HIGH (0: WPNAV_SPEED_DN) above LAND_ALT_LOW, LAND_SPEED below [m/s]."""
        p = self.params
        if self.pos[2] - self.home[2] > p["LAND_ALT_LOW"] / 100.0:
            return (p["LAND_SPEED_HIGH"] or p["WPNAV_SPEED_DN"]) / 100.0
        return p["LAND_SPEED"] / 100.0

    def _move(self, dt: float, target: list[float] | None, v_h: float, vel_cmd: list[float] | None,
              v_dn: float) -> None:
        """The shared point-mass flight with ArduCopter's approach (:func:`approach_speed_mps`) and
        position controller gains, no drag left to an integrator (it holds WPNAV_SPEED on long legs)."""
        p = self.params
        v_up = self._takeoff_climb_mps() if self.mode is FlightMode.TAKEOFF else p["MPC_Z_V_AUTO_UP"]
        if target is not None:
            nav = self.nav_pos
            v_h = min(v_h, approach_speed_mps(math.hypot(target[0] - nav[0], target[1] - nav[1]),
                                              BRAKE_FRACTION * p["MPC_ACC_HOR"]))
        target = self._to_true(target)
        trk = kinematics.Tracking(TRAJECTORY_JERK_MPS3, 2.0, p["PSC_POSXY_P"], p["PSC_VELXY_P"],
                                  vel_int=p["PSC_VELXY_I"], drag_per_s=0.0)
        self.acc, self.yaw_rad, self._setpoint = kinematics.move(
            self.pos, self.vel, self.yaw_rad, dt, target, v_h, vel_cmd, v_up, v_dn,
            p["MPC_ACC_HOR"], p["MPC_ACC_UP_MAX"], p["MPC_ACC_DOWN_MAX"], self.in_air,
            self.acc, self._setpoint, trk)

    def rtl_return_up_m(self) -> float:
        """ArduCopter's return height (mode_rtl.cpp compute_return_target), above home:

            h = min(max(RTL_ALT, current), max(RTL_CONE_SLOPE · d, 2.5 m))   (cone: RTL_CONE_SLOPE > 0)
            h = max(h, current, 2.5 m)                                       (RTL never descends first)
        """
        p, home = self.params, self.home
        current = self.pos[2] - home[2]
        h = max(p["RTL_ALT"] / 100.0, current)
        nav = self.nav_pos
        d = math.hypot(nav[0] - home[0], nav[1] - home[1])
        if p["RTL_CONE_SLOPE"] > 0:
            h = min(h, max(p["RTL_CONE_SLOPE"] * d, 2.5))
        return home[2] + max(h, current, 2.5)


# --- the wire: streams and commands --------------------------------------------------------------
_M = mavlink
EKF_STATUS_REPORT = ardupilotmega.MAVLINK_MSG_ID_EKF_STATUS_REPORT
#: what ArduCopter sends, all on request only but HEARTBEAT (its SRx_ rates are 0 in SITL)
DEFAULT_INTERVALS_S: dict[int, float | None] = {
    _M.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    **{msg_id: None for msg_id in (
        _M.MAVLINK_MSG_ID_SYS_STATUS, _M.MAVLINK_MSG_ID_GPS_RAW_INT, _M.MAVLINK_MSG_ID_MISSION_CURRENT,
        _M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, _M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, _M.MAVLINK_MSG_ID_ATTITUDE,
        _M.MAVLINK_MSG_ID_VFR_HUD, _M.MAVLINK_MSG_ID_SYSTEM_TIME, _M.MAVLINK_MSG_ID_BATTERY_STATUS,
        EKF_STATUS_REPORT, _M.MAVLINK_MSG_ID_HOME_POSITION, _M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
        _M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)},
}
#: REQUEST_DATA_STREAM's groups, as ArduCopter fills them (GCS_Mavlink.cpp), of what is simulated
DATA_STREAMS: dict[int, tuple[int, ...]] = {
    _M.MAV_DATA_STREAM_EXTENDED_STATUS: (_M.MAVLINK_MSG_ID_SYS_STATUS, _M.MAVLINK_MSG_ID_GPS_RAW_INT,
                                         _M.MAVLINK_MSG_ID_MISSION_CURRENT),
    _M.MAV_DATA_STREAM_POSITION: (_M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, _M.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
    _M.MAV_DATA_STREAM_EXTRA1: (_M.MAVLINK_MSG_ID_ATTITUDE,),
    _M.MAV_DATA_STREAM_EXTRA2: (_M.MAVLINK_MSG_ID_VFR_HUD,),
    _M.MAV_DATA_STREAM_EXTRA3: (_M.MAVLINK_MSG_ID_SYSTEM_TIME, _M.MAVLINK_MSG_ID_BATTERY_STATUS, EKF_STATUS_REPORT),
}
#: ArduCopter's AUTOPILOT_VERSION: 4.7.0-dev (FIRMWARE_VERSION_TYPE_DEV), its capability bits
ARDUPILOT_VERSION = (4 << 24) | (7 << 16) | (0 << 8) | _M.FIRMWARE_VERSION_TYPE_DEV
ARDUPILOT_CAPABILITIES = (
    _M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | _M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | _M.MAV_PROTOCOL_CAPABILITY_MISSION_INT | _M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | _M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | _M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT | _M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | _M.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE | _M.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
    | getattr(_M, "MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST", 1 << 17)
)


class ArduPilotStreams(StreamEncoder):
    """ArduCopter's HEARTBEAT, EKF_STATUS_REPORT and AUTOPILOT_VERSION, its positions before the
    EKF has one; the rest as PX4 fills them."""

    ap: ArduCopter

    def encode(self, msg_id: int) -> Any | None:
        ap = self.ap
        if msg_id == _M.MAVLINK_MSG_ID_HEARTBEAT:
            return _M.MAVLink_heartbeat_message(_M.MAV_TYPE_QUADROTOR, _M.MAV_AUTOPILOT_ARDUPILOTMEGA, ap.base_mode(),
                                                ap.custom_mode, ap.system_status(), 3)
        if msg_id == EKF_STATUS_REPORT:
            var = 0.02 if ap.ekf_using_gps else 0.0
            return ardupilotmega.MAVLink_ekf_status_report_message(ap.ekf_flags(), var, var, var, var, 0.0)
        if msg_id == _M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT and not ap.position_published:
            # before its first fix ArduCopter sends GLOBAL_POSITION_INT all zeros (the recording)
            return _M.MAVLink_global_position_int_message(int(ap.t_s * 1e3) & 0xFFFFFFFF, 0, 0, 0, 0, 0, 0, 0, 0)
        if msg_id == _M.MAVLINK_MSG_ID_LOCAL_POSITION_NED and not (ap.position_valid
                                                                   or ap.dead_reckoning.since_s is not None):
            return None  # no local position before the EKF uses GPS (the recording: from then on)
        if msg_id == _M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return _M.MAVLink_autopilot_version_message(
                ARDUPILOT_CAPABILITIES, ARDUPILOT_VERSION, 0, 0, 0, list(b"51a5eed1"), [0] * 8, [0] * 8, 0x1209,
                0x5740, 0x5EED0000 | self.system_id, [0] * 18)
        return super().encode(msg_id)


class ArduPilotCommands(CommandProtocol):
    """ArduCopter's answers where they differ from PX4's: DO_SET_MODE with ArduCopter mode numbers,
    NAV_TAKEOFF at a relative height in GUIDED, RTL and LAND commands as the modes, position
    targets as GUIDED targets, REQUEST_DATA_STREAM."""

    ap: ArduCopter

    def handlers(self) -> dict[str, Callable[[Any], None]]:
        return {**super().handlers(), "REQUEST_DATA_STREAM": self.on_request_data_stream}

    def _command(self, msg: Any, p: list[float], frame: int, lat: float, lon: float, alt: float) -> None:
        ap, cmd = self.ap, msg.command
        if cmd == CMD_DO_SET_MODE:
            if not int(p[0]) & _M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                self.ack(msg, UNSUPPORTED)
                return
            result, _ = ap.set_custom_mode(int(p[1]))
        elif cmd == CMD_NAV_TAKEOFF:
            result, _ = ap.guided_takeoff(alt)  # ArduCopter: param7 is the height above home
        elif cmd == CMD_NAV_RETURN_TO_LAUNCH:
            result, _ = ap.set_custom_mode(RTL)
        elif cmd == CMD_NAV_LAND:
            result, _ = ap.set_custom_mode(LAND)
        elif cmd == CMD_DO_REPOSITION and ap.custom_mode not in (GUIDED, LOITER):
            result = DENIED
        else:
            super()._command(msg, p, frame, lat, lon, alt)
            return
        self.ack(msg, result)

    def on_set_position_target_local_ned(self, msg: Any) -> None:
        if msg.coordinate_frame == FRAME_LOCAL_NED and all(math.isfinite(v) for v in (msg.x, msg.y, msg.z)):
            self.ap.guided_target([msg.y, msg.x, -msg.z])

    def on_set_position_target_global_int(self, msg: Any) -> None:
        alt = self.alt_amsl(msg.coordinate_frame, msg.alt)
        if math.isfinite(alt):
            self.ap.guided_target(self.ap.lla_to_enu(msg.lat_int * 1e-7, msg.lon_int * 1e-7, alt))

    def on_request_data_stream(self, msg: Any) -> None:
        """Start (stop) a group of streams at req_message_rate [Hz of autopilot time]; stream 0: all."""
        groups = list(DATA_STREAMS) if msg.req_stream_id == _M.MAV_DATA_STREAM_ALL else [msg.req_stream_id]
        on = msg.start_stop and msg.req_message_rate > 0
        for group in groups:
            for msg_id in DATA_STREAMS.get(group, ()):
                self.schedule.set_interval(msg_id, 1e6 / msg.req_message_rate if on else -1)


__all__ = ["DATA_STREAMS", "DEFAULT_INTERVALS_S", "ArduCopter", "ArduPilotCommands", "ArduPilotParams",
           "ArduPilotStreams", "ardupilot_params"]
