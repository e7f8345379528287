"""Central-difference derivatives, the reference every analytic Jacobian is tested against
(GTSAM's numericalDerivative in spirit):

    ∂f/∂x_j ≈ (f(x + h e_j) − f(x − h e_j)) / (2h)
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def numerical_jacobian(f: Callable[[np.ndarray], np.ndarray | float], x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """(m, n) Jacobian of f: R^n -> R^m (a scalar f gives (1, n)) at x (n,) by central differences."""
    x = np.asarray(x, dtype=float)
    f0 = np.atleast_1d(np.asarray(f(x), dtype=float))
    jac = np.empty((f0.size, x.size))
    for j in range(x.size):
        step = np.zeros_like(x)
        step[j] = h
        fp = np.atleast_1d(np.asarray(f(x + step), dtype=float))
        fm = np.atleast_1d(np.asarray(f(x - step), dtype=float))
        jac[:, j] = (fp - fm).ravel() / (2.0 * h)
    return jac
