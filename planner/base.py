"""What every planner shares: the stop rule, the candidate ring, and the exact final check.

A concrete planner implements ``_propose(state, leg_cap_m) -> (waypoint (3,), status, objective)``;
:meth:`BasePlanner.plan` then refuses anything the exact check (planner.geometry.leg_checks) does
not pass and falls back to the feasible ring candidate nearest to the proposal, so no planner can
return a waypoint that violates a constraint.
"""

from __future__ import annotations

import logging

import numpy as np

from estimator.noise import NoiseModel
from planner.geometry import in_free_space, leg_violations, legs_feasible
from planner.stop import FloorWatch, stop_reason
from planner.types import REASON_NO_LEG, PlanningConstraints, PlanningState, PlanResult
from uavloc.errors import PlannerError

log = logging.getLogger(__name__)

#: a proposal shorter than this is no move at all [m]; the fallback replaces it.
MIN_MOVE_M = 1.0


def ring_candidates(
    start_enu_m: np.ndarray,
    leg_cap_m: float,
    altitudes_m: np.ndarray,
    n_headings: int = 24,
    length_fractions: tuple[float, ...] = (1.0, 0.5),
    min_leg_m: float = 0.0,
) -> np.ndarray:
    """(C, 3) leg ends on rings around the start, C = n_headings·len(length_fractions)·len(altitudes).

    end = start + ℓ·(cos θ, sin θ) horizontally at altitude z, with the 3-D leg length ℓ_3d =
    f·leg_cap_m for each fraction f (the horizontal run shrinks by the climb):
    ℓ_h = sqrt(ℓ_3d² − (z − z_start)²). Rings whose 3-D length is below min_leg_m, or that the climb
    alone exceeds, are left out.
    """
    x = np.asarray(start_enu_m, dtype=float)
    theta = 2 * np.pi * np.arange(n_headings) / n_headings
    out = []
    for z in np.atleast_1d(altitudes_m):
        dz = float(z) - x[2]
        for f in length_fractions:
            length = f * leg_cap_m
            if length < min_leg_m or abs(dz) >= length:
                continue
            run = np.sqrt(length**2 - dz**2)
            ends = np.column_stack(
                [x[0] + run * np.cos(theta), x[1] + run * np.sin(theta), np.full(n_headings, float(z))]
            )
            out.append(ends)
    return np.concatenate(out) if out else np.zeros((0, 3))


class BasePlanner:
    """Stop rule + exact check + fallback around a subclass's `_propose`.

    Subclasses set `name` and implement `_propose(state, leg_cap_m)`; they keep their own state
    between calls (one planner object per mission).
    """

    name = "base"

    def __init__(self, constraints: PlanningConstraints, noise: NoiseModel, rng_seed: int = 0) -> None:
        self.constraints = constraints
        self.noise = noise
        self.rng = np.random.default_rng(rng_seed)
        #: the stop rule's floor watch over this mission's bounds (None: never at the floor)
        self.floor_watch: FloorWatch | None = FloorWatch.of(constraints)

    # -- to implement ----------------------------------------------------------------------------
    def _propose(self, state: PlanningState, leg_cap_m: float) -> tuple[np.ndarray, str, float]:
        raise NotImplementedError

    # -- shared ----------------------------------------------------------------------------------
    def prepare(self) -> None:
        """One-time work before take-off (planner.types.Planner.prepare): none for most planners."""

    def leg_cap_m(self, state: PlanningState) -> float:
        """Longest leg allowed now: min(leg_max_m, survey budget left) [m]."""
        return float(min(self.constraints.leg_max_m, self.constraints.budget_m - state.flown_m))

    def candidate_altitudes_m(self, state: PlanningState) -> np.ndarray:
        """Altitudes the ring tries: the band's floor, the current altitude (clipped), the cruise altitude."""
        c = self.constraints
        z = np.clip(state.uav_enu_m[2], c.alt_min_m, c.alt_max_m)
        return np.unique(np.array([c.alt_min_m, z, c.cruise_alt_m]))

    def feasible_ring(self, state: PlanningState, n_headings: int = 24) -> np.ndarray:
        """(C, 3) ring candidates that pass the exact check (full and half legs, three altitudes)."""
        c = self.constraints
        cap = self.leg_cap_m(state)
        ring = ring_candidates(
            state.uav_enu_m, cap, self.candidate_altitudes_m(state), n_headings, (1.0, 0.6, 0.3), c.min_leg_m
        )
        if len(ring) == 0:
            return ring
        ok = legs_feasible(c, state.uav_enu_m, ring, cap, state.energy_remaining_m)
        return ring[ok]

    def _done(self, state: PlanningState, reason: str) -> PlanResult:
        log.info("%s planner: done (%s) at %s after %.0f m", self.name, reason, state.uav_enu_m, state.flown_m)
        return PlanResult(
            waypoint_enu_m=state.uav_enu_m.copy(),
            horizon_enu_m=np.zeros((0, 3)),
            done=True,
            reason=reason,
            status=self.name,
        )

    def plan(self, state: PlanningState) -> PlanResult:
        """Next waypoint, or done (target reached / floor reached / budget spent / no feasible leg)."""
        c = self.constraints
        if not bool(in_free_space(state.uav_enu_m[:2], c)):
            raise PlannerError(
                f"UAV at {state.uav_enu_m.tolist()} is outside the fence or inside a no-fly zone; "
                "the planner cannot route from there (return home)"
            )
        reason = stop_reason(c, state, self.floor_watch)
        if reason is not None:
            return self._done(state, reason)
        cap = self.leg_cap_m(state)
        wp, status, objective = self._propose(state, cap)
        wp = np.asarray(wp, dtype=float).reshape(3)
        bad = leg_violations(c, state.uav_enu_m, wp, cap, state.energy_remaining_m)
        length = float(np.linalg.norm(wp - state.uav_enu_m))
        if bad or length < MIN_MOVE_M:
            ring = self.feasible_ring(state)
            if len(ring) == 0:
                log.warning("%s planner: no feasible leg from %s", self.name, state.uav_enu_m)
                return self._done(state, REASON_NO_LEG)
            log.info("%s planner: proposal %s fails %s; nearest feasible ring candidate instead",
                     self.name, wp, bad or ["min_leg"])
            wp = ring[int(np.argmin(np.linalg.norm(ring - wp, axis=1)))]
            status, objective = f"{status}+fallback", float("nan")
            length = float(np.linalg.norm(wp - state.uav_enu_m))
        horizon = getattr(self, "last_horizon_enu_m", None)
        if horizon is None or not np.allclose(horizon[0], wp):
            horizon = wp[None, :].copy()
        return PlanResult(
            waypoint_enu_m=wp,
            horizon_enu_m=np.asarray(horizon, dtype=float).copy(),
            done=False,
            objective=float(objective),
            status=status,
        )
