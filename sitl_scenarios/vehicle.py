"""Built-in MAVLink multicopter that MAVSDK takes for PX4 (DESIGN.md §9).

MAVLink 2 over UDP, system 1 component 1, PX4 heartbeat and custom modes, the telemetry streams
MAVSDK uses, the command, parameter and mission protocols, offboard position setpoints. The flight
logic is :class:`sitl_scenarios.mavlink_autopilot.Autopilot`; this module is the link, the clock
and the public API.

Use it in a test or inside `uavloc sim`::

    async with VehicleSimulator(origin, VehicleConfig(), speedup=10, target=("127.0.0.1", 14540)) as sim:
        ...                       # MAVSDK: add_any_connection("udpin://0.0.0.0:14540")
        sim.state().pos_enu_m     # true position for the simulated gNB
        sim.pause_link(8.0)       # fault injection

or standalone: `python -m sitl_scenarios.vehicle --scenario paper --speedup 10`.

Time: the simulation runs `speedup` times faster than the wall clock; every MAVLink timestamp is
simulated time, and so are the message intervals a ground station sets (SET_MESSAGE_INTERVAL). On
the wire a stream is capped at `max_stream_wall_hz` and the heartbeat is sent at least once per
wall second, whatever the speedup, so MAVSDK's wall-clock link timeout (about 3 s) never fires on a
healthy link. Fault durations are simulated seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
import select
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from estimator.geodesy import Origin
from sitl_scenarios import mavlink_px4 as px4
from sitl_scenarios.mavlink_autopilot import (
    ACCEPTED,
    CHARGE_CRITICAL,
    CHARGE_EMERGENCY,
    DENIED,
    FRAME_GLOBAL,
    FRAME_GLOBAL_INT,
    FRAME_GLOBAL_RELATIVE_ALT,
    FRAME_GLOBAL_RELATIVE_ALT_INT,
    FRAME_GLOBAL_TERRAIN_ALT,
    FRAME_GLOBAL_TERRAIN_ALT_INT,
    FRAME_LOCAL_NED,
    FRAME_MISSION,
    UNSUPPORTED,
    Autopilot,
    MissionItem,
    VehicleState,
    mission_command_supported,
)
from sitl_scenarios.mavlink_px4 import FlightMode
from sitl_scenarios.scenario import Scenario, VehicleConfig, load_scenario
from uavloc.errors import ScenarioError, SimulatorError

log = logging.getLogger(__name__)

SYSTEM_ID = 1
COMPONENT_ID = 1
DEFAULT_TARGET = ("127.0.0.1", 14540)

# SYS_STATUS sensor bits (MAV_SYS_STATUS_SENSOR)
_S_GYRO, _S_ACCEL, _S_MAG, _S_BARO, _S_GPS = 1, 2, 4, 8, 32
_S_MOTORS, _S_AHRS, _S_BATTERY, _S_PREARM = 0x8000, 0x200000, 0x2000000, 0x10000000
_SENSORS_PRESENT = _S_GYRO | _S_ACCEL | _S_MAG | _S_BARO | _S_GPS | _S_MOTORS | _S_AHRS | _S_BATTERY | _S_PREARM

# MAV_CMD handled
CMD_NAV_RETURN_TO_LAUNCH = 20
CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_DO_SET_MODE = 176
CMD_DO_CHANGE_SPEED = 178
CMD_DO_SET_HOME = 179
CMD_DO_REPOSITION = 192
CMD_DO_PAUSE_CONTINUE = 193
CMD_MISSION_START = 300
CMD_COMPONENT_ARM_DISARM = 400
CMD_GET_MESSAGE_INTERVAL = 510
CMD_SET_MESSAGE_INTERVAL = 511
CMD_REQUEST_MESSAGE = 512
CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
FORCE_MAGIC = 21196.0

# default stream intervals, simulated seconds (None: only on request)
_DEFAULT_INTERVALS_S: dict[int, float | None] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 0.5,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.1,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 0.1,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 0.1,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 0.1,
    mavlink.MAVLINK_MSG_ID_ALTITUDE: 0.2,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 0.2,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: 0.25,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 2.0,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: None,
}

_FAULT_KINDS = ("link_pause", "gps_loss", "low_battery", "reposition_refused")

#: MAV_RESULT_COMMAND_UNSUPPORTED_MAV_FRAME: what PX4 main before #26626 answered to every COMMAND_INT
#: whose frame was not MAV_FRAME_GLOBAL_INT (MAVSDK's goto_location among them)
RESULT_UNSUPPORTED_MAV_FRAME = 9


@dataclass(frozen=True)
class FaultEvent:
    """A scheduled fault (scenario `[[faults.vehicle]]`): kind, simulated start time [s], duration
    [simulated s] (link_pause, gps_loss, reposition_refused; the last two last for ever without a
    duration), battery_pct (low_battery).

    reposition_refused: COMMAND_INT DO_REPOSITION is answered with MAV_RESULT 9 (unsupported frame),
    as the PX4 build before PX4 #26626 did; MAVSDK 4.1 reports UNKNOWN and then wedges."""

    kind: str
    at_s: float
    duration_s: float | None = None
    battery_pct: float | None = None


def faults_from_scenario(faults: dict[str, Any], where: str = "faults") -> list[FaultEvent]:
    """The vehicle's fault events from a scenario's free-form `[faults]` table (key `vehicle`).

    Other keys of `[faults]` belong to other simulators and are ignored here; inside `vehicle`
    every table is checked strictly.
    """
    raw = faults.get("vehicle", [])
    if not isinstance(raw, list):
        raise ScenarioError(f"{where}.vehicle: expected a list of tables ([[faults.vehicle]]), got {raw!r}")
    events = []
    allowed = {"kind", "at_s", "duration_s", "battery_pct"}
    for i, item in enumerate(raw):
        w = f"{where}.vehicle[{i}]"
        if not isinstance(item, dict):
            raise ScenarioError(f"{w}: expected a table, got {item!r}")
        unknown = sorted(set(item) - allowed)
        if unknown:
            raise ScenarioError(f"{w}: unknown key(s) {', '.join(map(repr, unknown))}; allowed: {sorted(allowed)}")
        kind = item.get("kind")
        if kind not in _FAULT_KINDS:
            raise ScenarioError(f"{w}.kind must be one of {', '.join(_FAULT_KINDS)}, got {kind!r}")
        nums = {}
        for key in ("at_s", "duration_s", "battery_pct"):
            v = item.get(key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v)):
                raise ScenarioError(f"{w}.{key}: expected a finite number, got {v!r}")
            nums[key] = None if v is None else float(v)
        if nums["at_s"] is None or nums["at_s"] < 0:
            raise ScenarioError(f"{w}.at_s: a start time >= 0 [s] is required, got {nums['at_s']!r}")
        if kind == "link_pause" and not (nums["duration_s"] or 0) > 0:
            raise ScenarioError(f"{w}.duration_s: link_pause needs a positive duration, got {nums['duration_s']!r}")
        if nums["duration_s"] is not None and nums["duration_s"] <= 0:
            raise ScenarioError(f"{w}.duration_s must be positive, got {nums['duration_s']!r}")
        if kind == "low_battery" and (nums["battery_pct"] is None or not 0 <= nums["battery_pct"] <= 100):
            raise ScenarioError(f"{w}.battery_pct: low_battery needs a value in [0, 100], got {nums['battery_pct']!r}")
        events.append(FaultEvent(kind, nums["at_s"], nums["duration_s"], nums["battery_pct"]))
    return events


class _Sender:
    """File-like sink for pymavlink: every packed message goes to each peer."""

    def __init__(self, sim: VehicleSimulator) -> None:
        self._sim = sim

    def write(self, buf: bytes) -> None:
        self._sim._sendto_peers(buf)


@dataclass
class _Upload:
    mission_type: int
    count: int
    items: list[MissionItem]
    sysid: int
    compid: int
    last_wall_s: float
    retries: int = 0


class VehicleSimulator:
    """A PX4-like multicopter on a UDP MAVLink link, run in its own thread.

    origin: home and ENU origin (the vehicle starts there, on the ground); vehicle: speeds, GPS
    noise, battery; seed: GPS noise generator seed; speedup: simulated seconds per wall second;
    target: (host, port), or a list of them, the vehicle sends to before anyone talks to it (None:
    only answer), like PX4's API link to 127.0.0.1:14540 (and its GCS link to 14550); whoever sends
    to the vehicle is answered too; bind: local (host, port), port 0 picks a free one; faults:
    scheduled fault events; gps_fix_delay_s: simulated time until the first GPS fix;
    tick_wall_s: simulation step in wall seconds; max_stream_wall_hz: cap of each stream's rate
    on the wire.

    Start/stop: `async with` (the caller's loop is never blocked: the simulation runs in a
    thread), `with`, or :meth:`start` / :meth:`stop`. An error inside the simulation thread is
    raised as :class:`SimulatorError` by :meth:`stop` (and by :meth:`state` once the thread died).
    """

    def __init__(
        self,
        origin: Origin,
        vehicle: VehicleConfig | None = None,
        *,
        seed: int = 0,
        speedup: float = 1.0,
        target: tuple[str, int] | list[tuple[str, int]] | None = DEFAULT_TARGET,
        bind: tuple[str, int] = ("0.0.0.0", 0),
        faults: list[FaultEvent] | tuple[FaultEvent, ...] = (),
        gps_fix_delay_s: float = 2.0,
        tick_wall_s: float = 0.01,
        max_stream_wall_hz: float = 25.0,
    ) -> None:
        if not (math.isfinite(speedup) and speedup > 0):
            raise SimulatorError(f"speedup must be a positive number, got {speedup!r}")
        if not tick_wall_s > 0 or not max_stream_wall_hz > 0:
            raise SimulatorError("tick_wall_s and max_stream_wall_hz must be positive")
        self.origin = origin
        self.vehicle = vehicle or VehicleConfig()
        self.speedup = float(speedup)
        if target is None:
            self.targets: list[tuple[str, int]] = []
        elif isinstance(target, tuple):
            self.targets = [target]
        else:
            self.targets = [tuple(t) for t in target]
        self.bind = bind
        self.tick_wall_s = tick_wall_s
        self.max_stream_wall_hz = max_stream_wall_hz
        self._rng = np.random.default_rng([int(seed), 0x5EED])
        self._ap = Autopilot(origin, self.vehicle, self._rng, gps_fix_delay_s=gps_fix_delay_s)
        self._faults = sorted(faults, key=lambda f: f.at_s)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self._error: BaseException | None = None
        self._tx = mavlink.MAVLink(_Sender(self), srcSystem=SYSTEM_ID, srcComponent=COMPONENT_ID)
        self._rx = mavlink.MAVLink(None, srcSystem=SYSTEM_ID, srcComponent=COMPONENT_ID)
        self._rx.robust_parsing = True
        self._peers: dict[tuple[str, int], None] = {}
        self._intervals_s = dict(_DEFAULT_INTERVALS_S)
        self._next_wall_s: dict[int, float] = {}
        self._link_down_until_s: float | None = None
        self._gps_back_at_s: float | None = None
        self._refuse_reposition_until_s = -math.inf  # fault reposition_refused
        self._upload: _Upload | None = None
        self._unix_start_s = time.time()
        self._wall_last_s = 0.0
        self.packets_in = 0
        self.packets_out = 0

    @classmethod
    def from_scenario(cls, scenario: Scenario, **kwargs: Any) -> VehicleSimulator:
        """A simulator at the scenario's origin with its vehicle, seed and `[[faults.vehicle]]`."""
        if kwargs.get("seed") is None:
            kwargs["seed"] = scenario.seed
        if kwargs.get("faults") is None:
            kwargs["faults"] = faults_from_scenario(scenario.faults)
        return cls(scenario.origin_geo, scenario.vehicle, **kwargs)

    # --- lifecycle ----------------------------------------------------------------------------
    def start(self) -> None:
        """Bind the socket and start the simulation thread (returns at once)."""
        if self._thread is not None:
            raise SimulatorError("vehicle simulator already started")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(self.bind)
        except OSError as exc:
            sock.close()
            raise SimulatorError(f"cannot bind the vehicle's UDP socket to {self.bind}: {exc}") from exc
        sock.setblocking(False)
        self._sock = sock
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="uavloc-vehicle-sim", daemon=True)
        self._thread.start()
        log.info("vehicle simulator on udp %s:%d -> %s, speedup %g", *self.local_address, self.targets, self.speedup)

    def stop(self) -> None:
        """Stop the thread, close the socket; raises SimulatorError if the simulation had failed."""
        thread = self._thread
        if thread is not None:
            self._stop.set()
            thread.join(timeout=5.0)
            if thread.is_alive():
                raise SimulatorError("vehicle simulator thread did not stop within 5 s")
        self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._error is not None:
            err, self._error = self._error, None
            raise SimulatorError(f"vehicle simulator failed: {err!r}") from err

    def __enter__(self) -> VehicleSimulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    async def __aenter__(self) -> VehicleSimulator:
        self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await asyncio.to_thread(self.stop)

    @property
    def local_address(self) -> tuple[str, int]:
        if self._sock is None:
            raise SimulatorError("vehicle simulator not started")
        return self._sock.getsockname()

    # --- state and faults (thread-safe) -------------------------------------------------------
    def state(self) -> VehicleState:
        """The true state now (a snapshot)."""
        self._raise_if_failed()
        with self._lock:
            return self._ap.snapshot(link_up=not self._link_down())

    def param(self, name: str) -> float:
        with self._lock:
            return self._ap.params[name]

    def set_param(self, name: str, value: float) -> None:
        with self._lock:
            self._ap.params.set(name, value)

    def pause_link(self, duration_s: float) -> None:
        """Stop sending and drop everything received for duration_s simulated seconds."""
        if not duration_s > 0:
            raise SimulatorError(f"link pause duration must be positive, got {duration_s!r}")
        with self._lock:
            self._link_down_until_s = self._ap.t_s + duration_s
            log.info("vehicle: link paused for %.1f s (sim)", duration_s)

    def resume_link(self) -> None:
        with self._lock:
            self._link_down_until_s = None

    def lose_gps(self, duration_s: float | None = None) -> None:
        """No GPS fix (for duration_s simulated seconds, or until :meth:`restore_gps`)."""
        with self._lock:
            self._ap.set_gps_lost(True)
            self._gps_back_at_s = None if duration_s is None else self._ap.t_s + duration_s

    def restore_gps(self) -> None:
        with self._lock:
            self._ap.set_gps_lost(False)
            self._gps_back_at_s = None

    def refuse_reposition(self, duration_s: float | None = None) -> None:
        """Answer COMMAND_INT DO_REPOSITION with MAV_RESULT 9 (for duration_s simulated seconds, or
        for ever), like the PX4 build before PX4 #26626 (fault `reposition_refused`)."""
        with self._lock:
            self._refuse_reposition_until_s = math.inf if duration_s is None else self._ap.t_s + duration_s

    def set_battery_pct(self, pct: float) -> None:
        """Set the remaining charge (e.g. 12 for a low battery); it keeps draining from there."""
        if not (math.isfinite(pct) and 0 <= pct <= 100):
            raise SimulatorError(f"battery percentage must be in [0, 100], got {pct!r}")
        with self._lock:
            self._ap.set_battery_pct(pct)

    async def wait_for(
        self, predicate: Callable[[VehicleState], bool], timeout_s: float, poll_s: float = 0.02
    ) -> VehicleState:
        """Wait (wall seconds) until predicate(state) holds; SimulatorError on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.state()
            if predicate(st):
                return st
            if time.monotonic() > deadline:
                raise SimulatorError(f"vehicle state condition not met within {timeout_s} s; last state {st}")
            await asyncio.sleep(poll_s)

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise SimulatorError(f"vehicle simulator failed: {self._error!r}") from self._error

    def _link_down(self) -> bool:
        return self._link_down_until_s is not None and self._ap.t_s < self._link_down_until_s

    # --- thread -------------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._wall_last_s = time.monotonic()
            next_tick = self._wall_last_s
            while not self._stop.is_set():
                now = time.monotonic()
                if now >= next_tick:
                    with self._lock:
                        self._tick(now)
                    next_tick = max(next_tick + self.tick_wall_s, now)
                assert self._sock is not None
                readable, _, _ = select.select([self._sock], [], [], max(0.0, next_tick - time.monotonic()))
                if readable:
                    self._receive_all()
        except BaseException as exc:  # handed to stop()/state(); the thread must not die silently
            log.exception("vehicle simulator thread failed")
            self._error = exc

    def _tick(self, now: float) -> None:
        dt_wall = now - self._wall_last_s
        self._wall_last_s = now
        ap = self._ap
        ap.step(dt_wall * self.speedup, now)
        self._apply_faults()
        if self._link_down():
            ap.messages.clear()
            ap.reached.clear()
            return
        if self._link_down_until_s is not None:
            self._link_down_until_s = None
            log.info("vehicle: link resumed")
        for severity, text in ap.messages:
            self._send(mavlink.MAVLink_statustext_message(severity, text.encode()[:50], 0, 0))
        ap.messages.clear()
        for seq in ap.reached:
            self._send(mavlink.MAVLink_mission_item_reached_message(seq))
        ap.reached.clear()
        self._upload_timeouts(now)
        for msg_id, interval_s in self._intervals_s.items():
            if interval_s is None:
                continue
            due = self._next_wall_s.get(msg_id, 0.0)
            if now >= due:
                self._send_stream(msg_id)
                period = max(interval_s / self.speedup, 1.0 / self.max_stream_wall_hz)
                if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
                    period = min(period, 1.0)
                self._next_wall_s[msg_id] = max(due + period, now) if now - due < period else now + period

    def _apply_faults(self) -> None:
        ap = self._ap
        while self._faults and self._faults[0].at_s <= ap.t_s:
            f = self._faults.pop(0)
            log.info("vehicle: scheduled fault %s at %.1f s", f.kind, ap.t_s)
            if f.kind == "link_pause":
                self._link_down_until_s = ap.t_s + (f.duration_s or 0.0)
            elif f.kind == "gps_loss":
                ap.set_gps_lost(True)
                self._gps_back_at_s = None if f.duration_s is None else ap.t_s + f.duration_s
            elif f.kind == "low_battery":
                ap.set_battery_pct(f.battery_pct if f.battery_pct is not None else 10.0)
            elif f.kind == "reposition_refused":
                self._refuse_reposition_until_s = math.inf if f.duration_s is None else ap.t_s + f.duration_s
        if self._gps_back_at_s is not None and ap.t_s >= self._gps_back_at_s:
            ap.set_gps_lost(False)
            self._gps_back_at_s = None

    def _sendto_peers(self, buf: bytes) -> None:
        assert self._sock is not None
        for addr in self._peers_now():
            try:
                self._sock.sendto(buf, addr)
                self.packets_out += 1
            except OSError as exc:  # e.g. ICMP port unreachable reported on a later send
                log.debug("vehicle: send to %s failed: %s", addr, exc)

    def _peers_now(self) -> list[tuple[str, int]]:
        peers = dict(self._peers)
        for t in self.targets:
            peers.setdefault(t, None)
        return list(peers)

    def _send(self, msg: Any) -> None:
        self._tx.send(msg)

    def _receive_all(self) -> None:
        assert self._sock is not None
        while True:
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # ICMP errors surface here on some systems
                log.debug("vehicle: receive error: %s", exc)
                return
            with self._lock:
                if self._link_down():
                    continue
                self.packets_in += 1
                if addr not in self._peers and addr not in self.targets:
                    log.info("vehicle: ground station at %s:%d", *addr)
                self._peers[addr] = None
                try:
                    msgs = self._rx.parse_buffer(data) or []
                except mavlink.MAVError as exc:
                    log.debug("vehicle: bad packet from %s: %s", addr, exc)
                    continue
                for msg in msgs:
                    self._handle(msg)

    # --- incoming -----------------------------------------------------------------------------
    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, SYSTEM_ID) and tc in (0, COMPONENT_ID)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA" or not self._for_us(msg):
            return
        handler = getattr(self, f"_on_{kind.lower()}", None)
        if handler is None:
            if kind not in ("HEARTBEAT", "SYSTEM_TIME", "PING"):
                log.debug("vehicle: ignored %s", kind)
            return
        try:
            handler(msg)
        except (ValueError, OverflowError, struct.error, SimulatorError) as exc:
            # a malformed request must not take the vehicle down; PX4 would refuse it too
            log.warning("vehicle: %s from %d/%d refused: %s", kind, msg.get_srcSystem(), msg.get_srcComponent(), exc)
            if kind in ("COMMAND_LONG", "COMMAND_INT"):
                self._ack(msg, DENIED)

    def _ack(self, msg: Any, result: int) -> None:
        self._send(mavlink.MAVLink_command_ack_message(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_command_long(self, msg: Any) -> None:
        p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        lat, lon, alt = p[4], p[5], p[6]
        self._command(msg, p, FRAME_GLOBAL, lat, lon, alt)

    def _on_command_int(self, msg: Any) -> None:
        if msg.command == CMD_DO_REPOSITION and self._ap.t_s < self._refuse_reposition_until_s:
            log.info("vehicle: fault: COMMAND_INT DO_REPOSITION refused with MAV_RESULT %d",
                     RESULT_UNSUPPORTED_MAV_FRAME)
            self._ack(msg, RESULT_UNSUPPORTED_MAV_FRAME)
            return
        p = [msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z]
        unset = (0, 2**31 - 1)
        lat = math.nan if msg.x in unset and msg.y in unset else msg.x * 1e-7
        lon = math.nan if msg.x in unset and msg.y in unset else msg.y * 1e-7
        self._command(msg, p, msg.frame, lat, lon, msg.z)

    def _alt_amsl(self, frame: int, alt: float) -> float:
        if not math.isfinite(alt):
            return math.nan
        if frame in (FRAME_GLOBAL_RELATIVE_ALT, FRAME_GLOBAL_RELATIVE_ALT_INT, FRAME_GLOBAL_TERRAIN_ALT,
                     FRAME_GLOBAL_TERRAIN_ALT_INT):
            return self.origin.alt_m + self._ap.home[2] + alt
        return alt

    def _command(self, msg: Any, p: list[float], frame: int, lat: float, lon: float, alt: float) -> None:
        ap, cmd = self._ap, msg.command
        log.debug("vehicle: command %d %s", cmd, p)
        result: int
        if cmd == CMD_COMPONENT_ARM_DISARM:
            force = abs(p[1] - FORCE_MAGIC) < 0.5
            result, _ = ap.arm(force) if p[0] > 0.5 else ap.disarm(force)
        elif cmd == CMD_NAV_TAKEOFF:
            result, _ = ap.takeoff(self._alt_amsl(frame, alt))
        elif cmd == CMD_NAV_LAND:
            result, _ = ap.land(lat, lon)
        elif cmd == CMD_NAV_RETURN_TO_LAUNCH:
            result, _ = ap.return_to_launch()
        elif cmd == CMD_DO_REPOSITION:
            result, _ = ap.reposition(lat, lon, self._alt_amsl(frame, alt), p[0])
        elif cmd == CMD_DO_SET_MODE:
            result = self._set_mode(int(p[0]), int(p[1]), int(p[2]))
        elif cmd == CMD_DO_CHANGE_SPEED:
            result, _ = ap.change_speed(p[1])
        elif cmd == CMD_DO_SET_HOME:
            result, _ = ap.set_home(p[0] > 0.5, lat, lon, self._alt_amsl(frame, alt))
        elif cmd == CMD_MISSION_START:
            result, _ = ap.mission_start(int(p[0]) if math.isfinite(p[0]) else 0)
        elif cmd == CMD_DO_PAUSE_CONTINUE:
            result, _ = ap.set_mode(FlightMode.MISSION if p[0] > 0.5 else FlightMode.HOLD)
        elif cmd == CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(int(p[0]), p[1])
        elif cmd == CMD_GET_MESSAGE_INTERVAL:
            result = self._get_interval(int(p[0]))
        elif cmd == CMD_REQUEST_MESSAGE:
            msg_id = int(p[0])
            result = ACCEPTED if self._can_send(msg_id) else UNSUPPORTED
            self._ack(msg, result)
            if result == ACCEPTED:
                self._send_stream(msg_id)
            return
        elif cmd == CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._ack(msg, ACCEPTED)
            self._send_stream(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
            return
        else:
            log.debug("vehicle: unsupported command %d", cmd)
            result = UNSUPPORTED
        self._ack(msg, result)

    def _set_mode(self, base_mode: int, main: int, sub: int) -> int:
        if not base_mode & px4.MODE_FLAG_CUSTOM_MODE_ENABLED:
            return UNSUPPORTED
        mode = px4.mode_from_px4(main, sub)
        if mode is None:
            self._ap.messages.append((4, f"Mode {main}.{sub} not available (no RC)"))
            return DENIED
        result, _ = self._ap.set_mode(mode)
        return result

    def _can_send(self, msg_id: int) -> bool:
        return msg_id in self._intervals_s

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        if not self._can_send(msg_id) or not math.isfinite(interval_us):
            return UNSUPPORTED
        if interval_us < 0:
            self._intervals_s[msg_id] = None
        elif interval_us == 0:
            self._intervals_s[msg_id] = _DEFAULT_INTERVALS_S[msg_id]
        else:
            self._intervals_s[msg_id] = interval_us * 1e-6
        self._next_wall_s[msg_id] = 0.0
        return ACCEPTED

    def _get_interval(self, msg_id: int) -> int:
        if not self._can_send(msg_id):
            return UNSUPPORTED
        iv = self._intervals_s[msg_id]
        self._send(mavlink.MAVLink_message_interval_message(msg_id, -1 if iv is None else int(iv * 1e6)))
        return ACCEPTED

    # parameters
    def _send_param(self, index: int) -> None:
        spec, value = self._ap.params.entry(index)
        self._send(mavlink.MAVLink_param_value_message(
            spec.name.encode(), px4.encode_param_value(value, spec.type), spec.type,
            len(self._ap.params), index))

    def _on_param_request_list(self, msg: Any) -> None:
        for k in range(len(self._ap.params)):
            self._send_param(k)

    def _on_param_request_read(self, msg: Any) -> None:
        name = _param_name(msg.param_id)
        k = self._ap.params.index_of(name) if msg.param_index < 0 else msg.param_index
        if k is None or not 0 <= k < len(self._ap.params):
            log.debug("vehicle: unknown parameter %r / index %d requested", name, msg.param_index)
            return  # PX4 does not answer for an unknown parameter
        self._send_param(k)

    def _on_param_set(self, msg: Any) -> None:
        name = _param_name(msg.param_id)
        k = self._ap.params.index_of(name)
        if k is None:
            log.debug("vehicle: PARAM_SET of unknown parameter %r", name)
            return
        spec, _ = self._ap.params.entry(k)
        value = px4.decode_param_value(msg.param_value, spec.type)
        if math.isfinite(value):
            self._ap.params.set(name, value)
            log.info("vehicle: parameter %s = %g", name, value)
        self._send_param(k)

    # missions
    def _mission_ack(self, msg: Any, mission_type: int, result: int) -> None:
        self._send(mavlink.MAVLink_mission_ack_message(
            msg.get_srcSystem(), msg.get_srcComponent(), result, mission_type))

    def _on_mission_count(self, msg: Any) -> None:
        mtype = getattr(msg, "mission_type", 0)
        if msg.count == 0:
            self._ap.set_mission(mtype, [])
            self._upload = None
            self._mission_ack(msg, mtype, mavlink.MAV_MISSION_ACCEPTED)
            return
        if msg.count > 1000:
            self._mission_ack(msg, mtype, mavlink.MAV_MISSION_NO_SPACE)
            return
        self._upload = _Upload(mtype, msg.count, [], msg.get_srcSystem(), msg.get_srcComponent(),
                               self._wall_last_s)
        self._request_next()

    def _request_next(self) -> None:
        up = self._upload
        assert up is not None
        self._send(mavlink.MAVLink_mission_request_int_message(
            up.sysid, up.compid, len(up.items), up.mission_type))

    def _upload_timeouts(self, now: float) -> None:
        up = self._upload
        if up is None or now - up.last_wall_s < 0.25:
            return
        up.retries += 1
        up.last_wall_s = now
        if up.retries > 8:
            log.info("vehicle: mission upload timed out at item %d of %d", len(up.items), up.count)
            self._upload = None
            return
        self._request_next()

    def _on_mission_item_int(self, msg: Any) -> None:
        self._mission_item(msg, msg.x, msg.y)

    def _on_mission_item(self, msg: Any) -> None:
        glob = msg.frame in (FRAME_GLOBAL, FRAME_GLOBAL_RELATIVE_ALT, FRAME_GLOBAL_TERRAIN_ALT)
        x = round(msg.x * 1e7) if glob else int(msg.x)
        y = round(msg.y * 1e7) if glob else int(msg.y)
        self._mission_item(msg, x, y)

    def _mission_item(self, msg: Any, x: int, y: int) -> None:
        up = self._upload
        mtype = getattr(msg, "mission_type", 0)
        if up is None or mtype != up.mission_type:
            return
        if msg.seq != len(up.items):
            self._request_next()  # out of order or repeated: ask again for the one we need
            return
        if mtype == 0 and not mission_command_supported(msg.command):
            self._upload = None
            self._mission_ack(msg, mtype, mavlink.MAV_MISSION_UNSUPPORTED)
            return
        if mtype == 0 and msg.frame not in (FRAME_GLOBAL, FRAME_GLOBAL_INT, FRAME_GLOBAL_RELATIVE_ALT,
                                            FRAME_GLOBAL_RELATIVE_ALT_INT, FRAME_GLOBAL_TERRAIN_ALT,
                                            FRAME_GLOBAL_TERRAIN_ALT_INT, FRAME_MISSION):
            self._upload = None
            self._mission_ack(msg, mtype, mavlink.MAV_MISSION_UNSUPPORTED_FRAME)
            return
        up.items.append(MissionItem(msg.seq, msg.frame, msg.command, msg.current, msg.autocontinue,
                                    msg.param1, msg.param2, msg.param3, msg.param4, x, y, msg.z, mtype))
        up.last_wall_s, up.retries = self._wall_last_s, 0
        if len(up.items) < up.count:
            self._request_next()
            return
        self._ap.set_mission(mtype, up.items)
        self._upload = None
        log.info("vehicle: mission type %d uploaded, %d items", mtype, len(up.items))
        self._mission_ack(msg, mtype, mavlink.MAV_MISSION_ACCEPTED)
        if mtype == 0:
            self._send_stream(mavlink.MAVLINK_MSG_ID_MISSION_CURRENT)

    def _on_mission_request_list(self, msg: Any) -> None:
        mtype = getattr(msg, "mission_type", 0)
        self._send(mavlink.MAVLink_mission_count_message(
            msg.get_srcSystem(), msg.get_srcComponent(), len(self._ap.mission_items(mtype)), mtype))

    def _on_mission_request_int(self, msg: Any) -> None:
        self._send_item(msg, as_int=True)

    def _on_mission_request(self, msg: Any) -> None:
        self._send_item(msg, as_int=False)

    def _send_item(self, msg: Any, as_int: bool) -> None:
        mtype = getattr(msg, "mission_type", 0)
        items = self._ap.mission_items(mtype)
        if not 0 <= msg.seq < len(items):
            self._mission_ack(msg, mtype, mavlink.MAV_MISSION_INVALID_SEQUENCE)
            return
        it = items[msg.seq]
        current = int(mtype == 0 and msg.seq == self._ap.mission.current)
        if as_int:
            out = mavlink.MAVLink_mission_item_int_message(
                msg.get_srcSystem(), msg.get_srcComponent(), it.seq, it.frame, it.command, current,
                it.autocontinue, it.param1, it.param2, it.param3, it.param4, it.x, it.y, it.z, mtype)
        else:
            glob = it.frame in (FRAME_GLOBAL, FRAME_GLOBAL_INT, FRAME_GLOBAL_RELATIVE_ALT,
                                FRAME_GLOBAL_RELATIVE_ALT_INT, FRAME_GLOBAL_TERRAIN_ALT, FRAME_GLOBAL_TERRAIN_ALT_INT)
            scale = 1e-7 if glob else 1.0
            out = mavlink.MAVLink_mission_item_message(
                msg.get_srcSystem(), msg.get_srcComponent(), it.seq, it.frame, it.command, current,
                it.autocontinue, it.param1, it.param2, it.param3, it.param4, it.x * scale, it.y * scale,
                it.z, mtype)
        self._send(out)

    def _on_mission_ack(self, msg: Any) -> None:
        log.debug("vehicle: mission ack %d from ground station", msg.type)

    def _on_mission_clear_all(self, msg: Any) -> None:
        mtype = getattr(msg, "mission_type", 0)
        self._ap.set_mission(mtype, [])
        self._mission_ack(msg, mtype, mavlink.MAV_MISSION_ACCEPTED)

    def _on_mission_set_current(self, msg: Any) -> None:
        if self._ap.set_mission_current(msg.seq):
            self._send_stream(mavlink.MAVLINK_MSG_ID_MISSION_CURRENT)
        else:
            self._mission_ack(msg, 0, mavlink.MAV_MISSION_INVALID_SEQUENCE)

    # offboard
    def _on_set_position_target_local_ned(self, msg: Any) -> None:
        if msg.coordinate_frame != FRAME_LOCAL_NED:
            log.debug("vehicle: offboard frame %d not supported", msg.coordinate_frame)
            return
        pos = None if msg.type_mask & 0b111 == 0b111 else [msg.y, msg.x, -msg.z]
        vel = None if msg.type_mask & 0b111000 == 0b111000 else [msg.vy, msg.vx, -msg.vz]
        if pos is not None and not all(math.isfinite(v) for v in pos):
            pos = None
        self._ap.offboard_setpoint(pos, vel, self._wall_last_s)

    def _on_set_position_target_global_int(self, msg: Any) -> None:
        if msg.type_mask & 0b111 == 0b111:
            vel = [msg.vy, msg.vx, -msg.vz]
            self._ap.offboard_setpoint(None, vel, self._wall_last_s)
            return
        alt = self._alt_amsl(msg.coordinate_frame, msg.alt)
        pos = self._ap.lla_to_enu(msg.lat_int * 1e-7, msg.lon_int * 1e-7, alt)
        self._ap.offboard_setpoint(pos, None, self._wall_last_s)

    def _on_timesync(self, msg: Any) -> None:
        if msg.tc1 == 0:
            self._send(mavlink.MAVLink_timesync_message(int(self._ap.t_s * 1e9), msg.ts1))

    # --- outgoing -----------------------------------------------------------------------------
    def _send_stream(self, msg_id: int) -> None:
        ap = self._ap
        t_ms = int(ap.t_s * 1e3) & 0xFFFFFFFF
        t_us = int(ap.t_s * 1e6)
        M = mavlink
        if msg_id == M.MAVLINK_MSG_ID_HEARTBEAT:
            if ap.charge_state >= CHARGE_EMERGENCY or (ap.gps_lost and ap.in_air):
                status = M.MAV_STATE_CRITICAL
            else:
                status = M.MAV_STATE_ACTIVE if ap.armed else M.MAV_STATE_STANDBY
            self._send(M.MAVLink_heartbeat_message(
                M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, px4.px4_base_mode(ap.mode, ap.armed),
                px4.px4_custom_mode(ap.mode), status, 3))
        elif msg_id == M.MAVLINK_MSG_ID_SYS_STATUS:
            health = _SENSORS_PRESENT & ~(_S_GPS | _S_PREARM)
            if ap.gps_ok:
                health |= _S_GPS
            if ap.gps_ok and ap.home_set and ap.charge_state < CHARGE_CRITICAL:
                health |= _S_PREARM
            v_mv, i_ca = self._battery_electrics()
            self._send(M.MAVLink_sys_status_message(
                _SENSORS_PRESENT, _SENSORS_PRESENT, health, 250, v_mv, i_ca, int(ap.battery_pct),
                0, 0, 0, 0, 0, 0))
        elif msg_id == M.MAVLINK_MSG_ID_GPS_RAW_INT:
            if not ap.gps_ok:  # a receiver without a fix: no position, unknown accuracy
                self._send(M.MAVLink_gps_raw_int_message(
                    t_us, 1, 0, 0, 0, 65535, 65535, 65535, 65535, 0, 0, 0, 0, 0, 0, 0))
                return
            est = ap.estimated_position()
            lat, lon, alt = ap.enu_to_lla(est)
            vh = math.hypot(ap.vel[0], ap.vel[1])
            cog = int((math.degrees(math.atan2(ap.vel[0], ap.vel[1])) % 360) * 100) if vh > 0.3 else 65535
            sigma_mm = int(max(self.vehicle.gps_sigma_m, 0.01) * 1000)
            self._send(M.MAVLink_gps_raw_int_message(
                t_us, 3, round(lat * 1e7), round(lon * 1e7), int(alt * 1000), 80, 120,
                int(vh * 100), cog, 12, int(alt * 1000), sigma_mm, int(sigma_mm * 1.5), 100, 0, 0))
        elif msg_id == M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            if not ap.gps_ok:
                return  # no global position estimate: PX4 stops publishing it
            est = ap.estimated_position()
            lat, lon, alt = ap.enu_to_lla(est)
            self._send(M.MAVLink_global_position_int_message(
                t_ms, round(lat * 1e7), round(lon * 1e7), int(alt * 1000),
                int((est[2] - ap.home[2]) * 1000), int(ap.vel[1] * 100), int(ap.vel[0] * 100),
                int(-ap.vel[2] * 100), int((math.degrees(ap.yaw_rad) % 360) * 100)))
        elif msg_id == M.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            if not ap.gps_ok:
                return
            est = ap.estimated_position()
            self._send(M.MAVLink_local_position_ned_message(
                t_ms, est[1], est[0], -est[2], ap.vel[1], ap.vel[0], -ap.vel[2]))
        elif msg_id == M.MAVLINK_MSG_ID_ATTITUDE:
            roll, pitch = ap.tilt_rad()
            self._send(M.MAVLink_attitude_message(t_ms, roll, pitch, _wrap_pi(ap.yaw_rad), 0.0, 0.0, 0.0))
        elif msg_id == M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            roll, pitch = ap.tilt_rad()
            q = _quaternion(roll, pitch, _wrap_pi(ap.yaw_rad))
            self._send(M.MAVLink_attitude_quaternion_message(t_ms, *q, 0.0, 0.0, 0.0, [0.0, 0.0, 0.0, 0.0]))
        elif msg_id == M.MAVLINK_MSG_ID_ALTITUDE:
            est_up = float(ap.estimated_position()[2]) if ap.gps_ok else ap.pos[2]
            amsl = self.origin.alt_m + est_up
            self._send(M.MAVLink_altitude_message(
                t_us, amsl, amsl, est_up, est_up - ap.home[2], math.nan, math.nan))  # no range finder
        elif msg_id == M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            self._send(M.MAVLink_extended_sys_state_message(0, ap.landed_state))
        elif msg_id == M.MAVLINK_MSG_ID_VFR_HUD:
            vh = math.hypot(ap.vel[0], ap.vel[1])
            self._send(M.MAVLink_vfr_hud_message(
                vh, vh, int(math.degrees(ap.yaw_rad) % 360), 50 if ap.in_air else 0,
                self.origin.alt_m + ap.pos[2], ap.vel[2]))
        elif msg_id == M.MAVLINK_MSG_ID_HOME_POSITION:
            if not ap.home_set:
                return
            lat, lon, alt = ap.enu_to_lla(ap.home)
            h = ap.home
            self._send(M.MAVLink_home_position_message(
                round(lat * 1e7), round(lon * 1e7), int(alt * 1000), h[1], h[0], -h[2],
                [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t_us))
        elif msg_id == M.MAVLINK_MSG_ID_BATTERY_STATUS:
            v_mv, i_ca = self._battery_electrics()
            used_mah = int((100.0 - ap.battery_pct) / 100.0 * 5000)
            remaining_s = int(ap.battery_pct / 100.0 * self.vehicle.battery_capacity_s)
            self._send(M.MAVLink_battery_status_message(
                0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, 32767, [v_mv] + [65535] * 9, i_ca,
                used_mah, -1, int(ap.battery_pct), remaining_s, ap.charge_state, [0, 0, 0, 0], 0, 0))
        elif msg_id == M.MAVLINK_MSG_ID_MISSION_CURRENT:
            m = ap.mission
            self._send(M.MAVLink_mission_current_message(
                m.current, len(m.items), ap.mission_state, 1 if ap.mode is FlightMode.MISSION else 2))
        elif msg_id == M.MAVLINK_MSG_ID_SYSTEM_TIME:
            self._send(M.MAVLink_system_time_message(int((self._unix_start_s + ap.t_s) * 1e6), t_ms))
        elif msg_id == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            major, minor, patch = px4.PX4_VERSION
            sw = px4.px4_sw_version(major, minor, patch)
            self._send(M.MAVLink_autopilot_version_message(
                px4.PX4_CAPABILITIES, sw, sw, 0, 0, list(b"51a5eed1"), [0] * 8, [0] * 8, 0x26AC, 0x0011,
                0x5EED0000 | SYSTEM_ID, [0] * 18))

    def _battery_electrics(self) -> tuple[int, int]:
        """(voltage [mV], current [cA]) of a 4S LiPo: 3.6 V (empty) .. 4.05 V (full) per cell."""
        ap = self._ap
        cells = int(ap.params["BAT1_N_CELLS"])
        v = cells * (3.6 + 0.45 * ap.battery_pct / 100.0)
        amps = 15.0 if ap.in_air else (1.5 if ap.armed else 0.5)
        return int(v * 1000), int(amps * 100)


def _param_name(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", errors="replace")
    return str(raw).split("\x00", 1)[0]


def _quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the ZYX Euler angles (aerospace convention, body FRD in NED)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


# --- standalone -------------------------------------------------------------------------------
def _parse_target(parts: list[str]) -> tuple[str, int] | None:
    text = " ".join(parts).strip()
    for prefix in ("udp://", "udpout://", "udp "):
        if text.startswith(prefix):
            text = text[len(prefix):].strip()
    if text in ("", "none"):
        return None
    host, _, port = text.rpartition(":")
    try:
        return (host or "127.0.0.1", int(port))
    except ValueError as exc:
        raise SimulatorError(f"--target must be [udp] HOST:PORT, got {' '.join(parts)!r}") from exc


def main(argv: list[str] | None = None) -> int:
    """`python -m sitl_scenarios.vehicle --scenario FILE [--speedup X] [--target udp HOST:PORT]`."""
    ap = argparse.ArgumentParser(prog="python -m sitl_scenarios.vehicle", description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="paper", help="scenario file or bundled name (default: paper)")
    ap.add_argument("--speedup", type=float, default=1.0, help="simulated seconds per wall second")
    ap.add_argument("--target", nargs="+", action="append", default=None,
                    help="where to send before a ground station talks: [udp] HOST:PORT (repeatable; "
                         "default 127.0.0.1:14540), or none")
    ap.add_argument("--bind", default="0.0.0.0:0", help="local HOST:PORT (port 0: any)")
    ap.add_argument("--seed", type=int, default=None, help="GPS noise seed (default: the scenario's)")
    ap.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        scenario = load_scenario(args.scenario)
        bind_host, _, bind_port = args.bind.rpartition(":")
        targets = [_parse_target(t) for t in (args.target or [["127.0.0.1:14540"]])]
        kwargs: dict[str, Any] = {"speedup": args.speedup, "target": [t for t in targets if t is not None],
                                  "bind": (bind_host or "0.0.0.0", int(bind_port))}
        if args.seed is not None:
            kwargs["seed"] = args.seed
        sim = VehicleSimulator.from_scenario(scenario, **kwargs)
        with sim:
            t_end = None if args.duration is None else time.monotonic() + args.duration
            while t_end is None or time.monotonic() < t_end:
                time.sleep(min(2.0, max(0.0, (t_end or math.inf) - time.monotonic())))
                s = sim.state()
                e, n, u = s.pos_enu_m
                log.info("t=%.1f s %s armed=%s pos_enu=(%.1f, %.1f, %.1f) battery=%.0f%%",
                         s.t_s, s.mode, s.armed, e, n, u, s.battery_pct)
    except KeyboardInterrupt:
        return 0
    except (ScenarioError, SimulatorError, ValueError) as exc:
        log.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

__all__ = ["FaultEvent", "VehicleSimulator", "VehicleState", "faults_from_scenario", "main"]
