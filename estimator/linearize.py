"""Linearization of the SLAM cost (docs/design.md §5): the IRLS-weighted normal equations at a point.

Every factor's vectorised error and Jacobian enters here once: the range factor (range_terms on
estimator.factors.range_residuals / range_alpha / range_jacobian, the one source of the range
model that initialization and the planner's prediction also call; RangeFactor one at a time),
the GPS factors (estimator.gps), the bias priors, the relative-motion factors and the
marginalization prior. The batch solver, the online window and its marginalization, and the CRLB
(estimator.crlb) all call it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from estimator.factors import range_alpha, range_jacobian, range_residuals
from estimator.gps import gps_chain_terms
from estimator.problem import (
    Problem,
    users_from_theta,
)
from estimator.robust import loss_psi_weight, nlos_terms_curvature

#: flat indices of a 3×3's lower triangle (i > j) and of the upper entries they mirror
_SYM3_LOWER = np.array([3, 6, 7])
_SYM3_UPPER = np.array([1, 2, 5])


@functools.cache
def _upper_pairs(p: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of the strict upper triangle of a p×p matrix (np.triu_indices costs more
    than the products it indexes)."""
    return np.triu_indices(p, 1)


@dataclass
class Prior:
    """Gaussian prior from marginalized keyframes over z = [x_first (3, if has_x), Θ.ravel() (K·p)].

    L_prior(z) = cᵀ(z − z0) + ½ (z − z0)ᵀ Λ (z − z0).
    """

    has_x: bool
    z0: np.ndarray
    info: np.ndarray
    grad: np.ndarray


@dataclass
class Linearization:
    """IRLS-weighted normal equations at one point (shapes as in estimator.schur.schur_solve)."""

    cost: float
    hxx: np.ndarray  # (N, 3, 3)
    off: np.ndarray | None  # (N − 1,)
    hxu: np.ndarray  # (N, 3, K·p)
    huu: np.ndarray  # (K·p, K·p)
    gx: np.ndarray  # (N, 3)
    gu: np.ndarray  # (K·p,)
    e: np.ndarray  # (K, N) whitened range residuals, 0 where none
    w: np.ndarray  # (K, N) IRLS (EM) weights, 0 where none (also when H holds the observed information)
    rho_k: np.ndarray | None = None  # (K,) Σ_n ρ(e) of each user's ranges


def problem_residuals(prob: Problem, x: np.ndarray, theta: np.ndarray, mask_kn: np.ndarray) -> tuple:
    """Range residuals, user-major: (diff (3, K, n) = x_i − u_k, d (K, n), σ (K, n) or scalar,
    r = r̂ − d − b (K, n), e = r/σ (K, n), full), r and e zero where mask_kn (K, n) is False;
    full: mask_kn is all True. Shapes as in `range_terms`."""
    n = x.shape[0]
    users = users_from_theta(theta, prob.user_up_m, prob.user_dim)
    # diff_i = x_i − u_i, (3, K, n)
    diff = np.ascontiguousarray(x.T)[:, None, :] - users.T[:, :, None]
    # every user ranged from every keyframe (the common case): no masking passes
    full = bool(mask_kn.all())
    # b_k g_nk: the bias, or a tracked clock sawtooth's amplitude times its shape
    bias = 0.0
    if prob.params.estimate_bias:
        bias = theta[:, -1:] if prob.bias_gain is None else theta[:, -1:] * prob.bias_gain[:n].T
    # e = (r̂ − d − b) / σ_k(r̂), σ_k = s_k σ(r̂) (a scalar or (K, 1) when it does not depend on r̂)
    d, sig, r, e = range_residuals(diff, prob.range_m[:n].T, bias, prob.noise,
                                   None if prob.noise_scale_k is None else prob.noise_scale_k[:, None],
                                   mask=None if full else mask_kn)
    return diff, d, sig, r, e, full


def problem_nlos_args(prob: Problem, sig: np.ndarray | float) -> tuple:
    """(π (K, 1) or scalar, whitened NLoS mean m) of the "nlos" loss for ranges of σ `sig`."""
    pi = prob.params.nlos_prob if prob.nlos_prob_k is None else prob.nlos_prob_k[:, None]
    return pi, prob.params.nlos_mean_m / sig


def range_terms(
    prob: Problem, x: np.ndarray, theta: np.ndarray, mask_kn: np.ndarray, observed: float | None = None,
) -> tuple[np.ndarray, ...]:
    """Whitened range residuals and Jacobians (see estimator.factors.RangeFactor), user-major.

    x: (n, 3); theta: (K, p); mask_kn: (K, n) ranges to use; ranges are prob.range_m[:n].
    Arrays are laid out (K, n) so that numpy's inner loops run over keyframes (long), not over
    3 coordinates. Returns e, w, rho (K, n), J (3 + p, K, n) = [∂e/∂x; ∂e/∂θ_k], ψ = ρ'(e) and
    the EM/IRLS weight (K, n) (w itself unless `observed` made w the observed information), zero
    where mask_kn is False.
    """
    params = prob.params
    diff, d, sig, _r, e, full = problem_residuals(prob, x, theta, mask_kn)
    nl = problem_nlos_args(prob, sig) if params.loss == "nlos" else None
    if observed is not None and nl is not None:
        # the observed information ψ'(e) instead of the EM weight γ (robust.nlos_curvature),
        # floored at observed (a float) when the unfloored one is not positive definite
        rho, psi, w_em, w = nlos_terms_curvature(e, *nl)
        if observed > -np.inf:
            w = np.maximum(w, observed)
    else:
        rho, psi, w = loss_psi_weight(e, params.loss, params.loss_scale, nl)
        w_em = w
    if not full:
        w = w * mask_kn
        w_em = w if w_em is w else w_em * mask_kn
        psi = psi * mask_kn
        rho = rho * mask_kn
    jac = range_jac(prob, diff, d, sig, None if full else mask_kn)
    return e, w, rho, jac, psi, w_em


def range_jac(prob: Problem, diff: np.ndarray, d: np.ndarray, sig: np.ndarray | float,
               mask_kn: np.ndarray | None) -> np.ndarray:
    """(3 + p, K, n) range Jacobians [∂e/∂x; ∂e/∂θ_k] at problem_residuals' diff, d, σ (mask_kn None: every
    range), zero where mask_kn is False:  α = 1/σ;  ∂e/∂x = −α û, ∂e/∂u = α û, ∂e/∂b = −g/σ
    (estimator.factors)."""
    n = d.shape[1]
    return range_jacobian(diff, d, range_alpha(sig, mask_kn), sig, prob.user_dim, prob.params.estimate_bias,
                          None if prob.bias_gain is None else prob.bias_gain[:n].T, mask_kn)


def linearize(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None,
    observed: float | None = None,
) -> Linearization:
    """IRLS-weighted normal equations H Δ = g (g = −∇L) at (x (N, 3), Θ (K, p)).

    Per range, with J = [∂e/∂x | ∂e/∂θ_k] (1 × (3 + p)):
        H_nn = I/σ_gps² + Σ_k w J_xᵀ J_x,   H_(n,k) = w J_xᵀ J_θ,   H_kk = Σ_n w J_θᵀ J_θ
        g_n = −(x_n − x̂_n)/σ_gps² − Σ_k ψ J_x,   g_k = −Σ_n ψ J_θ      (+ bias, motion, prior)
    with ψ = ρ'(e) (= w e except for the "nlos" loss, estimator.robust).
    Users with active[k] False are held fixed (identity block, zero gradient).
    observed: None for the IRLS weight w; else (the "nlos" loss only) w = max(ψ'(e), observed),
    the observed information (robust.nlos_curvature) for the covariance, −inf for no floor.
    """
    params, noise = prob.params, prob.noise
    n, k_all = prob.range_m.shape
    p = prob.p
    mask_kn = prob.mask[:n].T & active[:, None]
    e, w, rho, jac, psi, w_em = range_terms(prob, x, theta, mask_kn, observed)
    linked = prob.gps_linked
    if linked:
        # Gauss–Markov GPS factors (estimator.gps): diagonal, off-diagonal and gradient terms
        gt = gps_chain_terms(x, prob.gps_enu_m[:n], prob.gps_phi(), noise.sigma_gps_m, prob.gps_first)
        inv_g2 = 0.0
        dgps = np.zeros_like(x)
        cost = gt.cost + float(rho.sum())
    else:
        inv_g2 = 1.0 / noise.sigma_gps_m**2
        dgps = x - prob.gps_enu_m
        cost = 0.5 * inv_g2 * float(np.vdot(dgps, dgps)) + float(rho.sum())
    # with w J_x (3, K, n) and J_θ (p, K, n) = [−J_x[:d]; (J_b)], each block is one product:
    #   H_nn = Σ_k w J_x J_xᵀ (+ GPS),  H_(n,k) = w J_x J_θᵀ,  H_kk = Σ_n w J_θ J_θᵀ
    jx, jt = jac[:3], jac[3:]
    jw = jx * w
    hxx = np.einsum("ikn,jkn->nij", jw, jx)
    # exactly symmetric (the two triangles' products round differently)
    hxx.reshape(n, 9)[:, _SYM3_LOWER] = hxx.reshape(n, 9)[:, _SYM3_UPPER]
    hxu4 = np.empty((n, 3, k_all, p))
    for i in range(3):
        for j in range(p):
            # one (K, n) product each, written through a strided view (a broadcast product over
            # all four axes would run its inner loop over the p columns: 3× slower)
            np.multiply(jw[i], jt[j], out=hxu4[:, i, :, j].T)
    hxu = hxu4.reshape(n, 3, k_all * p)
    huu_blocks = np.einsum("akn,bkn->kab", jt * w, jt)
    iu, ju = _upper_pairs(p)
    huu_blocks[:, ju, iu] = huu_blocks[:, iu, ju]
    # g_n = −(x_n − x̂_n)/σ_gps² − Σ_k ψ J_x,  g_k = −Σ_n ψ J_θ
    gx = -dgps * inv_g2 - np.einsum("ikn,kn->ni", jx, psi)
    gu = -np.einsum("akn,kn->ka", jt, psi)
    off = None
    if linked:
        hxx.reshape(n, 9)[:, ::4] += gt.diag[:, None]
        gx -= gt.grad
        off = gt.off.copy()
    else:
        hxx.reshape(n, 9)[:, ::4] += inv_g2
    if params.estimate_bias:
        # bias prior e_k = (b_k − μ_b,k) / σ_b,k (the held prior where the bias was selected off)
        sb = params.bias_prior_sigma_m if prob.bias_sigma_k is None else prob.bias_sigma_k
        inv_b2 = 1.0 / np.square(sb)  # scalar or (K,)
        bias = theta[:, -1] if prob.bias_mean_k is None else theta[:, -1] - prob.bias_mean_k
        huu_blocks[:, -1, -1] += inv_b2
        gu[:, -1] -= bias * inv_b2
        bb = inv_b2 * bias * bias
        cost += 0.5 * float(bb.sum() if active.all() else bb[active].sum())
    if not active.all():
        inactive = ~active
        huu_blocks[inactive] = np.eye(p)
        gu[inactive] = 0.0
    huu = np.zeros((k_all, p, k_all, p))
    ks = np.arange(k_all)
    huu[ks, :, ks, :] = huu_blocks  # block diagonal
    huu = huu.reshape(k_all * p, k_all * p)
    gu = gu.ravel()
    if prob.use_motion:
        # W_n = 1/σ_m,n² for linked pairs, 0 elsewhere (σ per keyframe: Problem.odom_weight)
        add = prob.odom_weight()[1:n]
        # e_m = (x_n − x_(n−1) − ô_n)/σ_m,n; cost ½ Σ W_n ||δ_n||², δ_n = x_n − x_(n−1) − ô_n
        em = (x[1:] - x[:-1] - prob.odom_enu_m[1:n]) * (add > 0)[:, None]
        wem = em * add[:, None]
        cost += 0.5 * float(np.vdot(wem, em))
        hxx.reshape(n, 9)[1:, ::4] += add[:, None]
        hxx.reshape(n, 9)[:-1, ::4] += add[:, None]
        off = -add if off is None else off - add
        gx[1:] -= wem
        gx[:-1] += wem
    if prior is not None:
        z = theta.ravel()
        if prior.has_x:
            z = np.concatenate([x[0], z])
        dz = z - prior.z0
        grad = prior.grad + prior.info @ dz
        cost += float(prior.grad @ dz + 0.5 * dz @ prior.info @ dz)
        if prior.has_x:
            hxx[0] += prior.info[:3, :3]
            hxu[0] += prior.info[:3, 3:]
            gx[0] -= grad[:3]
            huu += prior.info[3:, 3:]
            gu -= grad[3:]
        else:
            huu += prior.info
            gu -= grad
    return Linearization(cost, hxx, off, hxu, huu, gx, gu, e, w_em, rho.sum(axis=1))
