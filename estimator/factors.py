"""Factors of the SLAM cost (DESIGN.md §5), one small dataclass each, plus a slow dense reference.

    L = Σ_n ||x̂_n − x_n||² / σ_gps²  +  Σ_(n,k) ρ( (r̂_nk − ||x_n − u_k|| − b_k) / σ(d_nk) )
        + Σ_k (b_k / σ_b)²  +  Σ_n ||x_n − x_(n−1) − ô_n||² / σ_m²

(each squared term carries a factor ½ in the code). Every factor returns a *whitened* error and
its analytic Jacobian; tests compare each Jacobian with central differences.

σ(d) in the range factor: the solver minimises Σ ρ(e) with e = r / σ(d) exactly as written, so the
Jacobian differentiates *through* σ(d) (not IRLS-style with σ frozen per iteration):

    d = ||x − u||,  û = (x − u)/d,  r = r̂ − d − b,  e = r / σ(d)
    ∂e/∂d = −(1/σ + r σ'(d)/σ²) =: −α
    ∂e/∂x = −α û,   ∂e/∂u = +α û,   ∂e/∂b = −1/σ

With a = 0 (the default noise model) σ' = 0 and α = 1/σ. The robust loss enters only through the
IRLS weight w(e) (estimator.robust), which *is* frozen per iteration as in GTSAM.

The vectorised solver (estimator.slam) computes the same quantities on (N, K) arrays; the dense
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
    """Range keyframe -> user: e = (r̂ − ||x − u|| − b) / σ(||x − u||), a scalar.

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

    def error(self, x_enu_m: np.ndarray, theta: np.ndarray) -> float:
        u, b = self._user(theta)
        d = float(np.linalg.norm(np.asarray(x_enu_m, float) - u))
        # e = (r̂ − d − b) / σ(d)
        return (self.range_m - d - b) / float(self.noise.range_sigma_m(d))

    def jacobian(self, x_enu_m: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(∂e/∂x (3,), ∂e/∂θ (p,))."""
        u, b = self._user(theta)
        diff = np.asarray(x_enu_m, float) - u
        d = max(float(np.linalg.norm(diff)), 1e-9)
        uhat = diff / d
        sig = float(self.noise.range_sigma_m(d))
        dsig = float(self.noise.range_sigma_dd(d))
        r = self.range_m - d - b
        # α = 1/σ + r σ'/σ²
        alpha = 1.0 / sig + r * dsig / sig**2
        j_x = -alpha * uhat
        j_theta = [alpha * uhat[: self.user_dim]]
        if self.with_bias:
            # ∂e/∂b = −g/σ
            j_theta.append([-self.bias_gain / sig])
        return j_x, np.concatenate(j_theta)


@dataclass(frozen=True)
class BiasPriorFactor:
    """Weak zero-mean prior on a range bias: e = b / σ_b."""

    sigma_m: float

    def error(self, bias_m: float) -> float:
        return float(bias_m) / self.sigma_m

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
            nk = replace(noise, s0_m=noise.s0_m * scale[k], a_m=noise.a_m * scale[k])
            gain = 1.0 if prob.bias_gain is None else float(prob.bias_gain[i, k])
            f = RangeFactor(prob.range_m[i, k], nk, prob.user_dim, prob.user_up_m[k], params.estimate_bias, gain)
            e = f.error(uav_enu_m[i], theta[k])
            jx, jt = f.jacobian(uav_enu_m[i], theta[k])
            sig = float(nk.range_sigma_m(np.linalg.norm(uav_enu_m[i] - f._user(theta[k])[0])))
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
                                else float(prob.bias_sigma_k[k]))
            e = f.error(theta[k, -1])
            cost += 0.5 * e * e
            jb = np.zeros((1, p))
            jb[0, -1] = f.jacobian(theta[k, -1])
            add([(col[k], jb)], np.array([e]), 1.0)
    return h, g, cost
