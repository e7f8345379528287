"""Where a simulated fleet's vehicles take off (docs/fleet.md): one rule for the fast mode and the
built-in MAVLink vehicles, so that a fleet flown in `uavloc sim` starts where the campaign's does."""

from __future__ import annotations

import numpy as np

from estimator.geodesy import Origin
from planner.fleet import Separation
from sitl_scenarios.scenario import Scenario
from uavloc.errors import SimulatorError


def launch_points_enu_m(home_enu_m: np.ndarray, n_vehicles: int, separation: Separation) -> np.ndarray:
    """(V, 3) where a simulated fleet's vehicles take off: on a ring around home, vehicle v at bearing
    θ_v = 2πv/V from east, neighbours 5 m more than the horizontal separation
    apart (one vehicle: at home). A UE attaches to the nearest cell at take-off, so a ring gives each
    vehicle the users of its own sector; on a line, the middle vehicle of three took off with none."""
    home = np.asarray(home_enu_m, float)
    if n_vehicles == 1:
        return home[None, :].copy()
    # neighbours on the ring a chord 2 r sin(π/V) = separation + 5 m apart
    r = (separation.horizontal_m + 5.0) / (2.0 * np.sin(np.pi / n_vehicles))
    theta = 2.0 * np.pi * np.arange(n_vehicles) / n_vehicles
    return home[None, :] + np.column_stack([r * np.cos(theta), r * np.sin(theta), np.zeros(n_vehicles)])


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
