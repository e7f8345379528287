"""The online estimator: fixed-lag smoothing over a window of keyframes, marginalization into a
Gaussian prior (estimator.online_marginal), and information-filter steps between window solves
(estimator.online_filter, estimator.online_chain); see docs/keyframes-slam-model.md.

Its state is one object, estimator.online_state.OnlineState; the steps are functions of it (here:
the update, the window solve and its checks). OnlineEstimator is the thin class that owns one."""

from __future__ import annotations

import numpy as np

from estimator.batch import (
    grid_init,
    mirror_all,
)
from estimator.init import users_cost
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
from estimator.online_chain import last_keyframe_information
from estimator.online_filter import filter_step, place_keyframe
from estimator.online_marginal import marginalize_window
from estimator.online_state import OnlineState, window_problem
from estimator.problem import (
    Problem,
    check_keyframe,
    check_params,
    check_users,
    users_from_theta,
)
from estimator.solve import (
    free_biases,
    observed_s,
    solve_robust,
)
from estimator.types import Estimate, Keyframe, SolverParams
from uavloc.errors import EstimatorError

#: the online estimator starts a user once the window holds this many of its ranges ...
ONLINE_MIN_RANGES = 8
#: ... taken from fixes spread over at least this much ground [m]
ONLINE_MIN_EXTENT_M = 10.0
#: the checks of params.online_check_every (re-initialization and mirror tests, bias selection)
#: back off: after a check that changed nothing and left every mirror clearly worse
#: (Δχ² > ONLINE_CHECK_MARGIN · χ²_amb), the interval to the next one doubles, up to
#: ONLINE_CHECK_BACKOFF_MAX · online_check_every; it returns to online_check_every when a user
#: starts, a check flips, selects a different set of biases or finds a close mirror, or a user's
#: noise scale or NLoS probability moved by more than ONLINE_CHECK_EVIDENCE (relative) since the
#: last check
ONLINE_CHECK_MARGIN = 4.0
#: Levenberg–Marquardt iterations of one online full update (each run of the schedule) when
#: filter steps come in between (online_resolve_every > 1): a solve that needs more (a user just
#: started, known from a short arc, in a curved valley of the cost) goes on at the next update,
#: with more ranges, instead of costing tens of iterations at once
ONLINE_MAX_ITERATIONS = 3
ONLINE_CHECK_BACKOFF_MAX = 8
ONLINE_CHECK_EVIDENCE = 0.1
#: ... and, for the noise scale, by more than ONLINE_SCALE_EVIDENCE_Z of its own standard errors:
#: s_k estimated from n_k whitened residuals has a relative standard error of about 1/√(2 n_k)
#: (7 % from a window's 100 ranges), so a 10 % move of it is mostly its noise, not evidence
ONLINE_SCALE_EVIDENCE_Z = 3.0
#: a restarted user that the joint solve takes back to within this of its estimate [m] was not in
#: another basin (check_mirrors: the restart is dropped, the prior kept)
RESTART_SAME_BASIN_M = 2.0


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
    on the window fits clearly better, and tested for its mirror (see check_mirrors).

    The state is `state`, an OnlineState; the steps are the functions of estimator.online,
    estimator.online_filter and estimator.online_marginal.
    """

    def __init__(
        self, n_users: int, user_up_m: np.ndarray, noise: NoiseModel,
        params: SolverParams = SolverParams(),  # noqa: B008
    ):
        if not isinstance(noise, NoiseModel):
            raise EstimatorError(f"noise must be a NoiseModel, got {type(noise).__name__}")
        check_params(params)
        up = check_users(n_users, user_up_m)
        #: everything the estimator carries from one keyframe to the next
        self.state = OnlineState.initial(n_users, up, noise, params, ONLINE_MIN_RANGES)

    @property
    def estimate(self) -> Estimate | None:
        """The latest estimate, None before the first keyframe."""
        return self.state.estimate

    @property
    def n_keyframes_seen(self) -> int:
        return self.state.seen

    def add_keyframe(self, kf: Keyframe) -> Estimate:
        """Add one keyframe with its ranges; return the updated Estimate (add_keyframe below)."""
        return add_keyframe(self.state, kf)


def add_keyframe(st: OnlineState, kf: Keyframe) -> Estimate:
    """Add one keyframe with its ranges; return the updated Estimate.

    Between full window solves (every params.online_resolve_every keyframes, or whenever a
    user starts, a motion factor links the keyframe, the window is full or the filter step
    is large) the keyframe is folded in by one information-filter step (online_filter.filter_step).
    """
    gps, idx, rng, odom = check_keyframe(kf, st.k)
    if st.marginalize_due:
        marginalize_window(st)
    n = st.n
    st.gps_enu_m[n] = gps
    st.range_m[n] = np.nan
    st.range_m[n, idx] = rng
    # a motion factor where the keyframe carries a displacement and its σ (own, else the params')
    sm = kf.odom_sigma_m if kf.odom_sigma_m is not None else st.params.motion_sigma_m
    st.odom_mask[n] = odom is not None and n + st.seen > 0 and sm is not None
    st.odom_sigma_m[n] = float(sm) if st.odom_mask[n] else np.nan
    st.t_s[n] = float(kf.t_s)
    st.odom_enu_m[n] = odom if odom is not None else 0.0
    st.win_count[idx] += 1
    st.n_ranges[idx] += 1
    st.seen += 1
    st.n = n + 1
    every = int(st.params.online_resolve_every)
    # (not tried again after a refusal until a solve converges: it would be refused again)
    if (
        every > 1 and st.s is not None and not st.refused and st.n < st.capacity
        and (not st.odom_mask[n] or (st.s_aug is not None and n > 0))
        and (not st.gps_linked or (st.s_aug is not None and n > 0))
        and st.seen % every != 0
        and (st.all_active or not (~st.active[idx] & (st.win_count[idx] >= st.min_start)).any())
    ):
        est = filter_step(st, n, gps, idx, rng)
        if est is not None:
            st.estimate = est
            return est
        st.refused = True
    est = full_update(st, n, gps, idx, rng, odom)
    st.estimate = est
    return est


def full_update(
    st: OnlineState, n: int, gps: np.ndarray, idx: np.ndarray, rng: np.ndarray, odom: np.ndarray | None,
) -> Estimate:
    """Start users that are ready, re-solve the window (Levenberg–Marquardt from the previous
    solution, with the prior) and re-check mirrors; the window is marginalized down to
    params.window at this solution when the next keyframe arrives (online_marginal.marginalize_window)."""
    # a new keyframe starts at its GPS fix, or dead-reckoned from the previous one, moved to
    # where the ranges to the users already estimated put it
    st.x[n] = st.x[n - 1] + odom if (st.odom_mask[n] and n > 0) else gps
    if idx.size and st.active.any():
        st.x[n] = place_keyframe(st, st.x[n], gps, idx, rng)
    prob = window_problem(st)
    newly = np.zeros(st.k, dtype=bool)
    ready = ~st.active & (prob.mask.sum(axis=0) >= st.min_start)
    start = []
    for k in np.flatnonzero(ready):
        fixes = st.x[: st.n][prob.mask[:, k], :2]
        if float(np.max(np.ptp(fixes, axis=0))) >= ONLINE_MIN_EXTENT_M:
            start.append(k)
    for k, th in grid_init(prob, st.x[: st.n], start).items():
        st.theta[k] = th
        st.active[k] = newly[k] = True
    check = check_due(st, newly)
    if check:
        prob.bias_sigma_k = prob.bias_mean_k = None  # choose again which biases to estimate
    # with filter steps in between (online_resolve_every > 1) a solve is amortized over the
    # updates: capped iterations, one round of the NLoS-probability and noise-scale estimates
    # (the next update goes on from here); online_resolve_every = 1 solves fully every time
    amortize = int(st.params.online_resolve_every) > 1
    res = solve_robust(
        prob, st.x[: st.n].copy(), st.theta, st.active, st.prior,
        step_tol_m=st.params.online_step_tol_m, max_iterations=ONLINE_MAX_ITERATIONS if amortize else None,
        rounds=1 if amortize else None,
    )
    st.x[: st.n] = res.x
    st.theta = res.theta
    if prob.nlos_prob_k is not None:
        st.nlos_pi = prob.nlos_prob_k
    if prob.noise_scale_k is not None:
        st.noise_scale = prob.noise_scale_k.copy()
        st.noise_scale_list = st.noise_scale.tolist()
    st.bias_sigma_m, st.bias_mean_m = prob.bias_sigma_k, prob.bias_mean_k
    if check:
        res = check_mirrors(st, prob, res)
        st.last_check = st.seen
        after_check(st, newly, st.flipped)
    est = estimate_of(prob, res, st.active, st.mirrors, st.n_ranges)
    st.users_enu_m = users_from_theta(st.theta, st.user_up_m, st.params.user_dim)
    st.all_active = bool(st.active.all())
    st.nlos_pi_list = st.nlos_pi.tolist()
    st.s = res.s
    st.refused = st.refused and not res.converged
    st.s_aug = None
    if ((st.gps_linked or bool(st.odom_mask[: st.n].any())) and res.s is not None
            and int(st.params.online_resolve_every) > 1):
        # the summary of the Gauss–Markov filter steps (estimator.online_chain)
        st.s_aug = last_keyframe_information(res.lin, res.s)
    st.cost = res.lin.cost
    # the window is marginalized down to params.window at this solution, but at the start of
    # the next update (marginalize_window): the same prior, while this update, the one that
    # carries the solve, returns sooner
    st.marginalize_due = st.n > st.params.window
    return est


def check_due(st: OnlineState, newly: np.ndarray) -> bool:
    """Whether this full update re-runs the checks (ONLINE_CHECK_BACKOFF_MAX docstring)."""
    if np.any(newly):
        return True
    if st.check_state is not None:
        scale0, pi0, _ = st.check_state
        # a noise scale's move counted in its standard errors, 1/√(2 n_k) relative
        scale_tol = np.maximum(ONLINE_CHECK_EVIDENCE,
                               ONLINE_SCALE_EVIDENCE_Z / np.sqrt(2.0 * np.maximum(st.win_count, 1)))
        moved = bool(np.any(np.abs(st.noise_scale / scale0 - 1.0) > scale_tol)
                     or np.any(np.abs(st.nlos_pi / pi0 - 1.0) > ONLINE_CHECK_EVIDENCE))
        if moved:
            st.check_interval = max(int(st.params.online_check_every), 1)
    # the first full update past a multiple of the interval
    return st.seen // st.check_interval > st.last_check // st.check_interval


def after_check(st: OnlineState, newly: np.ndarray, flipped: bool) -> None:
    """Next check interval: doubled after an uneventful check, else online_check_every."""
    every = max(int(st.params.online_check_every), 1)
    chi2 = st.params.ambiguity_chi2
    close = any(
        mt is not None and mt.mirror_theta is not None and not mt.mirror_refuted
        and (mt.ambiguous or mt.delta_chi2 <= ONLINE_CHECK_MARGIN * chi2)
        for mt in st.mirrors
    )
    # which biases are free (a held one's σ moves with its noise scale under bias_held "sawtooth")
    bias_on = free_biases(st.params, st.bias_sigma_m)
    prev = st.check_state
    bias_changed = prev is not None and not (
        (prev[2] is None and bias_on is None)
        or (prev[2] is not None and bias_on is not None and np.array_equal(prev[2], bias_on)))
    quiet = not (np.any(newly) or flipped or close or bias_changed)
    st.check_interval = min(2 * st.check_interval, ONLINE_CHECK_BACKOFF_MAX * every) if quiet else every
    st.check_state = (st.noise_scale.copy(), st.nlos_pi.copy(), bias_on)


def check_mirrors(st: OnlineState, prob: Problem, res: SolveResult) -> SolveResult:
    """Re-initialization and mirror tests on the window.

    A user whose grid initialization on the window's ranges fits clearly better than its
    estimate (an early start from few ranges that went to a wrong basin) is restarted there
    and its part of the prior, linearized in the wrong basin, is dropped. A user whose mirror
    fits clearly better jumps to it with its prior reflected.

    Users are coupled only through the keyframe poses, so each user is judged by its own
    ranges with the window's track fixed, and all the restarts (then all the flips) are
    re-solved in one joint Levenberg–Marquardt run: one solve per check, not one per user
    (with 200 users along a first straight leg a solve per user made the worker fall minutes
    behind the flight). Flips are kept when the joint cost drops; if it does not, each flip
    is tried alone, as the joint run may have been spoilt by one of them.

    With a cell of limited reach (params.coverage_m) the window's silent keyframes judge the
    mirrors as in a batch solve (estimator.batch.mirror_all, estimator.silence): a mirror they
    refute is no ambiguity and never flipped to. A refuted estimate is left to the batch
    refreshes (estimator.refresh), which see every keyframe: the window forgets the silence
    as it slides, and its prior ties the user to where it was linearized.
    """
    chi2 = st.params.ambiguity_chi2
    flipped = False
    x_win = res.x
    restart: dict[int, np.ndarray] = {}
    # users ranged from the same keyframes are initialized and costed together (the same
    # numbers as one at a time: estimator.init.init_users, users_cost)
    # (a user the window no longer ranges enough, its ranges all marginalized when the UAV flew
    # out of its reach, has nothing in the window to restart from)
    active = np.flatnonzero(st.active & (prob.mask.sum(axis=0) >= prob.min_ranges())).tolist()
    fresh = grid_init(prob, x_win, active)
    groups: dict[bytes, list[int]] = {}
    for k in active:
        groups.setdefault(prob.mask[:, k].tobytes(), []).append(k)
    for ks in groups.values():
        rows = prob.mask[:, ks[0]]
        uav, rng_g, up = x_win[rows], prob.range_m[rows][:, ks], st.user_up_m[ks]
        fit_theta = np.array([fresh[k] for k in ks])
        cur = users_cost(uav, rng_g, res.theta[ks], up, st.noise, st.params)
        new = users_cost(uav, rng_g, fit_theta, up, st.noise, st.params)
        for i, k in enumerate(ks):
            th = fit_theta[i]
            # not when the fresh start is the current estimate's mirror: that is the mirror
            # test's call
            mt = (st.mirrors[k] if k < len(st.mirrors) else None)
            near_mirror = (
                mt is not None and mt.mirror_theta is not None
                and np.linalg.norm(th[:2] - mt.mirror_theta[:2]) < 0.1 * np.linalg.norm(
                    mt.mirror_theta[:2] - res.theta[k, :2])
            )
            if (2.0 * (cur[i] - new[i]) > chi2 and not near_mirror
                    and np.linalg.norm(th[:2] - res.theta[k, :2]) > 2.0):
                restart[int(k)] = th
    if restart:
        theta = res.theta.copy()
        prior = st.prior
        for k, th in restart.items():
            theta[k] = th
            prior = _dropped_prior(prior, user_offset(st, k), st.p)
        trial = levenberg_marquardt(prob, res.x, theta, st.active, prior)
        # a restart is kept when some restarted user stays in another basin; when all of them
        # come back to where they were, the fresh start only looked better under the
        # initialization's simpler model (π, noise scale): the estimate and its prior are kept
        back = all(np.linalg.norm(trial.theta[k, :2] - res.theta[k, :2]) <= RESTART_SAME_BASIN_M
                   for k in restart)
        if not back:
            res, st.prior, flipped = trial, prior, True
    # the users the window ranges enough are tested; the others keep their last test
    tested = np.zeros_like(st.active)
    tested[active] = True
    mirrors = _keep_untested(mirror_all(prob, res.theta, tested), st.mirrors)
    # a prior that also holds the first keyframe (Gauss–Markov GPS or motion links) ties the
    # users to the whole marginalized track: reflecting one user's part of it is no longer a
    # consistent mirror hypothesis, so the window's mirror test only flags, it does not flip
    can_flip = st.prior is None or not st.prior.has_x
    flip = [k for k, mt in enumerate(mirrors)
            if can_flip and tested[k] and mt is not None and mt.mirror_is_better(chi2)]
    for group in (([flip] if flip else []) + ([[k] for k in flip] if len(flip) > 1 else [])):
        theta, prior = res.theta.copy(), st.prior
        for k in group:
            theta[k] = mirrors[k].mirror_theta
            prior = _reflected_prior(prior, user_offset(st, k), res.theta[k, :2], mirrors[k].mirror_theta[:2])
        trial = levenberg_marquardt(prob, res.x, theta, st.active, prior)
        if trial.lin.cost < res.lin.cost:
            res, st.prior, flipped = trial, prior, True
            if group is flip:
                break
    st.flipped = flipped
    if flipped:
        res = observed_s(prob, res, st.active, st.prior)
        st.x[: st.n] = res.x
        st.theta = res.theta
        mirrors = _keep_untested(mirror_all(prob, res.theta, tested), st.mirrors)
    st.mirrors = mirrors
    return res


def _keep_untested(mirrors: list, previous: list) -> list:
    """The new mirror tests, and the last one of each user not tested now."""
    return [m if m is not None or k >= len(previous) else previous[k] for k, m in enumerate(mirrors)]


def user_offset(st: OnlineState, k: int) -> int:
    """Index of user k's first parameter in the prior's state vector."""
    has_x = st.prior is not None and st.prior.has_x
    return (3 if has_x else 0) + k * st.p


def _dropped_prior(pr: Prior | None, off: int, p: int) -> Prior | None:
    """The prior without any information on the user whose p parameters start at `off` (its
    rows and columns zeroed)."""
    if pr is None:
        return None
    sl = slice(off, off + p)
    info, grad = pr.info.copy(), pr.grad.copy()
    info[sl, :] = 0.0
    info[:, sl] = 0.0
    grad[sl] = 0.0
    return Prior(pr.has_x, pr.z0.copy(), info, grad)


def _reflected_prior(pr: Prior | None, off: int, u_h: np.ndarray, m_h: np.ndarray) -> Prior | None:
    """The prior with the horizontal coordinates at off, off+1 (a user's) reflected across the
    bisector of u → m.

    Reflection z' = c + R(z − c) with R = I − 2 n nᵀ, n = (m − u)/|m − u|, c = (u + m)/2:
    L'(z) = L(reflect(z)) gives c' = Rᵀc, Λ' = RᵀΛR, z0' = reflect(z0).
    """
    if pr is None:
        return None
    nvec = (m_h - u_h) / max(float(np.linalg.norm(m_h - u_h)), 1e-12)
    ctr = 0.5 * (u_h + m_h)
    refl2 = np.eye(2) - 2.0 * np.outer(nvec, nvec)
    r = np.eye(pr.z0.size)
    r[off : off + 2, off : off + 2] = refl2
    z0 = pr.z0.copy()
    z0[off : off + 2] = ctr + refl2 @ (z0[off : off + 2] - ctr)
    return Prior(pr.has_x, z0, r.T @ pr.info @ r, r.T @ pr.grad)
