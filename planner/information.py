"""The planner's hypotheses (posterior samples) and the predicted information of a leg (docs/design.md §6).

The objective itself is defined once, in CasADi (planner.objective): `objective_values` and
`prior_value` evaluate its kernels, the same functions IPOPT minimises. `predicted_information`
below is the slow, obvious reference the tests check them against: the same model computed from
the estimator's range factor (estimator.factors).

Model. A leg (or a horizon of legs) x_0 → w_1 → … → w_H is flown with a range measurement every Δ
metres. For user k at hypothesised position u, a measurement at m adds

    g gᵀ / σ_eff²(d),   g = (m − u)[:d] / |m − u|,   d = |m − u|,   σ_eff² = σ(d)² + σ_gps²

to its information (d = 2: the horizontal part of the unit vector; σ_gps folded into the range
variance because a GPS error along the line of sight shifts the range one-for-one). The sum over a
leg of length ℓ is replaced by the midpoint rule with Q points at fractions t_q = (q − ½)/Q, each
standing for ℓ/(Δ·Q) measurements, so it is smooth in the waypoints:

    I_k(u) = P_k + Σ_legs (ℓ/(Δ·Q)) Σ_q g_q g_qᵀ / σ_eff²(d_q)

P_k is the prior information: the inverse of the estimator's marginal covariance of user k (the
exact S⁻¹ block), plus ε·I.

Range bias. When the estimator also estimates a range bias b_k per user (`Estimate.bias_m` not
None), the range is r = |m − u_k| + b_k and a measurement's Jacobian on (u_k, b_k) is h = [−g; 1].
The information is then predicted in the joint (position, bias) space,

    J_k(u) = P_k + Σ_legs (ℓ/(Δ·Q)) Σ_q h_q h_qᵀ / σ_eff²(d_q),   h_q = [−g_q; 1]

with P_k the inverse of user k's (d+1)×(d+1) block of `Estimate.state.cov_theta_joint` (plus
ε·I), and the position accuracy is that of the position block of J_k⁻¹, whose inverse is the Schur
complement I_k = A − c cᵀ / s (J_k = [[A, c], [cᵀ, s]]): the criterion below is applied to it. A
bias is only separable from the position with ranges at diverse distances and elevations, and this
is what makes the planner look for them.

Objective (to minimise):

    J = Σ_k w_k Σ_s c_ks · f(I_k(u_ks)) + λ · Σ_legs ℓ,   f = tr(I⁻¹) ("A"), −log det I ("D"),
                                                          or 1/sqrt(λ_min(I)) ("E", d = 2)

"E" is the square root of the largest eigenvalue of the covariance, i.e. the 95 % error-ellipse
semi-major axis up to the factor sqrt(χ²₂(0.95)) — the stop rule's and the benchmark's measure.

over samples u_ks of each user's posterior (weights c_ks): sigma points of the estimate and, while
the estimator reports a mirror ambiguity, the same around the mirror solution (half the weight each).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from estimator.factors import range_jacobian, range_residuals
from estimator.nlos_shift import nlos_shift_cov
from estimator.noise import NoiseModel
from estimator.types import CHI2_2DOF_95, Estimate
from planner.objective import (
    N_NLOS,
    NO_COVERAGE_LIMIT_M,
    SQRT_EPS_M2,
    Shape,
    coverage_cut,
    goal_values,
    prior_values,
    row_values,
)

#: ε of the prior information regulariser [1/m²] (a 1 km standard deviation).
PRIOR_EPS_PER_M2 = 1e-6


@dataclass(frozen=True)
class Hypotheses:
    """Posterior samples the objective averages over.

    users_enu_m: (K, M, 3) sample positions [m]; sample_w: (K, M) weights (rows sum to 1);
    prior_info: (K, M, p, p) prior information per sample [1/m²] (the mirror's is reflected),
        p = d, or d + 1 with the bias last when `bias`;
    user_w: (K,) per-user weights; index: (K,) rows of the Estimate these users are;
    bias: True when each user has a range bias (joint position + bias information);
    noise_scale: (K,) factor by which each user's ranges are noisier than σ(d), as the estimator
        found (Estimate.state.noise_scale); None: 1.
    nlos: (K, M, N_NLOS) each sample's NLoS state and GPS floor [π₀ n, n, α₀, α₁, α₂, κ, α₃, v_f]
        (:func:`nlos_row`, planner.objective): the shift a one-sided NLoS excess leaves in the
        bound, where the user is seen in line of sight, and the variance the GPS floor leaves in
        it; None: neither.
    """

    users_enu_m: np.ndarray
    sample_w: np.ndarray
    prior_info: np.ndarray
    user_w: np.ndarray
    index: np.ndarray
    bias: bool = False
    noise_scale: np.ndarray | None = None
    nlos: np.ndarray | None = None

    @property
    def dim(self) -> int:
        """d: the users' position dimension."""
        return int(self.prior_info.shape[-1]) - int(self.bias)

    @property
    def n_par(self) -> int:
        """p: parameters per user (d, or d + 1 with a bias)."""
        return int(self.prior_info.shape[-1])


def users_initialised(estimate: Estimate) -> np.ndarray:
    """(K,) bool: users with a finite position and a finite covariance."""
    pos = np.all(np.isfinite(estimate.users_enu_m), axis=1)
    cov = np.all(np.isfinite(estimate.cov_users_m2.reshape(estimate.n_users, -1)), axis=1)
    return pos & cov


def _info_from_cov(cov: np.ndarray) -> np.ndarray:
    """(d, d) information inv(Σ) + ε·I of a covariance, symmetrised."""
    d = cov.shape[0]
    info = np.linalg.pinv(0.5 * (cov + cov.T), hermitian=True)
    return 0.5 * (info + info.T) + PRIOR_EPS_PER_M2 * np.eye(d)


#: the GPS floor takes at most this share of a user's smallest horizontal variance (without its NLoS
#: shift), so the part the survey shrinks stays positive definite
FLOOR_SHARE_MAX = 0.9


def survey_cov(estimate: Estimate, k: int, cov: np.ndarray, floor_var_m2: float = 0.0) -> np.ndarray:
    """User k's covariance `cov` (position first, any size ≥ 2) without its NLoS shift
    ½ |δ_k|² on the horizontal axes (ModelState.nlos_shift_m, estimator.nlos_shift.nlos_shift_cov)
    and without the GPS floor's variance `floor_var_m2` on them (:func:`floor_var_of`): the part
    more ranges shrink, which the planner's prior holds; the objective adds the shift back as it
    predicts it after the horizon, and the floor as it is (planner.objective, :func:`nlos_row`)."""
    st = estimate.state
    shift = 0.0 if st is None or st.nlos_shift_m is None else float(st.nlos_shift_m[k])
    out = np.asarray(cov, dtype=float)
    if shift > 0.0:
        out = out - nlos_shift_cov(shift, cov.shape[0])
    if floor_var_m2 > 0.0:
        out = out.copy()
        out[0, 0] -= floor_var_m2
        out[1, 1] -= floor_var_m2
    return out


def floor_var_of(estimate: Estimate, k: int, floor_m: float) -> float:
    """v_f [m²]: the variance per horizontal axis that the GPS floor r_floor = `floor_m` (the 95 %
    bound the drifting GPS leaves however the survey flies, PlanningConstraints.floor_m) holds in
    user k's covariance and no range removes,

        v_f = min(r_floor² / χ²₂(0.95), FLOOR_SHARE_MAX · λ_min(Σ_k,h))

    (Σ_k,h: the horizontal block without the NLoS shift; the cap keeps the rest positive definite
    where the estimate holds less than the floor). 0 without a floor."""
    if not floor_m > 0.0:
        return 0.0
    cov_h = survey_cov(estimate, k, np.asarray(estimate.cov_users_m2[k], dtype=float))[:2, :2]
    lam_min = float(np.linalg.eigvalsh(0.5 * (cov_h + cov_h.T))[0])
    return float(min(floor_m**2 / CHI2_2DOF_95, FLOOR_SHARE_MAX * max(lam_min, 0.0)))


def nlos_row(estimate: Estimate, k: int, reflect: np.ndarray | None = None, floor_var_m2: float = 0.0) -> np.ndarray:
    """(N_NLOS,) user k's NLoS state and GPS floor for the objective, [π₀ n, n, α₀, α₁, α₂, κ, α₃, v_f]
    (planner.objective): n its ranges so far, π₀ its NLoS share (ModelState.nlos_prob_k), α its
    NLoS profile by bearing and elevation (ModelState.nlos_bearing_logit; a profile of three, by
    bearing alone, has α₃ = 0) and κ = |δ_k| / π₀ the shift per unit
    share (estimator.nlos_shift: |δ| = κ π); zeros (no shift, κ = 0) where the estimate has none.
    v_f = floor_var_m2: the GPS floor's variance per horizontal axis (:func:`floor_var_of`).
    reflect: (2, 2) the mirror's reflection of the horizontal plane, applied to (α₁, α₂)."""
    out = np.zeros(N_NLOS)
    out[7] = floor_var_m2
    st = estimate.state
    if st is None or st.nlos_shift_m is None or st.nlos_prob_k is None:
        return out
    shift, pi0 = float(st.nlos_shift_m[k]), float(st.nlos_prob_k[k])
    if not (shift > 0.0 and pi0 > 0.0):
        return out
    n = float(estimate.n_ranges[k])
    alpha = np.zeros(4)
    if st.nlos_bearing_logit is not None:
        given = np.asarray(st.nlos_bearing_logit[k], dtype=float)
        alpha[:len(given)] = given
    if reflect is not None:
        alpha[1:3] = reflect @ alpha[1:3]
    out[:7] = [pi0 * n, n, *alpha[:3], shift / pi0, alpha[3]]
    return out


def predicted_nlos_var_m2(start_enu_m: np.ndarray, waypoints_enu_m: np.ndarray, hyp: Hypotheses,
                          model: PredictionModel) -> np.ndarray:
    """(C, K, M) v = ½ (κ π̂)² + v_f [m²], the variance per horizontal axis the ranges leave unseen
    after flying each candidate horizon (C, H, 3), the NLoS shift's and the GPS floor's: the slow
    reference of planner.objective's

        π̂ = (π₀ n + Σ_legs (ℓ/(ΔQ)) Σ_q p(β_q, ε_q)) / (n + Σ_legs ℓ/Δ),
        p(β, ε) = σ(α₀ + α₁ cos β + α₂ sin β + α₃ sin ε)

    with β and ε the bearing and elevation of the quadrature point from the user sample."""
    pts, lengths = quadrature_points(start_enu_m, waypoints_enu_m, model.n_quad)
    K, M = hyp.sample_w.shape
    nl = np.zeros((K, M, N_NLOS)) if hyp.nlos is None else np.asarray(hyp.nlos, dtype=float)
    n_meas = np.repeat(lengths / (model.delta_m * model.n_quad), model.n_quad, axis=1)  # (C, HQ)
    rel = pts[:, None, None, :, :] - hyp.users_enu_m[None, :, :, None, :]  # (C, K, M, HQ, 3)
    rho = np.sqrt(np.sum(rel[..., :2] ** 2, axis=-1) + SQRT_EPS_M2)
    dist = np.sqrt(np.sum(rel**2, axis=-1) + SQRT_EPS_M2)
    a = nl[None, :, :, None, :]
    p_nlos = 1.0 / (1.0 + np.exp(-(a[..., 2] + a[..., 3] * rel[..., 0] / rho + a[..., 4] * rel[..., 1] / rho
                                   + a[..., 6] * rel[..., 2] / dist)))
    count = nl[None, ..., 0] + np.einsum("cq,ckmq->ckm", n_meas, p_nlos)
    total = nl[None, ..., 1] + n_meas.sum(axis=1)[:, None, None]
    return 0.5 * (nl[None, ..., 5] * count / (total + 1e-9)) ** 2 + nl[None, ..., 7]


def joint_prior_info(estimate: Estimate, k: int, floor_var_m2: float = 0.0) -> np.ndarray:
    """(d+1, d+1) prior information of user k's (position, bias), bias last [1/m², 1/m²].

    The inverse of user k's block of `estimate.state.cov_theta_joint` (rows: the active users of
    `state.active` in order, d + 1 each) without its NLoS shift and the GPS floor's variance
    floor_var_m2 (survey_cov), plus ε·I. Without a
    usable joint covariance: the position marginal's information and ε for the bias (an unknown
    bias, uncorrelated).
    """
    d = int(estimate.cov_users_m2.shape[1])
    p = d + 1
    st = estimate.state
    if st is not None and st.cov_theta_joint is not None:
        joint = np.asarray(st.cov_theta_joint, dtype=float)
        active = np.asarray(st.active, dtype=bool)
        na = int(active.sum())
        if joint.shape == (na * p, na * p) and 0 <= k < len(active) and active[k]:
            j = int(np.count_nonzero(active[:k]))
            block = joint[j * p:(j + 1) * p, j * p:(j + 1) * p]
            if np.all(np.isfinite(block)):
                return _info_from_cov(survey_cov(estimate, k, block, floor_var_m2))
    out = PRIOR_EPS_PER_M2 * np.eye(p)
    out[:d, :d] = _info_from_cov(survey_cov(estimate, k, np.asarray(estimate.cov_users_m2[k], dtype=float),
                                            floor_var_m2))
    return out


def hypotheses_from_estimate(
    estimate: Estimate,
    user_weights: np.ndarray | None = None,
    sigma_points: str = "major",
    kappa: float = 2.0,
    max_offset_m: float = 30.0,
    users: np.ndarray | None = None,
    home_enu_m: np.ndarray | None = None,
    max_range_m: float = np.inf,
    floor_m: float = 0.0,
) -> Hypotheses:
    """Samples of the initialised users' posterior (or of `users`, a (K,) bool mask).

    Sigma points (unscented along r axes): u, u ± sqrt((r + κ) λ_i) v_i for the r eigen-axes used
    (Σ = Σ λ_i v_i v_iᵀ; "major": the largest only, r = 1; "all": r = d; "none": the mean only),
    weights κ/(r + κ) and 1/(2(r + κ)); offsets capped at `max_offset_m`. While user k is ambiguous,
    the same set around the mirror solution with Σ reflected (R = I − 2nnᵀ, n along mirror − u),
    each set weighted ½. Every user gets M = (2r + 1)·(2 if any user is ambiguous else 1) samples
    (unused ones weight 0) so the sizes are fixed. A mirror farther than `max_range_m` horizontally
    from `home_enu_m` is implausible (a diverged solve) and left out. With range biases
    (`estimate.bias_m` not None) the prior information is the joint (position, bias) one of
    :func:`joint_prior_info` (the mirror's reflected by diag(R, 1)); sigma points stay on the
    position marginal. The prior information leaves out the NLoS shift and the GPS floor
    `floor_m` (the 95 % bound the drifting GPS leaves, :func:`floor_var_of`) that no range shrinks
    (survey_cov), and the rows carry them for the objective to add back (:func:`nlos_row`); the
    sigma points span the whole covariance, shift included (where the user may be).
    """
    if sigma_points not in ("major", "all", "none"):
        raise ValueError(f"sigma_points must be 'major', 'all' or 'none', got {sigma_points!r}")
    mask = users_initialised(estimate) if users is None else np.asarray(users, dtype=bool)
    idx = np.flatnonzero(mask)
    d = int(estimate.cov_users_m2.shape[1])
    r = {"major": 1, "all": d, "none": 0}[sigma_points]
    bias = estimate.bias_m is not None
    p = d + int(bias)
    amb = np.asarray(estimate.ambiguous, dtype=bool) & np.all(np.isfinite(estimate.mirror_enu_m), axis=1)
    if home_enu_m is not None and np.isfinite(max_range_m):
        with np.errstate(invalid="ignore"):
            amb &= np.linalg.norm(estimate.mirror_enu_m[:, :2] - home_enu_m[:2], axis=1) <= max_range_m
    n_set = 2 * r + 1
    n_hyp = 2 if np.any(amb[idx]) else 1
    M = n_set * n_hyp
    K = len(idx)
    U = np.zeros((K, M, 3))
    W = np.zeros((K, M))
    P = np.tile(np.eye(p) * PRIOR_EPS_PER_M2, (K, M, 1, 1))
    NL = np.zeros((K, M, N_NLOS))
    for row, k in enumerate(idx):
        cov = np.asarray(estimate.cov_users_m2[k], dtype=float)
        v_f = floor_var_of(estimate, k, floor_m)
        prior_joint = joint_prior_info(estimate, k, v_f) if bias else None
        centres = [(estimate.users_enu_m[k], np.eye(d))]
        if amb[k]:
            n = np.zeros(d)
            n[:2] = (estimate.mirror_enu_m[k] - estimate.users_enu_m[k])[:2]
            n /= max(np.linalg.norm(n), 1e-9)
            centres.append((estimate.mirror_enu_m[k], np.eye(d) - 2 * np.outer(n, n)))
        share = 1.0 / len(centres)
        for h, (centre, R) in enumerate(centres):
            cov_h = R @ cov @ R.T
            s0 = h * n_set
            U[row, s0:s0 + n_set] = centre
            NL[row, s0:s0 + n_set] = nlos_row(estimate, k, R[:2, :2] if h else None, v_f)
            if bias:
                R_ext = np.eye(p)
                R_ext[:d, :d] = R
                P[row, s0:s0 + n_set] = R_ext @ prior_joint @ R_ext.T
            else:
                P[row, s0:s0 + n_set] = _info_from_cov(R @ survey_cov(estimate, k, cov, v_f) @ R.T)
            W[row, s0] = share * (kappa / (r + kappa) if r else 1.0)
            lam, vec = np.linalg.eigh(0.5 * (cov_h + cov_h.T))
            for i in range(r):
                axis = d - 1 - i  # largest eigenvalues first
                offset = np.sqrt((r + kappa) * max(lam[axis], 0.0)) * vec[:, axis]
                scale = min(1.0, max_offset_m / max(np.linalg.norm(offset), 1e-12))
                for sgn, j in ((1.0, 1 + 2 * i), (-1.0, 2 + 2 * i)):
                    U[row, s0 + j, :d] += sgn * scale * offset
                    W[row, s0 + j] = share / (2 * (r + kappa))
    w = np.ones(K) if user_weights is None else np.asarray(user_weights, dtype=float)[idx]
    scale = None if estimate.state is None else np.asarray(estimate.state.noise_scale, dtype=float)[idx]
    return Hypotheses(users_enu_m=U, sample_w=W, prior_info=P, user_w=w, index=idx, bias=bias, noise_scale=scale,
                      nlos=NL if np.any(NL[..., [5, 7]] > 0.0) else None)


def hypotheses_from_truth(
    users_enu_m: np.ndarray, estimate: Estimate | None, dim: int = 2, user_weights: np.ndarray | None = None,
    floor_m: float = 0.0,
) -> Hypotheses:
    """The oracle's single hypothesis: the true positions (K, 3), with the estimator's information
    (its marginal blocks; ε·I for users it has not initialised, or with no estimate yet; the joint
    (position, bias) information when the estimate carries range biases), without the NLoS shift
    and the GPS floor, which the rows carry (as :func:`hypotheses_from_estimate`)."""
    U = np.asarray(users_enu_m, dtype=float).reshape(-1, 3)
    K = len(U)
    bias = estimate is not None and estimate.bias_m is not None
    p = dim + int(bias)
    P = np.tile(np.eye(p) * PRIOR_EPS_PER_M2, (K, 1, 1, 1))
    NL = np.zeros((K, 1, N_NLOS))
    if estimate is not None:
        ok = users_initialised(estimate)
        for k in np.flatnonzero(ok):
            v_f = floor_var_of(estimate, int(k), floor_m)
            NL[k, 0] = nlos_row(estimate, int(k), None, v_f)
            if bias:
                P[k, 0] = joint_prior_info(estimate, int(k), v_f)
            else:
                P[k, 0] = _info_from_cov(survey_cov(estimate, int(k), np.asarray(estimate.cov_users_m2[k], dtype=float),
                                                    v_f))
    w = np.ones(K) if user_weights is None else np.asarray(user_weights, dtype=float)
    return Hypotheses(users_enu_m=U[:, None, :], sample_w=np.ones((K, 1)), prior_info=P, user_w=w,
                      index=np.arange(K), bias=bias, nlos=NL if np.any(NL[..., [5, 7]] > 0.0) else None)


def quadrature_points(start_enu_m: np.ndarray, waypoints_enu_m: np.ndarray, n_quad: int):
    """Midpoint-rule samples of a horizon of legs.

    start_enu_m: (3,); waypoints_enu_m: (C, H, 3) → points (C, H·Q, 3) at m = a + t_q (b − a),
    t_q = (q − ½)/Q for each leg a → b, and lengths (C, H) [m].
    """
    W = np.asarray(waypoints_enu_m, dtype=float)
    C, H, _ = W.shape
    a = np.concatenate([np.broadcast_to(start_enu_m, (C, 1, 3)), W[:, :-1]], axis=1)
    lengths = np.linalg.norm(W - a, axis=2)
    t = (np.arange(n_quad) + 0.5) / n_quad
    pts = a[:, :, None, :] + t[None, None, :, None] * (W - a)[:, :, None, :]
    return pts.reshape(C, H * n_quad, 3), lengths


@dataclass(frozen=True)
class PredictionModel:
    """How the objective predicts what a horizon measures: `noise`, the range and GPS noise the
    estimator assumes (σ(d), σ_gps); a range measurement every `delta_m` metres flown [m] (Δ);
    `n_quad` midpoint-rule points per leg (Q, :func:`quadrature_points`); and the cell's reach
    `coverage_m`, the slant range beyond which a UE is not heard [m] (inf: everywhere)."""

    noise: NoiseModel
    delta_m: float
    n_quad: int
    coverage_m: float = float("inf")


def predicted_information(
    start_enu_m: np.ndarray,
    waypoints_enu_m: np.ndarray,
    hyp: Hypotheses,
    model: PredictionModel,
) -> tuple[np.ndarray, np.ndarray]:
    """Posterior information after flying each candidate horizon.

    waypoints_enu_m: (C, H, 3) → info (C, K, M, p, p) [1/m²] and leg lengths (C, H) [m].
    I = P + Σ_legs (ℓ/(ΔQ)) Σ_q c(d) g gᵀ / ((s_k σ(d))² + σ_gps²)   (p = d), or with range biases
    J = P + Σ_legs (ℓ/(ΔQ)) Σ_q h hᵀ / ((s_k σ(d))² + σ_gps²),  h = [−g; 1]  (p = d + 1;
    :func:`position_information` reduces J to the position information); s_k the user's noise
    scale (hyp.noise_scale). h/σ_eff is (minus) the range factor's Jacobian on (u, b) with the
    UAV at its fix, computed by the solvers' range model (estimator.factors.range_residuals,
    range_jacobian); g differs from the unit vector of `d` only by the 1e-9 m floor of d.
    """
    noise, n_quad = model.noise, model.n_quad
    pts, lengths = quadrature_points(start_enu_m, waypoints_enu_m, n_quad)
    n_meas = np.repeat(lengths / (model.delta_m * n_quad), n_quad, axis=1)  # (C, H·Q)
    # x − u coordinates first, (3, C, K, M, HQ)
    diff = pts.transpose(2, 0, 1)[:, :, None, None, :] - hyp.users_enu_m.transpose(2, 0, 1)[:, None, :, :, None]
    # the range factor's Jacobian on θ_k = (u, [b]) at the noise-free prediction (r = 0, so α = 1/σ_eff),
    # UAV at its fix: σ_eff² = (s_k σ(d))² + σ_gps² (estimator.factors, the solvers' range model)
    scale = None if hyp.noise_scale is None else hyp.noise_scale[None, :, None, None]
    dist, sig, _, _ = range_residuals(diff, None, 0.0, noise, scale, noise.sigma_gps_m**2)
    sig = np.broadcast_to(sig, dist.shape)
    # no ranges beyond the cell's reach (planner.objective, "Coverage")
    cut = coverage_cut(dist, min(model.coverage_m, NO_COVERAGE_LIMIT_M))
    j_theta = range_jacobian(diff, dist, 1.0 / sig, sig, hyp.dim, hyp.bias)[3:]  # (p, C, K, M, HQ)
    # I = P + Σ_q n_q J_θ J_θᵀ  (J_θ = [û/σ_eff; −1/σ_eff] = −h/σ_eff)
    info = hyp.prior_info[None] + np.einsum("ckmq,ickmq,jckmq->ckmij", np.broadcast_to(
        n_meas[:, None, None, :], dist.shape) * cut, j_theta, j_theta)
    return info, lengths


def position_information(info: np.ndarray, bias: bool) -> np.ndarray:
    """(…, d, d) information of the positions alone: `info` itself without biases; with a bias last,
    the Schur complement A − c cᵀ / s of J = [[A, c], [cᵀ, s]] (the inverse of J⁻¹'s position block)."""
    if not bias:
        return info
    a, c, s = info[..., :-1, :-1], info[..., :-1, -1], info[..., -1, -1]
    return a - c[..., :, None] * c[..., None, :] / s[..., None, None]


@dataclass(frozen=True)
class Rows:
    """The hypotheses as the R = K·M rows of the objective: users (R, 3) [m], prior information
    (R, p, p), noise scale (R,), NLoS state (R, N_NLOS) and weights w_k c_ks (R,)."""

    users_enu_m: np.ndarray
    prior_info: np.ndarray
    scale: np.ndarray
    nlos: np.ndarray
    weights: np.ndarray


def hypothesis_rows(hyp: Hypotheses) -> Rows:
    """:class:`Rows` of the hypotheses."""
    K, M = hyp.sample_w.shape
    scale = np.ones(K) if hyp.noise_scale is None else np.asarray(hyp.noise_scale, dtype=float)
    nlos = np.zeros((K, M, N_NLOS)) if hyp.nlos is None else np.asarray(hyp.nlos, dtype=float)
    return Rows(hyp.users_enu_m.reshape(K * M, 3), hyp.prior_info.reshape(K * M, hyp.n_par, hyp.n_par),
                np.repeat(scale, M), nlos.reshape(K * M, N_NLOS), (hyp.user_w[:, None] * hyp.sample_w).reshape(K * M))


def noise_parameters(noise: NoiseModel, coverage_m: float = float("inf")) -> np.ndarray:
    """[s0, a, b, σ_gps², R] of the objective's range noise and the cell's reach R [m]
    (planner.objective; NO_COVERAGE_LIMIT_M when not limited)."""
    return np.array([noise.range_s0_m, noise.range_a_m, noise.range_b_per_m, noise.sigma_gps_m**2,
                     min(coverage_m, NO_COVERAGE_LIMIT_M)])


def objective_values(
    start_enu_m: np.ndarray,
    waypoints_enu_m: np.ndarray,
    hyp: Hypotheses,
    model: PredictionModel,
    criterion: str = "A",
    cost_per_m: float = 0.0,
    compiled: bool = True,
    goal: np.ndarray | None = None,
) -> np.ndarray:
    """(C,) J = Σ_k w_k Σ_s c_ks g(f(I_ks)) + λ Σ ℓ for candidate horizons (C, H, 3) (or (C, 3): H = 1):
    planner.objective's kernel evaluated, the function IPOPT minimises. goal: [f_T, w] of the
    hinge g (planner.objective.goal_expr); None: g(f) = f."""
    W = np.asarray(waypoints_enu_m, dtype=float)
    if W.ndim == 2:
        W = W[:, None, :]
    shape = Shape(hyp.dim, hyp.bias, criterion, W.shape[1], model.n_quad)
    rows = hypothesis_rows(hyp)
    f = row_values(shape, start_enu_m, W, rows.users_enu_m, rows.prior_info, rows.scale,
                   noise_parameters(model.noise, model.coverage_m), model.delta_m, rows.nlos, compiled)
    a = np.concatenate([np.broadcast_to(start_enu_m, (len(W), 1, 3)), W[:, :-1]], axis=1)
    lengths = np.sqrt(np.sum((W - a) ** 2, axis=2) + SQRT_EPS_M2)  # as the kernel's ℓ
    return goal_values(f, goal) @ rows.weights + cost_per_m * lengths.sum(axis=1)


def prior_row_values(hyp: Hypotheses, criterion: str = "A") -> np.ndarray:
    """(K·M,) f(P_ks) of every row (hypothesis_rows' order): the criterion before flying."""
    rows = hypothesis_rows(hyp)
    return prior_values(Shape(hyp.dim, hyp.bias, criterion, 1, 2), rows.prior_info, rows.nlos)


def prior_value(hyp: Hypotheses, criterion: str = "A", goal: np.ndarray | None = None) -> float:
    """Σ_k w_k Σ_s c_ks g(f(P_ks)): the objective before flying (no cost; the NLoS shift as it is;
    goal as in :func:`objective_values`)."""
    return float(goal_values(prior_row_values(hyp, criterion), goal) @ hypothesis_rows(hyp).weights)


#: grid step of the search for ground no cell has covered yet [m]
SEARCH_GRID_M = 25.0


def track_points_en_m(visited_enu_m: np.ndarray, step_m: float = 10.0) -> np.ndarray:
    """(T, 2) east-north points every ≤ step_m along a track of positions (V, 3) joined by straight legs."""
    v = np.asarray(visited_enu_m, dtype=float).reshape(-1, 3)
    pts = [v[:1, :2]]
    for a, b in itertools.pairwise(v):
        n = max(1, int(np.ceil(np.linalg.norm(b[:2] - a[:2]) / step_m)))
        pts.append(a[:2] + np.linspace(0.0, 1.0, n + 1)[1:, None] * (b[:2] - a[:2]))
    return np.concatenate(pts)


def unsearched_point(constraints, track_en_m: np.ndarray, from_en_m: np.ndarray) -> np.ndarray | None:
    """(2,) the free point (fence, no-fly zones, distance from home, on a SEARCH_GRID_M grid) nearest
    `from_en_m` (2,) [m] where a UE would not have heard the cell from anywhere on the track (T, 2)
    [m] — horizontally beyond the cell's reach at cruise altitude (PlanningConstraints.reach_m) of
    every track point — else None (the ground is covered, or the reach is not limited). A user the mission
    lists but no cell has heard is somewhere such; the nearest such ground first is the greedy
    cover (the farthest first crossed the world back and forth)."""
    from planner.geometry import in_free_space

    c = constraints
    if not np.isfinite(c.coverage_m) or len(track_en_m) == 0:
        return None
    lo = c.home_enu_m[:2] - c.max_distance_m
    hi = c.home_enu_m[:2] + c.max_distance_m
    if len(c.fence_enu_m):
        lo, hi = np.maximum(lo, c.fence_enu_m.min(axis=0)), np.minimum(hi, c.fence_enu_m.max(axis=0))
    ge = np.arange(lo[0], hi[0] + 1e-9, SEARCH_GRID_M)
    gn = np.arange(lo[1], hi[1] + 1e-9, SEARCH_GRID_M)
    grid = np.stack(np.meshgrid(ge, gn, indexing="ij"), axis=-1).reshape(-1, 2)
    grid = grid[in_free_space(grid, c) & (np.linalg.norm(grid - c.home_enu_m[:2], axis=1) <= c.max_distance_m)]
    if len(grid) == 0:
        return None
    far = np.min(np.linalg.norm(grid[:, None, :] - np.asarray(track_en_m)[None, :, :], axis=2), axis=1)
    open_ground = grid[far > c.reach_m]
    if len(open_ground) == 0:
        return None
    return open_ground[int(np.argmin(np.linalg.norm(open_ground - np.asarray(from_en_m)[:2], axis=1)))].copy()


def explore_waypoint(planner, state, visited_enu_m: np.ndarray) -> np.ndarray:
    """Where to fly while no user can be planned for: search, or spread the track out.

    With a cell of limited reach (PlanningConstraints.coverage_m), while ground remains that no
    point of the track has covered (:func:`unsearched_point`: a user never heard is there), the
    feasible ring leg ending nearest that ground.

    Among the planner's feasible ring candidates, maximise the smallest eigenvalue of the
    east-north scatter of the track (visited positions (V, 3), joined by straight legs, plus the
    candidate leg), i.e. make the track as non-collinear and wide as possible — what
    multilateration needs and what removes the mirror ambiguity of a straight line. Ties (the
    first leg) go to the leg ending nearest the fence centroid (home without a fence). Returns the
    current position when no candidate is feasible (the planner then reports "no feasible leg").
    """
    ring = planner.feasible_ring(state)
    if len(ring) == 0:
        return state.uav_enu_m.copy()
    c = planner.constraints
    target = unsearched_point(c, track_points_en_m(np.vstack([visited_enu_m.reshape(-1, 3), state.uav_enu_m])),
                              state.uav_enu_m[:2])
    if target is not None:
        return ring[int(np.argmin(np.linalg.norm(ring[:, :2] - target, axis=1)))].copy()
    t = np.linspace(0.0, 1.0, 9)[:, None]
    track = [state.uav_enu_m[None, :2]]
    for a, b in itertools.pairwise(visited_enu_m):
        track.append(a[:2] + t * (b[:2] - a[:2]))
    track = np.concatenate(track)  # (T, 2)
    legs = state.uav_enu_m[None, None, :2] + t[None] * (ring[:, None, :2] - state.uav_enu_m[None, None, :2])
    pts = np.concatenate([np.broadcast_to(track, (len(ring), *track.shape)), legs], axis=1)  # (C, T', 2)
    centred = pts - pts.mean(axis=1, keepdims=True)
    scatter = np.einsum("cti,ctj->cij", centred, centred) / pts.shape[1]
    lam_min = np.linalg.eigvalsh(scatter)[:, 0]
    centre = c.fence_enu_m.mean(axis=0) if len(c.fence_enu_m) else c.home_enu_m[:2]
    tie = np.linalg.norm(ring[:, :2] - centre, axis=1)
    score = lam_min - 1e-3 * tie
    return ring[int(np.argmax(score))].copy()
