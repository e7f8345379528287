"""The command protocol of the built-in vehicle: COMMAND_LONG / COMMAND_INT answered with
COMMAND_ACK as PX4 does, message intervals, offboard setpoints (SET_POSITION_TARGET_*) and
TIMESYNC. Every command number and result comes from pymavlink (:mod:`sitl_scenarios.vehicle.mav`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from estimator.geodesy import Origin
from sitl_scenarios.vehicle import px4
from sitl_scenarios.vehicle.autopilot import Autopilot
from sitl_scenarios.vehicle.faults import VehicleFaults
from sitl_scenarios.vehicle.mav import (
    ACCEPTED,
    CMD_COMPONENT_ARM_DISARM,
    CMD_DO_CHANGE_SPEED,
    CMD_DO_PAUSE_CONTINUE,
    CMD_DO_REPOSITION,
    CMD_DO_SET_HOME,
    CMD_DO_SET_MODE,
    CMD_GET_MESSAGE_INTERVAL,
    CMD_MISSION_START,
    CMD_NAV_LAND,
    CMD_NAV_RETURN_TO_LAUNCH,
    CMD_NAV_TAKEOFF,
    CMD_REQUEST_AUTOPILOT_CAPABILITIES,
    CMD_REQUEST_MESSAGE,
    CMD_SET_MESSAGE_INTERVAL,
    DENIED,
    FORCE_MAGIC,
    FRAME_GLOBAL,
    FRAME_LOCAL_NED,
    RELATIVE_ALT_FRAMES,
    RESULT_UNSUPPORTED_MAV_FRAME,
    SEV_WARNING,
    UNSUPPORTED,
)
from sitl_scenarios.vehicle.px4 import FlightMode
from sitl_scenarios.vehicle.streams import StreamSchedule

log = logging.getLogger(__name__)

#: COMMAND_INT x / y that mean "not given" (0, or INT32_MAX as MAVSDK sends)
_UNSET_INT = (0, 2**31 - 1)
#: POSITION_TARGET_TYPEMASK bits that ignore the position / the velocity
_IGNORE_POS = (mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
               | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE)
_IGNORE_VEL = (mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
               | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE)


class CommandProtocol:
    """Answers commands, offboard setpoints and TIMESYNC for the autopilot `ap`.

    send: puts a message on the link; send_stream: sends a stream message now (REQUEST_MESSAGE);
    schedule: the stream intervals; faults: DO_REPOSITION refusals; wall_s: the wall clock of the
    last tick (offboard setpoints age in wall time)."""

    def __init__(
        self,
        ap: Autopilot,
        origin: Origin,
        send: Callable[[Any], None],
        send_stream: Callable[[int], None],
        schedule: StreamSchedule,
        faults: VehicleFaults,
        wall_s: Callable[[], float],
    ) -> None:
        self.ap = ap
        self.origin = origin
        self._send = send
        self._send_stream = send_stream
        self.schedule = schedule
        self.faults = faults
        self._wall_s = wall_s

    def handlers(self) -> dict[str, Callable[[Any], None]]:
        """{MAVLink message type: its handler}."""
        return {
            "COMMAND_LONG": self.on_command_long,
            "COMMAND_INT": self.on_command_int,
            "SET_POSITION_TARGET_LOCAL_NED": self.on_set_position_target_local_ned,
            "SET_POSITION_TARGET_GLOBAL_INT": self.on_set_position_target_global_int,
            "TIMESYNC": self.on_timesync,
        }

    def ack(self, msg: Any, result: int) -> None:
        self._send(mavlink.MAVLink_command_ack_message(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def on_command_long(self, msg: Any) -> None:
        p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        lat, lon, alt = p[4], p[5], p[6]
        self._command(msg, p, FRAME_GLOBAL, lat, lon, alt)

    def on_command_int(self, msg: Any) -> None:
        if msg.command == CMD_DO_REPOSITION and self.faults.refusing_reposition(self.ap.t_s):
            log.info("vehicle: fault: COMMAND_INT DO_REPOSITION refused with MAV_RESULT %d",
                     RESULT_UNSUPPORTED_MAV_FRAME)
            self.ack(msg, RESULT_UNSUPPORTED_MAV_FRAME)
            return
        p = [msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z]
        unset = msg.x in _UNSET_INT and msg.y in _UNSET_INT
        lat = math.nan if unset else msg.x * 1e-7
        lon = math.nan if unset else msg.y * 1e-7
        self._command(msg, p, msg.frame, lat, lon, msg.z)

    def alt_amsl(self, frame: int, alt: float) -> float:
        """A command's or setpoint's altitude as AMSL [m] (relative frames: above home)."""
        if not math.isfinite(alt):
            return math.nan
        if frame in RELATIVE_ALT_FRAMES:
            return self.origin.alt_m + self.ap.home[2] + alt
        return alt

    def _command(self, msg: Any, p: list[float], frame: int, lat: float, lon: float, alt: float) -> None:
        ap, cmd = self.ap, msg.command
        log.debug("vehicle: command %d %s", cmd, p)
        result: int
        if cmd == CMD_COMPONENT_ARM_DISARM:
            force = abs(p[1] - FORCE_MAGIC) < 0.5
            result, _ = ap.arm(force) if p[0] > 0.5 else ap.disarm(force)
        elif cmd == CMD_NAV_TAKEOFF:
            result, _ = ap.takeoff(self.alt_amsl(frame, alt))
        elif cmd == CMD_NAV_LAND:
            result, _ = ap.land(lat, lon)
        elif cmd == CMD_NAV_RETURN_TO_LAUNCH:
            result, _ = ap.return_to_launch()
        elif cmd == CMD_DO_REPOSITION:
            result, _ = ap.reposition(lat, lon, self.alt_amsl(frame, alt), p[0])
        elif cmd == CMD_DO_SET_MODE:
            result = self._set_mode(int(p[0]), int(p[1]), int(p[2]))
        elif cmd == CMD_DO_CHANGE_SPEED:
            result, _ = ap.change_speed(p[1])
        elif cmd == CMD_DO_SET_HOME:
            result, _ = ap.set_home(p[0] > 0.5, lat, lon, self.alt_amsl(frame, alt))
        elif cmd == CMD_MISSION_START:
            result, _ = ap.mission_start(int(p[0]) if math.isfinite(p[0]) else 0)
        elif cmd == CMD_DO_PAUSE_CONTINUE:
            result, _ = ap.set_mode(FlightMode.MISSION if p[0] > 0.5 else FlightMode.HOLD)
        elif cmd == CMD_SET_MESSAGE_INTERVAL:
            result = self.schedule.set_interval(int(p[0]), p[1])
        elif cmd == CMD_GET_MESSAGE_INTERVAL:
            result = self._get_interval(int(p[0]))
        elif cmd == CMD_REQUEST_MESSAGE:
            msg_id = int(p[0])
            result = ACCEPTED if self.schedule.can_send(msg_id) else UNSUPPORTED
            self.ack(msg, result)
            if result == ACCEPTED:
                self._send_stream(msg_id)
            return
        elif cmd == CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self.ack(msg, ACCEPTED)
            self._send_stream(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
            return
        else:
            log.debug("vehicle: unsupported command %d", cmd)
            result = UNSUPPORTED
        self.ack(msg, result)

    def _set_mode(self, base_mode: int, main: int, sub: int) -> int:
        if not base_mode & px4.MODE_FLAG_CUSTOM_MODE_ENABLED:
            return UNSUPPORTED
        mode = px4.mode_from_px4(main, sub)
        if mode is None:
            self.ap.messages.append((SEV_WARNING, f"Mode {main}.{sub} not available (no RC)"))
            return DENIED
        result, _ = self.ap.set_mode(mode)
        return result

    def _get_interval(self, msg_id: int) -> int:
        if not self.schedule.can_send(msg_id):
            return UNSUPPORTED
        self._send(mavlink.MAVLink_message_interval_message(msg_id, self.schedule.interval_us(msg_id)))
        return ACCEPTED

    # offboard
    def on_set_position_target_local_ned(self, msg: Any) -> None:
        if msg.coordinate_frame != FRAME_LOCAL_NED:
            log.debug("vehicle: offboard frame %d not supported", msg.coordinate_frame)
            return
        pos = None if msg.type_mask & _IGNORE_POS == _IGNORE_POS else [msg.y, msg.x, -msg.z]
        vel = None if msg.type_mask & _IGNORE_VEL == _IGNORE_VEL else [msg.vy, msg.vx, -msg.vz]
        if pos is not None and not all(math.isfinite(v) for v in pos):
            pos = None
        self.ap.offboard_setpoint(pos, vel, self._wall_s())

    def on_set_position_target_global_int(self, msg: Any) -> None:
        if msg.type_mask & _IGNORE_POS == _IGNORE_POS:
            vel = [msg.vy, msg.vx, -msg.vz]
            self.ap.offboard_setpoint(None, vel, self._wall_s())
            return
        alt = self.alt_amsl(msg.coordinate_frame, msg.alt)
        pos = self.ap.lla_to_enu(msg.lat_int * 1e-7, msg.lon_int * 1e-7, alt)
        self.ap.offboard_setpoint(pos, None, self._wall_s())

    def on_timesync(self, msg: Any) -> None:
        if msg.tc1 == 0:
            self._send(mavlink.MAVLink_timesync_message(int(self.ap.t_s * 1e9), msg.ts1))
