"""The mission controller's public face and its wiring (docs/design.md §1, §7).

:func:`controller_from_mission` builds a :class:`MissionController` for a mission file
(:class:`mission.config.MissionConfig`; a simulation scenario's is built by
sitl_scenarios.scenario.controller_from_scenario from its mission part). The controller itself
lives in the `mission.control` package, split by responsibility:

- `mission.control.config`: ControllerConfig, MissionResult, the states and statuses;
- `mission.control.state`: FlightState, the one object the flight and its background tasks share;
- `mission.control.pipeline`: the measurement pipeline (Δ-trigger and placer, owning their queues);
- `mission.control.estimator_worker`: the estimator off the event loop;
- `mission.control.safety_monitor`: the safety decision (pure) and its loop; the energy estimate;
- `mission.control.legs`: take-off and the survey's legs;
- `mission.control.journal`: the mission log's records and the status line;
- `mission.control.flight`: MissionController, the flight top to bottom.

The names these modules define are imported from them, not from here.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from estimator.types import SolverParams
from mission.config import with_settings
from mission.control.config import ControllerConfig, MissionUser
from mission.control.flight import MissionController
from mission.estimation import mission_solver_params
from mission.gnb import GnbClient
from mission.kernel_cache import use_kernel_cache
from mission.safety import SafetyLimits
from mission.vehicle import Vehicle
from planner.fleet import Separation
from planner.types import Planner
from uavloc.errors import PlannerError

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------
# building a controller from a mission file


#: the planner that plans at the users' true positions: simulations only
ORACLE_PLANNER = "oracle"


def resolve_planner_name(name: str, truth_known: bool = True) -> str:
    """The planner to use: `name`, except "casadi" falls back to "lawnmower" when CasADi's planner
    is not available. The oracle is refused where the true positions are unknown (a flight:
    truth_known False)."""
    from planner import planner_names

    names = planner_names()
    if name == "casadi" and name not in names:
        log.warning("the casadi planner is not available; planning with the lawnmower baseline")
        return "lawnmower"
    if name not in names:
        raise PlannerError(f"unknown planner {name!r}; choose one of {', '.join(names)}")
    if name == ORACLE_PLANNER and not truth_known:
        raise PlannerError("the oracle planner plans at the users' true positions, which only a simulation "
                           "knows (uavloc sim); choose one of "
                           f"{', '.join(n for n in names if n != ORACLE_PLANNER)}")
    return name


def controller_from_mission(mission, vehicle: Vehicle | Sequence[Vehicle], gnb: GnbClient | Sequence[GnbClient],
                            log_path: str | Path, *,
                            planner: str | None = None, seed: int = 0, time_scale: float = 1.0,
                            truth: Callable[[Origin], np.ndarray] | None = None,
                            header_config: dict | None = None, params: SolverParams | None = None,
                            constraints: Callable[[Origin], Any] | None = None,
                            buildings: Callable[[Origin], list] | None = None,
                            origin: Callable[[Sequence], Origin] | None = None,
                            **overrides: Any) -> MissionController:
    """A :class:`MissionController` flying a :class:`mission.config.MissionConfig` (a mission file).

    vehicle, gnb: its vehicle and gNB adapters, or a fleet's lists of them (one each per
    `[[vehicles]]` entry, in its order: docs/fleet.md). Each vehicle flies in its own altitude band
    at its own cruise altitude with its own planner of the mission's kind.

    planner: planner name (default: the mission's `flight.planner`); seed: planner seed;
    time_scale: simulator speedup; truth: simulation only (see MissionController); constraints:
    home -> PlanningConstraints (default `mission.planning_constraints(home)`); origin: the
    vehicles' homes -> the mission's ENU origin (MissionController; default vehicle 0's home);
    overrides: ControllerConfig fields, or mission file settings by their key alone (`time_limit_s=600`:
    the mission is flown with them, mission.config.with_settings). Geodetic polygons of the
    mission file become home-ENU once the vehicle's home is known (the planner and the safety
    limits are built then).
    """
    from planner import make_planner

    own = {f.name for f in dataclasses.fields(ControllerConfig)}
    settings = {k: v for k, v in overrides.items() if k not in own}
    if settings:
        mission = with_settings(mission, settings, "controller overrides")
    overrides = {k: v for k, v in overrides.items() if k in own}
    name = resolve_planner_name(planner or mission.flight.planner, truth_known=truth is not None)
    noise = mission.noise_model()
    make_constraints = constraints or mission.planning_constraints

    fleet = mission.fleet_size > 1

    def planner_at(home: Origin, vehicle: int = 0) -> Planner:
        # the oracle gets the true users in the controller's frame (ENU from the vehicle's home)
        opts = {"true_users_enu_m": truth(home)} if name == ORACLE_PLANNER else {}
        use_kernel_cache()
        c = make_constraints(home)
        if fleet:
            c = mission.vehicle_constraints(c, vehicle)
        # each vehicle's planner its own seed (the fast mode's, sitl_scenarios.campaign.fast)
        return make_planner(name, c, noise, rng_seed=seed + 7919 * vehicle, **opts)

    def limits_at(home: Origin, vehicle: int = 0) -> SafetyLimits:
        return SafetyLimits.from_mission(mission, home, vehicle=vehicle if fleet else None)

    g = mission.geofence
    if not fleet and not (g.polygon_lat_lon_deg or g.no_fly_lat_lon_deg):
        # ENU polygons do not depend on home: build now (a caller may wrap the planner before
        # run); the oracle's true users do, it is built once home is known
        here = Origin(0.0, 0.0, 0.0)
        planner_obj = planner_at if name == ORACLE_PLANNER else planner_at(here)
        limits = limits_at(here)
    else:
        planner_obj, limits = planner_at, limits_at
    config = ControllerConfig.from_mission(mission, time_scale=time_scale, **overrides)

    def vehicle_config(v: int) -> ControllerConfig:
        """Vehicle v's settings: the mission's, at its own cruise altitude within its own band."""
        if not fleet:
            return config
        lo, hi = mission.vehicle_band_m(v)
        return dataclasses.replace(config, flight=dataclasses.replace(
            config.flight, altitude_m=mission.vehicle_cruise_alt_m(v), alt_min_m=lo, alt_max_m=hi))

    users = [MissionUser(u.id, u.rnti, u.ground_height_m) for u in mission.users]
    cfg = {"mission": mission.name, "planner": name, "seed": seed, **(header_config or {})}
    radio = {"mu": mission.gnb.mu, "fs_hz": mission.gnb.fs_hz}
    if params is None:
        params = mission_solver_params(mission)
    return MissionController(vehicle, gnb, planner_obj, users, noise, limits, config, log_path,
                             params=params, truth=truth, header_config=cfg, radio=radio, buildings=buildings,
                             vehicle_ids=[v.id for v in mission.vehicles] if fleet else None,
                             vehicle_config=vehicle_config,
                             separation=Separation(mission.safety.separation_m, mission.safety.separation_vertical_m),
                             origin=origin)

