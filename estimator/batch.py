"""The batch solver: initialization, the solve, UE clock tracking (estimator.clock), mirror tests."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from estimator.clock import fit_sawtooth, refine_sawtooth
from estimator.init import init_users, mirror_tests
from estimator.linearize import (
    Prior,
)
from estimator.lm import (
    SolveResult,
    levenberg_marquardt,
)
from estimator.marginals import (
    estimate_of,
)
from estimator.noise import NoiseModel
from estimator.problem import (
    Problem,
    pack_keyframes,
    users_from_theta,
)
from estimator.silence import silence_refutes
from estimator.solve import (
    held_bias_prior,
    observed_s,
    select_biases,
    solve_robust,
)
from estimator.types import Estimate, Keyframe, SolverParams
from uavloc.errors import EstimatorError

#: clock tracking (params.track_clock): a user is tested for a sawtooth when it has
#: CLOCK_MIN_RANGES ranges and its whitened residuals' RMS exceeds CLOCK_TRIGGER_SCALE and
#: CLOCK_TRIGGER_RMS_Z of its standard deviation 1/√(2m) under white noise, or their lag-one
#: autocorrelation exceeds CLOCK_TRIGGER_Z of its standard deviation; rounds of fit + re-solve
CLOCK_TRIGGER_SCALE = 1.08
CLOCK_TRIGGER_RMS_Z = 2.5
CLOCK_TRIGGER_Z = 2.0
#: ... or when the NLoS mixture calls more than this share of its ranges NLoS (the tops of a
#: sawtooth no bias explains look like NLoS excess, and the kept ones then look white enough)
CLOCK_TRIGGER_NLOS_PROB = 0.1
CLOCK_MIN_RANGES = 40
CLOCK_ROUNDS = 3


def grid_init(prob: Problem, uav: np.ndarray, users: Sequence[int]) -> dict[int, np.ndarray]:
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


def mirror_all(
    prob: Problem, theta: np.ndarray, active: np.ndarray, n_rows: int | None = None
) -> list:
    """Mirror test per user on the first n_rows keyframes (UAV at GPS). None for inactive users.

    With a cell of limited reach (params.coverage_m finite) the silence of the keyframes judges
    each user's two hypotheses (estimator.silence): a refuted mirror makes the user unambiguous
    (MirrorTest.mirror_refuted, ambiguous False), a refuted estimate asks for a flip to its
    mirror (MirrorTest.estimate_refuted, _resolve_mirrors)."""
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
    if np.isfinite(prob.params.coverage_m):
        _judge_silence(prob, out, theta, n)
    return out


def _judge_silence(prob: Problem, mirrors: list, theta: np.ndarray, n: int) -> None:
    """Mark in `mirrors` (in place) the hypotheses that silence refutes (estimator.silence): users
    with a mirror solution whose estimate or mirror it refutes."""
    ks = [k for k, mt in enumerate(mirrors) if mt is not None and mt.mirror_theta is not None]
    if not ks:
        return
    est = users_from_theta(theta[ks], prob.user_up_m[ks], prob.user_dim)
    mir = users_from_theta(np.array([mirrors[k].mirror_theta for k in ks]), prob.user_up_m[ks], prob.user_dim)
    est_ref, mir_ref = silence_refutes(prob, ks, est, mir, n)
    for k, e_r, m_r in zip(ks, est_ref.tolist(), mir_ref.tolist(), strict=True):
        if m_r:
            mirrors[k] = dataclasses.replace(mirrors[k], ambiguous=False, mirror_refuted=True)
        elif e_r:
            mirrors[k] = dataclasses.replace(mirrors[k], estimate_refuted=True)


def _resolve_mirrors(prob: Problem, res: SolveResult, active: np.ndarray, prior: Prior | None = None):
    """Mirror tests; a user whose mirror fits clearly better (Δχ² < −χ²_amb, and silence does not
    refute it) or whose estimate silence refutes and its mirror explains the ranges about as well
    (MirrorTest.silence_prefers_mirror) jumps there and the problem is re-solved once, kept when
    its cost 2·ΔL rises by less than χ²_amb per user the silence moved (falls, when none).
    Returns (result, mirror tests)."""
    chi2 = prob.params.ambiguity_chi2
    mirrors = mirror_all(prob, res.theta, active)
    flip = [k for k, mt in enumerate(mirrors) if mt is not None and mt.mirror_is_better(chi2)]
    silent = [k for k, mt in enumerate(mirrors) if mt is not None and mt.silence_prefers_mirror(chi2)]
    if flip or silent:
        theta = res.theta.copy()
        for k in flip + silent:
            theta[k] = mirrors[k].mirror_theta
        res2 = observed_s(prob, levenberg_marquardt(prob, res.x, theta, active, prior), active, prior)
        if 2.0 * (res2.lin.cost - res.lin.cost) < chi2 * len(silent):
            res = res2
            mirrors = mirror_all(prob, res.theta, active)
    return res, mirrors


def solve_batch(
    keyframes: Sequence[Keyframe], n_users: int, user_up_m: np.ndarray, noise: NoiseModel,
    params: SolverParams = SolverParams(), init_users_enu_m: np.ndarray | None = None,  # noqa: B008
    warm: Estimate | None = None,
) -> Estimate:
    """Estimate users and UAV keyframes from all keyframes at once.

    keyframes: N keyframes (GPS fix, ranges to users, optional odometry).
    n_users: K; user_up_m: (K,) ground height of each user [m, ENU up] (fixed in 2-D mode,
        the initial value in 3-D mode); init_users_enu_m: optional (K, 3) starts [m, ENU], rows
        with NaN are initialised by grid search.
    Users with fewer than p + 1 ranges (p unknowns) are not estimated: NaN rows, inf covariance.
    warm: an Estimate solve_batch returned for a prefix of these keyframes (a refresh,
        estimator.refresh): see _warm_solve; state.warm_started says whether it was used.
    A fleet's keyframes (Keyframe.vehicle) are solved sorted by vehicle, each vehicle's chain in the
    order given (estimator.problem); the returned uav_enu_m rows are in the order given.
    Raises EstimatorError on malformed input, naming the offending value.
    """
    order = _fleet_order(keyframes)
    if order is None:
        return _solve_batch(keyframes, n_users, user_up_m, noise, params, init_users_enu_m, warm)
    if warm is not None:
        # the warm track in the solve's row order: its keyframes where it has them, the others at
        # their fixes (a warm answer that does not fit is refused by _warm_solve as before)
        x_prev = np.asarray(warm.uav_enu_m, dtype=float)
        if x_prev.ndim == 2 and x_prev.shape[1] == 3 and 0 < x_prev.shape[0] <= len(keyframes):
            x_in = np.array([np.asarray(kf.gps_enu_m, dtype=float) for kf in keyframes])
            x_in[: x_prev.shape[0]] = x_prev
            warm = dataclasses.replace(warm, uav_enu_m=x_in[order])
    est = _solve_batch([keyframes[i] for i in order], n_users, user_up_m, noise, params, init_users_enu_m, warm)
    uav = np.empty_like(est.uav_enu_m)
    uav[order] = est.uav_enu_m
    return dataclasses.replace(est, uav_enu_m=uav)


def _fleet_order(keyframes: Sequence[Keyframe]) -> np.ndarray | None:
    """(N,) the keyframes' order sorted by vehicle, stable (each vehicle's in the order given), or
    None when they are already so (one vehicle). Malformed vehicles are left to pack_keyframes."""
    try:
        v = np.array([kf.vehicle for kf in keyframes])
    except AttributeError:
        return None
    if v.ndim != 1 or v.dtype.kind not in "iu" or v.size < 2 or v.min() < 0 or np.all(v[1:] >= v[:-1]):
        return None
    if any(isinstance(kf.vehicle, bool | np.bool_) for kf in keyframes):
        return None
    return np.argsort(v, kind="stable")


def _solve_batch(
    keyframes: Sequence[Keyframe], n_users: int, user_up_m: np.ndarray, noise: NoiseModel,
    params: SolverParams, init_users_enu_m: np.ndarray | None, warm: Estimate | None,
) -> Estimate:
    """solve_batch of keyframes in the solve's row order."""
    prob = pack_keyframes(keyframes, n_users, user_up_m, noise, params)
    k_all, p = prob.n_users, prob.p
    n_ranges = prob.mask.sum(axis=0)
    active = n_ranges >= prob.min_ranges()
    if warm is not None:
        est = _warm_solve(prob, warm, active, n_ranges)
        if est is not None:
            return est
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
    for k, th in grid_init(prob, x, search).items():
        theta[k] = th
    theta[~active] = 0.0
    res = solve_robust(prob, x, theta, active)
    clocks: list = [None] * k_all
    triggered = None
    if params.track_clock and params.estimate_bias and prob.t_s is not None:
        # (a sawtooth is carried by the bias: its amplitude)
        res, clocks, triggered = _track_clocks(prob, res, active)
    solved = res
    res, mirrors = _resolve_mirrors(prob, res, active)
    if triggered is None or res is not solved:
        triggered = _clock_trigger(prob, res, res.lin.w.T >= 0.5, active)
    return estimate_of(prob, res, active, mirrors, n_ranges, clock=clocks, clock_triggered=triggered, widen=True)


def _warm_solve(prob: Problem, warm: Estimate, active: np.ndarray, n_ranges: np.ndarray) -> Estimate | None:
    """The batch solve started from `warm`, the answer for the first N' < N keyframes, keeping its
    model choices: the UAV track and the users (θ with the biases) start where it left them (new
    keyframes at their GPS fixes), and the per-user NLoS probabilities π_k, noise scales s_k, bias
    selection and clock sawtooths (period and phase; the amplitude A_k is re-estimated with the
    positions, r̂ = d + A_k · frac(t/P_k − φ_k) extended to the new keyframes) are the warm
    answer's. One robust solve and the mirror tests then replace the cold solve's bias selection,
    clock detection and their re-solves (estimator.refresh: a cold solve re-makes the choices as
    the data grow). None — solve cold — when the warm answer does not fit: another size, fewer
    keyframes, a user it had not started, choices it does not carry, or a user without a sawtooth
    whose residuals now trigger the clock test (_clock_trigger) and did not in the cold solve."""
    n, k_all, p = prob.n_keyframes, prob.n_users, prob.p
    x_prev = np.asarray(warm.uav_enu_m, dtype=float)
    st = warm.state
    if st is None:
        return None
    warm_active = np.asarray(st.active, dtype=bool)
    clocks = st.clock
    if (
        warm.n_users != k_all or x_prev.ndim != 2 or not 0 < x_prev.shape[0] <= n
        or warm_active.shape != (k_all,) or np.any(active & ~warm_active)
        or clocks is None or len(clocks) != k_all
        or (prob.params.estimate_bias and (warm.bias_m is None or st.bias_on is None))
        or (prob.params.loss == "nlos" and prob.params.nlos_adapt and st.nlos_prob_k is None)
    ):
        return None
    x = prob.gps_enu_m.copy()
    x[: x_prev.shape[0]] = x_prev
    theta = np.zeros((k_all, p))
    theta[:, : prob.user_dim] = np.asarray(warm.users_enu_m, dtype=float)[:, : prob.user_dim]
    if prob.params.estimate_bias:
        theta[:, -1] = np.nan_to_num(np.asarray(warm.bias_m, dtype=float))
        if any(c is not None for c in clocks):
            t = prob.t_s[:n]
            gain = np.ones((n, k_all))
            for k, fit in enumerate(clocks):
                if fit is not None:
                    gain[:, k] = fit.gain(t)
            prob.bias_gain = gain
            prob.bias_force_k = np.array([c is not None for c in clocks])
    theta[~active] = 0.0
    if not np.all(np.isfinite(theta[active])):
        return None
    if st.nlos_prob_k is not None:
        prob.nlos_prob_k = np.asarray(st.nlos_prob_k, dtype=float).copy()
    if prob.params.estimate_noise_scale:
        prob.noise_scale_k = np.asarray(st.noise_scale, dtype=float).copy()
    if prob.params.estimate_bias:
        # the warm answer's bias selection: free biases, the others held (held_bias_prior)
        select_biases(prob, np.asarray(st.bias_on, dtype=bool), held_bias_prior(prob))
    res = solve_robust(prob, x, theta, active)
    if prob.params.estimate_bias and any(c is not None for c in clocks):
        res, clocks = _refine_clocks(prob, res, active, clocks)
    triggered = _clock_trigger(prob, res, res.lin.w.T >= 0.5, active)
    if prob.params.track_clock and prob.params.estimate_bias:
        # a user without a sawtooth whose residuals now call for one (more periods seen since the
        # cold solve, which did not test it): the clock detection needs the cold solve
        tested = np.zeros(k_all, dtype=bool) if st.clock_triggered is None else st.clock_triggered
        untracked = np.array([c is None for c in clocks])
        if np.any(triggered & untracked & ~tested):
            return None
    res, mirrors = _resolve_mirrors(prob, res, active)
    was = triggered if st.clock_triggered is None else st.clock_triggered
    return estimate_of(prob, res, active, mirrors, n_ranges,
                     clock=list(clocks) if prob.params.estimate_bias else [None] * k_all,
                     clock_triggered=triggered | was, warm_started=True, widen=True)


def _clock_trigger(prob: Problem, res: SolveResult, kept: np.ndarray, active: np.ndarray) -> np.ndarray:
    """(K,) users to test for a clock sawtooth: active, with CLOCK_MIN_RANGES kept ranges
    (kept (n, K)), and whose whitened residuals e (the noise scale undone: the test is against
    the assumed σ(d)) about their mean ē are too large or too smooth for white noise:

        RMS = √(Σ (e − ē)² / m) ≥ max(CLOCK_TRIGGER_SCALE, 1 + CLOCK_TRIGGER_RMS_Z / √(2m)),   or
        z = ρ₁ √m₁ ≥ CLOCK_TRIGGER_Z,   ρ₁ = Σ (e_i − ē)(e_(i+1) − ē) / Σ (e − ē)²

    over the m kept ranges and the m₁ pairs of consecutive keyframes both kept (ρ₁ ~ N(0, 1/m₁)
    for white residuals: z ≥ 2 for ~2 % of users without a sawtooth, which costs them a fit that
    the fit's own test then rejects); or whose NLoS probability π_k exceeds
    CLOCK_TRIGGER_NLOS_PROB (seen: π 0.2–0.3 for a 12 m sawtooth, the kept ranges' RMS 1.1).
    A sawtooth sampled many times per period is smooth (ρ₁ ≈ its share of the variance); its
    variance alone hides in the noise of a short log (an 8 m sawtooth at
    σ = 3 m over 120 ranges slipped under the RMS test in 4 of 40 logs, 4–6 m off). The RMS of m
    white residuals has a standard deviation of about 1/√(2m): a fixed 1.08 alone is 1.6 of it at
    m = 200 (it fired on 4 % of white users there, each costing a fit) and 0.7 at m = 40."""
    n = prob.n_keyframes
    wk = kept.T & prob.mask[:n].T
    cnt = wk.sum(axis=1)
    sc = np.ones(prob.n_users) if prob.noise_scale_k is None else prob.noise_scale_k
    e = res.lin.e * sc[:, None]
    mean = (e * wk).sum(axis=1) / np.maximum(cnt, 1)
    dev = (e - mean[:, None]) * wk
    ss = (dev * dev).sum(axis=1)
    rms = np.sqrt(ss / np.maximum(cnt, 1))
    # ρ₁ over consecutive kept pairs (dev is 0 where not kept)
    pairs = (wk[:, 1:] & wk[:, :-1]).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(ss > 0, (dev[:, 1:] * dev[:, :-1]).sum(axis=1) / ss, 0.0) * np.sqrt(pairs)
    rms_min = np.maximum(CLOCK_TRIGGER_SCALE, 1.0 + CLOCK_TRIGGER_RMS_Z / np.sqrt(2.0 * np.maximum(cnt, 1)))
    nlos = np.zeros(prob.n_users, dtype=bool)
    if prob.nlos_prob_k is not None:
        nlos = prob.nlos_prob_k > CLOCK_TRIGGER_NLOS_PROB
    return active & (cnt >= CLOCK_MIN_RANGES) & ((rms >= rms_min) | (z >= CLOCK_TRIGGER_Z) | nlos)


def _clock_residuals(prob: Problem, res: SolveResult) -> tuple[np.ndarray, np.ndarray]:
    """What a clock fit sees at a solution: r̂ − d (n, K) (the sawtooth or bias, and the noise)
    and the range's gradient in the user's position ∂d/∂u = (u − x)/d (n, K, user_dim), the
    nuisance columns of the fit (a solve without the sawtooth moved the user to absorb part of
    it, and the fit takes that back)."""
    n = prob.n_keyframes
    users = users_from_theta(res.theta, prob.user_up_m, prob.user_dim)
    diff = res.x[:, None, :] - users[None, :, :]
    d = np.linalg.norm(diff, axis=2)
    return prob.range_m[:n] - d, -diff[:, :, : prob.user_dim] / d[:, :, None]


def _fit_clocks(prob: Problem, res: SolveResult, users: np.ndarray, gain: np.ndarray, fit_one) -> list:
    """Fit each of `users` (indices) with fit_one(k, t, r, grad) -> SawtoothFit | None on the
    ranges the loss keeps (weight ≥ ½: an NLoS excess is no sawtooth), given CLOCK_MIN_RANGES of
    them (_clock_residuals: r and grad); a fit's gain written into gain (n, K) at all of the
    user's ranges. Returns [(k, fit)] of the users fitted."""
    if len(users) == 0:  # the common case of a cold solve: no residuals to compute
        return []
    n = prob.n_keyframes
    t = prob.t_s[:n]
    kept = res.lin.w.T >= 0.5
    r_all, grad_all = _clock_residuals(prob, res)
    out = []
    for k in users:
        rows = prob.mask[:n, k] & kept[:, k]
        if int(rows.sum()) < CLOCK_MIN_RANGES:
            continue
        # in time order (a fleet's rows are sorted by vehicle first)
        rows = np.flatnonzero(rows)
        rows = rows[np.argsort(t[rows], kind="stable")]
        fit = fit_one(k, t[rows], r_all[rows, k], grad_all[rows, k])
        if fit is None:
            continue
        all_k = prob.mask[:n, k]
        gain[all_k, k] = fit.gain(t[all_k])
        out.append((k, fit))
    return out


def _refine_clocks(prob: Problem, res: SolveResult, active: np.ndarray, clocks: list) -> tuple[SolveResult, list]:
    """A warm solve's tracked sawtooths re-fitted near their (P, φ) on its residuals
    (estimator.clock.refine_sawtooth: more periods seen since the cold solve that found them
    pin them down better), and the problem solved again when any moved."""

    def refine(k, t, r, grad):
        new = refine_sawtooth(t, r, clocks[k], grad)
        moved = new.period_s != clocks[k].period_s or new.phase != clocks[k].phase
        return new if moved else None

    gain = prob.bias_gain.copy()
    tracked = np.array([k for k, c in enumerate(clocks) if c is not None and active[k]], dtype=np.intp)
    moved = _fit_clocks(prob, res, tracked, gain, refine)
    if not moved:
        return res, clocks
    out = list(clocks)
    for k, fit in moved:
        out[k] = fit
    prob.bias_gain = gain
    return solve_robust(prob, res.x, res.theta, active), out


def _track_clocks(prob: Problem, res: SolveResult, active: np.ndarray) -> tuple[SolveResult, list, np.ndarray | None]:
    """Fit a clock sawtooth (estimator.clock) to each user whose range residuals are noisier or
    smoother than white noise of its σ(d) (_clock_trigger); an accepted fit turns the user's bias
    into the sawtooth's amplitude, r̂ = d + A_k · frac(t/P_k − φ_k) (prob.bias_gain, the bias kept free), so that A_k is
    estimated with the positions and its uncertainty enters their covariance; then solve again.
    CLOCK_ROUNDS rounds, each refitting (P, φ) on the residuals of the last solution.
    Returns (result, [SawtoothFit or None] per user, the (K,) clock trigger at that result or None
    when the last round re-solved after computing it). Needs params.estimate_bias (the amplitude
    is the user's bias)."""
    fits: list = [None] * prob.n_users
    gain = np.ones((prob.n_keyframes, prob.n_users))
    for _ in range(CLOCK_ROUNDS):
        trig = _clock_trigger(prob, res, res.lin.w.T >= 0.5, active)
        users = np.flatnonzero(active & (trig | np.array([f is not None for f in fits])))
        found = _fit_clocks(prob, res, users, gain, lambda k, t, r, grad: fit_sawtooth(t, r, grad))
        if not found:
            # res is the one the trigger was computed at
            return res, fits, trig
        theta = res.theta.copy()
        for k, fit in found:
            fits[k] = fit
            theta[k, -1] = fit.amplitude_m
        prob.bias_gain = gain.copy()
        prob.noise_scale_k, prob.bias_sigma_k, prob.bias_mean_k = None, None, None
        prob.bias_force_k = np.array([f is not None for f in fits])
        res = solve_robust(prob, res.x, theta, active)
    return res, fits, None
