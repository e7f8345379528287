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


def _banded(hxx: np.ndarray, off: np.ndarray) -> np.ndarray:
    """Upper banded form (4, 3N) of the block-tridiagonal H_xx (scipy's ab[u + i − j, j] = a[i, j])."""
    n = hxx.shape[0]
    ab = np.zeros((4, 3 * n))
    ab[3] = hxx.reshape(n, 9)[:, ::4].ravel()
    ab[2].reshape(n, 3)[:, 1] = hxx[:, 0, 1]
    ab[2].reshape(n, 3)[:, 2] = hxx[:, 1, 2]
    ab[1].reshape(n, 3)[:, 2] = hxx[:, 0, 2]
    ab[0, 3:] = np.repeat(off, 3)
    return ab


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
        ay = solveh_banded(_banded(hxx, off), np.column_stack([b2, gx.reshape(-1)]), lower=False)
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
