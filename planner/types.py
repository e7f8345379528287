"""The planner's contract with the mission controller (docs/design.md §6).

Plain dataclasses on numpy arrays, all positions in the mission's local ENU frame [m]:

- :class:`PlanningConstraints`: what may be flown (fence, no-fly zones, altitude band, leg length,
  distance from home, survey budget); built once per mission, e.g. with
  `mission.config.MissionConfig.planning_constraints(home)`.
- :class:`PlanningState`: where the UAV is and what the estimator knows, at one leg end.
- :class:`PlanResult`: the next waypoint (or `done` with a reason), with diagnostics.
- :class:`Planner`: anything with ``plan(state) -> PlanResult``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from estimator.types import Estimate
from uavloc.errors import PlannerError

#: `PlanResult.reason` values when `done` is True.
REASON_TARGET = "target reached"
REASON_BUDGET = "budget spent"
#: the users' bounds stopped shrinking above the target: what is left is what no flight removes
REASON_FLOOR = "floor reached"
REASON_NO_LEG = "no feasible leg"


def _polygon(points, name: str) -> np.ndarray:
    """(P, 2) float array of a polygon's vertices, or (0, 2) for an empty one."""
    arr = np.asarray(points, dtype=float).reshape(-1, 2) if len(points) else np.zeros((0, 2))
    if arr.shape[0] and (arr.shape[0] < 3 or not np.all(np.isfinite(arr))):
        raise PlannerError(f"{name} needs >= 3 finite [east, north] vertices, got {arr.tolist()!r}")
    return arr


@dataclass(frozen=True)
class PlanningConstraints:
    """Where and how far the UAV may fly, in ENU metres.

    home_enu_m: (3,) home position (return point; centre of the distance limit).
    fence_enu_m: (P, 2) inclusion polygon (east, north), may be non-convex; (0, 2): no polygon.
    no_fly_enu_m: tuple of (Q_i, 2) exclusion polygons (any shape).
    alt_min_m, alt_max_m: allowed band of the ENU `up` coordinate [m] (not above home: absolute).
    cruise_alt_m: ENU `up` at which the fixed-pattern baselines fly [m].
    leg_max_m: longest leg the planner may choose [m]; min_leg_m: shortest useful leg [m].
    max_distance_m: maximum horizontal distance from home [m].
    budget_m: metres the survey may fly in total (the state's `flown_m` counts against it).
    delta_m: measurement spacing Δ along a leg [m].
    target_radius_m: stop when every user's 95 % error ellipse is inside this radius [m].
    floor_m: the 95 % bound the GPS error leaves common to every user however the survey flies [m]
        (mission.config.gps_floor_m; 0: none); the stop rule ends a survey whose bounds are there
        (planner.stop.FloorWatch).
    margin_m: clearance kept from fence and no-fly edges [m].
    return_factor: the energy check asks leg + return_factor·(straight distance home) ≤ energy.
    coverage_m: the gNB's reach, the slant range beyond which it hears no UE [m] (inf: everywhere):
        the objective counts no ranges from beyond it (planner.objective, "Coverage").
    """

    home_enu_m: np.ndarray
    fence_enu_m: np.ndarray
    no_fly_enu_m: tuple[np.ndarray, ...]
    alt_min_m: float
    alt_max_m: float
    cruise_alt_m: float
    leg_max_m: float
    max_distance_m: float
    budget_m: float
    delta_m: float = 2.0
    target_radius_m: float = 2.0
    floor_m: float = 0.0
    margin_m: float = 2.0
    min_leg_m: float = 10.0
    return_factor: float = 1.2
    coverage_m: float = float("inf")

    def __post_init__(self) -> None:
        home = np.asarray(self.home_enu_m, dtype=float).reshape(3)
        object.__setattr__(self, "home_enu_m", home)
        object.__setattr__(self, "fence_enu_m", _polygon(self.fence_enu_m, "fence_enu_m"))
        object.__setattr__(
            self,
            "no_fly_enu_m",
            tuple(_polygon(p, f"no_fly_enu_m[{i}]") for i, p in enumerate(self.no_fly_enu_m)),
        )
        if not np.all(np.isfinite(home)):
            raise PlannerError(f"home_enu_m must be finite, got {home}")
        if not self.alt_min_m <= self.cruise_alt_m <= self.alt_max_m:
            raise PlannerError(
                f"need alt_min_m <= cruise_alt_m <= alt_max_m, got {self.alt_min_m}, {self.cruise_alt_m}, "
                f"{self.alt_max_m}"
            )
        for name in ("leg_max_m", "max_distance_m", "budget_m", "delta_m", "target_radius_m", "min_leg_m"):
            if not getattr(self, name) > 0:
                raise PlannerError(f"{name} must be positive, got {getattr(self, name)!r}")
        if self.min_leg_m > self.leg_max_m:
            raise PlannerError(f"min_leg_m {self.min_leg_m} exceeds leg_max_m {self.leg_max_m}")
        if not self.floor_m >= 0:
            raise PlannerError(f"floor_m must be >= 0, got {self.floor_m!r}")
        if not self.coverage_m > 0:
            raise PlannerError(f"coverage_m must be positive, got {self.coverage_m!r}")
        if self.margin_m < 0 or self.return_factor < 1:
            raise PlannerError(f"need margin_m >= 0 and return_factor >= 1, got {self.margin_m}, {self.return_factor}")

    @property
    def reach_m(self) -> float:
        """Horizontal distance [m] within which a UE on the ground hears the cell of a UAV at the
        cruise altitude: √(R² − h²), R = coverage_m, h the cruise height above home (inf: no limit)."""
        h = self.cruise_alt_m - self.home_enu_m[2]
        return float(np.sqrt(max(self.coverage_m**2 - h * h, 0.0)))

    @property
    def edges_enu_m(self) -> tuple[np.ndarray, np.ndarray]:
        """(E, 2) start and (E, 2) end points of every fence and no-fly edge [m]."""
        polys = ([self.fence_enu_m] if len(self.fence_enu_m) else []) + list(self.no_fly_enu_m)
        if not polys:
            return np.zeros((0, 2)), np.zeros((0, 2))
        e0 = np.concatenate(polys)
        e1 = np.concatenate([np.roll(p, -1, axis=0) for p in polys])
        return e0, e1


@dataclass(frozen=True)
class PlanningState:
    """The situation at a leg end.

    uav_enu_m: (3,) current UAV position [m, ENU].
    estimate: the estimator's latest :class:`Estimate`, or None before the first range.
    flown_m: metres flown in the survey so far (counts against `PlanningConstraints.budget_m`).
    energy_remaining_m: metres the battery still allows, return home included (inf: not limited).
    users: (K,) bool, the users this vehicle's legs can measure and the planner plans for (a fleet's
        vehicle: those its gNB serves and those none serves yet, planner.fleet); None: every user.
    """

    uav_enu_m: np.ndarray
    estimate: Estimate | None = None
    flown_m: float = 0.0
    energy_remaining_m: float = float("inf")
    users: np.ndarray | None = None

    def __post_init__(self) -> None:
        x = np.asarray(self.uav_enu_m, dtype=float).reshape(3)
        if not np.all(np.isfinite(x)):
            raise PlannerError(f"uav_enu_m must be finite, got {x}")
        object.__setattr__(self, "uav_enu_m", x)
        if self.users is not None:
            u = np.asarray(self.users, dtype=bool)
            if u.ndim != 1 or (self.estimate is not None and u.shape != (self.estimate.n_users,)):
                raise PlannerError(f"users must be a (K,) bool mask, got shape {u.shape}")
            object.__setattr__(self, "users", u)


@dataclass(frozen=True)
class PlanResult:
    """The planner's answer.

    waypoint_enu_m: (3,) next waypoint [m, ENU] (the current position when `done`).
    horizon_enu_m: (H, 3) the planned waypoints, the first being `waypoint_enu_m` (H = 0 when done).
    done: stop the survey and return home; reason: REASON_TARGET, REASON_FLOOR,
        REASON_BUDGET or REASON_NO_LEG.
    objective: the planner's predicted objective for the chosen leg (nan for fixed patterns).
    status: how the waypoint was found ("ipopt", "ring", "explore", "lawnmower", ...).
    solve_time_s: compute time of the call [s], measured by the caller (the planner is pure: no
    clock); diagnostic only, never used in a decision.
    """

    waypoint_enu_m: np.ndarray
    horizon_enu_m: np.ndarray
    done: bool
    reason: str = ""
    objective: float = float("nan")
    status: str = ""
    solve_time_s: float = 0.0


class Planner(Protocol):
    """A planner: stateful per mission (warm start, pattern progress, seeded randomness)."""

    name: str
    constraints: PlanningConstraints

    def plan(self, state: PlanningState) -> PlanResult:
        """The next waypoint from `state`, or `done`; raises PlannerError on bad input."""
        ...

    def prepare(self) -> None:
        """Do now, before take-off, the one-time work the first plans would pay for (building and
        compiling solver kernels), so that the vehicle never hovers for it."""
        ...
