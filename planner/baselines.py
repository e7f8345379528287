"""Fixed-pattern and naive baselines behind the planner interface (docs/design.md §6).

- :class:`LawnmowerPlanner`: boustrophedon lanes over the fence (or the distance disc) at the cruise
  altitude; legs follow the lanes, split at `leg_max_m`; the pattern restarts reversed when done.
- :class:`CirclePlanner`: explores until every user has an estimate, then circles the users'
  first estimated centroid at a fixed radius.
- :class:`RandomPlanner`: a seeded random feasible ring candidate each leg.

They ignore the covariance (except for the circle's centre) and share the stop rule, the exact
check and the fallback of :class:`planner.base.BasePlanner`.
"""

from __future__ import annotations

import logging

import numpy as np

from estimator.noise import NoiseModel
from planner.base import BasePlanner
from planner.geometry import clearance_m, in_free_space, legs_feasible, route_en
from planner.information import explore_waypoint, users_initialised
from planner.types import PlanningConstraints, PlanningState
from uavloc.errors import PlannerError

log = logging.getLogger(__name__)


def _free_runs(points_m: np.ndarray, free: np.ndarray) -> list[np.ndarray]:
    """Split (N, 2) points along a line into runs of consecutive free points; each run (2, 2): ends."""
    runs, start = [], None
    for i, ok in enumerate(np.append(free, False)):
        if ok and start is None:
            start = i
        elif not ok and start is not None:
            if i - 1 > start:
                runs.append(points_m[[start, i - 1]])
            start = None
    return runs


def lawnmower_path(
    constraints: PlanningConstraints, lane_spacing_m: float, altitude_m: float, step_m: float = 1.0
) -> np.ndarray:
    """(V, 3) vertices of boustrophedon lanes (east-west lines, `lane_spacing_m` apart) over the free space.

    Region: the fence's bounding box, or the square around home of half-side `max_distance_m`.
    Each lane is sampled every `step_m` and cut into runs of points that are free, keep the margin
    + 1 m and lie inside the distance disc (−1 m); run ends become vertices, every other lane
    reversed. Between vertices the planner routes around obstacles (planner.geometry.route_en).
    """
    c = constraints
    if lane_spacing_m <= 0:
        raise PlannerError(f"lane_spacing_m must be positive, got {lane_spacing_m}")
    if len(c.fence_enu_m):
        lo, hi = c.fence_enu_m.min(axis=0), c.fence_enu_m.max(axis=0)
    else:
        lo, hi = c.home_enu_m[:2] - c.max_distance_m, c.home_enu_m[:2] + c.max_distance_m
    n_lanes = max(1, int(np.floor((hi[1] - lo[1]) / lane_spacing_m)))
    # centre the lanes in the region: first lane half a spacing in from the south edge
    ys = lo[1] + (hi[1] - lo[1] - (n_lanes - 1) * lane_spacing_m) / 2 + lane_spacing_m * np.arange(n_lanes)
    xs = np.arange(lo[0], hi[0] + step_m, step_m)
    vertices = []
    for j, y in enumerate(ys):
        pts = np.column_stack([xs, np.full_like(xs, y)])
        free = (
            in_free_space(pts, c)
            & (clearance_m(pts, c) >= c.margin_m + 1.0)
            & (np.linalg.norm(pts - c.home_enu_m[:2], axis=1) <= c.max_distance_m - 1.0)
        )
        runs = _free_runs(pts, free)
        if j % 2 == 1:
            runs = [r[::-1] for r in runs[::-1]]
        for r in runs:
            vertices.extend(r)
    if not vertices:
        raise PlannerError("the lawnmower found no free lane in the fence")
    v = np.array(vertices)
    return np.column_stack([v, np.full(len(v), altitude_m)])


def toward(start_enu_m: np.ndarray, target_enu_m: np.ndarray, leg_cap_m: float) -> np.ndarray:
    """The target, or the point `leg_cap_m` along the straight line to it when it is farther."""
    d = float(np.linalg.norm(target_enu_m - start_enu_m))
    if d <= leg_cap_m:
        return np.asarray(target_enu_m, dtype=float).copy()
    return start_enu_m + (target_enu_m - start_enu_m) * (0.999 * leg_cap_m / d)


def routed_step(
    constraints: PlanningConstraints, start_enu_m: np.ndarray, target_enu_m: np.ndarray, leg_cap_m: float
) -> np.ndarray | None:
    """First leg (capped at `leg_cap_m`) of the shortest free route to the target at its altitude;
    None when the target cannot be reached."""
    hops = route_en(constraints, start_enu_m[:2], target_enu_m[:2])
    if hops is None:
        return None
    hop = np.array([*hops[0], target_enu_m[2]])
    return toward(start_enu_m, hop, leg_cap_m)


class LawnmowerPlanner(BasePlanner):
    """Boustrophedon coverage at the cruise altitude; see :func:`lawnmower_path`.

    Each call flies toward the next lane vertex (at most `leg_max_m`), around obstacles along the
    shortest free route; an unreachable vertex is skipped.
    """

    name = "lawnmower"

    def __init__(
        self, constraints: PlanningConstraints, noise: NoiseModel, rng_seed: int = 0, lane_spacing_m: float = 50.0
    ) -> None:
        super().__init__(constraints, noise, rng_seed)
        self.path_enu_m = lawnmower_path(constraints, lane_spacing_m, constraints.cruise_alt_m)
        self._next: int | None = None

    def _propose(self, state: PlanningState, leg_cap_m: float) -> tuple[np.ndarray, str, float]:
        x = state.uav_enu_m
        if self._next is None:
            # start at whichever end of the pattern is nearer
            if np.linalg.norm(self.path_enu_m[-1] - x) < np.linalg.norm(self.path_enu_m[0] - x):
                self.path_enu_m = self.path_enu_m[::-1].copy()
            self._next = 0
        for _ in range(len(self.path_enu_m) + 1):
            target = self.path_enu_m[self._next]
            # a vertex nearer than the shortest useful leg is as good as reached: the flight counts
            # a waypoint reached within its acceptance radius (2 m by default) and a drifting GPS
            # fix wanders by about that, so a tighter test sends the UAV to the same vertex again
            # and again
            if np.linalg.norm(target - x) < self.constraints.min_leg_m:
                self._advance()
                continue
            step = routed_step(self.constraints, x, target, leg_cap_m)
            if step is not None:
                return step, self.name, float("nan")
            log.info("lawnmower: vertex %s unreachable from %s; skipped", target, x)
            self._advance()
        return x.copy(), self.name, float("nan")  # the base falls back to the ring

    def _advance(self) -> None:
        self._next += 1
        if self._next >= len(self.path_enu_m):
            self.path_enu_m = self.path_enu_m[::-1].copy()
            self._next = 1 if len(self.path_enu_m) > 1 else 0


class RandomPlanner(BasePlanner):
    """A uniformly drawn feasible ring candidate (36 headings, three lengths) each leg; seeded."""

    name = "random"

    def _propose(self, state: PlanningState, leg_cap_m: float) -> tuple[np.ndarray, str, float]:
        ring = self.feasible_ring(state, n_headings=36)
        if len(ring) == 0:
            return state.uav_enu_m.copy(), self.name, float("nan")  # the base turns this into "no leg"
        return ring[self.rng.integers(len(ring))].copy(), self.name, float("nan")


class CirclePlanner(BasePlanner):
    """Explore until every user is initialised, then circle their estimated centroid.

    The centre is fixed at the first estimate with all users initialised (the paper-style "circle
    around the first estimate"); radius `radius_m` (default: 40 m); waypoints advance along the
    circle by a chord of at most `leg_max_m`; infeasible circle points are skipped.
    """

    name = "circle"

    def __init__(
        self, constraints: PlanningConstraints, noise: NoiseModel, rng_seed: int = 0, radius_m: float = 40.0
    ) -> None:
        super().__init__(constraints, noise, rng_seed)
        if radius_m <= 0:
            raise PlannerError(f"circle radius_m must be positive, got {radius_m}")
        self.radius_m = radius_m
        self.centre_enu_m: np.ndarray | None = None
        self._angle: float | None = None
        self._visited: list[np.ndarray] = []

    def _propose(self, state: PlanningState, leg_cap_m: float) -> tuple[np.ndarray, str, float]:
        self._visited.append(state.uav_enu_m.copy())
        est = state.estimate
        if self.centre_enu_m is None and est is not None and users_initialised(est).all():
            self.centre_enu_m = np.mean(est.users_enu_m[:, :2], axis=0)
            log.info("circle planner: centre %s", self.centre_enu_m)
        if self.centre_enu_m is None:
            wp = explore_waypoint(self, state, np.array(self._visited))
            return wp, "circle:explore", float("nan")
        c, x = self.constraints, state.uav_enu_m
        if self._angle is None:
            self._angle = float(np.arctan2(*(x[:2] - self.centre_enu_m)[::-1]))
        # chord 2 r sin(Δθ/2) ≤ leg cap  →  Δθ = 2 asin(min(1, cap / 2r))
        step = 2 * np.arcsin(min(1.0, 0.95 * leg_cap_m / (2 * self.radius_m)))
        step = min(step, np.pi / 4)
        for k in range(1, 9):
            a = self._angle + k * step
            p = np.array([*(self.centre_enu_m + self.radius_m * np.array([np.cos(a), np.sin(a)])), c.cruise_alt_m])
            if legs_feasible(c, x, p[None], leg_cap_m, state.energy_remaining_m)[0]:
                self._angle = a
                return p, self.name, float("nan")
        self._angle += step
        a = self._angle
        p = np.array([*(self.centre_enu_m + self.radius_m * np.array([np.cos(a), np.sin(a)])), c.cruise_alt_m])
        return p, self.name, float("nan")
