"""Numbers a report shows: error ellipses, range errors against the reference users, the estimated
track through RTL and landing, axis limits, and the texts of the titles. Pure functions."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from estimator.noise import NoiseModel
from estimator.types import CHI2_2DOF_95
from mission.report.inputs import ReportInputs
from mission.result import UserResult

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


@dataclass(frozen=True)
class EstimatedTrack:
    """The estimated UAV track as the report draws it (ENU [m]): keyframes_enu_m (N, 3) the
    estimator's corrected positions at its keyframes; before_enu_m (B, 3) and after_enu_m (A, 3) the
    telemetry before the first and after the last keyframe (take-off; RTL and landing, where no
    range comes) shifted by the first's and the last keyframe's correction (estimate − GPS), each
    joined to its keyframe (empty: no telemetry there)."""

    keyframes_enu_m: np.ndarray
    before_enu_m: np.ndarray
    after_enu_m: np.ndarray

    def all_enu_m(self) -> np.ndarray:
        """(B + N + A, 3) every point, for fitting the axes."""
        return np.vstack([self.before_enu_m, self.keyframes_enu_m, self.after_enu_m])


def estimated_track(kf_t_s: np.ndarray, kf_gps_enu_m: np.ndarray, uav_enu_m: np.ndarray | None,
                    tel_t_s: np.ndarray | None, tel_enu_m: np.ndarray | None) -> EstimatedTrack | None:
    """:class:`EstimatedTrack` of the keyframes (kf_t_s (N,) [s], kf_gps_enu_m (N, 3) and the
    estimate uav_enu_m (N, 3) [m]) and the telemetry (tel_t_s (T,) [s], tel_enu_m (T, 3) [m], same
    clock); None without an estimated track. The estimator corrects only keyframes: past the last
    one the telemetry is shifted by the last correction c = uav_enu_m[-1] − kf_gps_enu_m[-1] (the GPS
    error drifts slowly: a shift, not an estimate)."""
    if uav_enu_m is None or len(uav_enu_m) == 0:
        return None
    uav = np.asarray(uav_enu_m, float)
    gps = np.asarray(kf_gps_enu_m, float)
    empty = np.zeros((0, 3))
    if tel_t_s is None or tel_enu_m is None or len(tel_t_s) == 0:
        return EstimatedTrack(uav, empty, empty)
    t = np.asarray(tel_t_s, float)
    tel = np.asarray(tel_enu_m, float)
    first = t < kf_t_s[0]
    last = t > kf_t_s[-1]
    before = np.vstack([tel[first] + (uav[0] - gps[0]), uav[:1]]) if first.any() else empty
    after = np.vstack([uav[-1:], tel[last] + (uav[-1] - gps[-1])]) if last.any() else empty
    return EstimatedTrack(uav, before, after)


def fit_limits_m(points_m: np.ndarray, margin_frac: float = 0.12, min_span_m: float = 20.0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Axis limits (lo (D,), hi (D,)) [m] around the finite rows of points_m (P, D): their extent,
    widened to at least min_span_m, with margin_frac of the span on each side."""
    p = np.asarray(points_m, float)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) == 0:
        half = np.full(np.asarray(points_m).shape[1], min_span_m / 2)
        return -half, half
    lo, hi = p.min(axis=0), p.max(axis=0)
    mid, span = 0.5 * (lo + hi), np.maximum(hi - lo, min_span_m)
    half = 0.5 * span * (1.0 + 2.0 * margin_frac)
    return mid - half, mid + half


def ring_in_view(ring_m: np.ndarray, lo_m: np.ndarray, hi_m: np.ndarray, step_m: float = 1.0) -> bool:
    """Whether any part of the closed 2-D ring (P + 1, 2) [m] lies inside the box lo..hi (2,) [m]
    (its edges sampled every step_m)."""
    r = np.asarray(ring_m, float)
    for a, b in itertools.pairwise(r):
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / step_m)) + 1)
        s = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
        if np.any(np.all((s >= lo_m) & (s <= hi_m), axis=1)):
            return True
    return False


def sigma_text(noise: NoiseModel) -> str:
    """The range noise model σ(d) = s0 + a·exp(b·d) as a title writes it: "σ(d) = 3.00 m" when
    it does not depend on d (a = 0, or b = 0: then s0 + a)."""
    s0, a, b = noise.range_s0_m, noise.range_a_m, noise.range_b_per_m
    if a == 0.0:
        return f"σ(d) = {s0:.2f} m"
    if b == 0.0:
        return f"σ(d) = {s0 + a:.2f} m"
    return f"σ(d) = {s0:.2f} + {a:.3g}·exp({b:.3g}·d) m"


def errors_text(users: Sequence[UserResult]) -> str:
    """Each user's horizontal error as the summary prints it ("ue1 1.40 m, ue2 1.26 m"; "ue3 not
    located" where its truth is known but it is not); "" when no user's truth is known."""
    parts = []
    for u in users:
        if u.truth is None:
            continue
        parts.append(f"{u.id} {u.error_m:.2f} m" if u.error_m is not None else f"{u.id} not located")
    return ", ".join(parts)
