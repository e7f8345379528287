"""The stopping rule (docs/design.md §6): every user located well enough, the bounds at their
floor, or the budget spent."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estimator.types import Estimate
from planner.types import REASON_BUDGET, REASON_FLOOR, REASON_TARGET, PlanningConstraints, PlanningState

#: the floor watch's window: the bounds must have shrunk over the last max(FLOOR_WINDOW_MIN_M,
#: FLOOR_WINDOW_SHARE · budget) metres flown [m]
FLOOR_WINDOW_MIN_M = 200.0
FLOOR_WINDOW_SHARE = 0.1
#: ... by at least this share of their value at the window's start, or the survey is at its floor
FLOOR_MIN_SHRINK = 0.05
#: ... and only when the estimate judged holds at least this share of the keyframes the window's
#: metres make (window / Δ): a lagging estimator (a busy machine) shows no shrinking because it has
#: not solved the new ranges yet, which is no floor
FLOOR_MIN_NEW_KEYFRAME_SHARE = 0.5
#: a user whose bound is within this factor of the GPS floor (PlanningConstraints.floor_m) has
#: nothing left that a flight removes: r95² ≤ 1.15² r_floor² leaves at most 0.57 r_floor of the
#: bound to the ranges
FLOOR_MARGIN = 1.15


def budget_left_m(constraints: PlanningConstraints, state: PlanningState) -> float:
    """Survey metres still allowed: min(budget − flown, energy − return_factor·|x − home|) [m]."""
    survey = constraints.budget_m - state.flown_m
    # energy to keep for the way home, measured from where the UAV is now
    home = constraints.return_factor * float(np.linalg.norm(state.uav_enu_m - constraints.home_enu_m))
    return float(min(survey, state.energy_remaining_m - home))


def reported_bound_95_m(estimate: Estimate) -> np.ndarray:
    """(K,) the bound the mission prints for each user [m] (Estimate.error_bound_95_m: r95 of its
    whole east-north covariance, the one-sided NLoS shift included); inf where not located."""
    return estimate.error_bound_95_m()


def targets_reached(estimate: Estimate | None, target_radius_m: float) -> bool:
    """True when every user's printed 95 % bound r95 ≤ target_radius_m and no user is ambiguous.

    r95_k = sqrt(χ²₂(0.95) · λ_max(Σ_k,en)), Σ_k the covariance the mission reports, widened by
    the shift ½ |δ_k|² I of a one-sided NLoS excess (estimator.nlos_shift): that shift shrinks as
    the user is seen from its line-of-sight side, which the planner's objective asks for; an
    uninitialised user (inf) or an unresolved mirror ambiguity keeps the survey going.
    """
    if estimate is None or estimate.n_users == 0:
        return False
    bound = reported_bound_95_m(estimate)
    ambiguous = np.asarray(estimate.ambiguous, dtype=bool)
    return bool(np.all(bound <= target_radius_m) and not np.any(ambiguous))


@dataclass
class FloorWatch:
    """Whether a survey's bounds stopped shrinking above the target (REASON_FLOOR). Fed at each leg
    end with the metres flown and the printed bounds (K,) [m]; the survey is at its floor when
    every user still above the target is at its own, that is when its bound is

    - within FLOOR_MARGIN of the GPS floor r_floor (what no flight removes,
      PlanningConstraints.floor_m): r95_k ≤ FLOOR_MARGIN · r_floor; or
    - stalled: it did not shrink by FLOOR_MIN_SHRINK over the last `window_m` metres flown,
      r95_k(now) > (1 − FLOOR_MIN_SHRINK) · r95_k(now − window), and its NLoS shift |δ_k| did not
      grow by FLOOR_MIN_SHRINK · r95_k(now − window) (an NLoS excess found mid-survey widens a
      bound, and flying to the user's clear side may undo it).

    A user is judged stalled only when the estimate now holds at least
    FLOOR_MIN_NEW_KEYFRAME_SHARE · window / Δ keyframes more than the one then (when both say how
    many they hold, Estimate.keyframes_used: a lagging estimator is not a floor), and, when the
    ranges per user are known (Estimate.n_ranges), only if that many of the new ones are its own: a
    user the survey was not measuring (its vehicle busy with users far from it, or its cell out
    of reach) has not shown that more flight leaves it where it is. The two ways mix
    across users: with a target below the GPS floor, users near the floor are done and a user whose
    bound stalled higher (behind a building) ends the survey as well as it would alone.

    An ambiguous or unlocated user (inf) is never at its floor.
    """

    target_radius_m: float
    floor_m: float
    window_m: float
    delta_m: float = 0.0
    history: list[tuple[float, int, np.ndarray, np.ndarray | None, np.ndarray | None]] = field(default_factory=list)

    @classmethod
    def of(cls, constraints: PlanningConstraints) -> FloorWatch:
        window = max(FLOOR_WINDOW_MIN_M, FLOOR_WINDOW_SHARE * constraints.budget_m)
        return cls(constraints.target_radius_m, constraints.floor_m, window, constraints.delta_m)

    def update(self, flown_m: float, bound_95_m: np.ndarray, ambiguous: np.ndarray | None = None,
               keyframes_used: int = 0, nlos_shift_m: np.ndarray | None = None,
               n_ranges: np.ndarray | None = None) -> bool:
        """Record one leg end; True when the survey is at its floor (class docstring). keyframes_used:
        the keyframes the estimate holds (0: not said); nlos_shift_m: (K,) each user's NLoS shift
        |δ_k| [m] (ModelState.nlos_shift_m), None when not estimated; n_ranges: (K,) the ranges each
        user's estimate holds (Estimate.n_ranges), None: not said."""
        bound = np.asarray(bound_95_m, dtype=float).copy()
        if ambiguous is not None:
            bound[np.asarray(ambiguous, dtype=bool)] = np.inf
        shift_m = None if nlos_shift_m is None else np.nan_to_num(np.asarray(nlos_shift_m, dtype=float))
        if self.history and len(self.history[-1][2]) != len(bound):
            self.history.clear()
        counts = None if n_ranges is None else np.asarray(n_ranges, dtype=float).copy()
        self.history.append((float(flown_m), int(keyframes_used), bound, shift_m, counts))
        above = bound > self.target_radius_m
        if not np.any(above) or not np.all(np.isfinite(bound[above])):
            return False
        near_floor = bound <= FLOOR_MARGIN * self.floor_m if self.floor_m > 0.0 else np.zeros_like(above)
        if np.all(near_floor[above]):
            return True
        # the newest record at least `window_m` back
        past = [(kf, b, sh, n) for m, kf, b, sh, n in self.history if m <= flown_m - self.window_m]
        if not past:
            return False
        kf_before, before, shift_before, counts_before = past[-1]
        if (keyframes_used > 0 and kf_before > 0 and self.delta_m > 0.0
                and keyframes_used - kf_before < FLOOR_MIN_NEW_KEYFRAME_SHARE * self.window_m / self.delta_m):
            return False
        stalled = bound > (1.0 - FLOOR_MIN_SHRINK) * before
        if shift_m is not None and shift_before is not None:
            # an NLoS excess found in the window: the planner may yet fly to where it shrinks
            stalled &= ~(shift_m - shift_before > FLOOR_MIN_SHRINK * before)
        if counts is not None and counts_before is not None and self.delta_m > 0.0:
            stalled &= counts - counts_before >= FLOOR_MIN_NEW_KEYFRAME_SHARE * self.window_m / self.delta_m
        return bool(np.all((near_floor | stalled)[above]))


def stop_reason(constraints: PlanningConstraints, state: PlanningState,
                floor: FloorWatch | None = None) -> str | None:
    """REASON_TARGET, REASON_FLOOR (with a `floor` watch, fed here), REASON_BUDGET, or None to
    keep surveying.

    Budget spent: less than `min_leg_m` of survey metres left (see :func:`budget_left_m`).
    """
    est = state.estimate
    if targets_reached(est, constraints.target_radius_m):
        return REASON_TARGET
    if (floor is not None and est is not None and est.n_users
            and floor.update(state.flown_m, reported_bound_95_m(est), est.ambiguous, est.keyframes_used,
                             None if est.state is None else est.state.nlos_shift_m, est.n_ranges)):
        return REASON_FLOOR
    if budget_left_m(constraints, state) < constraints.min_leg_m:
        return REASON_BUDGET
    return None
