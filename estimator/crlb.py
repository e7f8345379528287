"""Cramér–Rao lower bound of the users for a given geometry (docs/design.md §5).

The Fisher information of the model at the true positions is the normal matrix of the SLAM cost
evaluated there with zero residuals (unit IRLS weights): GPS priors on the keyframes, ranges
where visible, optional motion factors and bias priors. Eliminating the keyframes (and biases)

    CRLB(users) = S⁻¹,   S = H_uu − H_ux H_xx⁻¹ H_xu   at the truth.

It is the bound for estimators of this cost; with a distance-dependent spread (a ≠ 0) a Gaussian
model carries extra information through σ(d) itself (2(σ'/σ)² ∇d∇dᵀ per range) that the
estimator does not use and this bound leaves out. With a = 0 (the default) they coincide.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from estimator.linearize import linearize
from estimator.noise import NoiseModel
from estimator.problem import Problem, check_params
from estimator.schur import schur_solve
from estimator.types import SolverParams
from uavloc.errors import EstimatorError


def crlb_users(
    uav_enu_m: np.ndarray, users_enu_m: np.ndarray, visible: np.ndarray, noise: NoiseModel,
    params: SolverParams = SolverParams(),  # noqa: B008
    t_s: np.ndarray | None = None, bias_gain: np.ndarray | None = None,
) -> np.ndarray:
    """(K·d, K·d) lower bound on the joint covariance of the users' coordinates [m²].

    uav_enu_m: (N, 3) true keyframe positions [m, ENU]; users_enu_m: (K, 3) true users [m, ENU];
    visible: (N, K) bool, which ranges are measured; d = params.user_dim; t_s: (N,) keyframe
    times [s], needed for Gauss–Markov GPS factors (noise.gps_tau_s > 0; None: GPS white);
    bias_gain: (N, K) gain g_nk of user k's bias in range n, r̂ = d + b_k g_nk (Problem.bias_gain:
    a tracked clock sawtooth's shape, b_k its amplitude; needs params.estimate_bias; None: 1).
    Coordinates are ordered user by user (east, north[, up]). Users that no range sees get inf on
    their diagonal.
    """
    check_params(params)
    if not isinstance(noise, NoiseModel):
        raise EstimatorError(f"noise must be a NoiseModel, got {type(noise).__name__}")
    uav = np.asarray(uav_enu_m, dtype=float)
    users = np.asarray(users_enu_m, dtype=float)
    vis = np.asarray(visible, dtype=bool)
    if uav.ndim != 2 or uav.shape[1] != 3 or uav.shape[0] < 1:
        raise EstimatorError(f"uav_enu_m must have shape (N, 3), got {uav.shape}")
    if users.ndim != 2 or users.shape[1] != 3 or users.shape[0] < 1:
        raise EstimatorError(f"users_enu_m must have shape (K, 3), got {users.shape}")
    n, k_all = uav.shape[0], users.shape[0]
    if vis.shape != (n, k_all):
        raise EstimatorError(f"visible must have shape ({n}, {k_all}), got {vis.shape}")
    if not (np.all(np.isfinite(uav)) and np.all(np.isfinite(users))):
        raise EstimatorError("uav_enu_m and users_enu_m must be finite")
    d_u = params.user_dim
    p = d_u + (1 if params.estimate_bias else 0)
    dist = np.linalg.norm(uav[:, None, :] - users[None, :, :], axis=2)
    rng = np.where(vis, dist, np.nan)
    odom = np.diff(uav, axis=0, prepend=uav[:1])
    odom_mask = np.zeros(n, dtype=bool)
    if params.motion_sigma_m is not None:
        odom_mask[1:] = True
    # Fisher information of the Gaussian range model: unit weights whatever the solver's loss
    # (the "nlos" loss weighs even a zero residual by γ(0) < 1)
    times = None if t_s is None else np.asarray(t_s, dtype=float)
    if times is not None and times.shape != (n,):
        raise EstimatorError(f"t_s must have shape ({n},), got {times.shape}")
    gain = None
    if bias_gain is not None:
        gain = np.asarray(bias_gain, dtype=float)
        if not params.estimate_bias:
            raise EstimatorError("bias_gain needs params.estimate_bias")
        if gain.shape != (n, k_all) or not np.all(np.isfinite(gain)):
            raise EstimatorError(f"bias_gain must be finite with shape ({n}, {k_all}), got {gain.shape}")
    prob = Problem(uav, rng, vis, odom, odom_mask, users[:, 2].copy(), noise, replace(params, loss="none"),
                   t_s=times, bias_gain=gain)
    theta = np.zeros((k_all, p))
    theta[:, :d_u] = users[:, :d_u]
    active = vis.sum(axis=0) > 0
    lin = linearize(prob, uav.copy(), theta, active)
    _, _, s = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, 0.0)
    out = np.zeros((k_all * d_u, k_all * d_u))
    ia = np.flatnonzero(np.repeat(active, p))
    cov_a = np.linalg.inv(s[np.ix_(ia, ia)])
    na = int(active.sum())
    pos = cov_a.reshape(na, p, na, p)[:, :d_u, :, :d_u].reshape(na * d_u, na * d_u)
    ip = (np.flatnonzero(active)[:, None] * d_u + np.arange(d_u)[None, :]).ravel()
    out[np.ix_(ip, ip)] = 0.5 * (pos + pos.T)
    for k in np.flatnonzero(~active):
        idx = np.arange(k * d_u, (k + 1) * d_u)
        out[idx, idx] = np.inf
    return out
