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
