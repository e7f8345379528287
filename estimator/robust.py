"""Robust losses for range factors (docs/design.md §5), applied by iteratively reweighted least squares.

A loss ρ acts on a whitened residual e = r / σ(d). The solver minimises Σ ρ(e) and, at each
Levenberg–Marquardt iteration, replaces it by the weighted quadratic ½ w e² with the IRLS weight

    w(e) = ρ'(e) / e

so that the gradient of the weighted problem equals the gradient of the robust cost (GTSAM's
`noiseModel.Robust` does the same). Losses, with threshold c in whitened units:

    none:    ρ(e) = ½ e²                                          w = 1
    huber:   ρ(e) = ½ e²            (|e| ≤ c),  c|e| − ½c² (else)  w = min(1, c/|e|)
    cauchy:  ρ(e) = ½ c² log(1 + (e/c)²)                          w = 1 / (1 + (e/c)²)
    tukey:   ρ(e) = c²/6 (1 − (1 − (e/c)²)³) (|e| ≤ c), c²/6 (else)  w = (1 − (e/c)²)² or 0

nlos (LoS/NLoS mixture; c unused): a range is LoS with probability 1 − π, e ~ N(0, 1), or NLoS
with probability π, e = LoS noise + an excess ~ Exp(mean m) (m = μ_nlos/σ(d), whitened), always
positive. The NLoS density is the convolution

    f(e) = (1/m) exp(1/(2m²) − e/m) Φ(e − 1/m) = φ(e) M(t)/m,   t = e − 1/m,  M(t) = Φ(t)/φ(t)

so the mixture density is p(e) = φ(e) [(1 − π) + (π/m) M(t)] and its negative log, with ρ(0) = 0:

    ρ(e) = ½e² − log((1 − π) + (π/m) M(t)) + log((1 − π) + (π/m) M(−1/m))
    ψ(e) = ρ'(e) = e − (1 − γ)(t + 1/M(t))                       (M' = 1 + t M)
    γ(e) = (1 − π) / ((1 − π) + (π/m) M(t))                       posterior P(LoS | e)

It is quadratic for e < 0 (no NLoS explains a short range), grows only like e/m for large
positive e, and is not symmetric, so one-sided NLoS excess does not bias it the way a symmetric
loss is biased. Its IRLS weight is the EM weight w = γ (the Hessian of the EM surrogate
Σ γ ½e² + (1 − γ)(−log f)), while the gradient uses the exact ψ (ψ ≠ w e: the NLoS part keeps
a slope 1/m), so Levenberg–Marquardt minimises the mixture likelihood itself.

For every other loss ψ = w e. GPS priors, motion factors and bias priors are never robustified.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erfc, erfcx

from uavloc.errors import EstimatorError

LOSSES = ("none", "huber", "cauchy", "tukey", "nlos")
#: default NLoS probability π and whitened NLoS mean m of the "nlos" loss when none are given
NLOS_PROB = 0.1
NLOS_MEAN_WHITENED = 20.0 / 3.0
#: M(t) = Φ(t)/φ(t) is evaluated up to this t (finite there; Φ(t) = 1 in double precision)
_MILLS_T_MAX = 37.0
#: ... and by erfc · exp up to this x = −t/√2 (below: erfcx)
_MILLS_X_FAST = 5.0
_SQRT_HALF_PI = math.sqrt(0.5 * math.pi)
_SQRT_HALF = math.sqrt(0.5)
#: losses whose influence goes back to zero: need a start from a convex loss
REDESCENDING = ("tukey",)


def nlos_args(params, sigma_m: np.ndarray | float) -> tuple:
    """(π, m) of the "nlos" loss for ranges of standard deviation sigma_m [m] (m = μ/σ)."""
    return (params.nlos_prob, params.nlos_mean_m / sigma_m)


def check_loss(loss: str, scale: float) -> None:
    """Raise EstimatorError for an unknown loss name or a non-positive threshold."""
    if loss not in LOSSES:
        raise EstimatorError(f"unknown robust loss {loss!r}; expected one of {LOSSES}")
    if not (np.isfinite(scale) and scale > 0):
        raise EstimatorError(f"loss_scale must be a positive finite number, got {scale!r}")


def mills_ratio(t: np.ndarray) -> np.ndarray:
    """M(t) = Φ(t)/φ(t) = √(π/2) erfcx(x), x = −t/√2, for t ≤ _MILLS_T_MAX (finite there), any shape.

    erfcx(x) = erfc(x) exp(x²) is evaluated so where x ≤ _MILLS_X_FAST (t ≥ −7.07, every range
    but a gross short outlier): erfc and exp cost half of erfcx, to 2e-15 relative (the error of
    exp(x²) grows like x² ε, 7e-14 at t = 37); erfcx itself for the rest, where erfc underflows.
    """
    x = np.minimum(t, _MILLS_T_MAX) * -_SQRT_HALF
    xs = np.minimum(x, _MILLS_X_FAST)
    m = erfc(xs) * np.exp(xs * xs)
    far = x > _MILLS_X_FAST
    if far.any():
        if np.ndim(m):
            m[far] = erfcx(x[far])
        else:
            m = erfcx(x)
    return _SQRT_HALF_PI * m


def _nlos_all(
    e: np.ndarray, prob: np.ndarray | float, mean_w: np.ndarray | float,
    need_rho: bool, need_psi: bool, need_curv: bool,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """(ρ, ψ, γ, ψ') of the "nlos" loss at whitened residuals e, each None unless asked for,
    sharing M(t) (the costly part) — the one evaluation behind nlos_terms, nlos_terms_curvature
    and nlos_curvature.

    With q = (π/m) M(t), g = (1 − π) + q and h = t + 1/M(t):
        γ = (1 − π)/g,   ψ = e − (1 − γ) h   (1 − γ = q/g),
        ρ = ½e² − log g + log g(0),
        ψ' = γ + (1 − γ)(1/M² + t/M) − γ(1 − γ)h²   (nlos_curvature).
    M is evaluated at min(t, T) (T = 37, where Φ(T) = 1 in double precision and M(T) ≈ 1e297 is
    still finite); beyond T, γ ≈ 0 and 1/M ≈ 0 already, and log g(t) = log g(T) + (t² − T²)/2
    (log M grows like t²/2 there).
    """
    e = np.asarray(e, dtype=float)
    inv_m = 1.0 / mean_w
    t = e - inv_m
    mills = mills_ratio(t)
    one_m_pi = 1.0 - prob
    q = (prob * inv_m) * mills
    g = one_m_pi + q
    rho = psi = gamma = curv = None
    if need_psi or need_curv:
        gamma = one_m_pi / g
        inv_mills = 1.0 / mills
        h = t + inv_mills
        one_m_g = q / g
        if need_psi:
            psi = e - one_m_g * h
        if need_curv:
            curv = gamma + one_m_g * (inv_mills * (inv_mills + t) - gamma * h * h)
    if need_rho:
        log_g = np.log(g)
        over = t > _MILLS_T_MAX
        if over.any():
            log_g = log_g + np.where(over, 0.5 * (t * t - _MILLS_T_MAX**2), 0.0)
        g0 = one_m_pi + (prob * inv_m) * mills_ratio(-inv_m)
        rho = 0.5 * e * e - log_g + np.log(g0)
    return rho, psi, gamma, curv


def nlos_terms(
    e: np.ndarray, prob: np.ndarray | float = NLOS_PROB, mean_w: np.ndarray | float = NLOS_MEAN_WHITENED,
    need_rho: bool = True, need_psi: bool = True,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """ρ, ψ = ρ', γ of the LoS/NLoS mixture loss (module docstring) at whitened residuals e.

    prob: π in (0, 1) and mean_w: whitened NLoS mean m > 0, each scalar or broadcastable to e.
    Returns (ρ or None when need_rho is False, ψ and γ or None when need_psi is False), each the
    shape of e (formulas: _nlos_all).
    """
    rho, psi, gamma, _ = _nlos_all(e, prob, mean_w, need_rho, need_psi, False)
    return rho, psi, gamma


def nlos_terms_curvature(
    e: np.ndarray, prob: np.ndarray | float = NLOS_PROB, mean_w: np.ndarray | float = NLOS_MEAN_WHITENED,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(ρ, ψ, γ, ψ') of the "nlos" loss at e in one pass (nlos_terms and nlos_curvature sharing
    M(t))."""
    return _nlos_all(e, prob, mean_w, True, True, True)


def nlos_curvature(
    e: np.ndarray, prob: np.ndarray | float = NLOS_PROB, mean_w: np.ndarray | float = NLOS_MEAN_WHITENED,
) -> np.ndarray:
    """ψ'(e) = ρ''(e) of the "nlos" loss at whitened residuals e (shape of e): the observed
    information of one range, where the IRLS weight γ is the complete-data (EM) information.

    With h = t + 1/M(t) (the LoS score e minus the NLoS score e − h) and the NLoS term's own
    curvature c_N = 1/M² + t/M (−log f = ½e² − log M(t) + const, (log M)' = 1/M + t):

        ψ' = γ + (1 − γ) c_N − γ (1 − γ) h²

    the last term being the missing information of the unknown LoS/NLoS label (Louis 1982). It is
    negative for ranges the mixture cannot tell apart (e ≈ 2–4), which the EM weight counts as half
    a LoS range: a covariance from γ is too optimistic under NLoS.
    """
    return _nlos_all(e, prob, mean_w, False, False, True)[3]


def loss_rho(e: np.ndarray, loss: str, c: float, nlos: tuple | None = None) -> np.ndarray:
    """ρ(e) of whitened residuals `e` (any shape), same shape.

    nlos: (π, m) of the "nlos" loss (m scalar or broadcastable to e); defaults NLOS_PROB,
    NLOS_MEAN_WHITENED. Ignored by the other losses.
    """
    e = np.asarray(e, dtype=float)
    if loss == "nlos":
        return nlos_terms(e, *(nlos or ()), need_psi=False)[0]
    if loss == "none":
        # ρ = ½ e²
        return 0.5 * e * e
    if loss == "huber":
        a = np.abs(e)
        # ρ = ½e² inside, c|e| − ½c² outside
        return np.where(a <= c, 0.5 * e * e, c * a - 0.5 * c * c)
    if loss == "cauchy":
        # ρ = ½ c² log(1 + (e/c)²)
        return 0.5 * c * c * np.log1p((e / c) ** 2)
    if loss == "tukey":
        # ρ = c²/6 (1 − (1 − (e/c)²)³), flat beyond c
        t = np.minimum((e / c) ** 2, 1.0)
        return c * c / 6.0 * (1.0 - (1.0 - t) ** 3)
    raise EstimatorError(f"unknown robust loss {loss!r}; expected one of {LOSSES}")


def loss_weight(e: np.ndarray, loss: str, c: float, nlos: tuple | None = None) -> np.ndarray:
    """IRLS weight w(e) of whitened residuals `e` (any shape), in [0, 1]: ρ'(e)/e, or for "nlos"
    the posterior LoS probability γ(e) (module docstring)."""
    e = np.asarray(e, dtype=float)
    if loss == "nlos":
        return nlos_terms(e, *(nlos or ()), need_rho=False)[2]
    if loss == "none":
        return np.ones_like(e)
    if loss == "huber":
        a = np.abs(e)
        # w = min(1, c/|e|)
        return np.minimum(1.0, c / np.maximum(a, 1e-300))
    if loss == "cauchy":
        # w = 1 / (1 + (e/c)²)
        return 1.0 / (1.0 + (e / c) ** 2)
    if loss == "tukey":
        # w = (1 − (e/c)²)² inside, 0 outside
        t = np.maximum(1.0 - (e / c) ** 2, 0.0)
        return t * t
    raise EstimatorError(f"unknown robust loss {loss!r}; expected one of {LOSSES}")


def loss_psi_weight(
    e: np.ndarray, loss: str, c: float, nlos: tuple | None = None, need_rho: bool = True,
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """(ρ(e) or None, ψ(e) = ρ'(e), w(e)) in one pass; ψ = w e except for "nlos"."""
    e = np.asarray(e, dtype=float)
    if loss == "nlos":
        return nlos_terms(e, *(nlos or ()), need_rho=need_rho)
    w = loss_weight(e, loss, c)
    return (loss_rho(e, loss, c) if need_rho else None), w * e, w
