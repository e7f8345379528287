"""Initialization of users and the mirror-ambiguity test (docs/design.md §5).

Both work on one user at a time with the UAV held at its GPS fixes. The GPS error of a keyframe
projects onto the range direction, so its variance is folded into the range variance (the UAV
positions are marginalized to first order):

    σ_eff(d)² = σ(d)² + σ_gps²,     e_i = (r̂_i − ||x̂_i − u|| − b) / σ_eff(d_i)

Initialization (not by luck): first the closed-form least-squares multilateration (ranges squared
less their mean are linear in the user's position), kept when the fixes spread in two dimensions
and it fits the ranges the way a true position fits clean ones (mean truncated quadratic cost, see
`init_users`). Otherwise a search: the user lies within the horizontal range ρ_i = √(r̂_i² − Δz_i²)
of every UAV fix, which bounds a search box; a G×G grid over it is scored with a truncated
quadratic (so NLoS outliers cannot drag the start), the best few local minima of the grid are
refined on a finer grid around each, and the lowest cost wins. Either start then takes two
Gauss–Newton steps on the truncated quadratic, and the joint solver polishes it. Users ranged from
the same fixes are initialised in one pass (`init_users`), and so are their mirror tests
(`mirror_tests`).

Mirror test: ranges from a straight flight line cannot tell a user from its reflection across the
line. Fit the line to the user's UAV fixes (principal axis of the horizontal positions), reflect
the estimate and refine from there to the mirror solution m. Two numbers:

    separation  χ²_sep = Σ_i ((||x̃_i − u|| − ||x̃_i − u'||) / σ_eff)²  (u' the exact reflection
                of u) on the fixes smoothed along
                the track (moving average of 2·SMOOTH_HALF + 1), i.e. how far apart the two
                hypotheses' noise-free ranges are for the path flown;
    likelihood  Δχ² = 2 (L(m) − L(u)) on the measured ranges.

    ambiguous  ⇔  χ²_sep < χ²_amb   (and m is not u itself)

The likelihood ratio alone is not a usable test: on an exactly straight line the range noise
correlates with the GPS noise across the line, so Δχ² fluctuates around zero with a spread that
grows like √N (±15 at N = 100) although the geometry cannot tell the two apart. The smoothed-
track separation of the exact reflection stays around 1 for a straight line and is in the
hundreds or more for a circle or a lawnmower. The solver jumps to the mirror when the geometry separates the two
(χ²_sep ≥ χ²_amb) and the mirror fits better by more than χ²_amb.

With a cell of limited reach (SolverParams.coverage_m) the keyframes that did not range a user
can refute one of the two hypotheses (estimator.silence, applied by estimator.batch.mirror_all).
"""

from __future__ import annotations

import contextlib
import functools
import math
from dataclasses import dataclass

import numpy as np

from estimator.factors import range_jacobian, range_residuals
from estimator.noise import NoiseModel
from estimator.robust import loss_psi_weight, loss_rho, nlos_args
from estimator.types import SolverParams

#: grid points per axis of the initialization search
GRID_SIZE = 19
#: at most this many ranges enter the grid scoring (evenly subsampled)
GRID_MAX_RANGES = 40
#: robust threshold (whitened) used to score the grid and the first refinement
GRID_CAUCHY_SCALE = 2.0
#: the closed-form start needs fixes spread at least this much across their main axis (s2/s1) ...
LINEAR_INIT_MIN_SPREAD = 0.25
#: ... and must fit with a mean truncated cost min(e², GRID_CAUCHY_SCALE²) at most this, else grid
LINEAR_INIT_MAX_COST = 1.5
#: at most this many ranges (evenly subsampled) enter the refinement of the start
REFINE_MAX_RANGES = 400
#: half-width (in fixes) of the moving average that smooths GPS noise out of the track
SMOOTH_HALF = 10
#: a user's refinement (refine_user, refine_users) stops after a step of under 1 mm, or after a
#: whole (not halved) Gauss–Newton step that lowered its cost Σρ by less than this: the steps after
#: it lower it by less again (χ² = 2 Σρ moves by under 1e-3: the mirror test's Δχ² is compared
#: with thresholds of several units, and a solve refines every start further)
REFINE_COST_TOL = 5e-4


@dataclass(frozen=True)
class UserFit:
    """One user's fit with the UAV at its GPS fixes: theta = [e, n, (up), (bias)], cost = Σρ + prior."""

    theta: np.ndarray
    cost: float


def _sigma_eff(noise: NoiseModel, d: np.ndarray) -> np.ndarray | float:
    # σ_eff = √(σ(d)² + σ_gps²)
    if noise.range_a_m == 0.0:
        return float(np.sqrt(noise.range_s0_m**2 + noise.sigma_gps_m**2))
    return np.sqrt(noise.range_sigma_m(d) ** 2 + noise.sigma_gps_m**2)


def _theta_to_user(theta: np.ndarray, user_dim: int, up_m: float) -> tuple[np.ndarray, float]:
    u = np.array([theta[0], theta[1], theta[2] if user_dim == 3 else up_m])
    b = float(theta[user_dim]) if theta.shape[0] > user_dim else 0.0
    return u, b


def user_cost(
    uav_enu_m: np.ndarray, range_m: np.ndarray, theta: np.ndarray, up_m: float, noise: NoiseModel,
    params: SolverParams, loss: str | None = None, scale: float | None = None,
) -> float:
    """Cost of one user: Σ ρ(e_i) (+ ½(b/σ_b)²). uav (M, 3) [m], range (M,) [m], theta (p,)."""
    loss = params.loss if loss is None else loss
    scale = params.loss_scale if scale is None else scale
    u, b = _theta_to_user(theta, params.user_dim, up_m)
    # e = (r̂ − d − b) / σ_eff(d): the range factor with the UAV at its fix (estimator.factors)
    _, sig, _, e = range_residuals((uav_enu_m - u).T, range_m, b, noise, gps_var_m2=noise.sigma_gps_m**2)
    cost = float(np.sum(loss_rho(e, loss, scale, nlos_args(params, sig))))
    if params.estimate_bias:
        cost += 0.5 * (b / params.bias_prior_sigma_m) ** 2
    return cost


def refine_user(
    uav_enu_m: np.ndarray, range_m: np.ndarray, theta0: np.ndarray, up_m: float, noise: NoiseModel,
    params: SolverParams, iterations: int = 25, loss: str | None = None, scale: float | None = None,
    stop_near: np.ndarray | None = None, near_m: float = 0.0,
) -> UserFit:
    """Robust Gauss–Newton (with step halving) on one user, UAV fixed. Shapes as in `user_cost`.

    σ_eff is the range factor's, at the measured ranges (estimator.factors). stop_near (2,): stop
    as soon as an iterate is within near_m of this horizontal point (the mirror test's refinement
    of a reflection that walks back to the estimate: its outcome is known then).
    """
    loss = params.loss if loss is None else loss
    scale = params.loss_scale if scale is None else scale
    d_u = params.user_dim
    theta = np.array(theta0, dtype=float)
    cost = user_cost(uav_enu_m, range_m, theta, up_m, noise, params, loss, scale)
    gps_var = noise.sigma_gps_m**2
    for _ in range(iterations):
        u, b = _theta_to_user(theta, d_u, up_m)
        diff = (uav_enu_m - u).T
        # the range factor with the UAV at its fix (estimator.factors), σ_eff held fixed in the
        # Jacobian (α = 1/σ_eff): ∂e/∂u = û/σ, ∂e/∂b = −1/σ
        d, sig, _, e = range_residuals(diff, range_m, b, noise, gps_var_m2=gps_var)
        sig = np.broadcast_to(sig, d.shape)
        _, psi, w = loss_psi_weight(e, loss, scale, nlos_args(params, sig), need_rho=False)
        j = range_jacobian(diff, d, 1.0 / sig, sig, d_u, params.estimate_bias)[3:].T
        h = (j * w[:, None]).T @ j
        g = -j.T @ psi
        if params.estimate_bias:
            h[-1, -1] += 1.0 / params.bias_prior_sigma_m**2
            g[-1] -= b / params.bias_prior_sigma_m**2
        h[np.diag_indices_from(h)] += 1e-9 * (1.0 + np.diag(h))
        try:
            step = np.linalg.solve(h, g)
        except np.linalg.LinAlgError:
            break
        whole = True  # the whole Gauss–Newton step accepted (REFINE_COST_TOL)
        for _half in range(8):
            trial = theta + step
            # a wild first step (near-singular h) may reach absurd distances: its cost is then
            # huge, inf or NaN, rejected below, and the step halved
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                c = user_cost(uav_enu_m, range_m, trial, up_m, noise, params, loss, scale)
            if c <= cost:
                break
            step *= 0.5
            whole = False
        else:
            break
        gain = cost - c
        theta, cost = trial, c
        if np.max(np.abs(step)) < 1e-3 or (whole and gain < REFINE_COST_TOL):
            break
        if stop_near is not None and np.linalg.norm(theta[:2] - stop_near) < near_m:
            break
    return UserFit(theta, cost)


def users_cost(
    uav_enu_m: np.ndarray, range_m: np.ndarray, theta: np.ndarray, up_m: np.ndarray, noise: NoiseModel,
    params: SolverParams, loss: str | None = None, scale: float | None = None,
) -> np.ndarray:
    """`user_cost` of K users ranged from the same fixes, at once: (K,).

    uav_enu_m: (M, 3) [m]; range_m: (M, K) [m]; theta: (K, p); up_m: (K,) [m].
    """
    loss = params.loss if loss is None else loss
    scale = params.loss_scale if scale is None else scale
    d_u = params.user_dim
    pos = np.empty((theta.shape[0], 3))
    pos[:, :2] = theta[:, :2]
    pos[:, 2] = theta[:, 2] if d_u == 3 else up_m
    b = theta[:, d_u][:, None] if theta.shape[1] > d_u else 0.0
    diff = uav_enu_m.T[:, None, :] - pos.T[:, :, None]  # (3, K, M)
    _, sig, _, e = range_residuals(diff, range_m.T, b, noise, gps_var_m2=noise.sigma_gps_m**2)
    cost = np.sum(loss_rho(e, loss, scale, nlos_args(params, sig)), axis=1)
    if params.estimate_bias:
        cost = cost + 0.5 * (theta[:, d_u] / params.bias_prior_sigma_m) ** 2
    return cost


def refine_users(
    uav_enu_m: np.ndarray, range_m: np.ndarray, theta0: np.ndarray, up_m: np.ndarray, noise: NoiseModel,
    params: SolverParams, iterations: int = 25, loss: str | None = None, scale: float | None = None,
    stop_near: np.ndarray | None = None, near_m: float = 0.0,
) -> list[UserFit]:
    """`refine_user` of K users ranged from the same fixes, at once (the same iterations, step
    halving and stopping rules per user; tests check it against refine_user).

    uav_enu_m: (M, 3) [m]; range_m: (M, K) [m]; theta0: (K, p); up_m: (K,) [m]; stop_near:
    (K, 2) or None (refine_user). Returns K UserFit.
    """
    loss = params.loss if loss is None else loss
    scale = params.loss_scale if scale is None else scale
    d_u = params.user_dim
    up = np.asarray(up_m, dtype=float)
    theta = np.array(theta0, dtype=float)
    cost = users_cost(uav_enu_m, range_m, theta, up, noise, params, loss, scale)
    gps_var = noise.sigma_gps_m**2
    inv_b2 = 1.0 / params.bias_prior_sigma_m**2
    live = np.ones(theta.shape[0], dtype=bool)
    for _ in range(iterations):
        idx = np.flatnonzero(live)
        if idx.size == 0:
            break
        th = theta[idx]
        pos = np.empty((idx.size, 3))
        pos[:, :2] = th[:, :2]
        pos[:, 2] = th[:, 2] if d_u == 3 else up[idx]
        b = th[:, d_u][:, None] if params.estimate_bias else 0.0
        diff = uav_enu_m.T[:, None, :] - pos.T[:, :, None]  # (3, k, M)
        # as refine_user: the range factor with the UAV at its fix, σ_eff fixed in the Jacobian
        d, sig, _, e = range_residuals(diff, range_m[:, idx].T, b, noise, gps_var_m2=gps_var)
        sig = np.broadcast_to(sig, d.shape)
        _, psi, w = loss_psi_weight(e, loss, scale, nlos_args(params, sig), need_rho=False)
        j = range_jacobian(diff, d, 1.0 / sig, sig, d_u, params.estimate_bias)[3:]  # (p, k, M)
        h = np.einsum("akm,bkm->kab", j * w, j)
        g = -np.einsum("akm,km->ka", j, psi)
        if params.estimate_bias:
            h[:, -1, -1] += inv_b2
            g[:, -1] -= th[:, d_u] * inv_b2
        dg = np.einsum("kaa->ka", h)
        dg += 1e-9 * (1.0 + dg)
        step = np.full_like(g, np.nan)
        try:
            step = np.linalg.solve(h, g[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            for i in range(idx.size):
                with contextlib.suppress(np.linalg.LinAlgError):
                    step[i] = np.linalg.solve(h[i], g[i])
        # users whose system is singular stop (refine_user breaks)
        ok = np.all(np.isfinite(step), axis=1)
        live[idx[~ok]] = False
        idx, th, step = idx[ok], th[ok], step[ok]
        # step halving per user: the first of the steps 2^-h (h = 0..7) whose cost does not rise;
        # the full steps first, then the 7 halvings of the users that need them in one pass
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            new_cost = users_cost(uav_enu_m, range_m[:, idx], th + step, up[idx], noise, params, loss, scale)
        pending = ~(new_cost <= cost[idx])
        whole = ~pending  # the whole step accepted (REFINE_COST_TOL)
        sel = np.flatnonzero(pending)
        if sel.size:
            halves = 0.5 ** np.arange(1, 8)
            cand = th[sel][:, None, :] + halves[None, :, None] * step[sel][:, None, :]  # (s, 7, p)
            reps = np.repeat(idx[sel], halves.size)
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                c = users_cost(uav_enu_m, range_m[:, reps], cand.reshape(-1, th.shape[1]), up[reps], noise, params,
                               loss, scale).reshape(sel.size, halves.size)
            ok = c <= cost[idx[sel]][:, None]
            first = np.argmax(ok, axis=1)
            found = ok[np.arange(sel.size), first]
            rows = sel[found]
            step[rows] *= halves[first[found]][:, None]
            new_cost[rows] = c[found, first[found]]
            pending[rows] = False
        # no acceptable step: the user stops where it is
        live[idx[pending]] = False
        acc = ~pending
        ia = idx[acc]
        theta[ia] = th[acc] + step[acc]
        gain = cost[ia] - new_cost[acc]
        cost[ia] = new_cost[acc]
        done = (np.max(np.abs(step[acc]), axis=1) < 1e-3) | (whole[acc] & (gain < REFINE_COST_TOL))
        if stop_near is not None:
            done |= np.linalg.norm(theta[ia, :2] - stop_near[ia], axis=1) < near_m
        live[ia[done]] = False
    return [UserFit(theta[k].copy(), float(cost[k])) for k in range(theta.shape[0])]


def _grid_cost(uav: np.ndarray, rng: np.ndarray, dz: np.ndarray, cand: np.ndarray, noise: NoiseModel) -> np.ndarray:
    """(K, G) truncated-quadratic cost Σ_i min(e_i², c²) of each user's horizontal candidates.

    uav: (M, 3) fixes; rng: (K, M) ranges; dz: (K, M) fix height above the user; cand: (K, G, 2).
    The (K, G, M) passes dominate the cost, so there are few of them, all in place.
    """
    k_n, g_n, _ = cand.shape
    m_n = uav.shape[0]
    # single precision: the passes run twice as fast, and distances of a few hundred metres keep
    # errors below 0.1 mm, far inside a grid cell
    f4 = np.float32
    # d_kgi² = ||c_kg||² − 2 c_kg·h_i + ||h_i||² + dz_ki²  (h the fixes' horizontal position), one
    # matrix product: [e, n, 1, ||c||²] · [−2 h_e; −2 h_n; ||h||² + dz²; 1]; relative to the mean
    # fix, so that the terms stay small
    h0 = uav[:, :2].mean(axis=0)
    ce = cand - h0
    he = uav[:, :2] - h0
    a = np.empty((k_n, g_n, 4), dtype=f4)
    a[:, :, :2] = ce
    a[:, :, 2] = 1.0
    a[:, :, 3] = np.einsum("kgi,kgi->kg", ce, ce)
    b = np.empty((k_n, 4, m_n), dtype=f4)
    b[:, 0] = -2.0 * he[:, 0]
    b[:, 1] = -2.0 * he[:, 1]
    b[:, 2] = (he[:, 0] ** 2 + he[:, 1] ** 2)[None, :] + dz * dz
    b[:, 3] = 1.0
    d = np.matmul(a, b)
    # rounding leaves d² slightly negative only where a fix is (nearly) at a candidate, i.e. where
    # the height difference is below the rounding error of the sum (a pass spared otherwise)
    # (|terms| ≤ (||c|| + √(||h||² + dz²))², each rounded to a few eps)
    terms = (math.sqrt(float(np.max(a[:, :, 3]))) + math.sqrt(float(np.max(b[:, 2])))) ** 2
    if float(np.min(np.abs(dz))) ** 2 <= 8.0 * float(np.finfo(f4).eps) * terms:
        np.maximum(d, 0.0, out=d)
    np.sqrt(d, out=d)
    c2 = GRID_CAUCHY_SCALE**2
    ones = np.ones(m_n, dtype=f4)
    if noise.range_a_m == 0.0:
        # constant σ_eff: min(((r − d)/σ)², c²) = min((r − d)², (cσ)²)/σ²
        sig = float(_sigma_eff(noise, d))
        d -= rng.astype(f4)[:, None, :]
        d *= d
        np.minimum(d, f4(c2 * sig * sig), out=d)
        return (d @ ones).astype(float) / (sig * sig)
    # e = (r̂ − d)/σ_eff(r̂) (the range factor's σ at the measured range);  Σ min(e², c²)
    sig = _sigma_eff(noise, np.maximum(rng, 0.0)).astype(f4)
    d -= rng.astype(f4)[:, None, :]
    d /= sig[:, None, :]
    d *= d
    np.minimum(d, f4(c2), out=d)
    return (d @ ones).astype(float)


#: 0..1 in GRID_SIZE steps, and the 7×7 zoom offsets in coarse cells, (49, 2)
_GRID_FRAC = np.linspace(0.0, 1.0, GRID_SIZE)
_ZOOM_OFF = np.stack(np.meshgrid(np.linspace(-1.0, 1.0, 7), np.linspace(-1.0, 1.0, 7), indexing="ij"),
                     axis=-1).reshape(-1, 2)
#: offsets of the 8 neighbours of a grid cell
_NEIGHBOURS = [(de, dn) for de in (-1, 0, 1) for dn in (-1, 0, 1) if de or dn]


def _search_box(
    uav: np.ndarray, rng: np.ndarray, up_m: np.ndarray, noise: NoiseModel, sig: np.ndarray | float | None = None,
    exact: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Where each of K users can be: (lo, hi) corners (K, 2) [m, ENU] of the box.

    The user lies within the horizontal range ρ_i = √(r̂_i² − Δz_i²) (+ 4 σ_eff + 2 m) of every
    fix: the intersection of those boxes, or their union where they do not intersect (outliers).
    exact: the reach at a range 4 σ_eff longer instead, √((r̂_i + 4 σ_eff)² − Δz_i²) + 2 m. A range
    error grows the horizontal distance by r/ρ times itself, so the first box can leave out the
    truth of a user the UAV passed nearly overhead (9 of 20 users on the benchmark's N = 200
    circle); the grid search keeps it (its cells are sized on it), the linear start's check
    uses the exact one.
    uav: (M, 3); rng: (K, M); up_m: (K,); sig: σ_eff(r̂) when already at hand.
    """
    dz = uav[None, :, 2] - up_m[:, None]
    margin = 4.0 * (_sigma_eff(noise, rng) if sig is None else sig)
    if exact:
        r_far = rng + margin
        reach = np.sqrt(np.maximum(r_far * r_far - dz * dz, 0.0)) + 2.0  # (K, M)
    else:
        reach = np.sqrt(np.maximum(rng**2 - dz**2, 0.0)) + margin + 2.0
    # per coordinate c: lo_c = max_i (h_i,c − reach_i), hi_c = min_i (h_i,c + reach_i), (K, M) each
    lo, hi = np.empty((rng.shape[0], 2)), np.empty((rng.shape[0], 2))
    below = [uav[:, c] - reach for c in (0, 1)]
    above = [uav[:, c] + reach for c in (0, 1)]
    for c in (0, 1):
        lo[:, c] = below[c].max(axis=1)
        hi[:, c] = above[c].min(axis=1)
    empty = ~(hi > lo).all(axis=1)
    if empty.any():
        for c in (0, 1):
            lo[empty, c] = below[c][empty].min(axis=1)
            hi[empty, c] = above[c][empty].max(axis=1)
    return lo, hi


def _grid_starts(
    uav: np.ndarray, rng: np.ndarray, up_m: np.ndarray, noise: NoiseModel, n_best: int
) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal starts of K users ranged from the same fixes: the best local minima of a coarse
    grid, each refined on a finer grid around it (cell/3 resolution).

    uav: (M, 3); rng: (K, M); up_m: (K,). Returns starts (K, n_best, 2) and their grid costs
    (K, n_best), inf where a user's grid has fewer than n_best local minima.
    """
    k_n = rng.shape[0]
    dz = uav[None, :, 2] - up_m[:, None]
    lo, hi = _search_box(uav, rng, up_m, noise)
    g = GRID_SIZE
    ge = lo[:, 0:1] + (hi[:, 0:1] - lo[:, 0:1]) * _GRID_FRAC
    gn = lo[:, 1:2] + (hi[:, 1:2] - lo[:, 1:2]) * _GRID_FRAC
    cand = np.empty((k_n, g, g, 2))
    cand[..., 0] = ge[:, :, None]
    cand[..., 1] = gn[:, None, :]
    cand = cand.reshape(k_n, g * g, 2)
    cost = _grid_cost(uav, rng, dz, cand, noise).reshape(k_n, g, g)
    padded = np.full((k_n, g + 2, g + 2), np.inf)
    padded[:, 1:-1, 1:-1] = cost
    is_min = np.ones_like(cost, dtype=bool)
    for de, dn in _NEIGHBOURS:
        is_min &= cost <= padded[:, 1 + de : 1 + de + g, 1 + dn : 1 + dn + g]
    # each user's n_best lowest local minima (non-minima sort last, as inf)
    ranked = np.where(is_min, cost, np.inf).reshape(k_n, g * g)
    idx = np.argsort(ranked, axis=1, kind="stable")[:, :n_best]
    users = np.arange(k_n)[:, None]
    valid = np.isfinite(ranked[users, idx])
    # zoom: a 7×7 grid spanning ±1 coarse cell around each start
    cell = np.empty((k_n, 1, 1, 2))
    cell[:, 0, 0, 0] = ge[:, 1] - ge[:, 0]
    cell[:, 0, 0, 1] = gn[:, 1] - gn[:, 0]
    fine = cand[users, idx][:, :, None, :] + _ZOOM_OFF * cell  # (K, n_best, 49, 2)
    fcost = _grid_cost(uav, rng, dz, fine.reshape(k_n, -1, 2), noise).reshape(k_n, n_best, -1)
    best = np.argmin(fcost, axis=2)
    starts = np.arange(n_best)[None, :]
    out_cost = fcost[users, starts, best]
    out_cost[~valid] = np.inf
    return fine[users, starts, best], out_cost


@functools.lru_cache(maxsize=64)
def _grid_subset(m: int, most: int = GRID_MAX_RANGES) -> slice | np.ndarray:
    """Indices of at most `most` of m ranges, evenly spread (by default those that score the grid)."""
    if m <= most:
        return slice(None)
    sub = np.unique(np.linspace(0, m - 1, most).round().astype(int))
    sub.flags.writeable = False  # shared between calls
    return sub


def _truncated_terms(
    uav: np.ndarray, rng: np.ndarray, up_m: np.ndarray, u: np.ndarray, noise: NoiseModel,
    sig: np.ndarray | float | None = None,
) -> tuple:
    """Truncated quadratic of K users at horizontal positions u (K, 2) from fixes uav (M, 3) with
    ranges rng (K, M): (Σ_i min(e_i², c²) (K,), u − h east and north (K, M), d (K, M),
    e = (r̂ − d)/σ_eff(r̂) (K, M), w = [|e| ≤ c] (K, M)). sig: σ_eff(r̂) when already at hand."""
    c2 = GRID_CAUCHY_SCALE**2
    de = u[:, 0:1] - uav[:, 0]
    dn = u[:, 1:2] - uav[:, 1]
    d = np.sqrt(de * de + dn * dn + (uav[None, :, 2] - up_m[:, None]) ** 2)
    # σ_eff at the measured range, not at d: a far-off position must not buy small whitened
    # residuals with the larger σ(d) of its larger distances
    if sig is None:
        sig = _sigma_eff(noise, rng)
    e = (rng - d) / sig
    e2 = e * e
    return np.minimum(e2, c2).sum(axis=1), de, dn, d, e, (e2 <= c2).astype(float)


def _refine_starts(
    uav: np.ndarray, rng: np.ndarray, up_m: np.ndarray, start: np.ndarray, noise: NoiseModel, iterations: int = 2,
    terms: tuple | None = None, sig: np.ndarray | float | None = None,
) -> np.ndarray:
    """Gauss–Newton on the truncated quadratic Σ_i min(e_i², c²) of each of K users from the same
    fixes, UAV held at the fixes (ranges beyond c get no weight); a user's step is kept only
    where it lowers that cost.

    uav: (M, 3); rng: (K, M); up_m: (K,); start: (K, 2); terms: `_truncated_terms` at start and
    sig: σ_eff(rng), when already at hand. Returns (K, 2) [m, ENU].

    e_i = (r_i − d_i)/σ_eff(r_i),  ∂e_i/∂u = −(u − h_i)/(d_i σ_eff(r_i)),
    Δu = −(Σ w jjᵀ)⁻¹ Σ w j e,  w_i = [|e_i| ≤ c].
    """
    u = start.copy()
    if sig is None:
        sig = _sigma_eff(noise, rng)  # fixed: it depends on the measured ranges only
    cost, de, dn, d, e, w = _truncated_terms(uav, rng, up_m, u, noise, sig) if terms is None else terms
    for _ in range(iterations):
        # j = ∂e/∂u = −(u − h)/(d σ);  H = Σ w j jᵀ, g = Σ w j e
        f = -w / (d * sig)
        je, jn = de * f, dn * f
        a, b, cc = (je * je).sum(axis=1), (je * jn).sum(axis=1), (jn * jn).sum(axis=1)
        ge, gn = (je * e).sum(axis=1), (jn * e).sum(axis=1)
        det = a * cc - b * b
        ok = det > 1e-12 * np.maximum(a * cc, 1e-300)
        safe = np.where(ok, det, 1.0)
        step = -np.stack([(cc * ge - b * gn) / safe, (a * gn - b * ge) / safe], axis=1)
        step[~ok] = 0.0
        trial = u + step
        t_cost, t_de, t_dn, t_d, t_e, t_w = _truncated_terms(uav, rng, up_m, trial, noise, sig)
        better = t_cost < cost
        if better.all():  # the usual case: every user moves
            u, cost, de, dn, d, e, w = trial, t_cost, t_de, t_dn, t_d, t_e, t_w
            continue
        if not better.any():
            break
        u = np.where(better[:, None], trial, u)
        cost = np.where(better, t_cost, cost)
        sel = better[:, None]
        de, dn, d, e, w = (np.where(sel, new, old) for new, old in ((t_de, de), (t_dn, dn), (t_d, d), (t_e, e),
                                                                      (t_w, w)))
    return u


def _linear_starts(uav: np.ndarray, rng: np.ndarray, up_m: np.ndarray) -> np.ndarray | None:
    """Horizontal least-squares multilateration of K users from the same fixes, or None when the
    fixes are too close to a line for it (their spread s2/s1 below LINEAR_INIT_MIN_SPREAD).

    uav: (M, 3); rng: (K, M); up_m: (K,). Returns (K, 2) [m, ENU].

    ||h_i − u||² + dz_i² = r_i² (h the horizontal fix, dz its height above the user) less its
    mean over the fixes is linear in u:  −2 (h_i − h̄)·(u − h̄) = b_i − b̄,
    b_i = r_i² − dz_i² − ||h_i − h̄||²; one 2×2 normal matrix [[p, q], [q, s]] = Σ (h_i − h̄)(h_i − h̄)ᵀ
    serves every user:  u − h̄ = −½ [[p, q], [q, s]]⁻¹ Σ_i (b_i − b̄)(h_i − h̄).
    """
    cx, cy, _, _, spread = _track_line(uav[:, :2])
    if spread < LINEAR_INIT_MIN_SPREAD:
        return None
    hc = uav[:, :2] - (cx, cy)
    (p, q), (_, s) = (hc.T @ hc).tolist()
    det = p * s - q * q
    dz = uav[None, :, 2] - up_m[:, None]
    b = rng * rng - dz * dz - np.sum(hc * hc, axis=1)[None, :]
    b -= b.mean(axis=1, keepdims=True)
    y = b @ hc  # (K, 2)
    out = np.empty((rng.shape[0], 2))
    out[:, 0] = cx - 0.5 * (s * y[:, 0] - q * y[:, 1]) / det
    out[:, 1] = cy - 0.5 * (p * y[:, 1] - q * y[:, 0]) / det
    return out


def init_users(
    uav_enu_m: np.ndarray, range_m: np.ndarray, up_m: np.ndarray, noise: NoiseModel, params: SolverParams,
    n_starts: int = 3,
) -> list[UserFit]:
    """Initial θ of K users ranged from the same fixes.

    First the closed-form multilateration (`_linear_starts`); a user keeps it when it fits its
    ranges as well as a true position fits clean ones — mean truncated cost Σ min(e², c²)/M at
    most LINEAR_INIT_MAX_COST (about 0.9 expected at the truth, 1.5 is 3 standard errors above
    with 40 ranges). Outliers (NLoS) drag the linear fit and raise its cost, and fixes along a
    line give none: those users get the coarse-to-fine grid search, all of them in one pass
    (the joint solver polishes the start; the grid's cell is a third of the coarse one, a few
    metres).

    uav_enu_m: (M, 3) UAV fixes [m, ENU]; range_m: (M, K) [m]; up_m: (K,) ground heights [m].
    Returns K UserFit (θ = [e, n, (up), (bias)], half the truncated cost of the start).
    """
    m, k_n = range_m.shape
    up = np.asarray(up_m, dtype=float)
    # the linear start and the refinement use up to REFINE_MAX_RANGES ranges, the grid fewer
    ref = _grid_subset(m, REFINE_MAX_RANGES)
    uav_r, rng_r = uav_enu_m[ref], range_m[ref].T
    start = np.empty((k_n, 2))
    cost = np.full(k_n, np.inf)
    lin = _linear_starts(uav_r, rng_r, up)
    sig_r = _sigma_eff(noise, rng_r)  # of the measured ranges: shared by the checks and the refinement
    # a few Gauss–Newton steps on each start: the joint solve then starts where the users' NLoS
    # probabilities, estimated at its first residuals, are what they will be at the solution. The
    # linear start is refined before its fit test: the closed form weighs all ranges alike and
    # amplifies the noise where the fixes surround the user poorly (8 of 20 users of the
    # benchmark's N = 200 circle failed the test unrefined and paid for a grid search)
    if lin is not None and np.all(np.isfinite(lin)):
        lin = _refine_starts(uav_r, rng_r, up, lin, noise, sig=sig_r)
        lin_cost = _truncated_terms(uav_r, rng_r, up, lin, noise, sig_r)[0]
        lo, hi = _search_box(uav_r, rng_r, up, noise, sig_r, exact=True)
        good = (lin_cost <= LINEAR_INIT_MAX_COST * rng_r.shape[1]) & np.all((lin >= lo) & (lin <= hi), axis=1)
        start[good], cost[good] = lin[good], lin_cost[good]
    search = np.flatnonzero(~np.isfinite(cost))
    if search.size:
        sub = _grid_subset(m)
        starts, costs = _grid_starts(uav_enu_m[sub], range_m[sub].T[search], up[search], noise, n_starts)
        best = np.argmin(costs, axis=1)
        rows = np.arange(search.size)
        sig_s = sig_r if np.ndim(sig_r) == 0 else sig_r[search]
        start[search] = _refine_starts(uav_r, rng_r[search], up[search], starts[rows, best], noise, sig=sig_s)
        cost[search] = costs[rows, best]
    out = []
    for k in range(k_n):
        theta0 = np.zeros(params.user_dim + (1 if params.estimate_bias else 0))
        theta0[:2] = start[k]
        if params.user_dim == 3:
            theta0[2] = up[k]
        out.append(UserFit(theta0, 0.5 * float(cost[k])))
    return out


def init_user(
    uav_enu_m: np.ndarray, range_m: np.ndarray, up_m: float, noise: NoiseModel, params: SolverParams,
    n_starts: int = 3,
) -> UserFit:
    """`init_users` of one user: uav_enu_m (M, 3) [m, ENU], range_m (M,) [m], up_m [m]."""
    return init_users(uav_enu_m, range_m[:, None], np.array([up_m]), noise, params, n_starts)[0]


@dataclass(frozen=True)
class MirrorTest:
    """Result of the mirror test for one user (see the module docstring).

    mirror_refuted, estimate_refuted: silence refutes that hypothesis (estimator.silence, a cell of
    limited reach; set by estimator.batch.mirror_all): a refuted mirror is no ambiguity (ambiguous
    False) and never flipped to; a refuted estimate whose mirror is not is flipped to the mirror."""

    ambiguous: bool
    mirror_theta: np.ndarray | None  # refined mirror θ, None when the reflection coincides with u
    delta_chi2: float  # 2 (L(mirror) − L(u)); negative: the mirror fits better
    separation_chi2: float  # χ²_sep of the two hypotheses on the smoothed track
    linearity: float  # s2/s1 of the horizontal fixes (0: a perfect line)
    mirror_refuted: bool = False
    estimate_refuted: bool = False

    def mirror_is_better(self, chi2_threshold: float) -> bool:
        """The geometry separates the two and the mirror fits clearly better (and silence does not
        refute it)."""
        return (
            self.mirror_theta is not None
            and not self.mirror_refuted
            and self.separation_chi2 >= chi2_threshold
            and self.delta_chi2 < -chi2_threshold
        )

    def silence_prefers_mirror(self, chi2_threshold: float) -> bool:
        """Silence refutes the estimate and not the mirror, and the mirror explains the ranges
        about as well (Δχ² < χ²_amb): the user belongs at the mirror."""
        return (
            self.mirror_theta is not None
            and self.estimate_refuted
            and not self.mirror_refuted
            and self.delta_chi2 < chi2_threshold
        )


def smooth_track(pos_enu_m: np.ndarray, half: int = SMOOTH_HALF) -> np.ndarray:
    """(M, 3) moving average over ±half fixes in time order (shrinking at the ends)."""
    m = pos_enu_m.shape[0]
    c = np.empty((m + 1, 3))
    c[0] = 0.0
    np.cumsum(pos_enu_m, axis=0, out=c[1:])
    i = np.arange(m)
    lo, hi = np.maximum(i - half, 0), np.minimum(i + half + 1, m)
    return (c[hi] - c[lo]) / (hi - lo)[:, None]


def _track_line(h: np.ndarray) -> tuple[float, float, float, float, float]:
    """Best-fit line of horizontal fixes h (M, 2): (c_x, c_y, v_x, v_y, linearity)."""
    c = h.mean(axis=0)
    # principal axis v of the fixes: the leading eigenvector of the 2×2 scatter [[a, b], [b, d]]
    # (the right singular vectors of h − c; singular values s_i = √λ_i)
    hc = h - c
    (a, b), (_, d) = (hc.T @ hc).tolist()
    mid, rad = 0.5 * (a + d), math.hypot(0.5 * (a - d), b)
    lam1, lam2 = mid + rad, max(mid - rad, 0.0)
    lin = math.sqrt(lam2 / lam1) if lam1 > 0 else 1.0
    vx, vy = (lam1 - d, b) if a >= d else (b, lam1 - a)
    norm = math.hypot(vx, vy)
    vx, vy = (vx / norm, vy / norm) if norm > 0 else (1.0, 0.0)
    cx, cy = c.tolist()
    return cx, cy, vx, vy, lin


def mirror_test(
    uav_enu_m: np.ndarray, range_m: np.ndarray, theta: np.ndarray, up_m: float, noise: NoiseModel,
    params: SolverParams, chi2_threshold: float, min_offset_m: float = 2.0,
) -> MirrorTest:
    """Reflect θ across the best-fit line of the fixes (in time order, (M, 3)) and compare."""
    cx, cy, vx, vy, lin = _track_line(uav_enu_m[:, :2])
    # u' = c + (2 v vᵀ − I)(u − c)
    ux, uy = float(theta[0]) - cx, float(theta[1]) - cy
    dot = vx * ux + vy * uy
    m_h = np.array([cx + 2.0 * dot * vx - ux, cy + 2.0 * dot * vy - uy])
    u_h = theta[:2]
    if math.hypot(2.0 * (dot * vx - ux), 2.0 * (dot * vy - uy)) < min_offset_m:
        return MirrorTest(False, None, np.inf, 0.0, lin)
    t_m = np.array(theta, dtype=float)
    t_m[:2] = m_h
    # χ²_sep on the smoothed track, first for the plain reflection: a curved path is done here
    track = smooth_track(uav_enu_m)
    u, _ = _theta_to_user(theta, params.user_dim, up_m)

    def separation(tm: np.ndarray) -> float:
        mu, _ = _theta_to_user(tm, params.user_dim, up_m)
        d1 = np.linalg.norm(track - u, axis=1)
        d2 = np.linalg.norm(track - mu, axis=1)
        return float(np.sum(((d1 - d2) / _sigma_eff(noise, d1)) ** 2))

    cost_u = user_cost(uav_enu_m, range_m, theta, up_m, noise, params)
    # geometric separation of u and its exact reflection: the refined mirror would add its own
    # estimation noise to the statistic
    sep = separation(t_m)
    if sep > 100.0 * chi2_threshold:
        cost_m = user_cost(uav_enu_m, range_m, t_m, up_m, noise, params)
        if cost_m - cost_u > 50.0 * chi2_threshold:
            return MirrorTest(False, None, 2.0 * (cost_m - cost_u), np.inf, lin)
    # (a reflection that walks back to within min_offset_m of u has its outcome: refined no further)
    fit = refine_user(uav_enu_m, range_m, t_m, up_m, noise, params, 15, stop_near=u_h, near_m=min_offset_m)
    if np.linalg.norm(fit.theta[:2] - u_h) < min_offset_m:
        return MirrorTest(False, None, np.inf, 0.0, lin)
    delta = 2.0 * (fit.cost - cost_u)
    return MirrorTest(bool(sep < chi2_threshold), fit.theta, float(delta), sep, lin)


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, M) distances ||a_j − b_i|| of points a (M, 3) and b (P, 3), coordinate by coordinate
    (long rows of M: cheaper than a (P, M, 3) difference)."""
    at = a.T
    d = np.subtract.outer(b[:, 0], at[0])
    d *= d
    for i in (1, 2):
        t = np.subtract.outer(b[:, i], at[i])
        t *= t
        d += t
    return np.sqrt(d, out=d)


def mirror_tests(
    uav_enu_m: np.ndarray, range_m: np.ndarray, theta: np.ndarray, up_m: np.ndarray, noise: NoiseModel,
    params: SolverParams, chi2_threshold: float, min_offset_m: float = 2.0,
) -> list[MirrorTest]:
    """`mirror_test` of several users that share their fixes, at once (same results).

    uav_enu_m: (M, 3) fixes in time order; range_m: (M, K) each user's ranges from them;
    theta: (K, p); up_m: (K,). Returns K MirrorTest.

    The users share the fitted line and the smoothed track; the common outcome — a path that
    separates the reflection (χ²_sep > 100 χ²_amb) and a reflection that fits far worse — is
    decided for all users in one pass; the rest go through `mirror_test` one by one.
    """
    k_n = theta.shape[0]
    cx, cy, vx, vy, lin = _track_line(uav_enu_m[:, :2])
    # u' = c + (2 v vᵀ − I)(u − c), for all users
    ux, uy = theta[:, 0] - cx, theta[:, 1] - cy
    dot = vx * ux + vy * uy
    offset = np.hypot(2.0 * (dot * vx - ux), 2.0 * (dot * vy - uy))
    t_m = theta.astype(float, copy=True)
    t_m[:, 0] = cx + 2.0 * dot * vx - ux
    t_m[:, 1] = cy + 2.0 * dot * vy - uy
    track = smooth_track(uav_enu_m)
    # both hypotheses of every user, stacked: rows 0..K−1 are u, rows K..2K−1 the reflections
    both = np.concatenate([theta, t_m])
    pos = np.empty((2 * k_n, 3))
    pos[:, :2] = both[:, :2]
    pos[:, 2] = both[:, 2] if params.user_dim == 3 else np.concatenate([up_m, up_m])
    bias = both[:, params.user_dim][:, None] if params.estimate_bias else 0.0
    # χ²_sep = Σ_i ((d1_i − d2_i)/σ_eff(d1_i))² on the smoothed track
    d_track = _distances(track, pos)
    sep = np.sum(((d_track[:k_n] - d_track[k_n:]) / _sigma_eff(noise, d_track[:k_n])) ** 2, axis=1)
    # cost Σ ρ(e_i) (+ bias prior) of each hypothesis, as user_cost
    diff = uav_enu_m.T[:, None, :] - pos.T[:, :, None]  # (3, 2K, M)
    _, sig, _, e = range_residuals(diff, np.concatenate([range_m.T, range_m.T]), bias, noise,
                                   gps_var_m2=noise.sigma_gps_m**2)
    cost = np.sum(loss_rho(e, params.loss, params.loss_scale, nlos_args(params, sig)), axis=1)
    if params.estimate_bias:
        cost += 0.5 * (both[:, params.user_dim] / params.bias_prior_sigma_m) ** 2
    out: list[MirrorTest | None] = [None] * k_n
    refine = []
    for k in range(k_n):
        if offset[k] < min_offset_m:
            out[k] = MirrorTest(False, None, np.inf, 0.0, lin)
        elif sep[k] > 100.0 * chi2_threshold and cost[k_n + k] - cost[k] > 50.0 * chi2_threshold:
            out[k] = MirrorTest(False, None, 2.0 * float(cost[k_n + k] - cost[k]), np.inf, lin)
        else:
            refine.append(k)
    if refine:
        # the rest as mirror_test does them: the reflection refined to the mirror solution, all
        # of them in one pass
        fits = refine_users(uav_enu_m, range_m[:, refine], t_m[refine], up_m[refine], noise, params, 15,
                            stop_near=theta[refine, :2], near_m=min_offset_m)
        for k, fit in zip(refine, fits, strict=True):
            if np.linalg.norm(fit.theta[:2] - theta[k, :2]) < min_offset_m:
                out[k] = MirrorTest(False, None, np.inf, 0.0, lin)
            else:
                out[k] = MirrorTest(bool(sep[k] < chi2_threshold), fit.theta, 2.0 * (fit.cost - float(cost[k])),
                                    float(sep[k]), lin)
    return out
