"""Schur-complement solve of the block-arrow normal equations (docs/design.md §5).

Unknowns: keyframe positions x (N, 3) and packed user parameters θ (P,). Normal equations

    [ H_xx   H_xu ] [Δx]   [g_x]
    [ H_ux   H_uu ] [Δθ] = [g_u]

H_xx is block diagonal with 3×3 blocks (GPS priors + ranges) or, with relative-motion factors,
block tridiagonal whose off-diagonal blocks are −I/σ_m² (a scalar times I per pair). Eliminating
the keyframes:

    S   = H_uu − H_ux H_xx⁻¹ H_xu
    S Δθ = g_u − H_ux H_xx⁻¹ g_x
    Δx  = H_xx⁻¹ (g_x − H_xu Δθ)

Block diagonal: batched closed-form 3×3 inverses, O(N·P²). Block tridiagonal: a banded Cholesky
(`scipy.linalg.solveh_banded`, bandwidth 3) with P + 1 right-hand sides, O(N·P²) as well.
S⁻¹ is the exact marginal covariance of θ at the linearization point.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solveh_banded
from scipy.linalg.lapack import dposv as _dposv

from uavloc.errors import EstimatorError


def sym3_cofactors(a00, a01, a02, a11, a12, a22):
    """Cofactors and determinant of the symmetric 3×3 [[a00 a01 a02] [a01 a11 a12] [a02 a12 a22]].

    Works on Python floats (one matrix, no numpy overhead) and on equal-shape arrays (a stack).
    Returns (c00, c01, c02, c11, c12, c22, det), so that A⁻¹ = [[c00 c01 c02] [c01 c11 c12]
    [c02 c12 c22]] / det (adj(A) / det(A)).
    """
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    # det(A) by the first row's cofactor expansion
    return c00, c01, c02, c11, c12, c22, a00 * c00 + a01 * c01 + a02 * c02


def inv3_sym_batched(a: np.ndarray) -> np.ndarray:
    """Inverse of a stack of symmetric 3×3 matrices by cofactors: (N, 3, 3) -> (N, 3, 3).

    A⁻¹ = adj(A) / det(A); symmetric positive definite inputs expected (GPS prior makes them so).
    """
    c00, c01, c02, c11, c12, c22, det = sym3_cofactors(
        a[:, 0, 0], a[:, 0, 1], a[:, 0, 2], a[:, 1, 1], a[:, 1, 2], a[:, 2, 2])
    inv_det = 1.0 / det
    out = np.empty_like(a)
    out[:, 0, 0] = c00 * inv_det
    out[:, 0, 1] = out[:, 1, 0] = c01 * inv_det
    out[:, 0, 2] = out[:, 2, 0] = c02 * inv_det
    out[:, 1, 1] = c11 * inv_det
    out[:, 1, 2] = out[:, 2, 1] = c12 * inv_det
    out[:, 2, 2] = c22 * inv_det
    return out


def banded_blocks(hxx: np.ndarray, off: np.ndarray) -> np.ndarray:
    """Upper banded form (4, 3N) of the block-tridiagonal H_xx (scipy's ab[u + i − j, j] = a[i, j])."""
    n = hxx.shape[0]
    ab = np.zeros((4, 3 * n))
    ab[3] = hxx.reshape(n, 9)[:, ::4].ravel()
    ab[2].reshape(n, 3)[:, 1] = hxx[:, 0, 1]
    ab[2].reshape(n, 3)[:, 2] = hxx[:, 1, 2]
    ab[1].reshape(n, 3)[:, 2] = hxx[:, 0, 2]
    ab[0, 3:] = np.repeat(off, 3)
    return ab


def _chol3_batched(a: np.ndarray) -> tuple | None:
    """Cholesky factors H_nn = R_nᵀ R_n of a stack of symmetric 3×3 matrices (N, 3, 3), R_n upper:

        r00 = √a00,  r01 = a01/r00,  r02 = a02/r00,  r11 = √(a11 − r01²),
        r12 = (a12 − r01 r02)/r11,  r22 = √(a22 − r02² − r12²)

    Returns (r00, r01, r02, r11, r12, r22) as (N, 1) columns with the diagonal inverted
    (1/r00, 1/r11, 1/r22), or None unless every block is positive definite (each pivot positive
    and finite)."""
    a = a.reshape(a.shape[0], 9)
    p0 = a[:, 0:1]
    if not np.all(p0 > 0.0):
        return None
    r00 = np.sqrt(p0)
    i00 = 1.0 / r00
    r01 = a[:, 1:2] * i00
    r02 = a[:, 2:3] * i00
    p1 = a[:, 4:5] - r01 * r01
    if not np.all(p1 > 0.0):
        return None
    i11 = 1.0 / np.sqrt(p1)
    r12 = (a[:, 5:6] - r01 * r02) * i11
    p2 = a[:, 8:9] - r02 * r02 - r12 * r12
    if not (np.all(p2 > 0.0) and np.all(np.isfinite(p2))):
        return None
    return i00, r01, r02, i11, r12, 1.0 / np.sqrt(p2)


def _schur_chol(chol: tuple, hxu: np.ndarray, huu: np.ndarray, gx: np.ndarray, gu: np.ndarray) -> tuple:
    """schur_solve with block-diagonal H_xx given its Cholesky factors (_chol3_batched): with
    [G_n | y_n] = R_n⁻ᵀ [H_(n,θ) | g_n] (forward substitution),

        H_ux H_xx⁻¹ [H_xu | g_x] = Σ_n G_nᵀ [G_n | y_n]   (one symmetric product [G | y]ᵀ [G | y]),
        Δx_n = R_n⁻¹ (y_n − G_n Δθ)   (back substitution)

    the same numbers as the cofactor inverse's (schur_solve's other branch) up to rounding, at half
    the product's cost (a symmetric rank-3N update instead of a general product)."""
    i00, r01, r02, i11, r12, i22 = chol
    n, _, p = hxu.shape
    # [G | y] laid out (3, N, P + 1): row i of every keyframe contiguous
    gy = np.empty((3, n, p + 1))
    gy[:, :, :p] = hxu.transpose(1, 0, 2)
    gy[:, :, p] = gx.T
    g0, g1, g2 = gy[0], gy[1], gy[2]
    # forward substitution Rᵀ G = B: G0 = B0/r00, G1 = (B1 − r01 G0)/r11, G2 = (B2 − r02 G0 − r12 G1)/r22
    g0 *= i00
    g1 -= r01 * g0
    g1 *= i11
    g2 -= r02 * g0
    g2 -= r12 * g1
    g2 *= i22
    flat = gy.reshape(3 * n, p + 1)
    # [G | y]ᵀ [G | y]: numpy runs a product of an array with its own transpose as a symmetric
    # rank-k update (BLAS syrk), exactly symmetric
    gtg = flat.T @ flat
    # S = H_uu − H_ux H_xx⁻¹ H_xu
    s = huu - gtg[:p, :p]
    s = 0.5 * (s + s.T)
    # S Δθ = g_u − H_ux H_xx⁻¹ g_x
    rhs = gu - gtg[:p, p]
    _, du, info = _dposv(s, rhs)
    if info != 0:
        raise np.linalg.LinAlgError("Schur complement S is not positive definite")
    # z = y − G Δθ, then back substitution R Δx = z: Δx2 = z2/r22, Δx1 = (z1 − r12 Δx2)/r11,
    # Δx0 = (z0 − r01 Δx1 − r02 Δx2)/r00
    z = gy[:, :, p] - gy[:, :, :p] @ du
    d2 = z[2] * i22[:, 0]
    d1 = (z[1] - r12[:, 0] * d2) * i11[:, 0]
    d0 = (z[0] - r01[:, 0] * d1 - r02[:, 0] * d2) * i00[:, 0]
    return np.column_stack([d0, d1, d2]), du, s


def schur_solve(
    hxx: np.ndarray, off: np.ndarray | None, hxu: np.ndarray, huu: np.ndarray, gx: np.ndarray,
    gu: np.ndarray, lam: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve the (damped) normal equations by eliminating the keyframes.

    hxx: (N, 3, 3) diagonal blocks; off: (N−1,) scalar s_n of the off-diagonal block s_n·I between
    keyframes n and n+1, or None; hxu: (N, 3, P) coupling, hxu[n] = block H_(n,θ);
    huu: (P, P); gx: (N, 3); gu: (P,); lam: Levenberg–Marquardt damping, H + λ·diag(H).
    Returns (Δx (N, 3), Δθ (P,), S (P, P)) where S is the Schur complement of the damped system.
    Raises numpy.linalg.LinAlgError when S is not positive definite.
    """
    n = hxx.shape[0]
    p = huu.shape[0]
    if lam > 0.0:
        hxx = hxx.copy()
        hxx.reshape(n, 9)[:, ::4] *= 1.0 + lam
        huu = huu.copy()
        huu[np.diag_indices(p)] += lam * np.maximum(np.diag(huu), 1e-12)
    if off is None:
        chol = _chol3_batched(hxx)
        if chol is not None:
            return _schur_chol(chol, hxu, huu, gx, gu)
        hinv = inv3_sym_batched(hxx)
        if not np.all(np.isfinite(hinv)):
            raise EstimatorError("keyframe block of the normal matrix is singular")
        # [A_n | y_n] = H_nn⁻¹ [H_(n,θ) | g_n]  (A = H_xx⁻¹ H_xu, y = H_xx⁻¹ g_x), one batched
        # product per keyframe, in keyframe-major order (row 3n + i)
        bg = np.empty((n, 3, p + 1))
        bg[:, :, :p] = hxu
        bg[:, :, p] = gx
        ay = np.matmul(hinv, bg).reshape(3 * n, p + 1)
        b2 = bg[:, :, :p].reshape(3 * n, p)
    else:
        # banded solve in keyframe-major order (row 3n + i)
        b2 = hxu.reshape(3 * n, p)
        ay = solveh_banded(banded_blocks(hxx, off), np.column_stack([b2, gx.reshape(-1)]), lower=False)
    a2, y2 = ay[:, :p], ay[:, p]
    # H_ux H_xx⁻¹ [H_xu | g_x] in one product
    bay = b2.T @ ay
    # S = H_uu − H_ux H_xx⁻¹ H_xu
    s = huu - bay[:, :p]
    s = 0.5 * (s + s.T)
    # S Δθ = g_u − H_ux H_xx⁻¹ g_x
    rhs = gu - bay[:, p]
    # Cholesky factorization and solve in one LAPACK call; info > 0: S not positive definite
    _, du, info = _dposv(s, rhs)
    if info != 0:
        raise np.linalg.LinAlgError("Schur complement S is not positive definite")
    # Δx = H_xx⁻¹ (g_x − H_xu Δθ) = y − A Δθ
    dx = (y2 - a2 @ du).reshape(n, 3)
    return dx, du, s
