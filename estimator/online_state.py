"""The online estimator's state (estimator.online): everything it carries from one keyframe to the
next, in one object. The estimator's steps are functions of it: the window solve and its checks
(estimator.online), the filter steps between solves (estimator.online_filter) and the
marginalization of the window's oldest keyframes (estimator.online_marginal)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estimator.linearize import Prior
from estimator.noise import NoiseModel
from estimator.problem import Problem
from estimator.types import Estimate, SolverParams


@dataclass(slots=True, eq=False)
class OnlineState:
    """The state of an OnlineEstimator. K users, p = user_dim (+1 with a range bias) parameters
    per user, P = K·p; C = capacity keyframe slots, the first n of them the window (oldest first).
    Positions are local ENU [m], times [s]. Arrays are updated in place where the steps can.

    Fixed configuration (set at construction):
        k: K, the number of users.
        p: parameters per user, θ_k = [east, north (, up when user_dim = 3) (, range bias [m])].
        capacity: C = params.window + max(params.online_resolve_every, 1) keyframe slots: a full
            solve marginalizes down to `window` keyframes, the filter steps in between add up to
            online_resolve_every − 1 more.
        user_up_m: (K,) known user heights [m, ENU up] (2-D mode).
        noise: the NoiseModel; params: the SolverParams.
        min_start: ranges in the window a user needs to start (max(p + 1, ONLINE_MIN_RANGES)).
        inv_g2: 1/σ_gps² [1/m²].
        gps_linked: the GPS errors are Gauss–Markov (noise.gps_tau_used_s > 0): consecutive
            keyframes are linked by their GPS factors.

    The window's keyframes (slots [:n] valid; shifted down as the oldest are marginalized):
        gps_enu_m: (C, 3) GPS fixes [m].
        range_m: (C, K) measured ranges [m], NaN where a keyframe has no range to a user.
        odom_enu_m: (C, 3) odometry displacement from the previous keyframe [m] (0 where none).
        odom_mask: (C,) bool, the keyframe carries a motion factor to the previous one.
        odom_sigma_m: (C,) σ_m of each keyframe's motion factor [m], NaN where none.
        t_s: (C,) keyframe times [s] (Gauss–Markov GPS links).
        x: (C, 3) estimated UAV positions [m].
        n: keyframes in the window.
        win_count: (K,) int, ranges per user in the window.
        gps_first: window keyframe 0 carries its own GPS prior (nothing marginalized yet, or no
            GPS link of it lives in the prior).

    The users:
        theta: (K, p) parameters θ (position [m], bias [m]); rows of inactive users are unused.
        users_enu_m: (K, 3) users_from_theta(θ) [m], kept in step with θ.
        active: (K,) bool, users started (estimated).
        n_ranges: (K,) int, ranges per user seen in all (window and marginalized).

    The information summary:
        prior: the Gaussian prior of the marginalized keyframes (on Θ, or on [x_0, Θ] when
            has_x: Gauss–Markov GPS or motion links), None before the first marginalization.
        s: (P, P) users' information S at the last solution, None before the first solve.
        s_aug: (3 + P, 3 + P) information of [last window keyframe, Θ] (the Gauss–Markov GPS and
            motion filter steps, estimator.online_chain), or None.
        cost: the last full solve's cost (½ Σ ρ of the whitened residuals plus the prior).

    The model choices, re-estimated by each full solve:
        nlos_pi: (K,) NLoS probability π_k of the "nlos" loss.
        noise_scale: (K,) range noise scale s_k (1: as the NoiseModel says).
        bias_sigma_m, bias_mean_m: (K,) prior σ and mean of each user's range bias [m] chosen by
            the last full solve's bias selection (the held prior of params.bias_held where it
            held a bias); None: params.bias_prior_sigma_m and 0 for all.

    The schedule:
        seen: keyframes added in all.
        refused: a filter step was refused since the last full update whose solve converged
            (within its capped iterations): the users still move by more than a step may.
        marginalize_due: the last full solve left more than params.window keyframes; they are
            marginalized at the start of the next update.
        last_check: `seen` at the last re-initialization / mirror check.
        check_interval: keyframes between checks (backs off, online.ONLINE_CHECK_BACKOFF_MAX).
        check_state: (noise_scale, nlos_pi, bias selection) at the last check, None before it.
        flipped: the last check moved a user (restart or mirror flip).
        mirrors: (K,) MirrorTest | None of each user, from the last check.
        estimate: the last Estimate returned, None before the first keyframe.

    Caches (derived; kept so the per-keyframe steps do not rebuild them):
        arange_p: (1, p) np.arange(p); arange_k: (K,) np.arange(K); k_list: list(range(K)).
        bd_cache: m -> flat indices of the m diagonal p×p blocks of an (m·p, m·p) matrix.
        all_active: active.all().
        nlos_pi_list, noise_scale_list: nlos_pi and noise_scale as Python lists (float loops).
    """

    # fixed configuration
    k: int
    p: int
    capacity: int
    user_up_m: np.ndarray
    noise: NoiseModel
    params: SolverParams
    min_start: int
    inv_g2: float
    gps_linked: bool
    # the window's keyframes
    gps_enu_m: np.ndarray
    range_m: np.ndarray
    odom_enu_m: np.ndarray
    odom_mask: np.ndarray
    odom_sigma_m: np.ndarray
    t_s: np.ndarray
    x: np.ndarray
    n: int
    win_count: np.ndarray
    gps_first: bool
    # the users
    theta: np.ndarray
    users_enu_m: np.ndarray
    active: np.ndarray
    n_ranges: np.ndarray
    # the information summary
    prior: Prior | None
    s: np.ndarray | None
    s_aug: np.ndarray | None
    cost: float
    # the model choices
    nlos_pi: np.ndarray
    noise_scale: np.ndarray
    bias_sigma_m: np.ndarray | None
    bias_mean_m: np.ndarray | None
    # the schedule
    seen: int
    refused: bool
    marginalize_due: bool
    last_check: int
    check_interval: int
    check_state: tuple | None
    flipped: bool
    mirrors: list
    estimate: Estimate | None
    # caches
    arange_p: np.ndarray
    arange_k: np.ndarray
    k_list: list
    bd_cache: dict[int, np.ndarray] = field(default_factory=dict)
    all_active: bool = False
    nlos_pi_list: list = field(default_factory=list)
    noise_scale_list: list = field(default_factory=list)

    @classmethod
    def initial(cls, n_users: int, user_up_m: np.ndarray, noise: NoiseModel, params: SolverParams,
                min_start: int) -> OnlineState:
        """The state before the first keyframe (arguments checked by the caller)."""
        k = int(n_users)
        p = params.user_dim + (1 if params.estimate_bias else 0)
        cap = int(params.window) + max(int(params.online_resolve_every), 1)
        nlos_pi = np.full(k, float(params.nlos_prob))
        noise_scale = np.ones(k)
        return cls(
            k=k, p=p, capacity=cap, user_up_m=user_up_m, noise=noise, params=params,
            min_start=max(p + 1, int(min_start)), inv_g2=1.0 / noise.sigma_gps_m**2,
            gps_linked=noise.gps_tau_used_s > 0.0,
            gps_enu_m=np.zeros((cap, 3)), range_m=np.full((cap, k), np.nan), odom_enu_m=np.zeros((cap, 3)),
            odom_mask=np.zeros(cap, dtype=bool), odom_sigma_m=np.full(cap, np.nan), t_s=np.zeros(cap),
            x=np.zeros((cap, 3)), n=0, win_count=np.zeros(k, dtype=int), gps_first=True,
            theta=np.zeros((k, p)), users_enu_m=np.zeros((k, 3)), active=np.zeros(k, dtype=bool),
            n_ranges=np.zeros(k, dtype=int),
            prior=None, s=None, s_aug=None, cost=float("nan"),
            nlos_pi=nlos_pi, noise_scale=noise_scale, bias_sigma_m=None, bias_mean_m=None,
            seen=0, refused=False, marginalize_due=False, last_check=0,
            check_interval=max(int(params.online_check_every), 1), check_state=None, flipped=False,
            mirrors=[None] * k, estimate=None,
            arange_p=np.arange(p)[None, :], arange_k=np.arange(k), k_list=list(range(k)),
            all_active=False, nlos_pi_list=nlos_pi.tolist(), noise_scale_list=noise_scale.tolist(),
        )


def window_problem(st: OnlineState) -> Problem:
    """The window's keyframes as a Problem, with the current model choices (views of the state's
    arrays, not copies)."""
    n = st.n
    rng = st.range_m[:n]
    return Problem(
        st.gps_enu_m[:n], rng, ~np.isnan(rng), st.odom_enu_m[:n], st.odom_mask[:n], st.user_up_m,
        st.noise, st.params, st.nlos_pi, t_s=st.t_s[:n], gps_first=st.gps_first,
        noise_scale_k=st.noise_scale if st.params.estimate_noise_scale else None,
        bias_sigma_k=st.bias_sigma_m, bias_mean_k=st.bias_mean_m, odom_sigma_m=st.odom_sigma_m[:n],
    )
