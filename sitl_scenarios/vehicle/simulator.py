"""The built-in vehicle's simulator: the autopilot, its link and protocols, run in a thread
(docs/design.md §9). :class:`VehicleSimulator` is the public API; see :mod:`sitl_scenarios.vehicle`.

Time: the simulation runs `speedup` times faster than the wall clock, in fixed steps of
SIM_STEP_S simulated seconds (the wall time a tick brings is owed to it and worked off step by
step), and the streams are scheduled in simulated time after each step: what the vehicle does and
sends, every MAVLink timestamp and every stream's rate, is the same on an idle and on a busy
machine, only later. Should the simulation thread fall more than MAX_BEHIND_WALL_S behind the wall
clock (a starved process), it drops the excess and runs on from there, slower than `speedup` (and
says so in the log), rather than leaping. The message intervals a ground station sets
(SET_MESSAGE_INTERVAL) are simulated time too. On the wire a stream is capped at
`max_stream_wall_hz` and the heartbeat is sent at least once per wall second, whatever the
speedup, so MAVSDK's wall-clock link timeout (about 3 s) never fires on a healthy link. Fault
durations are simulated seconds.
"""

from __future__ import annotations

import asyncio
import logging
import math
import select
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from estimator.geodesy import Origin
from sitl_scenarios.scenario import Scenario, VehicleConfig
from sitl_scenarios.vehicle.autopilot import VehicleState
from sitl_scenarios.vehicle.faults import FaultEvent, VehicleFaults, faults_from_scenario
from sitl_scenarios.vehicle.link import UdpLink
from sitl_scenarios.vehicle.mav import DENIED
from sitl_scenarios.vehicle.missions import MissionProtocol
from sitl_scenarios.vehicle.parameters import ParamProtocol
from sitl_scenarios.vehicle.personality import personality
from sitl_scenarios.vehicle.streams import StreamSchedule
from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

SYSTEM_ID = 1
COMPONENT_ID = 1
DEFAULT_TARGET = ("127.0.0.1", 14540)
#: messages a ground station sends that need no answer
_SILENT = ("HEARTBEAT", "SYSTEM_TIME", "PING")
#: the simulation step [simulated s]: the 50 Hz streams get a fresh state each
SIM_STEP_S = 0.02
#: the most wall time [s] the simulation works off at once; beyond it falls behind the wall clock
MAX_BEHIND_WALL_S = 1.0


class VehicleSimulator:
    """A PX4-like multicopter on a UDP MAVLink link, run in its own thread.

    origin: home and ENU origin (the vehicle starts there, on the ground); vehicle: speeds, GPS
    noise, battery; seed: GPS noise generator seed; speedup: simulated seconds per wall second;
    target: (host, port), or a list of them, the vehicle sends to before anyone talks to it (None:
    only answer), like PX4's API link to 127.0.0.1:14540 (and its GCS link to 14550); whoever sends
    to the vehicle is answered too; bind: local (host, port), port 0 picks a free one; faults:
    scheduled fault events; gps_fix_delay_s: simulated time until the first GPS fix;
    tick_wall_s: simulation step in wall seconds; max_stream_wall_hz: cap of each stream's rate
    on the wire; clock: the wall clock [s] the simulation follows (time.monotonic; a test can hand
    in one it moves itself); system_id: its MAVLink system id (1..255; a fleet's vehicle i is
    i + 1, as PX4's `px4 -i i`), also its MAV_SYS_ID / SYSID_THISMAV parameter.

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
        clock: Callable[[], float] = time.monotonic,
        system_id: int = SYSTEM_ID,
    ) -> None:
        if not (math.isfinite(speedup) and speedup > 0):
            raise SimulatorError(f"speedup must be a positive number, got {speedup!r}")
        if isinstance(system_id, bool) or not isinstance(system_id, int) or not 1 <= system_id <= 255:
            raise SimulatorError(f"system_id must be an integer in 1..255, got {system_id!r}")
        self.system_id = system_id
        if not tick_wall_s > 0 or not max_stream_wall_hz > 0:
            raise SimulatorError("tick_wall_s and max_stream_wall_hz must be positive")
        self.origin = origin
        self.vehicle = vehicle or VehicleConfig()
        self.speedup = float(speedup)
        if target is None:
            targets: list[tuple[str, int]] = []
        elif isinstance(target, tuple):
            targets = [target]
        else:
            targets = [tuple(t) for t in target]
        self.tick_wall_s = tick_wall_s
        self.max_stream_wall_hz = max_stream_wall_hz
        self._clock = clock
        self._rng = np.random.default_rng([int(seed), 0x5EED])
        kind = personality(self.vehicle.autopilot)  # PX4 or ArduCopter on the wire and in flight
        self._ap = kind.autopilot(origin, self.vehicle, self._rng, gps_fix_delay_s=gps_fix_delay_s)
        for name in ("MAV_SYS_ID", "SYSID_THISMAV"):  # the personality's own name for it
            if self._ap.params.index_of(name) is not None:
                self._ap.params.set(name, system_id)
        self._faults = VehicleFaults(faults)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._link = UdpLink(targets, bind, system_id, COMPONENT_ID)
        self._wall_last_s = 0.0
        self._owed_s = 0.0  # simulated time the wall clock brought that is not yet simulated
        self.behind_s = 0.0  # simulated time dropped when the thread fell behind the wall clock
        self._gps_loss_when: Callable[[VehicleState], bool] | None = None
        self._schedule = StreamSchedule(self.speedup, max_stream_wall_hz, kind.intervals_s)
        self._streams = kind.streams(self._ap, origin, self.vehicle, time.time(), system_id)
        wall_s = self._wall_now
        self._commands = kind.commands(self._ap, origin, self._send, self._send_stream, self._schedule,
                                         self._faults, wall_s)
        self._missions = MissionProtocol(self._ap, self._send, self._send_stream, wall_s)
        self._handlers: dict[str, Callable[[Any], None]] = {
            **self._commands.handlers(),
            **ParamProtocol(self._ap, self._send).handlers(),
            **self._missions.handlers(),
        }

    @classmethod
    def from_scenario(cls, scenario: Scenario, index: int = 0, **kwargs: Any) -> VehicleSimulator:
        """The scenario's vehicle `index` (0..fleet_size−1) with the scenario's vehicle, seed and
        `[[faults.vehicle]]`: system id index + 1, home at the launch point the fast mode gives it
        (sitl_scenarios.fleet.vehicle_home; a one-vehicle scenario's is its origin). Each vehicle of
        a fleet draws its GPS noise from its own seed (the scenario's for vehicle 0) and needs its
        own `bind`/`target` ports (the caller's). Its faults: the `[[faults.vehicle]]` events that
        name it (`vehicle` = its `[[vehicles]]` id; no id: vehicle 0), as the fast mode reads them."""
        from sitl_scenarios.fleet import vehicle_home

        home = vehicle_home(scenario, index)
        if kwargs.get("seed") is None:
            kwargs["seed"] = scenario.seed
        if index > 0:
            kwargs["seed"] = int(np.random.SeedSequence([int(kwargs["seed"]), index]).generate_state(1)[0])
        if kwargs.get("faults") is None:
            ids = [v.id for v in scenario.mission.vehicles]
            kwargs["faults"] = [ev for ev in scenario.faults.vehicle
                                if (ids.index(ev.vehicle) if ev.vehicle else 0) == index]
        kwargs.setdefault("system_id", index + 1)
        return cls(home, scenario.vehicle, **kwargs)

    # --- lifecycle ----------------------------------------------------------------------------
    def start(self) -> None:
        """Bind the socket and start the simulation thread (returns at once)."""
        if self._thread is not None:
            raise SimulatorError("vehicle simulator already started")
        self._link.open()
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
        self._link.close()
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
        return self._link.local_address

    @property
    def targets(self) -> list[tuple[str, int]]:
        return self._link.targets

    @property
    def bind(self) -> tuple[str, int]:
        return self._link.bind

    @property
    def packets_in(self) -> int:
        return self._link.packets_in

    @property
    def packets_out(self) -> int:
        return self._link.packets_out

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
            self._faults.pause_link(self._ap.t_s, duration_s)
            log.info("vehicle: link paused for %.1f s (sim)", duration_s)

    def resume_link(self) -> None:
        with self._lock:
            self._faults.resume_link()

    def lose_gps(self, duration_s: float | None = None) -> None:
        """No GPS fix (for duration_s simulated seconds, or until :meth:`restore_gps`)."""
        with self._lock:
            self._faults.lose_gps(self._ap, duration_s)

    def lose_gps_when(self, predicate: Callable[[VehicleState], bool]) -> None:
        """No GPS fix from the first simulation step after which predicate(true state) holds: the
        simulation thread judges it at each step, however late a ground station would notice. The
        loss is reported in that step (a GPS_RAW_INT off its 5 Hz beat), so that the first report
        without a fix shows the state the loss was judged on: between two reports it would be seen
        up to 0.2 s later, the vehicle slower by then, and what the figures measure from the report
        would vary with the phase of the beat."""
        with self._lock:
            self._gps_loss_when = predicate

    def restore_gps(self) -> None:
        with self._lock:
            self._faults.restore_gps(self._ap)

    def refuse_reposition(self, duration_s: float | None = None) -> None:
        """Answer COMMAND_INT DO_REPOSITION with MAV_RESULT 9 (for duration_s simulated seconds, or
        for ever), like the PX4 build before PX4 #26626 (fault `reposition_refused`)."""
        with self._lock:
            self._faults.refuse_reposition(self._ap.t_s, duration_s)

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
        return self._faults.link_down(self._ap.t_s)

    # --- thread -------------------------------------------------------------------------------
    def _wall_now(self) -> float:
        return self._wall_last_s

    # --- thread -------------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._wall_last_s = self._clock()
            next_tick = self._wall_last_s
            while not self._stop.is_set():
                now = self._clock()
                if now >= next_tick:
                    with self._lock:
                        self._tick(now)
                    next_tick = max(next_tick + self.tick_wall_s, now)
                sock = self._link.sock
                assert sock is not None
                wait_s = min(max(0.0, next_tick - self._clock()), self.tick_wall_s)
                readable, _, _ = select.select([sock], [], [], wait_s)
                if readable:
                    self._receive_all()
        except BaseException as exc:  # handed to stop()/state(); the thread must not die silently
            log.exception("vehicle simulator thread failed")
            self._error = exc

    def _tick(self, now: float) -> None:
        dt_wall = now - self._wall_last_s
        self._wall_last_s = now
        owed = self._owed_s + dt_wall * self.speedup
        max_owed = MAX_BEHIND_WALL_S * self.speedup
        if owed > max_owed:
            log.warning("vehicle simulator fell %.2f s (simulated) behind the wall clock; running on from here",
                        owed - max_owed)
            self.behind_s += owed - max_owed
            owed = max_owed
        while owed >= SIM_STEP_S - 1e-9:
            owed -= SIM_STEP_S
            self._step(now)
        self._owed_s = max(owed, 0.0)
        self._missions.upload_timeouts(now)

    def _step(self, now: float) -> None:
        """One SIM_STEP_S of simulation, then what the vehicle sends at its end."""
        ap = self._ap
        ap.step(SIM_STEP_S, now)
        if self._gps_loss_when is not None and self._gps_loss_when(ap.snapshot(link_up=not self._link_down())):
            self._gps_loss_when = None
            self._faults.lose_gps(ap, None)
            self._schedule.send_next(mavlink.MAVLINK_MSG_ID_GPS_RAW_INT)
        self._faults.apply(ap)
        if self._link_down():
            ap.messages.clear()
            ap.reached.clear()
            return
        if self._faults.link_resumed(ap.t_s):
            log.info("vehicle: link resumed")
        for severity, text in ap.messages:
            self._send(mavlink.MAVLink_statustext_message(severity, text.encode()[:50], 0, 0))
        ap.messages.clear()
        for seq in ap.reached:
            self._send(mavlink.MAVLink_mission_item_reached_message(seq))
        ap.reached.clear()
        for msg_id in self._schedule.due(ap.t_s, now):
            self._send_stream(msg_id)

    def _send(self, msg: Any) -> None:
        self._link.send(msg)

    def _send_stream(self, msg_id: int) -> None:
        msg = self._streams.encode(msg_id)
        if msg is not None:
            self._send(msg)

    def _receive_all(self) -> None:
        for data, addr in self._link.datagrams():
            with self._lock:
                if self._link_down():
                    continue
                try:
                    msgs = self._link.accept(data, addr)
                except mavlink.MAVError as exc:
                    log.debug("vehicle: bad packet from %s: %s", addr, exc)
                    continue
                for msg in msgs:
                    self._handle(msg)

    # --- incoming -----------------------------------------------------------------------------
    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.system_id) and tc in (0, COMPONENT_ID)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA" or not self._for_us(msg):
            return
        handler = self._handlers.get(kind)
        if handler is None:
            if kind not in _SILENT:
                log.debug("vehicle: ignored %s", kind)
            return
        try:
            handler(msg)
        except (ValueError, OverflowError, struct.error, SimulatorError) as exc:
            # a malformed request must not take the vehicle down; PX4 would refuse it too
            log.warning("vehicle: %s from %d/%d refused: %s", kind, msg.get_srcSystem(), msg.get_srcComponent(), exc)
            if kind in ("COMMAND_LONG", "COMMAND_INT"):
                self._commands.ack(msg, DENIED)


__all__ = ["COMPONENT_ID", "DEFAULT_TARGET", "SYSTEM_ID", "FaultEvent", "VehicleSimulator", "VehicleState",
           "faults_from_scenario"]
