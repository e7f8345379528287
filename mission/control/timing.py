"""When a range was measured, and what not knowing it exactly costs (issue 48; docs/design.md §7).

A range is placed at the UAV's position at the time it was measured. That time is known within an
interval (mission.gnb.RttSample.t_unc_s: a telnet answer between the request's send and the
answer's receipt; a gNB stamp within its clock offset's uncertainty). Placed at the interval's
middle, the position it is given is off by up to v·h, and, the instant being anywhere in the
interval, by a standard deviation of

    e = v · h / √3      v: the UAV's speed around then [m/s], h: the half-interval [mission s]

(a uniform distribution over 2h), which the range's own noise model does not know. The placer
keeps a range when e ≤ σ(d) (the noise model's standard deviation at the measured range d,
estimator.noise) and drops it otherwise: a range
placed where the UAV was not would pull the estimate by up to e with the weight of σ(d) (under
load the interval grows to seconds, ×10 speed-up: tens of metres). The mission log's `rtt`
record carries h (`t_unc_s`, mission seconds) of every range kept, so a reader can see how well
each was timed; the ranges dropped are counted (the survey's `survey_time` event, the speed-up
entry of the result) and the first one is an event.

Pure: numbers in, numbers out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator.noise import NoiseModel


@dataclass(frozen=True)
class RangeTiming:
    """The verdict on one range's timing.

    half_s: h, the half-interval [mission s]; speed_mps: v; error_m: e = v·h/√3 [m]; sigma_m: σ(d)
    [m]; keep: e ≤ σ(d)."""

    half_s: float
    speed_mps: float
    error_m: float
    sigma_m: float

    @property
    def keep(self) -> bool:
        return self.error_m <= self.sigma_m

    def describe(self) -> str:
        return (f"timed within ±{self.half_s:.2f} s at {self.speed_mps:.1f} m/s: placed with a position error of "
                f"σ {self.error_m:.1f} m, against the range's σ(d) = {self.sigma_m:.1f} m")


def judge_range_timing(range_m: float, half_s: float, speed_mps: float, noise: NoiseModel) -> RangeTiming:
    """e = v·h/√3 against σ(d) at d = range_m (module docstring). A non-finite h or v is unbounded
    (never kept)."""
    h = float(half_s) if math.isfinite(half_s) else math.inf
    v = float(speed_mps) if math.isfinite(speed_mps) else math.inf
    # e = v · h / √3  (0 when either is 0: a hovering UAV is where it was)
    err = 0.0 if (h == 0.0 or v == 0.0) else v * h / math.sqrt(3.0)
    return RangeTiming(h, v, err, float(noise.range_sigma_m(max(float(range_m), 0.0))))


def speed_around_mps(t_s: np.ndarray, vel_enu_mps: np.ndarray, t0_s: float, t1_s: float) -> float | None:
    """The largest speed [m/s] of the velocity records (t_s (T,), vel_enu_mps (T, 3)) within
    [t0_s, t1_s], or of the nearest record to the interval when none lies within it; None without
    records."""
    tt = np.asarray(t_s, float)
    vv = np.asarray(vel_enu_mps, float).reshape(-1, 3)
    ok = np.isfinite(tt) & np.isfinite(vv).all(axis=1)
    tt, vv = tt[ok], vv[ok]
    if tt.size == 0:
        return None
    speed = np.linalg.norm(vv, axis=1)
    inside = (tt >= t0_s) & (tt <= t1_s)
    if inside.any():
        return float(speed[inside].max())
    dist = np.minimum(np.abs(tt - t0_s), np.abs(tt - t1_s))
    return float(speed[int(np.argmin(dist))])


__all__ = ["RangeTiming", "judge_range_timing", "speed_around_mps"]
