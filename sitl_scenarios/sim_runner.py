"""`uavloc sim`: a whole mission against simulators, started and shut down in one place.

:class:`SimulatedMission` is an async context manager that owns

- the vehicle: the built-in MAVLink vehicle (`sitl_scenarios.vehicle.VehicleSimulator`, in its own
  thread, at `speedup`) on a free loopback UDP port, or — with `connect` — a running PX4 SITL that
  MAVSDK reaches at that URL (a fleet's: one URL per vehicle, a list);
- the simulated OAI gNB (`sitl_scenarios.gnb.SimulatedGnb`) on a free loopback TCP port, whose UAV
  position is the built-in vehicle's true position, or the PX4 vehicle's reported position (it
  follows the vehicle the controller flies); its clock is the simulation's;
- the gNB adapter (`mission.gnb.OaiGnbClient`) and the MAVSDK vehicle adapter;
- the :class:`MissionController`, which :meth:`run` runs.

A fleet (`scenario.mission.fleet_size` > 1; docs/fleet.md): N built-in vehicles (system ids 1..N,
each at the launch point the fast mode gives it: `sitl_scenarios.fleet.vehicle_home`, each on its
own UDP ports) or N external autopilots (`connect`, a list of N URLs: PX4 SITL instances), N
MAVSDK adapters, N simulated gNBs (each on its own TCP ports, following its own vehicle: a built-in
vehicle's true position on its simulated clock, an external one's reported position on the
controller's mission clock) sharing one cell attachment (`sitl_scenarios.gnb.cells.SharedCells`,
the scenario's `[radio] coverage_m`), and N gNB adapters; the controller gets the lists. They are `.vehicle_sims`,
`.vehicles`, `.gnb_sims`, `.gnb_clients` (one element each for one vehicle); `.vehicle_sim`,
`.vehicle`, `.gnb_sim` and `.gnb_client` are element 0.

Frames: the scenario's positions are ENU of its origin. A built-in vehicle's home is its launch
point (the origin for one vehicle); the mission's frame is vehicle 0's home, and the `truth` and
buildings go through geodetic coordinates into it. With PX4 SITL the scenario's positions are
offsets from the vehicle's home (docs/design.md §9); with a fleet of them, from vehicle 0's home,
the mission's origin, and each gNB follows its vehicle in that frame. Fault tests reach the parts through
`.vehicle_sim`, `.gnb_sim`, `.controller` and :meth:`kill_gnb`.
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
from sitl_scenarios.fleet import enu_between
from sitl_scenarios.gnb import SimulatedGnb
from sitl_scenarios.gnb.cells import SharedCells
from sitl_scenarios.scenario import Scenario, controller_from_scenario
from sitl_scenarios.vehicle import VehicleSimulator
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


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port nobody listens on right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class SimulatedMission:
    """See the module docstring.

    scenario: the scenario; log_path: the mission log; seed: simulators' and planner's seed
    (default: the scenario's); speedup: built-in vehicle speed factor; planner: planner name;
    connect: MAVSDK URL of a running PX4 SITL (None: built-in vehicle), or a fleet's list of them,
    one per `[[vehicles]]` entry in its order; max_stream_wall_hz: cap of
    the built-in vehicle's telemetry rate on the wire; controller_overrides: ControllerConfig fields or
    mission settings by their key alone (mission.controller.controller_from_mission); header_config:
    more fields of the log header's `config` (the CLI's `command_line`).
    """

    def __init__(self, scenario: Scenario, log_path: str | Path, *, seed: int | None = None,
                 speedup: float = 20.0, planner: str | None = None, connect: str | Sequence[str] | None = None,
                 max_stream_wall_hz: float = 100.0, gnb_request_timeout_s: float = 1.0,
                 controller_overrides: dict | None = None, gnb_transport: str = "telnet",
                 gnb_mode: str | None = None, header_config: dict | None = None):
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
        self.vehicle_sims: list[VehicleSimulator] = []
        self.vehicles: list[MavsdkVehicle] = []
        #: a killed gNB's place holds None
        self.gnb_sims: list[SimulatedGnb | None] = []
        self.gnb_clients: list[OaiGnbClient] = []
        #: the fleet's shared cell attachment (None: one vehicle)
        self.cells: SharedCells | None = None
        self.vehicle_sim: VehicleSimulator | None = None
        self.gnb_sim: SimulatedGnb | None = None
        self.gnb_client: OaiGnbClient | None = None
        self.vehicle: MavsdkVehicle | None = None
        self.controller: MissionController | None = None
        self._stack: contextlib.AsyncExitStack | None = None
        self._gnb_stack: contextlib.AsyncExitStack | None = None
        self._t0 = time.monotonic()

    # -- positions seen by the simulated gNB (ENU of the scenario frame) ------------------------

    def _true_position_builtin(self, index: int = 0) -> np.ndarray | None:
        """Built-in vehicle `index`'s true position in the scenario's ENU frame [m] (its simulator
        works in the ENU frame of its own home, its launch point)."""
        sim = self.vehicle_sims[index]
        return enu_between(np.asarray(sim.state().pos_enu_m, float), sim.origin, self.scenario.origin_geo)

    def _fleet_positions(self) -> np.ndarray:
        """(N, 3) every built-in vehicle's true position in the scenario's ENU frame [m]."""
        return np.array([self._true_position_builtin(i) for i in range(len(self.vehicle_sims))])

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

    def _vehicle_clock(self, index: int) -> float:
        """Built-in vehicle `index`'s simulated clock [s]."""
        return float(self.vehicle_sims[index].state().t_s)

    def _sim_clock(self) -> float:
        if self.vehicle_sim is not None:
            return float(self.vehicle_sim.state().t_s)
        if self.controller is not None:
            return self.controller.now()  # PX4 SITL: the vehicle's clock, at any speed factor
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
            if self.connect is None:
                for i in range(self.fleet_size):
                    port = free_udp_port()
                    self.vehicle_sims.append(await stack.enter_async_context(VehicleSimulator.from_scenario(
                        self.scenario, i, seed=self.seed, speedup=self.speedup, target=("127.0.0.1", port),
                        bind=("127.0.0.1", 0), max_stream_wall_hz=self.max_stream_wall_hz)))
                    self.vehicles.append(await stack.enter_async_context(MavsdkVehicle(f"udpin://127.0.0.1:{port}")))
            else:
                for url in self.connect_urls:
                    self.vehicles.append(await stack.enter_async_context(MavsdkVehicle(url)))
            self.vehicle_sim = self.vehicle_sims[0] if self.vehicle_sims else None
            self.vehicle = self.vehicles[0]
            self._gnb_stack = contextlib.AsyncExitStack()
            await self._gnb_stack.__aenter__()
            stack.push_async_callback(self._close_gnb)
            if self.fleet_size > 1:
                positions = self._fleet_positions if self.connect is None else self._fleet_positions_followed
                self.cells = SharedCells.of_scenario(self.scenario, positions, self.fleet_size)
            for i in range(self.fleet_size):
                gnb = await self._gnb_stack.enter_async_context(self._simulated_gnb(i))
                self.gnb_sims.append(gnb)
                self.gnb_clients.append(await self._gnb_stack.enter_async_context(self._gnb_client(gnb)))
            self.gnb_sim, self.gnb_client = self.gnb_sims[0], self.gnb_clients[0]
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
        except BaseException:
            await stack.aclose()
            raise
        self._stack = stack
        return self

    def _simulated_gnb(self, index: int) -> SimulatedGnb:
        """The simulated gNB of vehicle `index` (not started): on free loopback ports, at its
        vehicle's true position on its vehicle's clock; a fleet's in its cell of the shared attachment."""
        if self.connect is not None and self.fleet_size == 1:
            position, clock = self._position_followed, self._sim_clock
        elif self.connect is not None:
            # an external fleet: its vehicle's reported position, the mission's clock
            position, clock = functools.partial(self._position_followed_in_fleet, index), self._sim_clock
        elif self.fleet_size == 1:
            position, clock = self._true_position_builtin, self._sim_clock
        else:
            position = functools.partial(self._true_position_builtin, index)
            clock = functools.partial(self._vehicle_clock, index)
        # gNB 0 draws as the one gNB of a one-vehicle mission; the others from seeds of their own
        seed = self.seed if index == 0 else int(np.random.SeedSequence([self.seed, index]).generate_state(1)[0])
        return SimulatedGnb(
            self.scenario, position, host="127.0.0.1", port=0, clock=clock, seed=seed,
            rest_port=0 if self.gnb_transport == "rest" else None,
            t_port=0 if self.gnb_mode in ("trace", "auto") else None,
            cell=None if self.cells is None else self.cells.cell(index))

    def _gnb_client(self, gnb: SimulatedGnb) -> OaiGnbClient:
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
        await sim.__aexit__(None, None, None)
        log.warning("simulated gNB %d killed", index)

    async def run(self) -> MissionResult:
        """Run the mission; the simulators keep running until the context exits."""
        if self.controller is None:
            raise MissionError("SimulatedMission.run() needs `async with SimulatedMission(...)` first")
        return await self.controller.run()
