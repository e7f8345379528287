"""Data passed between the estimator, the planner, replay and the controller.

These are the contract between the parts (docs/design.md §1, docs/architecture.md): plain frozen
dataclasses on numpy arrays. Shapes use N keyframes, K users, M range measurements, d = 2 (east,
north) or 3 user coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:
    from estimator.clock import SawtoothFit

#: χ²(2 dof) quantile for a 95 % ellipse: P(χ²₂ ≤ 5.991) = 0.95.
CHI2_2DOF_95 = 5.991464547107979
#: χ²(2 dof) quantile for a 99.9 % ellipse, −2 ln(0.001): a user beyond it is 1 in 1000 when honest.
CHI2_2DOF_999 = 13.815510557964274

LossName = Literal["none", "huber", "cauchy", "tukey", "nlos"]


@dataclass(frozen=True)
class SolverParams:
    """Settings of the SLAM solver (GTSAM-style params object).

    loss: robust loss on range factors only ("none", "huber", "cauchy", "tukey", "nlos"); never
        on GPS priors. Default "nlos" (LoS/NLoS mixture likelihood, estimator.robust): NLoS excess
        is one-sided, which biases a symmetric loss (Huber: 1.4 m mean error under 20 % NLoS
        with Exp(20 m) excess where "nlos" gets 0.43 m), and with nlos_adapt it is as efficient
        as least squares at LoS. It was "huber" before. "tukey" (redescending, use
        loss_scale ≈ 3) rejects NLoS outliers outright; the solver starts it from a Huber solution.
    loss_scale: loss threshold in whitened units (residual / σ(d)); unused by "nlos".
    nlos_prob, nlos_mean_m: the "nlos" loss's prior NLoS probability π and mean NLoS excess
        μ [m] (estimator.robust): a range is LoS with probability 1 − π, or carries a positive
        excess ~ Exp(mean μ). nlos_prob is where π starts.
    nlos_adapt: re-estimate π per user by EM, π_k = mean over its ranges of P(NLoS | e), between
        solves (estimator.solve.solve_robust); at LoS π_k falls to its floor and the loss becomes
        nearly quadratic (a fixed π biases the solution slightly towards short ranges).
    estimate_bias: add a range bias b_k per user, with a zero-mean prior of bias_prior_sigma_m.
        Default True (it was False): a commercial UE's clock sawtooth has a positive mean, and a
        UE without one pays little for the extra unknown under the weak prior.
    bias_select: with estimate_bias, hold the bias of a user whose estimate is insignificant
        (|b̂ − μ_h| < 4 sd, estimator.solve.solve_robust) under the prior of `bias_held`, so a UE
        without a clock offset loses nothing.
    bias_held: what a held bias is. "zero": 0, known (an ideal UE's clock, or an offset
        calibrated out). "sawtooth": a commercial UE's clock sawtooth too small to track, whose
        mean offset is unknown in [0, A_det/2] (estimator.clock.undetected_sawtooth_bias: mean
        1.09 m, σ 0.63 m at σ = 3 m); held at 0 as if known, such users ended 3–5 m off along
        their bearing with NEES 10–25 in the planner benchmark's hardware world.
    track_clock: the batch solver fits a UE clock sawtooth (drift and resets, estimator.clock)
        to each user whose residuals are noisier than σ(d) and removes it from its ranges.
    estimate_noise_scale: re-estimate a per-user scale s_k ≥ 1 of the range noise from the
        residuals, σ_k(d) = s_k σ(d) (estimator.solve.noise_scale_update), so that a UE noisier
        than the assumed σ(d) gets an honest covariance. Reported as Estimate.state.noise_scale.
    jackknife_blocks: G > 1: a batch solve reports each user's covariance as the larger, in every
        direction, of the model's S⁻¹ and the delete-a-block jackknife over G contiguous time
        blocks of its ranges (estimator.jackknife: what the model's independence misses, such as a
        block of NLoS excess from one side of the user); 0: the model's alone.
    nlos_shift: a batch solve adds to the covariance of each user whose ranges show NLoS (π_k
        above its floor) the position shift an NLoS excess from one side of it can make unseen,
        |δ| ≤ 2 π_k μ / c (estimator.nlos_shift: the excess's first harmonic in bearing is a
        position shift, which no residual shows).
    user_dim: 2 (east, north; up fixed at the known ground height) or 3.
    motion_sigma_m: per-axis σ of the relative-motion factor of a keyframe that carries a
        displacement (Keyframe.odom_enu_m) without its own σ (None: such keyframes get no motion
        factor). A keyframe with its own Keyframe.odom_sigma_m (replay and the flight integrate
        the autopilot's velocity, estimator.motion) always gets its factor with that σ.
    delta_m: keyframe spacing Δ [m] (paper: 2 m).
    window: keyframes kept in the online estimator before the oldest are marginalized (a full
        solve marginalizes down to `window`; the filter steps between full solves may add up to
        online_resolve_every − 1 more).
    ambiguity_chi2: a user is flagged ambiguous when its mirror solution costs less than this
        much more, 2·(L(mirror) − L(estimate)) < ambiguity_chi2 (estimator.init).
    coverage_m: the cell's reach, the slant range [m] beyond which the gNB hears no UE (inf:
        unknown or unlimited). A finite reach lets silence refute a mirror (estimator.silence):
        a user not ranged at enough keyframes that would have heard it at its mirror position is
        not there, and is not ambiguous. It must not overstate the reach by more than
        1/SILENT_REACH_SHARE − 1 (25 %). inf: no refutation, the mirror test alone (as before).
    online_check_every: the online estimator re-runs the mirror test every this many keyframes.
    step_tol_m, step_tol_uav_m: the batch solver stops when no user parameter moves by
        step_tol_m and no keyframe coordinate by max(step_tol_m, step_tol_uav_m). The keyframes
        (GPS σ ~ 1 m) need no micrometres: under a robust loss a keyframe with a range near the
        loss's knee converges linearly (factor ~0.2 per iteration) long after the users have
        (N = 10 000, K = 20: 7 iterations instead of 11). Before, both used step_tol_m.
        step_tol_m is 10 µm (it was 1 µm: one Gauss–Newton iteration more, ~20 % of a
        batch solve at N = 200, K = 5, for a change 10⁵ times smaller than a user's σ).
    step_tol_sigma: the users have also converged when the step still to go is below this many
        of their standard deviations, ||Δθ||_S = √(Δθᵀ S Δθ) < step_tol_sigma (S the users'
        information; no coordinate, nor any linear function of them, then moves by more than
        that many of its σ). 0 disables it (step_tol_m alone). Default 0.001: on the benchmark's
        N = 200, K = 5 problems (σ ≈ 0.3 m) a solve ends 0.03–0.13 mm from the tightly converged
        optimum; GTSAM's Levenberg–Marquardt at relative error 1e-8 stops 0.05–0.2 mm from it
        (benchmarks/estimator.py prints both).
    online_step_tol_m: step size at which an online update stops iterating (the batch solver
        uses step_tol_m). Iterations shrink the step about 10× each, so the error left is about
        a tenth of this; set it to step_tol_m to make online and batch agree to that level.
    online_resolve_every: the online estimator re-solves its window (and marginalizes down to
        `window`, starts users, re-checks mirrors) every this many keyframes; in between, a
        keyframe is folded into the users by one information-filter step (O(K²), no iteration).
        1: re-solve at every keyframe (then, with no marginalization, online equals batch).
        Default 5 (before: every keyframe re-solved, 1.4 ms per update at K = 5).
    online_max_step_m: a filter step that moves any user parameter by more than this re-solves
        the window instead.
    """

    loss: LossName = "nlos"
    loss_scale: float = 1.5
    nlos_prob: float = 0.1
    nlos_mean_m: float = 20.0
    nlos_adapt: bool = True
    estimate_bias: bool = True
    bias_prior_sigma_m: float = 10.0
    estimate_noise_scale: bool = True
    bias_select: bool = True
    bias_held: Literal["zero", "sawtooth"] = "zero"
    jackknife_blocks: int = 0
    nlos_shift: bool = False
    track_clock: bool = True
    user_dim: int = 2
    motion_sigma_m: float | None = None
    delta_m: float = 2.0
    max_iterations: int = 50
    step_tol_m: float = 1e-5
    step_tol_uav_m: float = 1e-3
    step_tol_sigma: float = 1e-3
    window: int = 100
    ambiguity_chi2: float = 9.0
    coverage_m: float = math.inf
    online_check_every: int = 10
    online_step_tol_m: float = 0.05
    online_resolve_every: int = 5
    online_max_step_m: float = 1.0


@dataclass(frozen=True)
class Keyframe:
    """One keyframe: the UAV's GPS position and the ranges measured there.

    gps_enu_m: (3,) GPS fix interpolated to the measurement time [m, ENU].
    user_idx: (m,) int indices into the user list; range_m: (m,) measured ranges [m].
    odom_enu_m: (3,) optional displacement from the previous keyframe measured by the autopilot
        (its velocity integrated, estimator.motion) [m, ENU] (None: no relative-motion factor).
    t_s: seconds since mission start.
    odom_sigma_m: per-axis σ of odom_enu_m [m] (None: SolverParams.motion_sigma_m).
    vehicle: index of the vehicle that took it, in a fleet (0..V−1; docs/fleet.md). Each vehicle's
        keyframes form their own chain: the drifting GPS error and the displacement link a keyframe
        to the previous keyframe of the same vehicle, never to another vehicle's.
    """

    gps_enu_m: np.ndarray
    user_idx: np.ndarray
    range_m: np.ndarray
    odom_enu_m: np.ndarray | None = None
    t_s: float = 0.0
    odom_sigma_m: float | None = None
    vehicle: int = 0


#: Estimate.source: a batch solution over every keyframe seen, or the online estimator's
SOURCE_BATCH = "batch"
SOURCE_ONLINE = "online"


def nlos_shift_var_m2(shift_m):
    """½ |δ|² [m²]: the variance per horizontal axis of a shift of length |δ| = `shift_m` [m]
    (scalar or any shape) in a direction uniform on the circle, E[δδᵀ] = ½ |δ|² I₂: what the
    covariance holds of a one-sided NLoS excess's shift (estimator.nlos_shift)."""
    return 0.5 * np.square(shift_m)


def error_bound_95_m(cov_en_m2: np.ndarray) -> np.ndarray:
    """(K,) r95 = sqrt(χ²₂(0.95) · λ_max(Σ_k)) [m] of (K, 2, 2) east-north covariances, inf where
    Σ_k is not finite: the bound every tool prints and the stop rule judges."""
    cov = np.asarray(cov_en_m2, dtype=float).reshape(-1, 2, 2)
    ok = np.all(np.isfinite(cov), axis=(1, 2))
    cov = np.where(ok[:, None, None], 0.5 * (cov + np.swapaxes(cov, 1, 2)), np.eye(2))
    lam = np.linalg.eigvalsh(cov)[:, -1]
    return np.where(ok, np.sqrt(CHI2_2DOF_95 * np.maximum(lam, 0.0)), np.inf)


@dataclass(frozen=True)
class ModelState:
    """The model choices and the joint uncertainty a solve ended with: a warm-started batch refresh
    keeps the choices (estimator.batch), the planner predicts with the uncertainty and the noise
    scales (planner.information), the mission's report shows them (mission.result).

    active: (K,) users estimated (enough ranges).
    cov_theta_joint: (A·p, A·p) joint covariance of the A active users' parameters θ_k (position,
        then the bias when estimated), users in index order, p rows each; None when S is singular.
    noise_scale: (K,) factor s_k by which user k's ranges are noisier than σ(d) (1: as assumed).
    nlos_prob_k: (K,) NLoS probability π_k the "nlos" loss ended with; None for other losses.
    bias_on: (K,) True where the range bias is estimated (False: selected off, held); None
        when biases are not estimated.
    bias_held_m: (K,) the mean of the prior a held bias is held under (0 with
        SolverParams.bias_held "zero"); None when biases are not estimated.
    clock: (K,) the tracked UE clock sawtooth of each user (None: none); None when the solve does
        not track clocks (the online estimator).
    clock_triggered: (K,) users whose residuals called for a clock test; None when not tested.
    nlos_shift_m: (K,) |δ_k| [m], the shift a one-sided NLoS excess can make unseen, added to the
        user's covariance (estimator.nlos_shift; 0: no NLoS seen); None when not asked for
        (SolverParams.nlos_shift) or not a batch answer.
    nlos_bearing_logit: (K, 4) α of each user's NLoS probability by the UAV's bearing β and
        elevation ε seen from it, p_k(β, ε) = σ(α₀ + α₁ cos β + α₂ sin β + α₃ sin ε)
        (estimator.nlos_shift.nlos_bearing_logit; 0 where nlos_shift_m is 0): where the planner
        can see the user in line of sight; None with nlos_shift_m.
    warm_started: a batch solve started from an earlier one's choices (estimator.batch._warm_solve).
    filter_step: the online estimator's information-filter step between its solves.
    """

    active: np.ndarray
    cov_theta_joint: np.ndarray | None
    noise_scale: np.ndarray
    nlos_prob_k: np.ndarray | None = None
    bias_on: np.ndarray | None = None
    bias_held_m: np.ndarray | None = None
    clock: tuple[SawtoothFit | None, ...] | None = None
    clock_triggered: np.ndarray | None = None
    nlos_shift_m: np.ndarray | None = None
    nlos_bearing_logit: np.ndarray | None = None
    warm_started: bool = False
    filter_step: bool = False


@dataclass(frozen=True)
class Estimate:
    """What the estimator knows about the users (and the UAV track it corrected).

    users_enu_m: (K, 3) user positions [m, ENU]; in 2-D mode `up` is the known ground height.
        Rows of users not yet initialised (no ranges) are NaN.
    cov_users_m2: (K, d, d) marginal covariance of each user [m²] (exact S⁻¹ blocks).
    info_users: (K·d, K·d) information matrix S of all users jointly (Schur complement over
        keyframes plus any marginalization prior) [1/m²].
    bias_m: (K,) estimated range bias per user [m], or None when biases are not estimated.
    uav_enu_m: (N, 3) corrected UAV keyframe positions still in the estimator [m, ENU].
    ambiguous: (K,) True where a mirror solution explains the ranges about as well and silence
        does not refute it (SolverParams.coverage_m, estimator.silence).
    mirror_enu_m: (K, 3) the reflected solution where ambiguous, NaN elsewhere.
    n_ranges: (K,) number of range measurements used per user.
    state: the solve's model choices and joint covariance (None: not from a solve, e.g. made by hand).
    source: SOURCE_BATCH or SOURCE_ONLINE once estimator.refresh publishes it ("" before);
        keyframes_used: the number of keyframes it is the answer for (0: not said).
    """

    users_enu_m: np.ndarray
    cov_users_m2: np.ndarray
    info_users: np.ndarray
    bias_m: np.ndarray | None
    uav_enu_m: np.ndarray
    ambiguous: np.ndarray
    mirror_enu_m: np.ndarray
    n_ranges: np.ndarray
    cost: float = float("nan")
    iterations: int = 0
    converged: bool = False
    state: ModelState | None = None
    source: str = ""
    keyframes_used: int = 0

    @property
    def n_users(self) -> int:
        return int(self.users_enu_m.shape[0])

    def cov_en_m2(self, k: int) -> np.ndarray:
        """(2, 2) east-north covariance of user k [m²]."""
        return np.asarray(self.cov_users_m2[k][:2, :2])

    def error_bound_95_m(self) -> np.ndarray:
        """(K,) semi-major axis of each user's 95 % east-north error ellipse [m]:
        r95 = sqrt(χ²₂(0.95) · λ_max(Σ_en)); inf for users without a covariance."""
        return error_bound_95_m(self.cov_users_m2[:, :2, :2])
