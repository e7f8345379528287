"""The one keyframe builder (docs/design.md §5, §10): a keyframe is a function of mission-log records.

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
from its own records), found by bisection in the records sorted once by time. The flight
therefore waits, when placing, for a velocity record after the trigger (:func:`velocity_covers`);
once it has one, its records give the integral the whole log gives.

In a fleet (docs/fleet.md) each vehicle's keyframes are built from that vehicle's records alone:
its triggers, the position time of its own previous keyframe and its own telemetry velocity, so
the displacement links a keyframe to the previous keyframe of the same vehicle; the keyframes
carry their vehicle (`Keyframe.vehicle`, the `vehicle` argument).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property

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

    @cached_property
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

    @cached_property
    def finite_sorted(self) -> tuple[np.ndarray, np.ndarray]:
        """(t_s (F,), vel_enu_mps (F, 3)) of the records with velocity, stably sorted by time (records
        at the same time stay in log order, as estimator.motion.integrate_velocity keeps them)."""
        tt, vv = np.asarray(self.t_s, float), np.asarray(self.vel_enu_mps, float).reshape(-1, 3)
        use = np.isfinite(vv).all(axis=1) & np.isfinite(tt)
        order = np.argsort(tt[use], kind="stable")
        return tt[use][order], vv[use][order]


def position_time_s(record_t_s: np.ndarray) -> float:
    """Time [s] of a trigger's UAV position: the mean of its records' (logged) times, where the
    flight interpolated the telemetry (mission.control.pipeline)."""
    return float(np.mean(np.asarray(record_t_s, dtype=float)))


def triggers_gps_enu_m(triggers: Sequence[TriggerRecords], origin: Origin) -> np.ndarray:
    """(N, 3) GPS priors of the triggers' keyframes [m, ENU of origin] (module docstring): the
    logged position itself where a trigger's records share one (the mean of equal numbers can
    differ in the last bit). One conversion of contiguous (N,) columns, however many triggers."""
    first = np.array([t.uav_lla[0] for t in triggers], dtype=float).reshape(-1, 3)
    gps = origin.lla_to_enu(*(np.ascontiguousarray(first[:, c]) for c in range(3))).reshape(-1, 3)
    for i, t in enumerate(triggers):
        lla = t.uav_lla
        if not bool(np.all(lla == lla[0])):
            gps[i] = origin.lla_to_enu(*(np.ascontiguousarray(lla[:, c]) for c in range(3))).mean(axis=0)
    return gps


def velocity_covers(velocity: VelocityRecords, t_s: float) -> bool:
    """Whether the records hold a velocity record strictly after t_s: from then on, more records
    do not change the displacement of a gap ending at t_s (module docstring)."""
    t_sorted, _ = velocity.finite_sorted
    return bool(t_sorted.size and t_sorted[-1] > t_s)


def velocity_odometry(velocity: VelocityRecords, t_pos_s: np.ndarray,
                      noise: NoiseModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ô (M, 3) [m, ENU], σ_m (M,) [m], ok (M,)): the displacement from each position time of
    t_pos_s (M,) [s] to the next and its σ (estimator.motion), ok where the records cover the gap;
    row 0 and rows not ok are not a displacement. Each gap's numbers come from its own records
    only, so any records holding its window (module docstring) give the same bits."""
    tt, vv = velocity.finite_sorted
    t_pos = np.asarray(t_pos_s, dtype=float)
    disp, ok, disc = integrate_velocity(tt, vv, t_pos)
    sigma = motion_sigma_m(np.diff(t_pos, prepend=t_pos[:1]), noise, disc)
    return disp, sigma, ok


def build_keyframes_of(triggers: Sequence[TriggerRecords], origin: Origin, prev_position_t_s: float | None,
                       velocity: VelocityRecords | None, noise: NoiseModel, vehicle: int = 0) -> list[Keyframe]:
    """The keyframes of consecutive triggers' records (module docstring), each with the
    displacement from the one before (the first: from position time prev_position_t_s, none when
    None) where `velocity` covers the gap, under the noise model's σ_v, τ_v; none without velocity.

    vehicle: the vehicle (fleet index, Keyframe.vehicle) that took every one of these triggers;
    prev_position_t_s and `velocity` must then be that vehicle's own (its previous keyframe, its
    telemetry)."""
    if not triggers:
        return []
    gps = triggers_gps_enu_m(triggers, origin)
    t_pos = np.array([t.position_t_s for t in triggers])
    first = 0 if prev_position_t_s is None else 1  # the row of triggers[0] among the times
    times = t_pos if prev_position_t_s is None else np.concatenate([[float(prev_position_t_s)], t_pos])
    ok = np.zeros(times.size, dtype=bool)
    if velocity is not None and times.size >= 2:
        disp, sigma, ok = velocity_odometry(velocity, times, noise)
    keyframes = []
    for i, trig in enumerate(triggers):
        row = i + first
        linked = row > 0 and bool(ok[row])
        keyframes.append(Keyframe(
            gps_enu_m=gps[i].copy(), user_idx=np.asarray(trig.user_idx).copy(),
            range_m=C_MPS * np.asarray(trig.toa_s, float), t_s=float(trig.t_s[0]),
            odom_enu_m=disp[row].copy() if linked else None, odom_sigma_m=float(sigma[row]) if linked else None,
            vehicle=int(vehicle)))
    return keyframes


def build_keyframe(trigger: TriggerRecords, origin: Origin, prev_position_t_s: float | None,
                   velocity: VelocityRecords | None, noise: NoiseModel, vehicle: int = 0) -> Keyframe:
    """The keyframe of one trigger's records: :func:`build_keyframes_of` for one trigger (of
    vehicle `vehicle`, with that vehicle's previous position time and velocity records)."""
    return build_keyframes_of([trigger], origin, prev_position_t_s, velocity, noise, vehicle)[0]
