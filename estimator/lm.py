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
from estimator.schur import schur_solve, sym3_cofactors
from uavloc.errors import EstimatorError

_LAM_START = 1e-4
_LAM_MAX = 1e10
#: levenberg_marquardt's `rescale` is offered the linearization once the users' undamped step is
#: below this many of their standard deviations, ||Δθ||_S
RESCALE_STEP_SIGMA = 0.25


def _blocks_pd(hxx: np.ndarray) -> bool:
    """Every 3×3 block of hxx (N, 3, 3) positive definite (its leading minors positive)."""
    a00 = hxx[:, 0, 0]
    m2 = a00 * hxx[:, 1, 1] - hxx[:, 0, 1] * hxx[:, 0, 1]
    det = sym3_cofactors(a00, hxx[:, 0, 1], hxx[:, 0, 2], hxx[:, 1, 1], hxx[:, 1, 2], hxx[:, 2, 2])[-1]
    return bool(np.all(a00 > 0.0) and np.all(m2 > 0.0) and np.all(det > 0.0))


@dataclass
class SolveResult:
    """Where a solve ended: keyframes x (N, 3) [m, ENU], users θ (K, p), the linearization `lin`
    there, the users' information S (K·p, K·p) or None when singular, the iterations taken and
    whether they converged."""

    x: np.ndarray
    theta: np.ndarray
    lin: Linearization
    s: np.ndarray | None
    iterations: int
    converged: bool
    #: the last step was the undamped Gauss–Newton step of `lin` (whose S is `s`): the gradient of
    #: the linear model at (x, θ) is zero
    gn_step: bool = False
    #: lin's normal equations and s are the observed information's (newton steps; lin.w, lin.e and
    #: lin.cost are as always): em_information gives the EM-weighted ones
    observed: bool = False


def levenberg_marquardt(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None,
    max_iterations: int | None = None, step_tol_m: float | None = None, newton: bool = False,
    rescale=None,
) -> SolveResult:
    """Minimise L from (x, Θ); stop when the largest user step component, or the distance still
    to go estimated from the contraction of the last two steps, is below params.step_tol_m (or
    step_tol_m) — or the users' step still to go is below params.step_tol_sigma of their
    standard deviations, ||Δθ||_S = √(Δθᵀ S Δθ) — and the same for the keyframes (absolute
    only) with the larger of step_tol_m and params.step_tol_uav_m.

    The returned S (undamped Schur complement) belongs to the last linearization point, which
    differs from the returned estimate by the last step (below the tolerances above).

    newton (the "nlos" loss only): the steps use the observed information ψ'(e) of each range
    (robust.nlos_curvature, unfloored: Newton's method) instead of its EM weight γ, where the
    keyframe blocks and S are positive definite (else that step is the EM-weighted one). The
    EM-weighted iteration converges linearly (each step ~0.2 of the last on the benchmark's
    problems, the LoS/NLoS mixture's tail ranges at π on its floor), Newton's quadratically;
    the optimum is the same (the gradient is ψ J either way). The returned linearization's
    weights w are the EM ones; its normal equations and S are the observed information's where
    newton steps were taken (SolveResult.observed; em_information gives the EM-weighted ones).

    rescale: None, or rescale(lin) -> bool, called once, at the first undamped step that does not
    end the solve and is below RESCALE_STEP_SIGMA of the users' standard deviations, with that
    step's linearization; True when it changed the problem's model (estimator.solve's per-user
    noise scales, in prob): the step is then taken without the cost test (the costs of two models
    do not compare; the step is a small Gauss–Newton one) and the solve goes on under the new model.
    """
    params = prob.params
    max_it = params.max_iterations if max_iterations is None else max_iterations
    tol = params.step_tol_m if step_tol_m is None else step_tol_m
    sig_tol = float(params.step_tol_sigma)
    newton = newton and params.loss == "nlos"
    obs = -np.inf if newton else None
    lin = linearize(prob, x, theta, active, prior, observed=obs)
    lam = 0.0
    s_final = None
    converged = gn_step = False
    prev: tuple[float, float] | None = None  # (user, keyframe) sizes of the last undamped step
    it = 0
    while it < max_it:
        it += 1
        try:
            if newton and not _blocks_pd(lin.hxx):
                raise np.linalg.LinAlgError("a keyframe block of the observed information is not positive definite")
            dx, du, s = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, lam)
        except (np.linalg.LinAlgError, EstimatorError):
            if newton:
                # the observed information is not positive definite here: the EM-weighted step
                newton, obs = False, None
                lin = linearize(prob, x, theta, active, prior)
                it -= 1
                continue
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
        if rescale is not None and su_sigma < RESCALE_STEP_SIGMA and lam == 0.0:
            changed, rescale = rescale(lin), None
            if changed:
                x, theta, prev = x_t, th_t, None
                lin = linearize(prob, x, theta, active, prior, observed=obs)
                continue
        lin_t = linearize(prob, x_t, th_t, active, prior, observed=obs)
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
    return SolveResult(x, theta, lin, s_final, it, converged, gn_step, observed=newton)


def em_information(prob: Problem, res: SolveResult, active: np.ndarray, prior: Prior | None = None) -> SolveResult:
    """res with the EM-weighted linearization and S (at its estimate) where its normal equations
    are the observed information's (levenberg_marquardt's newton steps); res itself otherwise."""
    if not res.observed:
        return res
    lin = linearize(prob, res.x, res.theta, active, prior)
    try:
        _, _, s = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, 0.0)
    except (np.linalg.LinAlgError, EstimatorError):
        s = None
    return SolveResult(res.x, res.theta, lin, s, res.iterations, res.converged)
