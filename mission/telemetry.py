"""Telemetry ring buffer: the UAV position at a measurement's time (DESIGN.md §3).

A measurement's UAV position is the telemetry interpolated to the measurement time, not the last
fix. :class:`TelemetryBuffer` keeps the last `capacity` fixes (time [s], ENU position [m]) in a
numpy ring and interpolates linearly between the two fixes around a time:

    p(t) = p_i + (t − t_i) / (t_{i+1} − t_i) · (p_{i+1} − p_i),   t_i ≤ t ≤ t_{i+1}

Pure: times are whatever clock the caller uses (the controller uses mission seconds).
"""

from __future__ import annotations

import numpy as np

from uavloc.errors import MissionError


class TelemetryBuffer:
    """The last `capacity` position fixes. t: seconds (non-decreasing); pos_enu_m: (3,) [m]."""

    def __init__(self, capacity: int = 2048):
        if capacity < 2:
            raise MissionError(f"telemetry buffer capacity must be >= 2, got {capacity}")
        self.capacity = int(capacity)
        self._t = np.zeros(self.capacity)
        self._p = np.zeros((self.capacity, 3))
        self._n = 0  # fixes stored (≤ capacity)
        self._head = 0  # index of the next write

    def __len__(self) -> int:
        return self._n

    def append(self, t_s: float, pos_enu_m: np.ndarray) -> None:
        """Add a fix. A fix older than the newest is dropped (out-of-order UDP); an equal time replaces."""
        p = np.asarray(pos_enu_m, float)
        if p.shape != (3,) or not np.all(np.isfinite(p)) or not np.isfinite(t_s):
            raise MissionError(f"telemetry fix must be a finite time and 3 finite ENU numbers, got {t_s!r}, {p!r}")
        if self._n:
            last = (self._head - 1) % self.capacity
            if t_s < self._t[last]:
                return
            if t_s == self._t[last]:
                self._p[last] = p
                return
        self._t[self._head] = t_s
        self._p[self._head] = p
        self._head = (self._head + 1) % self.capacity
        self._n = min(self._n + 1, self.capacity)

    def _ordered(self) -> tuple[np.ndarray, np.ndarray]:
        """(t (n,), pos (n, 3)) oldest first."""
        if self._n < self.capacity:
            return self._t[: self._n], self._p[: self._n]
        idx = (np.arange(self.capacity) + self._head) % self.capacity
        return self._t[idx], self._p[idx]

    @property
    def last_t_s(self) -> float | None:
        return None if not self._n else float(self._t[(self._head - 1) % self.capacity])

    @property
    def first_t_s(self) -> float | None:
        return None if not self._n else float(self._ordered()[0][0])

    def latest(self) -> tuple[float, np.ndarray] | None:
        """(t, pos_enu_m) of the newest fix, or None."""
        if not self._n:
            return None
        i = (self._head - 1) % self.capacity
        return float(self._t[i]), self._p[i].copy()

    def covers(self, t_s: float) -> bool:
        """True when a fix exists at or after t_s (so interpolation needs no extrapolation)."""
        return self._n > 0 and self.last_t_s >= t_s

    def at(self, t_s: float, max_extrapolate_s: float = 0.0) -> np.ndarray:
        """Position (3,) [m] at time t_s, linearly interpolated between the fixes around it.

        Beyond the newest fix, extrapolates with the last two fixes' velocity for at most
        `max_extrapolate_s`; earlier than the oldest stored fix, or further ahead, is a
        :class:`MissionError`.
        """
        if not self._n:
            raise MissionError("no telemetry yet: cannot place a measurement")
        t, p = self._ordered()
        if t_s < t[0]:
            raise MissionError(f"time {t_s:.3f} s is older than the oldest telemetry fix {t[0]:.3f} s")
        if t_s <= t[-1]:
            i = int(np.searchsorted(t, t_s, side="right"))
            if i >= len(t):
                return p[-1].copy()
            if i == 0:  # t_s == t[0]
                return p[0].copy()
            t0, t1 = t[i - 1], t[i]
            w = 0.0 if t1 == t0 else (t_s - t0) / (t1 - t0)
            # p(t) = p_i + w · (p_{i+1} − p_i)
            return p[i - 1] + w * (p[i] - p[i - 1])
        ahead = t_s - t[-1]
        if ahead > max_extrapolate_s:
            raise MissionError(
                f"time {t_s:.3f} s is {ahead:.3f} s after the newest telemetry fix (limit {max_extrapolate_s:g} s)"
            )
        if len(t) < 2 or t[-1] == t[-2]:
            return p[-1].copy()
        # p(t) = p_n + (t − t_n) · v,  v = (p_n − p_{n−1}) / (t_n − t_{n−1})
        v = (p[-1] - p[-2]) / (t[-1] - t[-2])
        return p[-1] + ahead * v
