"""The SLAM estimator: users and UAV keyframes jointly, batch and online (DESIGN.md §5).

Cost (negative log-likelihood; factors in estimator.factors, losses in estimator.robust):

    L = ½ Σ_n ||x_n − x̂_n||²/σ_gps² + Σ_(n,k) ρ(e_nk) + ½ Σ_k (b_k/σ_b)²
        + ½ Σ_n ||x_n − x_(n−1) − ô_n||²/σ_m² + L_prior(users, x_first)
    e_nk = (r̂_nk − ||x_n − u_k|| − b_k) / σ(d_nk)

Levenberg–Marquardt on the IRLS-weighted normal equations (Hessian weight w, gradient ψ = ρ'(e);
ψ = w e except for the "nlos" mixture loss), solved with the Schur complement over keyframes
(estimator.schur), O(N·K²) per iteration. Damping starts at 0 (Gauss–Newton) and grows only when
a step fails to lower L. With the "nlos" loss (the default) the per-user NLoS probability π_k is
re-estimated by maximum likelihood between solves (solve_robust).

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

Between window solves (every params.online_resolve_every keyframes) a new keyframe is folded in by
one information-filter step: linearized at its GPS fix and the current users, eliminated at once
into the users' information S (OnlineEstimator._filter_step), O(K²) plus the (K·p)³ inverse for
the covariance. The window is re-solved and marginalized at the next full update.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import erfcx

from estimator.clock import fit_sawtooth
from estimator.gps import gps_chain_terms
from estimator.init import init_user, init_users, mirror_tests, user_cost
from estimator.noise import NoiseModel
from estimator.problem import (
    Problem,
    check_keyframe,
    check_params,
    check_users,
    pack_keyframes,
    users_from_theta,
)
from estimator.robust import REDESCENDING, loss_psi_weight, nlos_args, nlos_terms
from estimator.schur import schur_solve, sym3_cofactors
from estimator.types import Estimate, Keyframe, SolverParams
from uavloc.errors import EstimatorError

_SQRT_HALF_PI = math.sqrt(0.5 * math.pi)
_SQRT_HALF = math.sqrt(0.5)
_LAM_START = 1e-4
_LAM_MAX = 1e10
#: the online estimator starts a user once the window holds this many of its ranges ...
ONLINE_MIN_RANGES = 8
#: ... taken from fixes spread over at least this much ground [m]
ONLINE_MIN_EXTENT_M = 10.0
#: Huber threshold of the warm start before a redescending loss
HUBER_WARM_SCALE = 1.5
#: "nlos" loss with nlos_adapt: bounds of the per-user NLoS probability π_k, the most rounds of
#: (solve, re-estimate π_k), and the change of π_k below which the rounds stop
NLOS_PROB_MIN = 0.005
NLOS_PROB_MAX = 0.5
NLOS_EM_ROUNDS = 10
NLOS_EM_TOL = 1e-4
#: step tolerance of the solves while π_k is still being re-estimated [m]
NLOS_ROUND_STEP_M = 1e-3
#: per-user range-noise scale (params.estimate_noise_scale): upper bound, fewest degrees of
#: freedom to estimate it from, relative change below which it is not re-solved, and most rounds
NOISE_SCALE_MAX = 10.0
NOISE_SCALE_MIN_DOF = 8
NOISE_SCALE_RESOLVE = 0.1
NOISE_SCALE_ROUNDS = 6
#: bias selection (params.bias_select): a bias below this many of its standard deviations is
#: fixed at 0 by a prior of BIAS_OFF_SIGMA_M
BIAS_SELECT_Z = 4.0
BIAS_OFF_SIGMA_M = 1e-3
#: ... and kept only when determined to this standard deviation [m] (a bias the geometry barely
#: separates from the position trades a large position error for a small fit gain)
BIAS_SELECT_MAX_SD_M = 1.5
#: clock tracking (params.track_clock): a user is tested for a sawtooth when its residuals' RMS
#: exceeds CLOCK_TRIGGER_SCALE σ(d) and it has CLOCK_MIN_RANGES ranges; rounds of fit + re-solve
CLOCK_TRIGGER_SCALE = 1.08
CLOCK_MIN_RANGES = 40
CLOCK_ROUNDS = 3


#: the 6 distinct entries (i ≤ j) of a symmetric 3×3: row and column indices, their flat index,
#: the flat index of their mirror (i > j) and of the entry they copy; _SYM3_OF[i, j]: which of
#: the 6 holds entry (i, j)
_SYM3_I = np.array([0, 0, 0, 1, 1, 2])
_SYM3_J = np.array([0, 1, 2, 1, 2, 2])
_SYM3_FLAT = 3 * _SYM3_I + _SYM3_J
_SYM3_LOWER = np.array([3, 6, 7])
_SYM3_UPPER = np.array([1, 2, 5])
_SYM3_OF = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])


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
    hxu: np.ndarray  # (N, 3, K·p)
    huu: np.ndarray  # (K·p, K·p)
    gx: np.ndarray  # (N, 3)
    gu: np.ndarray  # (K·p,)
    e: np.ndarray  # (K, N) whitened range residuals, 0 where none
    w: np.ndarray  # (K, N) IRLS weights, 0 where none
    rho_k: np.ndarray | None = None  # (K,) Σ_n ρ(e) of each user's ranges


def _residuals(prob: Problem, x: np.ndarray, theta: np.ndarray, mask_kn: np.ndarray) -> tuple:
    """Range residuals, user-major: (diff (3, K, n) = x_i − u_k, d (K, n), σ (K, n) or scalar,
    r = r̂ − d − b (K, n), e = r/σ (K, n), full), r and e zero where mask_kn (K, n) is False;
    full: mask_kn is all True. Shapes as in `_range_terms`."""
    noise = prob.noise
    n = x.shape[0]
    users = users_from_theta(theta, prob.user_up_m, prob.user_dim)
    # diff_i = x_i − u_i, (3, K, n)
    diff = np.ascontiguousarray(x.T)[:, None, :] - users.T[:, :, None]
    d = np.sqrt(diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2])
    np.maximum(d, 1e-9, out=d)
    # σ_k(d) = s_k σ(d); a scalar (or (K, 1)) when it does not depend on d (cheaper loss evaluation)
    sig = noise.s0_m if noise.a_m == 0.0 else noise.range_sigma_m(d)
    if prob.noise_scale_k is not None:
        sig = sig * prob.noise_scale_k[:, None]
    # every user ranged from every keyframe (the common case): no masking passes
    full = bool(mask_kn.all())
    r = prob.range_m[:n].T - d
    if prob.params.estimate_bias:
        # b_k g_nk: the bias, or a tracked clock sawtooth's amplitude times its shape
        r -= theta[:, -1:] if prob.bias_gain is None else theta[:, -1:] * prob.bias_gain[:n].T
    if not full:
        r[~mask_kn] = 0.0
    # e = (r̂ − d − b) / σ(d)
    return diff, d, sig, r, r / sig, full


def _nlos_args(prob: Problem, sig: np.ndarray | float) -> tuple:
    """(π (K, 1) or scalar, whitened NLoS mean m) of the "nlos" loss for ranges of σ `sig`."""
    pi = prob.params.nlos_prob if prob.nlos_prob_k is None else prob.nlos_prob_k[:, None]
    return pi, prob.params.nlos_mean_m / sig


def _range_terms(
    prob: Problem, x: np.ndarray, theta: np.ndarray, mask_kn: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Whitened range residuals and Jacobians (see estimator.factors.RangeFactor), user-major.

    x: (n, 3); theta: (K, p); mask_kn: (K, n) ranges to use; ranges are prob.range_m[:n].
    Arrays are laid out (K, n) so that numpy's inner loops run over keyframes (long), not over
    3 coordinates. Returns e, w, rho (K, n), J (3 + p, K, n) = [∂e/∂x; ∂e/∂θ_k] and ψ = ρ'(e)
    (K, n), zero where mask_kn is False.
    """
    params, noise = prob.params, prob.noise
    n = x.shape[0]
    d_u = prob.user_dim
    diff, d, sig, r, e, full = _residuals(prob, x, theta, mask_kn)
    nl = _nlos_args(prob, sig) if params.loss == "nlos" else None
    rho, psi, w = loss_psi_weight(e, params.loss, params.loss_scale, nl)
    if not full:
        w = w * mask_kn
        psi = psi * mask_kn
        rho = rho * mask_kn
    # α = 1/σ + r σ'/σ²;  ∂e/∂x = −α û, ∂e/∂u = α û, ∂e/∂b = −1/σ
    if noise.a_m != 0.0 and noise.b_per_m != 0.0:
        dsig = noise.range_sigma_dd(d)
        if prob.noise_scale_k is not None:
            dsig = dsig * prob.noise_scale_k[:, None]
        alpha = 1.0 / sig + r * dsig / sig**2
        if not full:
            alpha *= mask_kn
    else:
        alpha = 1.0 / sig if full else mask_kn / sig
    jac = np.empty((3 + prob.p, prob.n_users, n))
    np.multiply(diff, np.divide(-alpha, d), out=jac[:3])
    np.negative(jac[:d_u], out=jac[3 : 3 + d_u])
    if params.estimate_bias:
        # ∂e/∂b = −g/σ
        np.divide(-1.0, sig, out=jac[-1])
        if prob.bias_gain is not None:
            jac[-1] *= prob.bias_gain[:n].T
        if not full:
            jac[-1] *= mask_kn
    return e, w, rho, jac, psi


def linearize(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None
) -> Linearization:
    """IRLS-weighted normal equations H Δ = g (g = −∇L) at (x (N, 3), Θ (K, p)).

    Per range, with J = [∂e/∂x | ∂e/∂θ_k] (1 × (3 + p)):
        H_nn = I/σ_gps² + Σ_k w J_xᵀ J_x,   H_(n,k) = w J_xᵀ J_θ,   H_kk = Σ_n w J_θᵀ J_θ
        g_n = −(x_n − x̂_n)/σ_gps² − Σ_k ψ J_x,   g_k = −Σ_n ψ J_θ      (+ bias, motion, prior)
    with ψ = ρ'(e) (= w e except for the "nlos" loss, estimator.robust).
    Users with active[k] False are held fixed (identity block, zero gradient).
    """
    params, noise = prob.params, prob.noise
    n, k_all = prob.range_m.shape
    p = prob.p
    mask_kn = prob.mask[:n].T & active[:, None]
    e, w, rho, jac, psi = _range_terms(prob, x, theta, mask_kn)
    linked = prob.gps_linked
    if linked:
        # Gauss–Markov GPS factors (estimator.gps): diagonal, off-diagonal and gradient terms
        gt = gps_chain_terms(x, prob.gps_enu_m[:n], prob.gps_phi(), noise.sigma_gps_m, prob.gps_first)
        inv_g2 = 0.0
        dgps = np.zeros_like(x)
        cost = gt.cost + float(rho.sum())
    else:
        inv_g2 = 1.0 / noise.sigma_gps_m**2
        dgps = x - prob.gps_enu_m
        cost = 0.5 * inv_g2 * float(np.vdot(dgps, dgps)) + float(rho.sum())
    # J_θ = [−J_x[:d], (J_b)]: every block comes from the 6 distinct products O_ij = w J_x,i J_x,j
    # (i ≤ j, each (K, n)) and, with a bias, B_i = w J_x,i J_b and w J_b²:
    #   H_nn = Σ_k O (+ GPS),  H_(n,k) = [−O[:, :d], B],  H_kk = [[Σ_n O[:d, :d], −Σ_n B[:d]], [·, Σ_n w J_b²]]
    d_u = prob.user_dim
    # the 6 products, stacked (6, K, n) in the order of _SYM3 (one pass each for all of them)
    o6 = (jac[_SYM3_I] * w) * jac[_SYM3_J]
    hxx = np.empty((n, 9))
    hxx[:, _SYM3_FLAT] = o6.sum(axis=1).T
    hxx[:, _SYM3_LOWER] = hxx[:, _SYM3_UPPER]
    hxx = hxx.reshape(n, 3, 3)
    # H_(n,k)[i, j] = −O_ij (i < 3, j < d): (3, d, K, n) -> (n, 3, K, d), in one pass
    sel = _SYM3_OF[:, :d_u].ravel()
    hxu = np.empty((n, 3, k_all, p))
    np.negative(o6[sel].reshape(3, d_u, k_all, n).transpose(3, 0, 2, 1), out=hxu[..., :d_u])
    # H_kk[i, j] = Σ_n O_ij (i, j < d)
    huu_blocks = np.empty((k_all, p, p))
    huu_blocks[:, :d_u, :d_u] = o6[_SYM3_OF[:d_u, :d_u].ravel()].sum(axis=2).reshape(d_u, d_u, k_all).transpose(2, 0, 1)
    # g_n = −(x_n − x̂_n)/σ_gps² − Σ_k ψ J_x,  g_k = −Σ_n ψ J_θ = [Σ_n ψ J_x[:d], −Σ_n ψ J_b]
    jpsi = jac[:3] * psi
    gx = -dgps * inv_g2 - jpsi.sum(axis=1).T
    gu = np.empty((k_all, p))
    gu[:, :d_u] = jpsi[:d_u].sum(axis=2).T
    if params.estimate_bias:
        jb = jac[-1]
        wjb = w * jb
        ob = jac[:3] * wjb  # B_i = w J_x,i J_b, (3, K, n)
        hxu[..., d_u] = ob.transpose(2, 0, 1)
        sb_u = ob[:d_u].sum(axis=2).T  # (K, d)
        huu_blocks[:, :d_u, d_u] = -sb_u
        huu_blocks[:, d_u, :d_u] = -sb_u
        huu_blocks[:, d_u, d_u] = (wjb * jb).sum(axis=1)
        gu[:, d_u] = -(psi * jb).sum(axis=1)
    hxu = hxu.reshape(n, 3, k_all * p)
    off = None
    if linked:
        hxx.reshape(n, 9)[:, ::4] += gt.diag[:, None]
        gx -= gt.grad
        off = gt.off.copy()
    else:
        hxx.reshape(n, 9)[:, ::4] += inv_g2
    if params.estimate_bias:
        # bias prior e_k = b_k / σ_b,k (σ_b,k tiny where the bias was selected off)
        sb = params.bias_prior_sigma_m if prob.bias_sigma_k is None else prob.bias_sigma_k
        inv_b2 = np.broadcast_to(1.0 / np.square(sb), (k_all,))
        bias = theta[:, -1]
        huu_blocks[:, -1, -1] += inv_b2
        gu[:, -1] -= bias * inv_b2
        cost += 0.5 * float(np.sum((inv_b2 * bias * bias)[active]))
    if not active.all():
        inactive = ~active
        huu_blocks[inactive] = np.eye(p)
        gu[inactive] = 0.0
    huu = np.zeros((k_all, p, k_all, p))
    ks = np.arange(k_all)
    huu[ks, :, ks, :] = huu_blocks  # block diagonal
    huu = huu.reshape(k_all * p, k_all * p)
    gu = gu.ravel()
    if prob.use_motion:
        inv_m2 = 1.0 / params.motion_sigma_m**2
        om = prob.odom_mask[1:n]
        # e_m = (x_n − x_(n−1) − ô_n)/σ_m for linked pairs
        em = (x[1:] - x[:-1] - prob.odom_enu_m[1:n]) * om[:, None]
        cost += 0.5 * inv_m2 * float(np.vdot(em, em))
        add = inv_m2 * om
        hxx.reshape(n, 9)[1:, ::4] += add[:, None]
        hxx.reshape(n, 9)[:-1, ::4] += add[:, None]
        off = -add if off is None else off - add
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
            hxu[0] += prior.info[:3, 3:]
            gx[0] -= grad[:3]
            huu += prior.info[3:, 3:]
            gu -= grad[3:]
        else:
            huu += prior.info
            gu -= grad
    return Linearization(cost, hxx, off, hxu, huu, gx, gu, e, w, rho.sum(axis=1))


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
    """Minimise L from (x, Θ); stop when the largest user step component, or the distance still
    to go estimated from the contraction of the last two steps, is below params.step_tol_m (or
    step_tol_m) — or the users' step still to go is below params.step_tol_sigma of their
    standard deviations, ||Δθ||_S = √(Δθᵀ S Δθ) — and the same for the keyframes (absolute
    only) with the larger of step_tol_m and params.step_tol_uav_m.

    The returned S (undamped Schur complement) belongs to the last linearization point, which
    differs from the returned estimate by the last step (below the tolerances above).
    """
    params = prob.params
    max_it = params.max_iterations if max_iterations is None else max_iterations
    tol = params.step_tol_m if step_tol_m is None else step_tol_m
    sig_tol = float(params.step_tol_sigma)
    lin = linearize(prob, x, theta, active, prior)
    lam = 0.0
    s_final = None
    converged = False
    prev: tuple[float, float] | None = None  # (user, keyframe) sizes of the last undamped step
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
        # the users' step in their standard deviations, ||Δθ||_S (S undamped only at λ = 0)
        su_sigma = math.sqrt(max(float(du @ s @ du), 0.0)) if (sig_tol > 0.0 and lam == 0.0) else math.inf
        du = du.reshape(theta.shape)
        su, sx = float(np.max(np.abs(du))), float(np.max(np.abs(dx)))
        # distance still to go after this step: Gauss–Newton on these problems converges
        # linearly, each step r times the previous one (r the ratio of the last two undamped
        # steps), so the steps after this one add up to step·r/(1 − r)
        left_u, left_x, left_sigma = su, sx, su_sigma
        if prev is not None and lam == 0.0:
            ru, rx = su / max(prev[0], 1e-300), sx / max(prev[1], 1e-300)
            if ru < 0.5:
                left_u = su * ru / (1.0 - ru)
                left_sigma = su_sigma * ru / (1.0 - ru)
            if rx < 0.5:
                left_x = sx * rx / (1.0 - rx)
        # users to tol (or to sig_tol of their σ); keyframes (σ_gps ~ 1 m) to the looser
        # params.step_tol_uav_m
        users_done = min(su, left_u) < tol or min(su_sigma, left_sigma) < sig_tol
        if users_done and min(sx, left_x) < max(tol, params.step_tol_uav_m):
            x = x + dx
            theta = theta + du
            s_final = s if lam == 0.0 else None
            converged = True
            break
        x_t, th_t = x + dx, theta + du
        lin_t = linearize(prob, x_t, th_t, active, prior)
        if lin_t.cost <= lin.cost + 1e-12 * abs(lin.cost):
            x, theta, lin = x_t, th_t, lin_t
            prev = (su, sx) if lam == 0.0 else None
            lam = 0.0 if lam <= _LAM_START else lam / 10.0
        else:
            prev = None
            lam = max(_LAM_START, 10.0 * lam)
            if lam > _LAM_MAX:
                break
    if s_final is None:
        try:
            _, _, s_final = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, 0.0)
        except (np.linalg.LinAlgError, EstimatorError):
            s_final = None
    return _Result(x, theta, lin, s_final, it, converged)


def nlos_prob_update(prob: Problem, gamma: np.ndarray, active: np.ndarray) -> np.ndarray:
    """(K,) maximum-likelihood NLoS probability of each user at the residuals where the posterior
    LoS probabilities gamma (K, n) (0 where no range; Linearization.w) were evaluated.

    With q_i = f(e_i)/φ(e_i) the NLoS/LoS density ratio of range i, the log-likelihood of user
    k's ranges in π is Σ_i log(1 + π (q_i − 1)) (+ const), concave, with derivative

        D(π) = Σ_i a_i / (1 + π a_i),   D'(π) = −Σ_i (a_i / (1 + π a_i))²,   a_i = q_i − 1,

    solved by Newton's method within [NLOS_PROB_MIN, NLOS_PROB_MAX] (the root, or the bound
    where D keeps its sign). q is recovered from the posterior LoS probability γ at the
    current π: γ = (1 − π)/((1 − π) + π q)  ⇒  q = (1 − π)(1 − γ)/(π γ)  (inf where γ
    underflowed to 0, where the term a/(1 + πa) is 1/π). Inactive users keep their π.
    """
    n = gamma.shape[1]
    use = prob.mask[:n].T & active[:, None]
    pi0 = prob.nlos_prob_k.copy()
    gam = gamma
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        q = (1.0 - pi0)[:, None] * (1.0 - gam) / (pi0[:, None] * gam)
    huge = use & ~np.isfinite(q)
    a = np.where(use & ~huge, q - 1.0, 0.0)
    n_huge = huge.sum(axis=1)

    def slope(p: np.ndarray | float, a: np.ndarray, n_huge: np.ndarray, curvature: bool = True) -> tuple:
        # D(π) and D'(π) of every row of a; p scalar or (rows,)
        t = a / (1.0 + (p[:, None] if np.ndim(p) else p) * a)
        d = t.sum(axis=1) + n_huge / p
        return (d, -(t * t).sum(axis=1) - n_huge / (p * p)) if curvature else (d, None)

    # D is decreasing: D(π_min) ≤ 0 puts the maximum on the lower bound (the LoS case, no
    # iteration), D(π_max) ≥ 0 on the upper one; Newton's method for the others
    pi = np.minimum(np.maximum(pi0, NLOS_PROB_MIN), NLOS_PROB_MAX)
    lo = slope(NLOS_PROB_MIN, a, n_huge, curvature=False)[0] <= 0.0
    pi[lo] = NLOS_PROB_MIN
    free = ~lo
    if free.any():
        hi = free & (slope(NLOS_PROB_MAX, a, n_huge, curvature=False)[0] >= 0.0)
        pi[hi] = NLOS_PROB_MAX
        free &= ~hi
    if free.any():
        af, nf, pf = a[free], n_huge[free], pi[free]
        for _ in range(40):
            d, dp = slope(pf, af, nf)
            new = np.clip(pf - d / np.minimum(dp, -1e-300), NLOS_PROB_MIN, NLOS_PROB_MAX)
            done = float(np.max(np.abs(new - pf))) < 1e-13
            pf = new
            if done:
                break
        pi[free] = pf
    pi[~active] = pi0[~active]
    return pi


def noise_scale_update(prob: Problem, lin: Linearization, active: np.ndarray) -> np.ndarray:
    """(K,) per-user range-noise scale s_k from the residuals of a solve (σ_k(d) = s_k σ(d)).

    With e the whitened residuals at the current scale s_k and w their weights (the LoS
    posterior of the "nlos" loss, the IRLS weight otherwise; Linearization.w), the maximum-
    likelihood variance factor of user k's ranges, corrected for its p fitted parameters, is

        s_k'² = s_k² · Σ_n w e² / (Σ_n w − p)

    kept within [1, NOISE_SCALE_MAX]: the assumed σ(d) is a floor (a UE is not taken to be
    better than configured), and a user with fewer than NOISE_SCALE_MIN_DOF degrees of freedom
    keeps its scale. Inactive users keep theirs.
    """
    old = np.ones(prob.n_users) if prob.noise_scale_k is None else prob.noise_scale_k
    w, e = lin.w, lin.e
    n_eff = w.sum(axis=1)
    dof = n_eff - prob.p
    chi2 = (w * e * e).sum(axis=1)
    ok = active & (dof >= NOISE_SCALE_MIN_DOF)
    new = old.copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        # s'² = s² χ² / dof
        fit = old * np.sqrt(chi2 / np.maximum(dof, 1e-9))
    new[ok] = np.clip(fit[ok], 1.0, NOISE_SCALE_MAX)
    return new


def solve_robust(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None,
    step_tol_m: float | None = None,
) -> _Result:
    """:func:`solve_loss` and, with params.estimate_noise_scale, the per-user range-noise scale
    re-estimated from the solution's residuals (noise_scale_update, stored in prob.noise_scale_k):
    the problem is re-solved while a scale moves by more than NOISE_SCALE_RESOLVE (relative), and
    a smaller last change only re-linearizes at the solution so that the covariance uses it; at
    most NOISE_SCALE_ROUNDS rounds. A user whose ranges are noisier than the assumed σ(d) then
    gets a covariance that says so.

    With params.estimate_bias and params.bias_select (and prob.bias_sigma_k not yet chosen) the
    biases are selected: the problem is solved with every bias fixed at 0 (prior σ
    BIAS_OFF_SIGMA_M, in prob.bias_sigma_k), then one Gauss–Newton step of the model with free
    biases from that solution gives each bias b̂_k and its standard deviation sd_k (S⁻¹ there:
    the score test of b_k = 0; from that solve's S and the ranges' gradient, no new
    linearization). A user keeps its bias when |b̂_k| ≥ BIAS_SELECT_Z · sd_k and
    sd_k ≤ BIAS_SELECT_MAX_SD_M, and the problem is solved again with those biases free. A UE
    without a clock offset pays nothing for the unknown; one with a sawtooth keeps it. (A full
    solve of the free model instead of the step wanders, where the geometry barely separates a
    bias from the position, into basins 5–13 m away that fit a little better.)"""
    params = prob.params
    if not (params.estimate_bias and params.bias_select and prob.bias_sigma_k is None):
        return _solve_scaled(prob, x, theta, active, prior, step_tol_m)
    k_all, d_u = prob.n_users, prob.user_dim
    # every bias held at 0 by the tight prior σ_off
    inv_off2 = 1.0 / BIAS_OFF_SIGMA_M**2
    inv_free2 = 1.0 / params.bias_prior_sigma_m**2
    prob.bias_sigma_k = np.full(k_all, BIAS_OFF_SIGMA_M)
    theta = theta.copy()
    theta[:, -1] = 0.0
    res = _solve_scaled(prob, x, theta, active, prior, step_tol_m)
    ib = np.arange(k_all) * prob.p + d_u
    keep = np.zeros(k_all, dtype=bool)
    b_step = np.zeros(k_all)
    if res.s is not None:
        # the free model at this solution without a new linearization: its Schur complement
        # differs by the bias priors only (they enter H_uu alone), and its reduced gradient is the
        # ranges' pull on b, −∂L_ranges/∂b = −Σ_n ψ J_b, minus the free prior's b/σ_b² (the other
        # parameters' gradient is zero at the optimum)
        s_free = res.s.copy()
        s_free[ib, ib] -= inv_off2 - inv_free2
        n = res.x.shape[0]
        _, _, _, jac, psi = _range_terms(prob, res.x, res.theta, prob.mask[:n].T & active[:, None])
        g = np.zeros(s_free.shape[0])
        g[ib] = -(psi * jac[-1]).sum(axis=1) - res.theta[:, -1] * inv_free2
        try:
            cov = np.linalg.inv(s_free)
        except np.linalg.LinAlgError:
            cov = None
        if cov is not None and np.all(np.isfinite(cov)):
            b_step = res.theta[:, -1] + (cov @ g)[ib]
            sd = np.sqrt(np.maximum(np.diag(cov)[ib], 0.0))
            keep = active & (np.abs(b_step) >= BIAS_SELECT_Z * sd) & (sd <= BIAS_SELECT_MAX_SD_M)
    if prob.bias_force_k is not None:
        keep |= active & prob.bias_force_k
    if not keep.any():
        return res
    prob.bias_sigma_k = np.where(keep, params.bias_prior_sigma_m, BIAS_OFF_SIGMA_M)
    theta = res.theta.copy()
    theta[keep, -1] = b_step[keep]
    return _solve_scaled(prob, res.x, theta, active, prior, step_tol_m)


def _solve_scaled(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None,
    step_tol_m: float | None,
) -> _Result:
    """solve_loss, then rounds of noise_scale_update (see solve_robust)."""
    res = solve_loss(prob, x, theta, active, prior, step_tol_m)
    if not prob.params.estimate_noise_scale:
        return res
    if prob.noise_scale_k is None:
        prob.noise_scale_k = np.ones(prob.n_users)
    for _ in range(NOISE_SCALE_ROUNDS):
        new = noise_scale_update(prob, res.lin, active)
        ratio = new / prob.noise_scale_k
        change = float(np.max(np.abs(ratio - 1.0)))
        if change == 0.0:
            break
        prob.noise_scale_k = new
        if change <= NOISE_SCALE_RESOLVE:
            # a small change moves the solution by a fraction of its σ: keep it, and scale the
            # information of user k by 1/s_k (S' = D S D, D = diag(1/ratio_k) per parameter). A
            # user's information comes mostly from its own ranges, which scale exactly so; the
            # GPS part scaled too makes S' slightly conservative.
            if res.s is not None:
                # (the bias priors do not scale: S' = D (S − B) D + B)
                dvec = np.repeat(1.0 / ratio, prob.p)
                prior_b = np.zeros(prob.n_users * prob.p)
                if prob.params.estimate_bias:
                    sb = prob.params.bias_prior_sigma_m if prob.bias_sigma_k is None else prob.bias_sigma_k
                    prior_b[prob.user_dim :: prob.p] = 1.0 / np.square(sb)
                s_new = (res.s - np.diag(prior_b)) * dvec[:, None] * dvec[None, :] + np.diag(prior_b)
                res = _Result(res.x, res.theta, res.lin, s_new, res.iterations, res.converged)
            break
        res = solve_loss(prob, res.x, res.theta, active, prior, step_tol_m)
    return res


def solve_loss(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None,
    step_tol_m: float | None = None,
) -> _Result:
    """Levenberg–Marquardt with the loss's schedule: a redescending loss starts from a Huber
    solution; "nlos" with params.nlos_adapt alternates solves with the maximum-likelihood π_k at
    the solution's residuals (nlos_prob_update, stored in prob.nlos_prob_k) until no π_k moves
    by more than NLOS_EM_TOL: a joint maximum of the likelihood in (x, θ, π)."""
    params = prob.params
    if params.loss in REDESCENDING:
        # a redescending loss ignores what it deems outliers: start it from the Huber solution
        warm = replace(prob, params=replace(params, loss="huber", loss_scale=HUBER_WARM_SCALE))
        pre = levenberg_marquardt(warm, x, theta, active, prior, step_tol_m=step_tol_m)
        x, theta = pre.x, pre.theta
    if params.loss != "nlos" or not params.nlos_adapt:
        return levenberg_marquardt(prob, x, theta, active, prior, step_tol_m=step_tol_m)
    if prob.nlos_prob_k is None:
        # π_k from params.nlos_prob re-estimated at the starting residuals (at LoS it drops to
        # the floor at once, and the solve runs near-quadratic from the first iteration)
        prob.nlos_prob_k = np.full(prob.n_users, float(params.nlos_prob))
        mask_kn = prob.mask[: x.shape[0]].T & active[:, None]
        _, _, sig, _, e, _ = _residuals(prob, x, theta, mask_kn)
        gamma = nlos_terms(e, *_nlos_args(prob, sig), need_rho=False)[2] * mask_kn
        prob.nlos_prob_k = nlos_prob_update(prob, gamma, active)
    tol = params.step_tol_m if step_tol_m is None else step_tol_m
    # while π_k still moves, solve only to NLOS_ROUND_STEP_M; then to tol (all π_k on the
    # floor, i.e. LoS: to tol at once)
    tight = bool(np.all(prob.nlos_prob_k[active] <= NLOS_PROB_MIN))
    for _ in range(NLOS_EM_ROUNDS):
        res = levenberg_marquardt(
            prob, x, theta, active, prior, step_tol_m=tol if tight else max(tol, NLOS_ROUND_STEP_M))
        pi = nlos_prob_update(prob, res.lin.w, active)
        moved = float(np.max(np.abs(pi - prob.nlos_prob_k)))
        if moved <= NLOS_EM_TOL:
            if tight:
                break
            tight = True
        prob.nlos_prob_k = pi
        x, theta = res.x, res.theta
    return res


def _grid_init(prob: Problem, uav: np.ndarray, users: Sequence[int]) -> dict[int, np.ndarray]:
    """Initial θ_k of the given users by grid search, UAV at `uav` (n, 3), users ranged from the
    same keyframes searched together (estimator.init.init_users). Returns {k: θ_k (p,)}."""
    n = uav.shape[0]
    mask = prob.mask[:n]
    groups: dict[bytes, list[int]] = {}
    for k in users:
        groups.setdefault(mask[:, k].tobytes(), []).append(int(k))
    out = {}
    for ks in groups.values():
        rows = mask[:, ks[0]]
        fits = init_users(uav[rows], prob.range_m[:n][rows][:, ks], prob.user_up_m[ks], prob.noise, prob.params)
        out.update({k: f.theta for k, f in zip(ks, fits, strict=True)})
    return out


def _mirror_all(
    prob: Problem, theta: np.ndarray, active: np.ndarray, n_rows: int | None = None
) -> list:
    """Mirror test per user on the first n_rows keyframes (UAV at GPS). None for inactive users."""
    n = prob.n_keyframes if n_rows is None else n_rows
    out: list = [None] * prob.n_users
    mask = prob.mask[:n]
    # users ranged from the same keyframes share the fitted line and the smoothed track: test
    # each such group at once
    groups: dict[bytes, list[int]] = {}
    for k in np.flatnonzero(active).tolist():
        groups.setdefault(mask[:, k].tobytes(), []).append(k)
    for ks in groups.values():
        rows = mask[:, ks[0]]
        tests = mirror_tests(
            prob.gps_enu_m[:n][rows], prob.range_m[:n][rows][:, ks], theta[ks], prob.user_up_m[ks],
            prob.noise, prob.params, prob.params.ambiguity_chi2,
        )
        for k, mt in zip(ks, tests, strict=True):
            out[k] = mt
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
    ka_ = np.arange(na)
    blocks = cov_a4[ka_, :d, ka_, :d]  # the diagonal blocks, (na, d, d)
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
    if prob.nlos_prob_k is not None:
        extra["nlos_prob_k"] = prob.nlos_prob_k.copy()  # (K,) π_k the "nlos" loss ended with
    extra["noise_scale"] = (np.ones(k_all) if prob.noise_scale_k is None else prob.noise_scale_k.copy())
    if prob.params.estimate_bias:
        # (K,) True where the range bias is estimated (False: selected off, fixed at 0)
        sb = prob.bias_sigma_k
        extra["bias_on"] = np.ones(k_all, dtype=bool) if sb is None else sb > BIAS_OFF_SIGMA_M
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
    search = []
    for k in np.flatnonzero(active):
        if given is not None and np.all(np.isfinite(given[k])):
            theta[k] = 0.0
            theta[k, : prob.user_dim] = given[k, : prob.user_dim]
        else:
            search.append(k)
    for k, th in _grid_init(prob, x, search).items():
        theta[k] = th
    theta[~active] = 0.0
    res = solve_robust(prob, x, theta, active)
    clocks: list = [None] * k_all
    if params.track_clock and prob.t_s is not None:
        res, clocks = _track_clocks(prob, res, active)
    res, mirrors = _resolve_mirrors(prob, res, active)
    est = _estimate(prob, res, active, mirrors, n_ranges)
    est.extra["clock"] = clocks
    return est


def _track_clocks(prob: Problem, res: _Result, active: np.ndarray) -> tuple[_Result, list]:
    """Fit a clock sawtooth (estimator.clock) to each user whose range residuals are noisier than
    its σ(d) by CLOCK_TRIGGER_SCALE; an accepted fit turns the user's bias into the sawtooth's
    amplitude, r̂ = d + A_k · frac(t/P_k − φ_k) (prob.bias_gain, the bias kept free), so that A_k is
    estimated with the positions and its uncertainty enters their covariance; then solve again.
    CLOCK_ROUNDS rounds, each refitting (P, φ) on the residuals of the last solution.
    Returns (result, [SawtoothFit or None] per user)."""
    n = prob.n_keyframes
    fits: list = [None] * prob.n_users
    t = prob.t_s[:n]
    gain = np.ones((n, prob.n_users))
    for _ in range(CLOCK_ROUNDS):
        users = users_from_theta(res.theta, prob.user_up_m, prob.user_dim)
        d = np.linalg.norm(res.x[:, None, :] - users[None, :, :], axis=2)
        sig = prob.noise.range_sigma_m(d)
        bias = res.theta[:, -1] if prob.params.estimate_bias else np.zeros(prob.n_users)
        # only ranges the loss keeps (weight ≥ ½): an NLoS excess is no sawtooth
        kept = res.lin.w.T >= 0.5
        if not any(fits):
            # the trigger for all users at once: RMS of the whitened residuals about their mean
            # (the noise scale undone: the test is against the assumed σ(d))
            wk = kept.T & prob.mask[:n].T
            cnt = np.maximum(wk.sum(axis=1), 1)
            sc = np.ones(prob.n_users) if prob.noise_scale_k is None else prob.noise_scale_k
            e = res.lin.e * sc[:, None]
            mean = (e * wk).sum(axis=1) / cnt
            rms = np.sqrt((((e - mean[:, None]) ** 2) * wk).sum(axis=1) / cnt)
            if not np.any(active & (rms >= CLOCK_TRIGGER_SCALE) & (cnt >= CLOCK_MIN_RANGES)):
                break
        changed = False
        for k in np.flatnonzero(active):
            rows = prob.mask[:n, k] & kept[:, k]
            if int(rows.sum()) < CLOCK_MIN_RANGES:
                continue
            # r̂ − d: the sawtooth (or bias) and the noise
            r = prob.range_m[rows, k] - d[rows, k]
            if fits[k] is None:
                dev = r - bias[k] - np.mean(r - bias[k])
                if math.sqrt(float(np.mean((dev / sig[rows, k]) ** 2))) < CLOCK_TRIGGER_SCALE:
                    continue
            fit = fit_sawtooth(t[rows], r)
            if fit is None:
                continue
            fits[k] = fit
            all_k = prob.mask[:n, k]
            gain[all_k, k] = fit.value_m(t[all_k]) / fit.amplitude_m
            res.theta[k, -1] = fit.amplitude_m
            changed = True
        if not changed or not prob.params.estimate_bias:
            break
        prob.bias_gain = gain.copy()
        prob.noise_scale_k, prob.bias_sigma_k = None, None
        prob.bias_force_k = np.array([f is not None for f in fits])
        res = solve_robust(prob, res.x, res.theta, active)
    return res, fits


def _inv3_sym(a00: float, a01: float, a02: float, a11: float, a12: float, a22: float) -> np.ndarray:
    """(3, 3) inverse of the symmetric matrix [[a00 a01 a02] [a01 a11 a12] [a02 a12 a22]] by
    cofactors, A⁻¹ = adj(A)/det(A), in Python floats (one small matrix: cheaper than numpy)."""
    c00, c01, c02, c11, c12, c22, det = sym3_cofactors(a00, a01, a02, a11, a12, a22)
    r = 1.0 / det
    return np.array([[c00 * r, c01 * r, c02 * r], [c01 * r, c11 * r, c12 * r], [c02 * r, c12 * r, c22 * r]])


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
        # a full solve marginalizes down to `window` keyframes; the filter steps in between add
        # up to online_resolve_every − 1 more
        cap = int(params.window) + max(int(params.online_resolve_every), 1)
        self._cap = cap
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
        # per-user NLoS probability of the "nlos" loss, re-estimated by each full solve
        self._nlos_pi = np.full(self._k, float(params.nlos_prob))
        self._win_count = np.zeros(self._k, dtype=int)  # ranges per user in the window
        self._min_start = max(self._p + 1, ONLINE_MIN_RANGES)
        self._s: np.ndarray | None = None  # users' information S at the last solution
        self._cost = float("nan")
        self._last_check = 0
        self._inv_g2 = 1.0 / noise.sigma_gps_m**2
        self._diag3 = np.diag_indices(3)
        self._arange_p = np.arange(self._p)[None, :]
        self._arange_k = np.arange(self._k)
        self._bd_cache: dict[int, np.ndarray] = {}
        self._k_list = list(range(self._k))
        self._all_active = False  # cached self._active.all()
        self._nlos_pi_list = self._nlos_pi.tolist()
        self._users = np.zeros((self._k, 3))  # (K, 3) users_from_theta(θ), kept in step with θ
        self._t = np.zeros(cap)  # keyframe times [s] (Gauss–Markov GPS links)
        self._gps_linked = noise.gps_tau_used_s > 0.0
        self._gps_first = True  # window keyframe 0 carries its own GPS prior (nothing marginalized yet)
        self._scale = np.ones(self._k)  # per-user range noise scale s_k, re-estimated by each full solve
        self._scale_list = self._scale.tolist()
        self._bias_sigma: np.ndarray | None = None  # bias selection of the last full solve

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
            self._noise, self._params, self._nlos_pi, t_s=self._t[:n], gps_first=self._gps_first,
            noise_scale_k=self._scale if self._params.estimate_noise_scale else None,
            bias_sigma_k=self._bias_sigma,
        )

    def add_keyframe(self, kf: Keyframe) -> Estimate:
        """Add one keyframe with its ranges; return the updated Estimate.

        Between full window solves (every params.online_resolve_every keyframes, or whenever a
        user starts, a motion factor links the keyframe, the window is full or the filter step
        is large) the keyframe is folded in by one information-filter step (_filter_step).
        """
        gps, idx, rng, odom = check_keyframe(kf, self._k)
        n = self._n
        self._gps[n] = gps
        self._rng[n] = np.nan
        self._rng[n, idx] = rng
        self._odom_mask[n] = odom is not None and n + self._seen > 0 and self._params.motion_sigma_m is not None
        self._t[n] = float(kf.t_s)
        self._odom[n] = odom if odom is not None else 0.0
        self._win_count[idx] += 1
        self._n_ranges[idx] += 1
        self._seen += 1
        self._n = n + 1
        every = int(self._params.online_resolve_every)
        if (
            every > 1 and self._s is not None and not self._odom_mask[n] and self._n < self._cap
            and not self._gps_linked
            and self._seen % every != 0
            and (self._all_active or not (~self._active[idx] & (self._win_count[idx] >= self._min_start)).any())
        ):
            est = self._filter_step(n, gps, idx, rng)
            if est is not None:
                self._estimate = est
                return est
        est = self._full_update(n, gps, idx, rng, odom)
        self._estimate = est
        return est

    def _full_update(
        self, n: int, gps: np.ndarray, idx: np.ndarray, rng: np.ndarray, odom: np.ndarray | None,
    ) -> Estimate:
        """Start users that are ready, re-solve the window (Levenberg–Marquardt from the previous
        solution, with the prior), re-check mirrors, marginalize down to params.window."""
        # a new keyframe starts at its GPS fix, or dead-reckoned from the previous one, moved to
        # where the ranges to the users already estimated put it
        self._x[n] = self._x[n - 1] + odom if (self._odom_mask[n] and n > 0) else gps
        if idx.size and self._active.any():
            self._x[n] = self._place_keyframe(self._x[n], gps, idx, rng)
        prob = self._problem()
        newly = np.zeros(self._k, dtype=bool)
        ready = ~self._active & (prob.mask.sum(axis=0) >= self._min_start)
        start = []
        for k in np.flatnonzero(ready):
            fixes = self._x[: self._n][prob.mask[:, k], :2]
            if float(np.max(np.ptp(fixes, axis=0))) >= ONLINE_MIN_EXTENT_M:
                start.append(k)
        for k, th in _grid_init(prob, self._x[: self._n], start).items():
            self._theta[k] = th
            self._active[k] = newly[k] = True
        check_every = max(int(self._params.online_check_every), 1)
        if np.any(newly) or self._seen // check_every > self._last_check // check_every:
            prob.bias_sigma_k = None  # choose again which biases to estimate
        res = solve_robust(
            prob, self._x[: self._n].copy(), self._theta, self._active, self._prior,
            step_tol_m=self._params.online_step_tol_m,
        )
        self._x[: self._n] = res.x
        self._theta = res.theta
        if prob.nlos_prob_k is not None:
            self._nlos_pi = prob.nlos_prob_k
        if prob.noise_scale_k is not None:
            self._scale = prob.noise_scale_k.copy()
            self._scale_list = self._scale.tolist()
        self._bias_sigma = prob.bias_sigma_k
        check_every = max(int(self._params.online_check_every), 1)
        if np.any(newly) or self._seen // check_every > self._last_check // check_every:
            res = self._check_mirrors(prob, res)
            self._last_check = self._seen
        est = _estimate(prob, res, self._active, self._mirrors, self._n_ranges)
        self._users = users_from_theta(self._theta, self._up, self._params.user_dim)
        self._all_active = bool(self._active.all())
        self._nlos_pi_list = self._nlos_pi.tolist()
        self._s = res.s
        self._cost = res.lin.cost
        while self._n > self._params.window:
            self._marginalize_oldest()
        return est

    def _filter_step(self, n: int, gps: np.ndarray, idx: np.ndarray, rng: np.ndarray) -> Estimate | None:
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
        params, noise = self._params, self._noise
        self._x[n] = gps
        if self._all_active:
            if idx.size == 0:
                return self._filter_estimate(self._s, None)
            ka, r_list = idx, rng.tolist()
        else:
            use = self._active[idx]
            if not use.any():
                return self._filter_estimate(self._s, None)
            ka, r_list = idx[use], rng[use].tolist()
        ka_list = ka.tolist()
        # every user ranged, in order: S_add covers all of S
        full = ka_list == self._k_list
        p, d_u = self._p, params.user_dim
        with_bias = params.estimate_bias
        # per range, in Python floats (m ≤ K small): geometry, residual, Jacobian factors
        gx, gy, gz = gps.tolist()
        users = self._users[ka].tolist()
        biases = self._theta[ka, -1].tolist() if with_bias else None
        sig_dd = noise.a_m != 0.0 and noise.b_per_m != 0.0
        s0, a_m, b_m = noise.s0_m, noise.a_m, noise.b_per_m
        us, sigs, es = [], [], []
        for j, (r_j, (ux, uy, uz)) in enumerate(zip(r_list, users, strict=True)):
            dx, dy, dz = gx - ux, gy - uy, gz - uz
            d = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-9)
            # σ(d) = s0 + a·exp(b·d)
            sc = self._scale_list[ka_list[j]]
            sig = (s0 + a_m * math.exp(b_m * d) if a_m != 0.0 else s0) * sc
            res = r_j - d - (biases[j] if with_bias else 0.0)
            # α = 1/σ + r σ'/σ²
            alpha = 1.0 / sig + (res * sc * a_m * b_m * math.exp(b_m * d) / (sig * sig) if sig_dd else 0.0)
            f = alpha / d
            us.append((dx * f, dy * f, dz * f))  # α û = ∂e/∂u = −∂e/∂x
            sigs.append(sig)
            es.append(res / sig)
        if params.loss == "nlos":
            # the mixture loss in Python floats (estimator.robust.nlos_terms, same formulas)
            psi, w = [], []
            for e_j, sig_j, k in zip(es, sigs, ka_list, strict=True):
                pi_j = self._nlos_pi_list[k]
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
        # J_x = −α û, J_θ = [α û_(:d), (−1/σ)]: H_nn = I/σ_gps² + Σ w J_xᵀJ_x, g_n = −Σ ψ J_x,
        # B = H_nθ (3, m·p) with blocks w J_xᵀ J_θ, blockdiag H_θθ = w J_θᵀ J_θ, g_θ = −ψ J_θ
        ig = self._inv_g2
        h00 = h11 = h22 = ig
        h01 = h02 = h12 = 0.0
        g0 = g1 = g2 = 0.0
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
        hinv = _inv3_sym(h00, h01, h02, h11, h12, h22)
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
        hb = hinv @ b  # H_nn⁻¹ H_nθ
        hg = hinv @ np.array([g0, g1, g2])
        # S_add = blockdiag(w J_θᵀ J_θ) − Bᵀ H_nn⁻¹ B;  g_add = −ψ J_θ − Bᵀ H_nn⁻¹ g_n
        s_add = b.T @ hb
        np.negative(s_add, out=s_add)
        s_add.ravel()[self._blockdiag_index(m)] += ((jt * w_a[:, None])[:, :, None] * jt[:, None, :]).ravel()
        g_add = (jt * np.array(psi)[:, None]).ravel()
        np.negative(g_add, out=g_add)
        g_add -= b.T @ hg
        if full:
            s_new = self._s + s_add
        else:
            cols = (ka[:, None] * p + self._arange_p).ravel()
            s_new = self._s.copy()
            s_new[cols[:, None], cols] += s_add
        # P = S⁻¹ (the users' covariance), Δθ = P g
        try:
            cov = np.linalg.inv(s_new)
        except np.linalg.LinAlgError:
            return None
        dth = cov @ g_add if full else cov[:, cols] @ g_add
        if not (np.abs(dth).max() <= params.online_max_step_m):
            return None
        # Δx_n = H_nn⁻¹ (g_n − H_nθ Δθ)
        self._x[n] = gps + hg - hb @ (dth if full else dth[cols])
        self._theta = self._theta + dth.reshape(self._k, p)
        self._users[:, :d_u] = self._theta[:, :d_u]
        self._s = s_new
        return self._filter_estimate(s_new, cov)

    def _blockdiag_index(self, m: int) -> np.ndarray:
        """Flat indices of the m diagonal p×p blocks of an (m·p, m·p) matrix, block-row-major."""
        out = self._bd_cache.get(m)
        if out is None:
            p = self._p
            i = np.arange(m)[:, None, None] * p + np.arange(p)[None, :, None]
            j = np.arange(m)[:, None, None] * p + np.arange(p)[None, None, :]
            out = (i * (m * p) + j).ravel()
            self._bd_cache[m] = out
        return out

    def _filter_estimate(self, s: np.ndarray, cov_all: np.ndarray | None) -> Estimate:
        """Estimate after a filter step from S (K·p, K·p) and its inverse when known; mirrors
        and ambiguity flags from the last full solve."""
        k_all, p, d = self._k, self._p, self._params.user_dim
        users = self._users.copy()
        prev = self._estimate
        if cov_all is not None and p == d and self._active.all():
            # S⁻¹ blocks; the position information is S itself
            cov = cov_all.reshape(k_all, p, k_all, p)[self._arange_k, :, self._arange_k, :]
            info, cov_joint = s, cov_all
        else:
            users[~self._active] = np.nan
            cov, info, cov_joint = _covariances(s, self._active, k_all, p, d)
        bias = np.where(self._active, self._theta[:, -1], np.nan) if self._params.estimate_bias else None
        return Estimate(
            users_enu_m=users, cov_users_m2=cov, info_users=info, bias_m=bias,
            uav_enu_m=self._x[: self._n].copy(), ambiguous=prev.ambiguous.copy(),
            mirror_enu_m=prev.mirror_enu_m.copy(), n_ranges=self._n_ranges.copy(), cost=float("nan"),
            iterations=0, converged=True,
            extra={"active": self._active.copy(), "cov_theta_joint": cov_joint, "filter_step": True,
                   "noise_scale": self._scale.copy()},
        )

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
            sig = self._noise.range_sigma_m(d) * self._scale[k]
            e = (r_meas - d - bias) / sig
            _, psi, w = loss_psi_weight(
                e, self._params.loss, self._params.loss_scale, nlos_args(self._params, sig), need_rho=False)
            j = -diff / (d * sig)[:, None]
            h = (j * w[:, None]).T @ j + np.eye(3) * inv_g2
            g = -(x - gps) * inv_g2 - (j * psi[:, None]).sum(axis=0)
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
        # a prior that also holds the first keyframe (Gauss–Markov GPS or motion links) ties the
        # users to the whole marginalized track: reflecting one user's part of it is no longer a
        # consistent mirror hypothesis, so the window's mirror test only flags, it does not flip
        can_flip = self._prior is None or not self._prior.has_x
        for k, mt in enumerate(mirrors):
            if mt is None or not mt.mirror_is_better(chi2) or not can_flip:
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
        motion_link = bool(prob.use_motion and self._odom_mask[1])
        gps_link = bool(prob.gps_linked)
        link = motion_link or gps_link
        # variables v = [x_0 (3), x_1 (3), Θ (K·p)]; H and ∇ of every factor touching x_0
        dim = 6 + pu
        h = np.zeros((dim, dim))
        grad = np.zeros(dim)
        mask0 = prob.mask[:1].T & self._active[:, None]
        _e, w, _rho, jac, psi = _range_terms(prob, x[:1], theta, mask0)
        # H += Σ w JᵀJ,  ∇ += Σ ψ J
        jfull = np.zeros((k_all, dim))
        jfull[:, :3] = jac[:3, :, 0].T  # (K, 3)
        kk = np.arange(k_all)[:, None]
        jfull[kk, 6 + kk * p + np.arange(p)[None, :]] = jac[3:, :, 0].T  # (K, p)
        h += (jfull * w[:, :1]).T @ jfull
        grad += jfull.T @ psi[:, 0]
        if gps_link:
            # the GPS factors touching x_0: its own (if still in the window) and the link to x_1
            gt = gps_chain_terms(x[:2], prob.gps_enu_m[:2], prob.gps_phi()[:2], noise.sigma_gps_m, prob.gps_first)
            h[:3, :3] += np.eye(3) * gt.diag[0]
            h[3:6, 3:6] += np.eye(3) * gt.diag[1]
            h[:3, 3:6] += np.eye(3) * gt.off[0]
            h[3:6, :3] += np.eye(3) * gt.off[0]
            grad[:6] += gt.grad.ravel()
        else:
            inv_g2 = 1.0 / noise.sigma_gps_m**2
            h[:3, :3] += np.eye(3) * inv_g2
            grad[:3] += (x[0] - prob.gps_enu_m[0]) * inv_g2
        if motion_link:
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
        self._win_count -= prob.mask[0]
        for arr in (self._gps, self._rng, self._odom, self._odom_mask, self._x, self._t):
            arr[: n - 1] = arr[1:n]
        self._odom_mask[0] = False
        if gps_link:
            self._gps_first = False  # its link to the dropped keyframe now lives in the prior
        self._n = n - 1
