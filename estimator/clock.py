"""A commercial UE's clock sawtooth, tracked instead of treated as noise (DESIGN.md §4).

A Rel-15 UE corrects its downlink timing only when conformance requires it: its round trip drifts
at a steady rate and then resets, so the range error of user k is a sawtooth on top of any
constant offset:

    saw_k(t) = A_k · frac(t / P_k − φ_k)          (A > 0: rises and drops; A < 0: falls and jumps)

Treated as noise it is neither zero-mean nor white (a 12 m sawtooth is a 6 m bias plus ramps that
last a whole period). :func:`fit_sawtooth` finds the period P from the periodogram of a
user's range residuals (the sawtooth's fundamental is its strongest line), then the reset phase φ
and the drift (A/P) by least squares on a grid around it; the estimator then estimates the
amplitude A_k with the positions (the user's bias becomes A_k times the sawtooth's shape) and
solves again (estimator.slam._track_clocks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: a sawtooth is fitted only when the residuals span at least this many periods ...
CLOCK_MIN_PERIODS = 2.0
#: ... with at least this many samples per period
CLOCK_MIN_SAMPLES_PER_PERIOD = 4.0
#: ... and accepted when it removes this share of the residual variance at least, and at least
#: CLOCK_NULL_EXPLAINED_N / n of n residuals: the best sawtooth of the (P, φ) search fitted to
#: white noise explains about 13/n (median) and 23/n (99th percentile; n = 120–1000, 300 draws
#: each): a short log (n = 60: 0.33) no longer finds a sawtooth in noise; n ≥ 134 unchanged
CLOCK_MIN_EXPLAINED = 0.15
CLOCK_NULL_EXPLAINED_N = 20.0
#: the coarse (P, φ) grid's best fit must explain this share of that already, or no refinement
#: is tried (a sawtooth's coarse fit explains ≥ 0.9 of its refined share: the coarse grid is
#: 7.5° in phase and a third of a frequency bin in period)
CLOCK_COARSE_SHARE = 0.6
#: phases tried per period, periods tried around the periodogram peak
_N_PHASE = 48
_N_PERIOD = 31


@dataclass(frozen=True)
class SawtoothFit:
    """saw(t) = amplitude_m · frac(t / period_s − phase) (+ offset_m, the residuals' constant).

    explained: share of the residual variance the sawtooth removes (0..1).
    """

    period_s: float
    phase: float
    amplitude_m: float
    offset_m: float
    explained: float

    def value_m(self, t_s: np.ndarray) -> np.ndarray:
        """saw(t) [m] at times t_s (any shape)."""
        # A · frac(t/P − φ)
        u = np.asarray(t_s, dtype=float) / self.period_s - self.phase
        return self.amplitude_m * (u - np.floor(u))

    def gain(self, t_s: np.ndarray) -> np.ndarray:
        """The gain of the user's bias (its amplitude) in its ranges at t_s, saw(t)/A (any shape):
        the estimator's r̂ = d + A · gain (Problem.bias_gain)."""
        return self.value_m(t_s) / self.amplitude_m


def periodogram(t_s: np.ndarray, x: np.ndarray, freqs_hz: np.ndarray, chunk: int = 256) -> np.ndarray:
    """(F,) power |Σ_n x_n e^(−2πi f t_n)|² / n of a zero-mean series at uneven times (the classic
    periodogram; for the peak of a sawtooth's fundamental it agrees with Lomb–Scargle, and it
    spares the estimator scipy.signal's import time)."""
    out = np.empty(freqs_hz.size)
    for i in range(0, freqs_hz.size, chunk):
        ph = 2.0 * np.pi * freqs_hz[i : i + chunk, None] * t_s[None, :]
        c, s = np.cos(ph) @ x, np.sin(ph) @ x
        out[i : i + chunk] = (c * c + s * s) / t_s.size
    return out


def peak_frequency_hz(t_s: np.ndarray, x: np.ndarray, f_min_hz: float, f_max_hz: float,
                      oversample: float = 4.0) -> float:
    """Frequency [Hz] of the highest peak in [f_min_hz, f_max_hz] of the periodogram of
    :func:`periodogram` (zero-mean series x (n,) at times t_s (n,), t_s ≥ 0), on a grid
    `oversample` × finer than the resolution 1/span, by FFT in O(M log M), M = 16·span·f_max:

        P(f) = |Σ_n x_n e^(−2πi f t_n)|² / n,   t_n ≈ h · round(t_n / h),  h = 1 / (16 f_max)

    Each sample moves to its nearest grid time: a shift ≤ h/2 turns a line at f ≤ f_max by at
    most π f_max h = π/16, which leaves the peak where it is (the direct sum costs O(n · F) with
    F ∝ span: quadratic in the length of a log)."""
    h = 1.0 / (16.0 * f_max_hz)
    idx = np.rint(np.asarray(t_s, dtype=float) / h).astype(np.int64)
    grid = np.bincount(idx, weights=x)
    # a power of two at least `oversample` × the grid (a length with a large prime factor sends
    # the FFT to Bluestein's algorithm: 3188 = 4 · 797 took 0.37 ms, 4096 takes 0.02 ms)
    m = 1 << max(math.ceil(oversample * grid.size), grid.size, 2).bit_length()
    power = np.abs(np.fft.rfft(grid, n=m)) ** 2
    freqs = np.fft.rfftfreq(m, d=h)
    sel = (freqs >= f_min_hz) & (freqs <= f_max_hz)
    if not sel.any():
        return float(0.5 * (f_min_hz + f_max_hz))
    return float(freqs[sel][int(np.argmax(power[sel]))])


def _fit_grid_dense(t: np.ndarray, r: np.ndarray, periods: np.ndarray, phases: np.ndarray) -> tuple:
    """:func:`_fit_grid` the obvious way, on the whole (P, Φ, n) array of frac(t/P − φ): the slow
    reference of the tests."""
    u = t[None, None, :] / periods[:, None, None] - phases[None, :, None]
    s = u - np.floor(u)
    n = t.size
    sm = s.mean(axis=2)
    rm = r.mean()
    sc = s - sm[..., None]
    sxx = np.einsum("pfn,pfn->pf", sc, sc)
    sxy = np.einsum("pfn,n->pf", sc, r - rm)
    return _grid_best(r, rm, sm, sxx, sxy, periods, phases, n)


def _grid_best(r, rm, sm, sxx, sxy, periods, phases, n) -> tuple:
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(sxx > 1e-12, sxy / sxx, 0.0)
    # rss = Σ (r − r̄)² − A² Sxx
    rss = float(np.sum((r - rm) ** 2)) - a * a * sxx
    i, j = np.unravel_index(int(np.argmin(rss)), rss.shape)
    amp = float(a[i, j])
    return float(rss[i, j]), float(periods[i]), float(phases[j]), amp, float(rm - amp * sm[i, j]), n


def _fit_grid(t: np.ndarray, r: np.ndarray, periods: np.ndarray, phases: np.ndarray) -> tuple:
    """Least squares r ≈ c + A·frac(t/P − φ) over the (P, φ) grid; (rss, P, φ, A, c, n) of the best.

    Per period, with u_n = frac(t_n/P) sorted and k(φ) = #{u_n < φ} (phases in [0, 1)):
    s_n = frac(u_n − φ) = u_n − φ + [u_n < φ], so with ř = r − r̄ and prefix sums U_k = Σ_(i<k) u_(i),
    Ř_k = Σ_(i<k) ř_(i) over the sorted order,

        Σ s = Σu − nφ + k,   Σ s² = Σu² − 2φΣu + nφ² + 2(U_k − kφ) + k,   Σ s ř = Σ u ř + Ř_k

    and S_xx = Σ s² − (Σ s)²/n, S_xy = Σ s ř, A = S_xy/S_xx: O(P·(n log n + Φ)) instead of the
    O(P·Φ·n) of frac on the whole grid (_fit_grid_dense, the same numbers up to rounding)."""
    n = t.size
    rm = r.mean()
    rc = r - rm
    ph = np.mod(np.asarray(phases, dtype=float), 1.0)
    n_p = periods.size
    rows = np.arange(n_p)[:, None]
    u = t[None, :] / periods[:, None]
    u -= np.floor(u)
    order = np.argsort(u, axis=1, kind="stable")
    us = np.take_along_axis(u, order, axis=1)
    rs = rc[order]
    cu = np.zeros((n_p, n + 1))
    np.cumsum(us, axis=1, out=cu[:, 1:])
    cr = np.zeros((n_p, n + 1))
    np.cumsum(rs, axis=1, out=cr[:, 1:])
    # k(φ) per period by one search: row i's sorted u shifted by i keeps the whole array sorted
    k = np.searchsorted((us + rows).ravel(), (ph[None, :] + rows).ravel(), side="left").reshape(n_p, -1)
    k = np.clip(k - rows * n, 0, n)
    su = cu[:, -1:]
    su2 = np.einsum("pn,pn->p", us, us)[:, None]
    sur = np.einsum("pn,pn->p", us, rs)[:, None]
    s1 = su - n * ph[None, :] + k
    s2 = su2 - 2.0 * ph[None, :] * su + n * ph[None, :] ** 2 + 2.0 * (np.take_along_axis(cu, k, axis=1) - k * ph) + k
    sm = s1 / n
    sxx = s2 - s1 * s1 / n
    sxy = sur + np.take_along_axis(cr, k, axis=1)
    return _grid_best(r, rm, sm, sxx, sxy, periods, phases, n)


def fit_sawtooth(t_s: np.ndarray, resid_m: np.ndarray) -> SawtoothFit | None:
    """Fit a clock sawtooth to one user's range residuals.

    t_s: (n,) measurement times [s]; resid_m: (n,) measured minus modelled range [m] (no bias
    removed). Returns None when the times cover fewer than CLOCK_MIN_PERIODS of any period with
    CLOCK_MIN_SAMPLES_PER_PERIOD samples, or when the best sawtooth explains less than
    max(CLOCK_MIN_EXPLAINED, CLOCK_NULL_EXPLAINED_N / n) of the residual variance.
    """
    t = np.asarray(t_s, dtype=float)
    r = np.asarray(resid_m, dtype=float)
    ok = np.isfinite(t) & np.isfinite(r)
    t, r = t[ok], r[ok]
    if t.size < 16:
        return None
    t0 = float(t.min())
    t = t - t0
    span = float(t.max())
    dt = float(np.median(np.diff(np.sort(t))))
    if span <= 0 or dt <= 0:
        return None
    f_min = CLOCK_MIN_PERIODS / span
    f_max = 1.0 / (CLOCK_MIN_SAMPLES_PER_PERIOD * dt)
    if f_max <= f_min:
        return None
    # the periodogram's peak on a grid 4× finer than the frequency resolution 1/span
    rc = r - r.mean()
    f0 = peak_frequency_hz(t, rc, f_min, f_max)
    # (P, φ) grid around the peak: ± one frequency bin, then a finer grid around the best
    df = 1.0 / (4.0 * span)
    periods = 1.0 / np.linspace(max(f0 - 1.5 * df, f_min * 0.5), f0 + 1.5 * df, _N_PERIOD)
    phases = np.arange(_N_PHASE) / _N_PHASE
    rss, p_best, ph_best, _, _, _ = _fit_grid(t, r, periods, phases)
    total = float(np.sum(rc * rc))
    need = max(CLOCK_MIN_EXPLAINED, CLOCK_NULL_EXPLAINED_N / t.size)
    if total <= 0 or 1.0 - rss / total < CLOCK_COARSE_SHARE * need:
        # the refinement (± one coarse step) cannot make up for that much: no sawtooth
        return None
    dp = float(np.max(np.abs(np.diff(periods))))
    periods = p_best + np.linspace(-dp, dp, 21)
    phases = ph_best + np.linspace(-1.0, 1.0, 21) / _N_PHASE
    rss, p_best, ph_best, amp, off, _ = _fit_grid(t, r, periods, phases)
    explained = 1.0 - rss / total
    if explained < need:
        return None
    # back to absolute time: frac((t − t0)/P − φ) = frac(t/P − (φ + t0/P))
    phase = (ph_best + t0 / p_best) % 1.0
    return SawtoothFit(p_best, phase, amp, off, explained)
