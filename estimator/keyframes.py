"""Keyframe selection at Δ metres of flight (docs/design.md §5; the paper uses Δ = 2 m).

Keep the first position, then each position at least Δ (3-D distance) from the last *kept* one:

    keep n  ⇔  ||p_n − p_last_kept|| ≥ Δ
"""

from __future__ import annotations

import numpy as np

from uavloc.errors import EstimatorError


def _check_delta(delta_m: float) -> float:
    if isinstance(delta_m, bool) or not isinstance(delta_m, int | float | np.floating | np.integer):
        raise EstimatorError(f"delta_m must be a number, got {delta_m!r}")
    if not (np.isfinite(delta_m) and delta_m >= 0):
        raise EstimatorError(f"delta_m must be finite and >= 0, got {delta_m!r}")
    return float(delta_m)


def _check_pos(pos_enu_m: np.ndarray) -> np.ndarray:
    p = np.asarray(pos_enu_m, dtype=float)
    if p.ndim != 1 or p.shape[0] != 3:
        raise EstimatorError(f"position must have shape (3,), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise EstimatorError(f"position must be finite, got {p.tolist()}")
    return p


def select_keyframes(pos_enu_m: np.ndarray, delta_m: float) -> np.ndarray:
    """Indices of the keyframes to keep.

    pos_enu_m: (N, 3) UAV positions in time order [m, ENU]; delta_m: spacing Δ [m].
    Returns (M,) int indices into pos_enu_m, increasing, starting with 0 (empty when N = 0).
    """
    delta = _check_delta(delta_m)
    p = np.asarray(pos_enu_m, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise EstimatorError(f"pos_enu_m must have shape (N, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        bad = np.flatnonzero(~np.all(np.isfinite(p), axis=1))[0]
        raise EstimatorError(f"pos_enu_m row {bad} is not finite: {p[bad].tolist()}")
    sel = KeyframeSelector(delta)
    return np.array([i for i in range(p.shape[0]) if sel.accept(p[i])], dtype=np.intp)


class KeyframeSelector:
    """Online form of :func:`select_keyframes`: `accept(pos)` is True for a position to keep."""

    def __init__(self, delta_m: float):
        self.delta_m = _check_delta(delta_m)
        self._last: np.ndarray | None = None

    @property
    def last_kept_enu_m(self) -> np.ndarray | None:
        """(3,) the last accepted position [m, ENU], None before the first."""
        return None if self._last is None else self._last.copy()

    def accept(self, pos_enu_m: np.ndarray, force: bool = False) -> bool:
        """True (and remember it) when `pos_enu_m` (3,) is ≥ Δ from the last kept position, or when
        `force` (a keyframe the caller wants for another reason, e.g. time: the spacing counts from it)."""
        p = _check_pos(pos_enu_m)
        # keep ⇔ ||p − p_last|| ≥ Δ
        if force or self._last is None or float(np.linalg.norm(p - self._last)) >= self.delta_m:
            self._last = p
            return True
        return False
