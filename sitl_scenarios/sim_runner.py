"""`uavloc sim`: a whole mission against simulators, started and shut down in one place.

:class:`SimulatedMission` is an async context manager that owns

- the vehicle: the built-in MAVLink vehicle (`sitl_scenarios.vehicle.VehicleSimulator`, in its own
  thread, at `speedup`) on a free loopback UDP port, or — with `connect` — a running PX4 SITL that
  MAVSDK reaches at that URL;
- the simulated OAI gNB (`sitl_scenarios.gnb.SimulatedGnb`) on a free loopback TCP port, whose UAV
  position is the built-in vehicle's true position, or the PX4 vehicle's reported position (it
  follows the vehicle the controller flies); its clock is the simulation's;
- the gNB adapter (`mission.gnb.OaiGnbClient`) and the MAVSDK vehicle adapter;
- the :class:`MissionController`, which :meth:`run` runs.

Frames: with the built-in vehicle the scenario's origin is the vehicle's home; with PX4 SITL the
scenario's positions are offsets from the vehicle's home (docs/design.md §9). The `truth` record is
computed accordingly. Fault tests reach the parts through `.vehicle_sim`, `.gnb_sim`,
`.controller` and :meth:`kill_gnb`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import time
from pathlib import Path

import numpy as np

from estimator.geodesy import Origin
from mission.control.config import MissionResult
from mission.control.flight import MissionController
from mission.gnb import GnbConfig, OaiGnbClient
from mission.vehicle import MavsdkVehicle
from sitl_scenarios.gnb import SimulatedGnb
from sitl_scenarios.scenario import Scenario, controller_from_scenario
from sitl_scenarios.vehicle import VehicleSimulator
from uavloc.errors import MissionError

log = logging.getLogger(__name__)


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port nobody listens on right now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class SimulatedMission:
    """See the module docstring.

    scenario: the scenario; log_path: the mission log; seed: simulators' and planner's seed
    (default: the scenario's); speedup: built-in vehicle speed factor; planner: planner name;
    connect: MAVSDK URL of a running PX4 SITL (None: built-in vehicle); max_stream_wall_hz: cap of
    the built-in vehicle's telemetry rate on the wire; controller_overrides: ControllerConfig fields or
    mission settings by their key alone (mission.controller.controller_from_mission); header_config:
    more fields of the log header's `config` (the CLI's `command_line`).
    """

    def __init__(self, scenario: Scenario, log_path: str | Path, *, seed: int | None = None,
                 speedup: float = 20.0, planner: str | None = None, connect: str | None = None,
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
        self.vehicle_sim: VehicleSimulator | None = None
        self.gnb_sim: SimulatedGnb | None = None
        self.gnb_client: OaiGnbClient | None = None
        self.vehicle: MavsdkVehicle | None = None
        self.controller: MissionController | None = None
        self._stack: contextlib.AsyncExitStack | None = None
        self._gnb_stack: contextlib.AsyncExitStack | None = None
        self._t0 = time.monotonic()

    # -- positions seen by the simulated gNB (ENU of the scenario frame) ------------------------

    def _true_position_builtin(self) -> np.ndarray | None:
        return np.asarray(self.vehicle_sim.state().pos_enu_m, float)

    def _position_followed(self) -> np.ndarray | None:
        """PX4 SITL: the vehicle's reported position in the ENU frame of its home."""
        st = self.vehicle.state
        if st.position is None or st.home is None:
            return None
        home = Origin(st.home.lat_deg, st.home.lon_deg, st.home.alt_amsl_m)
        p = st.position
        return home.lla_to_enu(p.lat_deg, p.lon_deg, p.alt_amsl_m)

    def _sim_clock(self) -> float:
        if self.vehicle_sim is not None:
            return float(self.vehicle_sim.state().t_s)
        if self.controller is not None:
            return self.controller.now()  # PX4 SITL: the vehicle's clock, at any speed factor
        return time.monotonic() - self._t0

    def _truth(self, home: Origin) -> np.ndarray:
        """True users in the controller's frame (ENU from the vehicle's reported home)."""
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
                port = free_udp_port()
                self.vehicle_sim = await stack.enter_async_context(VehicleSimulator.from_scenario(
                    self.scenario, seed=self.seed, speedup=self.speedup, target=("127.0.0.1", port),
                    bind=("127.0.0.1", 0), max_stream_wall_hz=self.max_stream_wall_hz))
                url = f"udpin://127.0.0.1:{port}"
                position = self._true_position_builtin
            else:
                url = self.connect
                position = self._position_followed
            self.vehicle = await stack.enter_async_context(MavsdkVehicle(url))
            self._gnb_stack = contextlib.AsyncExitStack()
            await self._gnb_stack.__aenter__()
            stack.push_async_callback(self._close_gnb)
            self.gnb_sim = await self._gnb_stack.enter_async_context(SimulatedGnb(
                self.scenario, position, host="127.0.0.1", port=0, clock=self._sim_clock, seed=self.seed,
                rest_port=0 if self.gnb_transport == "rest" else None,
                t_port=0 if self.gnb_mode in ("trace", "auto") else None))
            rest = self.gnb_transport == "rest"
            self.gnb_client = await self._gnb_stack.enter_async_context(OaiGnbClient(GnbConfig.of(
                self.scenario.mission.gnb, "127.0.0.1", self.gnb_sim.rest_port if rest else self.gnb_sim.port,
                transport="rest" if rest else "telnet", seed=self.seed, mu=self.scenario.radio.mu,
                fs_hz=self.scenario.radio.fs_hz, mode=self.gnb_mode, t_port=self.gnb_sim.t_port or 2021,
                # an RTT keyframes take is at most this old in simulated seconds
                trace_max_age_s=self.scenario.mission.gnb.trace_max_age_s / self.speedup,
                # a jump the mission's own range noise can make (3 σ0) is no jump
                trace_jump_tolerance_m=max(self.scenario.mission.gnb.trace_jump_tolerance_m,
                                           3.0 * self.scenario.mission.noise.range_s0_m),
                request_timeout_s=self.gnb_request_timeout_s, connect_timeout_s=self.gnb_request_timeout_s,
                retries=1, backoff_max_s=0.2)))
            overrides = dict(self.controller_overrides)
            # the controller's gNB timeout covers the adapter's own timeout and one reconnect
            overrides.setdefault("gnb_timeout_s", 3.0 * self.gnb_request_timeout_s + 0.5)
            self.controller = controller_from_scenario(
                self.scenario, self.vehicle, self.gnb_client, self.log_path, planner=self.planner,
                seed=self.seed, time_scale=self.speedup, truth=self._truth, buildings=self._buildings,
                external_vehicle=self.connect is not None,
                header_config={"command": "sim", "speedup": self.speedup, "connect": self.connect,
                               "gnb_transport": self.gnb_transport, "gnb_mode": self.gnb_client.mode,
                               **self.header_config},
                **overrides)
        except BaseException:
            await stack.aclose()
            raise
        self._stack = stack
        return self

    async def __aexit__(self, *exc: object) -> None:
        stack, self._stack = self._stack, None
        if stack is not None:
            await stack.aclose()

    async def _close_gnb(self) -> None:
        gstack, self._gnb_stack = self._gnb_stack, None
        if gstack is not None:
            await gstack.aclose()

    async def kill_gnb(self) -> None:
        """Fault injection: stop the simulated gNB server (its port closes; the adapter sees a dead gNB)."""
        if self.gnb_sim is None:
            return
        sim, self.gnb_sim = self.gnb_sim, None
        await sim.__aexit__(None, None, None)
        log.warning("simulated gNB killed")

    async def run(self) -> MissionResult:
        """Run the mission; the simulators keep running until the context exits."""
        if self.controller is None:
            raise MissionError("SimulatedMission.run() needs `async with SimulatedMission(...)` first")
        return await self.controller.run()
