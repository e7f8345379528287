"""Fast mode: a kinematic vehicle and channel around the real estimator and planner (no MAVLink, no TCP).

The loop (the planner benchmark's, docs/design.md §5–6): the UAV starts at home at the cruise altitude;
the planner gives a waypoint; the UAV flies the straight leg at the scenario's cruise speed; every Δ
metres along it (spacing carried across legs) a keyframe is simulated and fed to the mission's
estimator, the same object a flight builds (mission.estimation.MissionEstimator from the scenario's
mission, as `uavloc sim` flies it: the online estimator refreshed by batch solves that track UE
clock sawtooths and drifting GPS, the stop rule confirming on the online estimate); the planner is
called again at the leg end with the estimate the mission would act on. The run ends where the
mission would: the mission's stop rule on a batch estimate, the planner done, or the budget flown;
the final answer is the mission's (the batch solution over every keyframe, replay's).

A keyframe at arc length s (time t = s / speed):
- GPS fix = truth + the vehicle simulator's GPS error (sitl_scenarios.vehicle.sensors.GpsError:
  independent per fix, or Gauss–Markov with the scenario's `vehicle.gps_tau_s`);
- a range to every user in coverage from the simulated gNB's radio model
  (sitl_scenarios.radio.RadioModel: σ(d) noise, UE clock sawtooth, NLoS excess behind buildings,
  TA and SRS quantization), turned into metres by estimator.ranging as the mission does.

Each leg is also checked here, independently of the planner, against the fence, no-fly zones,
altitude band, distance from home, leg length and budget (`leg_violation`).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from estimator.ranging import range_m_from_raw
from estimator.types import Estimate, Keyframe, SolverParams
from mission import geometry
from mission.control.legs import PLAN_AHEAD_S
from mission.estimation import MissionEstimator
from mission.kernel_cache import use_kernel_cache
from mission.result import STATUS_BUDGET, STATUS_TARGET, build_result, status_of_planner_reason
from planner import PlanningConstraints, PlanningState, make_planner
from sitl_scenarios.campaign.outcome import AccuracyTrack, Outcome
from sitl_scenarios.radio import RadioModel
from sitl_scenarios.scenario import Scenario
from sitl_scenarios.vehicle.sensors import GpsError


def leg_violation(c: PlanningConstraints, a: np.ndarray, b: np.ndarray, flown_m: float) -> str | None:
    """Name the first constraint the straight leg a → b (both (3,) ENU [m]) breaks, or None.
    Independent of planner.geometry on purpose: the fence and no-fly zones are judged by the
    safety gate's geometry (mission.geometry on shapely: the whole segment, the boundary inside
    the fence and inside a zone), the distance from home at the leg's farthest point."""
    length = float(np.linalg.norm(b - a))
    if length > c.leg_max_m + 1e-6 or flown_m + length > c.budget_m + 1e-6:
        return f"leg {length:.2f} m"
    if not c.alt_min_m - 1e-6 <= b[2] <= c.alt_max_m + 1e-6:
        return f"altitude {b[2]:.2f} m"
    # |p(t) − h| is convex along the leg: its largest value is at an end
    far_m = max(np.linalg.norm(a[:2] - c.home_enu_m[:2]), np.linalg.norm(b[:2] - c.home_enu_m[:2]))
    if far_m > c.max_distance_m + 1e-6:
        return "distance from home"
    leg = f"leg {np.round(a[:2], 2).tolist()} -> {np.round(b[:2], 2).tolist()}"
    if len(c.fence_enu_m) and not geometry.segment_inside(c.fence_enu_m, a, b):
        return f"outside the fence: {leg}"
    if any(geometry.segment_meets(zone, a, b) for zone in c.no_fly_enu_m):
        return f"in a no-fly zone: {leg}"
    return None


def fly_fast(sc: Scenario, planner_name: str, params: SolverParams, seed: int,
             targets_m: tuple[float, ...], planner_opts: dict | None = None,
             on_keyframe: Callable[[Keyframe, Estimate], None] | None = None, n_vehicles: int = 1) -> Outcome:
    """Fly one scenario in fast mode (see the module docstring); deterministic in (sc, planner, params, seed).

    on_keyframe(keyframe, estimate): called with each keyframe and the estimate the run then acts on."""
    if n_vehicles != 1:
        from uavloc.errors import CampaignError

        raise CampaignError(f"fast mode flies one vehicle here; n_vehicles={n_vehicles}")
    users = np.array([[u.east_m, u.north_m, u.up_m] for u in sc.users], float)
    setup = MissionEstimator.from_mission(sc.mission_config(), params=params)
    noise = setup.noise
    c = sc.planning_constraints()
    opts = dict(planner_opts or {})
    if planner_name == "oracle":
        opts.setdefault("true_users_enu_m", users)
    use_kernel_cache()
    planner = make_planner(planner_name, c, noise, rng_seed=seed, **opts)
    est = setup.estimator()
    confirm = setup.confirm
    keyframes: list[Keyframe] = []
    gps_ss, radio_ss = np.random.SeedSequence([seed, sc.seed]).spawn(2)
    gps = GpsError(sc.vehicle.gps_sigma_m, sc.vehicle.gps_tau_s, np.random.default_rng(gps_ss))
    radio = RadioModel(sc, np.random.default_rng(radio_ss))
    speed_mps = sc.vehicle.speed_mps
    delta_m = sc.mission.flight.delta_m
    track = AccuracyTrack(users, targets_m)
    out = Outcome()
    all_users = range(len(users))
    n_ranges = n_nlos = 0

    x = np.array([*c.home_enu_m[:2], c.cruise_alt_m])
    flown, since_kf, estimate, stopped = 0.0, delta_m, None, False
    while flown < c.budget_m:
        t0 = time.perf_counter()  # the planner has no clock: its compute time is timed here
        res = planner.plan(PlanningState(x, estimate, flown))
        out.plan_times_s.append(time.perf_counter() - t0)
        # the mission plans the next leg PLAN_AHEAD_S before this one ends: only a plan longer than
        # that keeps the vehicle waiting (the first one is made before take-off)
        if len(out.plan_times_s) > 1:
            out.hover_s += max(0.0, out.plan_times_s[-1] - PLAN_AHEAD_S)
        if res.done:
            status, reason = status_of_planner_reason(res.reason), res.reason or "planner done"
            break
        wp = np.asarray(res.waypoint_enu_m, float)
        bad = leg_violation(c, x, wp, flown)
        if bad:
            out.violations.append(bad)
        leg = float(np.linalg.norm(wp - x))
        # keyframes every Δ metres along the path: at arc lengths Δ − since_kf, 2Δ − since_kf, ...
        s = delta_m - since_kf
        while s <= leg + 1e-9:
            pos = x + (wp - x) * (s / leg)
            t_s = (flown + s) / speed_mps
            idx, ranges = [], []
            for k in all_users:
                raw = radio.measure(k, pos, t_s)
                if raw is None:  # beyond coverage: no answer
                    continue
                idx.append(k)
                ranges.append(range_m_from_raw(raw.ta, raw.mu, raw.srs_peak, raw.fs_hz))
                n_nlos += raw.nlos
            n_ranges += len(idx)
            kf = Keyframe(pos + gps.sample(t_s), np.array(idx, dtype=int), np.array(ranges, dtype=float), t_s=t_s)
            keyframes.append(kf)
            estimate = est.add_keyframe(kf, confirm)
            if on_keyframe is not None:
                on_keyframe(kf, estimate)
            track.update(estimate.users_enu_m[:, :2], estimate.cov_users_m2[:, :2, :2], flown + s,
                         t_s + out.hover_s)
            if setup.stops(estimate):
                stopped = True
                break
            s += delta_m
        if stopped:  # mid-leg, as the mission stops at once
            flown += s
            status, reason = STATUS_TARGET, "target reached"
            break
        since_kf = leg - (s - delta_m)
        flown += leg
        x = wp
    else:
        status, reason = STATUS_BUDGET, "budget spent"
    if est.online_failure is not None:
        out.estimator_errors.append(est.online_failure)
    final = None
    if keyframes:  # the mission's final answer
        final = setup.final(keyframes)
        track.update(final.users_enu_m[:, :2], final.cov_users_m2[:, :2, :2], flown, flown / speed_mps + out.hover_s)
    out.survey_s = flown / speed_mps + out.hover_s
    out.nlos_share = n_nlos / n_ranges if n_ranges else float("nan")
    # no log: the Result from the final estimate, through the mission's one constructor
    result = build_result(status=status, reason=reason, user_ids=[u.id for u in sc.users], estimate=final,
                          origin=sc.origin_geo, truth_enu_m=users, flown_m=flown, measurements=n_ranges,
                          keyframes=len(keyframes), duration_s=out.survey_s, survey_s=out.survey_s,
                          hover_s=out.hover_s)
    return track.fill(out).take_result(result)
