"""The spread of each user's estimate that its own data show: a delete-a-block jackknife.

The covariance S⁻¹ of a solve is honest when the model is: ranges independent given the
positions, LoS or NLoS range by range. Where a whole stretch of a user's ranges shares an error
the model lacks (a block of NLoS excess seen from one side of the user, an offset the bias
selection held), the solve absorbs it as a position shift that leaves the residuals white, and
S⁻¹ does not widen. Deleting that stretch does move the estimate. So each user's ranges are split
in time order into G contiguous blocks, and the user is re-estimated without each block in turn
(the UAV track held at the solution, one Gauss–Newton step from θ̂_k, the loss's weights at the
solution: with the block gone the gradient is the block's pull alone):

    H_(−g) = H_k − Σ_(i∈g) w_i J_i J_iᵀ,      δ_g = H_(−g)⁻¹ Σ_(i∈g) ψ_i J_i,     θ_(−g) = θ̂_k + δ_g

    V_J = (G − 1)/G · Σ_g (δ_g − δ̄)(δ_g − δ̄)ᵀ          (δ̄ the mean of the δ_g)

with H_k = Σ_i w_i J_iᵀJ_i (+ the bias prior) user k's information given the track and J_i = ∂e_i/∂θ_k,
ψ_i = ρ'(e_i) (estimator.linearize._range_terms; the gradient of the full problem in θ_k is zero
at θ̂). V_J estimates Var(θ̂_k) without trusting the model's independence (for a right model it
agrees with the model's covariance, up to its own G − 1 degrees of freedom). The covariance a
solve reports is the larger of the two in every direction (jackknife_inflate).
"""

from __future__ import annotations

import numpy as np

from estimator.linearize import range_terms
from estimator.problem import Problem

#: a user is jackknifed only with at least this many ranges per block and parameter
JACKKNIFE_MIN_PER_BLOCK = 4


def jackknife_cov(prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, blocks: int) -> np.ndarray:
    """(K, p, p) delete-a-block jackknife covariance V_J of each user's θ_k (module docstring),
    over `blocks` = G contiguous time blocks of its ranges; NaN for users not active or with fewer
    than G · p · JACKKNIFE_MIN_PER_BLOCK ranges, or whose H_(−g) is singular.

    x: (n, 3) the solution's keyframes [m, ENU]; theta: (K, p) its users; active: (K,) bool."""
    n, k_all, p = x.shape[0], prob.n_users, prob.p
    out = np.full((k_all, p, p), np.nan)
    if blocks < 2 or not np.any(active):
        return out
    mask_kn = prob.mask[:n].T & active[:, None]
    _e, w, _rho, jac, psi, _ = range_terms(prob, x, theta, mask_kn)
    jt = jac[3:]  # (p, K, n) J_θ of each range
    prior = np.zeros(k_all)
    if prob.params.estimate_bias:
        sb = prob.params.bias_prior_sigma_m if prob.bias_sigma_k is None else prob.bias_sigma_k
        prior = np.broadcast_to(1.0 / np.square(sb), (k_all,))
    for k in np.flatnonzero(active):
        rows = np.flatnonzero(mask_kn[k])
        if rows.size < blocks * p * JACKKNIFE_MIN_PER_BLOCK:
            continue
        # the G blocks' sums of w J Jᵀ and ψ J over contiguous runs of the user's ranges
        starts = np.linspace(0, rows.size, blocks + 1).astype(int)[:-1]
        j_k = jt[:, k, rows].T  # (m, p)
        hb = np.add.reduceat((w[k, rows, None, None] * j_k[:, :, None]) * j_k[:, None, :], starts, axis=0)  # (G, p, p)
        gb = np.add.reduceat(psi[k, rows, None] * j_k, starts, axis=0)  # (G, p)
        h_k = hb.sum(axis=0)
        if p > prob.user_dim:
            h_k[-1, -1] += prior[k]
        try:
            delta = np.linalg.solve(h_k[None] - hb, gb[:, :, None])[:, :, 0]  # (G, p)
        except np.linalg.LinAlgError:
            continue
        dev = delta - delta.mean(axis=0)
        out[k] = (blocks - 1) / blocks * (dev.T @ dev)
    return out


def jackknife_inflate(cov: np.ndarray, v_j: np.ndarray) -> np.ndarray:
    """(p, p) the larger of the covariances `cov` and `v_j` in every direction: with cov = L Lᵀ
    and L⁻¹ V_J L⁻ᵀ = U Λ Uᵀ, the covariance L U max(Λ, 1) Uᵀ Lᵀ (cov itself where V_J is
    nowhere larger, or either is not finite and positive definite)."""
    if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(v_j))):
        return cov
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return cov
    li = np.linalg.inv(chol)
    lam, u = np.linalg.eigh(li @ v_j @ li.T)
    if lam[-1] <= 1.0:
        return cov
    m = chol @ u
    out = (m * np.maximum(lam, 1.0)) @ m.T
    return 0.5 * (out + out.T)
