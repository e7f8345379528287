"""The vehicle side of the mission: a small :class:`Vehicle` protocol and its MAVSDK implementation.

The controller depends only on :class:`Vehicle` (docs/architecture.md). :class:`MavsdkVehicle` implements it
over the native `mavsdk.asyncio` binding, for PX4 and ArduPilot (real or SITL) and for the built-in
simulator alike; which autopilot it is comes from the HEARTBEAT (`MAV_AUTOPILOT_*`). What MAVSDK
does not do on ArduPilot is in :mod:`mission.vehicle.ardupilot` (docs/ardupilot.md). Every call has
a timeout; every plugin error is turned into a :class:`VehicleCommandError` carrying MAVSDK's result
code, right where the call is made (the MAVSDK-Python examples' style).

Telemetry (position, home, battery, armed, flight mode, landed state, health, status texts, link)
flows into one
:class:`VehicleState` owned by the adapter, while :meth:`Vehicle.run_telemetry` runs.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from mission.vehicle.telemetry import VehicleStatus
from mission.vehicle.types import GeoFix, VehicleCommandError, VehicleTimeoutError
from uavloc.errors import VehicleError

log = logging.getLogger(__name__)
#: tries of an idempotent command whose acknowledgement MAVSDK gave up waiting for (result TIMEOUT)
COMMAND_TIMEOUT_TRIES = 3


@dataclass(frozen=True)
class PositionFix:
    """A global position fix as received; t_mono_s: `time.monotonic()` at reception."""

    t_mono_s: float
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    rel_alt_m: float
    vel_ned_mps: tuple[float, float, float] | None = None


@dataclass
class VehicleState:
    """Latest telemetry of the vehicle, updated in place by the adapter's telemetry task."""

    position: PositionFix | None = None
    home: GeoFix | None = None
    battery_pct: float | None = None
    battery_voltage_v: float | None = None
    #: [0, 360) from north (GLOBAL_POSITION_INT's hdg)
    heading_deg: float | None = None
    #: MAVLink GPS_FIX_TYPE of GPS_RAW_INT (0..8) and its satellites visible
    gps_fix_type: int | None = None
    gps_satellites: int | None = None
    armed: bool | None = None
    flight_mode: str = "UNKNOWN"
    landed_state: str = "UNKNOWN"
    connected: bool = False
    global_position_ok: bool = False
    home_position_ok: bool = False
    last_rx_mono_s: float = 0.0
    vel_ned_mps: tuple[float, float, float] | None = None
    #: the autopilot's status texts (MAVLink STATUSTEXT) as (t_mono_s, severity name, text)
    texts: list[tuple[float, str, str]] = field(default_factory=list)
    #: which autopilot the HEARTBEAT names: "px4", "ardupilot" or "other"
    autopilot: str = "unknown"

    def status(self) -> VehicleStatus:
        """What a `telemetry` record carries beside the position (mission.vehicle.telemetry.VehicleStatus)."""
        pos = self.position
        return VehicleStatus(rel_alt_m=None if pos is None or not math.isfinite(pos.rel_alt_m) else pos.rel_alt_m,
                             heading_deg=self.heading_deg, battery_pct=self.battery_pct,
                             battery_voltage_v=self.battery_voltage_v, flight_mode=self.flight_mode,
                             armed=self.armed, gps_fix_type=self.gps_fix_type, gps_satellites=self.gps_satellites)

    def age_s(self, now_mono_s: float | None = None) -> float:
        """Wall seconds since anything was last received (inf before the first message)."""
        if not self.last_rx_mono_s:
            return math.inf
        return (time.monotonic() if now_mono_s is None else now_mono_s) - self.last_rx_mono_s


class Vehicle(Protocol):
    """What the mission controller needs from a vehicle."""

    state: VehicleState

    async def connect(self, timeout_s: float) -> None: ...

    async def wait_ready(self, timeout_s: float) -> GeoFix:
        """Wait until global position and home are ok; return home."""
        ...

    async def run_telemetry(self, on_position: Callable[[PositionFix], None],
                            on_vehicle_time: Callable[[float, float], None] | None = None) -> None:
        """Keep :attr:`state` up to date and call `on_position` on every fix, until cancelled;
        `on_vehicle_time(t_mono_s, boot_s)` on every vehicle boot time received (MAVLink
        `time_boot_ms`)."""
        ...

    async def arm(self) -> None: ...

    async def takeoff(self, height_m: float) -> None: ...

    async def goto_location(self, lat_deg: float, lon_deg: float, alt_amsl_m: float, yaw_deg: float) -> None: ...

    async def set_speed(self, speed_mps: float) -> None:
        """Command the horizontal cruise speed of the following legs (MAV_CMD_DO_CHANGE_SPEED)."""
        ...

    async def return_to_launch(self) -> None: ...

    def return_to_launch_blocking(self) -> None:
        """RTL without the event loop, from any thread (the signal watchdog's last resort,
        mission.control.last_resort); VehicleError when refused."""
        ...

    async def set_return_altitude(self, height_m: float) -> None:
        """The height above home the vehicle returns at on RTL (a fleet's vehicles each at their own
        altitude layer); VehicleError when the vehicle does not take it."""
        ...

    async def land(self) -> None: ...

    async def close(self) -> None: ...


_mavsdk_log = logging.getLogger(__name__ + ".mavsdk")
_mavsdk_log_routed = False


def _route_mavsdk_log() -> None:
    """Send MAVSDK's own log lines (printed on stdout by default) to Python logging instead, so
    that stdout stays clean for `--json`. Called from MAVSDK's threads; logging is thread-safe."""
    global _mavsdk_log_routed
    if _mavsdk_log_routed:
        return
    from mavsdk.logging import LogLevel, log_subscribe

    levels = {LogLevel.DEBUG: logging.DEBUG, LogLevel.INFO: logging.DEBUG,
              LogLevel.WARN: logging.INFO, LogLevel.ERROR: logging.WARNING}

    def handler(level, message, file, line) -> bool:
        _mavsdk_log.log(levels.get(level, logging.INFO), "%s", message)
        return True  # suppress MAVSDK's default printing

    log_subscribe(handler)
    _mavsdk_log_routed = True


def _enum_name(value: Any) -> str:
    return getattr(value, "name", str(value))


_library_wedged = False


def vehicle_library_wedged() -> bool:
    """True once a MAVSDK instance did not shut down in time (its threads are abandoned)."""
    return _library_wedged


class MavsdkVehicle:
    """:class:`Vehicle` over `mavsdk.asyncio` (one MAVSDK instance per vehicle).

    url: a MAVSDK connection URL, e.g. `udpin://0.0.0.0:14540` (PX4 SITL) or `udpin://127.0.0.1:PORT`.
    request_timeout_s: wall-time limit of every request to the vehicle; close_timeout_s: wall
    seconds :meth:`close` waits for MAVSDK to shut down before abandoning it (a wedged MAVSDK never
    returns from `destroy()`; see mission.runtime).
    """

    def __init__(self, url: str, request_timeout_s: float = 10.0, position_rate_hz: float = 10.0,
                 close_timeout_s: float = 5.0):
        self.url = url
        self.request_timeout_s = float(request_timeout_s)
        self.close_timeout_s = float(close_timeout_s)
        self.position_rate_hz = float(position_rate_hz)
        self.state = VehicleState()
        self._mavsdk = None
        self._system = None
        self._action = None
        self._telemetry = None
        self._ardupilot = None  # mission.vehicle.ardupilot.ArduPilotLink once the heartbeat says ArduPilot
        self._ardupilot_watch: asyncio.Task | None = None

    async def __aenter__(self) -> MavsdkVehicle:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- connection -----------------------------------------------------------------------------

    async def connect(self, timeout_s: float = 30.0) -> None:
        """Open the MAVLink connection and wait for the first autopilot."""
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkConnectionError
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        _route_mavsdk_log()
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        try:
            async with asyncio.timeout(self.request_timeout_s):
                await self._mavsdk.add_any_connection(self.url)
        except MavsdkConnectionError as exc:
            raise VehicleError(f"cannot open MAVLink connection {self.url!r}: {exc}") from exc
        except TimeoutError as exc:
            raise VehicleTimeoutError(f"opening MAVLink connection {self.url!r} timed out") from exc
        log.info("waiting for an autopilot on %s", self.url)
        system = await self._mavsdk.first_autopilot(timeout_s=timeout_s)
        if system is None:
            raise VehicleTimeoutError(f"no autopilot heartbeat on {self.url!r} within {timeout_s:g} s")
        self._system = system
        self._action = ActionAsync(system)
        self._telemetry = TelemetryAsync(system)
        self.state.connected = True
        self.state.last_rx_mono_s = time.monotonic()
        log.info("autopilot found on %s", self.url)
        await self._detect_autopilot(system)

    async def _detect_autopilot(self, system) -> None:
        """The HEARTBEAT's MAV_AUTOPILOT (MavlinkDirect); on ArduPilot, start following what
        MAVSDK does not (mission.vehicle.ardupilot) and request the streams it would not send."""
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
        from pymavlink.dialects.v20 import common as mavlink

        from mission.vehicle.ardupilot import heartbeat_autopilot

        kind = None
        direct = MavlinkDirectAsync(system)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(self.request_timeout_s):
                async with contextlib.aclosing(direct.subscribe_message("HEARTBEAT")) as beats:
                    async for msg in beats:
                        kind = heartbeat_autopilot(msg.fields_json)
                        if msg.component_id == 1 and kind not in (None, mavlink.MAV_AUTOPILOT_INVALID):
                            break
        self.state.autopilot = {mavlink.MAV_AUTOPILOT_PX4: "px4",
                                mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot"}.get(kind, "other")
        log.info("autopilot: %s (MAV_AUTOPILOT %s)", self.state.autopilot, kind)
        if self.state.autopilot != "ardupilot":
            return
        from mission.vehicle.ardupilot import ArduPilotLink

        self._ardupilot = ArduPilotLink(system, self.state, self.request_timeout_s, self.position_rate_hz,
                                        target_system=await system.get_system_id())
        self._ardupilot_watch = asyncio.create_task(self._ardupilot.watch(), name="ardupilot-watch")
        await self._ardupilot.request_streams()

    async def close(self) -> None:
        """Shut MAVSDK down in a daemon thread; give up on it after close_timeout_s (wall)."""
        global _library_wedged
        if self._ardupilot_watch is not None:
            self._ardupilot_watch.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._ardupilot_watch
            self._ardupilot_watch = None
        if self._mavsdk is None:
            return
        mav, self._mavsdk = self._mavsdk, None
        done = threading.Event()

        def destroy() -> None:
            try:
                mav.destroy()
            except Exception:  # a failing shutdown must not hide the mission's result
                log.exception("MAVSDK shutdown failed")
            finally:
                done.set()

        threading.Thread(target=destroy, name="mavsdk-destroy", daemon=True).start()
        deadline = time.monotonic() + self.close_timeout_s
        while not done.is_set() and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        if not done.is_set():
            _library_wedged = True
            log.error("MAVSDK did not shut down within %g s: abandoned", self.close_timeout_s)

    def _need(self) -> None:
        if self._system is None:
            raise VehicleError("vehicle not connected: call connect() first")

    async def wait_ready(self, timeout_s: float = 60.0) -> GeoFix:
        """Wait until the autopilot reports global position ok and home ok, then return home
        (ArduPilot: its EKF, GPS fix and HOME_POSITION, mission.vehicle.ardupilot)."""
        self._need()
        if self._ardupilot is not None:
            await self._ardupilot.wait_ready(timeout_s)
            return self.state.home
        try:
            async with asyncio.timeout(timeout_s):
                async with contextlib.aclosing(self._telemetry.subscribe_health()) as health:
                    async for h in health:
                        self.state.global_position_ok = bool(h.is_global_position_ok)
                        self.state.home_position_ok = bool(h.is_home_position_ok)
                        if h.is_global_position_ok and h.is_home_position_ok:
                            break
                async with contextlib.aclosing(self._telemetry.subscribe_home()) as homes:
                    async for hp in homes:
                        if all(math.isfinite(v) for v in (hp.latitude_deg, hp.longitude_deg,
                                                          hp.absolute_altitude_m)):
                            home = GeoFix(hp.latitude_deg, hp.longitude_deg, hp.absolute_altitude_m)
                            break
        except TimeoutError as exc:
            s = self.state
            raise VehicleTimeoutError(
                f"vehicle not ready within {timeout_s:g} s (global position ok: {s.global_position_ok}, "
                f"home ok: {s.home_position_ok})"
            ) from exc
        self.state.home = home
        return home

    # -- telemetry ------------------------------------------------------------------------------

    async def run_telemetry(self, on_position: Callable[[PositionFix], None],
                            on_vehicle_time: Callable[[float, float], None] | None = None) -> None:
        """Subscribe to every stream the mission uses; runs until cancelled. The vehicle's clock
        comes from SYSTEM_TIME's `time_boot_ms` (MAVSDK's telemetry carries no timestamps; its
        MavlinkDirect plugin gives the raw message)."""
        self._need()
        tel, st = self._telemetry, self.state
        ardupilot = self._ardupilot  # ArduPilot: its heartbeat, EKF and home come from ArduPilotLink.watch
        if ardupilot is None:
            await self._request("set position rate", tel.set_rate_position(self.position_rate_hz), optional=True)

        def touch() -> None:
            st.last_rx_mono_s = time.monotonic()

        async def follow(gen: AsyncIterator, handle: Callable[[Any], None]) -> None:
            async with contextlib.aclosing(gen) as it:
                async for item in it:
                    touch()
                    handle(item)

        def on_pos(p) -> None:
            fix = PositionFix(time.monotonic(), p.latitude_deg, p.longitude_deg, p.absolute_altitude_m,
                              p.relative_altitude_m, st.vel_ned_mps)
            if ardupilot is not None and not ardupilot.fix_usable(fix.lat_deg, fix.lon_deg):
                return
            if all(math.isfinite(v) for v in (fix.lat_deg, fix.lon_deg, fix.alt_amsl_m)):
                st.position = fix
                on_position(fix)

        def on_home(h) -> None:
            if all(math.isfinite(v) for v in (h.latitude_deg, h.longitude_deg, h.absolute_altitude_m)):
                st.home = GeoFix(h.latitude_deg, h.longitude_deg, h.absolute_altitude_m)

        def on_battery(b) -> None:
            if math.isfinite(b.remaining_percent):
                st.battery_pct = float(b.remaining_percent)
            # MAVSDK reports NaN (or 0) when the autopilot sent no voltage
            if math.isfinite(b.voltage_v) and b.voltage_v > 0:
                st.battery_voltage_v = float(b.voltage_v)

        def on_heading(h) -> None:
            if math.isfinite(h.heading_deg):
                st.heading_deg = float(h.heading_deg) % 360.0

        def on_gps(g) -> None:
            st.gps_fix_type = int(getattr(g.fix_type, "value", g.fix_type))
            st.gps_satellites = int(g.num_satellites)

        def on_health(h) -> None:
            st.global_position_ok = bool(h.is_global_position_ok)
            st.home_position_ok = bool(h.is_home_position_ok)

        def on_vel(v) -> None:
            st.vel_ned_mps = (float(v.north_m_s), float(v.east_m_s), float(v.down_m_s))

        def on_armed(a) -> None:
            st.armed = bool(a)

        def on_mode(m) -> None:
            st.flight_mode = _enum_name(m)

        def on_text(t) -> None:
            st.texts.append((time.monotonic(), _enum_name(t.type), str(t.text).strip()))

        def on_landed(s) -> None:
            st.landed_state = _enum_name(s)

        async def follow_link() -> None:
            async with contextlib.aclosing(self._system.is_connected_state()) as it:
                async for connected in it:
                    if connected != st.connected:
                        log.warning("vehicle link %s", "restored" if connected else "lost")
                    st.connected = bool(connected)
                    if connected:
                        touch()

        def on_system_time(msg) -> None:
            if on_vehicle_time is None:
                return
            try:
                boot_ms = json.loads(msg.fields_json)["time_boot_ms"]
            except (ValueError, KeyError, TypeError):
                log.debug("vehicle: SYSTEM_TIME without time_boot_ms: %r", msg.fields_json)
                return
            if isinstance(boot_ms, int | float) and math.isfinite(boot_ms) and boot_ms > 0:
                on_vehicle_time(time.monotonic(), boot_ms / 1000.0)

        async with asyncio.TaskGroup() as tg:
            tg.create_task(follow(tel.subscribe_position(), on_pos))
            if on_vehicle_time is not None:
                from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync

                direct = MavlinkDirectAsync(self._system)
                tg.create_task(follow(direct.subscribe_message("SYSTEM_TIME"), on_system_time))
            tg.create_task(follow(tel.subscribe_battery(), on_battery))
            tg.create_task(follow(tel.subscribe_velocity_ned(), on_vel))
            tg.create_task(follow(tel.subscribe_heading(), on_heading))
            if ardupilot is None:  # ArduPilot: GPS_RAW_INT comes from ArduPilotLink.watch
                tg.create_task(follow(tel.subscribe_gps_info(), on_gps))
            if ardupilot is None:
                tg.create_task(follow(tel.subscribe_home(), on_home))
                tg.create_task(follow(tel.subscribe_health(), on_health))
                tg.create_task(follow(tel.subscribe_armed(), on_armed))
                tg.create_task(follow(tel.subscribe_flight_mode(), on_mode))
                tg.create_task(follow(tel.subscribe_landed_state(), on_landed))
            tg.create_task(follow(tel.subscribe_status_text(), on_text))
            tg.create_task(follow_link())

    # -- commands -------------------------------------------------------------------------------

    async def _request(self, what: str, call: Awaitable, optional: bool = False, timeout_s: float | None = None):
        """Await one MAVSDK request with a timeout; plugin errors become VehicleCommandError."""
        from mavsdk.exceptions import MavsdkError

        limit = self.request_timeout_s if timeout_s is None else timeout_s
        try:
            async with asyncio.timeout(limit):
                return await call
        except TimeoutError as exc:
            if optional:
                log.warning("vehicle: %s timed out after %g s (ignored)", what, limit)
                return None
            raise VehicleTimeoutError(f"vehicle: {what} timed out after {limit:g} s") from exc
        except MavsdkError as exc:
            result = _enum_name(getattr(exc, "result", "UNKNOWN"))
            if optional:
                log.warning("vehicle: %s failed: %s (ignored)", what, result)
                return None
            raise VehicleCommandError(f"vehicle: {what} failed: {result}", result) from exc

    async def _request_again_on_timeout(self, what: str, make_call: Callable[[], Awaitable],
                                        timeouts: tuple[str, ...] = ("TIMEOUT",)):
        """An idempotent command (arm, the take-off height, take-off) sent again when MAVSDK gave up
        waiting for its acknowledgement (a result in `timeouts`: on a loaded machine the answer can
        come after MAVSDK's own retransmissions), COMMAND_TIMEOUT_TRIES times in all."""
        for attempt in range(COMMAND_TIMEOUT_TRIES):
            try:
                return await self._request(what, make_call())
            except VehicleCommandError as exc:
                if exc.result not in timeouts or attempt + 1 == COMMAND_TIMEOUT_TRIES:
                    raise
                log.warning("vehicle: %s: no acknowledgement (MAVSDK %s), sending it again (try %d of %d)",
                            what, exc.result, attempt + 2, COMMAND_TIMEOUT_TRIES)
        raise AssertionError("unreachable")

    async def arm(self) -> None:
        self._need()
        if self._ardupilot is not None:
            return await self._ardupilot.arm()
        await self._request_again_on_timeout("arm", self._action.arm)

    async def takeoff(self, height_m: float) -> None:
        """Set the takeoff height above home and take off."""
        self._need()
        if self._ardupilot is not None:
            return await self._ardupilot.takeoff(float(height_m))
        # the take-off height is a parameter (MIS_TAKEOFF_ALT): MAVSDK's parameter set reports an
        # unanswered request as PARAMETER_ERROR, seen under load (benchmarks/load.py, paper ×4 beside
        # four busy loops), so that result is a timeout here too
        await self._request_again_on_timeout(f"set takeoff altitude {height_m:g} m",
                                             lambda: self._action.set_takeoff_altitude(float(height_m)),
                                             timeouts=("TIMEOUT", "PARAMETER_ERROR"))
        await self._request_again_on_timeout("takeoff", self._action.takeoff)

    async def goto_location(self, lat_deg: float, lon_deg: float, alt_amsl_m: float,
                            yaw_deg: float = float("nan")) -> None:
        self._need()
        if self._ardupilot is not None:
            return await self._ardupilot.goto(lat_deg, lon_deg, alt_amsl_m, yaw_deg)
        await self._request(
            f"goto ({lat_deg:.7f}, {lon_deg:.7f}, {alt_amsl_m:.1f} m AMSL)",
            self._action.goto_location(lat_deg, lon_deg, alt_amsl_m, yaw_deg),
        )

    async def set_speed(self, speed_mps: float) -> None:
        """MAV_CMD_DO_CHANGE_SPEED (ground speed) through MAVSDK's `set_current_speed`. PX4 (v1.18-dev
        SITL, measured) flies the following repositions at this speed instead of MPC_XY_CRUISE and
        keeps it over later repositions; MAVSDK's goto_location sends no speed of its own."""
        self._need()
        if self._ardupilot is not None:
            return await self._ardupilot.set_speed(float(speed_mps))
        await self._request(f"set speed {speed_mps:g} m/s", self._action.set_current_speed(float(speed_mps)))

    async def return_to_launch(self) -> None:
        self._need()
        if self._ardupilot is not None:
            return await self._ardupilot.return_to_launch()
        await self._request("return to launch", self._action.return_to_launch())

    def return_to_launch_blocking(self) -> None:
        """RTL without the event loop, from any thread: the signal watchdog's last resort when the
        loop does not answer (mission.control.last_resort). MAVSDK's blocking call, the one
        `ActionAsync` runs in the loop's executor; blocks until the autopilot answers or MAVSDK's
        own command timeout. VehicleCommandError when refused."""
        from mavsdk.exceptions import MavsdkError

        self._need()
        if self._ardupilot is not None:
            return self._ardupilot.return_to_launch_blocking()
        try:
            self._action._plugin.return_to_launch()
        except MavsdkError as exc:
            result = _enum_name(getattr(exc, "result", "UNKNOWN"))
            raise VehicleCommandError(f"vehicle: return to launch failed: {result}", result) from exc

    async def set_return_altitude(self, height_m: float) -> None:
        """PX4: RTL_RETURN_ALT through MAVSDK's `set_return_to_launch_altitude` (PX4 returns at
        max(current height, it), docs/fleet.md); ArduPilot: RTL_ALT [cm] (PARAM_SET, acknowledged
        by its PARAM_VALUE)."""
        self._need()
        if self._ardupilot is not None:
            return await self._ardupilot.set_param("RTL_ALT", 100.0 * float(height_m))
        await self._request(f"set return altitude {height_m:g} m",
                            self._action.set_return_to_launch_altitude(float(height_m)))

    async def land(self) -> None:
        self._need()
        if self._ardupilot is not None:
            return await self._ardupilot.land()
        await self._request("land", self._action.land())

    async def disarm(self) -> None:
        self._need()
        if self._ardupilot is not None:
            return await self._ardupilot.disarm()
        await self._request("disarm", self._action.disarm())
