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
Except where the "nlos" loss found NLoS (some π_k above its floor; solve.observed_s): there the
EM weight γ overstates the information of ranges the mixture cannot classify, and S is the
observed information instead — ψ'(e) per range (robust.nlos_curvature, negative for ambiguous
ranges) with each free π_k marginalized, since it is estimated too.

Online (fixed-lag smoothing): keyframes are kept in a window; when it holds more than
`params.window`, the oldest keyframe is marginalized at the current estimate into a Gaussian prior
on the users (and biases, and the next keyframe when a motion factor links them):

    L_prior(z) ≈ cᵀ(z − z₀) + ½ (z − z₀)ᵀ Λ (z − z₀),  Λ = H_rr − H_r0 H_00⁻¹ H_0r,
                                                      c = ∇_r − H_r0 H_00⁻¹ ∇_0

exact at the linearization point z₀; each update then costs O(window · K²), independent of N.

Between window solves (every params.online_resolve_every keyframes) a new keyframe is folded in by
one information-filter step: linearized at its GPS fix and the current users, eliminated at once
into the users' information S (OnlineEstimator._filter_step), O(K²) plus the (K·p)³ inverse for
the covariance. The window is re-solved and marginalized at the next full update (unlinked
keyframes in one block, OnlineEstimator._marginalize_block). The re-initialization, mirror and
bias-selection checks back off while they find nothing (estimator.online.ONLINE_CHECK_BACKOFF_MAX).
"""

from __future__ import annotations

from estimator.batch import (  # noqa: F401
    CLOCK_MIN_RANGES,
    CLOCK_ROUNDS,
    CLOCK_TRIGGER_SCALE,
    _grid_init,
    _mirror_all,
    _resolve_mirrors,
    _track_clocks,
    solve_batch,
)
from estimator.linearize import (  # noqa: F401
    _SYM3_FLAT,
    _SYM3_I,
    _SYM3_J,
    _SYM3_LOWER,
    _SYM3_OF,
    _SYM3_UPPER,
    Linearization,
    Prior,
    _nlos_args,
    _range_terms,
    _residuals,
    linearize,
)
from estimator.lm import (  # noqa: F401
    _LAM_MAX,
    _LAM_START,
    _Result,
    levenberg_marquardt,
)
from estimator.marginals import (  # noqa: F401
    _covariances,
    _estimate,
)
from estimator.online import (  # noqa: F401
    ONLINE_MIN_EXTENT_M,
    ONLINE_MIN_RANGES,
    OnlineEstimator,
)
from estimator.online_filter import (  # noqa: F401
    _SQRT_HALF,
    _SQRT_HALF_PI,
    _inv3_sym,
)
from estimator.solve import (  # noqa: F401
    BIAS_OFF_SIGMA_M,
    BIAS_SELECT_MAX_SD_M,
    BIAS_SELECT_Z,
    HUBER_WARM_SCALE,
    NLOS_EM_ROUNDS,
    NLOS_EM_TOL,
    NLOS_PROB_MAX,
    NLOS_PROB_MIN,
    NLOS_ROUND_STEP_M,
    NOISE_SCALE_MAX,
    NOISE_SCALE_MIN_DOF,
    NOISE_SCALE_RESOLVE,
    NOISE_SCALE_ROUNDS,
    _solve_scaled,
    nlos_prob_update,
    noise_scale_update,
    solve_loss,
    solve_robust,
)
