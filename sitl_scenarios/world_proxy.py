"""The world's simulators as the parent sees them: small proxies over the world's control channel
(`sitl_scenarios.world.WorldProcess.call`) with the simulators' own method names, so the fault
tests read as they did when the simulators lived in the mission's process.

- :class:`VehicleProxy` is a `VehicleSimulator` of the world: `state()`, `pause_link()`,
  `resume_link()`, `lose_gps()`, `restore_gps()`, `refuse_reposition()`, `set_battery_pct()`,
  `param()`, `set_param()`, `behind_s`, `wait_for()` (a predicate cannot cross processes: it is
  judged here, on `state()` polled over the channel);
- :class:`GnbProxy` is a `SimulatedGnb` of the world: `clock()`, `inject()`, the attributes the fault
  tests set (`rtt_module`, `current_rnti[k]`, `faults.<field>`) and read (`requests`,
  `rest_requests`, `crashed`), and `stamps()`, each range it computed with its stamp and UAV position;
- :class:`CellsProxy` is a fleet's `SharedCells`: `on_air`, `serving`.

Each call is one request answered over a pipe (a fraction of a millisecond on an idle machine; it
blocks the caller, so the controller never uses them: fault injection and tests only). A request
the world cannot answer raises SimulatorError.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from sitl_scenarios.vehicle.state import VehicleState
from sitl_scenarios.world import WorldProcess
from uavloc.errors import SimulatorError


class VehicleProxy:
    """Vehicle `index` of the world (see the module docstring)."""

    def __init__(self, world: WorldProcess, index: int) -> None:
        info = world.info.vehicles[index]
        self._world = world
        self.index = index
        self.system_id: int = info.system_id
        #: home and ENU origin of the vehicle's own frame
        self.origin: Origin = info.origin
        self.local_address: tuple[str, int] = info.address

    def _call(self, name: str, *args: Any) -> Any:
        return self._world.call("vehicle", self.index, name, args)

    def state(self) -> VehicleState:
        """The true state now (a snapshot)."""
        return self._call("state")

    def pause_link(self, duration_s: float) -> None:
        """Stop sending and drop everything received for duration_s simulated seconds."""
        self._call("pause_link", duration_s)

    def resume_link(self) -> None:
        self._call("resume_link")

    def lose_gps(self, duration_s: float | None = None) -> None:
        """No GPS fix (for duration_s simulated seconds, or until :meth:`restore_gps`)."""
        self._call("lose_gps", duration_s)

    def restore_gps(self) -> None:
        self._call("restore_gps")

    def refuse_reposition(self, duration_s: float | None = None) -> None:
        self._call("refuse_reposition", duration_s)

    def set_battery_pct(self, pct: float) -> None:
        """Set the remaining charge (e.g. 12 for a low battery); it keeps draining from there."""
        self._call("set_battery_pct", pct)

    def param(self, name: str) -> float:
        return self._call("param", name)

    def set_param(self, name: str, value: float) -> None:
        self._call("set_param", name, value)

    @property
    def behind_s(self) -> float:
        """Simulated time [s] the vehicle dropped when its thread fell behind the wall clock."""
        return self._world.call("vehicle_attr", self.index, "behind_s")

    @property
    def packets_in(self) -> int:
        return self._world.call("vehicle_attr", self.index, "packets_in")

    @property
    def packets_out(self) -> int:
        return self._world.call("vehicle_attr", self.index, "packets_out")

    async def wait_for(self, predicate: Callable[[VehicleState], bool], timeout_s: float,
                       poll_s: float = 0.02) -> VehicleState:
        """Wait (wall seconds) until predicate(state) holds, polling the world off the event loop;
        SimulatorError on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = await self._world.acall("vehicle", self.index, "state", ())
            if predicate(st):
                return st
            if time.monotonic() > deadline:
                raise SimulatorError(f"vehicle state condition not met within {timeout_s} s; last state {st}")
            await asyncio.sleep(poll_s)


class _Rntis:
    """A gNB's `current_rnti` list in the world: index, assign, iterate."""

    def __init__(self, gnb: GnbProxy) -> None:
        self._gnb = gnb

    def _list(self) -> list[int]:
        return self._gnb._get("current_rnti")

    def __getitem__(self, k: int) -> int:
        return self._list()[k]

    def __setitem__(self, k: int, rnti: int) -> None:
        self._gnb._set("current_rnti", (k, rnti))

    def __len__(self) -> int:
        return len(self._list())

    def __iter__(self) -> Iterator[int]:
        return iter(self._list())

    def __repr__(self) -> str:
        return repr(self._list())


class _Faults:
    """A gNB's `faults` (GnbFaults) in the world: read and set its fields."""

    def __init__(self, gnb: GnbProxy) -> None:
        object.__setattr__(self, "_gnb", gnb)

    def __getattr__(self, name: str) -> Any:
        return self._gnb._get(f"faults.{name}")

    def __setattr__(self, name: str, value: Any) -> None:
        self._gnb._set(f"faults.{name}", value)


class GnbProxy:
    """gNB `index` of the world (see the module docstring); `port`, `rest_port`, `t_port` where it
    listens on 127.0.0.1; `cell` its cell's index in the fleet's shared attachment (None: a single gNB)."""

    def __init__(self, world: WorldProcess, index: int) -> None:
        info = world.info.gnbs[index]
        self._world = world
        self.index = index
        self.host = "127.0.0.1"
        self.port: int = info.port
        self.rest_port: int | None = info.rest_port
        self.t_port: int | None = info.t_port
        self.cell: int | None = info.cell

    def _get(self, name: str) -> Any:
        return self._world.call("gnb_get", self.index, name)

    def _set(self, name: str, value: Any) -> None:
        self._world.call("gnb_set", self.index, name, value)

    def clock(self) -> float:
        """The gNB's clock: its vehicle's simulated time [s]."""
        return self._get("clock")

    def inject(self, kind: str, count: int = 1, delay_s: float | None = None) -> None:
        """Make the next `count` answers (connections, for "refuse") faulty (SimulatedGnb.inject)."""
        self._world.call("gnb_inject", self.index, kind, count, delay_s)

    def stamps(self) -> list[tuple[float, np.ndarray, int, float]]:
        """(t_s, uav_enu_m (3,), rnti, true_range_m) of every range the gNB computed (the latest
        world.TRACK_LEN): its stamp, the UAV position it used (the scenario's ENU frame) and the
        true distance it started from."""
        return self._get("stamps")

    @property
    def rtt_module(self) -> str:
        return self._get("rtt_module")

    @rtt_module.setter
    def rtt_module(self, name: str) -> None:
        self._set("rtt_module", name)

    @property
    def rtt_command(self) -> str:
        return self._get("rtt_command")

    @rtt_command.setter
    def rtt_command(self, name: str) -> None:
        self._set("rtt_command", name)

    @property
    def current_rnti(self) -> _Rntis:
        """Each user's current C-RNTI (`gnb.current_rnti[k] = rnti` sets it in the world)."""
        return _Rntis(self)

    @property
    def faults(self) -> _Faults:
        """The gNB's GnbFaults (`gnb.faults.rtt_module_lost_at_s = t` sets it in the world)."""
        return _Faults(self)

    @property
    def requests(self) -> int:
        """Telnet request lines served."""
        return self._get("requests")

    @property
    def connections(self) -> int:
        return self._get("connections")

    @property
    def rest_requests(self) -> int | None:
        """REST requests served (None: no REST API)."""
        return self._get("rest_requests")

    @property
    def crashed(self) -> str | None:
        return self._get("crashed")


class CellsProxy:
    """A fleet's shared cells in the world."""

    def __init__(self, world: WorldProcess) -> None:
        self._world = world

    @property
    def on_air(self) -> np.ndarray:
        """(V,) bool: which gNBs are on the air."""
        return np.asarray(self._world.call("cells")["on_air"], bool)

    @property
    def serving(self) -> np.ndarray:
        """(K,) each UE's serving cell (−1: none)."""
        return np.asarray(self._world.call("cells")["serving"], int)
