"""Noise model shared by the estimator, the planner and the simulators (docs/design.md §4, §5).

    σ(d) = s0 + a · exp(b · d)          range standard deviation at slant distance d [m]

The estimator weighs a measured range r̂ by σ(r̂), the spread at the distance it measured, not at
the distance of the current estimate (estimator.factors).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from uavloc.errors import EstimatorError

#: GPS correlation time [s] assumed when a log does not say (NoiseModel.gps_tau_s None)
DEFAULT_GPS_TAU_S = 60.0
#: the autopilot's velocity error assumed when a log does not say (NoiseModel.vel_sigma_mps,
#: vel_tau_s None): σ_v per axis [m/s] and correlation time τ_v [s] (estimator.motion); an EKF's
#: velocity is good to a few cm/s, these are on the safe side
DEFAULT_VEL_SIGMA_MPS = 0.1
DEFAULT_VEL_TAU_S = 1.0
#: σ(d)'s exponent b·d is capped here (exp(700) ≈ 1e304: finite, and 1/σ² is then 0)
SIGMA_EXPONENT_MAX = 700.0


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise of GPS and ranges.

    sigma_gps_m: per-axis standard deviation of a GPS fix [m] (paper: 1 m).
    range_s0_m, range_a_m, range_b_per_m: range spread σ(d) = s0 + a·exp(b·d) [m] (the mission
        file's [noise] names; these defaults are the mission file's too): s0 = 3 m, a = 0, b = 0 /m.
    gps_tau_s: correlation time τ of the GPS error [s]: 0 independent per fix (white); > 0
        first-order Gauss–Markov, β(t + Δt) = e^(−Δt/τ) β(t) + w, stationary σ_gps per axis (an
        autopilot's EKF output drifts like this); None unknown (a log without it): the estimator
        then assumes DEFAULT_GPS_TAU_S (replay, and a flight from its take-off, first try to
        estimate it from the telemetry: estimator.gps.estimate_gps_tau_s).
    vel_sigma_mps, vel_tau_s: σ_v per axis [m/s] and correlation time τ_v [s] of the error of the
        autopilot's velocity, for the relative-motion factors (estimator.motion); None unknown:
        DEFAULT_VEL_SIGMA_MPS, DEFAULT_VEL_TAU_S.
    """

    sigma_gps_m: float = 1.0
    range_s0_m: float = 3.0
    range_a_m: float = 0.0
    range_b_per_m: float = 0.0
    gps_tau_s: float | None = 0.0
    vel_sigma_mps: float | None = None
    vel_tau_s: float | None = None

    def __post_init__(self) -> None:
        for name in ("sigma_gps_m", "range_s0_m", "range_a_m", "range_b_per_m"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise EstimatorError(f"noise model {name} must be a finite number, got {value!r}")
        tau = self.gps_tau_s
        if tau is not None and (isinstance(tau, bool) or not isinstance(tau, int | float)
                                or not math.isfinite(tau) or tau < 0):
            raise EstimatorError(f"gps_tau_s must be a finite number >= 0 or None, got {tau!r}")
        for name in ("vel_sigma_mps", "vel_tau_s"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int | float)
                                      or not math.isfinite(value) or value <= 0):
                raise EstimatorError(f"{name} must be a positive number or None, got {value!r}")
        if self.sigma_gps_m <= 0:
            raise EstimatorError(f"sigma_gps_m must be positive, got {self.sigma_gps_m}")
        if self.range_s0_m <= 0:
            raise EstimatorError(f"range_s0_m must be positive, got {self.range_s0_m}")
        if self.range_a_m < 0:
            raise EstimatorError(f"range_a_m must be non-negative, got {self.range_a_m}")

    @property
    def gps_tau_used_s(self) -> float:
        """τ the estimator uses: gps_tau_s, or DEFAULT_GPS_TAU_S when unknown (None)."""
        return DEFAULT_GPS_TAU_S if self.gps_tau_s is None else float(self.gps_tau_s)

    @property
    def vel_sigma_used_mps(self) -> float:
        """σ_v the motion factors use: vel_sigma_mps, or DEFAULT_VEL_SIGMA_MPS when unknown."""
        return DEFAULT_VEL_SIGMA_MPS if self.vel_sigma_mps is None else float(self.vel_sigma_mps)

    @property
    def vel_tau_used_s(self) -> float:
        """τ_v the motion factors use: vel_tau_s, or DEFAULT_VEL_TAU_S when unknown."""
        return DEFAULT_VEL_TAU_S if self.vel_tau_s is None else float(self.vel_tau_s)

    def range_sigma_m(self, d_m: np.ndarray | float) -> np.ndarray:
        """σ(d) = s0 + a·exp(min(b·d, SIGMA_EXPONENT_MAX)) [m]; `d_m` any shape, result the same
        shape. The exponent is capped so that an absurd distance (a wild trial step, a bogus
        range of 10⁶ m) gives a huge finite σ, whose range then carries no information, instead
        of an overflow."""
        d = np.asarray(d_m, dtype=float)
        # σ(d) = s0 + a·exp(b·d)
        return self.range_s0_m + self.range_a_m * np.exp(np.minimum(self.range_b_per_m * d, SIGMA_EXPONENT_MAX))

    def range_sigma_dd(self, d_m: np.ndarray | float) -> np.ndarray:
        """dσ/dd = a·b·exp(b·d) [m/m] (0 where the exponent is capped), same shape as `d_m`."""
        d = np.asarray(d_m, dtype=float)
        # dσ/dd = a·b·exp(b·d)
        bd = self.range_b_per_m * d
        return np.where(bd < SIGMA_EXPONENT_MAX,
                        self.range_a_m * self.range_b_per_m * np.exp(np.minimum(bd, SIGMA_EXPONENT_MAX)), 0.0)

    @classmethod
    def from_log_dict(cls, noise: dict | None) -> NoiseModel:
        """Build from a mission-log header `noise` section (docs/design.md §10); defaults when absent.
        `range_sigma_m` holds range_s0_m, range_a_m, range_b_per_m; logs written before these names
        hold s0, a, b (read as the same)."""
        if not noise:
            return cls()
        rs = noise.get("range_sigma_m", {}) or {}
        if not isinstance(rs, dict):
            raise EstimatorError(f"noise range_sigma_m must be an object, got {rs!r}")
        for key in ("gps_tau_s", "vel_sigma_mps", "vel_tau_s"):
            v = noise.get(key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float)):
                raise EstimatorError(f"noise {key} must be a number, got {v!r}")
        tau, vs, vt = noise.get("gps_tau_s"), noise.get("vel_sigma_mps"), noise.get("vel_tau_s")
        spread = {}
        for name in RANGE_SIGMA_FIELDS:
            old = LEGACY_RANGE_SIGMA_KEYS[name]
            if name in rs and old in rs:
                raise EstimatorError(f"noise range_sigma_m has both {name!r} and its old name {old!r}: {rs!r}")
            if name in rs or old in rs:
                spread[name] = rs[name] if name in rs else rs[old]
        try:
            return cls(
                sigma_gps_m=float(noise.get("sigma_gps_m", cls.sigma_gps_m)),
                **{name: float(v) for name, v in spread.items()},
                gps_tau_s=None if tau is None else float(tau),
                vel_sigma_mps=None if vs is None else float(vs),
                vel_tau_s=None if vt is None else float(vt),
            )
        except (TypeError, ValueError, AttributeError) as exc:
            raise EstimatorError(f"noise section is malformed: {noise!r}") from exc

    def to_log_dict(self) -> dict:
        """The mission-log header `noise` section (range_sigma_m under the NoiseModel's names)."""
        out: dict = {"sigma_gps_m": self.sigma_gps_m}
        if self.gps_tau_s is not None:
            out["gps_tau_s"] = self.gps_tau_s
        if self.vel_sigma_mps is not None:
            out["vel_sigma_mps"] = self.vel_sigma_mps
        if self.vel_tau_s is not None:
            out["vel_tau_s"] = self.vel_tau_s
        out["range_sigma_m"] = {name: getattr(self, name) for name in RANGE_SIGMA_FIELDS}
        return out


#: σ(d)'s parameters, by their one name (NoiseModel's, the mission file's, the log header's)
RANGE_SIGMA_FIELDS = ("range_s0_m", "range_a_m", "range_b_per_m")
#: their names in the `range_sigma_m` of logs written before (still read)
LEGACY_RANGE_SIGMA_KEYS = {"range_s0_m": "s0", "range_a_m": "a", "range_b_per_m": "b"}
