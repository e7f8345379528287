"""`uavloc sim`: a whole mission against simulators, started and shut down in one place.

:class:`SimulatedMission` is an async context manager that owns

- the simulated world (`sitl_scenarios.world.WorldProcess`): a child process of its own that runs
  the built-in MAVLink vehicle(s) (`sitl_scenarios.vehicle.VehicleSimulator`, at `speedup`), the
  simulated OAI gNB(s) (`sitl_scenarios.gnb.SimulatedGnb`) and a fleet's shared cells, on loopback
  ports it opens itself and reports back; each gNB's UAV position and clock are its vehicle's true
  position and simulated clock, read in the world at the moment the gNB stamps a range;
- or — with `connect` — a running PX4 (or ArduPilot) SITL that MAVSDK reaches at that URL (a
  fleet's: one URL per vehicle, a list), and then the simulated gNB(s) in this process, following
  the vehicle's *reported* position as the controller's MAVSDK adapter receives it (only this
  process has it) on the controller's mission clock;
- or — with `oai` (an OAI build folder) — a real OAI gNB and nrUE per user over rfsim instead of
  the simulated gNB (`sitl_scenarios.oai`, docs/oai-in-the-loop.md): the world then runs its vehicle
  only, at the pace rfsim keeps, and a bridge puts the vehicle's true distance on each UE's channel;
- the gNB adapter(s) (`mission.gnb.OaiGnbClient`) and the MAVSDK vehicle adapter(s), which reach
  the world only over its sockets, as they reach PX4 and a gNB;
- the :class:`MissionController`, which :meth:`run` runs.

A fleet (`scenario.mission.fleet_size` > 1; docs/fleet.md): N built-in vehicles (system ids 1..N,
each at the launch point the fast mode gives it: `sitl_scenarios.fleet.vehicle_home`, each on its
own UDP ports) or N external autopilots (`connect`), N MAVSDK adapters, N simulated gNBs (each on
its own TCP ports, following its own vehicle) sharing one cell attachment
(`sitl_scenarios.gnb.cells.SharedCells`, the scenario's `[radio] coverage_m`), and N gNB adapters;
the controller gets the lists. They are `.vehicle_sims`, `.vehicles`, `.gnb_sims`, `.gnb_clients`
(one element each for one vehicle); `.vehicle_sim`, `.vehicle`, `.gnb_sim` and `.gnb_client` are
element 0.

Fault tests reach the world through `.vehicle_sims` / `.gnb_sims` / `.cells`, proxies with the
simulators' method names over the world's control channel (`sitl_scenarios.world_proxy`),
`.world` (`starve()`, `feed()`, `track()`), `.controller` and :meth:`kill_gnb`.

Frames: the scenario's positions are ENU of its origin. A built-in vehicle's home is its launch
point (the origin for one vehicle); the mission's frame is vehicle 0's home, and the `truth` and
buildings go through geodetic coordinates into it. With PX4 SITL the scenario's positions are
offsets from the vehicle's home (docs/design.md §9); with a fleet of them, from vehicle 0's home,
the mission's origin, and each gNB follows its vehicle in that frame.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import socket
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from estimator.geodesy import Origin
from mission.control.config import MissionResult
from mission.control.flight import MissionController
from mission.gnb import GnbConfig, OaiGnbClient
from mission.vehicle import MavsdkVehicle
from sitl_scenarios.gnb import SimulatedGnb
from sitl_scenarios.gnb.cells import SharedCells
from sitl_scenarios.scenario import Scenario, controller_from_scenario
from sitl_scenarios.world import WorldProcess, WorldSpec, gnb_seed
from sitl_scenarios.world_proxy import CellsProxy, GnbProxy, VehicleProxy
from uavloc.errors import MissionError

log = logging.getLogger(__name__)


def connect_urls(connect: str | Sequence[str] | None, scenario: Scenario) -> list[str] | None:
    """The external autopilots' MAVSDK URLs of `SimulatedMission(connect=...)`: one URL (a string)
    flies one vehicle; a list flies the scenario's fleet, one URL per `[[vehicles]]` entry. None:
    built-in vehicles. MissionError, naming `connect`, when the count is not the fleet's."""
    if connect is None:
        return None
    urls = [connect] if isinstance(connect, str) else [str(u) for u in connect]
    n = scenario.mission.fleet_size
    if len(urls) != n or not all(u.strip() for u in urls):
        what = f"the {n} vehicles of its [[vehicles]]" if n > 1 else "its one vehicle"
        raise MissionError(f"connect: scenario {scenario.name!r} flies {what}: give one MAVLink URL per vehicle, "
                           f"got {len(urls)} ({', '.join(map(repr, urls)) or 'none'})")
    return urls


def reserve_udp_port(host: str = "127.0.0.1") -> socket.socket:
    """A UDP socket bound to a port the OS picks, held until closed: while it is open no other
    socket of any process is given that port, so a port named to a peer before its listener binds
    stays free for that listener (close it just before)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind((host, 0))
    except OSError:
        s.close()
        raise
    return s


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port nobody listens on right now (the OS picks it; another socket may take it at once:
    hold it with :func:`reserve_udp_port` where that matters)."""
    with reserve_udp_port(host) as s:
        return s.getsockname()[1]


class SimulatedMission:
    """See the module docstring.

    scenario: the scenario; log_path: the mission log; seed: simulators' and planner's seed
    (default: the scenario's); speedup: built-in vehicle speed factor; planner: planner name;
    connect: MAVSDK URL of a running PX4 SITL (None: built-in vehicle), or a fleet's list of them,
    one per `[[vehicles]]` entry in its order; max_stream_wall_hz: cap of
    the built-in vehicle's telemetry rate on the wire; controller_overrides: ControllerConfig fields or
    mission settings by their key alone (mission.controller.controller_from_mission); header_config:
    more fields of the log header's `config` (the CLI's `command_line`); oai: an OAI build folder
    (None: the simulated gNB), whose real gNB and nrUE(s) serve the mission in trace mode;
    t_relay: with `oai`, the T client reaches each gNB's T port through a sitl_scenarios.oai.t_relay
    TRelay that :meth:`cut_trace` cuts (fault injection: the gNB keeps running).
    """

    def __init__(self, scenario: Scenario, log_path: str | Path, *, seed: int | None = None,
                 speedup: float = 20.0, planner: str | None = None, connect: str | Sequence[str] | None = None,
                 max_stream_wall_hz: float = 100.0, gnb_request_timeout_s: float = 1.0,
                 controller_overrides: dict | None = None, gnb_transport: str = "telnet",
                 gnb_mode: str | None = None, header_config: dict | None = None, oai: str | Path | None = None,
                 t_relay: bool = False):
        if not (math.isfinite(speedup) and speedup > 0):
            raise MissionError(f"speedup must be a positive number, got {speedup!r}")
        self.scenario = scenario
        self.log_path = Path(log_path)
        self.seed = scenario.seed if seed is None else int(seed)
        self.speedup = float(speedup) if connect is None else 1.0
        self.planner = planner
        self.header_config = dict(header_config or {})
        self.connect = connect
        #: the external autopilots' URLs, one per vehicle (None: built-in vehicles)
        self.connect_urls = connect_urls(connect, scenario)
        self.max_stream_wall_hz = max_stream_wall_hz
        self.gnb_request_timeout_s = gnb_request_timeout_s
        self.controller_overrides = dict(controller_overrides or {})
        if gnb_transport not in ("telnet", "rest"):
            raise MissionError(f"gnb_transport must be 'telnet' or 'rest', got {gnb_transport!r}")
        self.gnb_transport = gnb_transport
        #: how the adapter measures (None: the scenario's [gnb] mode); "trace" reads the simulated
        #: gNB's T tracer, "auto" lets the adapter choose
        self.gnb_mode = gnb_mode if gnb_mode is not None else scenario.mission.gnb.mode
        if self.gnb_mode not in ("rtt", "trace", "auto"):
            raise MissionError(f"the simulated gNB measures in mode rtt, trace or auto, not {self.gnb_mode!r}")
        #: how many vehicles fly: the mission's fleet (built-in vehicles), one per `connect` URL
        self.fleet_size = scenario.mission.fleet_size if connect is None else len(self.connect_urls)
        #: the world's process (None: `connect`, an external autopilot)
        self.world: WorldProcess | None = None
        #: the world's built-in vehicles (proxies; none with `connect`)
        self.vehicle_sims: list[VehicleProxy] = []
        self.vehicles: list[MavsdkVehicle] = []
        #: the world's gNBs (proxies), or with `connect` this process's SimulatedGnb; a killed
        #: gNB's place holds None
        self.gnb_sims: list[GnbProxy | SimulatedGnb | None] = []
        self.gnb_clients: list[OaiGnbClient] = []
        #: the fleet's shared cell attachment (None: one vehicle)
        self.cells: CellsProxy | SharedCells | None = None
        self.vehicle_sim: VehicleProxy | None = None
        self.gnb_sim: GnbProxy | SimulatedGnb | None = None
        self.gnb_client: OaiGnbClient | None = None
        self.vehicle: MavsdkVehicle | None = None
        self.controller: MissionController | None = None
        self._stack: contextlib.AsyncExitStack | None = None
        self._gnb_stack: contextlib.AsyncExitStack | None = None
        self._t0 = time.monotonic()
        #: a real OAI gNB and nrUE in the loop (`oai`: an OAI build folder; docs/oai-in-the-loop.md)
        self.oai = None
        self._channel_pending: list = []
        self.t_relay = bool(t_relay)
        #: with t_relay: each user's T relay (the latest attach attempt's)
        self.t_relays: list = []
        if oai is not None:
            if gnb_transport != "telnet":
                raise MissionError("a real OAI gNB is reached over telnet (--gnb-transport rest is not supported "
                                   "with --oai)")
            from sitl_scenarios.oai.loop import OaiInTheLoop

            # a stock OAI gNB has no RTT command: its ranges come from its T trace unless rtt is asked
            # for (of a build patched with patches/oai-2025.w36: OaiInTheLoop refuses another)
            self.gnb_mode = gnb_mode if gnb_mode in ("auto", "rtt") else "trace"
            self.oai = OaiInTheLoop(oai, self.log_path.parent / "oai", scenario, rtt=self.gnb_mode == "rtt")

    # -- positions seen by the simulated gNB (ENU of the scenario frame) ------------------------

    def _fleet_positions(self) -> np.ndarray:
        """(N, 3) every built-in vehicle's true position in the scenario's ENU frame [m] (asked of
        the world)."""
        if self.world is None:
            raise MissionError("true positions are the built-in vehicles' (this mission flies external ones)")
        return self.world.positions()

    # -- with `connect`: the gNB follows the external vehicle's reported position --------------

    def _position_followed(self) -> np.ndarray | None:
        """PX4 SITL: the vehicle's reported position in the ENU frame of its home."""
        st = self.vehicle.state
        if st.position is None or st.home is None:
            return None
        home = Origin(st.home.lat_deg, st.home.lon_deg, st.home.alt_amsl_m)
        p = st.position
        return home.lla_to_enu(p.lat_deg, p.lon_deg, p.alt_amsl_m)

    def _position_followed_in_fleet(self, index: int) -> np.ndarray | None:
        """External vehicle `index`'s reported position [m] in the mission's ENU frame: the
        controller's origin (vehicle 0's home as PX4 reported it before take-off), vehicle 0's
        reported home until the controller knows it; None while unknown."""
        origin = self.controller.origin if self.controller is not None else None
        if origin is None:
            home = self.vehicles[0].state.home
            if home is None:
                return None
            origin = Origin(home.lat_deg, home.lon_deg, home.alt_amsl_m)
        p = self.vehicles[index].state.position
        if p is None:
            return None
        return np.asarray(origin.lla_to_enu(p.lat_deg, p.lon_deg, p.alt_amsl_m), float)

    def _fleet_positions_followed(self) -> np.ndarray | None:
        """(N, 3) every external vehicle's reported position in the mission's ENU frame [m] (a row
        of NaN: not known yet; None: no vehicle's is)."""
        rows = [self._position_followed_in_fleet(i) for i in range(len(self.vehicles))]
        if all(r is None for r in rows):
            return None
        return np.array([np.full(3, np.nan) if r is None else r for r in rows], float)

    def _sim_clock(self) -> float:
        """An external vehicle's gNB clock: the vehicle's clock, at any speed factor, through the
        controller (before it exists: this process's monotonic time since the start)."""
        if self.controller is not None:
            return self.controller.now()
        return time.monotonic() - self._t0

    def _truth(self, home: Origin) -> np.ndarray:
        """True users in the controller's frame (ENU from the vehicle's reported home: vehicle 0's
        for a fleet)."""
        users = np.array([[u.east_m, u.north_m, u.up_m] for u in self.scenario.users], float)
        if self.connect is not None:
            return users  # scenario positions are offsets from the vehicle's home
        lat, lon, alt = self.scenario.origin_geo.enu_to_lla(users)
        return home.lla_to_enu(lat, lon, alt)

    def _buildings(self, home: Origin) -> list:
        """The scenario's buildings in the controller's frame (ENU from the vehicle's home)."""
        out = []
        for b in self.scenario.buildings:
            fp = np.asarray(b.footprint_enu_m, float)
            if self.connect is None:  # the built-in vehicle's world is the scenario's origin
                lat, lon, alt = self.scenario.origin_geo.enu_to_lla(np.column_stack([fp, np.zeros(len(fp))]))
                fp = home.lla_to_enu(lat, lon, alt)[:, :2]
            out.append((fp, b.height_m))
        return out

    # -- lifecycle ------------------------------------------------------------------------------

    async def __aenter__(self) -> SimulatedMission:
        stack = contextlib.AsyncExitStack()
        await stack.__aenter__()
        try:
            self._gnb_stack = contextlib.AsyncExitStack()
            await self._gnb_stack.__aenter__()
            if self.oai is not None:
                await self._enter_oai(stack)
            elif self.connect is None:
                await self._enter_world(stack)
            else:
                for url in self.connect_urls:
                    self.vehicles.append(await stack.enter_async_context(MavsdkVehicle(url)))
                self.vehicle = self.vehicles[0]  # what the gNBs follow
                stack.push_async_callback(self._close_gnb)
                if self.fleet_size > 1:
                    self.cells = SharedCells.of_scenario(self.scenario, self._fleet_positions_followed,
                                                         self.fleet_size)
                for i in range(self.fleet_size):
                    self.gnb_sims.append(await self._gnb_stack.enter_async_context(self._followed_gnb(i)))
            self.vehicle_sim = self.vehicle_sims[0] if self.vehicle_sims else None
            self.vehicle = self.vehicles[0]
            for gnb in self.gnb_sims:
                self.gnb_clients.append(await self._gnb_stack.enter_async_context(self._gnb_client(gnb)))
            self.gnb_sim = self.gnb_sims[0] if self.gnb_sims else None
            self.gnb_client = self.gnb_clients[0]
            overrides = dict(self.controller_overrides)
            # the controller's gNB timeout covers the adapter's own timeout and one reconnect
            overrides.setdefault("gnb_timeout_s", 3.0 * self.gnb_request_timeout_s + 0.5)
            fleet = self.fleet_size > 1
            self.controller = controller_from_scenario(
                self.scenario, self.vehicles if fleet else self.vehicle,
                self.gnb_clients if fleet else self.gnb_client, self.log_path, planner=self.planner,
                seed=self.seed, time_scale=self.speedup, truth=self._truth, buildings=self._buildings,
                external_vehicle=self.connect is not None,
                header_config={"command": "sim", "speedup": self.speedup,
                               "connect": self.connect_urls if fleet or self.connect is None else self.connect_urls[0],
                               "gnb_transport": self.gnb_transport, "gnb_mode": self.gnb_client.mode,
                               **self.header_config},
                **overrides)
            if self.oai is not None:
                self.controller.log_writer.subscribe(self._flush_channel)
        except BaseException:
            await stack.aclose()
            raise
        self._stack = stack
        return self

    async def _enter_oai(self, stack: contextlib.AsyncExitStack) -> None:
        """A real OAI gNB and nrUE (sitl_scenarios.oai.loop): the gNB, the adapter's T client, the
        UE's attach, rfsim's pace (the world's speed-up follows it), the world without simulated
        gNBs (with `connect`: the external autopilot), then the bridge that puts the vehicle's true
        distance (an autopilot's: its reported position) on the UE's channel."""
        oai = self.oai

        def make_client(port: int, t_port: int) -> contextlib.AbstractAsyncContextManager:
            return relayed_client(port, t_port) if self.t_relay else adapter(port, t_port)

        @contextlib.asynccontextmanager
        async def relayed_client(port: int, t_port: int):
            from sitl_scenarios.oai.t_relay import TRelay

            async with TRelay(t_port) as relay, adapter(port, relay.port) as client:
                self.t_relays.append(relay)
                yield client

        def adapter(port: int, t_port: int) -> OaiGnbClient:
            sc = self.scenario
            return OaiGnbClient(GnbConfig.of(
                sc.mission.gnb, "127.0.0.1", port, transport="telnet", seed=self.seed, mu=sc.radio.mu,
                fs_hz=sc.radio.fs_hz, mode=self.gnb_mode, t_port=t_port,
                trace_jump_tolerance_m=max(sc.mission.gnb.trace_jump_tolerance_m, 3.0 * sc.mission.noise.range_s0_m),
                request_timeout_s=max(self.gnb_request_timeout_s, 3.0), connect_timeout_s=5.0, retries=1,
                backoff_max_s=0.5))

        # the adapter closes before OAI (start_radio's stack)
        self.gnb_clients.append(await oai.start_radio(stack, make_client))
        from sitl_scenarios.oai.loop import scenario_with_rntis

        self.scenario = scenario_with_rntis(self.scenario, oai.rntis)
        requested = self.speedup
        self.speedup = oai.speedup(requested) if self.connect is None else 1.0  # an autopilot keeps its own pace
        if self.speedup < requested:
            log.warning("rfsim runs at %.2f × real time: the world runs at %g × (not %g ×)", oai.pace_at_start,
                        self.speedup, requested)
        self.header_config["oai"] = oai.header(self.speedup)
        if self.connect is None:
            await self._enter_world(stack)
            world = self.world

            async def position() -> np.ndarray:
                return np.asarray(await world.acall("positions"), float)[0]
        else:
            # an external autopilot: the bridge follows the position it reports (its estimate; the
            # simulator's truth is not on its MAVLink link), in the ENU frame of its home
            self.vehicles.append(await stack.enter_async_context(MavsdkVehicle(self.connect_urls[0])))
            self.vehicle = self.vehicles[0]

            async def position() -> np.ndarray | None:
                return self._position_followed()

        # an autopilot reports its position once the mission connected it: the bridge walks out then
        await oai.start_bridge(stack, position, self._channel_setting, self.speedup, walk_first=self.connect is None,
                               seed=self.seed)

    def _channel_setting(self, setting) -> None:
        """The bridge's sink: each rfsim distance set becomes a `channel` record once the log is open
        (the settings before it are kept and written after the header, their time clamped to the
        log's start: :meth:`_flush_channel`)."""
        self._channel_pending.append(setting)
        self._flush_channel()

    def _flush_channel(self, _record: dict | None = None) -> None:
        """Write the pending channel settings when the log is open (also a log listener: the header
        opens it)."""
        c = self.controller
        if c is None or not c.log_writer.is_open or not self._channel_pending:
            return
        pending, self._channel_pending = self._channel_pending, []
        for s in pending:
            c.log_writer.write("channel", max(0.0, c.mission_t(s.t_mono_s)), **s.record())

    async def _enter_world(self, stack: contextlib.AsyncExitStack) -> None:
        """Start the world's process (the built-in vehicles, the gNBs, the fleet's cells) and the
        MAVSDK adapters that listen to its vehicles; the gNB adapters close before the world."""
        # the MAVSDK adapters' ports are held while the world starts: its own sockets (bound to
        # ports the OS picks) were once given one of them, and the adapter could not bind it
        held = [reserve_udp_port() for _ in range(self.fleet_size)]
        stack.callback(lambda: [s.close() for s in held])
        ports = tuple(s.getsockname()[1] for s in held)
        self.world = await stack.enter_async_context(WorldProcess(WorldSpec(
            self.scenario, self.seed, self.speedup, ports, max_stream_wall_hz=self.max_stream_wall_hz,
            gnb_transport=self.gnb_transport, gnb_mode=self.gnb_mode, gnbs=self.oai is None)))
        for i, port in enumerate(ports):
            self.vehicle_sims.append(VehicleProxy(self.world, i))
            held[i].close()
            self.vehicles.append(await stack.enter_async_context(MavsdkVehicle(f"udpin://127.0.0.1:{port}")))
        stack.push_async_callback(self._close_gnb)
        self.gnb_sims.extend(GnbProxy(self.world, i) for i in range(len(self.world.info.gnbs)))
        self.cells = CellsProxy(self.world) if self.fleet_size > 1 else None

    def _followed_gnb(self, index: int) -> SimulatedGnb:
        """With `connect`: the simulated gNB of external vehicle `index` (not started), in this
        process, on free loopback ports, at the vehicle's reported position on the mission clock; a
        fleet's in its cell of the shared attachment."""
        if self.fleet_size == 1:
            position = self._position_followed
        else:
            position = functools.partial(self._position_followed_in_fleet, index)
        return SimulatedGnb(
            self.scenario, position, host="127.0.0.1", port=0, clock=self._sim_clock,
            seed=gnb_seed(self.seed, index), rest_port=0 if self.gnb_transport == "rest" else None,
            t_port=0 if self.gnb_mode in ("trace", "auto") else None,
            cell=None if self.cells is None else self.cells.cell(index))

    def _gnb_client(self, gnb: GnbProxy | SimulatedGnb) -> OaiGnbClient:
        """The gNB adapter of a simulated gNB (not started)."""
        rest = self.gnb_transport == "rest"
        return OaiGnbClient(GnbConfig.of(
            self.scenario.mission.gnb, "127.0.0.1", gnb.rest_port if rest else gnb.port,
            transport="rest" if rest else "telnet", seed=self.seed, mu=self.scenario.radio.mu,
            fs_hz=self.scenario.radio.fs_hz, mode=self.gnb_mode, t_port=gnb.t_port or 2021,
            # an RTT keyframes take is at most this old in simulated seconds
            trace_max_age_s=self.scenario.mission.gnb.trace_max_age_s / self.speedup,
            # a jump the mission's own range noise can make (3 σ0) is no jump
            trace_jump_tolerance_m=max(self.scenario.mission.gnb.trace_jump_tolerance_m,
                                       3.0 * self.scenario.mission.noise.range_s0_m),
            request_timeout_s=self.gnb_request_timeout_s, connect_timeout_s=self.gnb_request_timeout_s,
            retries=1, backoff_max_s=0.2))

    async def __aexit__(self, *exc: object) -> None:
        stack, self._stack = self._stack, None
        if stack is not None:
            await stack.aclose()

    async def _close_gnb(self) -> None:
        gstack, self._gnb_stack = self._gnb_stack, None
        if gstack is not None:
            await gstack.aclose()

    async def kill_gnb(self, index: int = 0) -> None:
        """Fault injection: stop vehicle `index`'s simulated gNB server (its port closes; the adapter
        sees a dead gNB; a fleet's gNB leaves the air and its UEs attach to the others)."""
        if not 0 <= index < len(self.gnb_sims) or self.gnb_sims[index] is None:
            return
        sim = self.gnb_sims[index]
        self.gnb_sims[index] = None
        if index == 0:
            self.gnb_sim = None
        if self.world is not None:
            await self.world.acall("kill_gnb", index)
        else:
            await sim.__aexit__(None, None, None)
            log.warning("simulated gNB %d killed", index)

    def cut_trace(self, hold_s: float = 0.0) -> None:
        """Fault injection (`oai` with `t_relay`): cut the T client's connection to the newest gNB's T
        port and refuse reconnects for hold_s wall seconds; the gNB and nrUE keep running."""
        if not self.t_relays:
            raise MissionError("cut_trace needs SimulatedMission(..., oai=BUILD, t_relay=True)")
        self.t_relays[-1].cut(hold_s)

    async def run(self) -> MissionResult:
        """Run the mission; the simulators keep running until the context exits."""
        if self.controller is None:
            raise MissionError("SimulatedMission.run() needs `async with SimulatedMission(...)` first")
        return await self.controller.run()
