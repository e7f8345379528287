"""The report's figures (PNG through matplotlib; the caller picks the backend):

- `top_view`: GPS track, estimated UAV track, true (when known) and estimated users with 95 %
  error ellipses (east/north), and the log's geofence, no-fly zones and buildings when it has them.
- `side_view`: the same seen from the south (east/up) — the altitude profile and band.
- `range_error`: range error r̂ − d against the true distance d with ±σ(d) and ±2σ(d) of the
  noise model (needs the users' true positions; otherwise the estimated ones, said in the title).
- `range_time`: measured range over time per user, with the distance from the estimated
  track to the estimated user; the UE clock sawtooth shows as a slow rise-and-drop of the gap.
- `error_vs_flown`: 95 % error bound (and true error when known) against metres flown.
"""

from __future__ import annotations

import math

import numpy as np

from estimator.types import CHI2_2DOF_95
from mission.report.inputs import ReportInputs
from mission.report.statistics import MAX_SCATTER_POINTS, ellipse_en_m, range_errors, reference_users, thin

#: figure size [inches] and resolution [dpi] of every PNG: 8 × 6 in at 100 dpi = 800 × 600 px.
FIG_SIZE_IN = (8.0, 6.0)
FIG_DPI = 100
FIGURES = ("top_view", "side_view", "range_error", "range_time", "error_vs_flown")


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
    _draw_shapes(ax, inp)
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


def _en_ring(inp: ReportInputs, ring_lat_lon_deg: np.ndarray) -> np.ndarray:
    """(P + 1, 2) closed east-north ring [m] of an open lat/lon ring, about the report's origin."""
    lat, lon = ring_lat_lon_deg[:, 0], ring_lat_lon_deg[:, 1]
    en = inp.origin.lla_to_enu(lat, lon, np.full_like(lat, inp.origin.alt_m))[:, :2]
    return np.vstack([en, en[:1]])


def _draw_shapes(ax, inp: ReportInputs) -> None:
    """The log header's geofence, no-fly zones and buildings on a top view."""
    sh = inp.shapes
    if sh.geofence_lat_lon_deg is not None:
        r = _en_ring(inp, sh.geofence_lat_lon_deg)
        ax.plot(r[:, 0], r[:, 1], "-", color="tab:green", lw=1.5, label="geofence")
    for i, zone in enumerate(sh.no_fly_lat_lon_deg):
        r = _en_ring(inp, zone)
        ax.fill(r[:, 0], r[:, 1], color="tab:red", alpha=0.2, label="no-fly zone" if i == 0 else None)
    for i, b in enumerate(sh.buildings):
        r = _en_ring(inp, b.footprint_lat_lon_deg)
        ax.fill(r[:, 0], r[:, 1], color="0.4", alpha=0.35, label="building" if i == 0 else None)


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
    band = inp.shapes.altitude_band_m
    if band is not None:
        ax.axhspan(band[0], band[1], color="tab:green", alpha=0.08, label="altitude band")
    ax.set_title(f"{inp.title}: side view from the south")
    ax.legend(fontsize=7, loc="best", ncol=2)
    return fig


def _fig_range_error(plt, inp: ReportInputs):
    fig, ax = plt.subplots(figsize=FIG_SIZE_IN, dpi=FIG_DPI)
    d, e, which = range_errors(inp)
    colors = _user_colors(inp.n_users)
    for k, uid in enumerate(inp.user_ids):
        sel = np.flatnonzero((inp.meas_user == k) & np.isfinite(d))
        sel = sel[thin(sel.size, MAX_SCATTER_POINTS // max(inp.n_users, 1))]
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
    ax.set_title(f"range error vs distance ({which} users); "
                 f"σ(d) = {n.range_s0_m:.2f} + {n.range_a_m:.3g}·exp({n.range_b_per_m:.3g}·d)")
    ax.legend(fontsize=7, loc="best", markerscale=4)
    return fig


def _fig_range_time(plt, inp: ReportInputs):
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=FIG_SIZE_IN, dpi=FIG_DPI, sharex=True,
                                  gridspec_kw={"height_ratios": [2, 1]})
    ref, which = reference_users(inp)
    colors = _user_colors(inp.n_users)
    for k, uid in enumerate(inp.user_ids):
        sel = np.flatnonzero(inp.meas_user == k)
        sel = sel[thin(sel.size, MAX_SCATTER_POINTS // max(inp.n_users, 1))]
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
                ax.plot([inp.result.flown_m], [bound[k]], "o", color=colors[k], label=f"{uid} 95 % bound (final)")
            if err is not None and np.isfinite(err[k]):
                ax.plot([inp.result.flown_m], [err[k]], "x", color=colors[k], label=f"{uid} true error (final)")
        ax.text(0.5, 0.9, "no history (replay with history to see the curve)", transform=ax.transAxes,
                ha="center", fontsize=9)
    ax.set_xlabel("metres flown [m]")
    ax.set_ylabel("position error [m]")
    ax.grid(True, which="both", alpha=0.3)
    ax.set_title("user position error and 95 % error bound vs metres flown")
    ax.legend(fontsize=7, loc="best")
    return fig


FIGURE_FUNCS = {
    "top_view": _fig_top_view,
    "side_view": _fig_side_view,
    "range_error": _fig_range_error,
    "range_time": _fig_range_time,
    "error_vs_flown": _fig_error_vs_flown,
}
