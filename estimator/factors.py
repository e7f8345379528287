"""Factors of the SLAM cost (docs/design.md §5), one small dataclass each, plus a slow dense reference.

    L = Σ_n ||x̂_n − x_n||² / σ_gps²  +  Σ_(n,k) ρ( (r̂_nk − ||x_n − u_k|| − b_k) / σ(d_nk) )
        + Σ_k (b_k / σ_b)²  +  Σ_n ||x_n − x_(n−1) − ô_n||² / σ_m²

(each squared term carries a factor ½ in the code). Every factor returns a *whitened* error and
its analytic Jacobian; tests compare each Jacobian with central differences.

σ in the range factor is the spread at the measured range, σ(r̂), a constant of the factor:

    d = ||x − u||,  û = (x − u)/d,  r = r̂ − d − b,  e = r / σ(r̂)
    ∂e/∂d = −1/σ =: −α,   ∂e/∂x = −α û,   ∂e/∂u = +α û,   ∂e/∂b = −1/σ

σ at the estimate's distance, e = r / σ(d), has its least squares at infinity when σ grows with
d (a = 0.3 m, b = 0.01 /m: e → 0 as d → ∞, the LS cost lacks the 2 log σ(d) of the likelihood):
wide worlds sent users tens of kilometres away, σ(d) to overflow and the solves to NaN (issue 21).
σ(r̂) and σ(d) differ by σ'·(r̂ − d), a few per cent of σ at the solution (b·σ ≈ 0.05), and the
weighted least squares in d then has its minimum where the ranges put it. With a = 0 (the default
noise model) both are s0. The robust loss enters only through the IRLS weight w(e)
(estimator.robust), frozen per iteration as in GTSAM.

The vectorised solver (estimator.linearize) computes the same quantities on (N, K) arrays; the dense
reference :func:`dense_normal_equations` assembles the full normal matrix from these factor
objects one by one, so the fast Schur path can be checked against `np.linalg.solve`/`inv`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from estimator.gps import GpsFactor
from estimator.noise import NoiseModel
from estimator.problem import Problem
from estimator.robust import loss_psi_weight


@dataclass(frozen=True)
class GpsPriorFactor:
    """GPS fix on a keyframe: e = (x − x̂) / σ_gps, (3,). Never robustified."""

    gps_enu_m: np.ndarray
    sigma_m: float

    def error(self, x_enu_m: np.ndarray) -> np.ndarray:
        # e = (x − x̂) / σ_gps
        return (np.asarray(x_enu_m, float) - self.gps_enu_m) / self.sigma_m

    def jacobian(self, x_enu_m: np.ndarray) -> np.ndarray:
        """(3, 3) ∂e/∂x = I / σ_gps."""
        return np.eye(3) / self.sigma_m


@dataclass(frozen=True)
class RangeFactor:
    """Range keyframe -> user: e = (r̂ − ||x − u|| − b) / σ(r̂), a scalar (σ at the measured range).

    User parameters θ = [east, north, (up if user_dim == 3), (bias if with_bias)]; in 2-D mode the
    user's up coordinate is the known `user_up_m`. The bias enters as b·g with gain g = bias_gain
    (1; a tracked clock sawtooth's shape frac(t/P − φ), b then its amplitude):
    e = (r̂ − ||x − u|| − b g) / σ.
    """

    range_m: float
    noise: NoiseModel
    user_dim: int = 2
    user_up_m: float = 0.0
    with_bias: bool = False
    bias_gain: float = 1.0

    def _user(self, theta: np.ndarray) -> tuple[np.ndarray, float]:
        theta = np.asarray(theta, float)
        u = np.array([theta[0], theta[1], theta[2] if self.user_dim == 3 else self.user_up_m])
        b = float(theta[-1]) * self.bias_gain if self.with_bias else 0.0
        return u, b

    @property
    def sigma_m(self) -> float:
        """σ(r̂) [m], the spread at the measured range (clamped at 0 m)."""
        return float(self.noise.range_sigma_m(max(self.range_m, 0.0)))

    def error(self, x_enu_m: np.ndarray, theta: np.ndarray) -> float:
        u, b = self._user(theta)
        d = float(np.linalg.norm(np.asarray(x_enu_m, float) - u))
        # e = (r̂ − d − b) / σ(r̂)
        return (self.range_m - d - b) / self.sigma_m

    def jacobian(self, x_enu_m: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(∂e/∂x (3,), ∂e/∂θ (p,))."""
        u, _b = self._user(theta)
        diff = np.asarray(x_enu_m, float) - u
        d = max(float(np.linalg.norm(diff)), 1e-9)
        uhat = diff / d
        sig = self.sigma_m
        # α = 1/σ(r̂)
        alpha = 1.0 / sig
        j_x = -alpha * uhat
        j_theta = [alpha * uhat[: self.user_dim]]
        if self.with_bias:
            # ∂e/∂b = −g/σ
            j_theta.append([-self.bias_gain / sig])
        return j_x, np.concatenate(j_theta)


def range_residuals(
    diff_enu_m: np.ndarray, range_m: np.ndarray | None, bias_m: np.ndarray | float, noise: NoiseModel,
    scale: np.ndarray | None = None, gps_var_m2: float = 0.0, mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | float, np.ndarray, np.ndarray]:
    """The range factor's error, vectorised: the one source of the range model for the batch and
    online linearization (estimator.linearize), initialization and the mirror test (estimator.init)
    and the planner's predicted information (planner.information). RangeFactor is the same factor
    one range at a time, for the dense reference.

        d = max(||x − u||, 1e-9),  σ = √((s σ(r̂))² + σ_gps²),  r = r̂ − d − b,  e = r / σ

    (σ at the measured range r̂ ≥ 0 where there is one, at d for the noise-free prediction)

    diff_enu_m: (3, ...) x − u, coordinates first (numpy's inner loops then run over the long
        axes) [m]; range_m: (...) measured ranges r̂ [m], or None for the noise-free prediction
        (r = 0); bias_m: b (times its gain), broadcastable to (...) [m], or 0.0; scale: per-user
        noise scale s broadcastable to (...), or None (1); gps_var_m2: σ_gps² folded into the range
        variance where the UAV is held at its fix (initialization, planner), 0 where it is a
        variable of the solve; mask: (...) bool, ranges to use (r and e are 0 elsewhere), or None.
    Returns d (...) [m]; σ [m], a scalar (or s alone) when it does not depend on the range (a = 0),
    else (...); r (...) [m]; e (...).
    """
    d = np.sqrt(diff_enu_m[0] * diff_enu_m[0] + diff_enu_m[1] * diff_enu_m[1] + diff_enu_m[2] * diff_enu_m[2])
    np.maximum(d, 1e-9, out=d)
    # σ(r̂) = s0 + a·exp(b·r̂): a scalar when a = 0 (a cheaper loss evaluation); σ(d) predicted
    if noise.range_a_m == 0.0:
        sig = noise.range_s0_m
    elif range_m is None:
        sig = noise.range_sigma_m(d)
    else:
        at = np.asarray(range_m, dtype=float)
        # masked entries (NaN ranges) take d: their r and e are 0 whatever σ is
        sig = noise.range_sigma_m(np.where(np.isfinite(at), np.maximum(at, 0.0), d))
    if scale is not None:
        sig = sig * scale
    if gps_var_m2:
        # σ_eff = √(σ² + σ_gps²)
        sig = np.sqrt(sig * sig + gps_var_m2)
    if range_m is None:
        r = np.zeros_like(d)
    else:
        r = range_m - d
        if not (np.isscalar(bias_m) and bias_m == 0.0):
            r -= bias_m
        if mask is not None:
            r[~mask] = 0.0
    return d, sig, r, r / sig


def range_alpha(sig: np.ndarray | float, mask: np.ndarray | None = None) -> np.ndarray | float:
    """α = −∂e/∂d = 1/σ of the range factor (σ as returned by range_residuals: a constant of the
    factor, σ(r̂)), 0 where not mask; a scalar when σ is one and there is no mask."""
    return 1.0 / sig if mask is None else mask / sig


def range_jacobian(
    diff_enu_m: np.ndarray, d: np.ndarray, alpha: np.ndarray, sig: np.ndarray | float, user_dim: int,
    with_bias: bool, gain: np.ndarray | None = None, mask: np.ndarray | None = None,
) -> np.ndarray:
    """(3 + p, ...) [∂e/∂x; ∂e/∂θ] of the range factor, θ = [east, north, (up), (bias)], p = user_dim
    (+ 1 with_bias); shapes as in range_residuals, gain the bias's gain g (None: 1):

        ∂e/∂x = −α û,   ∂e/∂u = α û (its first user_dim coordinates),   ∂e/∂b = −g/σ
    """
    p = user_dim + (1 if with_bias else 0)
    jac = np.empty((3 + p, *d.shape))
    np.multiply(diff_enu_m, np.divide(-alpha, d), out=jac[:3])
    np.negative(jac[:user_dim], out=jac[3 : 3 + user_dim])
    if with_bias:
        np.divide(-1.0, sig, out=jac[-1])
        if gain is not None:
            jac[-1] *= gain
        if mask is not None:
            jac[-1] *= mask
    return jac


@dataclass(frozen=True)
class BiasPriorFactor:
    """Prior on a range bias: e = (b − μ_b) / σ_b (weak and zero-mean while the bias is free;
    the held prior of SolverParams.bias_held where the selection held it)."""

    sigma_m: float
    mean_m: float = 0.0

    def error(self, bias_m: float) -> float:
        return (float(bias_m) - self.mean_m) / self.sigma_m

    def jacobian(self, bias_m: float) -> float:
        return 1.0 / self.sigma_m


@dataclass(frozen=True)
class MotionFactor:
    """Relative motion between consecutive keyframes: e = (x_n − x_(n−1) − ô_n) / σ_m, (3,)."""

    odom_enu_m: np.ndarray
    sigma_m: float

    def error(self, x_prev_enu_m: np.ndarray, x_enu_m: np.ndarray) -> np.ndarray:
        # e = (x_n − x_(n−1) − ô_n) / σ_m
        return (np.asarray(x_enu_m, float) - np.asarray(x_prev_enu_m, float) - self.odom_enu_m) / self.sigma_m

    def jacobian(self, x_prev_enu_m: np.ndarray, x_enu_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(∂e/∂x_(n−1), ∂e/∂x_n) = (−I/σ_m, I/σ_m)."""
        return -np.eye(3) / self.sigma_m, np.eye(3) / self.sigma_m


def dense_normal_equations(
    prob: Problem, uav_enu_m: np.ndarray, theta: np.ndarray, active: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Slow, obvious reference: full normal matrix over z = [x_1..x_N, θ_active...].

    Returns (H (D, D), g (D,), cost) with H = Σ Jᵀ W J and g = −Σ Jᵀ W e, where W holds the IRLS
    weight of each range factor (1 for the others), and cost = Σ ρ(e) + ½ Σ ||e||² (non-range).
    Loops over factor objects; for tests and small problems only.
    """
    n, k_all = prob.range_m.shape
    p = prob.p
    params, noise = prob.params, prob.noise
    users = [k for k in range(k_all) if active[k]]
    col = {k: 3 * n + i * p for i, k in enumerate(users)}
    dim = 3 * n + p * len(users)
    h = np.zeros((dim, dim))
    g = np.zeros(dim)
    cost = 0.0

    def add(rows: list[tuple[int, np.ndarray]], e: np.ndarray, w: float) -> None:
        # stacked row block: J = [J_1 | J_2 | ...] at the given columns; H += w JᵀJ, g −= w Jᵀe
        for c1, j1 in rows:
            g[c1 : c1 + j1.shape[1]] -= w * j1.T @ e
            for c2, j2 in rows:
                h[c1 : c1 + j1.shape[1], c2 : c2 + j2.shape[1]] += w * j1.T @ j2

    phi = prob.gps_phi() if prob.gps_linked else np.zeros(n)
    # σ_m,n of each keyframe's motion factor (Problem.odom_weight: 0 where none)
    wm = prob.odom_weight() if prob.use_motion else np.zeros(n)
    scale = np.ones(k_all) if prob.noise_scale_k is None else prob.noise_scale_k
    for i in range(n):
        if i > 0 or prob.gps_first or not prob.gps_linked:
            gf = GpsFactor(prob.gps_enu_m[i], noise.sigma_gps_m, float(phi[i]),
                           prob.gps_enu_m[i - 1] if i > 0 else None)
            e = gf.error(uav_enu_m[i], uav_enu_m[i - 1] if i > 0 else None)
            cost += 0.5 * float(e @ e)
            jx, jprev = gf.jacobian()
            add([(3 * i, jx)] + ([(3 * (i - 1), jprev)] if phi[i] != 0.0 else []), e, 1.0)
        if wm[i] > 0:
            m = MotionFactor(prob.odom_enu_m[i], float(1.0 / np.sqrt(wm[i])))
            e = m.error(uav_enu_m[i - 1], uav_enu_m[i])
            j0, j1 = m.jacobian(uav_enu_m[i - 1], uav_enu_m[i])
            cost += 0.5 * float(e @ e)
            add([(3 * (i - 1), j0), (3 * i, j1)], e, 1.0)
        for k in users:
            if not prob.mask[i, k]:
                continue
            # σ_k(d) = s_k σ(d): the same model with s0 and a scaled by s_k
            nk = replace(noise, range_s0_m=noise.range_s0_m * scale[k], range_a_m=noise.range_a_m * scale[k])
            gain = 1.0 if prob.bias_gain is None else float(prob.bias_gain[i, k])
            f = RangeFactor(prob.range_m[i, k], nk, prob.user_dim, prob.user_up_m[k], params.estimate_bias, gain)
            e = f.error(uav_enu_m[i], theta[k])
            jx, jt = f.jacobian(uav_enu_m[i], theta[k])
            sig = f.sigma_m
            pi = params.nlos_prob if prob.nlos_prob_k is None else float(prob.nlos_prob_k[k])
            rho, psi, w = loss_psi_weight(np.array([e]), params.loss, params.loss_scale, (pi, params.nlos_mean_m / sig))
            cost += float(rho[0])
            # H += w JᵀJ, g −= ψ J: pass e' = ψ/w so that add's w·e' = ψ (w > 0 for every loss
            # except Tukey beyond c, where ψ = 0 too)
            add([(3 * i, jx[None, :]), (col[k], jt[None, :])], np.array([psi[0] / w[0] if w[0] > 0 else 0.0]),
                float(w[0]))
    if params.estimate_bias:
        for k in users:
            f = BiasPriorFactor(params.bias_prior_sigma_m if prob.bias_sigma_k is None
                                else float(prob.bias_sigma_k[k]),
                                0.0 if prob.bias_mean_k is None else float(prob.bias_mean_k[k]))
            e = f.error(theta[k, -1])
            cost += 0.5 * e * e
            jb = np.zeros((1, p))
            jb[0, -1] = f.jacobian(theta[k, -1])
            add([(col[k], jb)], np.array([e]), 1.0)
    return h, g, cost
