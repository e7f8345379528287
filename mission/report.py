"""Mission report: figures in the spirit of the paper, `report.json` and a self-contained
`report.html` (DESIGN.md §11 `--out DIR`).

The figures (PNG, matplotlib's Agg backend, chosen inside :func:`write_report`):

- `top_view.png`: GPS track, estimated UAV track, true (when known) and estimated users with
  95 % error ellipses (east/north).
- `side_view.png`: the same seen from the south (east/up) — the altitude profile.
- `range_error.png`: range error r̂ − d against the true distance d with ±σ(d) and ±2σ(d) of the
  noise model (needs the users' true positions; otherwise the estimated ones, said in the title).
- `range_time.png`: measured range over time per user, with the distance from the estimated
  track to the estimated user; the UE clock sawtooth shows as a slow rise-and-drop of the gap.
- `error_vs_flown.png`: 95 % error bound (and true error when known) against metres flown.

Everything the report draws comes in one :class:`ReportInputs` of plain arrays, so the report does
not depend on how replay or the mission controller store their results; :func:`inputs_from_replay`
builds it from a replay result.
"""

from __future__ import annotations

import base64
import html
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from estimator.types import CHI2_2DOF_95
from uavloc.errors import MissionError

log = logging.getLogger(__name__)

#: figure size [inches] and resolution [dpi] of every PNG: 8 × 6 in at 100 dpi = 800 × 600 px.
FIG_SIZE_IN = (8.0, 6.0)
FIG_DPI = 100
FIGURES = ("top_view", "side_view", "range_error", "range_time", "error_vs_flown")
#: at most this many points per scatter series (longer series are thinned evenly, for speed)
MAX_SCATTER_POINTS = 20_000


@dataclass(frozen=True)
class ReportInputs:
    """Everything a report or an export draws. Shapes: K users, N keyframes, M range measurements,
    T telemetry fixes, H history steps, W waypoints. Positions are ENU [m] about `origin`.

    user_ids: K names. users_enu_m (K, 3) estimated users (NaN rows: not located);
    cov_en_m2 (K, 2, 2) their east-north covariance [m²]; bias_m (K,) estimated range bias or None.
    truth_enu_m (K, 3) true users or None. ambiguous (K,) bool or None.
    kf_t_s (N,), kf_gps_enu_m (N, 3): keyframe times and GPS positions; uav_enu_m (N, 3) the
    estimator's corrected track (or None).
    tel_t_s (T,), tel_enu_m (T, 3): telemetry track (or None: the keyframes are the track).
    meas_t_s (M,), meas_user (M,), meas_range_m (M,), meas_uav_enu_m (M, 3): every range used, with
    the GPS position it was taken at.
    noise: the noise model the estimator used.
    hist_flown_m (H,), hist_bound_95_m (H, K), hist_error_m (H, K) or None: how the estimate evolved.
    waypoints_enu_m (W, 3) or None: the planner's waypoints, if the mission logged them.
    flown_m, status, title: summary.
    """

    origin: Origin
    user_ids: list[str]
    users_enu_m: np.ndarray
    cov_en_m2: np.ndarray
    noise: NoiseModel
    kf_t_s: np.ndarray
    kf_gps_enu_m: np.ndarray
    meas_t_s: np.ndarray
    meas_user: np.ndarray
    meas_range_m: np.ndarray
    meas_uav_enu_m: np.ndarray
    bias_m: np.ndarray | None = None
    truth_enu_m: np.ndarray | None = None
    ambiguous: np.ndarray | None = None
    uav_enu_m: np.ndarray | None = None
    tel_t_s: np.ndarray | None = None
    tel_enu_m: np.ndarray | None = None
    hist_flown_m: np.ndarray | None = None
    hist_bound_95_m: np.ndarray | None = None
    hist_error_m: np.ndarray | None = None
    waypoints_enu_m: np.ndarray | None = None
    flown_m: float = float("nan")
    status: str = ""
    title: str = "uavloc mission"
    extra: dict = field(default_factory=dict)

    @property
    def n_users(self) -> int:
        return len(self.user_ids)

    def track_enu_m(self) -> np.ndarray:
        """(T, 3) the flown GPS track: telemetry when present, else the keyframe GPS positions."""
        if self.tel_enu_m is not None and len(self.tel_enu_m) >= 2:
            return self.tel_enu_m
        return self.kf_gps_enu_m

    def error_bound_95_m(self) -> np.ndarray:
        """(K,) semi-major axis of each user's 95 % ellipse [m]; inf where unknown."""
        out = np.full(self.n_users, np.inf)
        for k in range(self.n_users):
            c = self.cov_en_m2[k]
            if np.all(np.isfinite(c)):
                out[k] = math.sqrt(CHI2_2DOF_95 * max(float(np.linalg.eigvalsh(c)[-1]), 0.0))
        return out

    def error_m(self) -> np.ndarray | None:
        """(K,) horizontal error of each estimated user [m] when the truth is known."""
        if self.truth_enu_m is None:
            return None
        return np.linalg.norm(self.users_enu_m[:, :2] - self.truth_enu_m[:, :2], axis=1)


def inputs_from_replay(result: Any, title: str | None = None) -> ReportInputs:
    """Build :class:`ReportInputs` from a `mission.replay.ReplayResult` (duck-typed: keyframes,
    estimate, log, noise, truth_enu_m, flown_m, history)."""
    mlog = result.log
    origin = mlog.header.origin
    est = result.estimate
    kfs = list(result.keyframes)
    k = mlog.n_users
    meas_t = np.concatenate([np.full(len(kf.range_m), kf.t_s) for kf in kfs]) if kfs else np.zeros(0)
    meas_user = np.concatenate([np.asarray(kf.user_idx, int) for kf in kfs]) if kfs else np.zeros(0, int)
    meas_r = np.concatenate([np.asarray(kf.range_m, float) for kf in kfs]) if kfs else np.zeros(0)
    meas_uav = (np.concatenate([np.repeat(np.asarray(kf.gps_enu_m, float)[None], len(kf.range_m), 0) for kf in kfs])
                if kfs else np.zeros((0, 3)))
    cov = np.array([est.cov_en_m2(j) for j in range(k)]).reshape(k, 2, 2)
    tel_t = tel_enu = None
    if len(mlog.tel_t_s) >= 2:
        tel_t = mlog.tel_t_s
        tel_enu = origin.lla_to_enu(mlog.tel_lla[:, 0], mlog.tel_lla[:, 1], mlog.tel_lla[:, 2])
    uav = np.asarray(est.uav_enu_m, float)
    if uav.shape != result.kf_gps_enu_m.shape:
        uav = None  # a fixed-lag estimator keeps only the last keyframes: nothing to draw against
    hist = getattr(result, "history", None)
    wps = waypoints_from_log(mlog)
    return ReportInputs(
        origin=origin,
        user_ids=[u.id for u in mlog.header.users],
        users_enu_m=np.asarray(est.users_enu_m, float),
        cov_en_m2=cov,
        noise=result.noise,
        kf_t_s=np.asarray(result.kf_t_s, float),
        kf_gps_enu_m=np.asarray(result.kf_gps_enu_m, float),
        meas_t_s=meas_t, meas_user=meas_user, meas_range_m=meas_r, meas_uav_enu_m=meas_uav,
        bias_m=None if est.bias_m is None else np.asarray(est.bias_m, float),
        truth_enu_m=None if result.truth_enu_m is None else np.asarray(result.truth_enu_m, float),
        ambiguous=np.asarray(est.ambiguous, bool),
        uav_enu_m=uav,
        tel_t_s=tel_t, tel_enu_m=tel_enu,
        hist_flown_m=None if hist is None else np.asarray(hist.flown_m, float),
        hist_bound_95_m=None if hist is None else np.asarray(hist.bound_95_m, float),
        hist_error_m=None if hist is None or hist.error_m is None else np.asarray(hist.error_m, float),
        waypoints_enu_m=wps,
        flown_m=float(result.flown_m),
        status=_status(est),
        title=title or f"uavloc replay of {Path(str(mlog.path)).name}",
    )


def _status(est: Any) -> str:
    if not np.all(np.isfinite(est.users_enu_m)):
        return "incomplete"
    if np.any(est.ambiguous):
        return "ambiguous"
    return "ok"


def waypoints_from_log(mlog: Any) -> np.ndarray | None:
    """(W, 3) ENU of the log's `waypoint` records that carry lat_deg/lon_deg/alt_m, or None."""
    pts = []
    for w in getattr(mlog, "waypoints", []) or []:
        try:
            pts.append((float(w["lat_deg"]), float(w["lon_deg"]), float(w["alt_m"])))
        except (KeyError, TypeError, ValueError):
            continue
    if not pts:
        return None
    a = np.asarray(pts)
    return mlog.header.origin.lla_to_enu(a[:, 0], a[:, 1], a[:, 2])


# ---------------------------------------------------------------------------------------------
# geometry helpers shared with mission/export.py


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


def _thin(n: int, max_points: int = MAX_SCATTER_POINTS) -> np.ndarray:
    """Indices of at most `max_points` of n, evenly spaced."""
    if n <= max_points:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_points).astype(int))


# ---------------------------------------------------------------------------------------------
# figures


def _user_colors(k: int) -> list:
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return [cmap(i % 10) for i in range(k)]


def _fig_top_view(plt, inp: ReportInputs):
    fig = plt.figure(figsize=FIG_SIZE_IN, dpi=FIG_DPI)
    small = _users_to_zoom(inp)
    if small:  # zoom panels in a column of their own, so they never cover the map
        grid = fig.add_gridspec(3, 4, wspace=0.35, hspace=0.45)
        ax = fig.add_subplot(grid[:, :3])
        zoom_axes = [fig.add_subplot(grid[i, 3]) for i in range(len(small))]
    else:
        ax = fig.add_subplot(1, 1, 1)
        zoom_axes = []
    track = inp.track_enu_m()
    ax.plot(track[:, 0], track[:, 1], "-", color="0.6", lw=1.0, label="GPS track")
    if inp.uav_enu_m is not None and len(inp.uav_enu_m):
        ax.plot(inp.uav_enu_m[:, 0], inp.uav_enu_m[:, 1], "-", color="tab:blue", lw=1.0, alpha=0.8,
                label="estimated UAV track")
    if inp.waypoints_enu_m is not None:
        ax.plot(inp.waypoints_enu_m[:, 0], inp.waypoints_enu_m[:, 1], "x", color="k", ms=5, label="waypoints")
    ax.plot([0], [0], "^", color="k", ms=8, label="home / origin")
    colors = _user_colors(inp.n_users)
    for k, uid in enumerate(inp.user_ids):
        u = inp.users_enu_m[k]
        if np.all(np.isfinite(u[:2])):
            ax.plot(u[0], u[1], "o", color=colors[k], ms=7, mec="k", label=f"{uid} estimate")
            ring = ellipse_en_m(u, inp.cov_en_m2[k])
            if np.all(np.isfinite(ring)):
                ax.plot(ring[:, 0], ring[:, 1], "-", color=colors[k], lw=1.2)
        if inp.truth_enu_m is not None and np.all(np.isfinite(inp.truth_enu_m[k, :2])):
            ax.plot(inp.truth_enu_m[k, 0], inp.truth_enu_m[k, 1], "*", color=colors[k], ms=13, mec="k",
                    label=f"{uid} true")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.set_title(f"{inp.title}: top view (ellipses: 95 %)")
    ax.legend(fontsize=7, loc="best", ncol=2)
    _zoom_panels(zoom_axes, small, inp, colors)
    return fig


def _users_to_zoom(inp: ReportInputs) -> list[int]:
    """Up to 3 users whose 95 % ellipse is too small to see on the whole map (< 3 % of its span)."""
    span = max(np.ptp(inp.track_enu_m()[:, 0]), np.ptp(inp.track_enu_m()[:, 1]), 1.0)
    bound = inp.error_bound_95_m()
    return [k for k in range(inp.n_users)
            if np.all(np.isfinite(inp.users_enu_m[k, :2])) and np.isfinite(bound[k]) and bound[k] < 0.03 * span][:3]


def _zoom_panels(axes: list, small: list[int], inp: ReportInputs, colors: list) -> None:
    """One zoomed panel per user in `small`: its estimate, 95 % ellipse and (when known) truth."""
    bound = inp.error_bound_95_m()
    for ins, k in zip(axes, small, strict=True):
        u = inp.users_enu_m[k]
        ring = ellipse_en_m(u, inp.cov_en_m2[k])
        ins.plot(ring[:, 0], ring[:, 1], "-", color=colors[k], lw=1.2)
        ins.plot(u[0], u[1], "o", color=colors[k], mec="k", ms=5)
        half = 1.3 * bound[k]
        if inp.truth_enu_m is not None and np.all(np.isfinite(inp.truth_enu_m[k, :2])):
            t = inp.truth_enu_m[k]
            ins.plot(t[0], t[1], "*", color=colors[k], mec="k", ms=9)
            half = max(half, 1.2 * float(np.hypot(*(t[:2] - u[:2]))))
        ins.set_xlim(u[0] - half, u[0] + half)
        ins.set_ylim(u[1] - half, u[1] + half)
        ins.set_aspect("equal")
        ins.tick_params(labelsize=6)
        ins.set_title(f"{inp.user_ids[k]} (±{half:.1f} m)", fontsize=7)


def _fig_side_view(plt, inp: ReportInputs):
    fig, ax = plt.subplots(figsize=FIG_SIZE_IN, dpi=FIG_DPI)
    track = inp.track_enu_m()
    ax.plot(track[:, 0], track[:, 2], "-", color="0.6", lw=1.0, label="GPS track")
    if inp.uav_enu_m is not None and len(inp.uav_enu_m):
        ax.plot(inp.uav_enu_m[:, 0], inp.uav_enu_m[:, 2], "-", color="tab:blue", lw=1.0, alpha=0.8,
                label="estimated UAV track")
    colors = _user_colors(inp.n_users)
    for k, uid in enumerate(inp.user_ids):
        u = inp.users_enu_m[k]
        if np.all(np.isfinite(u)):
            # horizontal 95 % extent along east: ± scale·σ_e
            half = math.sqrt(CHI2_2DOF_95 * max(float(inp.cov_en_m2[k][0, 0]), 0.0)) \
                if np.isfinite(inp.cov_en_m2[k][0, 0]) else 0.0
            ax.errorbar([u[0]], [u[2]], xerr=[[half], [half]], fmt="o", color=colors[k], mec="k", capsize=4,
                        label=f"{uid} estimate (±95 % east)")
        if inp.truth_enu_m is not None and np.all(np.isfinite(inp.truth_enu_m[k])):
            ax.plot(inp.truth_enu_m[k, 0], inp.truth_enu_m[k, 2], "*", color=colors[k], ms=13, mec="k",
                    label=f"{uid} true")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("up [m]")
    ax.grid(True, alpha=0.3)
    ax.set_title(f"{inp.title}: side view from the south")
    ax.legend(fontsize=7, loc="best", ncol=2)
    return fig


def _reference_users(inp: ReportInputs) -> tuple[np.ndarray, str]:
    if inp.truth_enu_m is not None and np.all(np.isfinite(inp.truth_enu_m)):
        return inp.truth_enu_m, "true"
    return inp.users_enu_m, "estimated"


def range_errors(inp: ReportInputs) -> tuple[np.ndarray, np.ndarray, str]:
    """d (M,) distance from each measurement's GPS position to the reference user (true if known,
    else estimated) and e = r̂ − d (M,) [m]; and which reference was used."""
    ref, which = _reference_users(inp)
    if inp.meas_user.size == 0:
        return np.zeros(0), np.zeros(0), which
    d = np.linalg.norm(inp.meas_uav_enu_m - ref[inp.meas_user], axis=1)
    return d, inp.meas_range_m - d, which


def _fig_range_error(plt, inp: ReportInputs):
    fig, ax = plt.subplots(figsize=FIG_SIZE_IN, dpi=FIG_DPI)
    d, e, which = range_errors(inp)
    colors = _user_colors(inp.n_users)
    for k, uid in enumerate(inp.user_ids):
        sel = np.flatnonzero((inp.meas_user == k) & np.isfinite(d))
        sel = sel[_thin(sel.size, MAX_SCATTER_POINTS // max(inp.n_users, 1))]
        if sel.size:
            ax.plot(d[sel], e[sel], ".", ms=2.5, alpha=0.5, color=colors[k], label=uid)
    if np.any(np.isfinite(d)):
        dd = np.linspace(max(float(np.nanmin(d)), 0.0), float(np.nanmax(d)), 200)
        s = inp.noise.range_sigma_m(dd)
        ax.plot(dd, s, "k-", lw=1.2, label="±σ(d) model")
        ax.plot(dd, -s, "k-", lw=1.2)
        ax.plot(dd, 2 * s, "k--", lw=0.8, label="±2σ(d)")
        ax.plot(dd, -2 * s, "k--", lw=0.8)
    n = inp.noise
    ax.set_xlabel(f"distance to the {which} user [m]")
    ax.set_ylabel("range error r̂ − d [m]")
    ax.grid(True, alpha=0.3)
    ax.set_title(f"range error vs distance ({which} users); σ(d) = {n.s0_m:.2f} + {n.a_m:.3g}·exp({n.b_per_m:.3g}·d)")
    ax.legend(fontsize=7, loc="best", markerscale=4)
    return fig


def _fig_range_time(plt, inp: ReportInputs):
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=FIG_SIZE_IN, dpi=FIG_DPI, sharex=True,
                                  gridspec_kw={"height_ratios": [2, 1]})
    ref, which = _reference_users(inp)
    colors = _user_colors(inp.n_users)
    for k, uid in enumerate(inp.user_ids):
        sel = np.flatnonzero(inp.meas_user == k)
        sel = sel[_thin(sel.size, MAX_SCATTER_POINTS // max(inp.n_users, 1))]
        if not sel.size:
            continue
        t = inp.meas_t_s[sel]
        ax.plot(t, inp.meas_range_m[sel], ".", ms=2.5, color=colors[k], label=f"{uid} measured")
        if np.all(np.isfinite(ref[k])):
            dist = np.linalg.norm(inp.meas_uav_enu_m[sel] - ref[k], axis=1)
            ax.plot(t, dist, "-", lw=0.8, color=colors[k], alpha=0.7)
            ax2.plot(t, inp.meas_range_m[sel] - dist, ".", ms=2.5, color=colors[k], label=uid)
    ax.set_ylabel("range [m]")
    ax.set_title(f"range over time (lines: distance to the {which} user)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="best", markerscale=4)
    ax2.set_xlabel("time since mission start [s]")
    ax2.set_ylabel("r̂ − d [m]")
    ax2.grid(True, alpha=0.3)
    ax2.set_title("gap (clock sawtooth, bias, noise)", fontsize=9)
    return fig


def _fig_error_vs_flown(plt, inp: ReportInputs):
    fig, ax = plt.subplots(figsize=FIG_SIZE_IN, dpi=FIG_DPI)
    colors = _user_colors(inp.n_users)
    if inp.hist_flown_m is not None and inp.hist_bound_95_m is not None and len(inp.hist_flown_m):
        x = inp.hist_flown_m
        for k, uid in enumerate(inp.user_ids):
            b = np.where(np.isfinite(inp.hist_bound_95_m[:, k]), inp.hist_bound_95_m[:, k], np.nan)
            ax.plot(x, b, "-", color=colors[k], lw=1.3, label=f"{uid} 95 % bound")
            if inp.hist_error_m is not None:
                ax.plot(x, inp.hist_error_m[:, k], ":", color=colors[k], lw=1.3, label=f"{uid} true error")
        ax.set_yscale("log")
    else:
        bound = inp.error_bound_95_m()
        err = inp.error_m()
        for k, uid in enumerate(inp.user_ids):
            if np.isfinite(bound[k]):
                ax.plot([inp.flown_m], [bound[k]], "o", color=colors[k], label=f"{uid} 95 % bound (final)")
            if err is not None and np.isfinite(err[k]):
                ax.plot([inp.flown_m], [err[k]], "x", color=colors[k], label=f"{uid} true error (final)")
        ax.text(0.5, 0.9, "no history (replay with history to see the curve)", transform=ax.transAxes,
                ha="center", fontsize=9)
    ax.set_xlabel("metres flown [m]")
    ax.set_ylabel("position error [m]")
    ax.grid(True, which="both", alpha=0.3)
    ax.set_title("user position error and 95 % error bound vs metres flown")
    ax.legend(fontsize=7, loc="best")
    return fig


_FIGURE_FUNCS = {
    "top_view": _fig_top_view,
    "side_view": _fig_side_view,
    "range_error": _fig_range_error,
    "range_time": _fig_range_time,
    "error_vs_flown": _fig_error_vs_flown,
}


# ---------------------------------------------------------------------------------------------
# report.json / report.html


def _f(x: Any) -> Any:
    """Finite float or None (JSON has no NaN)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def report_document(inp: ReportInputs, figures: dict[str, str] | None = None) -> dict:
    """The content of report.json: summary, users, noise model, range statistics, figure files."""
    lat, lon, alt = inp.origin.enu_to_lla(inp.users_enu_m)
    bound = inp.error_bound_95_m()
    err = inp.error_m()
    _d, e, which = range_errors(inp)
    users = []
    for k, uid in enumerate(inp.user_ids):
        located = bool(np.all(np.isfinite(inp.users_enu_m[k])))
        cov = inp.cov_en_m2[k]
        sel = inp.meas_user == k
        entry = {
            "id": uid,
            "lat_deg": _f(lat[k]) if located else None,
            "lon_deg": _f(lon[k]) if located else None,
            "alt_m": _f(alt[k]) if located else None,
            "enu_m": [_f(x) for x in inp.users_enu_m[k]] if located else None,
            "cov_en_m2": cov.tolist() if np.all(np.isfinite(cov)) else None,
            "sigma_east_m": _f(math.sqrt(cov[0, 0])) if np.isfinite(cov[0, 0]) and cov[0, 0] >= 0 else None,
            "sigma_north_m": _f(math.sqrt(cov[1, 1])) if np.isfinite(cov[1, 1]) and cov[1, 1] >= 0 else None,
            "error_bound_95_m": _f(bound[k]),
            "measurements": int(sel.sum()),
            "range_error_mean_m": _f(np.mean(e[sel])) if sel.any() else None,
            "range_error_std_m": _f(np.std(e[sel])) if sel.sum() > 1 else None,
        }
        if inp.bias_m is not None:
            entry["bias_m"] = _f(inp.bias_m[k])
        if inp.ambiguous is not None:
            entry["ambiguous"] = bool(inp.ambiguous[k])
        if err is not None:
            entry["error_m"] = _f(err[k])
            t = inp.truth_enu_m[k]
            tl = inp.origin.enu_to_lla(t)
            entry["truth"] = {"lat_deg": _f(tl[0]), "lon_deg": _f(tl[1]), "alt_m": _f(tl[2]),
                              "enu_m": [_f(x) for x in t]}
        users.append(entry)
    return {
        "title": inp.title,
        "status": inp.status,
        "origin": inp.origin.to_dict(),
        "flown_m": _f(inp.flown_m),
        "keyframes": len(inp.kf_t_s),
        "measurements": len(inp.meas_range_m),
        "duration_s": _f(inp.kf_t_s[-1] - inp.kf_t_s[0]) if len(inp.kf_t_s) else None,
        "noise": inp.noise.to_log_dict(),
        "range_error_reference": which,
        "users": users,
        "figures": figures or {},
        **({"extra": inp.extra} if inp.extra else {}),
    }


def _html_page(doc: dict, pngs: dict[str, bytes]) -> str:
    esc = html.escape
    rows = []
    for u in doc["users"]:
        def cell(v, fmt="{:.2f}"):
            return "–" if v is None else (fmt.format(v) if isinstance(v, float) else esc(str(v)))
        rows.append(
            "<tr>" + "".join(f"<td>{c}</td>" for c in (
                esc(u["id"]), cell(u["lat_deg"], "{:.7f}"), cell(u["lon_deg"], "{:.7f}"), cell(u["alt_m"], "{:.1f}"),
                cell(u["error_bound_95_m"]), cell(u.get("error_m")), cell(u.get("bias_m")), str(u["measurements"]),
                "yes" if u.get("ambiguous") else "no",
            )) + "</tr>"
        )
    imgs = "\n".join(
        f'<figure><img alt="{esc(name)}" src="data:image/png;base64,{base64.b64encode(data).decode("ascii")}">'
        f"<figcaption>{esc(name.replace('_', ' '))}</figcaption></figure>"
        for name, data in pngs.items()
    )
    n = doc["noise"]["range_sigma_m"]
    flown = doc["flown_m"]
    o = doc["origin"]
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{esc(doc["title"])}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; max-width: 1000px; }}
table {{ border-collapse: collapse; }} td, th {{ border: 1px solid #bbb; padding: 3px 8px; text-align: right; }}
figure {{ margin: 1em 0; }} img {{ max-width: 100%; border: 1px solid #ddd; }}
</style></head><body>
<h1>{esc(doc["title"])}</h1>
<p>Status: <b>{esc(str(doc["status"]))}</b>; {doc["measurements"]} ranges at {doc["keyframes"]} keyframes;
{"–" if flown is None else f"{flown:.0f}"} m flown. Origin {o["lat_deg"]:.7f}, {o["lon_deg"]:.7f}, {o["alt_m"]:.1f} m.
Noise model σ(d) = {n["s0"]:.3g} + {n["a"]:.3g}·exp({n["b"]:.3g}·d) m,
σ<sub>GPS</sub> = {doc["noise"]["sigma_gps_m"]:.3g} m.</p>
<table><tr><th>user</th><th>lat [deg]</th><th>lon [deg]</th><th>alt [m]</th><th>95 % bound [m]</th>
<th>error [m]</th><th>bias [m]</th><th>ranges</th><th>ambiguous</th></tr>
{"".join(rows)}
</table>
{imgs}
</body></html>
"""


def write_report(result_or_inputs: Any, out_dir: str | Path, figures: tuple[str, ...] = FIGURES,
                 exports: bool = True) -> dict[str, Path]:
    """Write the figures, report.json and report.html into `out_dir` (created), and with `exports`
    also mission.geojson, mission.kml and mission.plan (see mission/export.py). Accepts a
    :class:`ReportInputs` or a replay result. Returns {name: path} of every file written."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    inp = result_or_inputs if isinstance(result_or_inputs, ReportInputs) else inputs_from_replay(result_or_inputs)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MissionError(f"cannot create report directory {out}: {exc}") from exc
    unknown = sorted(set(figures) - set(_FIGURE_FUNCS))
    if unknown:
        raise MissionError(f"unknown report figure(s) {unknown}; known: {', '.join(FIGURES)}")
    t0 = time.perf_counter()
    paths: dict[str, Path] = {}
    pngs: dict[str, bytes] = {}
    for name in figures:
        fig = _FIGURE_FUNCS[name](plt, inp)
        try:
            path = out / f"{name}.png"
            fig.savefig(path, dpi=FIG_DPI)
        except OSError as exc:
            raise MissionError(f"cannot write {out / name}.png: {exc}") from exc
        finally:
            plt.close(fig)
        paths[name] = path
        pngs[name] = path.read_bytes()
    doc = report_document(inp, {name: p.name for name, p in paths.items()})
    try:
        (out / "report.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        (out / "report.html").write_text(_html_page(doc, pngs), encoding="utf-8")
    except OSError as exc:
        raise MissionError(f"cannot write the report into {out}: {exc}") from exc
    paths["report.json"] = out / "report.json"
    paths["report.html"] = out / "report.html"
    if exports:
        from mission.export import write_exports

        paths.update(write_exports(inp, out))
    log.info("report: %d figures, report.json, report.html in %s (%.1f s)", len(figures), out,
             time.perf_counter() - t0)
    return paths
