"""Where a simulated fleet's vehicles take off (docs/fleet.md): one rule for the fast mode and the
built-in MAVLink vehicles, so that a fleet flown in `uavloc sim` starts where the campaign's does."""

from __future__ import annotations

import numpy as np

from estimator.geodesy import Origin
from planner.fleet import Separation
from sitl_scenarios.scenario import Scenario, launch_points_enu_m
from uavloc.errors import SimulatorError


def scenario_launch_points_enu_m(scenario: Scenario) -> np.ndarray:
    """(V, 3) the launch points of the scenario's fleet (V = `mission.fleet_size`) in the scenario's
    ENU frame [m], as the fast mode places them (home at the scenario's origin)."""
    safety = scenario.mission.safety
    home = scenario.planning_constraints().home_enu_m
    return launch_points_enu_m(home, scenario.mission.fleet_size,
                               Separation(safety.separation_m, safety.separation_vertical_m))


def vehicle_home(scenario: Scenario, index: int) -> Origin:
    """The geodetic home of the scenario's vehicle `index` (0..fleet_size−1): its launch point
    (the scenario's origin for a one-vehicle scenario)."""
    n = scenario.mission.fleet_size
    if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < n:
        raise SimulatorError(f"vehicle index must be 0..{n - 1} for scenario {scenario.name!r}, got {index!r}")
    if n == 1:
        return scenario.origin_geo
    lat, lon, alt = scenario.origin_geo.enu_to_lla(scenario_launch_points_enu_m(scenario)[index])
    return Origin(float(lat), float(lon), float(alt))


def enu_between(pos_enu_m: np.ndarray, frame: Origin, to: Origin) -> np.ndarray:
    """Positions (..., 3) [m] in the ENU frame of `frame` -> the same points in the ENU frame of `to`."""
    if frame == to:
        return np.asarray(pos_enu_m, float)
    return to.lla_to_enu(*frame.enu_to_lla(pos_enu_m))
