"""Relative-motion factors from the autopilot's velocity (docs/design.md §5).

The displacement of the UAV between consecutive keyframes is the integral of its velocity. The
autopilot reports its (EKF) velocity v̂ with every position fix; integrated between the keyframe
times t_(n−1) and t_n it gives the factor's measurement

    ô_n = ∫ v̂ dt over [t_(n−1), t_n]                   (trapezoid on the records: v̂ piecewise linear)

and e_n = (x_n − x_(n−1) − ô_n) / σ_m,n (estimator.factors.MotionFactor).

Noise. An EKF's velocity error ε(t) is small (a few cm/s) and correlated over the filter's time
constant τ_v (about a second): it is not white per record, and it does not drift like the position
(the GPS velocity observes it directly). Modelled as first-order Gauss–Markov (σ_v, τ_v), its
integral over Δt has variance 2σ_v²τ_v² (Δt/τ_v − 1 + e^(−Δt/τ_v)): ≈ σ_v²Δt² for Δt ≪ τ_v, and
≈ 2σ_v²τ_v Δt, a random walk, for Δt ≫ τ_v. The factors of a chain are treated as independent,
so the form that keeps a *sum* of factors honest is the random walk:

    σ_m(Δt)² = 2 σ_v² τ_v Δt + σ_t²

exact for spans of many keyframes (what the users' covariance feels), conservative for one short
gap (where the exact variance is smaller), and never overconfident the way σ_v·Δt would be when
Δt < 2τ_v (n factors of σ_v·Δt sum to n σ_v²Δt² < 2σ_v²τ_v·nΔt). σ_t (MOTION_SIGMA_FLOOR_M)
covers the time alignment of the keyframes with the records and keeps a zero-length gap finite.
σ_v and τ_v come from the noise model (NoiseModel.vel_sigma_used_mps, vel_tau_used_s; header keys
`vel_sigma_mps`, `vel_tau_s`), defaults DEFAULT_VEL_SIGMA_MPS, DEFAULT_VEL_TAU_S.

Measured (`python benchmarks/honesty.py`, the same seeded logs without → with the factors; their
telemetry velocity is the truth plus white 0.05 m/s at 5 Hz, so the default σ_v, τ_v are
conservative there): white GPS, 48 users: mean error 0.35 → 0.34 m, RMSE/CRLB 1.01 → 0.99, NEES
2.04 → 1.95, 96 % → 96 % inside; Gauss–Markov GPS τ 60 s, 60 users: 1.09 → 1.01 m, NEES 2.58 →
2.45, 85 → 87 % inside; τ 120 s: 0.98 → 1.00 m, NEES 1.54 → 1.63, 100 %; τ 600 s: 1.47 → 1.47 m,
NEES 2.62 → 2.60, 88 %. The drifting GPS's common offset, which flying does not average away, is
what the velocity cannot see: it sharpens the track's shape, not its position.

No factor where it cannot be computed honestly: a keyframe gap not covered by velocity records on
both sides, records more than MAX_VEL_GAP_S apart inside it, or a gap longer than MAX_MOTION_DT_S.
"""

from __future__ import annotations

import numpy as np

from estimator.noise import NoiseModel
from uavloc.errors import EstimatorError

#: σ_t of the motion factor: time alignment of keyframes and velocity records [m]
MOTION_SIGMA_FLOOR_M = 0.01
#: velocity records further apart than this inside a keyframe gap: no factor [s]
MAX_VEL_GAP_S = 1.0
#: keyframe gaps longer than this get no factor [s]
MAX_MOTION_DT_S = 60.0


def motion_sigma_m(dt_s: np.ndarray | float, noise: NoiseModel, extra_var_m2: np.ndarray | float = 0.0) -> np.ndarray:
    """Per-axis σ [m] of the displacement integrated over dt_s [s] (any shape; module docstring),
    with extra_var_m2 the integration's own uncertainty (integrate_velocity's disc_var_m2).

        σ_m(Δt) = √(2 σ_v² τ_v Δt + σ_t² + σ_disc²)
    """
    dt = np.maximum(np.asarray(dt_s, dtype=float), 0.0)
    sv, tv = noise.vel_sigma_used_mps, noise.vel_tau_used_s
    return np.sqrt(2.0 * sv * sv * tv * dt + MOTION_SIGMA_FLOOR_M**2 + extra_var_m2)


def velocity_enu_of_ned(vel_ned_mps: np.ndarray) -> np.ndarray:
    """(T, 3) [north, east, down] → [east, north, up] [m/s]."""
    v = np.asarray(vel_ned_mps, dtype=float)
    return np.column_stack([v[:, 1], v[:, 0], -v[:, 2]])


def integrate_velocity(
    tel_t_s: np.ndarray, vel_enu_mps: np.ndarray, t_s: np.ndarray, max_gap_s: float = MAX_VEL_GAP_S,
    max_dt_s: float = MAX_MOTION_DT_S,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Displacements between consecutive times from velocity records.

    tel_t_s: (T,) record times [s] (sorted here); vel_enu_mps: (T, 3) velocity [m/s, ENU], NaN
    rows (no velocity) are skipped; t_s: (N,) keyframe times [s].
    Returns disp (N, 3) [m, ENU], disp_n = ∫ v dt over [t_(n−1), t_n] with v linear between
    records (the trapezoid rule on the records, exact inside an interval), and ok (N,) bool: True
    where the gap is covered (records at or before t_(n−1) and at or after t_n, none more than
    max_gap_s apart in between, 0 ≤ t_n − t_(n−1) ≤ max_dt_s); row 0 and rows not ok are 0/False;
    and disc_var_m2 (N,): the variance the records leave in the integral [m²]. Between two records
    the velocity may change anywhere, not linearly: a step Δv_j at a uniformly random time of an
    interval of length o_j errs by Δv_j (c − o_j/2), variance (o_j |Δv_j|)²/12, so

        σ_disc,n² = Σ_j (o_nj |v_(j+1) − v_j|)² / 12,   o_nj the part of interval j inside the gap n

    (negligible for smooth flight: 6 mm over 0.4 s at 0.4 m/s² and 5 Hz; large where records miss a turn).

        P(t_j) = Σ_(i ≤ j) ½ (v_(i−1) + v_i) h_i,   h_i = t_i − t_(i−1)
        P(t) = P(t_j) + v_j s + (v_(j+1) − v_j) s² / (2 h_(j+1)),   s = t − t_j ∈ [0, h_(j+1)]
        disp_n = P(t_n) − P(t_(n−1))
    """
    tt = np.asarray(tel_t_s, dtype=float)
    vv = np.asarray(vel_enu_mps, dtype=float)
    tk = np.asarray(t_s, dtype=float)
    if tt.ndim != 1 or vv.shape != (tt.shape[0], 3):
        raise EstimatorError(f"velocity records must be (T,) times and (T, 3) velocities, got {tt.shape}, {vv.shape}")
    if tk.ndim != 1:
        raise EstimatorError(f"keyframe times must be 1-D, got shape {tk.shape}")
    n = tk.shape[0]
    disp = np.zeros((n, 3))
    ok = np.zeros(n, dtype=bool)
    disc = np.zeros(n)
    use = np.isfinite(vv).all(axis=1) & np.isfinite(tt)
    tt, vv = tt[use], vv[use]
    order = np.argsort(tt, kind="stable")
    tt, vv = tt[order], vv[order]
    if tt.size:
        # strictly increasing times: of records at the same time keep the last
        keep = np.append(np.diff(tt) > 0, True)
        tt, vv = tt[keep], vv[keep]
    if tt.size < 2 or n < 2:
        return disp, ok, disc
    h = np.diff(tt)
    inside = np.isfinite(tk) & (tk >= tt[0]) & (tk <= tt[-1])
    tc = np.clip(np.where(np.isfinite(tk), tk, tt[0]), tt[0], tt[-1])
    # interval j = [t_j, t_(j+1)] holding each time (the last time falls in the last interval)
    j = np.clip(np.searchsorted(tt, tc, side="right") - 1, 0, tt.size - 2)
    # records more than max_gap_s apart among the intervals j_(n−1) .. j_n
    big = np.concatenate([[0], np.cumsum(h > max_gap_s)])
    gaps = big[j[1:] + 1] - big[j[:-1]]
    dt = tk[1:] - tk[:-1]
    ok[1:] = inside[1:] & inside[:-1] & (gaps == 0) & (dt >= 0) & (dt <= max_dt_s)
    # Each gap from its own records only (no running sum from the first record), so that the
    # flight, which keeps the recent records, gets the same bits as replay over the whole log:
    # F_j(s) = v_j s + (v_(j+1) − v_j) s²/(2 h_j) is the integral over [t_j, t_j + s], F_j(h_j) the
    # trapezoid T_j; a gap from a ∈ interval j_a to b ∈ interval j_b:
    #   j_a = j_b: F(s_b) − F(s_a);  else (T_(j_a) − F_(j_a)(s_a)) + Σ_(j_a < j < j_b) T_j + F_(j_b)(s_b)
    trap = 0.5 * (vv[1:] + vv[:-1]) * h[:, None]
    s_k = (tc - tt[j])[:, None]
    f_k = vv[j] * s_k + (vv[j + 1] - vv[j]) * (s_k * s_k) / (2.0 * h[j][:, None])
    ja, jb = j[:-1], j[1:]
    same = (ja == jb)[:, None]
    full = _segment_sums(trap, ja + 1, jb)
    disp[1:] = np.where(same, f_k[1:] - f_k[:-1], (trap[ja] - f_k[:-1]) + full + f_k[1:])
    disp[~ok] = 0.0
    # σ_disc²: the two partial ends and the whole intervals between them
    dv2 = np.sum(np.square(np.diff(vv, axis=0)), axis=1) / 12.0  # |Δv_j|²/12
    a_t, b_t = tc[:-1], tc[1:]
    same1 = same[:, 0]
    o_a = np.where(same1, b_t - a_t, tt[ja + 1] - a_t)
    o_b = np.where(same1, 0.0, b_t - tt[jb])
    mid = _segment_sums(h * h * dv2, ja + 1, jb)
    disc[1:] = np.where(ok[1:], o_a * o_a * dv2[ja] + o_b * o_b * dv2[jb] + mid, 0.0)
    return disp, ok, disc


def _segment_sums(values: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """Σ values[start_g:stop_g] along axis 0 for each g, each segment summed on its own (0 where
    start ≥ stop). values (J, ...); start, stop (G,) ints in [0, J]."""
    padded = np.concatenate([values, np.zeros((1, *values.shape[1:]))])
    idx = np.empty(2 * start.size, dtype=np.intp)
    idx[0::2] = np.minimum(start, values.shape[0])
    idx[1::2] = np.minimum(np.maximum(stop, start), values.shape[0])
    sums = np.add.reduceat(padded, idx, axis=0)[0::2]
    empty = stop <= start
    sums[empty] = 0.0
    return sums
