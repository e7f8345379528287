"""Active planning: choose the next waypoint that shrinks the users' uncertainty fastest (docs/design.md §6).

Pure numpy + CasADi: no asyncio, sockets, files or clocks (the caller times `plan` for
`PlanResult.solve_time_s`).

How the mission controller uses it
----------------------------------
Once per mission::

    constraints = mission.planning_constraints(home)     # a mission.config.MissionConfig
    planner = make_planner(mission.flight.planner, constraints, mission.noise_model(), rng_seed=seed)

At takeoff and at every leg end::

    result = planner.plan(PlanningState(uav_enu_m=x, estimate=latest_estimate_or_None,
                                        flown_m=survey_metres_so_far,
                                        energy_remaining_m=battery_metres_left_or_inf))
    if result.done:          # result.reason: "target reached" | "budget spent" | "no feasible leg"
        return_home()
    else:
        fly_to(result.waypoint_enu_m)   # (3,) ENU [m]; already passed the exact constraint check

Guarantees: a returned (not done) waypoint's straight leg from `uav_enu_m` passes
:func:`planner.geometry.leg_checks` (leg length, altitude band, distance from home, energy with
return home, inside the fence and outside no-fly zones with `margin_m` clearance along the whole
leg). `plan` raises :class:`uavloc.errors.PlannerError` when the UAV itself is outside the free
space (the controller should return home). The safety gate should still check independently.

Names: "casadi" (IPOPT on the information objective; options criterion "E"|"A"|"D", horizon,
cost_rel, sigma_points, weighting, user_weights — see planner.active.ActivePlanner), "greedy"
(best full-length heading of a 24-ring on the A-optimal objective), "oracle" (casadi given the
true users, `true_users_enu_m=`), "lawnmower", "circle", "random".

Users the estimator has not initialised yet (NaN rows): while no user can be planned for (or all
planned-for users already meet the target), planners explore — they fly the feasible leg that
spreads the track out most (see :func:`planner.information.explore_waypoint`). Users estimated
more than 5 km from home (a diverged solve) count as not initialised.
"""

from planner.factory import make_planner, planner_names
from planner.stop import budget_left_m, stop_reason, targets_reached
from planner.types import (
    REASON_BUDGET,
    REASON_FLOOR,
    REASON_NO_LEG,
    REASON_TARGET,
    Planner,
    PlanningConstraints,
    PlanningState,
    PlanResult,
)

__all__ = [
    "REASON_BUDGET",
    "REASON_FLOOR",
    "REASON_NO_LEG",
    "REASON_TARGET",
    "PlanResult",
    "Planner",
    "PlanningConstraints",
    "PlanningState",
    "budget_left_m",
    "make_planner",
    "planner_names",
    "stop_reason",
    "targets_reached",
]
