"""The online estimator: fixed-lag smoothing over a window of keyframes, marginalization into a
Gaussian prior, and information-filter steps between window solves (estimator.slam docstring)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.special import erfcx

from estimator.batch import (
    _grid_init,
    _mirror_all,
)
from estimator.gps import gps_chain_terms, gps_phi
from estimator.init import init_user, user_cost
from estimator.linearize import (
    Prior,
    _range_terms,
    linearize,
)
from estimator.lm import (
    _Result,
    levenberg_marquardt,
)
from estimator.marginals import (
    _covariances,
    _estimate,
)
from estimator.noise import NoiseModel
from estimator.online_chain import chain_marginal_prior, chain_step, last_keyframe_information
from estimator.problem import (
    Problem,
    check_keyframe,
    check_params,
    check_users,
    users_from_theta,
)
from estimator.robust import loss_psi_weight, nlos_args
from estimator.schur import sym3_cofactors
from estimator.solve import (
    observed_s,
    solve_robust,
)
from estimator.types import Estimate, Keyframe, SolverParams
from uavloc.errors import EstimatorError

_SQRT_HALF_PI = math.sqrt(0.5 * math.pi)
_SQRT_HALF = math.sqrt(0.5)
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
#: a filter step may move a parameter by this many of its standard deviations (or by
#: params.online_max_step_m, whichever is larger) before the window is re-solved instead
ONLINE_STEP_SIGMA = 0.5
ONLINE_CHECK_BACKOFF_MAX = 8
ONLINE_CHECK_EVIDENCE = 0.1


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
        if (
            every > 1 and self._s is not None and self._n < self._cap
            and (not self._odom_mask[n] or (self._s_aug is not None and n > 0))
            and (not self._gps_linked or (self._s_aug is not None and n > 0))
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
        self._s_aug = None
        if ((self._gps_linked or bool(self._odom_mask[: self._n].any())) and res.s is not None
                and int(self._params.online_resolve_every) > 1):
            # the summary of the Gauss–Markov filter steps (estimator.online_chain)
            self._s_aug = last_keyframe_information(res.lin, res.s)
        self._cost = res.lin.cost
        if self._n > self._params.window:
            m = self._n - self._params.window
            if not (self._marginalize_block(m) or self._marginalize_chain(m)):
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
        # a Gauss–Markov GPS link or a motion factor ties x_n to the last keyframe: the chain step
        linked = self._gps_linked or bool(self._odom_mask[n])
        phi = 0.0
        if self._gps_linked:
            # the Gauss–Markov prediction x_n⁰ = x̂_n + φ_n (x_l − x̂_l): the GPS factor's residual is 0
            phi = float(gps_phi(self._t[n - 1 : n + 1], noise.gps_tau_used_s)[1])
            x0 = gps + phi * (self._x[n - 1] - self._gps[n - 1])
        else:
            x0 = gps
            self._x[n] = gps
            if not linked:
                self._s_aug = None  # no longer the summary of the last keyframe
        if self._all_active:
            if idx.size == 0:
                return self._chain_step(n, x0, phi, None) if linked else self._filter_estimate(self._s, None)
            ka, r_list = idx, rng.tolist()
        else:
            use = self._active[idx]
            if not use.any():
                return self._chain_step(n, x0, phi, None) if linked else self._filter_estimate(self._s, None)
            ka, r_list = idx[use], rng[use].tolist()
        ka_list = ka.tolist()
        # every user ranged, in order: S_add covers all of S
        full = ka_list == self._k_list
        p, d_u = self._p, params.user_dim
        with_bias = params.estimate_bias
        # per range, in Python floats (m ≤ K small): geometry, residual, Jacobian factors
        gx, gy, gz = x0.tolist()
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
        # (the GPS factor of a linked keyframe enters in _chain_step)
        ig = 0.0 if linked else self._inv_g2
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
        if linked:
            h_nn = np.array([[h00, h01, h02], [h01, h11, h12], [h02, h12, h22]])
            cols = (ka[:, None] * p + self._arange_p).ravel()
            h_tt = np.zeros((m * p, m * p))
            h_tt.ravel()[self._blockdiag_index(m)] = ((jt * w_a[:, None])[:, :, None] * jt[:, None, :]).ravel()
            g_t = (jt * np.array(psi)[:, None]).ravel()
            np.negative(g_t, out=g_t)
            return self._chain_step(n, x0, phi, (h_nn, np.array([g0, g1, g2]), b, cols, h_tt, g_t))
        hinv = _inv3_sym(h00, h01, h02, h11, h12, h22)
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
        if not self._step_ok(dth, cov):
            return None
        # Δx_n = H_nn⁻¹ (g_n − H_nθ Δθ)
        self._x[n] = gps + hg - hb @ (dth if full else dth[cols])
        self._theta = self._theta + dth.reshape(self._k, p)
        self._users[:, :d_u] = self._theta[:, :d_u]
        self._s = s_new
        return self._filter_estimate(s_new, cov)

    def _chain_step(self, n: int, x0: np.ndarray, phi: float, ranges: tuple | None) -> Estimate | None:
        """The filter step of a keyframe linked to the last one by its Gauss–Markov GPS factor
        and/or a relative-motion factor (estimator.online_chain): the window summarized by Ŝ, the
        information of [x_l, Θ]; x_l moves with the step, the older keyframes keep their positions
        until the next full solve.
        ranges: the new keyframe's range terms at x0 (online_chain.chain_step), None without any.
        None when the step is larger than params.online_max_step_m or J is not positive definite."""
        p_all = self._k * self._p
        if ranges is None:
            ranges = (np.zeros((3, 3)), np.zeros(3), np.zeros((3, 0)), np.zeros(0, dtype=np.intp),
                      np.zeros((0, 0)), np.zeros(0))
        # W_n = 1/(σ_gps² (1 − φ²)); a motion factor W_m = 1/σ_m², δ = x_n⁰ − x_l − ô_n
        w_gps = 1.0 / (self._noise.sigma_gps_m**2 * (1.0 - phi * phi))
        w_m, delta_m = 0.0, None
        if self._odom_mask[n]:
            w_m = 1.0 / float(self._odom_sigma[n]) ** 2
            delta_m = x0 - self._x[n - 1] - self._odom[n]
        try:
            dx_l, dx_n, dth, s_aug, cov = chain_step(self._s_aug, phi, w_gps, *ranges, w_m=w_m, delta_m=delta_m)
        except np.linalg.LinAlgError:
            return None
        if p_all and not self._step_ok(dth, cov):
            return None
        self._x[n - 1] += dx_l
        self._x[n] = x0 + dx_n
        self._theta = self._theta + dth.reshape(self._k, self._p)
        self._users[:, : self._params.user_dim] = self._theta[:, : self._params.user_dim]
        self._s_aug = s_aug
        # the users' information: Ŝ' with x_n eliminated
        s_nt = s_aug[:3, 3:]
        self._s = s_aug[3:, 3:] - s_nt.T @ np.linalg.solve(s_aug[:3, :3], s_nt)
        return self._filter_estimate(self._s, cov)

    def _step_ok(self, dth: np.ndarray, cov: np.ndarray) -> bool:
        """A filter step ΔΘ (P,) is kept when no parameter moves by more than the larger of
        params.online_max_step_m and, where that is at least twice as large, ONLINE_STEP_SIGMA of
        its standard deviation (from the step's covariance cov (P, P)): a user still known to
        several metres or worse (just started, few ranges from a short arc) moves metres per
        keyframe, within its uncertainty, without a re-solve."""
        step = np.abs(dth)
        lim = self._params.online_max_step_m
        if step.max() <= lim:
            return True
        rel = ONLINE_STEP_SIGMA * np.sqrt(np.maximum(np.diag(cov), 0.0))
        return bool(np.all(step <= np.where(rel >= 2.0 * lim, rel, lim)))

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

    def _check_due(self, newly: np.ndarray) -> bool:
        """Whether this full update re-runs the checks (ONLINE_CHECK_BACKOFF_MAX docstring)."""
        if np.any(newly):
            return True
        if self._check_state is not None:
            scale0, pi0, _ = self._check_state
            moved = max(float(np.max(np.abs(self._scale / scale0 - 1.0))),
                        float(np.max(np.abs(self._nlos_pi / pi0 - 1.0))))
            if moved > ONLINE_CHECK_EVIDENCE:
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
        self._flipped = flipped
        if flipped:
            res = observed_s(prob, res, self._active, self._prior)
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

    def _marginalize_block(self, m: int) -> bool:
        """Fold the m oldest keyframes into the prior at once when nothing links them to each
        other or to the rest (white GPS, no motion links, a prior on the users only); False
        (nothing done) otherwise. Each keyframe i is then independent given Θ, so the sequential
        _marginalize_oldest at the same point sums to

            Λ = Λ_prior + Σ_i (H_θθ,i − H_θi H_ii⁻¹ H_iθ),   c = ∇_prior + Σ_i (∇_θ,i − H_θi H_ii⁻¹ ∇_i)

        with H_ii = I/σ_gps² + Σ_k w J_x J_xᵀ, H_iθ = w J_x J_θᵀ (user k's columns),
        H_θθ,i = w J_θ J_θᵀ, ∇_i = (x_i − x̂_i)/σ_gps² + Σ_k ψ J_x, ∇_θ,i = ψ J_θ."""
        prob = self._problem()
        pr = self._prior
        if prob.gps_linked or (pr is not None and pr.has_x) or (
                prob.use_motion and bool(self._odom_mask[1 : m + 1].any())):
            return False
        k_all, p = self._k, self._p
        pu = k_all * p
        x = self._x[:m]
        theta = self._theta
        mask = prob.mask[:m].T & self._active[:, None]
        _e, w, _rho, jac, psi = _range_terms(prob, x, theta, mask)
        jx, jt = jac[:3], jac[3:]  # (3, K, m), (p, K, m)
        inv_g2 = 1.0 / self._noise.sigma_gps_m**2
        # H_ii (m, 3, 3), H_iθ (m, 3, K, p), ∇_i (m, 3)
        wjx = jx * w
        h_ii = np.einsum("akm,bkm->mab", wjx, jx) + np.eye(3) * inv_g2
        h_it = np.einsum("akm,ckm->makc", wjx, jt).reshape(m, 3, pu)
        g_i = (x - prob.gps_enu_m[:m]) * inv_g2 + np.einsum("akm,km->ma", jx, psi)
        info = np.zeros((pu, pu))
        blocks = np.einsum("akm,bkm->kab", jt * w, jt)  # (K, p, p)
        for k in range(k_all):
            info[k * p : (k + 1) * p, k * p : (k + 1) * p] = blocks[k]
        cvec = np.einsum("akm,km->ka", jt, psi).ravel()
        # minus Σ_i H_θi H_ii⁻¹ [H_iθ | ∇_i]
        sol = np.linalg.solve(h_ii, np.concatenate([h_it, g_i[:, :, None]], axis=2))  # (m, 3, pu + 1)
        info -= np.einsum("mai,maj->ij", h_it, sol[:, :, :pu])
        cvec -= np.einsum("mai,ma->i", h_it, sol[:, :, pu])
        if pr is not None:
            z = theta.ravel()
            info += pr.info
            cvec += pr.grad + pr.info @ (z - pr.z0)
        self._prior = Prior(False, theta.ravel().copy(), 0.5 * (info + info.T), cvec)
        n = self._n
        self._win_count -= prob.mask[:m].sum(axis=0)
        for arr in (self._gps, self._rng, self._odom, self._odom_mask, self._odom_sigma, self._x, self._t):
            arr[: n - m] = arr[m:n]
        self._odom_mask[0] = False
        self._odom_sigma[0] = np.nan
        self._n = n - m
        return True

    def _marginalize_chain(self, m: int) -> bool:
        """Fold the m oldest keyframes into a prior on [x_m, Θ] at once when Gauss–Markov GPS
        factors chain them (online_chain.chain_marginal_prior); False (nothing done) otherwise.
        The same prior as m calls of _marginalize_oldest at the same point."""
        prob = self._problem()
        if not prob.gps_linked or not 1 <= m < self._n:
            return False
        # the factors touching keyframes 0..m−1: all but keyframe m's ranges
        n1 = m + 1
        rng = prob.range_m[:n1].copy()
        rng[m] = np.nan
        sub = replace(prob, gps_enu_m=prob.gps_enu_m[:n1], range_m=rng, mask=~np.isnan(rng),
                      odom_enu_m=prob.odom_enu_m[:n1], odom_mask=prob.odom_mask[:n1], t_s=prob.t_s[:n1],
                      odom_sigma_m=None if prob.odom_sigma_m is None else prob.odom_sigma_m[:n1],
                      bias_gain=None if prob.bias_gain is None else prob.bias_gain[:n1])
        lin = linearize(sub, self._x[:n1], self._theta, self._active, self._prior)
        # linearize adds the bias priors and an identity block for inactive users: factors of the
        # window, not of these keyframes
        p, k_all = self._p, self._k
        blocks = lin.huu.reshape(k_all, p, k_all, p)
        if self._params.estimate_bias:
            sb = self._params.bias_prior_sigma_m if self._bias_sigma is None else self._bias_sigma
            inv_b2 = np.broadcast_to(1.0 / np.square(sb), (k_all,))
            act = np.flatnonzero(self._active)
            blocks[act, -1, act, -1] -= inv_b2[act]
            lin.gu.reshape(k_all, p)[act, -1] += self._theta[act, -1] * inv_b2[act]
        for k in np.flatnonzero(~self._active):
            blocks[k, :, k, :] -= np.eye(p)
        info, grad = chain_marginal_prior(lin, m)
        self._prior = Prior(True, np.concatenate([self._x[m], self._theta.ravel()]), info, grad)
        n = self._n
        self._win_count -= prob.mask[:m].sum(axis=0)
        for arr in (self._gps, self._rng, self._odom, self._odom_mask, self._odom_sigma, self._x, self._t):
            arr[: n - m] = arr[m:n]
        self._odom_mask[0] = False
        self._odom_sigma[0] = np.nan
        self._gps_first = False  # keyframe m's link to m − 1 now lives in the prior
        self._n = n - m
        return True

    def _marginalize_oldest(self) -> None:
        """Fold keyframe 0 of the window into the prior at the current estimate, then drop it."""
        prob = self._problem()
        noise = self._noise
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
            inv_m2 = 1.0 / float(self._odom_sigma[1]) ** 2
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
        for arr in (self._gps, self._rng, self._odom, self._odom_mask, self._odom_sigma, self._x, self._t):
            arr[: n - 1] = arr[1:n]
        self._odom_mask[0] = False
        self._odom_sigma[0] = np.nan
        if gps_link:
            self._gps_first = False  # its link to the dropped keyframe now lives in the prior
        self._n = n - 1
