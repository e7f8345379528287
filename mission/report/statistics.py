"""Numbers a report shows: error ellipses, range errors against the reference users."""

from __future__ import annotations

import math

import numpy as np

from estimator.types import CHI2_2DOF_95
from mission.report.inputs import ReportInputs

#: at most this many points per scatter series (longer series are thinned evenly, for speed)
MAX_SCATTER_POINTS = 20_000


def ellipse_en_m(center_en_m: np.ndarray, cov_en_m2: np.ndarray, scale: float = math.sqrt(CHI2_2DOF_95),
                 n: int = 72) -> np.ndarray:
    """(n + 1, 2) closed, counter-clockwise ring of the ellipse {p : (p−c)ᵀ Σ⁻¹ (p−c) = scale²}.

    p(θ) = c + V · diag(scale·√λ) · [cos θ, sin θ]ᵀ with Σ = V diag(λ) Vᵀ, det V = +1 (so that θ
    increasing runs counter-clockwise). NaN ring when Σ is not finite.
    """
    c = np.asarray(center_en_m, float)[:2]
    cov = np.asarray(cov_en_m2, float)
    if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(c))):
        return np.full((n + 1, 2), np.nan)
    lam, vec = np.linalg.eigh(0.5 * (cov + cov.T))
    if np.linalg.det(vec) < 0:
        vec[:, 1] = -vec[:, 1]
    theta = np.linspace(0.0, 2 * np.pi, n + 1)
    theta[-1] = 0.0  # close the ring exactly
    circle = np.stack([np.cos(theta), np.sin(theta)])
    pts = c[:, None] + vec @ (scale * np.sqrt(np.maximum(lam, 0.0))[:, None] * circle)
    return pts.T


def thin(n: int, max_points: int = MAX_SCATTER_POINTS) -> np.ndarray:
    """Indices of at most `max_points` of n, evenly spaced."""
    if n <= max_points:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_points).astype(int))


def reference_users(inp: ReportInputs) -> tuple[np.ndarray, str]:
    """(K, 3) the true users when known, else the estimated ones; and which ("true"/"estimated")."""
    if inp.truth_enu_m is not None and np.all(np.isfinite(inp.truth_enu_m)):
        return inp.truth_enu_m, "true"
    return inp.users_enu_m, "estimated"


def range_errors(inp: ReportInputs) -> tuple[np.ndarray, np.ndarray, str]:
    """d (M,) distance from each measurement's GPS position to the reference user (true if known,
    else estimated) and e = r̂ − d (M,) [m]; and which reference was used."""
    ref, which = reference_users(inp)
    if inp.meas_user.size == 0:
        return np.zeros(0), np.zeros(0), which
    d = np.linalg.norm(inp.meas_uav_enu_m - ref[inp.meas_user], axis=1)
    return d, inp.meas_range_m - d, which
