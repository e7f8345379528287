"""The online filter step when GPS factors link consecutive keyframes (Gauss–Markov GPS, estimator.gps).

With white GPS a new keyframe touches only the users, and the window is summarized by the users'
information S (estimator.online_filter.filter_step). A Gauss–Markov GPS factor links keyframe n to
keyframe n − 1 as well, so the summary keeps the last keyframe: the information Ŝ of
z = [x_l (3), Θ (K·p)] (x_l the window's last keyframe), every older keyframe eliminated. The
keyframe part of the normal matrix is a block-tridiagonal chain, so this is one more link of the
same elimination the batch solver does (estimator.schur), one keyframe at a time:

    variables v = [x_l, x_n, Θ];  J = blockdiag(Ŝ on (x_l, Θ)) + new factors,  g = −∇ of them
    J Δv = g,   Ŝ' = Schur complement of J over x_l   (the information of [x_n, Θ])

The new keyframe starts at its Gauss–Markov prediction x_n⁰ = x̂_n + φ_n (x_l − x̂_l), where its
GPS factor has zero residual (it adds information, no pull); its ranges are linearized there.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solveh_banded

from estimator.linearize import Linearization
from estimator.schur import banded_blocks


def last_keyframe_information(lin: Linearization, s: np.ndarray) -> np.ndarray:
    """(3 + P, 3 + P) information of z = [x_l, Θ] (x_l the last of the N keyframes of `lin`),
    all other keyframes eliminated, with the users' marginal information equal to s (P, P).

    With r the other keyframes, X = H_rr⁻¹ E (E: the 3 columns of H_rl, nonzero only at keyframe
    N − 2, the scalar·I link off[N−2]):

        L = H_ll − H_lr X,   C = H_lθ − H_lr H_rr⁻¹ H_rθ = H_lθ − Xᵀ H_rθ

    and the users' block T = s + Cᵀ L⁻¹ C, so that eliminating x_l again gives back s (the S of
    the solve, which may be the observed information or noise-scaled: solve.observed_s).
    H_rr⁻¹ by a banded Cholesky over the chain (3 right-hand sides), O(N).
    """
    hxx, off, hxu = lin.hxx, lin.off, lin.hxu
    n, p_all = hxu.shape[0], hxu.shape[2]
    h_ll = hxx[-1].copy()
    h_lt = hxu[-1].copy()
    if n > 1 and off is not None and off[-1] != 0.0:
        r = n - 1
        # H_rr X = H_rl: the link sits in the rows of keyframe r − 1 only
        rhs = np.zeros((3 * r, 3))
        rhs[-3:] = np.eye(3) * off[-1]
        x = solveh_banded(banded_blocks(hxx[:r], off[: r - 1]), rhs, lower=False)
        # L = H_ll − H_lr X,  C = H_lθ − Xᵀ H_rθ (H_lr = H_rlᵀ)
        h_ll -= off[-1] * x[-3:]
        h_lt -= x.T @ hxu[:r].reshape(3 * r, p_all)
    out = np.empty((3 + p_all, 3 + p_all))
    out[:3, :3] = 0.5 * (h_ll + h_ll.T)
    out[:3, 3:] = h_lt
    out[3:, :3] = h_lt.T
    # T = s + Cᵀ L⁻¹ C
    t = s + h_lt.T @ np.linalg.solve(out[:3, :3], h_lt)
    out[3:, 3:] = 0.5 * (t + t.T)
    return out


def chain_step(
    s_aug: np.ndarray, phi: float, w_gps: float, h_nn: np.ndarray, g_n: np.ndarray, b: np.ndarray,
    cols: np.ndarray, h_tt: np.ndarray, g_t: np.ndarray, w_m: float = 0.0, delta_m: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One keyframe onto the chain summary (module docstring).

    s_aug: (3 + P, 3 + P) information of [x_l, Θ]; phi: φ_n of the GPS link; w_gps: its weight
    W_n = 1/(σ_gps² (1 − φ_n²)); the new keyframe's ranges, linearized at x_n⁰: h_nn (3, 3)
    Σ w J_xᵀJ_x, g_n (3,) −Σ ψ J_x, b (3, m) H_nθ on the m columns `cols` of Θ they touch,
    h_tt (m, m) their H_θθ, g_t (m,) −Σ ψ J_θ. The GPS factor (zero residual at x_n⁰) adds

        H_nn += W I,  H_ll += φ² W I,  H_nl = −φ W I

    and a relative-motion factor linking x_n to x_l (w_m = 1/σ_m² > 0; delta_m (3,) its residual
    δ = x_n⁰ − x_l − ô_n at the linearization point), ½ W_m ||x_n − x_l − ô_n||², adds

        H_nn += W_m I,  H_ll += W_m I,  H_nl −= W_m I,  g_n −= W_m δ,  g_l += W_m δ

    Returns (Δx_l (3,), Δx_n (3,), ΔΘ (P,), Ŝ' (3 + P, 3 + P) the information of [x_n, Θ],
    cov (P, P) the users' covariance, (Ŝ'⁻¹)_ΘΘ). Raises numpy.linalg.LinAlgError when J is not
    positive definite.
    """
    p_all = s_aug.shape[0] - 3
    dim = 6 + p_all
    # v = [x_l (0:3), x_n (3:6), Θ (6:)]
    jm = np.zeros((dim, dim))
    jm[:3, :3] = s_aug[:3, :3]
    jm[:3, 6:] = s_aug[:3, 3:]
    jm[6:, :3] = s_aug[3:, :3]
    jm[6:, 6:] = s_aug[3:, 3:]
    d = np.arange(3)
    jm[d, d] += phi * phi * w_gps
    jm[d, d + 3] = jm[d + 3, d] = -phi * w_gps
    jm[3:6, 3:6] = h_nn
    jm[d + 3, d + 3] += w_gps
    c6 = cols + 6
    jm[3:6, c6] = b
    jm[c6, 3:6] = b.T
    jm[c6[:, None], c6] += h_tt
    g = np.zeros(dim)
    g[3:6] = g_n
    g[c6] = g_t
    if w_m:
        jm[d, d] += w_m
        jm[d + 3, d + 3] += w_m
        jm[d, d + 3] -= w_m
        jm[d + 3, d] -= w_m
        g[:3] += w_m * delta_m
        g[3:6] -= w_m * delta_m
    chol = np.linalg.cholesky(jm)
    dv = np.linalg.solve(chol.T, np.linalg.solve(chol, g))
    # Ŝ' = J_kk − J_kl J_ll⁻¹ J_lk over k = [x_n, Θ]
    j_lk = jm[:3, 3:]
    s_new = jm[3:, 3:] - j_lk.T @ np.linalg.solve(jm[:3, :3], j_lk)
    s_new = 0.5 * (s_new + s_new.T)
    cov = np.linalg.inv(s_new)[3:, 3:]
    return dv[:3], dv[3:6], dv[6:], s_new, 0.5 * (cov + cov.T)


def chain_marginal_prior(lin: Linearization, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Fold keyframes 0..m−1 of a chain into a Gaussian prior on z = [x_m (3), Θ (P)].

    lin: the linearization (at the current estimate) of only the factors that touch keyframes
    0..m−1 — their ranges, the GPS factors of keyframes 0..m (the last one links x_m), motion
    links up to x_m and the old prior — over keyframes 0..m and Θ. With r = 0..m−1 eliminated
    and ∇ = −g (lin holds g = −∇L):

        Λ = H_zz − H_zr H_rr⁻¹ H_rz,   c = ∇_z − H_zr H_rr⁻¹ ∇_r

    H_rz: the link off[m−1]·I from keyframe m−1 to x_m and H_rΘ; H_rr block-tridiagonal (banded
    Cholesky, O(m)). The same prior as folding the keyframes one by one at the same point.
    Returns (Λ (3 + P, 3 + P), c (3 + P,)).
    """
    hxx, off, hxu, huu, gx, gu = lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu
    p_all = huu.shape[0]
    link = 0.0 if off is None else float(off[m - 1])
    # H_rr⁻¹ [H_rΘ | H_rx_m | g_r]
    rhs = np.zeros((3 * m, p_all + 4))
    rhs[:, :p_all] = hxu[:m].reshape(3 * m, p_all)
    rhs[-3:, p_all : p_all + 3] = np.eye(3) * link
    rhs[:, -1] = gx[:m].ravel()
    sol = solveh_banded(banded_blocks(hxx[:m], np.zeros(m - 1) if off is None else off[: m - 1]), rhs, lower=False)
    info = np.empty((3 + p_all, 3 + p_all))
    h_rt = rhs[:, :p_all]
    # Λ_xx = H_mm − off² (H_rr⁻¹)_(m−1,m−1) ...: H_zr sol, with H_(x_m, r) nonzero at keyframe m−1 only
    info[:3, :3] = hxx[m] - link * sol[-3:, p_all : p_all + 3]
    info[:3, 3:] = hxu[m] - link * sol[-3:, :p_all]
    info[3:, :3] = info[:3, 3:].T
    info[3:, 3:] = huu - h_rt.T @ sol[:, :p_all]
    # c = ∇_z − H_zr H_rr⁻¹ ∇_r = −g_z + H_zr H_rr⁻¹ g_r
    grad = np.empty(3 + p_all)
    grad[:3] = -gx[m] + link * sol[-3:, -1]
    grad[3:] = -gu + h_rt.T @ sol[:, -1]
    return 0.5 * (info + info.T), grad
