"""The SLAM estimator: users and UAV keyframes jointly, batch and online (DESIGN.md §5).

Cost (negative log-likelihood; factors in estimator.factors, losses in estimator.robust):

    L = ½ Σ_n ||x_n − x̂_n||²/σ_gps² + Σ_(n,k) ρ(e_nk) + ½ Σ_k (b_k/σ_b)²
        + ½ Σ_n ||x_n − x_(n−1) − ô_n||²/σ_m² + L_prior(users, x_first)
    e_nk = (r̂_nk − ||x_n − u_k|| − b_k) / σ(d_nk)

Levenberg–Marquardt on the IRLS-weighted normal equations, solved with the Schur complement over
keyframes (estimator.schur), O(N·K²) per iteration. Damping starts at 0 (Gauss–Newton) and grows
only when a step fails to lower L.

Covariance: S⁻¹ of the IRLS-weighted information at the final linearization, S = Σ w JᵀJ over
ranges (+ priors) Schur-complemented over keyframes. Under a robust loss this is the information
the estimate actually uses: a range the loss discounts (an NLoS outlier) contributes with its
weight w < 1 instead of full weight, so the reported covariance does not claim information from
data the estimator has rejected (GTSAM's Marginals on a robust graph report the same matrix).

Online (fixed-lag smoothing): keyframes are kept in a window; when it holds more than
`params.window`, the oldest keyframe is marginalized at the current estimate into a Gaussian prior
on the users (and biases, and the next keyframe when a motion factor links them):

    L_prior(z) ≈ cᵀ(z − z₀) + ½ (z − z₀)ᵀ Λ (z − z₀),  Λ = H_rr − H_r0 H_00⁻¹ H_0r,
                                                      c = ∇_r − H_r0 H_00⁻¹ ∇_0

exact at the linearization point z₀; each update then costs O(window · K²), independent of N.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from estimator.init import init_user, mirror_test, user_cost
from estimator.noise import NoiseModel
from estimator.problem import (
    Problem,
    check_keyframe,
    check_params,
    check_users,
    pack_keyframes,
    users_from_theta,
)
from estimator.robust import REDESCENDING, loss_rho, loss_weight
from estimator.schur import schur_solve
from estimator.types import Estimate, Keyframe, SolverParams
from uavloc.errors import EstimatorError

_LAM_START = 1e-4
_LAM_MAX = 1e10
#: the online estimator starts a user once the window holds this many of its ranges ...
ONLINE_MIN_RANGES = 8
#: ... taken from fixes spread over at least this much ground [m]
ONLINE_MIN_EXTENT_M = 10.0
#: Huber threshold of the warm start before a redescending loss
HUBER_WARM_SCALE = 1.5


@dataclass
class Prior:
    """Gaussian prior from marginalized keyframes over z = [x_first (3, if has_x), Θ.ravel() (K·p)].

    L_prior(z) = cᵀ(z − z0) + ½ (z − z0)ᵀ Λ (z − z0).
    """

    has_x: bool
    z0: np.ndarray
    info: np.ndarray
    grad: np.ndarray


@dataclass
class Linearization:
    """IRLS-weighted normal equations at one point (shapes as in estimator.schur.schur_solve)."""

    cost: float
    hxx: np.ndarray  # (N, 3, 3)
    off: np.ndarray | None  # (N − 1,)
    hxu: np.ndarray  # (3, N, K·p)
    huu: np.ndarray  # (K·p, K·p)
    gx: np.ndarray  # (N, 3)
    gu: np.ndarray  # (K·p,)
    e: np.ndarray  # (K, N) whitened range residuals, 0 where none
    w: np.ndarray  # (K, N) IRLS weights, 0 where none


def _range_terms(
    prob: Problem, x: np.ndarray, theta: np.ndarray, mask_kn: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Whitened range residuals and Jacobians (see estimator.factors.RangeFactor), user-major.

    x: (n, 3); theta: (K, p); mask_kn: (K, n) ranges to use; ranges are prob.range_m[:n].
    Arrays are laid out (K, n) so that numpy's inner loops run over keyframes (long), not over
    3 coordinates. Returns e, w, rho (K, n) and J (3 + p, K, n) = [∂e/∂x; ∂e/∂θ_k], zero where
    mask_kn is False.
    """
    params, noise = prob.params, prob.noise
    n = x.shape[0]
    d_u = prob.user_dim
    users = users_from_theta(theta, prob.user_up_m, d_u)
    # diff_i = x_i − u_i, (3, K, n)
    diff = np.ascontiguousarray(x.T)[:, None, :] - users.T[:, :, None]
    d = np.sqrt(diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2])
    np.maximum(d, 1e-9, out=d)
    sig = noise.range_sigma_m(d)
    r = prob.range_m[:n].T - d
    if params.estimate_bias:
        r -= theta[:, -1:]
    r[~mask_kn] = 0.0
    # e = (r̂ − d − b) / σ(d)
    e = r / sig
    w = loss_weight(e, params.loss, params.loss_scale)
    w *= mask_kn
    rho = loss_rho(e, params.loss, params.loss_scale)
    rho *= mask_kn
    # α = 1/σ + r σ'/σ²;  ∂e/∂x = −α û, ∂e/∂u = α û, ∂e/∂b = −1/σ
    if noise.a_m != 0.0 and noise.b_per_m != 0.0:
        alpha = (1.0 / sig + r * noise.range_sigma_dd(d) / sig**2) * mask_kn
    else:
        alpha = mask_kn / sig
    jac = np.empty((3 + prob.p, prob.n_users, n))
    np.multiply(diff, -alpha / d, out=jac[:3])
    np.negative(jac[:d_u], out=jac[3 : 3 + d_u])
    if params.estimate_bias:
        np.divide(-1.0, sig, out=jac[-1])
        jac[-1] *= mask_kn
    return e, w, rho, jac


def linearize(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None
) -> Linearization:
    """IRLS-weighted normal equations H Δ = g (g = −∇L) at (x (N, 3), Θ (K, p)).

    Per range, with J = [∂e/∂x | ∂e/∂θ_k] (1 × (3 + p)):
        H_nn = I/σ_gps² + Σ_k w J_xᵀ J_x,   H_(n,k) = w J_xᵀ J_θ,   H_kk = Σ_n w J_θᵀ J_θ
        g_n = −(x_n − x̂_n)/σ_gps² − Σ_k w e J_x,   g_k = −Σ_n w e J_θ      (+ bias, motion, prior)
    Users with active[k] False are held fixed (identity block, zero gradient).
    """
    params, noise = prob.params, prob.noise
    n, k_all = prob.range_m.shape
    p = prob.p
    mask_kn = prob.mask[:n].T & active[:, None]
    e, w, rho, jac = _range_terms(prob, x, theta, mask_kn)
    wj = jac * w
    inv_g2 = 1.0 / noise.sigma_gps_m**2
    # O = w J_xᵀ J_x per range, (3, 3, K, n); H_nn = Σ_k O (+ I/σ_gps²)
    o_xx = wj[:3, None] * jac[None, :3]
    hxx = np.ascontiguousarray(o_xx.sum(axis=2).transpose(2, 0, 1))
    hxx.reshape(n, 9)[:, ::4] += inv_g2
    dgps = x - prob.gps_enu_m
    wje = wj * e
    gx = -dgps * inv_g2 - wje[:3].sum(axis=1).T
    cost = 0.5 * inv_g2 * float(np.vdot(dgps, dgps)) + float(rho.sum())
    if params.estimate_bias:
        o_xt = wj[:3, None] * jac[None, 3:]
        o_tt = wj[3:, None] * jac[None, 3:]
    else:
        # J_θ = −J_x[:d]: the coupling and user blocks are slices of O
        o_xt = -o_xx[:, : prob.user_dim]
        o_tt = o_xx[: prob.user_dim, : prob.user_dim]
    # H_(n,k) = w J_xᵀ J_θ: (3, p, K, n) -> (3, n, K·p)
    hxu = o_xt.transpose(0, 3, 2, 1).reshape(3, n, k_all * p)
    # H_kk = Σ_n w J_θᵀ J_θ: (p, p, K) -> (K, p, p)
    huu_blocks = o_tt.sum(axis=3).transpose(2, 0, 1)
    gu = -wje[3:].sum(axis=2).T
    if params.estimate_bias:
        inv_b2 = 1.0 / params.bias_prior_sigma_m**2
        bias = theta[:, -1]
        huu_blocks[:, -1, -1] += inv_b2
        gu[:, -1] -= bias * inv_b2
        cost += 0.5 * inv_b2 * float(np.sum(bias[active] ** 2))
    if not active.all():
        inactive = ~active
        huu_blocks[inactive] = np.eye(p)
        gu[inactive] = 0.0
    huu = np.zeros((k_all, p, k_all, p))
    np.einsum("kikj->kij", huu)[...] = huu_blocks  # block diagonal (a writable diagonal view)
    huu = huu.reshape(k_all * p, k_all * p)
    gu = gu.ravel()
    off = None
    if prob.use_motion:
        inv_m2 = 1.0 / params.motion_sigma_m**2
        om = prob.odom_mask[1:n]
        # e_m = (x_n − x_(n−1) − ô_n)/σ_m for linked pairs
        em = (x[1:] - x[:-1] - prob.odom_enu_m[1:n]) * om[:, None]
        cost += 0.5 * inv_m2 * float(np.vdot(em, em))
        add = inv_m2 * om
        hxx.reshape(n, 9)[1:, ::4] += add[:, None]
        hxx.reshape(n, 9)[:-1, ::4] += add[:, None]
        off = -add
        gx[1:] -= inv_m2 * em
        gx[:-1] += inv_m2 * em
    if prior is not None:
        z = theta.ravel()
        if prior.has_x:
            z = np.concatenate([x[0], z])
        dz = z - prior.z0
        grad = prior.grad + prior.info @ dz
        cost += float(prior.grad @ dz + 0.5 * dz @ prior.info @ dz)
        if prior.has_x:
            hxx[0] += prior.info[:3, :3]
            hxu[:, 0, :] += prior.info[:3, 3:]
            gx[0] -= grad[:3]
            huu += prior.info[3:, 3:]
            gu -= grad[3:]
        else:
            huu += prior.info
            gu -= grad
    return Linearization(cost, hxx, off, hxu, huu, gx, gu, e, w)


@dataclass
class _Result:
    x: np.ndarray
    theta: np.ndarray
    lin: Linearization
    s: np.ndarray | None
    iterations: int
    converged: bool


def levenberg_marquardt(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None,
    max_iterations: int | None = None, step_tol_m: float | None = None,
) -> _Result:
    """Minimise L from (x, Θ); stop when the largest step component is below params.step_tol_m.

    The returned S (undamped Schur complement) belongs to the last linearization point, which
    differs from the returned estimate by less than step_tol_m.
    """
    params = prob.params
    max_it = params.max_iterations if max_iterations is None else max_iterations
    tol = params.step_tol_m if step_tol_m is None else step_tol_m
    lin = linearize(prob, x, theta, active, prior)
    lam = 0.0
    s_final = None
    converged = False
    it = 0
    while it < max_it:
        it += 1
        try:
            dx, du, s = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, lam)
        except (np.linalg.LinAlgError, EstimatorError):
            lam = max(_LAM_START, 10.0 * lam)
            if lam > _LAM_MAX:
                break
            continue
        du = du.reshape(theta.shape)
        step = max(float(np.max(np.abs(dx))), float(np.max(np.abs(du))))
        if step < tol:
            x = x + dx
            theta = theta + du
            s_final = s if lam == 0.0 else None
            converged = True
            break
        x_t, th_t = x + dx, theta + du
        lin_t = linearize(prob, x_t, th_t, active, prior)
        if lin_t.cost <= lin.cost + 1e-12 * abs(lin.cost):
            x, theta, lin = x_t, th_t, lin_t
            lam = 0.0 if lam <= _LAM_START else lam / 10.0
        else:
            lam = max(_LAM_START, 10.0 * lam)
            if lam > _LAM_MAX:
                break
    if s_final is None:
        try:
            _, _, s_final = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, 0.0)
        except (np.linalg.LinAlgError, EstimatorError):
            s_final = None
    return _Result(x, theta, lin, s_final, it, converged)


def _init_theta(
    prob: Problem, uav: np.ndarray, mask: np.ndarray, k: int, theta_row: np.ndarray | None = None
) -> np.ndarray:
    """Initial θ_k: from a given position (refined) or by grid search, UAV at `uav` (n, 3)."""
    rows = mask[:, k]
    up = float(prob.user_up_m[k])
    if theta_row is not None:
        return theta_row
    return init_user(uav[rows], prob.range_m[: uav.shape[0]][rows, k], up, prob.noise, prob.params).theta


def _mirror_all(
    prob: Problem, theta: np.ndarray, active: np.ndarray, n_rows: int | None = None
) -> list:
    """Mirror test per user on the first n_rows keyframes (UAV at GPS). None for inactive users."""
    n = prob.n_keyframes if n_rows is None else n_rows
    out = []
    for k in range(prob.n_users):
        if not active[k]:
            out.append(None)
            continue
        rows = prob.mask[:n, k]
        out.append(
            mirror_test(
                prob.gps_enu_m[:n][rows], prob.range_m[:n][rows, k], theta[k], float(prob.user_up_m[k]),
                prob.noise, prob.params, prob.params.ambiguity_chi2,
            )
        )
    return out


def _covariances(
    s: np.ndarray | None, active: np.ndarray, k_all: int, p: int, d: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """From S (K·p, K·p): per-user position covariance (K, d, d), position information (K·d, K·d)
    with any bias marginalized out, and the full joint covariance of the active users' θ."""
    cov = np.full((k_all, d, d), np.inf)
    info = np.zeros((k_all * d, k_all * d))
    if s is None or not np.any(active):
        return cov, info, None
    all_active = bool(active.all())
    s_a = s if all_active else s[np.ix_(np.repeat(active, p), np.repeat(active, p))]
    try:
        np.linalg.cholesky(s_a)
        cov_a = np.linalg.inv(s_a)
    except np.linalg.LinAlgError:
        return cov, info, None
    cov_a = 0.5 * (cov_a + cov_a.T)
    na = s_a.shape[0] // p
    cov_a4 = cov_a.reshape(na, p, na, p)
    blocks = np.einsum("kikj->kij", cov_a4)[:, :d, :d]
    if p == d:
        info_pos = s_a
    else:
        info_pos = np.linalg.inv(cov_a4[:, :d, :, :d].reshape(na * d, na * d))
        info_pos = 0.5 * (info_pos + info_pos.T)
    if all_active:
        cov[:] = blocks
        info[:] = info_pos
    else:
        ka = np.flatnonzero(active)
        cov[ka] = blocks
        ip = (ka[:, None] * d + np.arange(d)[None, :]).ravel()
        info[np.ix_(ip, ip)] = info_pos
    return cov, info, cov_a


def _estimate(
    prob: Problem, res: _Result, active: np.ndarray, mirrors: list, n_ranges: np.ndarray,
) -> Estimate:
    k_all, p, d = prob.n_users, prob.p, prob.user_dim
    users = users_from_theta(res.theta, prob.user_up_m, d)
    users[~active] = np.nan
    cov, info, cov_joint = _covariances(res.s, active, k_all, p, d)
    bias = None
    if prob.params.estimate_bias:
        bias = np.where(active, res.theta[:, -1], np.nan)
    ambiguous = np.zeros(k_all, dtype=bool)
    mirror = np.full((k_all, 3), np.nan)
    for k, mt in enumerate(mirrors):
        if mt is not None and mt.ambiguous:
            ambiguous[k] = True
            mirror[k] = users_from_theta(mt.mirror_theta[None, :], prob.user_up_m[k : k + 1], d)[0]
    extra = {"active": active.copy(), "cov_theta_joint": cov_joint, "lin_cost": res.lin.cost}
    return Estimate(
        users_enu_m=users, cov_users_m2=cov, info_users=info, bias_m=bias, uav_enu_m=res.x.copy(),
        ambiguous=ambiguous, mirror_enu_m=mirror, n_ranges=n_ranges.copy(), cost=res.lin.cost,
        iterations=res.iterations, converged=res.converged, extra=extra,
    )


def _resolve_mirrors(prob: Problem, res: _Result, active: np.ndarray, prior: Prior | None = None):
    """Mirror tests; a user whose mirror fits clearly better (Δχ² < −χ²_amb) jumps there and
    the problem is re-solved once. Returns (result, mirror tests)."""
    mirrors = _mirror_all(prob, res.theta, active)
    flip = [k for k, mt in enumerate(mirrors) if mt is not None and mt.mirror_is_better(prob.params.ambiguity_chi2)]
    if flip:
        theta = res.theta.copy()
        for k in flip:
            theta[k] = mirrors[k].mirror_theta
        res2 = levenberg_marquardt(prob, res.x, theta, active, prior)
        if res2.lin.cost < res.lin.cost:
            res = res2
            mirrors = _mirror_all(prob, res.theta, active)
    return res, mirrors


def solve_batch(
    keyframes: Sequence[Keyframe], n_users: int, user_up_m: np.ndarray, noise: NoiseModel,
    params: SolverParams = SolverParams(), init_users_enu_m: np.ndarray | None = None,  # noqa: B008
) -> Estimate:
    """Estimate users and UAV keyframes from all keyframes at once.

    keyframes: N keyframes (GPS fix, ranges to users, optional odometry).
    n_users: K; user_up_m: (K,) ground height of each user [m, ENU up] (fixed in 2-D mode,
        the initial value in 3-D mode); init_users_enu_m: optional (K, 3) starts [m, ENU], rows
        with NaN are initialised by grid search.
    Users with fewer than p + 1 ranges (p unknowns) are not estimated: NaN rows, inf covariance.
    Raises EstimatorError on malformed input, naming the offending value.
    """
    prob = pack_keyframes(keyframes, n_users, user_up_m, noise, params)
    k_all, p = prob.n_users, prob.p
    n_ranges = prob.mask.sum(axis=0)
    active = n_ranges >= prob.min_ranges()
    theta = np.zeros((k_all, p))
    theta[:, :2] = np.nan
    given = None
    if init_users_enu_m is not None:
        given = np.asarray(init_users_enu_m, dtype=float)
        if given.shape != (k_all, 3):
            raise EstimatorError(f"init_users_enu_m must have shape ({k_all}, 3), got {given.shape}")
    x = prob.gps_enu_m.copy()
    for k in np.flatnonzero(active):
        row = None
        if given is not None and np.all(np.isfinite(given[k])):
            row = np.zeros(p)
            row[: prob.user_dim] = given[k, : prob.user_dim]
        theta[k] = _init_theta(prob, x, prob.mask, k, row)
    theta[~active] = 0.0
    if params.loss in REDESCENDING:
        # a redescending loss ignores what it deems outliers: start it from the Huber solution
        warm = replace(prob, params=replace(params, loss="huber", loss_scale=HUBER_WARM_SCALE))
        pre = levenberg_marquardt(warm, x, theta, active)
        x, theta = pre.x, pre.theta
    res = levenberg_marquardt(prob, x, theta, active)
    res, mirrors = _resolve_mirrors(prob, res, active)
    return _estimate(prob, res, active, mirrors, n_ranges)


class OnlineEstimator:
    """Incremental estimator: one keyframe at a time, warm-started, fixed-lag (window) smoothing.

    add_keyframe(kf) appends the keyframe (UAV initialised at its GPS fix), activates users that
    now have enough ranges (grid initialization on the window), iterates Levenberg–Marquardt from
    the previous solution and returns the new Estimate. Beyond params.window keyframes the oldest
    is marginalized into a prior on the users (module docstring), so an update costs
    O(window · K²) whatever the number of keyframes seen. A user starts once the window holds
    ONLINE_MIN_RANGES of its ranges spread over ONLINE_MIN_EXTENT_M of ground; ranges to a user
    that is not yet active when its keyframe leaves the window are dropped. Every
    params.online_check_every keyframes each user is re-initialised when a fresh grid search
    on the window fits clearly better, and tested for its mirror (see _check_mirrors).
    """

    def __init__(
        self, n_users: int, user_up_m: np.ndarray, noise: NoiseModel,
        params: SolverParams = SolverParams(),  # noqa: B008
    ):
        if not isinstance(noise, NoiseModel):
            raise EstimatorError(f"noise must be a NoiseModel, got {type(noise).__name__}")
        check_params(params)
        self._up = check_users(n_users, user_up_m)
        self._noise = noise
        self._params = params
        self._k = int(n_users)
        self._p = params.user_dim + (1 if params.estimate_bias else 0)
        cap = int(params.window) + 1
        self._gps = np.zeros((cap, 3))
        self._rng = np.full((cap, self._k), np.nan)
        self._odom = np.zeros((cap, 3))
        self._odom_mask = np.zeros(cap, dtype=bool)
        self._x = np.zeros((cap, 3))
        self._n = 0
        self._theta = np.zeros((self._k, self._p))
        self._active = np.zeros(self._k, dtype=bool)
        self._n_ranges = np.zeros(self._k, dtype=int)
        self._prior: Prior | None = None
        self._seen = 0
        self._mirrors: list = [None] * self._k
        self._estimate: Estimate | None = None

    @property
    def estimate(self) -> Estimate | None:
        """The latest estimate, None before the first keyframe."""
        return self._estimate

    @property
    def n_keyframes_seen(self) -> int:
        return self._seen

    def _problem(self) -> Problem:
        n = self._n
        rng = self._rng[:n]
        return Problem(
            self._gps[:n], rng, ~np.isnan(rng), self._odom[:n], self._odom_mask[:n], self._up,
            self._noise, self._params,
        )

    def add_keyframe(self, kf: Keyframe) -> Estimate:
        """Add one keyframe with its ranges; return the updated Estimate."""
        gps, idx, rng, odom = check_keyframe(kf, self._k)
        n = self._n
        self._gps[n] = gps
        self._rng[n] = np.nan
        self._rng[n, idx] = rng
        self._odom_mask[n] = odom is not None and n + self._seen > 0 and self._params.motion_sigma_m is not None
        self._odom[n] = odom if odom is not None else 0.0
        # a new keyframe starts at its GPS fix, or dead-reckoned from the previous one, moved to
        # where the ranges to the users already estimated put it
        self._x[n] = self._x[n - 1] + odom if (self._odom_mask[n] and n > 0) else gps
        if idx.size and self._active.any():
            self._x[n] = self._place_keyframe(self._x[n], gps, idx, rng)
        self._n = n + 1
        self._seen += 1
        self._n_ranges[idx] += 1
        prob = self._problem()
        newly = np.zeros(self._k, dtype=bool)
        ready = ~self._active & (prob.mask.sum(axis=0) >= max(prob.min_ranges(), ONLINE_MIN_RANGES))
        for k in np.flatnonzero(ready):
            fixes = self._x[: self._n][prob.mask[:, k], :2]
            if float(np.max(np.ptp(fixes, axis=0))) < ONLINE_MIN_EXTENT_M:
                continue
            self._theta[k] = _init_theta(prob, self._x[: self._n], prob.mask, k)
            self._active[k] = newly[k] = True
        res = levenberg_marquardt(
            prob, self._x[: self._n].copy(), self._theta, self._active, self._prior,
            step_tol_m=self._params.online_step_tol_m,
        )
        self._x[: self._n] = res.x
        self._theta = res.theta
        if np.any(newly) or self._seen % max(int(self._params.online_check_every), 1) == 0:
            res = self._check_mirrors(prob, res)
        est = _estimate(prob, res, self._active, self._mirrors, self._n_ranges)
        if self._n > self._params.window:
            self._marginalize_oldest()
        self._estimate = est
        return est

    def _place_keyframe(self, x0: np.ndarray, gps: np.ndarray, idx: np.ndarray, rng: np.ndarray) -> np.ndarray:
        """One Gauss–Newton step on the new keyframe alone (users fixed): a warm start that
        leaves the joint iterations only the users' small shift to absorb.

            min_x ||x − x̂||²/σ_gps² + Σ_k w (r̂_k − ||x − u_k|| − b_k)²/σ²
        """
        use = self._active[idx]
        if not use.any():
            return x0
        k = idx[use]
        users = users_from_theta(self._theta[k], self._up[k], self._params.user_dim)
        bias = self._theta[k, -1] if self._params.estimate_bias else 0.0
        r_meas = rng[use]
        inv_g2 = 1.0 / self._noise.sigma_gps_m**2
        x = x0.copy()
        for _ in range(1):
            diff = x - users
            d = np.maximum(np.sqrt((diff * diff).sum(axis=1)), 1e-9)
            sig = self._noise.range_sigma_m(d)
            e = (r_meas - d - bias) / sig
            w = loss_weight(e, self._params.loss, self._params.loss_scale)
            j = -diff / (d * sig)[:, None]
            h = (j * w[:, None]).T @ j + np.eye(3) * inv_g2
            g = -(x - gps) * inv_g2 - (j * (w * e)[:, None]).sum(axis=0)
            x = x + np.linalg.solve(h, g)
        return x

    def _check_mirrors(self, prob: Problem, res: _Result) -> _Result:
        """Re-initialization and mirror tests on the window.

        A user whose grid initialization on the window's ranges fits clearly better than its
        estimate (an early start from few ranges that went to a wrong basin) is restarted there
        and its part of the prior, linearized in the wrong basin, is dropped. A user whose mirror
        fits clearly better jumps to it with its prior reflected.
        """
        chi2 = self._params.ambiguity_chi2
        flipped = False
        x_win = res.x
        for k in np.flatnonzero(self._active):
            rows = prob.mask[:, k]
            up = float(self._up[k])
            fit = init_user(x_win[rows], prob.range_m[rows, k], up, self._noise, self._params)
            cur = user_cost(x_win[rows], prob.range_m[rows, k], res.theta[k], up, self._noise, self._params)
            new = user_cost(x_win[rows], prob.range_m[rows, k], fit.theta, up, self._noise, self._params)
            # not when the fresh start is the current estimate's mirror: that is the mirror test's call
            mt = (self._mirrors[k] if k < len(self._mirrors) else None)
            near_mirror = (
                mt is not None and mt.mirror_theta is not None
                and np.linalg.norm(fit.theta[:2] - mt.mirror_theta[:2]) < 0.1 * np.linalg.norm(
                    mt.mirror_theta[:2] - res.theta[k, :2])
            )
            if (2.0 * (cur - new) > chi2 and not near_mirror
                    and np.linalg.norm(fit.theta[:2] - res.theta[k, :2]) > 2.0):
                theta = res.theta.copy()
                theta[k] = fit.theta
                prior = self._dropped_prior(k)
                trial = levenberg_marquardt(prob, res.x, theta, self._active, prior)
                res, self._prior, flipped = trial, prior, True
        mirrors = _mirror_all(prob, res.theta, self._active)
        for k, mt in enumerate(mirrors):
            if mt is None or not mt.mirror_is_better(chi2):
                continue
            theta = res.theta.copy()
            theta[k] = mt.mirror_theta
            prior = self._reflected_prior(k, res.theta[k, :2], mt.mirror_theta[:2])
            trial = levenberg_marquardt(prob, res.x, theta, self._active, prior)
            if trial.lin.cost < res.lin.cost:
                res, self._prior, flipped = trial, prior, True
        if flipped:
            self._x[: self._n] = res.x
            self._theta = res.theta
            mirrors = _mirror_all(prob, res.theta, self._active)
        self._mirrors = mirrors
        return res

    def _dropped_prior(self, k: int) -> Prior | None:
        """The prior without any information on user k (its rows and columns zeroed)."""
        pr = self._prior
        if pr is None:
            return None
        off = (3 if pr.has_x else 0) + k * self._p
        sl = slice(off, off + self._p)
        info, grad = pr.info.copy(), pr.grad.copy()
        info[sl, :] = 0.0
        info[:, sl] = 0.0
        grad[sl] = 0.0
        return Prior(pr.has_x, pr.z0.copy(), info, grad)

    def _reflected_prior(self, k: int, u_h: np.ndarray, m_h: np.ndarray) -> Prior | None:
        """The prior with user k's horizontal coordinates reflected across the bisector of u → m.

        Reflection z' = c + R(z − c) with R = I − 2 n nᵀ, n = (m − u)/|m − u|, c = (u + m)/2:
        L'(z) = L(reflect(z)) gives c' = Rᵀc, Λ' = RᵀΛR, z0' = reflect(z0).
        """
        pr = self._prior
        if pr is None:
            return None
        nvec = (m_h - u_h) / max(float(np.linalg.norm(m_h - u_h)), 1e-12)
        ctr = 0.5 * (u_h + m_h)
        refl2 = np.eye(2) - 2.0 * np.outer(nvec, nvec)
        off = (3 if pr.has_x else 0) + k * self._p
        r = np.eye(pr.z0.size)
        r[off : off + 2, off : off + 2] = refl2
        z0 = pr.z0.copy()
        z0[off : off + 2] = ctr + refl2 @ (z0[off : off + 2] - ctr)
        return Prior(pr.has_x, z0, r.T @ pr.info @ r, r.T @ pr.grad)

    def _marginalize_oldest(self) -> None:
        """Fold keyframe 0 of the window into the prior at the current estimate, then drop it."""
        prob = self._problem()
        params, noise = self._params, self._noise
        k_all, p = self._k, self._p
        pu = k_all * p
        x = self._x[: self._n]
        theta = self._theta
        link = bool(prob.use_motion and self._odom_mask[1])
        # variables v = [x_0 (3), x_1 (3), Θ (K·p)]; H and ∇ of every factor touching x_0
        dim = 6 + pu
        h = np.zeros((dim, dim))
        grad = np.zeros(dim)
        mask0 = prob.mask[:1].T & self._active[:, None]
        e, w, _rho, jac = _range_terms(prob, x[:1], theta, mask0)
        sw = np.sqrt(w[:, 0])[:, None]
        jx0 = jac[:3, :, 0].T * sw  # (K, 3)
        jt0 = jac[3:, :, 0].T * sw  # (K, p)
        ew = e[:, 0] * sw[:, 0]
        jfull = np.zeros((k_all, dim))
        jfull[:, :3] = jx0
        kk = np.arange(k_all)[:, None]
        jfull[kk, 6 + kk * p + np.arange(p)[None, :]] = jt0
        h += jfull.T @ jfull
        grad += jfull.T @ ew
        inv_g2 = 1.0 / noise.sigma_gps_m**2
        h[:3, :3] += np.eye(3) * inv_g2
        grad[:3] += (x[0] - prob.gps_enu_m[0]) * inv_g2
        if link:
            inv_m2 = 1.0 / params.motion_sigma_m**2
            em = x[1] - x[0] - prob.odom_enu_m[1]
            h[:3, :3] += np.eye(3) * inv_m2
            h[3:6, 3:6] += np.eye(3) * inv_m2
            h[:3, 3:6] -= np.eye(3) * inv_m2
            h[3:6, :3] -= np.eye(3) * inv_m2
            grad[:3] -= em * inv_m2
            grad[3:6] += em * inv_m2
        pr = self._prior
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
        self._prior = Prior(link, z0, 0.5 * (info + info.T), cvec)
        # drop keyframe 0
        n = self._n
        for arr in (self._gps, self._rng, self._odom, self._odom_mask, self._x):
            arr[: n - 1] = arr[1:n]
        self._odom_mask[0] = False
        self._n = n - 1
