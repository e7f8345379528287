"""The telemetry streams of the built-in vehicle: which messages it sends by default and how
often (simulated seconds; SET_MESSAGE_INTERVAL changes them), and each message encoded from the
autopilot's state as PX4 fills it. No sockets: the simulator sends what :meth:`StreamEncoder.encode`
returns when :meth:`StreamSchedule.due` says so.
"""

from __future__ import annotations

import math
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from estimator.geodesy import Origin
from sitl_scenarios.scenario import VehicleConfig
from sitl_scenarios.vehicle import px4
from sitl_scenarios.vehicle.autopilot import Autopilot
from sitl_scenarios.vehicle.kinematics import quaternion, wrap_pi
from sitl_scenarios.vehicle.mav import ACCEPTED, CHARGE_CRITICAL, CHARGE_EMERGENCY, UNSUPPORTED
from sitl_scenarios.vehicle.px4 import FlightMode
from sitl_scenarios.vehicle.sensors import battery_electrics, remaining

# SYS_STATUS sensor bits (MAV_SYS_STATUS_SENSOR)
_S_GPS = mavlink.MAV_SYS_STATUS_SENSOR_GPS
_S_PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK
SENSORS_PRESENT = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | _S_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | mavlink.MAV_SYS_STATUS_AHRS
    | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY | _S_PREARM
)
#: MAVLink version of the heartbeat (the `mavlink_version` field)
MAVLINK_VERSION = 3

# default stream intervals, simulated seconds (None: only on request): those of the recorded PX4
# v1.18 (../shared/data/px4-v1.18-sih/legs, tests/test_px4_conformance.py); SYSTEM_TIME, which that
# recording's link does not carry, times uavloc's telemetry (mission.vehicle)
DEFAULT_INTERVALS_S: dict[int, float | None] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.02,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 0.02,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 0.02,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 0.02,
    mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: 0.02,
    mavlink.MAVLINK_MSG_ID_ALTITUDE: 1.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 0.2,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: 0.25,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 2.0,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: 2.0,
    mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: None,
}



class StreamSchedule:
    """Per message: its interval [simulated s] (None: only on request) and its next send time
    [simulated s]. The simulator asks after every simulation step, so each stream keeps its rate
    in vehicle time however the steps fall on the wall clock (a busy machine delays them, it does
    not thin the streams out).

    On the wire a stream is capped at `max_wall_hz` (an interval of at least speedup / max_wall_hz
    simulated seconds) and the heartbeat is sent at least once per wall second, whatever the
    speedup, so a ground station's wall-clock link timeout never fires on a healthy link."""

    def __init__(self, speedup: float, max_wall_hz: float,
                 defaults_s: dict[int, float | None] | None = None) -> None:
        self.speedup = speedup
        self.max_wall_hz = max_wall_hz
        #: every message the vehicle can send and its default interval (the personality's)
        self.defaults_s = DEFAULT_INTERVALS_S if defaults_s is None else defaults_s
        self.intervals_s: dict[int, float | None] = dict(self.defaults_s)
        self._next_s: dict[int, float] = {}
        self._heartbeat_wall_s = -math.inf

    def can_send(self, msg_id: int) -> bool:
        return msg_id in self.intervals_s

    def set_interval(self, msg_id: int, interval_us: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL: < 0 stops the stream, 0 restores the default; MAV_RESULT."""
        if not self.can_send(msg_id) or not math.isfinite(interval_us):
            return UNSUPPORTED
        if interval_us < 0:
            self.intervals_s[msg_id] = None
        elif interval_us == 0:
            self.intervals_s[msg_id] = self.defaults_s[msg_id]
        else:
            self.intervals_s[msg_id] = interval_us * 1e-6
        self._next_s[msg_id] = -math.inf
        return ACCEPTED

    def interval_us(self, msg_id: int) -> int:
        """MESSAGE_INTERVAL.interval_us of a stream (-1: not streamed)."""
        iv = self.intervals_s[msg_id]
        return -1 if iv is None else round(iv * 1e6)

    def send_next(self, msg_id: int) -> None:
        """Stream msg_id goes out at the next :meth:`due`, off its beat (its period runs from there)."""
        self._next_s[msg_id] = -math.inf

    def due(self, t_s: float, wall_s: float) -> list[int]:
        """The streams to send at vehicle time t_s [s] (wall time wall_s [s]), their next send
        times moved on: by one period, or to a period from now when they fell further behind."""
        out = []
        min_period_s = self.speedup / self.max_wall_hz
        for msg_id, interval_s in self.intervals_s.items():
            if interval_s is None:
                continue
            due = self._next_s.get(msg_id, -math.inf)
            heartbeat = msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT
            if t_s >= due - 1e-9 or (heartbeat and wall_s - self._heartbeat_wall_s >= 1.0):
                out.append(msg_id)
                period_s = max(interval_s, min_period_s)
                nxt = due + period_s
                self._next_s[msg_id] = nxt if nxt > t_s + 1e-9 else t_s + period_s
                if heartbeat:
                    self._heartbeat_wall_s = wall_s
        return out


class StreamEncoder:
    """Each stream message from the autopilot's state (positions: the estimate, with GPS error)."""

    def __init__(
        self, ap: Autopilot, origin: Origin, vehicle: VehicleConfig, unix_start_s: float, system_id: int
    ) -> None:
        self.ap = ap
        self.origin = origin
        self.vehicle = vehicle
        self.unix_start_s = unix_start_s
        self.system_id = system_id

    def encode(self, msg_id: int) -> Any | None:
        """The message `msg_id` now, or None when PX4 would not send it (no fix, no home)."""
        ap = self.ap
        t_ms = int(ap.t_s * 1e3) & 0xFFFFFFFF
        t_us = int(ap.t_s * 1e6)
        M = mavlink
        if msg_id == M.MAVLINK_MSG_ID_HEARTBEAT:
            if ap.charge_state >= CHARGE_EMERGENCY or ap.position_failsafe:
                status = M.MAV_STATE_CRITICAL
            elif ap.armed:
                status = M.MAV_STATE_ACTIVE
            else:  # PX4: UNINIT until its pre-arm checks (here: a fix and home) pass
                status = M.MAV_STATE_STANDBY if ap.gps_ok and ap.home_set else M.MAV_STATE_UNINIT
            return M.MAVLink_heartbeat_message(
                M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, px4.px4_base_mode(ap.mode, ap.armed),
                px4.px4_custom_mode(ap.mode), status, MAVLINK_VERSION)
        elif msg_id == M.MAVLINK_MSG_ID_SYS_STATUS:
            health = SENSORS_PRESENT & ~(_S_GPS | _S_PREARM)
            if ap.gps_ok:
                health |= _S_GPS
            if ap.gps_ok and ap.home_set and ap.charge_state < CHARGE_CRITICAL:
                health |= _S_PREARM
            v_mv, i_ca = self._electrics()
            return M.MAVLink_sys_status_message(
                SENSORS_PRESENT, SENSORS_PRESENT, health, 250, v_mv, i_ca, int(ap.battery_pct),
                0, 0, 0, 0, 0, 0)
        elif msg_id == M.MAVLINK_MSG_ID_GPS_RAW_INT:
            if not ap.gps_ok:  # a receiver without a fix: no position, unknown accuracy
                return M.MAVLink_gps_raw_int_message(
                    t_us, M.GPS_FIX_TYPE_NO_FIX, 0, 0, 0, 65535, 65535, 65535, 65535, 0, 0, 0, 0, 0, 0, 0)
            est = ap.gps_position()
            lat, lon, alt = ap.enu_to_lla(est)
            vh = math.hypot(ap.vel[0], ap.vel[1])
            cog = int((math.degrees(math.atan2(ap.vel[0], ap.vel[1])) % 360) * 100) if vh > 0.3 else 65535
            sigma_mm = int(max(self.vehicle.gps_sigma_m, 0.01) * 1000)
            return M.MAVLink_gps_raw_int_message(
                t_us, M.GPS_FIX_TYPE_3D_FIX, round(lat * 1e7), round(lon * 1e7), int(alt * 1000), 80, 120,
                int(vh * 100), cog, 12, int(alt * 1000), sigma_mm, int(sigma_mm * 1.5), 100, 0, 0)
        elif msg_id == M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            if not ap.position_published:
                return None  # no global position estimate yet
            est = ap.estimated_position()
            lat, lon, alt = ap.enu_to_lla(est)
            vel = ap.estimated_velocity()  # the EKF's velocity: small error, no drift (sensors.VelocityError)
            return M.MAVLink_global_position_int_message(
                t_ms, round(lat * 1e7), round(lon * 1e7), int(alt * 1000),
                int((est[2] - ap.home[2]) * 1000), round(vel[1] * 100), round(vel[0] * 100),
                round(-vel[2] * 100), int((math.degrees(ap.yaw_rad) % 360) * 100))
        elif msg_id == M.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            if not ap.position_published:
                return None
            est = ap.estimated_position()
            vel = ap.estimated_velocity()
            return M.MAVLink_local_position_ned_message(t_ms, est[1], est[0], -est[2], vel[1], vel[0], -vel[2])
        elif msg_id == M.MAVLINK_MSG_ID_ATTITUDE:
            roll, pitch = ap.tilt_rad()
            return M.MAVLink_attitude_message(t_ms, roll, pitch, wrap_pi(ap.yaw_rad), 0.0, 0.0, 0.0)
        elif msg_id == M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            roll, pitch = ap.tilt_rad()
            q = quaternion(roll, pitch, wrap_pi(ap.yaw_rad))
            return M.MAVLink_attitude_quaternion_message(t_ms, *q, 0.0, 0.0, 0.0, [0.0, 0.0, 0.0, 0.0])
        elif msg_id == M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED:
            sp = ap.trajectory_setpoint()
            yaw = wrap_pi(ap.yaw_rad)
            if sp is None:  # as PX4 on the ground: position and velocity ignored (type_mask 63)
                nan = math.nan
                return M.MAVLink_position_target_local_ned_message(
                    t_ms, M.MAV_FRAME_LOCAL_NED, 63, nan, nan, nan, nan, nan, nan, 0.0, 0.0, 0.0, yaw, 0.0)
            (pe, pn, pu), (ve, vn, vu), (ae, an, au) = sp
            return M.MAVLink_position_target_local_ned_message(
                t_ms, M.MAV_FRAME_LOCAL_NED, 0, pn, pe, -pu, vn, ve, -vu, an, ae, -au, yaw, 0.0)
        elif msg_id == M.MAVLINK_MSG_ID_ALTITUDE:
            est_up = float(ap.estimated_position()[2]) if ap.position_published else ap.pos[2]
            amsl = self.origin.alt_m + est_up
            return M.MAVLink_altitude_message(
                t_us, amsl, amsl, est_up, est_up - ap.home[2], math.nan, math.nan)  # no range finder
        elif msg_id == M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return M.MAVLink_extended_sys_state_message(M.MAV_VTOL_STATE_UNDEFINED, ap.landed_state)
        elif msg_id == M.MAVLINK_MSG_ID_VFR_HUD:
            vh = math.hypot(ap.vel[0], ap.vel[1])
            return M.MAVLink_vfr_hud_message(
                vh, vh, int(math.degrees(ap.yaw_rad) % 360), 50 if ap.in_air else 0,
                self.origin.alt_m + ap.pos[2], ap.vel[2])
        elif msg_id == M.MAVLINK_MSG_ID_HOME_POSITION:
            if not ap.home_set:
                return None
            lat, lon, alt = ap.enu_to_lla(ap.home)
            h = ap.home
            return M.MAVLink_home_position_message(
                round(lat * 1e7), round(lon * 1e7), int(alt * 1000), h[1], h[0], -h[2],
                [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t_us)
        elif msg_id == M.MAVLINK_MSG_ID_BATTERY_STATUS:
            v_mv, i_ca = self._electrics()
            used_mah, remaining_s = remaining(ap.battery_pct, self.vehicle.battery_capacity_s)
            return M.MAVLink_battery_status_message(
                0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, 32767, [v_mv] + [65535] * 9, i_ca,
                used_mah, -1, int(ap.battery_pct), remaining_s, ap.charge_state, [0, 0, 0, 0], 0, 0)
        elif msg_id == M.MAVLINK_MSG_ID_MISSION_CURRENT:
            m = ap.mission
            in_mission = 1 if ap.mode is FlightMode.MISSION else 2  # mission_mode: 1 in mission mode, 2 not
            return M.MAVLink_mission_current_message(m.current, len(m.items), ap.mission_state, in_mission)
        elif msg_id == M.MAVLINK_MSG_ID_SYSTEM_TIME:
            return M.MAVLink_system_time_message(int((self.unix_start_s + ap.t_s) * 1e6), t_ms)
        elif msg_id == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            major, minor, patch = px4.PX4_VERSION
            sw = px4.px4_sw_version(major, minor, patch)
            return M.MAVLink_autopilot_version_message(
                px4.PX4_CAPABILITIES, sw, sw, 0, 0, list(b"51a5eed1"), [0] * 8, [0] * 8, 0x26AC, 0x0011,
                0x5EED0000 | self.system_id, [0] * 18)
        return None

    def _electrics(self) -> tuple[int, int]:
        ap = self.ap
        return battery_electrics(ap.battery_pct, int(ap.params["BAT1_N_CELLS"]), ap.armed, ap.in_air)
