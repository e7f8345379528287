"""Built-in MAVLink multicopter that MAVSDK takes for PX4 (docs/design.md §9).

MAVLink 2 over UDP, system 1 component 1, PX4 heartbeat and custom modes, the telemetry streams
MAVSDK uses, the command, parameter and mission protocols, offboard position setpoints.

Use it in a test or inside `uavloc sim`::

    async with VehicleSimulator(origin, VehicleConfig(), speedup=10, target=("127.0.0.1", 14540)) as sim:
        ...                       # MAVSDK: add_any_connection("udpin://0.0.0.0:14540")
        sim.state().pos_enu_m     # true position for the simulated gNB
        sim.pause_link(8.0)       # fault injection

or standalone: `python -m sitl_scenarios.vehicle --scenario paper --speedup 10`.

The modules, by responsibility:

- `simulator`: :class:`VehicleSimulator`, the thread, the clock and the public API;
- `link`: the UDP socket, its peers, pymavlink's encoder and parser;
- `commands`, `parameters`, `missions`: the command (and offboard), parameter and mission protocols;
- `streams`: which telemetry messages are sent how often, and each one encoded;
- `autopilot`: arming, flight modes, failsafes, guidance (no sockets, no clocks); `state`: its snapshot;
- `navigator`: missions and return to launch; `kinematics`: the flight model;
- `sensors`: GPS error and battery; `faults`: the scenario's fault events and the faults in effect;
- `px4`, `params`, `mav`: PX4's custom modes, capabilities and parameters, and the MAVLink enum
  values, all from pymavlink;
- `cli`: `python -m sitl_scenarios.vehicle`.

Time: the simulation runs `speedup` times faster than the wall clock; every MAVLink timestamp is
simulated time. Fault durations are simulated seconds.
"""

from sitl_scenarios.vehicle.autopilot import VehicleState
from sitl_scenarios.vehicle.cli import main
from sitl_scenarios.vehicle.faults import FaultEvent, faults_from_scenario
from sitl_scenarios.vehicle.kinematics import quaternion as _quaternion
from sitl_scenarios.vehicle.kinematics import wrap_pi as _wrap_pi
from sitl_scenarios.vehicle.mav import RESULT_UNSUPPORTED_MAV_FRAME
from sitl_scenarios.vehicle.simulator import COMPONENT_ID, DEFAULT_TARGET, SYSTEM_ID, VehicleSimulator

__all__ = ["COMPONENT_ID", "DEFAULT_TARGET", "RESULT_UNSUPPORTED_MAV_FRAME", "SYSTEM_ID", "FaultEvent",
           "VehicleSimulator", "VehicleState", "_quaternion", "_wrap_pi", "faults_from_scenario", "main"]
