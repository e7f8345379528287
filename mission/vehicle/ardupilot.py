"""What MAVSDK does not do on ArduPilot, in one place: pymavlink messages through MAVSDK's
MavlinkDirect plugin, for :class:`mission.vehicle.MavsdkVehicle` once the HEARTBEAT says
MAV_AUTOPILOT_ARDUPILOTMEGA.

ArduPilot (ArduCopter 4.7 SITL, ../shared/data/ardupilot-4.7-sitl/) differs from PX4 where the
mission needs it:

- it streams nothing but HEARTBEAT until asked: :meth:`ArduPilotLink.request_streams` sets the
  message intervals the mission reads (SET_MESSAGE_INTERVAL; REQUEST_DATA_STREAM where refused);
- MAVSDK's health flags say nothing useful about it (the issue-26 attempt: "global position ok:
  False" while the EKF used GPS): readiness and the global position are judged from
  EKF_STATUS_REPORT (horizontal absolute position, not constant-position mode), GPS_RAW_INT (a 3-D
  fix) and HOME_POSITION; before its first fix it sends GLOBAL_POSITION_INT all zeros;
- its flight modes are custom modes (pymavlink `mavutil.mode_mapping_acm`): GUIDED for take-off and
  position targets, RTL and LAND by mode; NAV_TAKEOFF takes the height above home and only armed;
  legs are SET_POSITION_TARGET_GLOBAL_INT, which ArduPilot ignores outside GUIDED;
- it sends EXTENDED_SYS_STATE only on request: the landed state falls back to the heartbeat.

Every command waits for its COMMAND_ACK (MavlinkDirect.send_command) and a refusal becomes a
VehicleCommandError with the MAV_RESULT name.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as apm

from mission.vehicle.types import GeoFix, VehicleCommandError, VehicleTimeoutError
from uavloc.errors import VehicleError

log = logging.getLogger(__name__)

M = apm  # ardupilotmega includes common
#: ArduCopter's custom modes (pymavlink's table)
MODE_NUMBER = {name: number for number, name in mavutil.mode_mapping_acm.items()}
GUIDED, RTL, LAND = MODE_NUMBER["GUIDED"], MODE_NUMBER["RTL"], MODE_NUMBER["LAND"]
#: the names :attr:`VehicleState.flight_mode` gets where the mission reads them (MAVSDK's names,
#: as on PX4); any other mode keeps ArduCopter's name (GUIDED, STABILIZE, LOITER, ...)
MODE_NAME = {**mavutil.mode_mapping_acm, RTL: "RETURN_TO_LAUNCH", MODE_NUMBER["SMART_RTL"]: "RETURN_TO_LAUNCH",
             MODE_NUMBER["AUTO_RTL"]: "RETURN_TO_LAUNCH", LAND: "LAND"}
#: MAV_LANDED_STATE → MAVSDK's LandedState names
LANDED_NAME = {M.MAV_LANDED_STATE_UNDEFINED: "UNKNOWN", M.MAV_LANDED_STATE_ON_GROUND: "ON_GROUND",
               M.MAV_LANDED_STATE_IN_AIR: "IN_AIR", M.MAV_LANDED_STATE_TAKEOFF: "TAKING_OFF",
               M.MAV_LANDED_STATE_LANDING: "LANDING"}
EKF_NEEDED = M.EKF_ATTITUDE | M.EKF_VELOCITY_HORIZ | M.EKF_POS_HORIZ_ABS | M.EKF_POS_VERT_ABS
EKF_BAD = M.EKF_CONST_POS_MODE | M.EKF_UNINITIALIZED | M.EKF_GPS_GLITCHING
#: position only: velocity, acceleration and yaw rate ignored (yaw too unless given)
_MASK_POSITION = (M.POSITION_TARGET_TYPEMASK_VX_IGNORE | M.POSITION_TARGET_TYPEMASK_VY_IGNORE
                  | M.POSITION_TARGET_TYPEMASK_VZ_IGNORE | M.POSITION_TARGET_TYPEMASK_AX_IGNORE
                  | M.POSITION_TARGET_TYPEMASK_AY_IGNORE | M.POSITION_TARGET_TYPEMASK_AZ_IGNORE
                  | M.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)
_MASK_YAW = M.POSITION_TARGET_TYPEMASK_YAW_IGNORE
#: arming right after the EKF is ready may be refused for a moment (pre-arm checks settling)
ARM_RETRY_S = 0.5
#: wall seconds between requests for HOME_POSITION while it has not come
HOME_REQUEST_S = 2.0


def heartbeat_autopilot(fields_json: str) -> int | None:
    """MAV_AUTOPILOT of a HEARTBEAT given as MavlinkDirect's JSON, or None."""
    try:
        value = json.loads(fields_json)["autopilot"]
    except (ValueError, KeyError, TypeError):
        return None
    return value if isinstance(value, int) else None


def _result_name(result: int) -> str:
    entry = M.enums["MAV_RESULT"].get(result)
    return entry.name.removeprefix("MAV_RESULT_") if entry is not None else str(result)


class ArduPilotLink:
    """ArduPilot's side of :class:`mission.vehicle.MavsdkVehicle` (module docstring).

    system: the MAVSDK system; state: the adapter's VehicleState, updated by :meth:`watch`;
    request_timeout_s: wall limit per command; position_rate_hz: GLOBAL_POSITION_INT's rate.
    """

    def __init__(self, system: Any, state: Any, request_timeout_s: float, position_rate_hz: float,
                 target_system: int = 1):
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync

        self.direct = MavlinkDirectAsync(system)
        self.state = state
        self.request_timeout_s = request_timeout_s
        self.position_rate_hz = position_rate_hz
        self.target_system = target_system
        self.custom_mode: int | None = None
        self.ekf_flags = 0
        self.fix_type = 0
        self.has_landed_state = False  # EXTENDED_SYS_STATE seen
        self.position_seen = False  # the EKF had a global position once (before: GLOBAL_POSITION_INT is 0, 0)

    # -- messages -------------------------------------------------------------------------------
    def _direct(self, msg: Any) -> Any:
        """A pymavlink message as MavlinkDirect's MavlinkMessage (its fields as JSON)."""
        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        fields = {k: v for k, v in msg.to_dict().items() if k != "mavpackettype"}
        for k, v in fields.items():
            if isinstance(v, float) and not math.isfinite(v):
                fields[k] = 0.0
        return MavlinkMessage(message_name=msg.get_type(), system_id=0, component_id=0,
                              target_system_id=self.target_system, target_component_id=1,
                              fields_json=json.dumps(fields))

    async def command(self, what: str, command: int, *params: float) -> None:
        """COMMAND_LONG, waiting for its COMMAND_ACK; VehicleCommandError unless ACCEPTED."""
        from mavsdk.plugins.mavlink_direct import MavlinkDirectError

        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        msg = M.MAVLink_command_long_message(self.target_system, 1, command, 0, *p)
        try:
            async with asyncio.timeout(self.request_timeout_s):
                ack = await self.direct.send_command(self._direct(msg))
        except TimeoutError as exc:
            raise VehicleTimeoutError(f"vehicle: {what} timed out after {self.request_timeout_s:g} s") from exc
        except MavlinkDirectError as exc:
            raise VehicleCommandError(f"vehicle: {what} failed: {exc}", "NO_ACK") from exc
        try:
            result = int(json.loads(ack.fields_json)["result"])
        except (ValueError, KeyError, TypeError) as exc:
            raise VehicleCommandError(f"vehicle: {what}: no COMMAND_ACK", "NO_ACK") from exc
        if result != M.MAV_RESULT_ACCEPTED:
            name = _result_name(result)
            raise VehicleCommandError(f"vehicle: {what} failed: {name}", name)

    async def send(self, msg: Any) -> None:
        """A message that has no acknowledgement (a position target, REQUEST_DATA_STREAM)."""
        from mavsdk.plugins.mavlink_direct import MavlinkDirectError

        try:
            async with asyncio.timeout(self.request_timeout_s):
                await self.direct.send_message(self._direct(msg))
        except TimeoutError as exc:
            raise VehicleTimeoutError(f"vehicle: sending {msg.get_type()} timed out") from exc
        except MavlinkDirectError as exc:
            raise VehicleCommandError(f"vehicle: sending {msg.get_type()} failed: {exc}") from exc

    async def request_streams(self) -> None:
        """The message intervals the mission reads [Hz of autopilot time]; REQUEST_DATA_STREAM
        (all groups at the position rate) if ArduPilot refuses one."""
        rates_hz = {M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self.position_rate_hz, M.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
                    M.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0, M.MAVLINK_MSG_ID_GPS_RAW_INT: 2.0,
                    M.MAVLINK_MSG_ID_EKF_STATUS_REPORT: 2.0, M.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
                    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 2.0, M.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0}
        refused = []
        for msg_id, hz in rates_hz.items():
            try:
                await self.command(f"message interval of {msg_id}", M.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
            except VehicleCommandError as exc:
                refused.append(f"{msg_id}: {exc.result}")
        if refused:
            log.warning("vehicle: ArduPilot refused message intervals (%s): REQUEST_DATA_STREAM all at %g Hz",
                        ", ".join(refused), self.position_rate_hz)
            await self.send(M.MAVLink_request_data_stream_message(
                self.target_system, 1, M.MAV_DATA_STREAM_ALL, max(1, round(self.position_rate_hz)), 1))

    # -- state ----------------------------------------------------------------------------------
    @property
    def position_ok(self) -> bool:
        """The EKF has a global position (EKF_STATUS_REPORT) and the receiver a 3-D fix."""
        return (self.ekf_flags & EKF_NEEDED == EKF_NEEDED and not self.ekf_flags & EKF_BAD
                and self.fix_type >= M.GPS_FIX_TYPE_3D_FIX)

    def fix_usable(self, lat_deg: float, lon_deg: float) -> bool:
        """A GLOBAL_POSITION_INT worth passing on: none before the EKF's first global position
        (ArduPilot sends 0, 0 before its first fix); dead-reckoned ones after a loss are."""
        return self.position_seen and not (lat_deg == 0.0 and lon_deg == 0.0)

    def not_ready(self) -> str:
        st = self.state
        return (f"EKF global position ok: {self.position_ok} (EKF_STATUS_REPORT flags {self.ekf_flags:#x}), "
                f"GPS fix type: {self.fix_type}, home ok: {st.home_position_ok}")

    def _on(self, kind: str, f: dict) -> None:
        st = self.state
        if kind == "HEARTBEAT":
            self.custom_mode = int(f["custom_mode"])
            st.flight_mode = MODE_NAME.get(self.custom_mode, str(self.custom_mode))
            st.armed = bool(int(f["base_mode"]) & M.MAV_MODE_FLAG_SAFETY_ARMED)
            if not self.has_landed_state:  # no EXTENDED_SYS_STATE: ArduPilot disarms only on the ground
                active = int(f["system_status"]) == M.MAV_STATE_ACTIVE
                st.landed_state = "IN_AIR" if st.armed and active else ("ON_GROUND" if not st.armed else "UNKNOWN")
        elif kind == "EKF_STATUS_REPORT":
            self.ekf_flags = int(f["flags"])
        elif kind == "GPS_RAW_INT":
            self.fix_type = int(f["fix_type"])
            st.gps_fix_type = self.fix_type
            sats = int(f["satellites_visible"])
            st.gps_satellites = None if sats == 255 else sats  # 255: unknown
        elif kind == "EXTENDED_SYS_STATE":
            self.has_landed_state = True
            st.landed_state = LANDED_NAME.get(int(f["landed_state"]), "UNKNOWN")
        elif kind == "HOME_POSITION":
            lat, lon, alt = f["latitude"] * 1e-7, f["longitude"] * 1e-7, f["altitude"] * 1e-3
            if (lat, lon) != (0.0, 0.0):
                st.home = GeoFix(lat, lon, alt)
                st.home_position_ok = True
        st.global_position_ok = self.position_ok
        self.position_seen = self.position_seen or self.position_ok

    async def watch(self) -> None:
        """Follow ArduPilot's heartbeat, EKF, GPS, landed state and home into the state, until cancelled."""
        wanted = ("HEARTBEAT", "EKF_STATUS_REPORT", "GPS_RAW_INT", "EXTENDED_SYS_STATE", "HOME_POSITION")

        async def follow(kind: str) -> None:
            try:
                async with contextlib.aclosing(self.direct.subscribe_message(kind)) as it:
                    async for msg in it:
                        if msg.system_id != self.target_system or msg.component_id != 1:
                            continue
                        try:
                            self._on(kind, json.loads(msg.fields_json))
                        except (ValueError, KeyError, TypeError) as exc:
                            log.debug("vehicle: unreadable %s: %s", kind, exc)
                        self.state.last_rx_mono_s = time.monotonic()
            except Exception:  # one lost subscription must not end the others (its state goes stale)
                log.exception("vehicle: following ArduPilot's %s failed", kind)

        async with asyncio.TaskGroup() as tg:
            for kind in wanted:
                tg.create_task(follow(kind))

    async def wait_ready(self, timeout_s: float) -> None:
        """Until the EKF has a global position, a 3-D fix and home; HOME_POSITION is asked for every
        HOME_REQUEST_S meanwhile (ArduPilot sends it when home is set, or when asked)."""
        deadline = time.monotonic() + timeout_s
        asked = -math.inf
        while not (self.position_ok and self.state.home_position_ok):
            now = time.monotonic()
            if now > deadline:
                raise VehicleTimeoutError(f"vehicle not ready within {timeout_s:g} s ({self.not_ready()})")
            if self.position_ok and not self.state.home_position_ok and now - asked > HOME_REQUEST_S:
                asked = now
                try:
                    await self.command("request home", M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION)
                except VehicleError as exc:
                    log.info("vehicle: %s", exc)
            await asyncio.sleep(0.05)

    # -- commands -------------------------------------------------------------------------------
    async def set_mode(self, number: int) -> None:
        name = mavutil.mode_mapping_acm.get(number, str(number))
        await self.command(f"mode {name}", M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number)
        self.custom_mode = number

    async def arm(self) -> None:
        """GUIDED, then arm (retried while ArduPilot's pre-arm checks refuse, up to the request timeout)."""
        if self.custom_mode != GUIDED:
            await self.set_mode(GUIDED)
        deadline = time.monotonic() + self.request_timeout_s
        while True:
            try:
                await self.command("arm", M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
                return
            except VehicleCommandError as exc:
                if exc.result not in ("FAILED", "TEMPORARILY_REJECTED", "DENIED") or time.monotonic() > deadline:
                    raise
                await asyncio.sleep(ARM_RETRY_S)

    async def takeoff(self, height_m: float) -> None:
        """NAV_TAKEOFF in GUIDED; ArduCopter's param7 is the height above home."""
        if self.custom_mode != GUIDED:
            await self.set_mode(GUIDED)
        await self.command(f"takeoff to {height_m:g} m", M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, height_m)

    async def goto(self, lat_deg: float, lon_deg: float, alt_amsl_m: float, yaw_deg: float) -> None:
        """SET_POSITION_TARGET_GLOBAL_INT (AMSL); only in GUIDED: a vehicle the autopilot took out of
        GUIDED (a failsafe's RTL or LAND) is not taken back."""
        if self.custom_mode != GUIDED:
            mode = MODE_NAME.get(self.custom_mode, str(self.custom_mode))
            raise VehicleCommandError(f"vehicle: goto refused: ArduPilot is in {mode}, not GUIDED", "DENIED")
        mask = _MASK_POSITION | (0 if math.isfinite(yaw_deg) else _MASK_YAW)
        yaw = math.radians(yaw_deg) if math.isfinite(yaw_deg) else 0.0
        await self.send(M.MAVLink_set_position_target_global_int_message(
            0, self.target_system, 1, M.MAV_FRAME_GLOBAL_INT, mask, round(lat_deg * 1e7), round(lon_deg * 1e7),
            float(alt_amsl_m), 0, 0, 0, 0, 0, 0, yaw, 0))

    async def set_speed(self, speed_mps: float) -> None:
        """DO_CHANGE_SPEED (ground speed): ArduCopter flies the following GUIDED targets at it."""
        await self.command(f"set speed {speed_mps:g} m/s", M.MAV_CMD_DO_CHANGE_SPEED, 1, speed_mps, -1)

    async def set_param(self, name: str, value: float) -> None:
        """PARAM_SET, acknowledged by the PARAM_VALUE ArduPilot sends back with the value it holds;
        VehicleCommandError when it holds another value, VehicleTimeoutError without an answer."""
        msg = M.MAVLink_param_set_message(self.target_system, 1, name.encode(), float(value), M.MAV_PARAM_TYPE_REAL32)
        try:
            async with asyncio.timeout(self.request_timeout_s):
                async with contextlib.aclosing(self.direct.subscribe_message("PARAM_VALUE")) as it:
                    await self.send(msg)
                    async for got in it:
                        f = json.loads(got.fields_json)
                        if got.system_id != self.target_system or str(f.get("param_id", "")).rstrip("\x00") != name:
                            continue
                        if not math.isclose(float(f["param_value"]), float(value), rel_tol=1e-6, abs_tol=1e-6):
                            raise VehicleCommandError(f"vehicle: set {name} {value:g}: it holds {f['param_value']:g}",
                                                      "DENIED")
                        return
        except TimeoutError as exc:
            raise VehicleTimeoutError(f"vehicle: set {name} {value:g}: no PARAM_VALUE within "
                                      f"{self.request_timeout_s:g} s") from exc

    async def return_to_launch(self) -> None:
        await self.set_mode(RTL)

    def return_to_launch_blocking(self) -> None:
        """RTL without the event loop, from any thread (mission.control.last_resort): DO_SET_MODE
        RTL sent once through MavlinkDirect's blocking send; its COMMAND_ACK is not awaited."""
        msg = M.MAVLink_command_long_message(self.target_system, 1, M.MAV_CMD_DO_SET_MODE, 0,
                                             float(M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(RTL),
                                             0.0, 0.0, 0.0, 0.0, 0.0)
        # the blocking plugin MavlinkDirectAsync wraps (its calls run in the loop's executor)
        self.direct._plugin.send_message(self._direct(msg))

    async def land(self) -> None:
        await self.set_mode(LAND)

    async def disarm(self) -> None:
        await self.command("disarm", M.MAV_CMD_COMPONENT_ARM_DISARM, 0)


__all__ = ["ArduPilotLink", "heartbeat_autopilot"]
