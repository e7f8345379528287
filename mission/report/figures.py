"""The report's figures (PNG through matplotlib; the caller picks the backend), in the spirit of
the paper's. Every figure is titled after the mission (ReportInputs.title) and says, when the truth
is known, each user's horizontal error as the summary prints it (mission.result.Result):

- `top_view`: GPS track, estimated UAV track (through RTL and landing: past the last keyframe the
  telemetry shifted by the last keyframe's correction, drawn dashed), waypoints, true and
  estimated users with 95 % error ellipses, and the log's geofence, no-fly zones and buildings
  where they are near (the axes fit the flight and the users, the shapes are clipped).
- `side_view_east`, `side_view_north`: the same seen from the south (east–up) and from the west
  (north–up): the altitude profile, the users on the ground with their 95 % extent along the axis,
  buildings as silhouettes, the altitude band.
- `view_3d`: the tracks at their altitudes, the users on the ground, the buildings (mplot3d).
- `range_error`: range error r̂ − d against the true distance d, with each user's estimated bias
  and the model's ±σ(d) (and ±2σ(d)) about it (needs the true users; else the estimated ones,
  said in the title).
- `range_time`: measured range over time per user, with the distance from the GPS track to the
  reference user; the UE clock sawtooth shows as a slow rise-and-drop of the gap.
- `error_vs_flown`: 95 % error bound (and true error when known) against metres flown.

Legends sit below the axes (constrained layout), never over their edge.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np

from estimator.types import CHI2_2DOF_95
from mission.report.inputs import ReportInputs
from mission.report.statistics import (
    MAX_SCATTER_POINTS,
    EstimatedTrack,
    ellipse_en_m,
    errors_text,
    estimated_track,
    fit_limits_m,
    range_errors,
    reference_users,
    ring_in_view,
    sigma_text,
    thin,
)

#: figure size [inches] and resolution [dpi] of every PNG: 8 × 6 in at 100 dpi = 800 × 600 px.
FIG_SIZE_IN = (8.0, 6.0)
FIG_DPI = 100
FIGURES = ("top_view", "side_view_east", "side_view_north", "view_3d", "range_error", "range_time",
           "error_vs_flown")
#: the label of the estimated track past the last keyframe (what it is, said where it is drawn)
AFTER_LAST_LABEL = "estimated, after the last range: GPS + last correction"
#: the label of the estimated track before the first keyframe (take-off)
BEFORE_FIRST_LABEL = "estimated, before the first range: GPS + first correction"
#: (axis index, name, seen from) of the two side views
SIDE_AXES = {"side_view_east": (0, "east", "the south"), "side_view_north": (1, "north", "the west")}


def _with_errors(what: str, inp: ReportInputs) -> str:
    errs = errors_text(inp.result.users)
    return f"{what}; error {errs}" if errs else what


def _range_error_what(inp: ReportInputs) -> str:
    _d, _e, which = range_errors(inp)
    return f"range error vs distance to the {which} users, estimated bias ± {sigma_text(inp.noise)}"


_WHAT: dict[str, Callable[[ReportInputs], str]] = {
    "top_view": lambda inp: _with_errors("top view, 95 % ellipses", inp),
    "side_view_east": lambda inp: _with_errors("side view east–up (from the south)", inp),
    "side_view_north": lambda inp: _with_errors("side view north–up (from the west)", inp),
    "view_3d": lambda inp: _with_errors("3-D view", inp),
    "range_error": _range_error_what,
    "range_time": lambda inp: f"range over time (lines: distance to the {reference_users(inp)[1]} user)",
    "error_vs_flown": lambda inp: "user position error and 95 % error bound vs metres flown",
}


def figure_title(name: str, inp: ReportInputs) -> str:
    """The figure's title as one line (report.html's caption and alt text)."""
    return f"{inp.title}: {_WHAT[name](inp)}"


def _new_figure(plt, name: str, inp: ReportInputs):
    fig = plt.figure(figsize=FIG_SIZE_IN, dpi=FIG_DPI, layout="constrained")
    fig.suptitle(f"{inp.title}\n{_WHAT[name](inp)}", fontsize=10)
    return fig


#: a legend label longer than this [characters] makes the legend two columns wide, not three
LONG_LABEL_CHARS = 34


def _legend_below(fig, axes: list) -> None:
    """One legend of every labelled artist of `axes` (first label wins), below them in the figure;
    three columns, two when a label is long (the legend must fit the figure's width)."""
    seen: dict[str, object] = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(lab, h)
    ncol = 2 if max((len(lab) for lab in seen), default=0) > LONG_LABEL_CHARS else 3
    if seen:
        fig.legend(list(seen.values()), list(seen), loc="outside lower center", ncol=min(ncol, len(seen)),
                   fontsize=7, markerscale=1.0, frameon=False)


def _user_colors(k: int) -> list:
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return [cmap(i % 10) for i in range(k)]


def _est_tracks(inp: ReportInputs) -> list[EstimatedTrack]:
    """Each vehicle's :class:`EstimatedTrack`, from its own keyframes and telemetry."""
    out = []
    for v in inp.vehicles():
        kf = inp.vehicle_rows(inp.kf_vehicle, len(inp.kf_t_s), v)
        if not kf.any():
            continue
        tel_t = tel_enu = None
        if inp.tel_t_s is not None and inp.tel_enu_m is not None:
            tel = inp.vehicle_rows(inp.tel_vehicle, len(inp.tel_t_s), v)
            tel_t, tel_enu = inp.tel_t_s[tel], inp.tel_enu_m[tel]
        est = estimated_track(inp.kf_t_s[kf], inp.kf_gps_enu_m[kf], inp.uav_track_enu_m(v), tel_t, tel_enu)
        if est is not None:
            out.append(est)
    return out


def _en_ring(inp: ReportInputs, ring_lat_lon_deg: np.ndarray) -> np.ndarray:
    """(P + 1, 2) closed east-north ring [m] of an open lat/lon ring, about the report's origin."""
    lat, lon = ring_lat_lon_deg[:, 0], ring_lat_lon_deg[:, 1]
    en = inp.origin.lla_to_enu(lat, lon, np.full_like(lat, inp.origin.alt_m))[:, :2]
    return np.vstack([en, en[:1]])


def _plot_tracks(ax, inp: ReportInputs, cols: tuple[int, ...]) -> None:
    """GPS track, estimated track and its part past the last keyframe, on the columns `cols` of ENU;
    a fleet's, one line of each per vehicle."""
    for _, track in inp.tracks_enu_m():
        ax.plot(*(track[:, c] for c in cols), "-", color="0.6", lw=1.0, label="GPS track")
    for est in _est_tracks(inp):
        _plot_est_track(ax, est, cols)


def _plot_est_track(ax, est: EstimatedTrack, cols: tuple[int, ...]) -> None:
    if len(est.before_enu_m):
        ax.plot(*(est.before_enu_m[:, c] for c in cols), "--", color="tab:blue", lw=1.0, alpha=0.8,
                label=BEFORE_FIRST_LABEL)
    ax.plot(*(est.keyframes_enu_m[:, c] for c in cols), "-", color="tab:blue", lw=1.0, alpha=0.8,
            label="estimated UAV track (at keyframes)")
    if len(est.after_enu_m):
        ax.plot(*(est.after_enu_m[:, c] for c in cols), "--", color="tab:cyan", lw=1.2, label=AFTER_LAST_LABEL)


def _flight_points(inp: ReportInputs) -> np.ndarray:
    """(P, 3) ENU [m] of what every view must show: the tracks, waypoints, home and the users."""
    pts = [inp.track_enu_m(), np.zeros((1, 3)), inp.users_enu_m]
    pts += [est.all_enu_m() for est in _est_tracks(inp)]
    if inp.truth_enu_m is not None:
        pts.append(inp.truth_enu_m)
    if inp.waypoints_enu_m is not None:
        pts.append(inp.waypoints_enu_m)
    return np.vstack(pts)


def _users_to_zoom(inp: ReportInputs, span_m: float) -> list[int]:
    """Up to 3 users whose 95 % ellipse is too small to see on the map (< 3 % of its span)."""
    bound = inp.error_bound_95_m()
    return [k for k in range(inp.n_users)
            if np.all(np.isfinite(inp.users_enu_m[k, :2])) and np.isfinite(bound[k]) and bound[k] < 0.03 * span_m][:3]


def _fig_top_view(plt, inp: ReportInputs):
    fig = _new_figure(plt, "top_view", inp)
    colors = _user_colors(inp.n_users)
    rings = [ellipse_en_m(inp.users_enu_m[k], inp.cov_en_m2[k]) for k in range(inp.n_users)]
    pts = np.vstack([_flight_points(inp)[:, :2], *rings])
    lo, hi = fit_limits_m(pts)
    small = _users_to_zoom(inp, float(np.max(hi - lo)))
    if small:  # zoom panels in a column of their own, so they never cover the map
        grid = fig.add_gridspec(3, 4)
        ax = fig.add_subplot(grid[:, :3])
        zoom_axes = [fig.add_subplot(grid[i, 3]) for i in range(len(small))]
    else:
        ax = fig.add_subplot(1, 1, 1)
        zoom_axes = []
    _draw_shapes(ax, inp, lo, hi)
    _plot_tracks(ax, inp, (0, 1))
    if inp.waypoints_enu_m is not None:
        ax.plot(inp.waypoints_enu_m[:, 0], inp.waypoints_enu_m[:, 1], "x", color="k", ms=5, label="waypoints")
    ax.plot([0], [0], "^", color="k", ms=8, label="home / origin")
    for k in range(inp.n_users):
        u = inp.users_enu_m[k]
        if np.all(np.isfinite(rings[k])):
            ax.plot(rings[k][:, 0], rings[k][:, 1], "-", color=colors[k], lw=1.2, label="95 % ellipse")
        if np.all(np.isfinite(u[:2])):
            ax.plot(u[0], u[1], "o", color=colors[k], ms=7, mec="k", label="estimated user")
        if inp.truth_enu_m is not None and np.all(np.isfinite(inp.truth_enu_m[k, :2])):
            ax.plot(inp.truth_enu_m[k, 0], inp.truth_enu_m[k, 1], "*", color=colors[k], ms=13, mec="k",
                    label="true user")
        _label_user(ax, inp, k, (0, 1))
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")  # the limits stay the fitted ones
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.grid(True, alpha=0.3)
    _zoom_panels(zoom_axes, small, inp, colors)
    _legend_below(fig, [ax])
    return fig


def _label_user(ax, inp: ReportInputs, k: int, cols: tuple[int, int]) -> None:
    """The user's id beside its estimate (or its truth when not located)."""
    p = inp.users_enu_m[k]
    if not np.all(np.isfinite(p)) and inp.truth_enu_m is not None:
        p = inp.truth_enu_m[k]
    if np.all(np.isfinite(p)):
        ax.annotate(inp.user_ids[k], (p[cols[0]], p[cols[1]]), xytext=(6, 6), textcoords="offset points",
                    fontsize=8, weight="bold")


def _draw_shapes(ax, inp: ReportInputs, lo: np.ndarray, hi: np.ndarray) -> None:
    """The log header's geofence, no-fly zones and buildings on a top view, where they come into
    the view lo..hi (2,) [m] (clipped by the axes; they never set the limits)."""
    sh = inp.shapes
    if sh.geofence_lat_lon_deg is not None:
        r = _en_ring(inp, sh.geofence_lat_lon_deg)
        if ring_in_view(r, lo, hi):
            ax.plot(r[:, 0], r[:, 1], "-", color="tab:green", lw=1.5, label="geofence")
    for zone in sh.no_fly_lat_lon_deg:
        r = _en_ring(inp, zone)
        if ring_in_view(r, lo, hi):
            ax.fill(r[:, 0], r[:, 1], color="tab:red", alpha=0.2, label="no-fly zone")
    for b in sh.buildings:
        r = _en_ring(inp, b.footprint_lat_lon_deg)
        if ring_in_view(r, lo, hi):
            ax.fill(r[:, 0], r[:, 1], color="0.4", alpha=0.35, label="building")


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


def _side_view(plt, inp: ReportInputs, name: str):
    a, axis_name, _seen_from = SIDE_AXES[name]
    fig = _new_figure(plt, name, inp)
    ax = fig.add_subplot(1, 1, 1)
    pts = _flight_points(inp)[:, [a, 2]]
    lo, hi = fit_limits_m(pts)
    lo[1] = min(lo[1], 0.0)
    band = inp.shapes.altitude_band_m
    if band is not None:
        ax.axhspan(band[0], band[1], color="tab:green", alpha=0.08, label="altitude band")
    for b in inp.shapes.buildings:
        r = _en_ring(inp, b.footprint_lat_lon_deg)
        x0, x1 = float(r[:, a].min()), float(r[:, a].max())
        if x1 >= lo[0] and x0 <= hi[0]:
            ax.fill([x0, x1, x1, x0], [0, 0, b.height_m, b.height_m], color="0.4", alpha=0.3, label="building")
    _plot_tracks(ax, inp, (a, 2))
    colors = _user_colors(inp.n_users)
    for k in range(inp.n_users):
        u = inp.users_enu_m[k]
        if np.all(np.isfinite(u)):
            var = float(inp.cov_en_m2[k][a, a])
            # the 95 % ellipse's extent along this axis: ± sqrt(χ²₂(95 %)·σ_aa²)
            half = math.sqrt(CHI2_2DOF_95 * max(var, 0.0)) if np.isfinite(var) else 0.0
            ax.errorbar([u[a]], [u[2]], xerr=[[half], [half]], fmt="o", color=colors[k], mec="k", capsize=4,
                        label="estimated user, ± 95 %")
        if inp.truth_enu_m is not None and np.all(np.isfinite(inp.truth_enu_m[k])):
            ax.plot(inp.truth_enu_m[k, a], inp.truth_enu_m[k, 2], "*", color=colors[k], ms=13, mec="k",
                    label="true user")
        _label_user(ax, inp, k, (a, 2))
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_xlabel(f"{axis_name} [m]")
    ax.set_ylabel("up [m]")
    ax.grid(True, alpha=0.3)
    _legend_below(fig, [ax])
    return fig


def _fig_side_view_east(plt, inp: ReportInputs):
    return _side_view(plt, inp, "side_view_east")


def _fig_side_view_north(plt, inp: ReportInputs):
    return _side_view(plt, inp, "side_view_north")


def _building_faces(ring_en_m: np.ndarray, height_m: float) -> list[np.ndarray]:
    """The walls and roof of a prism on the closed ring (P + 1, 2) [m], from 0 to height_m."""
    faces = [np.array([[a[0], a[1], 0.0], [b[0], b[1], 0.0], [b[0], b[1], height_m], [a[0], a[1], height_m]])
             for a, b in itertools.pairwise(ring_en_m)]
    faces.append(np.c_[ring_en_m[:-1], np.full(len(ring_en_m) - 1, height_m)])
    return faces


def _fig_view_3d(plt, inp: ReportInputs):
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = _new_figure(plt, "view_3d", inp)
    ax = fig.add_subplot(1, 1, 1, projection="3d")
    lo, hi = fit_limits_m(_flight_points(inp))
    # equal east and north scales: the wider span for both
    mid, half = 0.5 * (lo[:2] + hi[:2]), 0.5 * float(np.max(hi[:2] - lo[:2]))
    lo[:2], hi[:2] = mid - half, mid + half
    lo[2] = min(lo[2], 0.0)
    for i, b in enumerate(inp.shapes.buildings):
        r = _en_ring(inp, b.footprint_lat_lon_deg)
        if ring_in_view(r, lo[:2], hi[:2]):
            r = np.clip(r, lo[:2], hi[:2])  # the part in the view (exact for boxes along the axes)
            hi[2] = max(hi[2], b.height_m)
            ax.add_collection3d(Poly3DCollection(_building_faces(r, b.height_m), facecolor="0.5", alpha=0.3,
                                                 edgecolor="0.3", lw=0.5, label="building" if i == 0 else None))
    _plot_tracks(ax, inp, (0, 1, 2))
    colors = _user_colors(inp.n_users)
    for k, uid in enumerate(inp.user_ids):
        u = inp.users_enu_m[k]
        if np.all(np.isfinite(u)):
            ring = ellipse_en_m(u, inp.cov_en_m2[k])
            if np.all(np.isfinite(ring)):
                ax.plot(ring[:, 0], ring[:, 1], np.full(len(ring), u[2]), "-", color=colors[k], lw=1.0,
                        label="95 % ellipse")
            ax.scatter([u[0]], [u[1]], [u[2]], color=colors[k], edgecolors="k", s=40, depthshade=False,
                       label="estimated user")
            ax.text(u[0], u[1], u[2], f"  {uid}", fontsize=8, weight="bold")
        if inp.truth_enu_m is not None and np.all(np.isfinite(inp.truth_enu_m[k])):
            t = inp.truth_enu_m[k]
            ax.scatter([t[0]], [t[1]], [t[2]], color=colors[k], edgecolors="k", marker="*", s=140,
                       depthshade=False, label="true user")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect((1.0, 1.0, 0.45), zoom=1.2)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_zlabel("up [m]")
    ax.view_init(elev=25, azim=-60)
    _legend_below(fig, [ax])
    return fig


def _fig_range_error(plt, inp: ReportInputs):
    fig = _new_figure(plt, "range_error", inp)
    ax = fig.add_subplot(1, 1, 1)
    d, e, which = range_errors(inp)
    colors = _user_colors(inp.n_users)
    for k, user in enumerate(inp.result.users):
        sel = np.flatnonzero((inp.meas_user == k) & np.isfinite(d))
        if not sel.size:
            continue
        dd = np.linspace(max(float(np.min(d[sel])), 0.0), float(np.max(d[sel])), 100)
        s = inp.noise.range_sigma_m(dd)
        # the estimated bias (the user's mean range bias; 0 when it was not estimated) ± σ(d)
        bias = 0.0 if user.bias_m is None else user.bias_m
        what = "no bias estimated" if user.bias_m is None else f"bias {bias:.1f} m"
        ax.fill_between(dd, bias - s, bias + s, color=colors[k], alpha=0.15, lw=0)
        ax.plot(dd, bias + 2 * s, ":", color=colors[k], lw=0.8)
        ax.plot(dd, bias - 2 * s, ":", color=colors[k], lw=0.8)
        ax.plot(dd, np.full_like(dd, bias), "-", color=colors[k], lw=1.5, label=f"{user.id}: {what} ± σ(d)")
        sel = sel[thin(sel.size, MAX_SCATTER_POINTS // max(inp.n_users, 1))]
        ax.plot(d[sel], e[sel], ".", ms=2.5, alpha=0.5, color=colors[k])
    ax.axhline(0.0, color="k", lw=0.6)
    ax.plot([], [], ":", color="0.3", lw=0.8, label="± 2σ(d)")
    ax.set_xlabel(f"distance to the {which} user [m]")
    ax.set_ylabel("range error r̂ − d [m]")
    ax.grid(True, alpha=0.3)
    _legend_below(fig, [ax])
    return fig


def _fig_range_time(plt, inp: ReportInputs):
    fig = _new_figure(plt, "range_time", inp)
    ax, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    ref, _which = reference_users(inp)
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
            ax2.plot(t, inp.meas_range_m[sel] - dist, ".", ms=2.5, color=colors[k])
    ax.set_ylabel("range [m]")
    ax.grid(True, alpha=0.3)
    ax2.set_xlabel("time since mission start [s]")
    ax2.set_ylabel("r̂ − d [m]")
    ax2.grid(True, alpha=0.3)
    ax2.set_title("gap (clock sawtooth, bias, noise)", fontsize=9)
    _legend_below(fig, [ax])
    return fig


def _fig_error_vs_flown(plt, inp: ReportInputs):
    fig = _new_figure(plt, "error_vs_flown", inp)
    ax = fig.add_subplot(1, 1, 1)
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
    _legend_below(fig, [ax])
    return fig


FIGURE_FUNCS = {
    "top_view": _fig_top_view,
    "side_view_east": _fig_side_view_east,
    "side_view_north": _fig_side_view_north,
    "view_3d": _fig_view_3d,
    "range_error": _fig_range_error,
    "range_time": _fig_range_time,
    "error_vs_flown": _fig_error_vs_flown,
}
