"""The stopping rule (docs/design.md §6): every user located well enough, or the budget spent."""

from __future__ import annotations

import numpy as np

from estimator.types import Estimate
from planner.types import REASON_BUDGET, REASON_TARGET, PlanningConstraints, PlanningState


def budget_left_m(constraints: PlanningConstraints, state: PlanningState) -> float:
    """Survey metres still allowed: min(budget − flown, energy − return_factor·|x − home|) [m]."""
    survey = constraints.budget_m - state.flown_m
    # energy to keep for the way home, measured from where the UAV is now
    home = constraints.return_factor * float(np.linalg.norm(state.uav_enu_m - constraints.home_enu_m))
    return float(min(survey, state.energy_remaining_m - home))


def targets_reached(estimate: Estimate | None, target_radius_m: float) -> bool:
    """True when every user's 95 % error-ellipse semi-major axis r95 ≤ target_radius_m, apart
    from the NLoS shift no survey shrinks.

    r95_k = sqrt(χ²₂(0.95) · λ_max(Σ_k,en − ½ |δ_k|² I)) from `Estimate.survey_bound_95_m()`
    (δ_k the shift of a one-sided NLoS excess, estimator.nlos_shift: a user behind a building
    keeps it however long the UAV flies, so waiting for it would spend the budget for nothing; the
    reported bound includes it); an uninitialised user (inf) or an unresolved mirror ambiguity
    keeps the survey going.
    """
    if estimate is None or estimate.n_users == 0:
        return False
    bound = estimate.survey_bound_95_m()
    ambiguous = np.asarray(estimate.ambiguous, dtype=bool)
    return bool(np.all(bound <= target_radius_m) and not np.any(ambiguous))


def stop_reason(constraints: PlanningConstraints, state: PlanningState) -> str | None:
    """REASON_TARGET, REASON_BUDGET, or None to keep surveying.

    Budget spent: less than `min_leg_m` of survey metres left (see :func:`budget_left_m`).
    """
    if targets_reached(state.estimate, constraints.target_radius_m):
        return REASON_TARGET
    if budget_left_m(constraints, state) < constraints.min_leg_m:
        return REASON_BUDGET
    return None
