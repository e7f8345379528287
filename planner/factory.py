"""`make_planner`: one place that turns a planner name into a planner object."""

from __future__ import annotations

from estimator.noise import NoiseModel
from planner.types import Planner, PlanningConstraints
from uavloc.errors import PlannerError


def _registry() -> dict:
    from planner.baselines import CirclePlanner, LawnmowerPlanner, RandomPlanner

    reg = {"lawnmower": LawnmowerPlanner, "circle": CirclePlanner, "random": RandomPlanner}
    try:
        from planner.active import ActivePlanner, GreedyPlanner, OraclePlanner, ReferenceActivePlanner
    except ImportError:  # pragma: no cover - only while planner.active is being written
        return reg
    reg.update({"casadi": ActivePlanner, "casadi_reference": ReferenceActivePlanner, "greedy": GreedyPlanner,
                "oracle": OraclePlanner})
    return reg


def planner_names() -> list[str]:
    """Names `make_planner` accepts."""
    return sorted(_registry())


def make_planner(
    name: str, constraints: PlanningConstraints, noise: NoiseModel, rng_seed: int = 0, **opts
) -> Planner:
    """A new planner (one per mission: planners keep warm starts and pattern progress).

    name: "casadi" (default of the mission), "lawnmower", "circle", "random", "greedy", "oracle"
    (needs `true_users_enu_m=(K, 3)`); opts go to the planner's constructor (e.g. lane_spacing_m,
    radius_m, horizon, criterion, cost_rel).
    """
    reg = _registry()
    if name not in reg:
        raise PlannerError(f"unknown planner {name!r}; choose one of {', '.join(sorted(reg))}")
    try:
        return reg[name](constraints, noise, rng_seed, **opts)
    except TypeError as exc:
        raise PlannerError(f"planner {name!r}: bad options {sorted(opts)}: {exc}") from exc
