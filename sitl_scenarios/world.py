"""The simulated world of `uavloc sim`, in a process of its own (docs/architecture.md, "The world").

The built-in vehicle(s) (`sitl_scenarios.vehicle.VehicleSimulator`, each in a thread), the
simulated gNB(s) (`sitl_scenarios.gnb.SimulatedGnb`, on the child's event loop) and a fleet's shared
cells (`sitl_scenarios.gnb.cells.SharedCells`) run in one child process, as a real autopilot and
gNB are other processes than the mission: a busy controller cannot make the world wait, and a busy
world is seen by the controller as what it is (late telemetry, late answers), not hidden by one
event loop serving both. The world knows the true positions; the controller reaches it only over
its sockets (MAVLink over UDP, the gNB's telnet/REST/T-tracer over TCP), exactly as PX4 and a gNB.

Parent side: :class:`WorldProcess` (an async context manager) starts the child from
multiprocessing's fork server (:func:`world_context`: the parent has threads and an event loop, so
no plain 'fork'; the server imports the world's modules once per parent), hands it a
:class:`WorldSpec`, and reads back the :class:`WorldInfo` (the ports the child opened on 127.0.0.1,
port 0) through a pipe. That pipe is also the control channel of the fault tests: one request at a
time, `(op, args)` -> `("ok", value)` or `("err", message)`; `sitl_scenarios.world_proxy` wraps it
in objects with the simulators' own method names. The child's log records of level WARNING and up
(everything at the parent's DEBUG) come back through a queue into the parent's logging; its stdout
and stderr go to /dev/null, so no library chatter reaches the user's terminal.

Life: closing the WorldProcess asks the child to stop (it closes the gNBs, then the vehicles) and
waits STOP_TIMEOUT_S, then terminates it, then kills it. The child ignores SIGINT (Ctrl-C at the
terminal reaches the whole process group; the parent decides when the world ends: after its RTL)
and ends on its own when the pipe reaches end of file, i.e. when the parent is gone however it
died (also SIGKILL); the process is a daemon, so a parent that exits normally without closing it
ends it too.

Time: each gNB stamps a range with its vehicle's simulated clock and computes it from that same
vehicle's true position (one snapshot of the vehicle, taken once per event-loop step: `_Truth`),
so the range is the true distance at the time it is stamped however late the answer leaves.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import functools
import logging
import logging.handlers
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from sitl_scenarios.gnb.faults import GnbFaults
from sitl_scenarios.scenario import Scenario
from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

#: the longest wait for the child to open its ports (a loaded machine imports slowly) [s]
START_TIMEOUT_S = 90.0
#: the longest wait for an answer on the control channel [s]
REQUEST_TIMEOUT_S = 20.0
#: after a stop request, how long the child has to close its simulators, then after terminate() [s]
STOP_TIMEOUT_S = 8.0
KILL_TIMEOUT_S = 2.0
#: how many vehicle snapshots the world remembers per vehicle (the stamp test reads them)
TRACK_LEN = 50_000


@dataclass(frozen=True)
class WorldSpec:
    """What the world is made of: the scenario, seed (vehicles' GPS noise, gNBs' radio draws),
    speedup (simulated seconds per wall second), the UDP ports the controller's MAVSDK listens on
    (one per vehicle: each vehicle sends there, as PX4 to 14540), the wire cap of the telemetry
    streams [Hz], and what the gNBs serve: `gnb_transport` "telnet" | "rest" (a REST port too),
    `gnb_mode` "rtt" | "trace" | "auto" (a T-tracer port with the latter two); `gnbs`: False when a
    real gNB serves the mission (`uavloc sim --oai`: the world then runs only its vehicles)."""

    scenario: Scenario
    seed: int
    speedup: float
    mavsdk_ports: tuple[int, ...]
    max_stream_wall_hz: float = 100.0
    gnb_transport: str = "telnet"
    gnb_mode: str = "rtt"
    gnbs: bool = True


@dataclass(frozen=True)
class VehicleInfo:
    """A vehicle of the world: MAVLink system id, home (its ENU origin), its UDP (host, port)."""

    system_id: int
    origin: Origin
    address: tuple[str, int]


@dataclass(frozen=True)
class GnbInfo:
    """A gNB of the world: its telnet, REST (None: none) and T-tracer (None: none) ports on
    127.0.0.1, and its cell in the fleet's shared attachment (None: a single gNB)."""

    port: int
    rest_port: int | None
    t_port: int | None
    cell: int | None


@dataclass(frozen=True)
class WorldInfo:
    """What the child reports once its ports are open."""

    pid: int
    vehicles: tuple[VehicleInfo, ...]
    gnbs: tuple[GnbInfo, ...]


def gnb_seed(seed: int, index: int) -> int:
    """gNB `index`'s seed: gNB 0 draws as the one gNB of a one-vehicle mission; the others from seeds
    of their own."""
    return seed if index == 0 else int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


# ---------------------------------------------------------------------------------------------
# the child


class _Truth:
    """The vehicles' true states as the gNBs and cells see them: one snapshot per vehicle per
    event-loop step, so a gNB's clock (its stamp) and its UAV position are of the same instant.
    Every snapshot handed out is remembered (t_s -> position in the scenario's frame, TRACK_LEN per
    vehicle) for the stamp test."""

    def __init__(self, sims: list, scenario_origin: Origin) -> None:
        self.sims = sims
        self.scenario_origin = scenario_origin
        self._now: dict[int, tuple[float, np.ndarray]] = {}
        self.track: list[collections.OrderedDict[float, np.ndarray]] = [collections.OrderedDict() for _ in sims]

    def at_now(self, index: int) -> tuple[float, np.ndarray]:
        """(t_s, (3,) true position in the scenario's ENU frame [m]) of vehicle `index` now."""
        got = self._now.get(index)
        if got is None:
            from sitl_scenarios.fleet import enu_between

            sim = self.sims[index]
            st = sim.state()
            got = (float(st.t_s), enu_between(np.asarray(st.pos_enu_m, float), sim.origin, self.scenario_origin))
            if not self._now:
                asyncio.get_running_loop().call_soon(self._now.clear)
            self._now[index] = got
            track = self.track[index]
            track[got[0]] = got[1]
            while len(track) > TRACK_LEN:
                track.popitem(last=False)
        return got

    def position(self, index: int) -> np.ndarray:
        return self.at_now(index)[1]

    def clock(self, index: int) -> float:
        return self.at_now(index)[0]

    def positions(self) -> np.ndarray:
        """(N, 3) every vehicle's true position in the scenario's ENU frame [m]."""
        return np.array([self.position(i) for i in range(len(self.sims))])


class _World:
    """The child's world: vehicles, cells, gNBs; answers the control requests."""

    def __init__(self, spec: WorldSpec) -> None:
        self.spec = spec
        self.vehicles: list = []
        self.gnbs: list = []
        self.cells = None
        self.truth: _Truth | None = None
        #: per gNB: (t_s, uav (3,), rnti, true_range_m) of each range it computed
        self.stamps: list[collections.deque] = []
        self._hogs: list[threading.Event] = []

    async def start(self, stack: contextlib.AsyncExitStack) -> WorldInfo:
        from sitl_scenarios.gnb import SimulatedGnb
        from sitl_scenarios.gnb.cells import SharedCells
        from sitl_scenarios.vehicle import VehicleSimulator

        spec, sc = self.spec, self.spec.scenario
        for i, port in enumerate(spec.mavsdk_ports):
            self.vehicles.append(await stack.enter_async_context(VehicleSimulator.from_scenario(
                sc, i, seed=spec.seed, speedup=spec.speedup, target=("127.0.0.1", port), bind=("127.0.0.1", 0),
                max_stream_wall_hz=spec.max_stream_wall_hz)))
        truth = self.truth = _Truth(self.vehicles, sc.origin_geo)
        n = len(self.vehicles)
        if n > 1:
            self.cells = SharedCells.of_scenario(sc, truth.positions, n)
        for i in range(n if spec.gnbs else 0):
            gnb = SimulatedGnb(
                sc, functools.partial(truth.position, i), host="127.0.0.1", port=0,
                clock=functools.partial(truth.clock, i), seed=gnb_seed(spec.seed, i),
                rest_port=0 if spec.gnb_transport == "rest" else None,
                t_port=0 if spec.gnb_mode in ("trace", "auto") else None,
                cell=None if self.cells is None else self.cells.cell(i))
            self.stamps.append(collections.deque(maxlen=TRACK_LEN))
            gnb.radio.measure = functools.partial(self._measured, i, gnb.radio.measure)
            self.gnbs.append(await stack.enter_async_context(gnb))
        stack.callback(self.feed)
        return WorldInfo(
            os.getpid(),
            tuple(VehicleInfo(v.system_id, v.origin, tuple(v.local_address)) for v in self.vehicles),
            tuple(GnbInfo(g.port, g.rest_port, g.t_port, None if g.cell is None else g.cell.index) for g in self.gnbs))

    def _measured(self, index: int, measure, user, uav_enu_m, t_s: float):
        """gNB `index`'s RadioModel.measure, remembered with its stamp and UAV position."""
        raw = measure(user, uav_enu_m, t_s)
        if raw is not None:
            self.stamps[index].append((float(t_s), np.array(uav_enu_m, float).reshape(3), raw.rnti, raw.true_range_m))
        return raw

    # -- control requests (the parent's proxies) -------------------------------------------------
    _VEHICLE_CALLS = frozenset({"state", "pause_link", "resume_link", "lose_gps", "restore_gps", "refuse_reposition",
                                "set_battery_pct", "param", "set_param"})
    _VEHICLE_ATTRS = frozenset({"behind_s", "packets_in", "packets_out", "speedup"})
    _GNB_ATTRS = frozenset({"rtt_module", "rtt_command", "requests", "connections", "crashed", "current_rnti",
                            "rfsim_offset", "reestab_count", "stock_reaction", "linger_s", "msg2_delay_s"})
    _GNB_SETTABLE = frozenset({"rtt_module", "rtt_command", "stock_reaction", "linger_s", "msg2_delay_s"})
    _FAULT_FIELDS = frozenset(f.name for f in dataclasses.fields(GnbFaults))

    def _gnb(self, index: int):
        gnb = self.gnbs[index] if 0 <= index < len(self.gnbs) else None
        if gnb is None:
            raise SimulatorError(f"the world has no gNB {index} (killed, or never there)")
        return gnb

    async def handle(self, op: str, args: tuple) -> Any:
        """One control request -> its value (SimulatorError for a bad one)."""
        if op == "vehicle":
            i, name, call_args = args
            if name not in self._VEHICLE_CALLS:
                raise SimulatorError(f"the world's vehicles have no call {name!r}")
            return getattr(self.vehicles[i], name)(*call_args)
        if op == "vehicle_attr":
            i, name = args
            if name not in self._VEHICLE_ATTRS:
                raise SimulatorError(f"the world's vehicles have no attribute {name!r}")
            return getattr(self.vehicles[i], name)
        if op == "gnb_get":
            i, name = args
            gnb = self._gnb(i)
            if name in self._GNB_ATTRS:
                value = getattr(gnb, name)
                return list(value) if name == "current_rnti" else value
            if name == "clock":
                return float(gnb.clock())
            if name == "rest_requests":
                return None if gnb.rest is None else gnb.rest.requests
            if name == "stamps":
                return list(self.stamps[i])
            if name.startswith("faults.") and name[7:] in self._FAULT_FIELDS:
                return getattr(gnb.faults, name[7:])
            raise SimulatorError(f"the world's gNBs have no readable attribute {name!r}")
        if op == "gnb_set":
            i, name, value = args
            gnb = self._gnb(i)
            if name in self._GNB_SETTABLE:
                setattr(gnb, name, value)
            elif name.startswith("faults.") and name[7:] in self._FAULT_FIELDS:
                setattr(gnb.faults, name[7:], value)
            elif name == "current_rnti":
                k, rnti = value
                gnb.current_rnti[k] = int(rnti)
            else:
                raise SimulatorError(f"the world's gNBs have no settable attribute {name!r}")
            return None
        if op == "gnb_inject":
            i, kind, count, delay_s = args
            self._gnb(i).inject(kind, count, delay_s)
            return None
        if op == "kill_gnb":
            (i,) = args
            if 0 <= i < len(self.gnbs) and self.gnbs[i] is not None:
                gnb, self.gnbs[i] = self.gnbs[i], None
                await gnb.__aexit__(None, None, None)
                log.warning("simulated gNB %d killed", i)
            return None
        if op == "cells":
            if self.cells is None:
                return None
            return {"on_air": self.cells.on_air.tolist(), "serving": self.cells.attachment.serving.tolist()}
        if op == "positions":
            return self.truth.positions()
        if op == "track":
            (i,) = args
            return dict(self.truth.track[i])
        if op == "starve":
            self.starve(int(args[0]))
            return None
        if op == "feed":
            self.feed()
            return None
        raise SimulatorError(f"unknown world request {op!r}")

    def starve(self, threads: int) -> None:
        """Fault: `threads` CPU-bound Python threads in the world's process (its simulators share
        the interpreter with them, as a busy machine's process would), until :meth:`feed`."""
        for _ in range(threads):
            stop = threading.Event()

            def spin(stop: threading.Event = stop) -> None:
                x = 0
                while not stop.is_set():
                    x += 1

            threading.Thread(target=spin, name="uavloc-world-hog", daemon=True).start()
            self._hogs.append(stop)

    def feed(self) -> None:
        for stop in self._hogs:
            stop.set()
        self._hogs.clear()


def _quiet_child(log_queue: Any, level: int) -> None:
    """The child's logging goes to the parent (records at `level` and up); stdout and stderr to
    /dev/null; Python warnings through logging; SIGINT ignored."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(logging.handlers.QueueHandler(log_queue))
    root.setLevel(level)
    logging.captureWarnings(True)
    devnull = os.open(os.devnull, os.O_WRONLY)
    for fd in (1, 2):
        os.dup2(devnull, fd)
    os.close(devnull)


def world_main(conn: Any, spec: WorldSpec, log_queue: Any, level: int) -> None:
    """The child's entry point: build the world, report its WorldInfo (or ("err", message)), serve
    control requests until asked to stop or until the parent is gone."""
    _quiet_child(log_queue, level)
    code = 0
    try:
        asyncio.run(_serve(conn, spec))
    except BaseException as exc:  # reported to the parent, which raises it as a SimulatorError
        code = 1
        log.exception("the world process failed")
        with contextlib.suppress(OSError, ValueError):
            conn.send(("err", f"{type(exc).__name__}: {exc}"))
    finally:
        with contextlib.suppress(OSError):
            conn.close()
    # everything is closed: hand the last log records over and end here, without the seconds an
    # interpreter with numpy, aiohttp and pymavlink loaded takes to tear itself down on a busy machine
    logging.shutdown()
    log_queue.close()
    log_queue.join_thread()
    os._exit(code)


async def _serve(conn: Any, spec: WorldSpec) -> None:
    loop = asyncio.get_running_loop()
    world = _World(spec)
    stop = asyncio.Event()
    pending: set[asyncio.Task] = set()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    async with contextlib.AsyncExitStack() as stack:
        try:
            info = await world.start(stack)
        except SimulatorError as exc:
            conn.send(("err", str(exc)))
            return
        conn.send(("ok", info))

        async def answer(op: str, args: tuple) -> None:
            try:
                reply = ("ok", await world.handle(op, args))
            except (SimulatorError, ValueError, TypeError, IndexError, KeyError) as exc:
                reply = ("err", f"{type(exc).__name__}: {exc}" if not isinstance(exc, SimulatorError) else str(exc))
            with contextlib.suppress(OSError, ValueError):
                conn.send(reply)

        def on_readable() -> None:
            try:
                while conn.poll():
                    op, args = conn.recv()
                    if op == "stop":
                        stop.set()
                        return
                    task = loop.create_task(answer(op, args))
                    pending.add(task)
                    task.add_done_callback(pending.discard)
            except (EOFError, OSError):  # the parent is gone
                stop.set()

        loop.add_reader(conn.fileno(), on_readable)
        try:
            await stop.wait()
        finally:
            loop.remove_reader(conn.fileno())
            for task in list(pending):
                task.cancel()
    with contextlib.suppress(OSError, ValueError):
        conn.send(("ok", "stopped"))


# ---------------------------------------------------------------------------------------------
# the parent


class _Relay(logging.Handler):
    """Hands a record from the world's process to the parent's logger of the same name."""

    def emit(self, record: logging.LogRecord) -> None:
        logger = logging.getLogger(record.name)
        if logger.isEnabledFor(record.levelno):
            logger.handle(record)


@contextlib.contextmanager
def _children_allowed():
    """Let a daemonic process (a Dask worker flying a full-mode campaign run) start the world:
    multiprocessing refuses children to daemons lest they be orphaned when the daemon is ended,
    and the world cannot be: it ends by itself when its pipe to the parent closes."""
    import multiprocessing

    config = multiprocessing.current_process()._config  # the only place the flag lives
    daemon = config.get("daemon")
    config["daemon"] = False
    try:
        yield
    finally:
        if daemon is not None:
            config["daemon"] = daemon
        else:
            config.pop("daemon", None)


#: what a world imports, also lazily (the vehicle, the gNB, their libraries): the fork server holds them
WORLD_MODULES = [__name__, "sitl_scenarios.vehicle.simulator", "sitl_scenarios.vehicle.cli",
                 "sitl_scenarios.gnb.server", "sitl_scenarios.gnb.rest", "sitl_scenarios.gnb.ttrace",
                 "sitl_scenarios.fleet", "mission.safety"]


def world_context() -> Any:
    """The multiprocessing context worlds start in: a fork server (a fresh interpreter, single-threaded,
    with :data:`WORLD_MODULES` imported once per parent) forks each world. Not a fork of this process
    (threads, an event loop), and not a fresh interpreter per world: a world imports some 500 modules,
    seconds on a busy machine, which a test session starting dozens of worlds would pay each time."""
    import multiprocessing

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(WORLD_MODULES)
    return ctx


def start_world_server() -> None:
    """Start the fork server now (its imports run beside the caller's own start-up); idempotent."""
    import multiprocessing.forkserver

    world_context()
    multiprocessing.forkserver.ensure_running()


class WorldProcess:
    """The world's child process, from the parent (see the module docstring). `info` once entered;
    :meth:`call` / :meth:`acall` send one control request."""

    def __init__(self, spec: WorldSpec) -> None:
        self.spec = spec
        self.info: WorldInfo | None = None
        self.process: Any = None
        self._conn: Any = None
        self._queue: Any = None
        self._listener: logging.handlers.QueueListener | None = None
        self._lock = threading.Lock()

    async def __aenter__(self) -> WorldProcess:
        await asyncio.to_thread(self.start)
        return self

    async def __aexit__(self, *exc: object) -> None:
        await asyncio.to_thread(self.close)

    def start(self) -> None:
        ctx = world_context()
        parent_conn, child_conn = ctx.Pipe(duplex=True)
        self._queue = ctx.Queue()
        # the parent's DEBUG (-vv) sees the world's every line; otherwise its warnings only
        level = logging.DEBUG if logging.getLogger("sitl_scenarios").isEnabledFor(logging.DEBUG) else logging.WARNING
        self._listener = logging.handlers.QueueListener(self._queue, _Relay())
        self._listener.start()
        self.process = ctx.Process(target=world_main, args=(child_conn, self.spec, self._queue, level),
                                   name="uavloc-world", daemon=True)
        self._conn = parent_conn
        try:
            with _children_allowed():
                self.process.start()
            child_conn.close()
            reply = self._receive(START_TIMEOUT_S, "to open its ports")
            if reply[0] != "ok":
                raise SimulatorError(f"the simulated world did not start: {reply[1]}")
            self.info = reply[1]
            log.info("simulated world in process %d: %d vehicle(s), %d gNB(s)", self.info.pid,
                     len(self.info.vehicles), len(self.info.gnbs))
        except BaseException:
            self.close()
            raise

    def _receive(self, timeout_s: float, what: str) -> tuple:
        """The child's next message; SimulatorError when it died or said nothing within timeout_s."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                if self._conn.poll(min(0.1, max(0.0, deadline - time.monotonic()))):
                    return self._conn.recv()
            except (EOFError, OSError):
                self.process.join(1.0)
                raise SimulatorError(f"the simulated world's process ended (exit code {self.process.exitcode}) "
                                     f"before {what}") from None
            if not self.process.is_alive():
                raise SimulatorError(f"the simulated world's process ended (exit code {self.process.exitcode}) "
                                     f"before {what}")
            if time.monotonic() > deadline:
                raise SimulatorError(f"the simulated world took more than {timeout_s:g} s {what}")

    def call(self, op: str, *args: Any, timeout_s: float = REQUEST_TIMEOUT_S) -> Any:
        """One control request, answered (blocks the caller: tests and fault injection only)."""
        with self._lock:
            if self._conn is None:
                raise SimulatorError(f"the simulated world is closed (request {op!r})")
            try:
                self._conn.send((op, args))
            except (OSError, ValueError) as exc:
                raise SimulatorError(f"the simulated world's process is gone (request {op!r}): {exc}") from exc
            status, value = self._receive(timeout_s, f"to answer {op!r}")
        if status != "ok":
            raise SimulatorError(value)
        return value

    async def acall(self, op: str, *args: Any, timeout_s: float = REQUEST_TIMEOUT_S) -> Any:
        """:meth:`call` off the event loop."""
        return await asyncio.to_thread(self.call, op, *args, timeout_s=timeout_s)

    def positions(self) -> np.ndarray:
        """(N, 3) every vehicle's true position in the scenario's ENU frame [m]."""
        return np.asarray(self.call("positions"), float)

    def track(self, index: int = 0) -> dict[float, np.ndarray]:
        """{t_s: (3,) true position [m, the scenario's ENU frame]} of every snapshot of vehicle
        `index` the world handed its gNBs and cells (the latest TRACK_LEN)."""
        return self.call("track", index)

    async def starve(self, threads: int) -> None:
        """Fault: `threads` CPU-bound Python threads in the world's process until :meth:`feed`."""
        await self.acall("starve", threads)

    async def feed(self) -> None:
        """End :meth:`starve`."""
        await self.acall("feed")

    def close(self) -> None:
        """Stop the child: ask it (STOP_TIMEOUT_S), then terminate it, then kill it (KILL_TIMEOUT_S
        each); idempotent."""
        proc, conn = self.process, self._conn
        deadline = time.monotonic() + STOP_TIMEOUT_S
        with self._lock:
            self._conn = None
            if proc is not None and conn is not None and proc.is_alive():
                with contextlib.suppress(OSError, ValueError, EOFError):
                    conn.send(("stop", ()))
                    while proc.is_alive() and time.monotonic() < deadline:
                        if conn.poll(0.05):
                            conn.recv()  # "stopped", or a late answer
            if conn is not None:
                conn.close()
        if proc is not None and proc.pid is not None:
            proc.join(max(0.0, deadline - time.monotonic()))
            if proc.is_alive():
                log.warning("the simulated world's process did not stop within %g s: terminating it", STOP_TIMEOUT_S)
                proc.terminate()
                proc.join(KILL_TIMEOUT_S)
            if proc.is_alive():
                proc.kill()
                proc.join(KILL_TIMEOUT_S)
            if proc.exitcode not in (0, None, -signal.SIGTERM, -signal.SIGKILL):
                log.warning("the simulated world's process exited with code %s", proc.exitcode)
        listener, self._listener = self._listener, None
        if listener is not None:
            listener.stop()
        if self._queue is not None:
            self._queue.close()
            self._queue.join_thread()
            self._queue = None
