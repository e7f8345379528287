"""One planner for a fleet: every vehicle's next leg, from the same objective, kept apart (docs/fleet.md).

Each vehicle carries a gNB, and a user is measured only by the vehicle whose gNB serves it
(`serving`, what the gNBs report: a UE stays on its cell until the cell moves out of reach). A
leg's information therefore goes to the users of its vehicle's cell, and the fleet's objective

    J(legs) = Σ_k w_k Σ_s c_ks g(f(I_ks)) + λ Σ_v ℓ_v,   I_ks = P_ks + Σ_v [serving_k = v] ΔI_ks(leg_v)

(planner.objective; ΔI the information a leg adds) is a sum over vehicles of each vehicle's own
users' terms: the joint minimum is each vehicle's minimum over its own users, subject to what
couples them, the separation between vehicles. So each vehicle's leg is chosen by its own planner
(the mission's, one per vehicle: warm starts and tracks are per vehicle) over the users its cell
serves and the users no cell serves yet (`PlanningState.users`), then checked against the legs the
other vehicles are committed to; a leg that comes too close is replaced by the separated ring leg
nearest to it, or, when none is, the vehicle holds where it is (a hold is always separated: every
committed leg was checked against it).

Separation. Two vehicles are apart when their horizontal distance is at least `horizontal_m` or
their altitudes differ by at least `vertical_m` (altitude layers). A leg is checked against the
whole remaining leg of every other vehicle in space, not in time: a leg flown late or early (wind,
a slow climb, an autopilot's own speed) is still apart. A vehicle with nowhere left to go for its
own users while users remain that no cell serves searches for them: a user some cell served and
lost (its vehicle went home, or flew out of reach) was within reach of where that vehicle last
planned from while it served it, so the searcher flies there first; for users no cell has heard, it
searches the ground no vehicle's track has covered nor will where the others are going, so that the
fleet covers the ground; once every user
is located and served, a vehicle whose users are within the target has nothing it can measure
(another cell serves the rest) and its part is done.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from estimator.types import Estimate
from planner.information import track_points_en_m, unsearched_point
from planner.stop import reported_bound_95_m
from planner.types import Planner, PlanningState, PlanResult
from uavloc.errors import PlannerError

log = logging.getLogger(__name__)

#: PlanResult.reason of a vehicle whose users are all within the target while other cells serve the rest
REASON_USERS_DONE = "its users done"
#: a vehicle that plans from within this distance [m] (or half the cell's reach, if less) of where a
#: lost user was last served, and still finds no cell serving it, stops looking for it there
SEARCH_NEAR_M = 40.0


@dataclass(frozen=True)
class Separation:
    """How far apart two vehicles must stay: horizontal_m apart [m], or vertical_m apart in altitude
    [m] (altitude layers; 0: no layers)."""

    horizontal_m: float = 15.0
    vertical_m: float = 10.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.horizontal_m) and self.horizontal_m > 0):
            raise PlannerError(f"separation horizontal_m must be positive, got {self.horizontal_m!r}")
        if not (np.isfinite(self.vertical_m) and self.vertical_m >= 0):
            raise PlannerError(f"separation vertical_m must be >= 0, got {self.vertical_m!r}")


def segment_distance_m(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> float:
    """Least horizontal distance [m] between the segments a0→a1 and b0→b1 (east, north of (≥2,) points).

    Two segments that cross are 0 apart; otherwise the least distance is from an end of one to the
    other segment:  min over the four ends e of |e − proj(e)|, proj onto the other segment clamped."""
    a0, a1, b0, b1 = (np.asarray(p, dtype=float)[:2] for p in (a0, a1, b0, b1))

    def cross(o, p, q) -> float:
        return float((p[0] - o[0]) * (q[1] - o[1]) - (p[1] - o[1]) * (q[0] - o[0]))

    d1, d2 = cross(b0, b1, a0), cross(b0, b1, a1)
    d3, d4 = cross(a0, a1, b0), cross(a0, a1, b1)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and d1 != 0 and d2 != 0 and d3 != 0 and d4 != 0:
        return 0.0

    def point_segment(p, s0, s1) -> float:
        v = s1 - s0
        vv = float(v @ v)
        t = 0.0 if vv == 0.0 else min(1.0, max(0.0, float((p - s0) @ v) / vv))
        return float(np.linalg.norm(p - (s0 + t * v)))

    return min(point_segment(a0, b0, b1), point_segment(a1, b0, b1),
               point_segment(b0, a0, a1), point_segment(b1, a0, a1))


def legs_separated(leg_a: np.ndarray, leg_b: np.ndarray, sep: Separation) -> bool:
    """True when every point of leg a is apart from every point of leg b (`Separation`); legs (2, 3)
    [start; end] in ENU [m] (a vehicle holding is a leg from its position to itself).

    Apart in altitude: the two legs' altitude intervals are vertical_m apart; else horizontally:
    segment_distance_m ≥ horizontal_m."""
    a, b = np.asarray(leg_a, dtype=float), np.asarray(leg_b, dtype=float)
    if sep.vertical_m > 0:
        gap = max(b[:, 2].min() - a[:, 2].max(), a[:, 2].min() - b[:, 2].max())
        if gap >= sep.vertical_m:
            return True
    return segment_distance_m(a[0], a[1], b[0], b[1]) >= sep.horizontal_m


def vehicles_apart(pos_enu_m: np.ndarray, sep: Separation) -> tuple[bool, float]:
    """Whether vehicles at positions (V, 3) [m, ENU] are pairwise apart now, and the least horizontal
    distance [m] between any two that are not altitude-separated (inf when there is none)."""
    p = np.asarray(pos_enu_m, dtype=float)
    least = np.inf
    ok = True
    for i in range(len(p)):
        for j in range(i + 1, len(p)):
            if sep.vertical_m > 0 and abs(p[i, 2] - p[j, 2]) >= sep.vertical_m:
                continue
            h = float(np.linalg.norm(p[i, :2] - p[j, :2]))
            least = min(least, h)
            ok &= h >= sep.horizontal_m
    return ok, least


def users_to_plan_for(vehicle: int, serving: np.ndarray) -> np.ndarray:
    """(K,) the users vehicle plans for: those its cell serves and those no cell serves (−1)."""
    s = np.asarray(serving)
    return (s == vehicle) | (s < 0)


def has_work(vehicle: int, serving: np.ndarray, estimate: Estimate | None, target_radius_m: float) -> bool:
    """Whether the vehicle still has users it can measure: one its cell serves whose reported bound
    is above the target (or not located yet), or one no cell serves (to be found)."""
    s = np.asarray(serving)
    if np.any(s < 0):
        return True
    mine = s == vehicle
    if not mine.any():
        return False
    if estimate is None:
        return True
    bound = reported_bound_95_m(estimate)
    return bool(np.any(mine & ~(bound <= target_radius_m)))


class FleetPlanner:
    """The fleet's planner (module docstring): one planner per vehicle, kept apart.

    plan(v, state, serving, committed) -> vehicle v's PlanResult. serving: (K,) the vehicle whose
    cell serves each user (−1: none); committed: per vehicle, the (2, 3) leg [position; waypoint] it
    is flying or holding (a vehicle that has landed or left the survey: None). A vehicle's own entry
    is ignored."""

    def __init__(self, planners: Sequence[Planner], separation: Separation = Separation()) -> None:
        if not planners:
            raise PlannerError("a fleet needs at least one vehicle's planner")
        self.planners = list(planners)
        self.separation = separation
        self.name = self.planners[0].name
        #: each vehicle's positions at its plans (V lists of (3,)): the ground the fleet has covered
        self.tracks: list[list[np.ndarray]] = [[] for _ in self.planners]
        #: user → (2,) east-north [m] of the serving vehicle's latest plan while a cell served it:
        #: a served user was within that cell's reach there, so a user lost by its cell is looked
        #: for there before anywhere else (forgotten once a vehicle has planned from near it)
        self.heard_en_m: dict[int, np.ndarray] = {}

    @property
    def n_vehicles(self) -> int:
        return len(self.planners)

    def prepare(self) -> None:
        for p in self.planners:
            p.prepare()

    def plan(self, vehicle: int, state: PlanningState, serving: np.ndarray,
             committed: Sequence[np.ndarray | None]) -> PlanResult:
        if not 0 <= vehicle < self.n_vehicles:
            raise PlannerError(f"vehicle {vehicle} outside 0..{self.n_vehicles - 1}")
        serving = np.asarray(serving)
        planner = self.planners[vehicle]
        self.tracks[vehicle].append(state.uav_enu_m.copy())
        self._note_heard(serving)
        if self.n_vehicles > 1 and not has_work(vehicle, serving, state.estimate,
                                                planner.constraints.target_radius_m):
            log.info("vehicle %d: its users are within the target, other cells serve the rest", vehicle)
            return PlanResult(state.uav_enu_m.copy(), np.zeros((0, 3)), done=True, reason=REASON_USERS_DONE,
                              status=planner.name)
        users = users_to_plan_for(vehicle, serving)
        res = planner.plan(dataclasses.replace(state, users=None if users.all() else users))
        others = [np.asarray(leg, dtype=float) for w, leg in enumerate(committed) if w != vehicle and leg is not None]
        if res.done:
            return res
        x = state.uav_enu_m
        # also when no other vehicle flies any more: the users it lost are still to be found
        if res.status.startswith("explore") and np.any(serving < 0):
            res = self._spread(planner, state, others, res, serving)
        if not others:
            return res
        if all(legs_separated(np.array([x, res.waypoint_enu_m]), o, self.separation) for o in others):
            return res
        ring = planner.feasible_ring(state) if hasattr(planner, "feasible_ring") else np.zeros((0, 3))
        ok = [wp for wp in ring if all(legs_separated(np.array([x, wp]), o, self.separation) for o in others)]
        if not ok:
            log.info("vehicle %d: no leg apart from the others; holding", vehicle)
            return PlanResult(x.copy(), x[None].copy(), done=False, status=f"{res.status}+hold")
        wp = min(ok, key=lambda p: float(np.linalg.norm(p - res.waypoint_enu_m)))
        return PlanResult(wp.copy(), wp[None].copy(), done=False, status=f"{res.status}+separated")

    def _note_heard(self, serving: np.ndarray) -> None:
        """Remember, for each served user, where its serving vehicle last planned from."""
        for k in np.flatnonzero(serving >= 0):
            track = self.tracks[int(serving[k])]
            if track:
                self.heard_en_m[int(k)] = track[-1][:2].copy()

    def _lost_user_point(self, state: PlanningState, serving: np.ndarray, reach_m: float) -> np.ndarray | None:
        """(2,) [m] the nearest point where a user that no cell serves now was last served, or None.
        A point a vehicle has planned from within half the cell's reach (or SEARCH_NEAR_M) is
        forgotten: the user would have attached there, so it is searched for like one never heard."""
        here = state.uav_enu_m[:2]
        near_m = min(0.5 * reach_m, SEARCH_NEAR_M) if np.isfinite(reach_m) else SEARCH_NEAR_M
        lost = []
        for k in np.flatnonzero(serving < 0):
            p = self.heard_en_m.get(int(k))
            if p is None:
                continue
            if float(np.linalg.norm(here - p)) <= near_m:
                del self.heard_en_m[int(k)]
                continue
            lost.append(p)
        if not lost:
            return None
        return min(lost, key=lambda p: float(np.linalg.norm(p - here)))

    def _spread(self, planner, state: PlanningState, others: list[np.ndarray], res: PlanResult,
                serving: np.ndarray) -> PlanResult:
        """An exploring vehicle's leg while users remain that no cell serves: toward where a cell
        last served such a user (it lost it: the user is within reach of there), else toward the
        ground no vehicle's track has covered, nor will where the others are going (a UE there
        would have attached to a cell passing within reach: planner.information.unsearched_point),
        so that the fleet searches different ground; the planner's own exploration when all is
        covered."""
        ring = planner.feasible_ring(state) if hasattr(planner, "feasible_ring") else np.zeros((0, 3))
        if len(ring) == 0:
            return res
        c = planner.constraints
        target = self._lost_user_point(state, serving, c.reach_m)
        status = "explore+lost"
        if target is None:
            pts = [track_points_en_m(np.array(t)) for t in self.tracks if t] + [track_points_en_m(o) for o in others]
            target = unsearched_point(c, np.concatenate(pts), state.uav_enu_m[:2])
            status = "explore+spread"
        if target is None:
            return res
        wp = ring[int(np.argmin(np.linalg.norm(ring[:, :2] - target, axis=1)))]
        return PlanResult(wp.copy(), wp[None].copy(), done=False, status=status)
