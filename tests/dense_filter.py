"""Dense reference for one online filter step (tests of estimator.online_filter / online_chain).

Variables v = [x_l (3), x_n (3), Θ (K·p)]: the last keyframe before the step, the new one and the
users. H starts as the estimator's Ŝ on (x_l, Θ); each factor of the new keyframe adds JᵀWJ to H
and −Jᵀψ to g at the prediction x_n⁰ and the previous Θ; the step is Δv = H⁻¹ g and the new Ŝ the
Schur complement of H over x_l.
"""

from __future__ import annotations

import numpy as np

from estimator.factors import RangeFactor
from estimator.online import full_update
from estimator.robust import loss_psi_weight


def step_to_dense(on, keyframes, j):
    """Feed keyframes[:j] (the last one by a full update), then keyframe j, which must be folded
    by a filter step. Returns (estimate, the step's Ŝ before it, Θ before it, π, x_l, H, g) with
    H and g holding Ŝ only (dim = 6 + K·p)."""
    for kf in keyframes[:j]:
        est = on.add_keyframe(kf)
    assert est.state.active.all()
    last = keyframes[j - 1]
    st = on.state
    full_update(st, st.n - 1, last.gps_enu_m, last.user_idx, last.range_m, last.odom_enu_m)
    theta0, s_aug, pi = st.theta.copy(), st.s_aug.copy(), st.nlos_pi.copy()
    x_l = st.x[st.n - 1].copy()
    est = on.add_keyframe(keyframes[j])
    assert est.state.filter_step
    dim = 6 + st.k * st.p
    h, g = np.zeros((dim, dim)), np.zeros(dim)
    sel = np.r_[0:3, 6:dim]
    h[np.ix_(sel, sel)] = s_aug
    return est, theta0, pi, x_l, h, g


def add_ranges(h, g, on, kf, x0, theta0, pi, user_up_m) -> None:
    """H += Σ w JᵀJ, g −= Σ ψ J over the ranges of kf (RangeFactor objects) at x0 and Θ."""
    noise, params, p = on.state.noise, on.state.params, on.state.p
    for k, r in zip(kf.user_idx, kf.range_m, strict=True):
        f = RangeFactor(float(r), noise, params.user_dim, float(user_up_m[k]), params.estimate_bias)
        e = f.error(x0, theta0[k])
        jx, jt = f.jacobian(x0, theta0[k])
        sig = f.sigma_m
        _, psi, w = loss_psi_weight(np.array([e]), params.loss, params.loss_scale, (pi[k], params.nlos_mean_m / sig))
        jr = np.zeros(h.shape[0])
        jr[3:6] = jx
        jr[6 + k * p : 6 + (k + 1) * p] = jt
        h += w[0] * np.outer(jr, jr)
        g -= psi[0] * jr


def assert_step_matches(on, est, h, g, theta0, x_l, x0) -> None:
    """The estimator's step, Ŝ and user covariances against Δv = H⁻¹ g and H's Schur complement."""
    k_all, p = on.state.k, on.state.p
    dv = np.linalg.solve(h, g)
    # to 1e-9 of the step (a user with a free bias under its weak prior conditions H less well:
    # 4e-11 m on a 0.5 m step)
    np.testing.assert_allclose(on.state.theta.ravel() - theta0.ravel(), dv[6:], rtol=1e-9, atol=1e-9 * np.abs(dv).max())
    np.testing.assert_allclose(est.uav_enu_m[-1], x0 + dv[3:6], rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(est.uav_enu_m[-2], x_l + dv[:3], rtol=1e-9, atol=1e-11)
    s_ref = h[3:, 3:] - h[3:, :3] @ np.linalg.solve(h[:3, :3], h[:3, 3:])
    np.testing.assert_allclose(on.state.s_aug, s_ref, rtol=1e-9, atol=1e-12 * np.abs(s_ref).max())
    cov_ref = np.linalg.inv(s_ref)[3:, 3:].reshape(k_all, p, k_all, p)
    for k in range(k_all):
        np.testing.assert_allclose(est.cov_users_m2[k], cov_ref[k, :2, k, :2], rtol=1e-9, atol=1e-12)
