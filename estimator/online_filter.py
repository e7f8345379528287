"""Information-filter steps of the online estimator between window solves (estimator.online):
one keyframe folded into the users' information, white GPS (filter_step) or linked to the
previous keyframe by its Gauss–Markov GPS or motion factor (chain_filter_step); and the placement
of a window solve's new keyframe (place_keyframe), from the same per-range terms (range_rows).
Functions of the estimator's state (estimator.online_state.OnlineState), which they update."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erfcx

from estimator.gps import gps_phi
from estimator.marginals import (
    user_covariances,
)
from estimator.noise import SIGMA_EXPONENT_MAX
from estimator.online_chain import chain_step
from estimator.online_state import OnlineState
from estimator.robust import loss_psi_weight
from estimator.schur import sym3_cofactors
from estimator.types import Estimate, ModelState

_SQRT_HALF_PI = math.sqrt(0.5 * math.pi)
_SQRT_HALF = math.sqrt(0.5)
#: a filter step may move a parameter by this many of its standard deviations (or by
#: params.online_max_step_m, whichever is larger) before the window is re-solved instead
ONLINE_STEP_SIGMA = 0.5


def _inv3_sym(a00: float, a01: float, a02: float, a11: float, a12: float, a22: float) -> np.ndarray:
    """(3, 3) inverse of the symmetric matrix [[a00 a01 a02] [a01 a11 a12] [a02 a12 a22]] by
    cofactors, A⁻¹ = adj(A)/det(A), in Python floats (one small matrix: cheaper than numpy)."""
    c00, c01, c02, c11, c12, c22, det = sym3_cofactors(a00, a01, a02, a11, a12, a22)
    r = 1.0 / det
    return np.array([[c00 * r, c01 * r, c02 * r], [c01 * r, c11 * r, c12 * r], [c02 * r, c12 * r, c22 * r]])


def _keyframe_normal(us: list, w: list, psi: list, inv_g2: float, g_start: tuple) -> tuple[float, ...]:
    """One keyframe's normal equations in x from its ranges (range_rows: α û, w, ψ per range),
    with J_x = −α û:  H_nn = I·inv_g2 + Σ w J_xᵀ J_x,  g_n = g_start − Σ ψ J_x.
    Returns the 6 entries of H_nn (00, 01, 02, 11, 12, 22) and g_n's 3, in Python floats."""
    h00 = h11 = h22 = inv_g2
    h01 = h02 = h12 = 0.0
    g0, g1, g2 = g_start
    for (vx, vy, vz), wj, pj in zip(us, w, psi, strict=True):
        wx, wy = wj * vx, wj * vy
        h00 += wx * vx
        h01 += wx * vy
        h02 += wx * vz
        h11 += wy * vy
        h12 += wy * vz
        h22 += wj * vz * vz
        g0 += pj * vx
        g1 += pj * vy
        g2 += pj * vz
    return h00, h01, h02, h11, h12, h22, g0, g1, g2


def filter_step(st: OnlineState, n: int, gps: np.ndarray, idx: np.ndarray, rng: np.ndarray) -> Estimate | None:
    """Fold keyframe n into the users by one information-filter step; None when the step is
    larger than params.online_max_step_m (the caller then re-solves the window).

    The window and prior are summarized by S (users' information at the last solution θ̂,
    where their gradient is zero). The new keyframe's factors (GPS prior, ranges to active
    users, weights w and ψ = ρ'(e) of the loss) are linearized at (x̂_n = GPS fix, θ̂):

        H_nn = I/σ_gps² + Σ_k w J_xᵀJ_x,  H_nk = w J_xᵀJ_θ,  H_kk = w J_θᵀJ_θ
        g_n = −(x_n − x̂_n)/σ_gps² − Σ_k ψ J_x,  g_k = −ψ J_θ

    and the keyframe is eliminated at once (Schur), the same algebra as estimator.schur:

        S ← S + H_θθ − H_θn H_nn⁻¹ H_nθ,   S Δθ = g_θ − H_θn H_nn⁻¹ g_n,
        Δx_n = H_nn⁻¹ (g_n − H_nθ Δθ)

    Older window keyframes keep their positions until the next full solve. Cost O(K²·p²)
    for the update plus O((K·p)³) for S⁻¹ (the covariance), independent of N and window.
    """
    params, noise = st.params, st.noise
    # a Gauss–Markov GPS link or a motion factor ties x_n to the last keyframe: the chain step
    linked = st.gps_linked or bool(st.odom_mask[n])
    phi = 0.0
    if st.gps_linked:
        # the Gauss–Markov prediction x_n⁰ = x̂_n + φ_n (x_l − x̂_l): the GPS factor's residual is 0
        phi = float(gps_phi(st.t_s[n - 1 : n + 1], noise.gps_tau_used_s)[1])
        x0 = gps + phi * (st.x[n - 1] - st.gps_enu_m[n - 1])
    else:
        x0 = gps
        st.x[n] = gps
        if not linked:
            st.s_aug = None  # no longer the summary of the last keyframe
    if st.all_active:
        if idx.size == 0:
            return chain_filter_step(st, n, x0, phi, None) if linked else filter_estimate(st, st.s, None)
        ka, r_list = idx, rng.tolist()
    else:
        use = st.active[idx]
        if not use.any():
            return chain_filter_step(st, n, x0, phi, None) if linked else filter_estimate(st, st.s, None)
        ka, r_list = idx[use], rng[use].tolist()
    ka_list = ka.tolist()
    # every user ranged, in order: S_add covers all of S
    full = ka_list == st.k_list
    p, d_u = st.p, params.user_dim
    with_bias = params.estimate_bias
    us, sigs, psi, w = range_rows(st, x0, ka_list, r_list)
    # J_x = −α û, J_θ = [α û_(:d), (−1/σ)]: H_nn = I/σ_gps² + Σ w J_xᵀJ_x, g_n = −Σ ψ J_x,
    # B = H_nθ (3, m·p) with blocks w J_xᵀ J_θ, blockdiag H_θθ = w J_θᵀ J_θ, g_θ = −ψ J_θ
    # (the GPS factor of a linked keyframe enters in chain_filter_step)
    h00, h01, h02, h11, h12, h22, g0, g1, g2 = _keyframe_normal(
        us, w, psi, 0.0 if linked else st.inv_g2, (0.0, 0.0, 0.0))
    m = ka.size
    u_a = np.array(us)  # α û, (m, 3)
    w_a = np.array(w)
    jt = np.empty((m, p))
    jt[:, :d_u] = u_a[:, :d_u]
    if with_bias:
        jt[:, -1] = -1.0 / np.array(sigs)
    # B[i, (j, c)] = w_j J_x,ji J_θ,jc = −w_j α û_ji J_θ,jc
    b = ((u_a * w_a[:, None]).T[:, :, None] * jt[None, :, :]).reshape(3, m * p)
    np.negative(b, out=b)
    if linked:
        h_nn = np.array([[h00, h01, h02], [h01, h11, h12], [h02, h12, h22]])
        cols = (ka[:, None] * p + st.arange_p).ravel()
        h_tt = np.zeros((m * p, m * p))
        h_tt.ravel()[blockdiag_index(st, m)] = ((jt * w_a[:, None])[:, :, None] * jt[:, None, :]).ravel()
        g_t = (jt * np.array(psi)[:, None]).ravel()
        np.negative(g_t, out=g_t)
        return chain_filter_step(st, n, x0, phi, (h_nn, np.array([g0, g1, g2]), b, cols, h_tt, g_t))
    hinv = _inv3_sym(h00, h01, h02, h11, h12, h22)
    hb = hinv @ b  # H_nn⁻¹ H_nθ
    hg = hinv @ np.array([g0, g1, g2])
    # S_add = blockdiag(w J_θᵀ J_θ) − Bᵀ H_nn⁻¹ B;  g_add = −ψ J_θ − Bᵀ H_nn⁻¹ g_n
    s_add = b.T @ hb
    np.negative(s_add, out=s_add)
    s_add.ravel()[blockdiag_index(st, m)] += ((jt * w_a[:, None])[:, :, None] * jt[:, None, :]).ravel()
    g_add = (jt * np.array(psi)[:, None]).ravel()
    np.negative(g_add, out=g_add)
    g_add -= b.T @ hg
    if full:
        s_new = st.s + s_add
    else:
        cols = (ka[:, None] * p + st.arange_p).ravel()
        s_new = st.s.copy()
        s_new[cols[:, None], cols] += s_add
    # P = S⁻¹ (the users' covariance), Δθ = P g
    try:
        cov = np.linalg.inv(s_new)
    except np.linalg.LinAlgError:
        return None
    dth = cov @ g_add if full else cov[:, cols] @ g_add
    if not step_ok(st, dth, cov):
        return None
    # Δx_n = H_nn⁻¹ (g_n − H_nθ Δθ)
    st.x[n] = gps + hg - hb @ (dth if full else dth[cols])
    st.theta = st.theta + dth.reshape(st.k, p)
    st.users_enu_m[:, :d_u] = st.theta[:, :d_u]
    st.s = s_new
    return filter_estimate(st, s_new, cov)


def range_rows(
    st: OnlineState, x0: np.ndarray, ka_list: list[int], r_list: list[float],
) -> tuple[list, list, list, list]:
    """The ranges r_list to the active users ka_list from a keyframe at x0 (3,), at the
    current users, biases, noise scales and NLoS probabilities, in Python floats (m ≤ K
    ranges: cheaper than numpy): per range α û = ∂e/∂u = −∂e/∂x (3-tuples), σ, ψ = ρ'(e)
    and the weight w of the loss (estimator.factors, estimator.robust: the same formulas)."""
    params, noise = st.params, st.noise
    gx, gy, gz = x0.tolist()
    users = st.users_enu_m[ka_list].tolist()
    with_bias = params.estimate_bias
    biases = st.theta[ka_list, -1].tolist() if with_bias else None
    s0, a_m, b_m = noise.range_s0_m, noise.range_a_m, noise.range_b_per_m
    us, sigs, es = [], [], []
    for j, (r_j, (ux, uy, uz)) in enumerate(zip(r_list, users, strict=True)):
        dx, dy, dz = gx - ux, gy - uy, gz - uz
        d = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-9)
        # σ(r̂) = s0 + a·exp(b·r̂), the spread at the measured range (estimator.factors)
        sc = st.noise_scale_list[ka_list[j]]
        sig = (s0 + a_m * math.exp(min(b_m * max(r_j, 0.0), SIGMA_EXPONENT_MAX)) if a_m != 0.0 else s0) * sc
        res = r_j - d - (biases[j] if with_bias else 0.0)
        # α = 1/σ
        f = 1.0 / (sig * d)
        us.append((dx * f, dy * f, dz * f))
        sigs.append(sig)
        es.append(res / sig)
    if params.loss == "nlos":
        # the mixture loss in Python floats (estimator.robust.nlos_terms, same formulas)
        psi, w = [], []
        for e_j, sig_j, k in zip(es, sigs, ka_list, strict=True):
            pi_j = st.nlos_pi_list[k]
            inv_m = sig_j / params.nlos_mean_m
            t = e_j - inv_m
            mills = _SQRT_HALF_PI * float(erfcx(-_SQRT_HALF * min(t, 37.0)))
            q = pi_j * inv_m * mills
            g = 1.0 - pi_j + q
            w.append((1.0 - pi_j) / g)
            psi.append(e_j - q / g * (t + 1.0 / mills))
    else:
        _, psi_a, w_a = loss_psi_weight(np.array(es), params.loss, params.loss_scale, None, need_rho=False)
        psi, w = psi_a.tolist(), w_a.tolist()
    return us, sigs, psi, w


def place_keyframe(st: OnlineState, x0: np.ndarray, gps: np.ndarray, idx: np.ndarray, rng: np.ndarray) -> np.ndarray:
    """One Gauss–Newton step on a new keyframe alone (users fixed) from x0: a warm start that
    leaves the joint iterations only the users' small shift to absorb.

        min_x ||x − x̂||²/σ_gps² + Σ_k w (r̂_k − ||x − u_k|| − b_k)²/σ²
    """
    use = st.active[idx]
    if not use.any():
        return x0
    us, _, psi, w = range_rows(st, x0, idx[use].tolist(), rng[use].tolist())
    ig = st.inv_g2
    # g = −(x0 − x̂)/σ_gps² − Σ ψ J_x
    h00, h01, h02, h11, h12, h22, g0, g1, g2 = _keyframe_normal(us, w, psi, ig, ((gps - x0) * ig).tolist())
    return x0 + _inv3_sym(h00, h01, h02, h11, h12, h22) @ np.array([g0, g1, g2])


def chain_filter_step(st: OnlineState, n: int, x0: np.ndarray, phi: float, ranges: tuple | None) -> Estimate | None:
    """The filter step of a keyframe linked to the last one by its Gauss–Markov GPS factor
    and/or a relative-motion factor (estimator.online_chain): the window summarized by Ŝ, the
    information of [x_l, Θ]; x_l moves with the step, the older keyframes keep their positions
    until the next full solve.
    ranges: the new keyframe's range terms at x0 (online_chain.chain_step), None without any.
    None when the step is larger than params.online_max_step_m or J is not positive definite."""
    p_all = st.k * st.p
    if ranges is None:
        ranges = (np.zeros((3, 3)), np.zeros(3), np.zeros((3, 0)), np.zeros(0, dtype=np.intp),
                  np.zeros((0, 0)), np.zeros(0))
    # W_n = 1/(σ_gps² (1 − φ²)); a motion factor W_m = 1/σ_m², δ = x_n⁰ − x_l − ô_n
    w_gps = 1.0 / (st.noise.sigma_gps_m**2 * (1.0 - phi * phi))
    w_m, delta_m = 0.0, None
    if st.odom_mask[n]:
        w_m = 1.0 / float(st.odom_sigma_m[n]) ** 2
        delta_m = x0 - st.x[n - 1] - st.odom_enu_m[n]
    try:
        dx_l, dx_n, dth, s_aug, cov = chain_step(st.s_aug, phi, w_gps, *ranges, w_m=w_m, delta_m=delta_m)
    except np.linalg.LinAlgError:
        return None
    if p_all and not step_ok(st, dth, cov):
        return None
    st.x[n - 1] += dx_l
    st.x[n] = x0 + dx_n
    st.theta = st.theta + dth.reshape(st.k, st.p)
    st.users_enu_m[:, : st.params.user_dim] = st.theta[:, : st.params.user_dim]
    st.s_aug = s_aug
    # the users' information: Ŝ' with x_n eliminated
    s_nt = s_aug[:3, 3:]
    st.s = s_aug[3:, 3:] - s_nt.T @ np.linalg.solve(s_aug[:3, :3], s_nt)
    return filter_estimate(st, st.s, cov)


def step_ok(st: OnlineState, dth: np.ndarray, cov: np.ndarray) -> bool:
    """A filter step ΔΘ (P,) is kept when no parameter moves by more than the larger of
    params.online_max_step_m and, where that is at least twice as large, ONLINE_STEP_SIGMA of
    its standard deviation (from the step's covariance cov (P, P)): a user still known to
    several metres or worse (just started, few ranges from a short arc) moves metres per
    keyframe, within its uncertainty, without a re-solve."""
    step = np.abs(dth)
    lim = st.params.online_max_step_m
    if step.max() <= lim:
        return True
    rel = ONLINE_STEP_SIGMA * np.sqrt(np.maximum(np.diag(cov), 0.0))
    return bool(np.all(step <= np.where(rel >= 2.0 * lim, rel, lim)))


def blockdiag_index(st: OnlineState, m: int) -> np.ndarray:
    """Flat indices of the m diagonal p×p blocks of an (m·p, m·p) matrix, block-row-major."""
    out = st.bd_cache.get(m)
    if out is None:
        p = st.p
        i = np.arange(m)[:, None, None] * p + np.arange(p)[None, :, None]
        j = np.arange(m)[:, None, None] * p + np.arange(p)[None, None, :]
        out = (i * (m * p) + j).ravel()
        st.bd_cache[m] = out
    return out


def filter_estimate(st: OnlineState, s: np.ndarray, cov_all: np.ndarray | None) -> Estimate:
    """Estimate after a filter step from S (K·p, K·p) and its inverse when known; mirrors
    and ambiguity flags from the last full solve."""
    k_all, p, d = st.k, st.p, st.params.user_dim
    users = st.users_enu_m.copy()
    prev = st.estimate
    if cov_all is not None and p == d and st.active.all():
        # S⁻¹ blocks; the position information is S itself
        cov = cov_all.reshape(k_all, p, k_all, p)[st.arange_k, :, st.arange_k, :]
        info, cov_joint = s, cov_all
    else:
        users[~st.active] = np.nan
        cov, info, cov_joint = user_covariances(s, st.active, k_all, p, d, cov_all)
    bias = np.where(st.active, st.theta[:, -1], np.nan) if st.params.estimate_bias else None
    return Estimate(
        users_enu_m=users, cov_users_m2=cov, info_users=info, bias_m=bias,
        uav_enu_m=st.x[: st.n].copy(), ambiguous=prev.ambiguous.copy(),
        mirror_enu_m=prev.mirror_enu_m.copy(), n_ranges=st.n_ranges.copy(), cost=float("nan"),
        iterations=0, converged=True,
        state=ModelState(active=st.active.copy(), cov_theta_joint=cov_joint,
                         noise_scale=st.noise_scale.copy(), filter_step=True),
    )
