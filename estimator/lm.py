"""Levenberg–Marquardt on the normal equations of estimator.linearize, solved by the Schur
complement over keyframes (estimator.schur)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator.linearize import (
    Linearization,
    Prior,
    linearize,
)
from estimator.problem import (
    Problem,
)
from estimator.schur import schur_solve
from uavloc.errors import EstimatorError

_LAM_START = 1e-4
_LAM_MAX = 1e10


@dataclass
class _Result:
    x: np.ndarray
    theta: np.ndarray
    lin: Linearization
    s: np.ndarray | None
    iterations: int
    converged: bool
    #: the last step was the undamped Gauss–Newton step of `lin` (whose S is `s`): the gradient of
    #: the linear model at (x, θ) is zero
    gn_step: bool = False


def levenberg_marquardt(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None,
    max_iterations: int | None = None, step_tol_m: float | None = None,
) -> _Result:
    """Minimise L from (x, Θ); stop when the largest user step component, or the distance still
    to go estimated from the contraction of the last two steps, is below params.step_tol_m (or
    step_tol_m) — or the users' step still to go is below params.step_tol_sigma of their
    standard deviations, ||Δθ||_S = √(Δθᵀ S Δθ) — and the same for the keyframes (absolute
    only) with the larger of step_tol_m and params.step_tol_uav_m.

    The returned S (undamped Schur complement) belongs to the last linearization point, which
    differs from the returned estimate by the last step (below the tolerances above).
    """
    params = prob.params
    max_it = params.max_iterations if max_iterations is None else max_iterations
    tol = params.step_tol_m if step_tol_m is None else step_tol_m
    sig_tol = float(params.step_tol_sigma)
    lin = linearize(prob, x, theta, active, prior)
    lam = 0.0
    s_final = None
    converged = gn_step = False
    prev: tuple[float, float] | None = None  # (user, keyframe) sizes of the last undamped step
    it = 0
    while it < max_it:
        it += 1
        try:
            dx, du, s = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, lam)
        except (np.linalg.LinAlgError, EstimatorError):
            lam = max(_LAM_START, 10.0 * lam)
            if lam > _LAM_MAX:
                break
            continue
        # the users' step in their standard deviations, ||Δθ||_S (S undamped only at λ = 0)
        su_sigma = math.sqrt(max(float(du @ s @ du), 0.0)) if (sig_tol > 0.0 and lam == 0.0) else math.inf
        du = du.reshape(theta.shape)
        su, sx = float(np.max(np.abs(du))), float(np.max(np.abs(dx)))
        # distance still to go after this step: Gauss–Newton on these problems converges
        # linearly, each step r times the previous one (r the ratio of the last two undamped
        # steps), so the steps after this one add up to step·r/(1 − r)
        left_u, left_x, left_sigma = su, sx, su_sigma
        if prev is not None and lam == 0.0:
            ru, rx = su / max(prev[0], 1e-300), sx / max(prev[1], 1e-300)
            if ru < 0.5:
                left_u = su * ru / (1.0 - ru)
                left_sigma = su_sigma * ru / (1.0 - ru)
            if rx < 0.5:
                left_x = sx * rx / (1.0 - rx)
        # users to tol (or to sig_tol of their σ); keyframes (σ_gps ~ 1 m) to the looser
        # params.step_tol_uav_m
        users_done = min(su, left_u) < tol or min(su_sigma, left_sigma) < sig_tol
        if users_done and min(sx, left_x) < max(tol, params.step_tol_uav_m):
            x = x + dx
            theta = theta + du
            s_final = s if lam == 0.0 else None
            converged, gn_step = True, lam == 0.0
            break
        x_t, th_t = x + dx, theta + du
        lin_t = linearize(prob, x_t, th_t, active, prior)
        if lin_t.cost <= lin.cost + 1e-12 * abs(lin.cost):
            x, theta, lin = x_t, th_t, lin_t
            prev = (su, sx) if lam == 0.0 else None
            lam = 0.0 if lam <= _LAM_START else lam / 10.0
        else:
            prev = None
            lam = max(_LAM_START, 10.0 * lam)
            if lam > _LAM_MAX:
                break
    if s_final is None:
        try:
            _, _, s_final = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, 0.0)
        except (np.linalg.LinAlgError, EstimatorError):
            s_final = None
    return _Result(x, theta, lin, s_final, it, converged, gn_step)
