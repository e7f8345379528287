"""The gNB host's clock against the controller's (issue 48): a pure estimator of their offset.

The T tracer's events and the gNB log's lines carry the gNB host's wall time (CLOCK_REALTIME);
the controller places a range by its own clocks. The two hosts' clocks differ by an offset θ (no
NTP, a drifting RTC, a container with another time). Each stamped item that arrives gives

    a_i = arrival_i − stamp_i = θ + l_i,        l_i ≥ 0 its latency (network, buffering, a late
                                                event loop)

so θ ≤ min_i a_i: the low envelope of a over recent items is the estimate, θ̂ = min a_i, too large
by the smallest latency seen. How well the envelope is pinned is the spread of its lowest quarter,

    u = q25(a) − min(a)                         (0 when a few items all arrived at once)

and a stamp s maps to the controller's wall time as s + θ̂, uncertain by u + the stamps' own
resolution. The offset is *bounded* once at least `min_samples` items arrived within the window
and u ≤ `max_spread_s`; before that, or when it is not, a stamped range cannot be placed in time
and is refused (counted by the caller). The window is the newest `window` items not older than
`horizon_s` (of arrival time): a stepped clock (NTP) is followed within the horizon.

No I/O, no clocks: the caller passes every instant.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

#: items kept (newest), and their age limit by arrival [s]
OFFSET_WINDOW = 256
OFFSET_HORIZON_S = 60.0
#: items needed before the offset counts as bounded
OFFSET_MIN_SAMPLES = 5
#: the envelope's spread above which the offset is not bounded [s]
OFFSET_MAX_SPREAD_S = 0.5


@dataclass(frozen=True)
class OffsetEstimate:
    """offset_s: θ̂ = min(arrival − stamp) [s] (controller wall − gNB wall); spread_s: u [s];
    samples: items in the window; bounded: usable to place stamps."""

    offset_s: float
    spread_s: float
    samples: int
    bounded: bool

    def to_dict(self) -> dict:
        return {"offset_s": round(self.offset_s, 6), "spread_s": round(self.spread_s, 6), "samples": self.samples,
                "bounded": self.bounded}


class ClockOffset:
    """Low-envelope estimator of the gNB host's clock offset (module docstring)."""

    def __init__(self, window: int = OFFSET_WINDOW, horizon_s: float = OFFSET_HORIZON_S,
                 min_samples: int = OFFSET_MIN_SAMPLES, max_spread_s: float = OFFSET_MAX_SPREAD_S) -> None:
        self.window, self.horizon_s = int(window), float(horizon_s)
        self.min_samples, self.max_spread_s = int(min_samples), float(max_spread_s)
        self._items: collections.deque[tuple[float, float]] = collections.deque(maxlen=self.window)
        #: stamped ranges refused because the offset was not bounded
        self.refused = 0

    def add(self, arrival_s: float, stamp_s: float) -> None:
        """One stamped item: its arrival (controller wall [s]) and its stamp (gNB wall [s])."""
        if not (math.isfinite(arrival_s) and math.isfinite(stamp_s)):
            return
        self._items.append((float(arrival_s), float(arrival_s) - float(stamp_s)))

    def estimate(self, now_s: float | None = None) -> OffsetEstimate | None:
        """The estimate over the window (items older than horizon_s before now_s, or before the
        newest arrival, left out); None before any item."""
        if not self._items:
            return None
        newest = self._items[-1][0] if now_s is None else float(now_s)
        while self._items and self._items[0][0] < newest - self.horizon_s:
            self._items.popleft()
        if not self._items:
            return None
        a = np.fromiter((x for _, x in self._items), float, len(self._items))
        # θ̂ = min a_i;  u = q25(a) − min a
        low = float(a.min())
        spread = float(np.percentile(a, 25)) - low
        return OffsetEstimate(low, spread, int(a.size), a.size >= self.min_samples and spread <= self.max_spread_s)

    def why_unbounded(self, est: OffsetEstimate | None) -> str:
        """Why `est` cannot place a stamp (for a GnbNoMeasurementError)."""
        if est is None:
            return "no time-stamped item from the gNB yet"
        if est.samples < self.min_samples:
            return f"only {est.samples} time-stamped item(s) from the gNB (need {self.min_samples})"
        return (f"arrival − stamp spreads {est.spread_s:.3f} s above its low envelope (limit "
                f"{self.max_spread_s:g} s)")


__all__ = ["ClockOffset", "OffsetEstimate"]
