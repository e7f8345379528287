"""The GPS factor: a fix x̂_n on keyframe n whose error drifts (first-order Gauss–Markov).

An autopilot's position output is a filter's estimate: its error β(t) = x̂(t) − x(t) is not new at
every fix but wanders slowly, with a correlation time τ of tens to hundreds of seconds:

    β_n = φ_n β_(n−1) + w_n,   φ_n = exp(−(t_n − t_(n−1))/τ),   w_n ~ N(0, σ_gps² (1 − φ_n²) I)

stationary with σ_gps per axis. Its negative log-likelihood over a chain of keyframes is a sum of
one factor per keyframe (β_n = x̂_n − x_n is a function of the keyframe, so no extra state):

    e_0 = (x_0 − x̂_0) / σ_gps                                      (first keyframe)
    e_n = ((x_n − x̂_n) − φ_n (x_(n−1) − x̂_(n−1))) / (σ_gps √q_n),  q_n = 1 − φ_n²   (n ≥ 1)
    ∂e_n/∂x_n = I / (σ_gps √q_n),   ∂e_n/∂x_(n−1) = −φ_n I / (σ_gps √q_n)

τ = 0 gives φ = 0: independent GPS priors, the white model. Every Jacobian is a scalar times I,
so the keyframe block of the normal matrix stays block-tridiagonal with scalar·I off-diagonal
blocks (estimator.schur): a solve stays linear in N. The users' covariance then carries the part
of the GPS error that flying longer does not average away (a common offset of the whole track).

:func:`gps_chain_terms` is the one vectorised source of this factor's error and normal-equation
blocks: the batch linearization, the online window, its marginalization and the CRLB call it;
:class:`GpsFactor` is the same factor one at a time, for the dense reference and the tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: floor of q_n = 1 − φ_n² (two fixes at the same time would otherwise have infinite weight)
Q_MIN = 1e-4


def gps_phi(t_s: np.ndarray, tau_s: float) -> np.ndarray:
    """(N,) φ_n = exp(−(t_n − t_(n−1))/τ) linking fix n to fix n−1; φ_0 = 0; all 0 when τ = 0.

    t_s: (N,) fix times [s]; time going backwards (a log out of order) counts as no time passed.
    """
    t = np.asarray(t_s, dtype=float)
    phi = np.zeros(t.shape[0])
    if tau_s > 0.0 and t.shape[0] > 1:
        # φ_n = exp(−Δt_n / τ)
        phi[1:] = np.exp(-np.maximum(np.diff(t), 0.0) / tau_s)
        np.minimum(phi, math.sqrt(1.0 - Q_MIN), out=phi)
    return phi


@dataclass(frozen=True)
class GpsChainTerms:
    """Normal-equation pieces of the GPS factors of N keyframes.

    cost: ½ Σ ||e_n||²; diag (N,): scalar added to each H_nn (times I); off (N−1,): scalar of the
    H_(n,n+1) block (times I); grad (N, 3): ∇ of the cost w.r.t. each x_n.
    """

    cost: float
    diag: np.ndarray
    off: np.ndarray
    grad: np.ndarray


def gps_chain_terms(
    x: np.ndarray, gps_enu_m: np.ndarray, phi: np.ndarray, sigma_gps_m: float, first: bool = True,
) -> GpsChainTerms:
    """Vectorised GPS factors of keyframes x (N, 3) with fixes gps_enu_m (N, 3), links φ (N,).

    first: keyframe 0 carries its own prior e_0 (False in an online window whose keyframe 0's
    factor linking it to an already marginalized keyframe lives in the marginalization prior).

        δ_n = β_n − φ_n β_(n−1) (β = x − x̂, φ_0 = 0),  W_n = 1/(σ² q_n) (W_0 = 0 unless first)
        cost = ½ Σ W_n ||δ_n||²
        ∇_n = W_n δ_n − φ_(n+1) W_(n+1) δ_(n+1)
        H_nn = (W_n + φ_(n+1)² W_(n+1)) I,   H_(n,n+1) = −φ_(n+1) W_(n+1) I
    """
    beta = x - gps_enu_m
    delta = beta.copy()
    delta[1:] -= phi[1:, None] * beta[:-1]
    q = 1.0 - phi * phi
    wgt = 1.0 / (sigma_gps_m * sigma_gps_m * q)
    if not first:
        wgt[0] = 0.0
    wd = delta * wgt[:, None]
    cost = 0.5 * float(np.vdot(wd, delta))
    grad = wd.copy()
    grad[:-1] -= phi[1:, None] * wd[1:]
    diag = wgt.copy()
    diag[:-1] += phi[1:] * phi[1:] * wgt[1:]
    off = -phi[1:] * wgt[1:]
    return GpsChainTerms(cost, diag, off, grad)


@dataclass(frozen=True)
class GpsFactor:
    """GPS fix on keyframe n, linked to the fix before it when φ > 0 (module docstring).

    e = ((x − x̂) − φ (x_prev − x̂_prev)) / (σ_gps √(1 − φ²)), (3,). Never robustified.
    φ = 0: the independent prior e = (x − x̂)/σ_gps (x_prev unused).
    """

    gps_enu_m: np.ndarray
    sigma_m: float
    phi: float = 0.0
    gps_prev_enu_m: np.ndarray | None = None

    def _scale(self) -> float:
        return 1.0 / (self.sigma_m * math.sqrt(1.0 - self.phi * self.phi))

    def error(self, x_enu_m: np.ndarray, x_prev_enu_m: np.ndarray | None = None) -> np.ndarray:
        # e = ((x − x̂) − φ (x_prev − x̂_prev)) / (σ √q)
        delta = np.asarray(x_enu_m, float) - self.gps_enu_m
        if self.phi != 0.0:
            delta = delta - self.phi * (np.asarray(x_prev_enu_m, float) - self.gps_prev_enu_m)
        return delta * self._scale()

    def jacobian(self) -> tuple[np.ndarray, np.ndarray]:
        """(∂e/∂x (3, 3), ∂e/∂x_prev (3, 3)) = (I, −φ I) / (σ √(1 − φ²))."""
        c = self._scale()
        return np.eye(3) * c, -self.phi * c * np.eye(3)


#: fewest consecutive fix pairs to estimate τ from
TAU_MIN_PAIRS = 20
#: median of χ²(1): median(Δβ²) = 0.4549 · var(Δβ) for Gaussian increments
_CHI2_1_MEDIAN = 0.454936423119572


def estimate_gps_tau_s(
    t_s: np.ndarray, pos_enu_m: np.ndarray, vel_enu_mps: np.ndarray, sigma_gps_m: float,
    series: np.ndarray | None = None,
) -> float | None:
    """Correlation time τ [s] of the GPS error from fixes and the autopilot's velocity.

    t_s: (T,) fix times [s]; pos_enu_m: (T, 3) fixes [m, ENU]; vel_enu_mps: (T, 3) velocity
    [m/s, ENU] (NaN rows: unknown); sigma_gps_m: the stationary σ of the error per axis.
    The velocity removes the motion from consecutive fixes and leaves the error's increment:

        Δβ_i = (x̂_i − x̂_(i−1)) − ½ (v_i + v_(i−1)) Δt_i,   E[Δβ_i²] = 2σ² (1 − e^(−Δt_i/τ)) per axis

    so with m = median(Δβ²) / (0.455 · 2σ²) over the horizontal axes (the median resists GPS
    glitches) and Δt the median step, τ = −Δt / ln(1 − m). Returns 0.0 (white) when m says
    τ < Δt, None with fewer than TAU_MIN_PAIRS usable pairs.

    series: (T,) int, which receiver each record is of (a fleet's vehicle; None: all one). A pair
    is two consecutive records of one series (each series in the order given), and the median
    pools every series' pairs: one τ for receivers of one kind, never a pair of two vehicles' fixes.
    """
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(pos_enu_m, dtype=float)
    v = np.asarray(vel_enu_mps, dtype=float)
    same = np.ones(max(t.shape[0] - 1, 0), dtype=bool)
    if series is not None:
        s = np.asarray(series)
        order = np.argsort(s, kind="stable")
        t, x, v, s = t[order], x[order], v[order], s[order]
        same = s[1:] == s[:-1]
    dt = np.diff(t)
    ok = np.isfinite(v).all(axis=1)
    use = ok[1:] & ok[:-1] & (dt > 0) & (dt < 5.0) & same
    if int(use.sum()) < TAU_MIN_PAIRS:
        return None
    # Δβ = Δx̂ − ½ (v_i + v_(i−1)) Δt, horizontal
    db = (x[1:, :2] - x[:-1, :2]) - 0.5 * (v[1:, :2] + v[:-1, :2]) * dt[:, None]
    db = db[use]
    m = float(np.median(db * db)) / (_CHI2_1_MEDIAN * 2.0 * sigma_gps_m**2)
    step = float(np.median(dt[use]))
    if m >= 1.0 - math.exp(-1.0):
        return 0.0
    # τ = −Δt / ln(1 − m)
    return -step / math.log1p(-max(m, 1e-12))


# -- the floor no flight removes ---------------------------------------------------------------------


def gps_mean_var_factor(tau_s: float, survey_s: float) -> float:
    """The share of σ_gps² a Gauss–Markov GPS error keeps when averaged over a survey of survey_s:

        Var[(1/T) ∫₀ᵀ β dt] / σ² = (2τ/T) · (1 − (τ/T)(1 − e^{−T/τ}))       (τ > 0, T > 0)

    1 when T ≪ τ (one offset for the whole track), 2τ/T when T ≫ τ, 0 for white errors (τ = 0:
    many independent fixes average out)."""
    if tau_s <= 0.0:
        return 0.0
    if survey_s <= 0.0:
        return 1.0
    x = survey_s / tau_s
    if x < 1e-6:  # 1 − x/3 + …: the series, where the closed form cancels
        return 1.0 - x / 3.0
    # (2/x) · (1 − (1 − e^{−x})/x), with expm1 for the small-x end
    return float(min(1.0, max(0.0, 2.0 / x * (1.0 + math.expm1(-x) / x))))


def gps_floor_bound_95_m(sigma_gps_m: float, tau_s: float, survey_s: float) -> float:
    """The 95 % horizontal bound [m] that the GPS error leaves common to every user however the
    survey flies: ranges place users relative to the track, and the part of the track's error that
    the survey's duration does not average away moves track and users together, which no range sees.

        r95_floor = sqrt(χ²₂(0.95) · σ_gps² · gps_mean_var_factor(τ, T))
    """
    from estimator.types import CHI2_2DOF_95

    return math.sqrt(CHI2_2DOF_95 * sigma_gps_m**2 * gps_mean_var_factor(tau_s, survey_s))


def gps_tau_for_floor_s(sigma_gps_m: float, survey_s: float, floor_m: float) -> float:
    """The longest correlation time τ [s] whose floor over survey_s is at most floor_m (bisection on
    the monotone gps_floor_bound_95_m); inf when even a constant offset stays below it."""
    if gps_floor_bound_95_m(sigma_gps_m, 1e12, survey_s) <= floor_m:
        return math.inf
    lo, hi = 0.0, 1e7
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if gps_floor_bound_95_m(sigma_gps_m, mid, survey_s) <= floor_m:
            lo = mid
        else:
            hi = mid
    return lo
