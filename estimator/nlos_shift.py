"""The position shift that an NLoS excess on one side of a user leaves unseen.

A building blocks the line of sight from a sector of bearings around a user, so its NLoS ranges
come from one side, not at random as the mixture loss models them (estimator.robust: each range
LoS or NLoS on its own). Write the range excess as a function of the UAV's bearing β seen from the
user: ε(β) = μ_e on a sector of width 2πf around β₀ (f the share of the views it covers), 0
elsewhere. Over views all around the user its Fourier series is

    ε(β) = f μ_e + a₁ cos(β − β₀) + …,      a₁ = (2 μ_e / π) sin(π f)

and moving the user by δ along β₀ changes every range by −c |δ| cos(β − β₀) (c = |g_h| / |g|, the
horizontal share of the line of sight g, i.e. the cosine of the elevation). The first harmonic is
therefore exactly a position shift, |δ| = a₁ / c: the solve takes it for the user's position and
the residuals stay white, so neither S⁻¹ nor the jackknife (estimator.jackknife) can see it; the
mean f μ_e is the range bias's. The mixture's π_k μ (π_k its EM probability, μ the NLoS mean
excess, SolverParams.nlos_mean_m) estimates the mean excess per range f μ_e, and sin(π f) ≤ π f:

    |δ_k| ≤ 2 π_k μ / c_k

The sector's direction is unknown (the mixture labels only the tail of the excess NLoS), so the
shift is reported as an isotropic horizontal covariance, the second moment of a shift of that
length in a direction uniform on the circle:

    Σ_k ← Σ_k + ½ |δ_k|² I₂

for the users whose π_k the EM raised above its floor (NLoS seen, estimator.solve.NLOS_PROB_MIN),
c_k the mean horizontal share over the user's ranges. A user whose ranges show no NLoS keeps its
covariance (`SolverParams.nlos_shift`).

The shift shrinks with π_k, i.e. as the user is seen from bearings where its line of sight is
clear. What the planner needs to find those bearings (planner.information) is where the NLoS
ranges came from: each user's NLoS probability as a function of the UAV's bearing β and
elevation ε seen from it,

    p_k(β, ε) = 1 / (1 + exp(−(α₀ + α₁ cos β + α₂ sin β + α₃ sin ε)))

fitted to the EM's posterior NLoS probabilities 1 − γ_i of the user's ranges (estimator.solve,
Linearization.w) by weighted logistic regression with a ridge λ_α |α|² (:func:`nlos_bearing_logit`):
its first harmonic is the sector the excess comes from. The elevation term is the blocker's
height: a building of height H at horizontal distance b from the user shadows the UAV only while
tan ε < H / b, so within the sector the NLoS ranges are the low ones (far away, or flown low) and
α₃ < 0; sin ε (= Δz / |g|, bounded) stands for the angle.
"""

from __future__ import annotations

import numpy as np

from estimator.problem import Problem
from estimator.solve import NLOS_PROB_MIN
from estimator.types import nlos_shift_var_m2

#: c_k is floored here: a user seen from straight above has no horizontal lever, and the bound
#: 2 π μ / c would grow without limit (c = 0.3: elevation 73°)
NLOS_SHIFT_MIN_HORIZONTAL = 0.3


def nlos_shift_m(prob: Problem, x: np.ndarray, users_enu_m: np.ndarray, active: np.ndarray) -> np.ndarray:
    """(K,) |δ_k| = 2 π_k μ / c_k [m] of each user (module docstring); 0 where π_k is at its
    floor, the user is not active, the loss is not "nlos" or no π_k was estimated.

    x: (n, 3) the solution's keyframes [m, ENU]; users_enu_m: (K, 3) its users [m, ENU];
    active: (K,) bool."""
    k_all = prob.n_users
    out = np.zeros(k_all)
    if prob.params.loss != "nlos" or prob.nlos_prob_k is None:
        return out
    n = x.shape[0]
    pi = np.asarray(prob.nlos_prob_k, dtype=float)
    for k in np.flatnonzero(active & (pi > NLOS_PROB_MIN)):
        rows = prob.mask[:n, k]
        if not np.any(rows):
            continue
        g = x[rows] - users_enu_m[k]
        c = float(np.mean(np.linalg.norm(g[:, :2], axis=1) / np.maximum(np.linalg.norm(g, axis=1), 1e-9)))
        # |δ| = 2 π_k μ / c
        out[k] = 2.0 * pi[k] * prob.params.nlos_mean_m / max(c, NLOS_SHIFT_MIN_HORIZONTAL)
    return out


def nlos_shift_cov(shift_m: float, p: int) -> np.ndarray:
    """(p, p) ½ |δ|² (types.nlos_shift_var_m2) on the two horizontal position axes (the first two
    of θ_k), 0 elsewhere."""
    out = np.zeros((p, p))
    out[0, 0] = out[1, 1] = nlos_shift_var_m2(shift_m)
    return out


#: ridge λ_α of the bearing profile's logistic fit (a weak prior towards p(β) = ½ everywhere, which
#: keeps α finite when the user's ranges are all NLoS or all LoS)
NLOS_BEARING_RIDGE = 1.0
#: features of that fit: (1, cos β, sin β, sin ε)
N_NLOS_FEATURES = 4
#: Newton iterations of that fit (the objective is strictly convex; 8 reach 1e-8 on its gradient)
NLOS_BEARING_ITER = 8


def nlos_bearing_logit(prob: Problem, x: np.ndarray, users_enu_m: np.ndarray, los_weight: np.ndarray,
                       shift_m: np.ndarray) -> np.ndarray:
    """(K, 4) α of each user's NLoS profile p_k(β, ε) by bearing and elevation (module docstring); 0
    where the user has no shift (shift_m (K,) ≤ 0).

    x: (n, 3) keyframes [m, ENU]; users_enu_m: (K, 3) [m, ENU]; los_weight: (K, n) the EM's posterior
    LoS probability γ of each range (Linearization.w). Minimises
    −Σ_i [y_i log p_i + (1 − y_i) log(1 − p_i)] + λ_α |α|²,  y_i = 1 − γ_i,  p_i = σ(φ_iᵀ α),
    φ_i = (1, cos β_i, sin β_i, sin ε_i), by Newton's method."""
    k_all = prob.n_users
    out = np.zeros((k_all, N_NLOS_FEATURES))
    n = x.shape[0]
    for k in np.flatnonzero(np.asarray(shift_m) > 0.0):
        rows = prob.mask[:n, k]
        if not np.any(rows):
            continue
        g = x[rows] - users_enu_m[k]
        rho = np.maximum(np.linalg.norm(g[:, :2], axis=1), 1e-9)
        dist = np.maximum(np.linalg.norm(g, axis=1), 1e-9)
        # φ = (1, cos β, sin β, sin ε)
        phi = np.column_stack([np.ones(len(g)), g[:, 0] / rho, g[:, 1] / rho, g[:, 2] / dist])  # (m, 4)
        y = np.clip(1.0 - np.asarray(los_weight[k, :n][rows], dtype=float), 0.0, 1.0)
        alpha = np.zeros(N_NLOS_FEATURES)
        for _ in range(NLOS_BEARING_ITER):
            p = 1.0 / (1.0 + np.exp(-(phi @ alpha)))
            grad = phi.T @ (p - y) + 2.0 * NLOS_BEARING_RIDGE * alpha
            hess = (phi * (p * (1.0 - p))[:, None]).T @ phi + 2.0 * NLOS_BEARING_RIDGE * np.eye(N_NLOS_FEATURES)
            alpha = alpha - np.linalg.solve(hess, grad)
        out[k] = alpha
    return out
