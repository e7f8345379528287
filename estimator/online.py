"""The online estimator: fixed-lag smoothing over a window of keyframes, marginalization into a
Gaussian prior (estimator.online_marginal), and information-filter steps between window solves
(estimator.online_filter, estimator.online_chain); see docs/keyframes-slam-model.md."""

from __future__ import annotations

import numpy as np

from estimator.batch import (
    _grid_init,
    _mirror_all,
)
from estimator.init import users_cost
from estimator.linearize import (
    Prior,
)
from estimator.lm import (
    _Result,
    levenberg_marquardt,
)
from estimator.marginals import (
    _estimate,
)
from estimator.noise import NoiseModel
from estimator.online_chain import last_keyframe_information
from estimator.online_filter import FilterSteps
from estimator.online_marginal import WindowMarginalization
from estimator.problem import (
    Problem,
    check_keyframe,
    check_params,
    check_users,
    users_from_theta,
)
from estimator.solve import (
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
#: another basin (_check_mirrors: the restart is dropped, the prior kept)
RESTART_SAME_BASIN_M = 2.0




class OnlineEstimator(FilterSteps, WindowMarginalization):
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
        self._odom_sigma = np.full(cap, np.nan)  # σ_m of each keyframe's motion factor [m], NaN where none
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
        #: a filter step was refused since the last full update whose solve converged (within its
        #: capped iterations): the users still move by more than a filter step may
        self._refused = False
        # information of [last window keyframe, Θ] (Gauss–Markov GPS filter steps), or None
        self._s_aug: np.ndarray | None = None
        self._cost = float("nan")
        self._last_check = 0
        self._check_interval = max(int(params.online_check_every), 1)
        self._check_state: tuple | None = None  # (noise scale, π, biases on) at the last check
        self._flipped = False  # the last check moved a user
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
        self._marginalize_due = False  # the last full solve left the window beyond params.window

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
            bias_sigma_k=self._bias_sigma, odom_sigma_m=self._odom_sigma[:n],
        )

    def add_keyframe(self, kf: Keyframe) -> Estimate:
        """Add one keyframe with its ranges; return the updated Estimate.

        Between full window solves (every params.online_resolve_every keyframes, or whenever a
        user starts, a motion factor links the keyframe, the window is full or the filter step
        is large) the keyframe is folded in by one information-filter step (_filter_step).
        """
        gps, idx, rng, odom = check_keyframe(kf, self._k)
        if self._marginalize_due:
            self._marginalize_window()
        n = self._n
        self._gps[n] = gps
        self._rng[n] = np.nan
        self._rng[n, idx] = rng
        # a motion factor where the keyframe carries a displacement and its σ (own, else the params')
        sm = kf.odom_sigma_m if kf.odom_sigma_m is not None else self._params.motion_sigma_m
        self._odom_mask[n] = odom is not None and n + self._seen > 0 and sm is not None
        self._odom_sigma[n] = float(sm) if self._odom_mask[n] else np.nan
        self._t[n] = float(kf.t_s)
        self._odom[n] = odom if odom is not None else 0.0
        self._win_count[idx] += 1
        self._n_ranges[idx] += 1
        self._seen += 1
        self._n = n + 1
        every = int(self._params.online_resolve_every)
        # (not tried again after a refusal until a solve converges: it would be refused again)
        if (
            every > 1 and self._s is not None and not self._refused and self._n < self._cap
            and (not self._odom_mask[n] or (self._s_aug is not None and n > 0))
            and (not self._gps_linked or (self._s_aug is not None and n > 0))
            and self._seen % every != 0
            and (self._all_active or not (~self._active[idx] & (self._win_count[idx] >= self._min_start)).any())
        ):
            est = self._filter_step(n, gps, idx, rng)
            if est is not None:
                self._estimate = est
                return est
            self._refused = True
        est = self._full_update(n, gps, idx, rng, odom)
        self._estimate = est
        return est

    def _full_update(
        self, n: int, gps: np.ndarray, idx: np.ndarray, rng: np.ndarray, odom: np.ndarray | None,
    ) -> Estimate:
        """Start users that are ready, re-solve the window (Levenberg–Marquardt from the previous
        solution, with the prior) and re-check mirrors; the window is marginalized down to
        params.window at this solution when the next keyframe arrives (_marginalize_window)."""
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
        check = self._check_due(newly)
        if check:
            prob.bias_sigma_k = None  # choose again which biases to estimate
        # with filter steps in between (online_resolve_every > 1) a solve is amortized over the
        # updates: capped iterations, one round of the NLoS-probability and noise-scale estimates
        # (the next update goes on from here); online_resolve_every = 1 solves fully every time
        amortize = int(self._params.online_resolve_every) > 1
        res = solve_robust(
            prob, self._x[: self._n].copy(), self._theta, self._active, self._prior,
            step_tol_m=self._params.online_step_tol_m, max_iterations=ONLINE_MAX_ITERATIONS if amortize else None,
            rounds=1 if amortize else None,
        )
        self._x[: self._n] = res.x
        self._theta = res.theta
        if prob.nlos_prob_k is not None:
            self._nlos_pi = prob.nlos_prob_k
        if prob.noise_scale_k is not None:
            self._scale = prob.noise_scale_k.copy()
            self._scale_list = self._scale.tolist()
        self._bias_sigma = prob.bias_sigma_k
        if check:
            res = self._check_mirrors(prob, res)
            self._last_check = self._seen
            self._after_check(newly, self._flipped)
        est = _estimate(prob, res, self._active, self._mirrors, self._n_ranges)
        self._users = users_from_theta(self._theta, self._up, self._params.user_dim)
        self._all_active = bool(self._active.all())
        self._nlos_pi_list = self._nlos_pi.tolist()
        self._s = res.s
        self._refused = self._refused and not res.converged
        self._s_aug = None
        if ((self._gps_linked or bool(self._odom_mask[: self._n].any())) and res.s is not None
                and int(self._params.online_resolve_every) > 1):
            # the summary of the Gauss–Markov filter steps (estimator.online_chain)
            self._s_aug = last_keyframe_information(res.lin, res.s)
        self._cost = res.lin.cost
        # the window is marginalized down to params.window at this solution, but at the start of
        # the next update (_marginalize_window): the same prior, while this update, the one that
        # carries the solve, returns sooner
        self._marginalize_due = self._n > self._params.window
        return est

    def _marginalize_window(self) -> None:
        """Fold the keyframes beyond params.window into the prior, at the last full solve's
        estimate (nothing has moved since: the update that solved deferred this)."""
        self._marginalize_due = False
        if self._n > self._params.window:
            m = self._n - self._params.window
            if not (self._marginalize_block(m) or self._marginalize_chain(m)):
                while self._n > self._params.window:
                    self._marginalize_oldest()

    def _check_due(self, newly: np.ndarray) -> bool:
        """Whether this full update re-runs the checks (ONLINE_CHECK_BACKOFF_MAX docstring)."""
        if np.any(newly):
            return True
        if self._check_state is not None:
            scale0, pi0, _ = self._check_state
            # a noise scale's move counted in its standard errors, 1/√(2 n_k) relative
            scale_tol = np.maximum(ONLINE_CHECK_EVIDENCE,
                                   ONLINE_SCALE_EVIDENCE_Z / np.sqrt(2.0 * np.maximum(self._win_count, 1)))
            moved = bool(np.any(np.abs(self._scale / scale0 - 1.0) > scale_tol)
                         or np.any(np.abs(self._nlos_pi / pi0 - 1.0) > ONLINE_CHECK_EVIDENCE))
            if moved:
                self._check_interval = max(int(self._params.online_check_every), 1)
        # the first full update past a multiple of the interval
        return self._seen // self._check_interval > self._last_check // self._check_interval

    def _after_check(self, newly: np.ndarray, flipped: bool) -> None:
        """Next check interval: doubled after an uneventful check, else online_check_every."""
        every = max(int(self._params.online_check_every), 1)
        chi2 = self._params.ambiguity_chi2
        close = any(
            mt is not None and mt.mirror_theta is not None
            and (mt.ambiguous or mt.delta_chi2 <= ONLINE_CHECK_MARGIN * chi2)
            for mt in self._mirrors
        )
        bias_on = None if self._bias_sigma is None else self._bias_sigma.copy()
        prev = self._check_state
        bias_changed = prev is not None and not (
            (prev[2] is None and bias_on is None)
            or (prev[2] is not None and bias_on is not None and np.array_equal(prev[2], bias_on)))
        quiet = not (np.any(newly) or flipped or close or bias_changed)
        self._check_interval = min(2 * self._check_interval, ONLINE_CHECK_BACKOFF_MAX * every) if quiet else every
        self._check_state = (self._scale.copy(), self._nlos_pi.copy(), bias_on)

    def _check_mirrors(self, prob: Problem, res: _Result) -> _Result:
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
        """
        chi2 = self._params.ambiguity_chi2
        flipped = False
        x_win = res.x
        restart: dict[int, np.ndarray] = {}
        # users ranged from the same keyframes are initialized and costed together (the same
        # numbers as one at a time: estimator.init.init_users, users_cost)
        active = np.flatnonzero(self._active).tolist()
        fresh = _grid_init(prob, x_win, active)
        groups: dict[bytes, list[int]] = {}
        for k in active:
            groups.setdefault(prob.mask[:, k].tobytes(), []).append(k)
        for ks in groups.values():
            rows = prob.mask[:, ks[0]]
            uav, rng_g, up = x_win[rows], prob.range_m[rows][:, ks], self._up[ks]
            fit_theta = np.array([fresh[k] for k in ks])
            cur = users_cost(uav, rng_g, res.theta[ks], up, self._noise, self._params)
            new = users_cost(uav, rng_g, fit_theta, up, self._noise, self._params)
            for i, k in enumerate(ks):
                th = fit_theta[i]
                # not when the fresh start is the current estimate's mirror: that is the mirror
                # test's call
                mt = (self._mirrors[k] if k < len(self._mirrors) else None)
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
            prior = self._prior
            for k, th in restart.items():
                theta[k] = th
                prior = _dropped_prior(prior, self._user_offset(k), self._p)
            trial = levenberg_marquardt(prob, res.x, theta, self._active, prior)
            # a restart is kept when some restarted user stays in another basin; when all of them
            # come back to where they were, the fresh start only looked better under the
            # initialization's simpler model (π, noise scale): the estimate and its prior are kept
            back = all(np.linalg.norm(trial.theta[k, :2] - res.theta[k, :2]) <= RESTART_SAME_BASIN_M
                       for k in restart)
            if not back:
                res, self._prior, flipped = trial, prior, True
        mirrors = _mirror_all(prob, res.theta, self._active)
        # a prior that also holds the first keyframe (Gauss–Markov GPS or motion links) ties the
        # users to the whole marginalized track: reflecting one user's part of it is no longer a
        # consistent mirror hypothesis, so the window's mirror test only flags, it does not flip
        can_flip = self._prior is None or not self._prior.has_x
        flip = [k for k, mt in enumerate(mirrors) if can_flip and mt is not None and mt.mirror_is_better(chi2)]
        for group in (([flip] if flip else []) + ([[k] for k in flip] if len(flip) > 1 else [])):
            theta, prior = res.theta.copy(), self._prior
            for k in group:
                theta[k] = mirrors[k].mirror_theta
                prior = _reflected_prior(prior, self._user_offset(k), res.theta[k, :2], mirrors[k].mirror_theta[:2])
            trial = levenberg_marquardt(prob, res.x, theta, self._active, prior)
            if trial.lin.cost < res.lin.cost:
                res, self._prior, flipped = trial, prior, True
                if group is flip:
                    break
        self._flipped = flipped
        if flipped:
            res = observed_s(prob, res, self._active, self._prior)
            self._x[: self._n] = res.x
            self._theta = res.theta
            mirrors = _mirror_all(prob, res.theta, self._active)
        self._mirrors = mirrors
        return res

    def _user_offset(self, k: int) -> int:
        """Index of user k's first parameter in the prior's state vector."""
        has_x = self._prior is not None and self._prior.has_x
        return (3 if has_x else 0) + k * self._p


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
