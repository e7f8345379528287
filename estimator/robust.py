"""Robust losses for range factors (DESIGN.md §5), applied by iteratively reweighted least squares.

A loss ρ acts on a whitened residual e = r / σ(d). The solver minimises Σ ρ(e) and, at each
Levenberg–Marquardt iteration, replaces it by the weighted quadratic ½ w e² with the IRLS weight

    w(e) = ρ'(e) / e

so that the gradient of the weighted problem equals the gradient of the robust cost (GTSAM's
`noiseModel.Robust` does the same). Losses, with threshold c in whitened units:

    none:    ρ(e) = ½ e²                                          w = 1
    huber:   ρ(e) = ½ e²            (|e| ≤ c),  c|e| − ½c² (else)  w = min(1, c/|e|)
    cauchy:  ρ(e) = ½ c² log(1 + (e/c)²)                          w = 1 / (1 + (e/c)²)
    tukey:   ρ(e) = c²/6 (1 − (1 − (e/c)²)³) (|e| ≤ c), c²/6 (else)  w = (1 − (e/c)²)² or 0

GPS priors, motion factors and bias priors are never robustified.
"""

from __future__ import annotations

import numpy as np

from uavloc.errors import EstimatorError

LOSSES = ("none", "huber", "cauchy", "tukey")
#: losses whose influence goes back to zero: need a start from a convex loss
REDESCENDING = ("tukey",)


def check_loss(loss: str, scale: float) -> None:
    """Raise EstimatorError for an unknown loss name or a non-positive threshold."""
    if loss not in LOSSES:
        raise EstimatorError(f"unknown robust loss {loss!r}; expected one of {LOSSES}")
    if not (np.isfinite(scale) and scale > 0):
        raise EstimatorError(f"loss_scale must be a positive finite number, got {scale!r}")


def loss_rho(e: np.ndarray, loss: str, c: float) -> np.ndarray:
    """ρ(e) of whitened residuals `e` (any shape), same shape."""
    e = np.asarray(e, dtype=float)
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


def loss_weight(e: np.ndarray, loss: str, c: float) -> np.ndarray:
    """IRLS weight w(e) = ρ'(e)/e of whitened residuals `e` (any shape), in [0, 1]."""
    e = np.asarray(e, dtype=float)
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
