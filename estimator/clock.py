"""A commercial UE's clock sawtooth, tracked instead of treated as noise (docs/design.md §4).

A Rel-15 UE corrects its downlink timing only when conformance requires it: its round trip drifts
at a steady rate and then resets, so the range error of user k is a sawtooth on top of any
constant offset:

    saw_k(t) = A_k · frac(t / P_k − φ_k)          (A > 0: rises and drops; A < 0: falls and jumps)

Treated as noise it is neither zero-mean nor white (a 12 m sawtooth is a 6 m bias plus ramps that
last a whole period). :func:`fit_sawtooth` finds the period P from the periodogram of a
user's range residuals (the sawtooth's fundamental is its strongest line), then the reset phase φ
and the drift (A/P) by least squares on a grid around it; the estimator then estimates the
amplitude A_k with the positions (the user's bias becomes A_k times the sawtooth's shape) and
solves again (estimator.batch._track_clocks).
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
#: white noise explains about 15/n (median) and 24/n (99th percentile) at n = 120–200, 19/n and
#: 28/n at n = 400 (300 draws each; the search over several peaks and their subharmonics adds
#: about 1/n to the single-peak search's): a short log (n = 60: 0.33) finds no sawtooth in noise
CLOCK_MIN_EXPLAINED = 0.15
CLOCK_NULL_EXPLAINED_N = 20.0
#: the coarse (P, φ) grid's best fit must explain this share of that already, or no refinement
#: is tried (a sawtooth's coarse fit explains ≥ 0.9 of its refined share: the coarse grid is
#: 7.5° in phase and 1/32 of a frequency bin in period)
CLOCK_COARSE_SHARE = 0.6
#: the period is searched around this many periodogram peaks, each also as the 2nd … (1 +
#: CLOCK_SUBHARMONICS)th harmonic of the fundamental
CLOCK_PEAKS = 3
CLOCK_SUBHARMONICS = 2
#: refine_sawtooth's grid: ± this many quarter frequency bins around the last period, ± this
#: many cycles around its phase
CLOCK_REFINE_BINS = 4
CLOCK_REFINE_PHASE = 0.06
#: the scan of the candidates: at most this many samples (every k-th of a longer log), ...
CLOCK_SCAN_MAX_SAMPLES = 2000
#: ... periods per candidate (± 1.5 quarter frequency bins), phases;
#: then the coarse grid around the best: periods (± one scan step), phases
_N_PERIOD_SCAN = 7
_N_PHASE_SCAN = 24
_N_PERIOD = 9
_N_PHASE = 48


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


def peak_frequencies_hz(t_s: np.ndarray, x: np.ndarray, f_min_hz: float, f_max_hz: float,
                        n_peaks: int = 1, oversample: float = 4.0) -> np.ndarray:
    """Frequencies [Hz] of the `n_peaks` highest local maxima in [f_min_hz, f_max_hz] of the
    periodogram of :func:`periodogram` (zero-mean series x (n,) at times t_s (n,), t_s ≥ 0),
    highest first, on a grid `oversample` × finer than the resolution 1/span, by FFT in
    O(M log M), M = 16·span·f_max:

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
    sel = np.flatnonzero((freqs >= f_min_hz) & (freqs <= f_max_hz))
    if sel.size == 0:
        return np.array([0.5 * (f_min_hz + f_max_hz)])
    p = power[sel]
    # local maxima (the band's ends count when they rise towards them)
    left = np.r_[True, p[1:] > p[:-1]]
    right = np.r_[p[:-1] >= p[1:], True]
    peaks = np.flatnonzero(left & right)
    top = peaks[np.argsort(p[peaks], kind="stable")[::-1][:n_peaks]]
    return freqs[sel][top]


def peak_frequency_hz(t_s: np.ndarray, x: np.ndarray, f_min_hz: float, f_max_hz: float,
                      oversample: float = 4.0) -> float:
    """Frequency [Hz] of the highest peak of :func:`peak_frequencies_hz`."""
    return float(peak_frequencies_hz(t_s, x, f_min_hz, f_max_hz, 1, oversample)[0])


def _columns(nuisance: np.ndarray, n: int) -> np.ndarray:
    """The nuisance columns as an (n, m) array (a (n,) vector is one column; n may be 0)."""
    z = np.asarray(nuisance, dtype=float)
    return z.reshape(n, 1) if z.ndim == 1 else z.reshape(n, -1 if n else z.shape[-1])


def _basis(n: int, nuisance: np.ndarray | None) -> np.ndarray:
    """(n, q) orthonormal basis of the constant and the nuisance columns (n, m) (QR; columns
    that add nothing new are dropped)."""
    cols = np.ones((n, 1)) if nuisance is None else np.column_stack([np.ones(n), nuisance])
    q, rdiag = np.linalg.qr(cols)
    keep = np.abs(np.diag(rdiag)) > 1e-9 * max(1.0, float(np.max(np.abs(np.diag(rdiag)))))
    return q[:, keep]


def _fit_grid_dense(t: np.ndarray, r: np.ndarray, periods: np.ndarray, phases: np.ndarray,
                    nuisance: np.ndarray | None = None) -> tuple:
    """:func:`_fit_grid` the obvious way, on the whole (P, Φ, n) array of frac(t/P − φ) projected
    off the constant and the nuisance columns: the slow reference of the tests."""
    u = t[None, None, :] / periods[:, None, None] - phases[None, :, None]
    s = u - np.floor(u)
    q = _basis(t.size, nuisance)
    rq = r - q @ (q.T @ r)
    sp = s - np.einsum("pfq,nq->pfn", np.einsum("pfn,nq->pfq", s, q), q)
    sxx = np.einsum("pfn,pfn->pf", sp, sp)
    sxy = np.einsum("pfn,n->pf", sp, rq)
    return _grid_best(t, r, rq, sxx, sxy, periods, phases, nuisance)


def _grid_best(t, r, rq, sxx, sxy, periods, phases, nuisance, need_offset: bool = True) -> tuple:
    """The best (P, φ) of a grid from S_xx, S_xy (P, Φ) of the projected sawtooth and the
    projected residuals rq: (rss, P, φ, A, c, n), c the constant of the least-squares fit of
    r − A·s on [1, nuisance] (NaN unless need_offset: a scan that only picks the period)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(sxx > 1e-12, sxy / sxx, 0.0)
    # rss = Σ rq² − A² Sxx
    rss = float(rq @ rq) - a * a * sxx
    i, j = np.unravel_index(int(np.argmin(rss)), rss.shape)
    amp, period, phase = float(a[i, j]), float(periods[i]), float(phases[j])
    if not need_offset:
        return float(rss[i, j]), period, phase, amp, math.nan, t.size
    u = t / period - phase
    rest = r - amp * (u - np.floor(u))
    cols = np.ones((t.size, 1)) if nuisance is None else np.column_stack([np.ones(t.size), nuisance])
    coef = np.linalg.lstsq(cols, rest, rcond=None)[0]
    return float(rss[i, j]), period, phase, amp, float(coef[0]), t.size


def _fit_grid(t: np.ndarray, r: np.ndarray, periods: np.ndarray, phases: np.ndarray,
              nuisance: np.ndarray | None = None, q: np.ndarray | None = None, need_offset: bool = True) -> tuple:
    """Least squares r ≈ c + A·frac(t/P − φ) + Z β over the (P, φ) grid (Z: the (n, m) nuisance
    columns, or none); (rss, P, φ, A, c, n) of the best (c NaN unless need_offset). q: _basis(n,
    nuisance) when the caller has it already.

    With Q (n, q) an orthonormal basis of [1, Z] (_basis), the sawtooth s and r projected off it,
    ř = r − Q Qᵀ r:  A = S_xy / S_xx,  S_xy = sᵀ ř,  S_xx = sᵀ s − |Qᵀ s|²,  rss = |ř|² − A² S_xx.
    Per period, with u_n = frac(t_n/P) and the phases in [0, 1):
    s_n = frac(u_n − φ) = u_n − φ + [u_n < φ], so with the sums over the samples below φ,
    k(φ) = #{u_n < φ}, U(φ) = Σ_(u_n<φ) u_n, Ř(φ) = Σ_(u_n<φ) ř_n, Q(φ) = Σ_(u_n<φ) q_n (Σ ř = 0),

        Σ s² = Σu² − 2φΣu + nφ² + 2(U − kφ) + k,   sᵀ ř = Σ u ř + Ř,   Qᵀ s = Σ u q − φ Σ q + Q

    Those sums come from one histogram per quantity: sample n of period P falls in bin
    b = #{φ_j ≤ u_n} of the sorted phases, u_n < φ_(j) ⟺ b ≤ j, and a prefix sum over the Φ + 1
    bins gives them at every phase. O(P·n·(q + 3) + P·Φ·q) instead of the O(P·Φ·n·q) of frac on
    the whole grid (_fit_grid_dense, the same numbers up to rounding)."""
    n = t.size
    if q is None:
        q = _basis(n, nuisance)
    rq = r - q @ (q.T @ r)
    ph = np.mod(np.asarray(phases, dtype=float), 1.0)
    n_p, n_f = periods.size, ph.size
    order = np.argsort(ph, kind="stable")
    u = t[None, :] / periods[:, None]
    u -= np.floor(u)
    # each (period, sample)'s bin, offset by period: one bincount histograms every period
    b = np.searchsorted(ph[order], u, side="right")
    b += (np.arange(n_p) * (n_f + 1))[:, None]
    b = b.ravel()
    cols = np.column_stack([rq, q])  # (n, 1 + q): ř, Q
    n_c = cols.shape[1]
    w = np.empty((2 + n_c, n_p * n))
    w[0] = 1.0
    w[1] = u.ravel()
    w[2:].reshape(n_c, n_p, n)[...] = cols.T[:, None, :]
    hist = np.stack([np.bincount(b, weights=wi, minlength=n_p * (n_f + 1)) for wi in w])
    below = np.empty((2 + n_c, n_p, n_f))
    below[:, :, order] = np.cumsum(hist.reshape(2 + n_c, n_p, n_f + 1), axis=2)[:, :, :n_f]
    k, uk, kc = below[0], below[1], np.moveaxis(below[2:], 0, 2)  # (P, Φ), (P, Φ), (P, Φ, 1 + q)
    su = u.sum(axis=1)[:, None]
    su2 = np.einsum("pn,pn->p", u, u)[:, None]
    s2 = su2 - 2.0 * ph[None, :] * su + n * ph[None, :] ** 2 + 2.0 * (uk - k * ph) + k
    suc = u @ cols  # Σ u ř, Σ u q (P, 1 + q)
    tot = cols.sum(axis=0)  # Σ ř (0), Σ q
    proj = suc[:, None, :] - ph[None, :, None] * tot[None, None, :] + kc
    sxy = proj[:, :, 0]
    sxx = s2 - np.einsum("pfq,pfq->pf", proj[:, :, 1:], proj[:, :, 1:])
    return _grid_best(t, r, rq, sxx, sxy, periods, phases, nuisance, need_offset)


def _finite_samples(t_s: np.ndarray, resid_m: np.ndarray, nuisance: np.ndarray | None) -> tuple:
    """(t (m,), r (m,), z (m, c) or None): the samples whose time, residual and nuisance columns
    (_columns of nuisance) are all finite."""
    t = np.asarray(t_s, dtype=float)
    r = np.asarray(resid_m, dtype=float)
    ok = np.isfinite(t) & np.isfinite(r)
    z = None
    if nuisance is not None:
        z = _columns(nuisance, t.size)
        ok &= np.all(np.isfinite(z), axis=1)
        z = z[ok]
    return t[ok], r[ok], z


def undetected_sawtooth_bias(sigma_m: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation [m] of the range bias a commercial UE's clock sawtooth leaves
    when it is too small for fit_sawtooth to accept, at range noise σ [m] (scalar or (K,)).

    A sawtooth A·frac(·) has variance A²/12, so it explains the share c = CLOCK_MIN_EXPLAINED of
    the residual variance σ² + A²/12 (the long-log floor of the acceptance test) from

        A_det = σ √(12 c / (1 − c))        (σ = 3 m: 4.37 m)

    on. Below that it is not tracked and its mean A/2 is a bias of b ~ U[0, A_det/2] (A uniform
    on [0, A_det]): mean A_det/4, standard deviation A_det/(4√3).
    """
    a_det = np.asarray(sigma_m, dtype=float) * math.sqrt(12.0 * CLOCK_MIN_EXPLAINED / (1.0 - CLOCK_MIN_EXPLAINED))
    return a_det / 4.0, a_det / (4.0 * math.sqrt(3.0))


def fit_sawtooth(t_s: np.ndarray, resid_m: np.ndarray, nuisance: np.ndarray | None = None) -> SawtoothFit | None:
    """Fit a clock sawtooth to one user's range residuals.

    t_s: (n,) measurement times [s]; resid_m: (n,) measured minus modelled range [m] (no bias
    removed); nuisance: optional (n, m) columns the residuals may also hold, fitted with the
    sawtooth (the estimator passes the range's gradient in the user's position: a sawtooth seen
    through a position the solve moved to absorb part of it). Returns None when the times cover
    fewer than CLOCK_MIN_PERIODS of any period with CLOCK_MIN_SAMPLES_PER_PERIOD samples, or when
    the best sawtooth explains less than max(CLOCK_MIN_EXPLAINED, CLOCK_NULL_EXPLAINED_N / n) of
    the residual variance (after the constant and the nuisance columns).

    The period is searched around CLOCK_PEAKS periodogram peaks and their CLOCK_SUBHARMONICS
    subharmonics: a sawtooth's fundamental is its strongest line in theory, but over a hundred
    unevenly timed samples its second harmonic (or a slow wander of the position's error) can
    outshine it (seen on simulated missions: P = 7.5 s and 8.5 s fitted for a 15 s sawtooth, the
    user 3–11 m off).
    """
    t, r, z = _finite_samples(t_s, resid_m, nuisance)
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
    q = _basis(t.size, z)
    rq = r - q @ (q.T @ r)
    total = float(rq @ rq)
    if total <= 0:
        return None
    # candidate fundamentals: the periodogram's highest peaks (grid 4× finer than the frequency
    # resolution 1/span) and their subharmonics, each with a (P, φ) grid of ± 1.5 steps df
    df = 1.0 / (4.0 * span)
    peaks = peak_frequencies_hz(t, rq, f_min, f_max, CLOCK_PEAKS)
    cands: list[float] = []
    for f in (f0 / h for f0 in peaks for h in range(1, CLOCK_SUBHARMONICS + 2)):
        if f >= f_min - df and all(abs(f - c) > 2.0 * df for c in cands):
            cands.append(f)
    # a scan of every candidate on a coarser grid (on every ⌈n / CLOCK_SCAN_MAX_SAMPLES⌉-th
    # sample: it only picks the candidate), then the coarse grid around the best of them
    # every grid stays at f ≥ f_min: a period the samples span fewer than CLOCK_MIN_PERIODS times
    # is not pinned by them (seen: a 15 s sawtooth over 41 s fitted as 25.3 s, the user 5.4 m off)
    periods = np.concatenate([1.0 / np.linspace(max(f - 1.5 * df, f_min), max(f + 1.5 * df, f_min), _N_PERIOD_SCAN)
                              for f in cands])
    every = -(-t.size // CLOCK_SCAN_MAX_SAMPLES)
    sub = slice(None, None, every)
    _, p_scan, _, _, _, _ = _fit_grid(t[sub], r[sub], periods, np.arange(_N_PHASE_SCAN) / _N_PHASE_SCAN,
                                      None if z is None else z[sub], q if every == 1 else None, need_offset=False)
    f_scan = 1.0 / p_scan
    step = 3.0 * df / (_N_PERIOD_SCAN - 1)
    periods = 1.0 / np.linspace(max(f_scan - step, f_min), max(f_scan + step, f_min), _N_PERIOD)
    phases = np.arange(_N_PHASE) / _N_PHASE
    rss, p_best, ph_best, _, _, _ = _fit_grid(t, r, periods, phases, z, q, need_offset=False)
    need = max(CLOCK_MIN_EXPLAINED, CLOCK_NULL_EXPLAINED_N / t.size)
    if 1.0 - rss / total < CLOCK_COARSE_SHARE * need:
        # the refinement (± one coarse step) cannot make up for that much: no sawtooth
        return None
    dp = 2.0 * step * p_best**2 / (_N_PERIOD - 1)
    periods = np.minimum(p_best + np.linspace(-dp, dp, 21), 1.0 / f_min)
    phases = ph_best + np.linspace(-1.0, 1.0, 21) / _N_PHASE
    rss, p_best, ph_best, amp, off, _ = _fit_grid(t, r, periods, phases, z, q)
    explained = 1.0 - rss / total
    if explained < need:
        return None
    # back to absolute time: frac((t − t0)/P − φ) = frac(t/P − (φ + t0/P))
    phase = (ph_best + t0 / p_best) % 1.0
    return SawtoothFit(p_best, phase, amp, off, explained)


def refine_sawtooth(t_s: np.ndarray, resid_m: np.ndarray, prev: SawtoothFit,
                    nuisance: np.ndarray | None = None) -> SawtoothFit:
    """Re-fit a tracked sawtooth near its last (P, φ) on new residuals (more samples, a moved
    solution): a (1/P, φ) grid of ± CLOCK_REFINE_BINS quarter frequency bins df = 1/(4·span)
    around 1/prev.period_s and ± CLOCK_REFINE_PHASE cycles around its phase at the samples'
    middle time, then a finer grid around the best. Shapes and nuisance as in fit_sawtooth
    (non-finite samples dropped); prev itself when fewer than 16 samples remain or they span
    fewer than CLOCK_MIN_PERIODS of its period (fit_sawtooth's own rule: such samples cannot
    pin a period, and the grid 1/P0 ± CLOCK_REFINE_BINS·df would reach zero frequency, an
    infinite period, at span ≤ P0). explained: as in fit_sawtooth (no acceptance test: the
    user's sawtooth was accepted when first fitted)."""
    t, r, z = _finite_samples(t_s, resid_m, nuisance)
    p0 = prev.period_s
    if t.size < 16 or not (math.isfinite(p0) and p0 > 0 and math.isfinite(prev.phase)):
        return prev
    span = float(t.max() - t.min())
    if span < CLOCK_MIN_PERIODS * p0:
        return prev
    tm = 0.5 * float(t.min() + t.max())
    tc = t - tm
    # the phase at the middle time: frac(t/P − φ) = frac((t − tm)/P − (φ − tm/P))
    ph0 = (prev.phase - tm / p0) % 1.0
    # span ≥ 2 P0: 1/P0 − CLOCK_REFINE_BINS·df ≥ 1/(2 P0) > 0
    df = 1.0 / (4.0 * span)
    f0 = 1.0 / p0
    periods = 1.0 / np.linspace(f0 - CLOCK_REFINE_BINS * df, f0 + CLOCK_REFINE_BINS * df, 2 * CLOCK_REFINE_BINS + 1)
    phases = ph0 + np.linspace(-CLOCK_REFINE_PHASE, CLOCK_REFINE_PHASE, 25)
    q = _basis(t.size, z)
    rq = r - q @ (q.T @ r)
    total = float(rq @ rq)
    _, p_best, ph_best, _, _, _ = _fit_grid(tc, r, periods, phases, z, q, need_offset=False)
    # the finer grid: ± one step df in frequency around the best (1/p_best − df ≥ 1/(4 P0) > 0)
    periods = 1.0 / (1.0 / p_best + np.linspace(-df, df, 11))
    phases = ph_best + np.linspace(-1.0, 1.0, 11) * (2.0 * CLOCK_REFINE_PHASE / 24)
    rss, p_best, ph_best, amp, off, _ = _fit_grid(tc, r, periods, phases, z, q)
    explained = 1.0 - rss / total if total > 0 else 0.0
    return SawtoothFit(p_best, (ph_best + tm / p_best) % 1.0, amp, off, explained)
