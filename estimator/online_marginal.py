"""Marginalization of the online estimator's oldest keyframes into its Gaussian prior
(estimator.online): one keyframe, a block of unlinked ones, or a Gauss–Markov chain. Functions of
the estimator's state (estimator.online_state.OnlineState), which they update."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from estimator.gps import gps_chain_terms
from estimator.linearize import (
    Prior,
    linearize,
    range_terms,
)
from estimator.online_chain import chain_marginal_prior
from estimator.online_state import OnlineState, window_problem
from estimator.problem import Problem


def marginalize_window(st: OnlineState) -> None:
    """Fold the keyframes beyond params.window into the prior, at the last full solve's
    estimate (nothing has moved since: the update that solved deferred this)."""
    st.marginalize_due = False
    if st.n > st.params.window:
        m = st.n - st.params.window
        if not (marginalize_block(st, m) or marginalize_chain(st, m)):
            while st.n > st.params.window:
                marginalize_oldest(st)


def marginalize_block(st: OnlineState, m: int) -> bool:
    """Fold the m oldest keyframes into the prior at once when nothing links them to each
    other or to the rest (white GPS, no motion links, a prior on the users only); False
    (nothing done) otherwise. Each keyframe i is then independent given Θ, so the sequential
    marginalize_oldest at the same point sums to

        Λ = Λ_prior + Σ_i (H_θθ,i − H_θi H_ii⁻¹ H_iθ),   c = ∇_prior + Σ_i (∇_θ,i − H_θi H_ii⁻¹ ∇_i)

    with H_ii = I/σ_gps² + Σ_k w J_x J_xᵀ, H_iθ = w J_x J_θᵀ (user k's columns),
    H_θθ,i = w J_θ J_θᵀ, ∇_i = (x_i − x̂_i)/σ_gps² + Σ_k ψ J_x, ∇_θ,i = ψ J_θ."""
    prob = window_problem(st)
    pr = st.prior
    if prob.gps_linked or (pr is not None and pr.has_x) or (
            prob.use_motion and bool(st.odom_mask[1 : m + 1].any())):
        return False
    k_all, p = st.k, st.p
    pu = k_all * p
    x = st.x[:m]
    theta = st.theta
    mask = prob.mask[:m].T & st.active[:, None]
    _e, w, _rho, jac, psi, _ = range_terms(prob, x, theta, mask)
    jx, jt = jac[:3], jac[3:]  # (3, K, m), (p, K, m)
    inv_g2 = 1.0 / st.noise.sigma_gps_m**2
    # H_ii (m, 3, 3), H_iθ (m, 3, K, p), ∇_i (m, 3)
    wjx = jx * w
    h_ii = np.einsum("akm,bkm->mab", wjx, jx) + np.eye(3) * inv_g2
    h_it = np.einsum("akm,ckm->makc", wjx, jt).reshape(m, 3, pu)
    g_i = (x - prob.gps_enu_m[:m]) * inv_g2 + np.einsum("akm,km->ma", jx, psi)
    info = np.zeros((pu, pu))
    blocks = np.einsum("akm,bkm->kab", jt * w, jt)  # (K, p, p)
    for k in range(k_all):
        info[k * p : (k + 1) * p, k * p : (k + 1) * p] = blocks[k]
    cvec = np.einsum("akm,km->ka", jt, psi).ravel()
    # minus Σ_i H_θi H_ii⁻¹ [H_iθ | ∇_i]
    sol = np.linalg.solve(h_ii, np.concatenate([h_it, g_i[:, :, None]], axis=2))  # (m, 3, pu + 1)
    info -= np.einsum("mai,maj->ij", h_it, sol[:, :, :pu])
    cvec -= np.einsum("mai,ma->i", h_it, sol[:, :, pu])
    if pr is not None:
        z = theta.ravel()
        info += pr.info
        cvec += pr.grad + pr.info @ (z - pr.z0)
    st.prior = Prior(False, theta.ravel().copy(), 0.5 * (info + info.T), cvec)
    drop_oldest(st, m, prob)
    return True


def marginalize_chain(st: OnlineState, m: int) -> bool:
    """Fold the m oldest keyframes into a prior on [x_m, Θ] at once when Gauss–Markov GPS
    factors chain them (online_chain.chain_marginal_prior); False (nothing done) otherwise.
    The same prior as m calls of marginalize_oldest at the same point."""
    prob = window_problem(st)
    if not prob.gps_linked or not 1 <= m < st.n:
        return False
    # the factors touching keyframes 0..m−1: all but keyframe m's ranges
    n1 = m + 1
    rng = prob.range_m[:n1].copy()
    rng[m] = np.nan
    sub = replace(prob, gps_enu_m=prob.gps_enu_m[:n1], range_m=rng, mask=~np.isnan(rng),
                  odom_enu_m=prob.odom_enu_m[:n1], odom_mask=prob.odom_mask[:n1], t_s=prob.t_s[:n1],
                  odom_sigma_m=None if prob.odom_sigma_m is None else prob.odom_sigma_m[:n1],
                  bias_gain=None if prob.bias_gain is None else prob.bias_gain[:n1])
    lin = linearize(sub, st.x[:n1], st.theta, st.active, st.prior)
    # linearize adds the bias priors and an identity block for inactive users: factors of the
    # window, not of these keyframes
    p, k_all = st.p, st.k
    blocks = lin.huu.reshape(k_all, p, k_all, p)
    if st.params.estimate_bias:
        sb = st.params.bias_prior_sigma_m if st.bias_sigma_m is None else st.bias_sigma_m
        inv_b2 = np.broadcast_to(1.0 / np.square(sb), (k_all,))
        act = np.flatnonzero(st.active)
        blocks[act, -1, act, -1] -= inv_b2[act]
        b = st.theta[act, -1] if st.bias_mean_m is None else st.theta[act, -1] - st.bias_mean_m[act]
        lin.gu.reshape(k_all, p)[act, -1] += b * inv_b2[act]
    for k in np.flatnonzero(~st.active):
        blocks[k, :, k, :] -= np.eye(p)
    info, grad = chain_marginal_prior(lin, m)
    st.prior = Prior(True, np.concatenate([st.x[m], st.theta.ravel()]), info, grad)
    drop_oldest(st, m, prob)
    st.gps_first = False  # keyframe m's link to m − 1 now lives in the prior
    return True


def marginalize_oldest(st: OnlineState) -> None:
    """Fold keyframe 0 of the window into the prior at the current estimate, then drop it."""
    prob = window_problem(st)
    noise = st.noise
    k_all, p = st.k, st.p
    pu = k_all * p
    x = st.x[: st.n]
    theta = st.theta
    motion_link = bool(prob.use_motion and st.odom_mask[1])
    gps_link = bool(prob.gps_linked)
    link = motion_link or gps_link
    # variables v = [x_0 (3), x_1 (3), Θ (K·p)]; H and ∇ of every factor touching x_0
    dim = 6 + pu
    h = np.zeros((dim, dim))
    grad = np.zeros(dim)
    mask0 = prob.mask[:1].T & st.active[:, None]
    _e, w, _rho, jac, psi, _ = range_terms(prob, x[:1], theta, mask0)
    # H += Σ w JᵀJ,  ∇ += Σ ψ J
    jfull = np.zeros((k_all, dim))
    jfull[:, :3] = jac[:3, :, 0].T  # (K, 3)
    kk = np.arange(k_all)[:, None]
    jfull[kk, 6 + kk * p + np.arange(p)[None, :]] = jac[3:, :, 0].T  # (K, p)
    h += (jfull * w[:, :1]).T @ jfull
    grad += jfull.T @ psi[:, 0]
    if gps_link:
        # the GPS factors touching x_0: its own (if still in the window) and the link to x_1
        gt = gps_chain_terms(x[:2], prob.gps_enu_m[:2], prob.gps_phi()[:2], noise.sigma_gps_m, prob.gps_first)
        h[:3, :3] += np.eye(3) * gt.diag[0]
        h[3:6, 3:6] += np.eye(3) * gt.diag[1]
        h[:3, 3:6] += np.eye(3) * gt.off[0]
        h[3:6, :3] += np.eye(3) * gt.off[0]
        grad[:6] += gt.grad.ravel()
    else:
        inv_g2 = 1.0 / noise.sigma_gps_m**2
        h[:3, :3] += np.eye(3) * inv_g2
        grad[:3] += (x[0] - prob.gps_enu_m[0]) * inv_g2
    if motion_link:
        inv_m2 = 1.0 / float(st.odom_sigma_m[1]) ** 2
        em = x[1] - x[0] - prob.odom_enu_m[1]
        h[:3, :3] += np.eye(3) * inv_m2
        h[3:6, 3:6] += np.eye(3) * inv_m2
        h[:3, 3:6] -= np.eye(3) * inv_m2
        h[3:6, :3] -= np.eye(3) * inv_m2
        grad[:3] -= em * inv_m2
        grad[3:6] += em * inv_m2
    pr = st.prior
    if pr is not None:
        z = theta.ravel()
        if pr.has_x:
            z = np.concatenate([x[0], z])
        gz = pr.grad + pr.info @ (z - pr.z0)
        sel = np.r_[0:3, 6:dim] if pr.has_x else np.r_[6:dim]
        h[np.ix_(sel, sel)] += pr.info
        grad[sel] += gz
    # Λ = H_rr − H_r0 H_00⁻¹ H_0r,  c = ∇_r − H_r0 H_00⁻¹ ∇_0
    h00_inv = np.linalg.inv(h[:3, :3])
    h_r0 = h[3:, :3]
    info = h[3:, 3:] - h_r0 @ h00_inv @ h_r0.T
    cvec = grad[3:] - h_r0 @ h00_inv @ grad[:3]
    z0 = np.concatenate([x[1], theta.ravel()])
    if not link:
        info, cvec, z0 = info[3:, 3:], cvec[3:], z0[3:]
    st.prior = Prior(link, z0, 0.5 * (info + info.T), cvec)
    # drop keyframe 0
    drop_oldest(st, 1, prob)
    if gps_link:
        st.gps_first = False  # its link to the dropped keyframe now lives in the prior


def drop_oldest(st: OnlineState, m: int, prob: Problem) -> None:
    """Drop the m oldest keyframes of the window (their factors now live in the prior): every
    per-keyframe array shifts with the window, the new keyframe 0 has no motion factor."""
    n = st.n
    st.win_count -= prob.mask[:m].sum(axis=0)
    for arr in (st.gps_enu_m, st.range_m, st.odom_enu_m, st.odom_mask, st.odom_sigma_m, st.x, st.t_s):
        arr[: n - m] = arr[m:n]
    st.odom_mask[0] = False
    st.odom_sigma_m[0] = np.nan
    st.n = n - m
