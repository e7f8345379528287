"""The one keyframe builder (DESIGN.md §5, §10): a keyframe is a function of mission-log records.

The flight (mission.control.pipeline) and replay (mission.replay) both call
:func:`build_keyframe` with the `rtt` records of one trigger as written, the previous keyframe's
position time and the telemetry velocity as logged, so the keyframes the flight's estimator gets
are the keyframes `uavloc replay` rebuilds from its log, bit for bit.

One keyframe n from its trigger's records i = 1..G (one per user measured):

    t_n       = t_1                                 (the first record's time, as logged)
    t_pos,n   = (1/G) Σ_i t_i                       (where the flight interpolated the telemetry)
    x̂_n       = ENU(uav_1)  if every record logs the same position (uavloc writes one per trigger),
                (1/G) Σ_i ENU(uav_i) otherwise      (logs of other tools)
    r̂_nk      = c · toa_s,i                         for the user k of record i
    ô_n, σ_m  = ∫ v̂ dt over [t_pos,n−1, t_pos,n]   (estimator.motion.integrate_velocity,
                motion_sigma_m) from the velocity records, where they cover the gap

The velocity integral uses only the records of its window: from the last velocity record at or
before t_pos,n−1 through the first one strictly after t_pos,n (estimator.motion computes each gap
from its own records). The flight therefore waits, when placing, for a velocity record after the
trigger (:func:`velocity_covers`); once it has one, its records give the integral the whole log gives.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from estimator.geodesy import Origin
from estimator.motion import integrate_velocity, motion_sigma_m, velocity_enu_of_ned
from estimator.noise import NoiseModel
from estimator.ranging import C_MPS
from estimator.types import Keyframe
from uavloc.errors import MissionLogError


@dataclass(frozen=True)
class TriggerRecords:
    """The `rtt` records of one trigger, as logged: t_s (G,) mission time [s], user_idx (G,) header
    user indices, uav_lla (G, 3) lat_deg/lon_deg/alt_m of the UAV, toa_s (G,) one-way ToA [s]."""

    t_s: np.ndarray
    user_idx: np.ndarray
    uav_lla: np.ndarray
    toa_s: np.ndarray

    @classmethod
    def from_records(cls, records: Sequence[Mapping], user_index: Mapping[str, int]) -> TriggerRecords:
        """From `rtt` records as written ({"t", "user", "uav": {lat_deg, lon_deg, alt_m}, "toa_s", ...})."""
        try:
            return cls(
                t_s=np.array([float(r["t"]) for r in records]),
                user_idx=np.array([user_index[r["user"]] for r in records], dtype=int),
                uav_lla=np.array([[float(r["uav"]["lat_deg"]), float(r["uav"]["lon_deg"]), float(r["uav"]["alt_m"])]
                                  for r in records]).reshape(-1, 3),
                toa_s=np.array([float(r["toa_s"]) for r in records]),
            )
        except (KeyError, TypeError) as exc:
            raise MissionLogError(f"rtt record without a usable {exc}: {list(records)!r}") from None

    @property
    def position_t_s(self) -> float:
        """Time [s] of the trigger's UAV position: the mean of its records' times."""
        return position_time_s(self.t_s)


@dataclass(frozen=True)
class VelocityRecords:
    """Telemetry velocity as logged: t_s (T,) [s], vel_enu_mps (T, 3) [m/s, ENU]; NaN rows are
    records without velocity (skipped)."""

    t_s: np.ndarray
    vel_enu_mps: np.ndarray

    @classmethod
    def from_ned(cls, t_s: np.ndarray, vel_ned_mps: np.ndarray) -> VelocityRecords:
        """From the log's `vel_ned_mps` (T, 3) [north, east, down]."""
        return cls(np.asarray(t_s, float), velocity_enu_of_ned(vel_ned_mps))


def position_time_s(record_t_s: np.ndarray) -> float:
    """Time [s] of a trigger's UAV position: the mean of its records' (logged) times, where the
    flight interpolated the telemetry (mission.control.pipeline)."""
    return float(np.mean(np.asarray(record_t_s, dtype=float)))


def trigger_gps_enu_m(trigger: TriggerRecords, origin: Origin) -> np.ndarray:
    """(3,) GPS prior of the trigger's keyframe [m, ENU of origin] (module docstring): the logged
    position itself when the records share one (the mean of equal numbers can differ in the last bit)."""
    lla = trigger.uav_lla
    if bool(np.all(lla == lla[0])):
        return np.asarray(origin.lla_to_enu(lla[0, 0], lla[0, 1], lla[0, 2]), float)
    return origin.lla_to_enu(lla[:, 0], lla[:, 1], lla[:, 2]).mean(axis=0)


def velocity_covers(velocity: VelocityRecords, t_s: float) -> bool:
    """Whether the records hold a velocity record strictly after t_s: from then on, more records
    do not change the displacement of a gap ending at t_s (module docstring)."""
    v = velocity.vel_enu_mps
    have = np.isfinite(v).all(axis=1) & (velocity.t_s > t_s)
    return bool(np.any(have))


def velocity_odometry(velocity: VelocityRecords, t_from_s: float, t_to_s: float,
                      noise: NoiseModel) -> tuple[np.ndarray | None, float | None]:
    """(ô (3,) [m, ENU], σ_m [m]) from position time t_from_s to t_to_s, or (None, None) where the
    records do not cover the gap (estimator.motion), integrated over the window of records from
    the last at or before t_from_s through the first strictly after t_to_s."""
    tt, vv = np.asarray(velocity.t_s, float), np.asarray(velocity.vel_enu_mps, float)
    finite = np.isfinite(vv).all(axis=1) & np.isfinite(tt)
    before = tt[finite & (tt <= t_from_s)]
    after = tt[finite & (tt > t_to_s)]
    lo = before.max() if before.size else -math.inf
    hi = after.min() if after.size else math.inf
    window = finite & (tt >= lo) & (tt <= hi)
    disp, ok, disc = integrate_velocity(tt[window], vv[window], np.array([t_from_s, t_to_s]))
    if not ok[1]:
        return None, None
    return disp[1].copy(), float(motion_sigma_m(t_to_s - t_from_s, noise, disc[1]))


def build_keyframe(trigger: TriggerRecords, origin: Origin, prev_position_t_s: float | None,
                   velocity: VelocityRecords | None, noise: NoiseModel) -> Keyframe:
    """The keyframe of one trigger's records (module docstring); with the displacement from the
    previous keyframe (position time prev_position_t_s) where `velocity` covers the gap, under
    the noise model's σ_v, τ_v; none for the first keyframe or without velocity."""
    odom, odom_sigma = None, None
    if prev_position_t_s is not None and velocity is not None:
        odom, odom_sigma = velocity_odometry(velocity, prev_position_t_s, trigger.position_t_s, noise)
    return Keyframe(gps_enu_m=trigger_gps_enu_m(trigger, origin), user_idx=np.asarray(trigger.user_idx).copy(),
                    range_m=C_MPS * np.asarray(trigger.toa_s, float), t_s=float(trigger.t_s[0]),
                    odom_enu_m=odom, odom_sigma_m=odom_sigma)

