"""Users' marginal covariances from the Schur complement S, and the Estimate of a solve."""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dpotrf as _dpotrf
from scipy.linalg.lapack import dpotri as _dpotri

from estimator.jackknife import jackknife_cov, jackknife_inflate
from estimator.lm import (
    SolveResult,
)
from estimator.nlos_shift import nlos_bearing_logit, nlos_shift_cov, nlos_shift_m
from estimator.problem import (
    Problem,
    users_from_theta,
)
from estimator.solve import free_biases
from estimator.types import Estimate, ModelState


def user_covariances(
    s: np.ndarray | None, active: np.ndarray, k_all: int, p: int, d: int, cov_s: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """From S (K·p, K·p): per-user position covariance (K, d, d), position information (K·d, K·d)
    with any bias marginalized out, and the full joint covariance of the active users' θ.
    cov_s: S⁻¹ when already at hand (every user active), else from S's Cholesky factor.

    With biases the position information is the Schur complement of S over them (the inverse of
    the covariance's position block): S_pp − S_pb S_bb⁻¹ S_bp."""
    cov = np.full((k_all, d, d), np.inf)
    info = np.zeros((k_all * d, k_all * d))
    if s is None or not np.any(active):
        return cov, info, None
    all_active = bool(active.all())
    s_a = s if all_active else s[np.ix_(np.repeat(active, p), np.repeat(active, p))]
    # S = L Lᵀ (positive definite, else no covariance), S⁻¹ from L
    c, bad = _dpotrf(s_a, lower=1, clean=1)
    if bad != 0:
        return cov, info, None
    if cov_s is not None and all_active:
        cov_a = cov_s
    else:
        cov_a, bad = _dpotri(c, lower=1)
        if bad != 0:
            return cov, info, None
        cov_a = np.tril(cov_a)
        cov_a = cov_a + np.tril(cov_a, -1).T
    cov_a = 0.5 * (cov_a + cov_a.T)
    na = s_a.shape[0] // p
    cov_a4 = cov_a.reshape(na, p, na, p)
    ka_ = np.arange(na)
    blocks = cov_a4[ka_, :d, ka_, :d]  # the diagonal blocks, (na, d, d)
    if p == d:
        info_pos = s_a
    else:
        s4 = s_a.reshape(na, p, na, p)
        s_pp = s4[:, :d, :, :d].reshape(na * d, na * d)
        s_pb = s4[:, :d, :, d:].reshape(na * d, na * (p - d))
        s_bb = s4[:, d:, :, d:].reshape(na * (p - d), na * (p - d))
        info_pos = s_pp - s_pb @ np.linalg.solve(s_bb, s_pb.T)
        info_pos = 0.5 * (info_pos + info_pos.T)
    if all_active:
        cov[:] = blocks
        info[:] = info_pos
    else:
        ka = np.flatnonzero(active)
        cov[ka] = blocks
        ip = (ka[:, None] * d + np.arange(d)[None, :]).ravel()
        info[np.ix_(ip, ip)] = info_pos
    return cov, info, cov_a


def _widen(
    prob: Problem, res: SolveResult, active: np.ndarray, users: np.ndarray, cov: np.ndarray, cov_joint: np.ndarray,
) -> np.ndarray | None:
    """Widen, in place, each active user's block of cov_joint (K_a·p, K_a·p) and its position
    covariance cov (K, d, d): the jackknife first (the larger of the two in every direction),
    then the NLoS shift added (estimate_of; users: (K, 3) the solution's users [m, ENU]).
    Returns the (K,) shifts [m] and the (K, 3) NLoS-by-bearing profiles of the users with one
    (estimator.nlos_shift.nlos_bearing_logit), (None, None) when not asked for."""
    params = prob.params
    p, d = prob.p, prob.user_dim
    v_j = None
    if params.jackknife_blocks:
        v_j = jackknife_cov(prob, res.x, res.theta, active, int(params.jackknife_blocks))
    shift = nlos_shift_m(prob, res.x, users, active) if params.nlos_shift else None
    logit = None if shift is None else nlos_bearing_logit(prob, res.x, users, res.lin.w, shift)
    for j, k in enumerate(np.flatnonzero(active)):
        sl = slice(j * p, (j + 1) * p)
        model = cov_joint[sl, sl]
        block = model if v_j is None else jackknife_inflate(model, v_j[k])
        if shift is not None and shift[k] > 0.0:
            block = block + nlos_shift_cov(float(shift[k]), p)
        if block is not model:
            cov_joint[sl, sl] = block
            cov[k] = block[:d, :d]
    return shift, logit


def estimate_of(
    prob: Problem, res: SolveResult, active: np.ndarray, mirrors: list, n_ranges: np.ndarray,
    clock: list | None = None, clock_triggered: np.ndarray | None = None, warm_started: bool = False,
    widen: bool = False,
) -> Estimate:
    """The Estimate of solution `res` (its users, covariances and model state).

    mirrors: (K,) mirror test per user (None: not tested); n_ranges: (K,) ranges per user;
    clock, clock_triggered, warm_started: the batch solve's clock tracking and warm start
    (ModelState); widen: a batch solve's answer, whose users' covariances (cov_users_m2 and the
    diagonal blocks of cov_theta_joint) are widened by what the model cannot see: to their
    delete-a-block jackknife where params.jackknife_blocks asks (estimator.jackknife), then by
    the shift of a one-sided NLoS excess where params.nlos_shift asks (estimator.nlos_shift);
    info_users stays the model's S."""
    k_all, p, d = prob.n_users, prob.p, prob.user_dim
    users = users_from_theta(res.theta, prob.user_up_m, d)
    users[~active] = np.nan
    cov, info, cov_joint = user_covariances(res.s, active, k_all, p, d)
    shift = logit = None
    if widen and cov_joint is not None:
        shift, logit = _widen(prob, res, active, users, cov, cov_joint)
    bias = None
    bias_on = bias_held = None
    if prob.params.estimate_bias:
        bias = np.where(active, res.theta[:, -1], np.nan)
        bias_on = free_biases(prob.params, prob.bias_sigma_k)
        if bias_on is None:
            bias_on = np.ones(k_all, dtype=bool)
        bias_held = np.zeros(k_all) if prob.bias_mean_k is None else np.where(bias_on, 0.0, prob.bias_mean_k)
    ambiguous = np.zeros(k_all, dtype=bool)
    mirror = np.full((k_all, 3), np.nan)
    for k, mt in enumerate(mirrors):
        if mt is not None and mt.ambiguous:
            ambiguous[k] = True
            mirror[k] = users_from_theta(mt.mirror_theta[None, :], prob.user_up_m[k : k + 1], d)[0]
    state = ModelState(
        active=active.copy(), cov_theta_joint=cov_joint,
        noise_scale=np.ones(k_all) if prob.noise_scale_k is None else prob.noise_scale_k.copy(),
        nlos_prob_k=None if prob.nlos_prob_k is None else prob.nlos_prob_k.copy(),
        bias_on=bias_on, bias_held_m=bias_held, clock=None if clock is None else tuple(clock),
        clock_triggered=None if clock_triggered is None else np.asarray(clock_triggered, dtype=bool).copy(),
        nlos_shift_m=shift, nlos_bearing_logit=logit, warm_started=warm_started,
    )
    return Estimate(
        users_enu_m=users, cov_users_m2=cov, info_users=info, bias_m=bias, uav_enu_m=res.x.copy(),
        ambiguous=ambiguous, mirror_enu_m=mirror, n_ranges=n_ranges.copy(), cost=res.lin.cost,
        iterations=res.iterations, converged=res.converged, state=state,
    )
