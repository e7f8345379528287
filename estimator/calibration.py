"""Fit the range-noise model and a per-user range bias from ranges to users at known positions
(docs/design.md §4: σ(d) = s0 + a·exp(b·d); the clock sawtooth's mean is a positive range bias).

Model of one measurement i (user k = user_idx[i], slant distance d_i from the logged UAV position to
the known user position):

    e_i = r̂_i − d_i  ~  N(β_k, σ(d_i)² + σ_gps²)        σ(d) = s0 + a·exp(b·d)

σ_gps is the known per-axis noise of the logged UAV position; projected on any line of sight its
variance is σ_gps², so it is added to (not fitted into) the range variance. A sawtooth's own spread
(amplitude²/12 for a full-period ramp) is not separated from σ(d): it shows up in s0.

The fit is maximum likelihood: for given (s0, a, b) the biases have the closed form
β_k = Σ w_i e_i / Σ w_i with w_i = 1/var_i (profile likelihood), so the optimizer searches three
numbers only. A constant-σ model (a = 0) is fitted too; the exponential term is kept only when a
likelihood-ratio test says the data support it and the distances spread enough to see it.

Pure numpy/scipy: no files. Callers build the residuals (see :func:`range_residuals`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, special, stats

from estimator.noise import NoiseModel
from uavloc.errors import EstimatorError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationParams:
    """Settings of :func:`fit_range_noise`.

    min_points: fewest usable measurements for any fit.
    min_points_per_user: a user with fewer gets no bias (NaN) and its points are left out.
    min_points_exponential: fewest measurements to try the exponential term.
    min_distance_spread_m: the exponential term needs distances spread over at least this [m].
    sigma_gps_m: known per-axis noise of the logged UAV positions [m], added to the range variance.
    outlier_sigma: after a first fit, drop points whose |e − β| exceeds this many σ and refit
        (0: keep everything). NLoS excess delays are what this removes.
    lr_alpha: significance of the likelihood-ratio test exponential vs constant σ (2 dof).
    sawtooth: model each user's residual as a UE clock sawtooth plus Gaussian noise,
        e = c_k + U(0, A_k) + N(0, σ(d)² + σ_gps²), instead of a Gaussian around β_k; then the bias
        is the sawtooth's mean β_k = c_k + A_k/2 and the sawtooth's spread (A²/12) is kept out of σ.
    """

    min_points: int = 30
    min_points_per_user: int = 10
    min_points_exponential: int = 100
    min_distance_spread_m: float = 50.0
    sigma_gps_m: float = 0.0
    outlier_sigma: float = 5.0
    lr_alpha: float = 0.05
    sawtooth: bool = False


@dataclass(frozen=True)
class CalibrationResult:
    """A fitted noise model.

    s0_m, a_m, b_per_m: σ(d) = s0 + a·exp(b·d) [m] (a = b = 0 for the constant model).
    bias_m: (K,) range bias per user [m] (NaN for users without enough points).
    s0_std_m, a_std_m, b_std_per_m: standard errors from the inverse Hessian of the NLL (NaN when
        not estimable); bias_std_m: (K,).
    model: "exponential" or "constant".
    n_points: (K,) points used per user; n_outliers: points dropped as outliers.
    distance_min_m, distance_max_m: span of the distances used.
    nll: negative log-likelihood at the optimum; lr_statistic: 2·(NLL_const − NLL_exp) (NaN when
        the exponential model was not tried).
    messages: plain-language notes on what the data did or did not support.
    sawtooth_amplitude_m (K,), sawtooth_amplitude_std_m (K,): fitted sawtooth amplitudes A_k [m]
        with the `sawtooth` model (None otherwise).
    """

    s0_m: float
    a_m: float
    b_per_m: float
    bias_m: np.ndarray
    s0_std_m: float
    a_std_m: float
    b_std_per_m: float
    bias_std_m: np.ndarray
    model: str
    n_points: np.ndarray
    n_outliers: int
    distance_min_m: float
    distance_max_m: float
    nll: float
    lr_statistic: float
    sigma_gps_m: float
    messages: list[str] = field(default_factory=list)
    sawtooth_amplitude_m: np.ndarray | None = None
    sawtooth_amplitude_std_m: np.ndarray | None = None

    def range_sigma_m(self, d_m: np.ndarray | float) -> np.ndarray:
        """σ(d) = s0 + a·exp(b·d) [m] of the fitted model."""
        d = np.asarray(d_m, float)
        return self.s0_m + self.a_m * np.exp(self.b_per_m * d)

    def noise_model(self, sigma_gps_m: float | None = None) -> NoiseModel:
        """The fitted model as the estimator's :class:`NoiseModel` (σ_gps from the argument, else
        the one the fit assumed, else 1 m)."""
        sg = sigma_gps_m if sigma_gps_m is not None else (self.sigma_gps_m or 1.0)
        return NoiseModel(sigma_gps_m=float(sg), range_s0_m=float(self.s0_m), range_a_m=float(self.a_m),
                          range_b_per_m=float(self.b_per_m))


def range_residuals(
    uav_enu_m: np.ndarray, users_enu_m: np.ndarray, user_idx: np.ndarray, range_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Slant distance and range residual of each measurement.

    uav_enu_m: (M, 3) UAV positions [m, ENU]; users_enu_m: (K, 3) known user positions [m, ENU];
    user_idx: (M,) int; range_m: (M,) measured ranges [m].
    Returns d: (M,) true slant distances [m] and e = r̂ − d: (M,) [m].
    """
    uav = np.asarray(uav_enu_m, float).reshape(-1, 3)
    users = np.asarray(users_enu_m, float).reshape(-1, 3)
    idx = np.asarray(user_idx, int)
    r = np.asarray(range_m, float)
    if not (uav.shape[0] == idx.shape[0] == r.shape[0]):
        raise EstimatorError(
            f"range_residuals: {uav.shape[0]} UAV positions, {idx.shape[0]} user indices, {r.shape[0]} ranges"
        )
    if idx.size and (idx.min() < 0 or idx.max() >= users.shape[0]):
        raise EstimatorError(f"range_residuals: user index out of 0..{users.shape[0] - 1}")
    # d = ||x − u||,  e = r̂ − d
    d = np.linalg.norm(uav - users[idx], axis=1)
    return d, r - d


# ---------------------------------------------------------------------------------------------
# likelihood


def _profile_bias(e: np.ndarray, var: np.ndarray, idx: np.ndarray, k: int) -> np.ndarray:
    """β_k = Σ_{i∈k} e_i / var_i  /  Σ_{i∈k} 1 / var_i  (the bias MLE for fixed variances)."""
    w = 1.0 / var
    num = np.bincount(idx, weights=w * e, minlength=k)
    den = np.bincount(idx, weights=w, minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / den


def _nll(e: np.ndarray, d: np.ndarray, idx: np.ndarray, k: int, s0: float, a: float, b: float,
         sg2: float, bias: np.ndarray | None = None) -> float:
    """NLL = Σ ½ log(2π var_i) + ½ (e_i − β_k)² / var_i,  var_i = (s0 + a·exp(b·d_i))² + σ_gps²."""
    with np.errstate(over="ignore"):
        sig = s0 + a * np.exp(b * d)
    var = sig * sig + sg2
    if not np.all(np.isfinite(var)) or np.any(var <= 0):
        return math.inf
    beta = _profile_bias(e, var, idx, k) if bias is None else bias
    r = e - beta[idx]
    return float(0.5 * np.sum(np.log(2 * np.pi * var) + r * r / var))


def _fit_constant(e, d, idx, k, sg2):
    """Constant σ: β_k = mean of e over user k; s0² = mean (e − β)² − σ_gps² (closed form MLE)."""
    beta = np.bincount(idx, weights=e, minlength=k) / np.maximum(np.bincount(idx, minlength=k), 1)
    r = e - beta[idx]
    s0_sq = float(np.mean(r * r)) - sg2
    if s0_sq <= 0:
        s0 = 1e-3
        log.debug("constant fit: residual variance below σ_gps²; s0 clamped to %g m", s0)
    else:
        s0 = math.sqrt(s0_sq)
    return s0, beta, _nll(e, d, idx, k, s0, 0.0, 0.0, sg2, beta)


def _fit_exponential(e, d, idx, k, sg2, s0_const):
    """Maximise the profile likelihood over θ = (log s0, log a, b·D), D = max distance, from a grid
    of starts in b·D (the likelihood is multimodal in b). The gradient is analytic: at the profiled
    biases ∂NLL/∂β = 0, so only the variance terms contribute (envelope theorem)."""
    dscale = max(float(d.max()), 1.0)
    dn = d / dscale

    def f_and_grad(theta):
        if abs(theta[0]) > 30 or abs(theta[1]) > 60 or abs(theta[2]) > 60:
            return 1e300, np.zeros(3)
        s0, a = math.exp(theta[0]), math.exp(theta[1])
        with np.errstate(over="ignore"):
            ex = a * np.exp(theta[2] * dn)
        sig = s0 + ex
        var = sig * sig + sg2
        if not np.all(np.isfinite(var)):
            return 1e300, np.zeros(3)
        beta = _profile_bias(e, var, idx, k)
        r = e - beta[idx]
        nll = float(0.5 * np.sum(np.log(2 * np.pi * var) + r * r / var))
        # ∂NLL/∂var_i = ½ (1/var_i − r_i²/var_i²);  ∂var/∂σ = 2σ
        g_sig = (1.0 / var - r * r / (var * var)) * sig
        # ∂σ/∂log s0 = s0,  ∂σ/∂log a = a·e^{b d},  ∂σ/∂(bD) = a·e^{b d}·d/D
        grad = np.array([np.sum(g_sig) * s0, np.sum(g_sig * ex), np.sum(g_sig * ex * dn)])
        return nll, grad

    best = None
    for bd in (1.0, 3.0, 6.0, 10.0):
        for frac in (0.3,):
            # start: σ(D) ≈ s0 + a·e^{bD} splits the constant fit's σ between the two terms
            s0_start = max(s0_const * (1 - frac), 1e-2)
            a_start = max(s0_const * frac / math.exp(bd), 1e-6)
            x0 = np.array([math.log(s0_start), math.log(a_start), bd])
            # BFGS (not L-BFGS-B: its Fortran core is slow per call on a loaded machine); gtol in NLL units
            res = optimize.minimize(f_and_grad, x0, jac=True, method="BFGS",
                                    options={"maxiter": 300, "gtol": 1e-3})
            if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
                best = res
    s0, a, b = math.exp(best.x[0]), math.exp(best.x[1]), best.x[2] / dscale
    return s0, a, b, float(best.fun)


def _hessian(fun, x: np.ndarray, rel: float = 1e-4) -> np.ndarray:
    """Central-difference Hessian of a scalar function (steps relative to |x|, at least 1e-6)."""
    n = x.size
    h = np.maximum(np.abs(x) * rel, 1e-6)
    H = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            xpp = x.copy()
            xpp[i] += h[i]
            xpp[j] += h[j]
            xpm = x.copy()
            xpm[i] += h[i]
            xpm[j] -= h[j]
            xmp = x.copy()
            xmp[i] -= h[i]
            xmp[j] += h[j]
            xmm = x.copy()
            xmm[i] -= h[i]
            xmm[j] -= h[j]
            # ∂²f/∂x_i∂x_j ≈ (f(++) − f(+−) − f(−+) + f(−−)) / (4 h_i h_j)
            H[i, j] = H[j, i] = (fun(xpp) - fun(xpm) - fun(xmp) + fun(xmm)) / (4 * h[i] * h[j])
    return H


def _std_errors(e, d, idx, k, sg2, s0, a, b, bias, exponential: bool):
    """Standard errors from the inverse Hessian of the full NLL in (s0, [a, b,] β)."""
    if exponential:
        x = np.concatenate([[s0, a, b], bias])

        def fun(p):
            return _nll(e, d, idx, k, p[0], p[1], p[2], sg2, p[3:])
    else:
        x = np.concatenate([[s0], bias])

        def fun(p):
            return _nll(e, d, idx, k, p[0], 0.0, 0.0, sg2, p[1:])
    try:
        cov = np.linalg.inv(_hessian(fun, x))
        std = np.sqrt(np.where(np.diag(cov) > 0, np.diag(cov), np.nan))
    except np.linalg.LinAlgError:
        std = np.full(x.size, np.nan)
    if exponential:
        return std[0], std[1], std[2], std[3:]
    return std[0], math.nan, math.nan, std[1:]


# ---------------------------------------------------------------------------------------------
# sawtooth + Gaussian model


def _log_diff_ndtr(z1: np.ndarray, z2: np.ndarray) -> np.ndarray:
    """log(Φ(z1) − Φ(z2)) for z1 > z2, stable in both tails (upper tail through Φ(−z))."""
    up = z2 > 0
    hi = np.where(up, special.log_ndtr(-z2), special.log_ndtr(z1))
    lo = np.where(up, special.log_ndtr(-z1), special.log_ndtr(z2))
    with np.errstate(divide="ignore"):
        return hi + np.log1p(-np.exp(np.minimum(lo - hi, -1e-300)))


def _saw_nll(e, d, idx, k, sg2, s0, a, b, c, amp, grad: bool = False):
    """NLL of e_i = c_k + U(0, A_k) + N(0, σ_i²), σ_i² = (s0 + a·e^{b d_i})² + σ_gps²:

        p(e) = (Φ(z1) − Φ(z2)) / A,   z1 = (e − c)/σ,  z2 = (e − c − A)/σ

    With `grad`: also ∂NLL/∂σ_i-terms folded to (s0, a·e^{bd}, per-point) and ∂/∂c_k, ∂/∂A_k."""
    with np.errstate(over="ignore"):
        ex = a * np.exp(b * d)
    sig = s0 + ex
    st = np.sqrt(sig * sig + sg2)
    A = amp[idx]
    z1 = (e - c[idx]) / st
    z2 = (e - c[idx] - A) / st
    logp = _log_diff_ndtr(z1, z2)
    nll = float(np.sum(np.log(A) - logp))
    if not grad:
        return nll
    # g1 = φ(z1)/P, g2 = −φ(z2)/P  (∂ log P / ∂z1, ∂ log P / ∂z2)
    lphi1 = -0.5 * z1 * z1 - 0.5 * np.log(2 * np.pi)
    lphi2 = -0.5 * z2 * z2 - 0.5 * np.log(2 * np.pi)
    g1 = np.exp(lphi1 - logp)
    g2 = -np.exp(lphi2 - logp)
    # ∂NLL/∂c = (g1 + g2)/σ;  ∂NLL/∂A = g2/σ + 1/A;  ∂NLL/∂σ_tot = (g1 z1 + g2 z2)/σ
    dc = np.bincount(idx, weights=(g1 + g2) / st, minlength=k)
    dA = np.bincount(idx, weights=g2 / st + 1.0 / A, minlength=k)
    dsig = (g1 * z1 + g2 * z2) / st * (sig / st)  # ∂σ_tot/∂σ = σ/σ_tot
    return nll, dsig, ex, dc, dA


def _fit_sawtooth(e, d, idx, k, sg2, exponential: bool, s0_init, a_init, b_init, beta_init):
    """Maximum likelihood of the sawtooth model over θ = (log s0, [log a, b·D,] c_k, log A_k)."""
    dscale = max(float(d.max()), 1.0)
    dn = d / dscale
    n_sig = 3 if exponential else 1
    lo_A, hi_A = math.log(1e-3), math.log(1e3)

    def unpack(x):
        s0 = math.exp(x[0])
        a, bD = (math.exp(x[1]), x[2]) if exponential else (0.0, 0.0)
        return s0, a, bD, x[n_sig:n_sig + k], np.exp(x[n_sig + k:])

    def f(x):
        if abs(x[0]) > 10 or (exponential and (not -20 <= x[1] <= 10 or abs(x[2]) > 60)) \
                or np.any(x[n_sig + k:] < lo_A) or np.any(x[n_sig + k:] > hi_A):
            return 1e300, np.zeros_like(x)
        s0, a, bD, c, amp = unpack(x)
        nll, dsig, ex, dc, dA = _saw_nll(e, dn, idx, k, sg2, s0, a, bD, c, amp, grad=True)
        if not math.isfinite(nll):
            return 1e300, np.zeros_like(x)
        g = np.empty_like(x)
        g[0] = np.sum(dsig) * s0
        if exponential:
            g[1] = np.sum(dsig * ex)
            g[2] = np.sum(dsig * ex * dn)
        g[n_sig:n_sig + k] = dc
        g[n_sig + k:] = dA * amp
        return nll, g

    best = None
    for amp_frac in (1.0, 3.0):
        amp0 = np.full(k, max(amp_frac * s0_init, 0.05))
        for s0_frac in (0.7,):
            x0 = [math.log(max(s0_init * s0_frac, 1e-2))]
            if exponential:
                x0 += [math.log(max(a_init, 1e-6)), b_init * dscale]
            x0 = np.concatenate([x0, np.nan_to_num(beta_init) - amp0 / 2, np.log(amp0)])
            res = optimize.minimize(f, x0, jac=True, method="BFGS", options={"maxiter": 1000, "gtol": 1e-3})
            if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
                best = res
    s0, a, bD, c, amp = unpack(best.x)
    return s0, a, bD / dscale, np.asarray(c, float), np.asarray(amp, float), float(best.fun)


def _saw_std_errors(e, d, idx, k, sg2, exponential, s0, a, b, c, amp):
    """Standard errors of (s0, a, b), the biases c + A/2 and the amplitudes A from the inverse
    Hessian of the sawtooth NLL in natural parameters."""
    n_sig = 3 if exponential else 1
    x = np.concatenate([[s0, a, b][:n_sig], c, amp])

    def fun(p):
        aa, bb = (p[1], p[2]) if exponential else (0.0, 0.0)
        if p[0] <= 0 or np.any(p[n_sig + k:] <= 0):
            return math.inf
        return _saw_nll(e, d, idx, k, sg2, p[0], aa, bb, p[n_sig:n_sig + k], p[n_sig + k:])

    try:
        cov = np.linalg.inv(_hessian(fun, x))
    except np.linalg.LinAlgError:
        cov = np.full((x.size, x.size), np.nan)
    var = np.diag(cov)
    std = np.sqrt(np.where(var > 0, var, np.nan))
    ic = np.arange(n_sig, n_sig + k)
    ia = ic + k
    # Var(c + A/2) = Var c + Var A / 4 + Cov(c, A)
    vb = var[ic] + var[ia] / 4 + cov[ic, ia]
    bias_std = np.sqrt(np.where(vb > 0, vb, np.nan))
    s_std, a_std, b_std = (std[0], std[1], std[2]) if exponential else (std[0], math.nan, math.nan)
    return s_std, a_std, b_std, bias_std, std[ia]


# ---------------------------------------------------------------------------------------------
# the fit


def fit_range_noise(
    distance_m: np.ndarray,
    residual_m: np.ndarray,
    user_idx: np.ndarray,
    n_users: int,
    params: CalibrationParams | None = None,
) -> CalibrationResult:
    """Maximum-likelihood fit of σ(d) = s0 + a·exp(b·d) and a bias per user.

    distance_m: (M,) true slant distances [m]; residual_m: (M,) r̂ − d [m]; user_idx: (M,) ints in
    0..n_users−1. Raises :class:`EstimatorError` when the data cannot support even a constant σ
    (too few points); a missing exponential term is not an error but a note in `messages`.
    """
    p = params or CalibrationParams()
    d = np.asarray(distance_m, float).ravel()
    e = np.asarray(residual_m, float).ravel()
    idx = np.asarray(user_idx, int).ravel()
    if not (d.size == e.size == idx.size):
        raise EstimatorError(f"calibration: {d.size} distances, {e.size} residuals, {idx.size} user indices")
    finite = np.isfinite(d) & np.isfinite(e)
    d, e, idx = d[finite], e[finite], idx[finite]
    messages: list[str] = []
    k = int(n_users)
    counts = np.bincount(idx, minlength=k) if idx.size else np.zeros(k, int)
    keep_users = counts >= p.min_points_per_user
    for j in np.flatnonzero(~keep_users):
        if counts[j]:
            messages.append(f"user #{j} has only {counts[j]} ranges (< {p.min_points_per_user}): no bias fitted")
    mask = keep_users[idx] if idx.size else np.zeros(0, bool)
    d, e, idx = d[mask], e[mask], idx[mask]
    if d.size < p.min_points:
        raise EstimatorError(
            f"cannot calibrate: {d.size} usable range measurements to users with known positions "
            f"(need at least {p.min_points}, and {p.min_points_per_user} per user)"
        )
    sg2 = float(p.sigma_gps_m) ** 2

    n_out = 0
    for rnd in range(4):
        s0c, beta_c, nll_c = _fit_constant(e, d, idx, k, sg2)
        spread = float(d.max() - d.min())
        try_exp = d.size >= p.min_points_exponential and spread >= p.min_distance_spread_m
        fit_exp = _fit_exponential(e, d, idx, k, sg2, s0c) if try_exp else None
        if p.outlier_sigma <= 0 or rnd == 3:
            break
        if fit_exp is not None:
            sig = fit_exp[0] + fit_exp[1] * np.exp(fit_exp[2] * d)
            var = sig * sig + sg2
            beta = _profile_bias(e, var, idx, k)
        else:
            var = np.full(d.size, s0c * s0c + sg2)
            beta = beta_c
        out = np.abs(e - beta[idx]) > p.outlier_sigma * np.sqrt(var)
        if not out.any():
            break
        n_out += int(out.sum())
        d, e, idx = d[~out], e[~out], idx[~out]
        if d.size < p.min_points:
            raise EstimatorError(
                f"cannot calibrate: only {d.size} measurements left after removing {n_out} outliers "
                f"(> {p.outlier_sigma} σ) — NLoS or wrong user positions?"
            )
    if n_out:
        messages.append(f"{n_out} outliers (|e − bias| > {p.outlier_sigma} σ, NLoS?) left out of the fit")

    spread = float(d.max() - d.min())
    lr = math.nan
    model = "constant"
    if d.size < p.min_points_exponential:
        messages.append(
            f"only {d.size} measurements (< {p.min_points_exponential}): fitted a constant σ, not the "
            "exponential term"
        )
    elif spread < p.min_distance_spread_m:
        messages.append(
            f"distances span only {spread:.1f} m (< {p.min_distance_spread_m:g} m): the data cannot show "
            "how σ grows with distance; fitted a constant σ"
        )
    elif fit_exp is not None:
        s0e, ae, be, nll_e = fit_exp
        # LR = 2 (NLL_const − NLL_exp)  ~  χ²(2) under the constant model
        lr = 2.0 * (nll_c - nll_e)
        crit = float(stats.chi2.ppf(1 - p.lr_alpha, 2))
        if lr > crit:
            model = "exponential"
        else:
            messages.append(
                f"the exponential term is not supported by the data (likelihood ratio {lr:.2f} ≤ "
                f"{crit:.2f}): σ looks constant over {d.min():.0f}–{d.max():.0f} m"
            )

    if model == "exponential":
        s0, a, b, nll = s0e, ae, be, nll_e
        sig = s0 + a * np.exp(b * d)
        beta = _profile_bias(e, sig * sig + sg2, idx, k)
    else:
        s0, a, b, nll = s0c, 0.0, 0.0, nll_c
        beta = beta_c
    used = np.bincount(idx, minlength=k)
    beta = np.where(used > 0, beta, np.nan)
    s0_std, a_std, b_std, bias_std = _std_errors(
        e, d, idx, k, sg2, s0, a, b, np.nan_to_num(beta), model == "exponential"
    )
    bias_std = np.where(used > 0, bias_std, np.nan)
    amp = amp_std = None
    if p.sawtooth:
        s0, a, b, c, amp, nll = _fit_sawtooth(e, d, idx, k, sg2, model == "exponential", s0, a, b, beta)
        s0_std, a_std, b_std, bias_std, amp_std = _saw_std_errors(
            e, d, idx, k, sg2, model == "exponential", s0, a, b, c, amp)
        # bias = mean of the sawtooth: β = c + A/2
        beta = np.where(used > 0, c + amp / 2, np.nan)
        amp = np.where(used > 0, amp, np.nan)
        bias_std = np.where(used > 0, bias_std, np.nan)
        amp_std = np.where(used > 0, amp_std, np.nan)
    if model == "exponential" and (not np.isfinite(b_std) or b_std > 0.5 * abs(b)):
        messages.append(f"b is poorly determined (b = {b:.4g} ± {b_std:.2g} /m): fly a wider range of distances")
    return CalibrationResult(
        s0_m=float(s0), a_m=float(a), b_per_m=float(b), bias_m=beta,
        s0_std_m=float(s0_std), a_std_m=float(a_std), b_std_per_m=float(b_std), bias_std_m=bias_std,
        model=model, n_points=used, n_outliers=n_out,
        distance_min_m=float(d.min()), distance_max_m=float(d.max()), nll=float(nll),
        lr_statistic=float(lr), sigma_gps_m=float(p.sigma_gps_m), messages=messages,
        sawtooth_amplitude_m=amp, sawtooth_amplitude_std_m=amp_std,
    )
