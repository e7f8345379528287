"""The solve schedule around Levenberg–Marquardt: robust-loss warm starts and the per-user NLoS
probability (EM), the per-user range-noise scale from the residuals, and the range-bias
selection (a score test from the bias-free solution)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from estimator.clock import undetected_sawtooth_bias
from estimator.linearize import (
    Linearization,
    Prior,
    linearize,
    problem_nlos_args,
    problem_residuals,
    range_jac,
    range_terms,
)
from estimator.lm import (
    SolveResult,
    em_information,
    levenberg_marquardt,
)
from estimator.problem import (
    Problem,
)
from estimator.robust import REDESCENDING, mills_ratio, nlos_terms
from estimator.schur import schur_solve
from uavloc.errors import EstimatorError

#: Huber threshold of the warm start before a redescending loss
HUBER_WARM_SCALE = 1.5
#: "nlos" loss with nlos_adapt: bounds of the per-user NLoS probability π_k, the most rounds of
#: (solve, re-estimate π_k), and the change of π_k below which the rounds stop
NLOS_PROB_MIN = 0.005
NLOS_PROB_MAX = 0.5
NLOS_EM_ROUNDS = 10
NLOS_EM_TOL = 1e-4
#: a π_k off its floor is kept only when it raises the likelihood of the user's ranges by
#: 2·(ℓ(π_k) − ℓ(NLOS_PROB_MIN)) ≥ NLOS_SELECT_CHI2: the 95 % point of the likelihood-ratio
#: test of π on its boundary (½χ²₀ + ½χ²₁). A LoS user's π drifts off the floor on its
#: Gaussian tail (0.01 at 2·Δℓ below 0.5 on the benchmark's problems), which cost it the
#: Newton steps, the per-user rounds and the observed information of a NLoS user; 5 % NLoS
#: ranges give 3–70, 20 % give 170–350
NLOS_SELECT_CHI2 = 2.71
#: step tolerance of the solves while π_k is still being re-estimated [m]
NLOS_ROUND_STEP_M = 1e-3
#: while some π_k still moves by more than NLOS_PARTIAL_MOVED, a round is a partial M-step of at
#: most NLOS_PARTIAL_ITERATIONS Levenberg–Marquardt iterations (at most NLOS_PARTIAL_ROUNDS such
#: rounds; they do not count against NLOS_EM_ROUNDS)
NLOS_PARTIAL_MOVED = 1e-3
NLOS_PARTIAL_ITERATIONS = 2
NLOS_PARTIAL_ROUNDS = 20
#: per-user range-noise scale (params.estimate_noise_scale): upper bound, fewest degrees of
#: freedom to estimate it from, relative change below which it is not re-solved, and most rounds
NOISE_SCALE_MAX = 10.0
NOISE_SCALE_MIN_DOF = 8
NOISE_SCALE_RESOLVE = 0.1
NOISE_SCALE_ROUNDS = 6
#: bias selection (params.bias_select): a bias below this many of its standard deviations is
#: held (held_bias_prior); with params.bias_held "zero" at 0 by a prior of BIAS_OFF_SIGMA_M
BIAS_SELECT_Z = 4.0
BIAS_OFF_SIGMA_M = 1e-3
#: ... and kept only when determined to this standard deviation [m] (a bias the geometry barely
#: separates from the position trades a large position error for a small fit gain). It was
#: 1.5 m: a commercial UE's 8.3 m bias at 5.3 σ (sd 1.56 m) was dropped, the sawtooth then called
#: NLoS (π 0.5), and the user ended 12.8 m off with a 95 % bound of 3.6 m
BIAS_SELECT_MAX_SD_M = 3.0


def held_bias_prior(prob: Problem) -> tuple[np.ndarray, np.ndarray]:
    """(K,) mean and (K,) σ [m] of the prior that holds a bias the selection turned off
    (params.bias_held): 0 and BIAS_OFF_SIGMA_M ("zero"), or the mean offset of a clock sawtooth
    too small to track at the user's range noise s_k·σ0 ("sawtooth",
    estimator.clock.undetected_sawtooth_bias; σ0 = noise.range_s0_m, the noise at short range)."""
    k_all = prob.n_users
    if prob.params.bias_held == "sawtooth":
        scale = np.ones(k_all) if prob.noise_scale_k is None else np.asarray(prob.noise_scale_k, dtype=float)
        mean, sd = undetected_sawtooth_bias(prob.noise.range_s0_m * scale)
        return np.asarray(mean, dtype=float), np.asarray(sd, dtype=float)
    return np.zeros(k_all), np.full(k_all, BIAS_OFF_SIGMA_M)


def select_biases(prob: Problem, free: np.ndarray, held: tuple[np.ndarray, np.ndarray]) -> None:
    """Write a bias selection into prob: the biases of `free` (K,) under the weak free prior
    N(0, params.bias_prior_sigma_m²), the others under `held` = (mean, σ) (K,) each
    (held_bias_prior)."""
    mean_h, sd_h = held
    prob.bias_sigma_k = np.where(free, prob.params.bias_prior_sigma_m, sd_h)
    prob.bias_mean_k = np.where(free, 0.0, mean_h)


def free_biases(params, bias_sigma_k: np.ndarray | None) -> np.ndarray | None:
    """(K,) True where a selection's prior σ (Problem.bias_sigma_k) leaves the bias free: a
    free bias has the free prior's σ exactly, a held one the held prior's. None: no selection."""
    return None if bias_sigma_k is None else np.asarray(bias_sigma_k) >= params.bias_prior_sigma_m


def nlos_prob_update(prob: Problem, gamma: np.ndarray, active: np.ndarray) -> np.ndarray:
    """(K,) maximum-likelihood NLoS probability of each user at the residuals where the posterior
    LoS probabilities gamma (K, n) (0 where no range; Linearization.w) were evaluated.

    With q_i = f(e_i)/φ(e_i) the NLoS/LoS density ratio of range i, the log-likelihood of user
    k's ranges in π is Σ_i log(1 + π (q_i − 1)) (+ const), concave, with derivative

        D(π) = Σ_i a_i / (1 + π a_i),   D'(π) = −Σ_i (a_i / (1 + π a_i))²,   a_i = q_i − 1,

    solved by Newton's method within [NLOS_PROB_MIN, NLOS_PROB_MAX] (the root, or the bound
    where D keeps its sign), and kept off the floor only where it passes the likelihood-ratio
    test against it (NLOS_SELECT_CHI2). q is recovered from the posterior LoS probability γ at the
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
        # π_f kept where the likelihood-ratio test against the floor passes (NLOS_SELECT_CHI2):
        # ℓ(π) − ℓ(π_min) = Σ_i log((1 + π a_i)/(1 + π_min a_i)) + n_huge log(π/π_min)
        gain = (np.log1p(pf[:, None] * af) - np.log1p(NLOS_PROB_MIN * af)).sum(axis=1) + nf * np.log(pf / NLOS_PROB_MIN)
        pi[free] = np.where(2.0 * gain >= NLOS_SELECT_CHI2, pf, NLOS_PROB_MIN)
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
    step_tol_m: float | None = None, max_iterations: int | None = None, rounds: int | None = None,
) -> SolveResult:
    """:func:`_solve_robust` (the schedule: loss, noise scale, bias selection), with S from the
    observed information when the "nlos" loss found NLoS (observed_s). max_iterations: of each
    Levenberg–Marquardt run (None: params.max_iterations). rounds: the most solves of the
    NLoS-probability (EM) and noise-scale re-estimation (None: NLOS_EM_ROUNDS, NOISE_SCALE_ROUNDS);
    the online estimator passes 1 and goes on at its next update (the estimates are kept in prob)."""
    res = _solve_robust(prob, x, theta, active, prior, step_tol_m, max_iterations, rounds)
    return observed_s(prob, res, active, prior)


def observed_s(prob: Problem, res: SolveResult, active: np.ndarray, prior: Prior | None = None) -> SolveResult:
    """res with S from the observed information of the "nlos" loss (ψ'(e) per range,
    robust.nlos_curvature) instead of its EM weight γ, when some active user's π_k is above
    NLOS_PROB_MIN (at LoS γ ≈ ψ' ≈ 1 and S is kept).

    The EM weight counts a range the mixture cannot classify (γ ≈ ½) as half a LoS range, but
    such a range carries almost no information about the position (its label is unknown: the
    missing information γ(1 − γ)h², Louis 1982): the 95 % ellipse from γ covered 85–87 % of
    the users under 20–30 % NLoS. ψ' is used unfloored when S and every keyframe block stay
    positive definite, else floored at 0 per range."""
    if prob.params.loss != "nlos" or prob.nlos_prob_k is None or res.s is None:
        return res
    if not np.any(prob.nlos_prob_k[active] > NLOS_PROB_MIN):
        return res
    free = active & (prob.nlos_prob_k > NLOS_PROB_MIN) & (prob.nlos_prob_k < NLOS_PROB_MAX)
    hxp, c_up, p_pp = _nlos_prob_blocks(prob, res.x, res.theta, active, free)
    kp = prob.n_users * prob.p
    for floor in (-np.inf, 0.0):
        lin = linearize(prob, res.x, res.theta, active, prior, observed=floor)
        # the joint system in (x, θ, π_free): π's columns appended to H_xu and H_uu
        hxu = np.concatenate([lin.hxu.reshape(lin.hxu.shape[0], 3, kp), hxp], axis=2)
        nf = hxp.shape[2]
        huu = np.zeros((kp + nf, kp + nf))
        huu[:kp, :kp] = lin.huu
        huu[:kp, kp:] = c_up
        huu[kp:, :kp] = c_up.T
        huu[kp:, kp:] = np.diag(p_pp)
        try:
            _, _, s_aug = schur_solve(lin.hxx, lin.off, hxu, huu, lin.gx, np.zeros(kp + nf), 0.0)
            # π marginalized: S = S_θθ − S_θπ S_ππ⁻¹ S_πθ
            s = s_aug[:kp, :kp]
            if nf:
                s = s - s_aug[:kp, kp:] @ np.linalg.solve(s_aug[kp:, kp:], s_aug[kp:, :kp])
                s = 0.5 * (s + s.T)
            np.linalg.cholesky(s)
        except (np.linalg.LinAlgError, EstimatorError):
            continue
        return SolveResult(res.x, res.theta, res.lin, s, res.iterations, res.converged)
    return res


def _nlos_prob_blocks(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, free: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Second derivatives of L = Σ ρ(e) involving the NLoS probabilities π_k of the users in
    `free` (F of them), which are estimated too (solve_loss) and so cost the positions some
    information. With q = (π/m) M(t), g = (1 − π) + q, h = t + 1/M(t) (robust.nlos_terms):

        ∂ψ/∂π = −h (M/m) / g²,   ∂²ρ/∂π² = (M/m − 1)² / g²

    Returns H_xπ (N, 3, F) = Σ_k ∂ψ/∂π J_x, H_θπ (K·p, F) = Σ_n ∂ψ/∂π J_θ, H_ππ (F,)."""
    n = x.shape[0]
    ks = np.flatnonzero(free)
    nf, p = ks.size, prob.p
    # only the free users' ranges enter: their residuals and Jacobians alone
    sub = user_subproblem(prob, ks)
    mask_kn = sub.mask[:n].T & active[ks][:, None]
    diff, d, sig, _, e, full = problem_residuals(sub, x, theta[ks], mask_kn)
    jac = range_jac(sub, diff, d, sig, None if full else mask_kn)
    pi, m = problem_nlos_args(sub, sig)
    inv_m = 1.0 / m
    t = e - inv_m
    mills = mills_ratio(t)
    g = (1.0 - pi) + pi * inv_m * mills
    mm = inv_m * mills
    dpsi = np.where(mask_kn, -(t + 1.0 / mills) * (mm / g) / g, 0.0)
    dpp = np.where(mask_kn, ((mm - 1.0) / g) ** 2, 0.0)
    hxp = np.zeros((n, 3, nf))
    c_up = np.zeros((prob.n_users * p, nf))
    for j, k in enumerate(ks.tolist()):
        hxp[:, :, j] = (jac[:3, j] * dpsi[j]).T
        c_up[k * p : (k + 1) * p, j] = (jac[3:, j] * dpsi[j]).sum(axis=1)
    return hxp, c_up, dpp.sum(axis=1)


def _solve_robust(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None,
    step_tol_m: float | None = None, max_iterations: int | None = None, rounds: int | None = None,
) -> SolveResult:
    """:func:`solve_loss` and, with params.estimate_noise_scale, the per-user range-noise scale
    re-estimated from the solution's residuals (noise_scale_update, stored in prob.noise_scale_k):
    the problem is re-solved while a scale moves by more than NOISE_SCALE_RESOLVE (relative), and
    a smaller last change only re-linearizes at the solution so that the covariance uses it; at
    most NOISE_SCALE_ROUNDS rounds. A solve takes a change above NOISE_SCALE_RESOLVE already on
    its way, near the optimum (_rescale_midway), instead of a re-solve from the optimum. A user
    whose ranges are noisier than the assumed σ(d) then gets a covariance that says so.

    With params.estimate_bias and params.bias_select (and prob.bias_sigma_k not yet chosen) the
    biases are selected: the problem is solved with every bias held under its prior N(μ_h, σ_h²)
    (held_bias_prior: at 0 by BIAS_OFF_SIGMA_M with params.bias_held "zero"), then one
    Gauss–Newton step of the model with free biases from that solution gives each bias b̂_k and its
    standard deviation sd_k (S⁻¹ there: the score test of b_k = μ_h; from that solve's S and the
    ranges' gradient, no new linearization). A user keeps its bias when |b̂_k − μ_h| ≥
    BIAS_SELECT_Z · sd_k and sd_k ≤ BIAS_SELECT_MAX_SD_M, and the problem is solved again with those biases free. A UE
    without a clock offset pays nothing for the unknown; one with a sawtooth keeps it. (A full
    solve of the free model instead of the step wanders, where the geometry barely separates a
    bias from the position, into basins 5–13 m away that fit a little better.)"""
    params = prob.params
    if not (params.estimate_bias and params.bias_select and prob.bias_sigma_k is None):
        return _solve_scaled(prob, x, theta, active, prior, step_tol_m, max_iterations, rounds)[0]
    k_all, d_u = prob.n_users, prob.user_dim
    # every bias held by its prior N(μ_h, σ_h²) (held_bias_prior: 0 and a tiny σ_h for "zero")
    held = held_bias_prior(prob)
    mu_h, sd_h = held
    inv_off2 = 1.0 / np.square(sd_h)
    inv_free2 = 1.0 / params.bias_prior_sigma_m**2
    select_biases(prob, np.zeros(k_all, dtype=bool), held)
    theta = theta.copy()
    theta[:, -1] = mu_h
    res, rescaled = _solve_scaled(prob, x, theta, active, prior, step_tol_m, max_iterations, rounds)
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
        g = np.zeros(s_free.shape[0])
        if res.gn_step:
            # after the Gauss–Newton step the linear model's gradient of the held problem is
            # zero: the ranges' pull −Σ ψ J_b there balances the held prior's (b − μ_h)/σ_h², so
            # −Σ ψ J_b − b/σ_b² = (b − μ_h)/(ρ_k² σ_h²) − b/σ_b² without evaluating the ranges
            # again (ρ_k: the noise scale's last change if it only rescaled S; ψ J_b ∝ 1/ρ_k²)
            b_h = res.theta[:, -1]
            g[ib] = (b_h - mu_h) * inv_off2 / np.square(rescaled) - b_h * inv_free2
        else:
            n = res.x.shape[0]
            _, _, _, jac, psi, _ = range_terms(prob, res.x, res.theta, prob.mask[:n].T & active[:, None])
            g[ib] = -(psi * jac[-1]).sum(axis=1) - res.theta[:, -1] * inv_free2
        try:
            cov = np.linalg.inv(s_free)
        except np.linalg.LinAlgError:
            cov = None
        if cov is not None and np.all(np.isfinite(cov)):
            b_step = res.theta[:, -1] + (cov @ g)[ib]
            sd = np.sqrt(np.maximum(np.diag(cov)[ib], 0.0))
            keep = active & (np.abs(b_step - mu_h) >= BIAS_SELECT_Z * sd) & (sd <= BIAS_SELECT_MAX_SD_M)
    if prob.bias_force_k is not None:
        keep |= active & prob.bias_force_k
    if not keep.any():
        return res
    select_biases(prob, keep, held)
    theta = res.theta.copy()
    theta[keep, -1] = b_step[keep]
    return _solve_scaled(prob, res.x, theta, active, prior, step_tol_m, max_iterations, rounds)[0]


def _rescale_midway(prob: Problem, active: np.ndarray, rounds: int | None):
    """The noise-scale update a solve of _solve_scaled makes on its way (levenberg_marquardt's
    `rescale`, once, near the optimum: the users' step below lm.RESCALE_STEP_SIGMA of their σ):
    where some s_k would move by more than NOISE_SCALE_RESOLVE at the solution, _solve_scaled
    would re-solve from there; the new s_k are taken there instead, and the solve converges to
    the optimum under them (the re-solve's iterations saved; the residuals that far from the
    optimum give the same s_k to a small fraction of the change). Smaller changes are left to
    _solve_scaled at the solution (the model unchanged). None (no update) without
    params.estimate_noise_scale or with `rounds` given (the online estimator's one round)."""
    if not prob.params.estimate_noise_scale or rounds is not None:
        return None
    pending = [True]

    def rescale(lin: Linearization) -> bool:
        if not pending[0] or prob.noise_scale_k is None:
            return False
        pending[0] = False
        new = noise_scale_update(prob, lin, active)
        if float(np.max(np.abs(new / prob.noise_scale_k - 1.0))) <= NOISE_SCALE_RESOLVE:
            return False
        prob.noise_scale_k = new
        return True

    return rescale


def _solve_scaled(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None,
    step_tol_m: float | None, max_iterations: int | None = None, rounds: int | None = None,
) -> tuple[SolveResult, np.ndarray]:
    """solve_loss, then rounds of noise_scale_update (see solve_robust). Returns (result, (K,)
    ratio of the noise scales to those of the last solve: ≠ 1 where a last change only rescaled
    S: a small one, or any in the last of `rounds` rounds)."""
    ones = np.ones(prob.n_users)
    if prob.params.estimate_noise_scale and prob.noise_scale_k is None:
        prob.noise_scale_k = ones.copy()
    res = solve_loss(prob, x, theta, active, prior, step_tol_m, max_iterations, rounds,
                     rescale=_rescale_midway(prob, active, rounds))
    if not prob.params.estimate_noise_scale:
        return res, ones
    n_rounds = NOISE_SCALE_ROUNDS if rounds is None else rounds
    for r in range(n_rounds):
        new = noise_scale_update(prob, res.lin, active)
        ratio = new / prob.noise_scale_k
        change = float(np.max(np.abs(ratio - 1.0)))
        if change == 0.0:
            break
        prob.noise_scale_k = new
        if change <= NOISE_SCALE_RESOLVE or (rounds is not None and r == n_rounds - 1):
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
                res = SolveResult(res.x, res.theta, res.lin, s_new, res.iterations, res.converged, res.gn_step)
            return res, ratio
        res = solve_loss(prob, res.x, res.theta, active, prior, step_tol_m, max_iterations, rounds,
                         rescale=_rescale_midway(prob, active, rounds))
    return res, ones


def user_subproblem(prob: Problem, users: np.ndarray) -> Problem:
    """The problem of the users with indices `users` alone (their ranges, per-user settings and
    bias gains; every keyframe kept). With the keyframes held fixed it is the conditional problem of
    those users: the others' ranges then do not involve them."""
    def cols(a):
        return None if a is None else a[..., users]
    return replace(
        prob, range_m=prob.range_m[:, users], mask=prob.mask[:, users], user_up_m=prob.user_up_m[users],
        nlos_prob_k=cols(prob.nlos_prob_k), noise_scale_k=cols(prob.noise_scale_k),
        bias_sigma_k=cols(prob.bias_sigma_k), bias_mean_k=cols(prob.bias_mean_k), bias_force_k=cols(prob.bias_force_k),
        bias_gain=cols(prob.bias_gain),
    )


def _nlos_user_rounds(prob: Problem, x: np.ndarray, theta: np.ndarray, users: np.ndarray) -> np.ndarray:
    """The partial rounds of solve_loss on the users in `users` (K,) alone, the keyframes x and the
    other users held fixed: at most NLOS_PARTIAL_ROUNDS rounds of one Gauss–Newton step of each
    user's θ_k at its π_k (kept where it lowers the user's cost, Σ_n ρ + ½ (b/σ_b)², which with x
    held is the user's part of L), then π_k (nlos_prob_update) and, with estimate_noise_scale, s_k
    (noise_scale_update) re-estimated there, until no π_k moves by NLOS_PARTIAL_MOVED. Each round raises
    the likelihood (generalized EM, coordinate-wise) and costs the ranges of these users only;
    the full rounds after them are joint solves. Writes π_k and s_k of these users into prob;
    returns Θ (K, p) with their θ_k updated.

    With x held the normal equations of user k are its own block (linearize's H_kk, g_k):

        H_kk = Σ_n w J_θ J_θᵀ (+ 1/σ_b² on the bias),   g_k = −Σ_n ψ J_θ (− b/σ_b²),   H_kk Δθ_k = g_k
    """
    ks = np.flatnonzero(users)
    theta = theta.copy()
    if ks.size == 0:
        return theta
    sub = user_subproblem(prob, ks)
    n = x.shape[0]
    mask_kn = sub.mask[:n].T
    d_u = sub.user_dim
    bias = sub.params.estimate_bias
    inv_b2 = 0.0
    if bias:
        sb = sub.params.bias_prior_sigma_m if sub.bias_sigma_k is None else sub.bias_sigma_k
        inv_b2 = 1.0 / np.square(sb) * np.ones(ks.size)
        mu_b = np.zeros(ks.size) if sub.bias_mean_k is None else sub.bias_mean_k
    act = np.ones(ks.size, dtype=bool)
    th = theta[ks].copy()

    def terms(th: np.ndarray) -> tuple:
        # (cost (k,), e, w, H (k, p, p), g (k, p)) of each user at θ, x held
        e, w, rho, jac, psi, _ = range_terms(sub, x, th, mask_kn)
        jt = jac[3:]  # (p, k, n)
        # J_θ = [α û (user coordinates), −g/σ (bias)]: ∂e/∂u = −∂e/∂x
        h = np.einsum("akn,bkn->kab", jt * w, jt)
        g = -np.einsum("akn,kn->ka", jt, psi)
        cost = rho.sum(axis=1)
        if bias:
            b = th[:, d_u]
            h[:, -1, -1] += inv_b2
            bm = b - mu_b
            g[:, -1] -= bm * inv_b2
            cost = cost + 0.5 * inv_b2 * bm * bm
        return cost, e, w, h, g

    cost, e, w, h, g = terms(th)
    for _ in range(NLOS_PARTIAL_ROUNDS):
        try:
            step = np.linalg.solve(h, g[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            break
        trial = th + step
        c_t, e_t, w_t, _, _ = terms(trial)
        better = c_t <= cost
        th = np.where(better[:, None], trial, th)
        # the weights and residuals where each user now is (at the current π and s)
        w = np.where(better[:, None], w_t, w)
        e = np.where(better[:, None], e_t, e)
        pi = nlos_prob_update(sub, w, act)
        moved = float(np.max(np.abs(pi - sub.nlos_prob_k)))
        sub.nlos_prob_k = pi
        if sub.params.estimate_noise_scale and sub.noise_scale_k is not None:
            sub.noise_scale_k = noise_scale_update(sub, _Weights(w, e), act)
        if moved <= NLOS_PARTIAL_MOVED or not better.any():
            break
        cost, e, w, h, g = terms(th)
    theta[ks] = th
    prob.nlos_prob_k = prob.nlos_prob_k.copy()
    prob.nlos_prob_k[ks] = sub.nlos_prob_k
    if sub.noise_scale_k is not None:
        prob.noise_scale_k = prob.noise_scale_k.copy()
        prob.noise_scale_k[ks] = sub.noise_scale_k
    return theta


@dataclass
class _Weights:
    """The part of a Linearization noise_scale_update reads: w and e (K, N)."""

    w: np.ndarray
    e: np.ndarray


def solve_loss(
    prob: Problem, x: np.ndarray, theta: np.ndarray, active: np.ndarray, prior: Prior | None = None,
    step_tol_m: float | None = None, max_iterations: int | None = None, rounds: int | None = None,
    conditional: bool = True, rescale=None,
) -> SolveResult:
    """Levenberg–Marquardt with the loss's schedule: a redescending loss starts from a Huber
    solution; "nlos" with params.nlos_adapt alternates solves with the maximum-likelihood π_k at
    the solution's residuals (nlos_prob_update, stored in prob.nlos_prob_k) until no π_k moves
    by more than NLOS_EM_TOL: a joint maximum of the likelihood in (x, θ, π)."""
    params = prob.params
    if params.loss in REDESCENDING:
        # a redescending loss ignores what it deems outliers: start it from the Huber solution
        warm = replace(prob, params=replace(params, loss="huber", loss_scale=HUBER_WARM_SCALE))
        pre = levenberg_marquardt(warm, x, theta, active, prior, max_iterations, step_tol_m=step_tol_m)
        x, theta = pre.x, pre.theta
    if params.loss != "nlos" or not params.nlos_adapt:
        return levenberg_marquardt(prob, x, theta, active, prior, max_iterations, step_tol_m=step_tol_m,
                                   rescale=rescale)
    if prob.nlos_prob_k is None:
        # π_k from params.nlos_prob re-estimated at the starting residuals (at LoS it drops to
        # the floor at once, and the solve runs near-quadratic from the first iteration)
        prob.nlos_prob_k = np.full(prob.n_users, float(params.nlos_prob))
        mask_kn = prob.mask[: x.shape[0]].T & active[:, None]
        _, _, sig, _, e, _ = problem_residuals(prob, x, theta, mask_kn)
        gamma = nlos_terms(e, *problem_nlos_args(prob, sig), need_rho=False)[2] * mask_kn
        prob.nlos_prob_k = nlos_prob_update(prob, gamma, active)
    tol = params.step_tol_m if step_tol_m is None else step_tol_m
    # while π_k still moves, solve only to NLOS_ROUND_STEP_M; then to tol (all π_k on the
    # floor, i.e. LoS: to tol at once). While it moves a lot (more than NLOS_PARTIAL_MOVED),
    # rounds are partial M-steps (generalized EM: the likelihood still rises every round), so that
    # the slow (linear) convergence of π does not cost a full solve per round; the rounds that
    # decide convergence are full solves. The partial rounds are, by default (`conditional`,
    # without a prior, all rounds allowed), those of the users whose π moves alone, the keyframes
    # and the other users held (_nlos_user_rounds: they cost the LoS users nothing), after which
    # the full rounds solve to tol; otherwise they are joint solves of a few iterations. While some
    # π_k is off its floor a solve takes Newton steps (levenberg_marquardt's newton: the EM-weighted
    # iteration converges linearly there), and the result's S is the EM-weighted one
    # (em_information); with every π_k on its floor the EM-weighted iteration is as fast.
    tight = bool(np.all(prob.nlos_prob_k[active] <= NLOS_PROB_MIN))
    users_only = conditional and rounds is None and prior is None
    moved = np.inf
    n_full = n_partial = 0
    while True:
        partial = (not users_only and rounds is None and not tight and moved > NLOS_PARTIAL_MOVED
                   and n_partial < NLOS_PARTIAL_ROUNDS)
        res = levenberg_marquardt(
            prob, x, theta, active, prior, step_tol_m=tol if tight else max(tol, NLOS_ROUND_STEP_M),
            max_iterations=NLOS_PARTIAL_ITERATIONS if partial else max_iterations,
            newton=rounds is None and bool(np.any(prob.nlos_prob_k[active] > NLOS_PROB_MIN)),
            rescale=None if partial else rescale)
        n_partial += partial
        n_full += not partial
        pi = nlos_prob_update(prob, res.lin.w, active)
        moved_k = np.abs(pi - prob.nlos_prob_k)
        moved = float(np.max(moved_k))
        by_user = users_only and moved > NLOS_EM_TOL and n_full < NLOS_EM_ROUNDS
        if (partial or by_user) and params.estimate_noise_scale and prob.noise_scale_k is not None:
            # the noise scale (solve_robust) moves with π: re-estimated with it while π moves a
            # lot, so that its own rounds (_solve_scaled) start near their fixed point
            prob.noise_scale_k = noise_scale_update(prob, res.lin, active)
        if by_user:
            prob.nlos_prob_k = pi
            users = active & ((pi > NLOS_PROB_MIN) | (moved_k > NLOS_EM_TOL))
            x, theta = res.x, _nlos_user_rounds(prob, res.x, res.theta, users)
            tight = True
            continue
        if not partial and moved <= NLOS_EM_TOL:
            if tight:
                break
            tight = True
        prob.nlos_prob_k = pi
        x, theta = res.x, res.theta
        if n_full >= (NLOS_EM_ROUNDS if rounds is None else rounds):
            break
    return em_information(prob, res, active, prior)
