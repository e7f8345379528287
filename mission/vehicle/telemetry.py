"""Telemetry ring buffer: the UAV position at a measurement's time (docs/design.md §3).

A measurement's UAV position is the telemetry interpolated to the measurement time, not the last
fix. :class:`TelemetryBuffer` keeps the last `capacity` fixes (time [s], ENU position [m]) in a
numpy ring and interpolates linearly between the two fixes around a time:

    p(t) = p_i + (t − t_i) / (t_{i+1} − t_i) · (p_{i+1} − p_i),   t_i ≤ t ≤ t_{i+1}

Pure: times are whatever clock the caller uses (the controller uses mission seconds).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import ClassVar

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

    def mean_since(self, t_s: float) -> np.ndarray | None:
        """Mean position (3,) [m] of the fixes at or after t_s (the newest fix alone when none
        is that recent), or None before the first fix. Averages white GPS noise out of the
        position of a hovering vehicle."""
        if not self._n:
            return None
        t, p = self._ordered()
        i = int(np.searchsorted(t, t_s, side="left"))
        return p[min(i, len(t) - 1) :].mean(axis=0)

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



class VehicleClock:
    """Mission seconds on the vehicle's clock (MAVLink boot time, `time_boot_ms`), from wall instants.

    The vehicle's boot time b at a wall instant t (monotonic) is extrapolated from the newest
    sample (m, b_m) with the rate r [vehicle s per wall s] fitted (least squares) over the samples
    of the last `window_s` wall seconds:

        b(t) = b_m + r · (t − m),   mission t = b(t) − b_0

    Before the first sample, mission t = (t − t0) · fallback_rate (the simulator's speedup, 1 for a
    real flight); b_0 is chosen at the first sample so that mission time is continuous there, and
    again after a vehicle reboot (boot time jumping back). Pure: the caller passes the instants.
    """

    def __init__(self, t0_mono_s: float, fallback_rate: float = 1.0, window_s: float = 5.0):
        if not (math.isfinite(fallback_rate) and fallback_rate > 0):
            raise MissionError(f"clock rate must be a positive number, got {fallback_rate!r}")
        self.t0_mono_s = float(t0_mono_s)
        self.fallback_rate = float(fallback_rate)
        self.window_s = float(window_s)
        self._samples: deque[tuple[float, float]] = deque()
        self._b0: float | None = None
        self._rate = self.fallback_rate

    @property
    def synced(self) -> bool:
        """True once the vehicle's time is known."""
        return self._b0 is not None

    @property
    def rate(self) -> float:
        """Vehicle seconds per wall second (the fallback rate until fitted over ≥ 1 wall second)."""
        return self._rate

    def mission_t(self, t_mono_s: float) -> float:
        if self._b0 is None:
            return (t_mono_s - self.t0_mono_s) * self.fallback_rate
        m, b = self._samples[-1]
        return b + self._rate * (t_mono_s - m) - self._b0

    def update(self, t_mono_s: float, boot_s: float) -> None:
        """A vehicle boot time `boot_s` [s] received at wall instant `t_mono_s`. Non-finite ignored."""
        if not (math.isfinite(t_mono_s) and math.isfinite(boot_s)):
            return
        if self._b0 is None or (self._samples and boot_s < self._samples[-1][1] - 1.0):
            before = self.mission_t(t_mono_s)  # continuity: first sample, or the vehicle rebooted
            self._samples.clear()
            self._b0 = boot_s - before
            self._samples.append((t_mono_s, boot_s))
            return
        if boot_s < self._samples[-1][1]:
            return  # out of order
        self._samples.append((t_mono_s, boot_s))
        while self._samples and self._samples[0][0] < t_mono_s - self.window_s:
            self._samples.popleft()
        m = np.array([s[0] for s in self._samples])
        if m[-1] - m[0] >= 1.0:
            b = np.array([s[1] for s in self._samples])
            # r = Σ (m − m̄)(b − b̄) / Σ (m − m̄)²
            dm = m - m.mean()
            r = float(dm @ (b - b.mean()) / (dm @ dm))
            if math.isfinite(r) and r > 0:
                self._rate = min(max(r, 1e-3), 1e4)


def odometer_dead_band_m(sigma_gps_m: float) -> float:
    """Dead band of the survey odometer [m]: max(5 m, 8 σ_gps).

    The difference of two GPS fixes has per-axis σ·√2, so its 3-D norm averages 2.26 σ and
    exceeds 5.7 σ once in a thousand: a band of 8 σ is crossed by flight, not by noise, and the
    noise it adds per counted step is O(σ²/band)."""
    return max(5.0, 8.0 * float(sigma_gps_m))


class Odometer:
    """Metres flown from noisy fixes: a step counts once the UAV is `dead_band_m` from the last
    counted point; :meth:`finish` counts the remainder (at a leg's end)."""

    def __init__(self, dead_band_m: float):
        if not dead_band_m > 0:
            raise MissionError(f"odometer dead band must be positive, got {dead_band_m!r}")
        self.dead_band_m = float(dead_band_m)
        self.total_m = 0.0
        self._counted: np.ndarray | None = None

    def start(self, pos_enu_m: np.ndarray) -> None:
        """Start counting from here (e.g. at the start of a leg), keeping the total."""
        self._counted = np.array(pos_enu_m, float)

    def update(self, pos_enu_m: np.ndarray) -> float:
        """Feed one fix; returns the total [m]."""
        p = np.asarray(pos_enu_m, float)
        if self._counted is None:
            self._counted = p.copy()
            return self.total_m
        step = float(np.linalg.norm(p - self._counted))
        if step >= self.dead_band_m:
            self.total_m += step
            self._counted = p.copy()
        return self.total_m

    def finish(self, pos_enu_m: np.ndarray) -> float:
        """Count the remainder up to this fix, whatever its length; returns the total [m]."""
        if self._counted is not None:
            self.total_m += float(np.linalg.norm(np.asarray(pos_enu_m, float) - self._counted))
        self._counted = np.array(pos_enu_m, float)
        return self.total_m


def odometer_m(track_enu_m: np.ndarray, dead_band_m: float) -> np.ndarray:
    """Cumulative metres flown along a (T, 3) track [m, ENU] by an :class:`Odometer`, the last
    point always counted. Returns (T,) [m], starting at 0."""
    track = np.asarray(track_enu_m, float)
    out = np.zeros(len(track))
    odo = Odometer(dead_band_m)
    for i, p in enumerate(track):
        out[i] = odo.finish(p) if i == len(track) - 1 else odo.update(p)
    return out


#: MAVLink GPS_FIX_TYPE (= MAVSDK's telemetry.FixType values 0..6) → what a ground station shows
GPS_FIX_NAMES = {0: "no GPS", 1: "no fix", 2: "2D fix", 3: "3D fix", 4: "DGPS", 5: "RTK float", 6: "RTK fixed",
                 7: "static", 8: "PPP"}


@dataclass(frozen=True)
class VehicleStatus:
    """The vehicle's health as a `telemetry` record carries it beside the position (docs/design.md
    §10), every field optional (None: the autopilot sent nothing yet, or a log written before
    these fields). The live view's instrument strip shows them.

    rel_alt_m: altitude above home [m] (the autopilot's relative altitude); heading_deg: [0, 360)
    from north; battery_pct: 0..100; battery_voltage_v: [V]; flight_mode: as the autopilot names
    it (MAVSDK's names, ArduCopter's custom mode names); armed; gps_fix_type: MAVLink GPS_FIX_TYPE
    (0..8, GPS_FIX_NAMES); gps_satellites: satellites visible.
    """

    rel_alt_m: float | None = None
    heading_deg: float | None = None
    battery_pct: float | None = None
    battery_voltage_v: float | None = None
    flight_mode: str | None = None
    armed: bool | None = None
    gps_fix_type: int | None = None
    gps_satellites: int | None = None

    #: record field → (lowest, highest) for the numbers
    RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "rel_alt_m": (-1000.0, 100_000.0), "heading_deg": (0.0, 360.0), "battery_pct": (0.0, 100.0),
        "battery_voltage_v": (0.0, 1000.0), "gps_fix_type": (0, 8), "gps_satellites": (0, 255)}
    INTEGERS: ClassVar[tuple[str, ...]] = ("gps_fix_type", "gps_satellites")

    def record_fields(self) -> dict:
        """The fields a `telemetry` record gets (those known), rounded for the log."""
        out: dict = {}
        for name in ("rel_alt_m", "heading_deg", "battery_pct", "battery_voltage_v"):
            v = getattr(self, name)
            if v is not None and math.isfinite(v):
                out[name] = round(float(v), 3)
        if self.flight_mode:
            out["flight_mode"] = str(self.flight_mode)
        if self.armed is not None:
            out["armed"] = bool(self.armed)
        for name in self.INTEGERS:
            v = getattr(self, name)
            if v is not None:
                out[name] = int(v)
        return out

    @classmethod
    def from_record(cls, rec: dict) -> VehicleStatus:
        """The status a `telemetry` record holds (absent fields None); a field of the wrong type or
        out of range is a :class:`MissionError` naming it."""
        vals: dict = {}
        for name, (lo, hi) in cls.RANGES.items():
            if name not in rec:
                continue
            v = rec[name]
            integer = name in cls.INTEGERS
            ok_type = isinstance(v, int) if integer else isinstance(v, int | float)
            if isinstance(v, bool) or not ok_type or not (math.isfinite(v) and lo <= v <= hi):
                kind = "an integer" if integer else "a finite number"
                raise MissionError(f"telemetry field {name!r} must be {kind} in [{lo:g}, {hi:g}], got {v!r}")
            vals[name] = int(v) if integer else float(v)
        if "flight_mode" in rec:
            if not isinstance(rec["flight_mode"], str) or len(rec["flight_mode"]) > 64:
                raise MissionError(f"telemetry field 'flight_mode' must be a string, got {rec['flight_mode']!r}")
            vals["flight_mode"] = rec["flight_mode"]
        if "armed" in rec:
            if not isinstance(rec["armed"], bool):
                raise MissionError(f"telemetry field 'armed' must be true or false, got {rec['armed']!r}")
            vals["armed"] = rec["armed"]
        return cls(**vals)
