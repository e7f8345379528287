"""Replay: re-run the estimator over a recorded mission log (docs/design.md §1, §10, §11).

Replay needs only the `header` and the `rtt` records. Consecutive `rtt` records taken at the same
UAV position (one trigger, all users) form one keyframe; its GPS prior is that position in the
mission's ENU frame. By default every trigger in the log is a keyframe (the controller already
spaced them Δ apart); `delta_m` re-selects keyframes at a spacing of Δ metres.

The final estimate is the batch solution over all keyframes; the history (error bound, and error
when the log holds `truth`, against metres flown) is the estimate a mission acts on as it would
have evolved during the flight: the batch refreshed on estimator.refresh's schedule.

A fleet's log (docs/fleet.md; records naming their `vehicle`) replays as the fleet flew: each
vehicle's keyframes are built from its own records (its triggers, its previous keyframe, its own
telemetry velocity), the keyframes carry their vehicle, and the estimator chains each vehicle's
keyframes apart. The metres flown are every vehicle's together, each over its own track.
"""

from __future__ import annotations

import heapq
import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, fields, replace

import numpy as np

from estimator.gps import estimate_gps_tau_s
from estimator.keyframes import KeyframeSelector
from estimator.noise import NoiseModel
from estimator.types import Estimate, Keyframe, SolverParams
from mission.estimation import MissionEstimator
from mission.keyframes import TriggerRecords, VelocityRecords, build_keyframes_of, triggers_gps_enu_m
from mission.log import MissionLog
from mission.result import (
    STATUS_BUDGET,
    STATUS_FLOOR,
    STATUS_NO_LEG,
    STATUS_TARGET,
    STATUS_TARGET_MISSED,
    Result,
    build_result,
    horizontal_error_m,
    result_status,
    vehicles_of_events,
)
from mission.vehicle.telemetry import odometer_dead_band_m, odometer_m
from planner.stop import targets_reached
from uavloc.errors import MissionLogError

log = logging.getLogger(__name__)

#: rtt records within this distance [m] and time [s] of a trigger's first record belong to it.
GROUP_RADIUS_M = 0.5
GROUP_WINDOW_S = 1.0


@dataclass(frozen=True)
class ReplayOptions:
    """How to replay. `params` None: the solver settings logged in the header (see
    :func:`solver_params_from_header`). `delta_m` None: keep every trigger of the log as a keyframe.
    `noise` None: the header's noise model (defaults when absent). `history`: also record how
    the error bound fell with metres flown (estimator.refresh's schedule of batch solves).
    `velocity`: link consecutive keyframes by relative-motion factors integrated from the
    telemetry's `vel_ned_mps` where the log has it (estimator.motion; False: GPS alone)."""

    params: SolverParams | None = None
    delta_m: float | None = None
    noise: NoiseModel | None = None
    history: bool = True
    velocity: bool = True


@dataclass(frozen=True)
class ReplayHistory:
    """The estimate a mission acts on after each keyframe (estimator.refresh): flown_m (H,),
    t_s (H,), bound_95_m (H, K), error_m (H, K) when truth is known (else None), users_enu_m (H, K, 3)."""

    flown_m: np.ndarray
    t_s: np.ndarray
    bound_95_m: np.ndarray
    error_m: np.ndarray | None
    users_enu_m: np.ndarray


@dataclass(frozen=True)
class ReplayResult:
    """Outcome of a replay.

    keyframes: the N keyframes used (GPS prior in ENU, user indices, ranges [m], vehicle), in time
        order (each vehicle's in its own order).
    kf_gps_enu_m (N, 3), kf_t_s (N,). estimate: the batch estimate over all keyframes.
    truth_enu_m (K, 3) or None; error_m (K,) horizontal error per user when truth is known.
    flown_m: survey metres: odometer (dead band max(5 m, 8 σ_gps)) over the telemetry between the first and the
        last range (over the keyframes without telemetry) [m]; a fleet's, the sum of each vehicle's
        odometer over its own track.
    """

    log: MissionLog
    noise: NoiseModel
    params: SolverParams
    keyframes: list[Keyframe]
    kf_gps_enu_m: np.ndarray
    kf_t_s: np.ndarray
    estimate: Estimate
    truth_enu_m: np.ndarray | None
    error_m: np.ndarray | None
    flown_m: float
    n_measurements: int
    history: ReplayHistory | None


def solver_params_from_header(mlog: MissionLog) -> SolverParams:
    """The solver settings the mission ran with (header `config.solver`, as the controller logs
    them: mission.estimation.solver_params_header), so that a replay reproduces the mission's
    estimates; SolverParams() when absent, a field's default where it is absent (coverage_m: inf,
    as in a log from before the cell's reach reached the estimator, or of an unlimited one).
    Unknown fields are ignored with a warning (a log from a newer or another tool)."""
    solver = mlog.header.config.get("solver")
    if solver is None:
        return SolverParams()
    if not isinstance(solver, dict):
        raise MissionLogError(f"{mlog.path}: header config.solver must be an object, got {solver!r}")
    known = {f.name for f in fields(SolverParams)}
    unknown = sorted(set(solver) - known)
    if unknown:
        log.warning("%s: ignoring unknown solver settings in the header: %s", mlog.path, ", ".join(unknown))
    defaults = SolverParams()
    kwargs = {}
    for name in sorted(set(solver) & known):
        value, default = solver[name], getattr(defaults, name)
        expected = type(default) if default is not None else (int, float)
        if isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, int | float) and not isinstance(default, bool):
            ok = isinstance(value, int | float) and not isinstance(value, bool)
        else:
            ok = value is None or isinstance(value, expected)
        if not ok:
            raise MissionLogError(f"{mlog.path}: header config.solver.{name} has the wrong type: {value!r}")
        kwargs[name] = value
    return replace(defaults, **kwargs)


def resolve_gps_tau(mlog: MissionLog, noise: NoiseModel) -> NoiseModel:
    """The noise model with a GPS correlation time: the given one, else the one the flight's
    estimator used (the log's `gps_tau` event: estimated from the take-off's telemetry or assumed;
    the stop rule judged with it, so the final answer uses it too), else estimated from the log's
    telemetry velocity (estimator.gps.estimate_gps_tau_s; a log of another tool or of a flight cut
    short before its survey), else left unknown (the estimator then assumes
    estimator.noise.DEFAULT_GPS_TAU_S).

    A fleet's telemetry is never mixed: each pair of fixes the estimate uses is two consecutive
    records of one vehicle, and the median pools every vehicle's pairs into one τ (the estimator
    holds one τ; the vehicles' receivers are of one kind). One vehicle: as before."""
    if noise.gps_tau_s is not None:
        return noise
    if mlog.gps_tau_s is not None:
        log.info("%s: no gps_tau_s in the header; the flight's (its gps_tau event): %.1f s", mlog.path, mlog.gps_tau_s)
        return replace(noise, gps_tau_s=mlog.gps_tau_s)
    vel = mlog.tel_vel_ned_mps
    tau = None
    if vel is not None and len(mlog.tel_t_s) > 1:
        origin = mlog.header.origin
        pos = origin.lla_to_enu(mlog.tel_lla[:, 0], mlog.tel_lla[:, 1], mlog.tel_lla[:, 2])
        # NED -> ENU
        vel_enu = np.column_stack([vel[:, 1], vel[:, 0], -vel[:, 2]])
        vehicles = _vehicle_column(mlog.tel_vehicle, len(mlog.tel_t_s))
        series = vehicles if vehicles.any() else None
        tau = estimate_gps_tau_s(mlog.tel_t_s, pos, vel_enu, noise.sigma_gps_m, series)
    if tau is None:
        log.info("%s: no gps_tau_s in the header and no telemetry velocity to estimate it: assuming %.0f s",
                 mlog.path, noise.gps_tau_used_s)
        return noise
    log.info("%s: no gps_tau_s in the header; estimated from the telemetry velocity: %.1f s", mlog.path, tau)
    return replace(noise, gps_tau_s=tau)


def build_keyframes(mlog: MissionLog, delta_m: float | None = None, noise: NoiseModel | None = None,
                    velocity: bool = True) -> list[Keyframe]:
    """Group the log's rtt records into triggers and build each one's keyframe
    (mission.keyframes.build_keyframes_of, the flight's builder), optionally re-selected at Δ spacing.

    A group is consecutive records of one vehicle (consecutive among that vehicle's records) with no
    user twice that share their first record's UAV position exactly (uavloc writes one position per
    trigger, however long the trigger's measurements took in vehicle seconds), or, in logs of other
    tools, lie within GROUP_RADIUS_M and GROUP_WINDOW_S of it. A group never mixes vehicles.

    With `velocity` and telemetry that carries `vel_ned_mps`, each keyframe also gets the
    displacement from the one of its vehicle kept before it, integrated from that vehicle's
    telemetry, and its σ (under `noise`, the header's when None); none where the records do not
    cover the gap. Δ re-selection keeps each vehicle's keyframes Δ apart along its own track.

    Returns the keyframes with their vehicle (Keyframe.vehicle), in time order: the vehicles'
    sequences merged by each keyframe's time (its first record's), each vehicle's keyframes in
    the order of its records (a one-vehicle log: exactly its groups' order, as before).
    """
    if len(mlog.rtt_t_s) == 0:
        return []
    noise = noise if noise is not None else mlog.header.noise
    rtt_vehicle = _vehicle_column(mlog.rtt_vehicle, len(mlog.rtt_t_s))
    tel_vehicle = _vehicle_column(mlog.tel_vehicle, len(mlog.tel_t_s))
    chains = [_vehicle_keyframes(mlog, np.flatnonzero(rtt_vehicle == v), np.flatnonzero(tel_vehicle == v), int(v),
                                 delta_m, noise, velocity)
              for v in np.unique(rtt_vehicle)]
    # time order across vehicles; heapq.merge keeps each vehicle's own order and breaks ties by vehicle
    return list(heapq.merge(*chains, key=lambda kf: kf.t_s))


def _vehicle_column(vehicle: np.ndarray | None, n: int) -> np.ndarray:
    """(n,) int the records' vehicles: the log's column, zeros (one vehicle) where it has none."""
    if vehicle is None or len(vehicle) != n:
        return np.zeros(n, int)
    return np.asarray(vehicle, int)


def _vehicle_keyframes(mlog: MissionLog, rtt_ix: np.ndarray, tel_ix: np.ndarray, vehicle: int,
                       delta_m: float | None, noise: NoiseModel, velocity: bool) -> list[Keyframe]:
    """The keyframes of one vehicle (:func:`build_keyframes`) from its rtt records rtt_ix (R,) and
    its telemetry records tel_ix (T,), both indices into the log's arrays in file order."""
    if rtt_ix.size == 0:
        return []
    origin = mlog.header.origin
    rtt_lla = mlog.rtt_uav_lla[rtt_ix]
    rtt_t, rtt_user = mlog.rtt_t_s[rtt_ix], mlog.rtt_user[rtt_ix]
    pos = origin.lla_to_enu(rtt_lla[:, 0], rtt_lla[:, 1], rtt_lla[:, 2])
    groups: list[list[int]] = []
    for i in range(len(rtt_ix)):
        if groups:
            g = groups[-1]
            first = g[0]
            same_uav = bool(np.array_equal(rtt_lla[i], rtt_lla[first]))
            near = (np.linalg.norm(pos[i] - pos[first]) <= GROUP_RADIUS_M
                    and abs(rtt_t[i] - rtt_t[first]) <= GROUP_WINDOW_S)
            if (same_uav or near) and rtt_user[i] not in rtt_user[g]:
                g.append(i)
                continue
        groups.append([i])
    vel = mlog.tel_vel_ned_mps
    records = (VelocityRecords.from_ned(mlog.tel_t_s[tel_ix], vel[tel_ix])
               if velocity and vel is not None and len(vel) and tel_ix.size else None)
    triggers = [TriggerRecords(t_s=rtt_t[idx], user_idx=rtt_user[idx], uav_lla=rtt_lla[idx],
                               toa_s=mlog.rtt_toa_s[rtt_ix][idx]) for idx in map(np.asarray, groups)]
    if delta_m:
        selector = KeyframeSelector(delta_m)
        gps = triggers_gps_enu_m(triggers, origin)
        triggers = [t for t, g in zip(triggers, gps, strict=True) if selector.accept(g)]
    return build_keyframes_of(triggers, origin, None, records, noise, vehicle)


def _survey_odometer(mlog: MissionLog, keyframes: list[Keyframe], kf_t: np.ndarray, kf_gps: np.ndarray,
                     noise: NoiseModel) -> tuple[np.ndarray, float]:
    """(metres flown at each keyframe (N,), survey metres) by odometer, as the controller counts
    them (replay's docstring). A fleet's: each vehicle's odometer over its own telemetry (or its own
    keyframes), summed; the survey window (first keyframe to the survey's end) is the mission's."""
    band_m = odometer_dead_band_m(noise.sigma_gps_m)
    origin = mlog.header.origin
    closed = mlog.last_event("survey_time")
    survey_end_s = max(kf_t[-1], float(closed["t"])) if closed is not None and "t" in closed else kf_t[-1]
    kf_vehicle = np.array([kf.vehicle for kf in keyframes], int)
    tel_vehicle = _vehicle_column(mlog.tel_vehicle, len(mlog.tel_t_s))
    in_survey = (mlog.tel_t_s >= kf_t[0]) & (mlog.tel_t_s <= survey_end_s)
    kf_flown = np.zeros(len(keyframes))
    flown_m = 0.0
    for v in np.unique(np.concatenate([kf_vehicle, tel_vehicle[in_survey]])):
        mine = in_survey & (tel_vehicle == v)
        own_kf = kf_vehicle == v
        if np.count_nonzero(mine) >= 2:
            tel = mlog.tel_lla[mine]
            cum = odometer_m(origin.lla_to_enu(tel[:, 0], tel[:, 1], tel[:, 2]), band_m)
            kf_flown += np.interp(kf_t, mlog.tel_t_s[mine], cum)
            flown_m += float(cum[-1])
        elif own_kf.any():
            # its keyframes' odometer, held from each of its keyframes to its next (0 before its first)
            cum = odometer_m(kf_gps[own_kf], band_m)
            if own_kf.all():
                kf_flown += cum
            else:
                at = np.searchsorted(kf_t[own_kf], kf_t, side="right") - 1
                kf_flown += np.where(at >= 0, cum[np.maximum(at, 0)], 0.0)
            flown_m += float(cum[-1])
    return kf_flown, flown_m


def replay(mlog: MissionLog, options: ReplayOptions = ReplayOptions(),
           progress: Callable[[int, int], None] | None = None) -> ReplayResult:
    """Re-run the estimator over a parsed log. `progress(done, total)` is called per keyframe."""
    noise = resolve_gps_tau(mlog, options.noise or mlog.header.noise)
    params = options.params if options.params is not None else solver_params_from_header(mlog)
    if options.delta_m is not None:
        params = replace(params, delta_m=options.delta_m)
    keyframes = build_keyframes(mlog, options.delta_m, noise, options.velocity)
    if not keyframes:
        raise MissionLogError(f"{mlog.path}: no rtt records to replay")
    n_users = mlog.n_users
    user_up_m = mlog.user_up_m()
    origin = mlog.header.origin
    kf_gps = np.array([kf.gps_enu_m for kf in keyframes])
    kf_t = np.array([kf.t_s for kf in keyframes])
    truth_enu = None
    if mlog.truth_lla is not None:
        truth_enu = origin.lla_to_enu(mlog.truth_lla[:, 0], mlog.truth_lla[:, 1], mlog.truth_lla[:, 2])

    # metres flown, as the controller counts them: an odometer with a dead band of max(5 m, 8 σ_gps)
    # over the telemetry of the survey (from the first range to the `survey_time` event that closes
    # it, or to the last range in a log without one; the survey flies on for the seconds the final
    # answer takes to confirm), else over the keyframes
    kf_flown, flown_m = _survey_odometer(mlog, keyframes, kf_t, kf_gps, noise)
    # the controller's own count, from every fix of its legs (the log's telemetry is a sample): the
    # last `survey_time` event of each vehicle, summed over a fleet's
    closed: dict[int, float] = {}
    for e in mlog.events:
        v, m = e.get("vehicle", 0), e.get("flown_m")
        if e.get("kind") == "survey_time" and isinstance(m, int | float) and math.isfinite(m):
            closed[v] = float(m)
    if closed:
        flown_m = sum(closed.values())

    # the mission's estimator (mission.estimation), without a stop rule
    setup = MissionEstimator(n_users, user_up_m, noise, params)
    history = None
    total = len(keyframes) + 1
    if options.history:
        refreshed = setup.estimator(online=False)
        bounds = np.full((len(keyframes), n_users), np.inf)
        users_hist = np.full((len(keyframes), n_users, 3), np.nan)
        for i, kf in enumerate(keyframes):
            est = refreshed.add_keyframe(kf)
            bounds[i] = est.error_bound_95_m()
            users_hist[i] = est.users_enu_m
            if progress is not None:
                progress(i + 1, total)
        errors = horizontal_error_m(users_hist, truth_enu[None]) if truth_enu is not None else None
        history = ReplayHistory(kf_flown, kf_t, bounds, errors, users_hist)

    estimate = setup.final(keyframes)
    if progress is not None:
        progress(total, total)
    error_m = horizontal_error_m(estimate.users_enu_m, truth_enu) if truth_enu is not None else None
    return ReplayResult(
        log=mlog, noise=noise, params=params, keyframes=keyframes, kf_gps_enu_m=kf_gps, kf_t_s=kf_t,
        estimate=estimate, truth_enu_m=truth_enu, error_m=error_m, flown_m=flown_m,
        n_measurements=int(sum(len(kf.range_m) for kf in keyframes)), history=history,
    )


#: "mission end: STATUS (REASON)": the end record's message, where logs written before the end
#: record carried `reason` find it
_END_MESSAGE = re.compile(r"^mission end: (?P<status>\S+) \((?P<reason>.*)\)$")


def end_of_log(mlog: MissionLog) -> tuple[str, str, float] | None:
    """(status, reason, t [s]) of the log's `end` event, or None when it has none. A log written
    before the record carried `reason` gives the one its message names."""
    end = mlog.last_event("end")
    if end is None or not isinstance(end.get("status"), str):
        return None
    reason = end.get("reason")
    if not isinstance(reason, str):
        m = _END_MESSAGE.match(str(end.get("message", "")))
        reason = m.group("reason") if m and m.group("status") == end["status"] else ""
    return end["status"], reason, float(end["t"])


def target_radius_of_header(mlog: MissionLog) -> float | None:
    """The stop rule's radius [m] the mission flew with (header `config.controller.flight.target_radius_m`,
    as the controller logs its settings), None when the log does not say (another tool's log)."""
    controller = mlog.header.config.get("controller")
    flight = controller.get("flight") if isinstance(controller, dict) else None
    r = flight.get("target_radius_m") if isinstance(flight, dict) else None
    ok = isinstance(r, int | float) and not isinstance(r, bool) and math.isfinite(r) and r > 0
    return float(r) if ok else None


def status_of_answer(status: str, reason: str, replayed: ReplayResult | None) -> tuple[str, str]:
    """(status, reason) the final answer (the replay of the mission's log, None: no ranges) supports,
    from those the mission recorded, under the header's target (:func:`target_radius_of_header`):
    `target_reached` only when every user's printed 95 % bound is within the target and none is
    ambiguous, as the stop rule judges it (planner.stop.targets_reached). A survey recorded as
    target_reached whose answer does not hold it is `target_missed` (the reason names the users
    beyond the target); one that ended at its floor, its budget or without a feasible leg whose
    answer bounds every user within the target has reached it. How a flight ended otherwise
    (returned, aborted, interrupted) stands, and so does every status without a target or an
    estimate to judge by. The flight ends with this status (mission.control.flight) and replay
    recomputes it from the same log."""
    target_radius_m = None if replayed is None else target_radius_of_header(replayed.log)
    if target_radius_m is None:
        return status, reason
    estimate, user_ids = replayed.estimate, [u.id for u in replayed.log.header.users]
    reached = targets_reached(estimate, target_radius_m)
    if status == STATUS_TARGET and not reached:
        bound = estimate.error_bound_95_m()
        ambiguous = np.asarray(estimate.ambiguous, bool)
        beyond = [f"{u} " + ("ambiguous" if ambiguous[k] else f"at {bound[k]:.2f} m" if np.isfinite(bound[k])
                             else "not located")
                  for k, u in enumerate(user_ids) if ambiguous[k] or not bound[k] <= target_radius_m]
        return STATUS_TARGET_MISSED, (f"the final answer bounds {', '.join(beyond)}, beyond the {target_radius_m:g} m "
                                      f"target the survey stopped at")
    if status in (STATUS_FLOOR, STATUS_BUDGET, STATUS_NO_LEG) and reached:
        return STATUS_TARGET, f"target reached in the final answer (the survey ended {status})"
    return status, reason


def result_of_log(mlog: MissionLog, replayed: ReplayResult | None) -> Result:
    """The mission's :class:`mission.result.Result` from its log and the replay of it (None: the log
    has no ranges: nothing located): status and reason those the log's `end` record holds judged
    against the replay's answer (:func:`status_of_answer`; Result.status_logged keeps the record's;
    without one: :func:`mission.result.result_status` of the estimate), duration from the header to
    that record (or the last record), the `survey_time` event's seconds. The mission builds its
    result so from its own closed log, and `uavloc replay` the same way."""
    end = end_of_log(mlog)
    est = None if replayed is None else replayed.estimate
    status_logged = None
    if end is not None:
        status_logged, reason, t_end = end
        status, reason = status_of_answer(status_logged, reason, replayed)
    else:
        status = result_status(est) if est is not None else "incomplete"
        reason, t_end = "the log has no end record", mlog.t_last_s
    survey = mlog.last_event("survey_time") or {}
    vehicles, breaches = (), None
    if mlog.header.vehicles:  # a fleet: each vehicle's part, and the vehicles' survey as one
        vehicles, breaches = vehicles_of_events([v.id for v in mlog.header.vehicles], mlog.events)
        survey = _fleet_survey(vehicles, [e for e in mlog.events if e.get("kind") == "survey_time"])

    def seconds(key: str) -> float | None:
        v = survey.get(key)
        return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None

    truth = None
    if mlog.truth_lla is not None:
        truth = mlog.header.origin.lla_to_enu(mlog.truth_lla[:, 0], mlog.truth_lla[:, 1], mlog.truth_lla[:, 2])
    return build_result(
        status=status, reason=reason, user_ids=[u.id for u in mlog.header.users], estimate=est,
        origin=mlog.header.origin, truth_enu_m=truth,
        flown_m=0.0 if replayed is None else replayed.flown_m,
        measurements=0 if replayed is None else replayed.n_measurements,
        keyframes=0 if replayed is None else len(replayed.keyframes),
        duration_s=t_end - mlog.t_start_s, survey_s=seconds("survey_s"), hover_s=seconds("hover_s"),
        largest_gap_s=seconds("largest_gap_s"), log_path=mlog.path, vehicles=vehicles, separation_breaches=breaches,
        status_logged=status_logged)


def _fleet_survey(vehicles, survey_events: list[dict]) -> dict:
    """A fleet's survey seconds: the longest vehicle's survey_s, the vehicles' hover summed, and the
    longest any vehicle went without a range (each vehicle's `survey_time` event)."""
    surveys = [v.survey_s for v in vehicles if v.survey_s is not None]
    hovers = [v.hover_s for v in vehicles if v.hover_s is not None]
    gaps = [float(e["largest_gap_s"]) for e in survey_events if isinstance(e.get("largest_gap_s"), int | float)]
    return {"survey_s": max(surveys) if surveys else None, "hover_s": sum(hovers) if hovers else None,
            "largest_gap_s": max(gaps) if gaps else None}


def result_of_replay(result: ReplayResult) -> Result:
    """:func:`result_of_log` of a replay's own log."""
    return result_of_log(result.log, result)
