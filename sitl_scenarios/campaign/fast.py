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
from dataclasses import dataclass

import numpy as np

from estimator.ranging import range_m_from_raw
from estimator.types import Estimate, Keyframe, SolverParams
from mission import geometry
from mission.control.legs import PLAN_AHEAD_S
from mission.estimation import MissionEstimator
from mission.kernel_cache import use_kernel_cache
from mission.result import STATUS_BUDGET, STATUS_FLOOR, STATUS_TARGET, build_result, status_of_planner_reason
from planner import PlanningConstraints, PlanningState, make_planner
from planner.fleet import REASON_USERS_DONE, FleetPlanner, Separation, vehicles_apart
from sitl_scenarios.campaign.outcome import AccuracyTrack, Outcome
from sitl_scenarios.fleet import launch_points_enu_m
from sitl_scenarios.radio import CellAttachment, RadioModel
from sitl_scenarios.scenario import Scenario
from sitl_scenarios.vehicle.sensors import GpsError
from uavloc.errors import CampaignError


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


#: seconds a fleet's vehicle holds when no leg keeps it apart from the others, before planning again
HOLD_S = 2.0


@dataclass
class _Flyer:
    """One vehicle of a fast-mode run on its current leg x → wp (ENU [m]): the next keyframe at arc
    length s, the leg started at flown_m / speed + hold_s seconds; holding when x == wp."""

    x: np.ndarray
    wp: np.ndarray
    speed_mps: float
    flown_m: float = 0.0
    since_kf_m: float = 0.0
    s_m: float = 0.0
    hold_s: float = 0.0
    flying: bool = True
    reason: str = ""

    @property
    def leg_m(self) -> float:
        return float(np.linalg.norm(self.wp - self.x))

    def time_s(self, s_m: float) -> float:
        """Mission seconds at arc length s_m of the current leg (hover for plans not included)."""
        return (self.flown_m + s_m) / self.speed_mps + self.hold_s

    def next_event(self) -> tuple[float, bool]:
        """(time [s], True for a keyframe / False for the leg's end) of this vehicle's next event."""
        leg = self.leg_m
        if leg > 0.0 and self.s_m <= leg + 1e-9:
            return self.time_s(self.s_m), True
        return self.time_s(leg) + (HOLD_S if leg == 0.0 else 0.0), False

    def arc_m(self, t_s: float) -> float:
        """Arc length [m] flown along the current leg at mission second t_s (0 before it, the leg's
        length after)."""
        return min(max((t_s - self.time_s(0.0)) * self.speed_mps, 0.0), self.leg_m)

    def position_at(self, t_s: float) -> np.ndarray:
        leg = self.leg_m
        if leg == 0.0:
            return self.x.copy()
        return self.x + (self.wp - self.x) * (self.arc_m(t_s) / leg)


def fly_fast(sc: Scenario, planner_name: str, params: SolverParams, seed: int,
             targets_m: tuple[float, ...], planner_opts: dict | None = None,
             on_keyframe: Callable[[Keyframe, Estimate], None] | None = None, n_vehicles: int = 1) -> Outcome:
    """Fly one scenario in fast mode (see the module docstring); deterministic in (sc, planner, params, seed,
    n_vehicles).

    n_vehicles: the fleet's size (docs/fleet.md): that many vehicles fly at once from launch points
    on a ring around home, each with its own GPS error, its own gNB (sitl_scenarios.radio.CellAttachment: a
    user is ranged by the vehicle whose cell serves it) and its own planner of the mission's kind,
    coordinated by planner.fleet.FleetPlanner; one estimator takes every vehicle's keyframes.
    on_keyframe(keyframe, estimate): called with each keyframe and the estimate the run then acts on."""
    if isinstance(n_vehicles, bool) or not isinstance(n_vehicles, int) or n_vehicles < 1:
        raise CampaignError(f"n_vehicles must be a positive integer, got {n_vehicles!r}")
    users = np.array([[u.east_m, u.north_m, u.up_m] for u in sc.users], float)
    setup = MissionEstimator.from_mission(sc.mission_config(), params=params)
    noise = setup.noise
    c = sc.planning_constraints()
    opts = dict(planner_opts or {})
    if planner_name == "oracle":
        opts.setdefault("true_users_enu_m", users)
    use_kernel_cache()
    sep = Separation(sc.mission.safety.separation_m, sc.mission.safety.separation_vertical_m)
    fleet = FleetPlanner([make_planner(planner_name, sc.mission.vehicle_constraints(c, v) if n_vehicles > 1 else c,
                                       noise, rng_seed=seed + 7919 * v, **opts) for v in range(n_vehicles)], sep)
    est = setup.estimator()
    confirm = setup.confirm
    leaves = fault_departures(sc, n_vehicles)
    keyframes: list[Keyframe] = []
    gps_ss, radio_ss = np.random.SeedSequence([seed, sc.seed]).spawn(2)
    gps = [GpsError(sc.vehicle.gps_sigma_m, sc.vehicle.gps_tau_s, np.random.default_rng(
        gps_ss if v == 0 else np.random.SeedSequence([seed, sc.seed, v]))) for v in range(n_vehicles)]
    radio = RadioModel(sc, np.random.default_rng(radio_ss))
    cells = CellAttachment(users, sc.radio.coverage_m)
    speed_mps = sc.vehicle.speed_mps
    delta_m = sc.mission.flight.delta_m
    track = AccuracyTrack(users, targets_m)
    out = Outcome()
    n_ranges = n_nlos = 0
    starts = launch_points_enu_m(c.home_enu_m, n_vehicles, sep)
    flyers = [_Flyer(x=np.array([*starts[v, :2], fleet.planners[v].constraints.cruise_alt_m]),
                     wp=np.array([*starts[v, :2], fleet.planners[v].constraints.cruise_alt_m]),
                     speed_mps=speed_mps, since_kf_m=delta_m) for v in range(n_vehicles)]
    estimate: Estimate | None = None
    serving = cells.update(np.array([f.x for f in flyers]))

    def flown_total(now_s: float, at: _Flyer | None = None) -> float:
        """Metres the fleet has flown at now_s; `at` is at its next keyframe's arc length exactly."""
        return sum(g.flown_m + (g.s_m if g is at else g.arc_m(now_s) if g.flying else 0.0) for g in flyers)

    def plan(v: int, now_s: float) -> None:
        """Vehicle v at its leg's end (flyers[v].x) plans its next leg, or leaves the survey."""
        f = flyers[v]
        if f.flown_m >= c.budget_m:
            f.flying, f.reason = False, "budget spent"
            return
        committed = [None if not g.flying else np.array([g.position_at(now_s), g.wp]) for g in flyers]
        t0 = time.perf_counter()  # the planner has no clock: its compute time is timed here
        res = fleet.plan(v, PlanningState(f.x, estimate, f.flown_m), serving, committed)
        out.plan_times_s.append(time.perf_counter() - t0)
        # the mission plans the next leg PLAN_AHEAD_S before this one ends: only a plan longer than
        # that keeps the vehicle waiting (the first one is made before take-off)
        if len(out.plan_times_s) > n_vehicles:
            out.hover_s += max(0.0, out.plan_times_s[-1] - PLAN_AHEAD_S)
        if res.done:
            f.flying, f.reason = False, res.reason or "planner done"
            return
        wp = np.asarray(res.waypoint_enu_m, float)
        bad = leg_violation(c, f.x, wp, f.flown_m) if np.any(wp != f.x) else None
        if bad:
            out.violations.append(f"vehicle {v}: {bad}" if n_vehicles > 1 else bad)
        f.wp = wp
        # keyframes every Δ metres along the path: at arc lengths Δ − since_kf, 2Δ − since_kf, ...
        f.s_m = delta_m - f.since_kf_m

    for v in range(n_vehicles):
        plan(v, 0.0)
    status = reason = ""
    now_s = 0.0
    while any(f.flying for f in flyers):
        v, (now_s, is_kf) = min(((i, f.next_event()) for i, f in enumerate(flyers) if f.flying),
                                key=lambda e: (e[1][0], e[0]))
        gone = [(w, why) for w, (at_s, why) in leaves.items() if at_s <= now_s and flyers[w].flying]
        for w, why in gone:  # a fault sends this vehicle home; its cell leaves with it, the others go on
            g = flyers[w]
            arc_m, g.x = g.arc_m(now_s), g.position_at(now_s)
            g.wp = g.x
            g.flown_m += arc_m
            g.flying, g.reason = False, why
            out.events.append(f"vehicle {_vehicle_id(sc, w)}: {why} at {now_s:.1f} s: returns home")
        if gone:
            continue
        f = flyers[v]
        if not is_kf:  # the leg's end
            leg = f.leg_m
            if leg == 0.0:
                f.hold_s += HOLD_S
            else:
                f.since_kf_m = leg - (f.s_m - delta_m)
                f.flown_m += leg
            f.x = f.wp.copy()
            plan(v, now_s)
            continue
        pos = f.x + (f.wp - f.x) * (f.s_m / f.leg_m)
        if n_vehicles > 1:
            where = np.array([g.position_at(now_s) if g is not f else pos for g in flyers])
            serving = cells.update(where, np.array([g.flying for g in flyers]))
            apart, least = vehicles_apart(where[[g.flying for g in flyers]], sep)
            if not apart:
                out.violations.append(f"separation {least:.1f} m at {now_s:.1f} s")
        idx, ranges = [], []
        for k in range(len(users)):
            if serving[k] != v and n_vehicles > 1:  # another cell's user, or no cell's
                continue
            raw = radio.measure(k, pos, now_s)
            if raw is None:  # beyond coverage: no answer
                continue
            idx.append(k)
            ranges.append(range_m_from_raw(raw.ta, raw.mu, raw.srs_peak, raw.fs_hz))
            n_nlos += raw.nlos
        n_ranges += len(idx)
        kf = Keyframe(pos + gps[v].sample(now_s), np.array(idx, dtype=int), np.array(ranges, dtype=float),
                      t_s=now_s, vehicle=v)
        keyframes.append(kf)
        estimate = est.add_keyframe(kf, confirm)
        if on_keyframe is not None:
            on_keyframe(kf, estimate)
        track.update(estimate.users_enu_m[:, :2], estimate.cov_users_m2[:, :2, :2], flown_total(now_s, f),
                     now_s + out.hover_s)
        if setup.stops(estimate):  # mid-leg, as the mission stops at once
            status, reason = STATUS_TARGET, "target reached"
            flown = flown_total(now_s, f)
            break
        f.s_m += delta_m
    else:
        last = max((f for f in flyers), key=lambda f: f.time_s(f.leg_m))
        reason = last.reason
        if reason == REASON_USERS_DONE:  # every vehicle left with its users within the target
            reason = "target reached"
        status = STATUS_BUDGET if reason == "budget spent" else status_of_planner_reason(reason)
        flown = sum(f.flown_m for f in flyers)
    if est.online_failure is not None:
        out.estimator_errors.append(est.online_failure)
    final = None
    end_s = now_s if status == STATUS_TARGET else max(f.time_s(0.0) for f in flyers)
    if keyframes:  # the mission's final answer
        final = setup.final(keyframes)
        if status == STATUS_FLOOR and setup.within_target(final):  # as a flight ends such a floor
            status, reason = STATUS_TARGET, "target reached"
        track.update(final.users_enu_m[:, :2], final.cov_users_m2[:, :2, :2], flown, end_s + out.hover_s)
    out.survey_s = end_s + out.hover_s
    out.nlos_share = n_nlos / n_ranges if n_ranges else float("nan")
    # no log: the Result from the final estimate, through the mission's one constructor
    result = build_result(status=status, reason=reason, user_ids=[u.id for u in sc.users], estimate=final,
                          origin=sc.origin_geo, truth_enu_m=users, flown_m=flown, measurements=n_ranges,
                          keyframes=len(keyframes), duration_s=out.survey_s, survey_s=out.survey_s,
                          hover_s=out.hover_s)
    return track.fill(out).take_result(result)


def _vehicle_id(sc: Scenario, v: int) -> str:
    """Vehicle v's id: its `[[vehicles]]` id, else its index."""
    return sc.mission.vehicles[v].id if v < len(sc.mission.vehicles) else str(v)


def fault_departures(sc: Scenario, n_vehicles: int) -> dict[int, tuple[float, str]]:
    """{vehicle: (mission second it leaves the survey for home, why)} from the scenario's vehicle faults,
    as the mission's safety monitor decides (mission.control.safety_monitor): a link lost longer than
    `[safety] link_lost_wait_s` (it returns once that wait is over), a battery at or below
    `battery_rtl_pct`. Other faults do not end a vehicle's survey in fast mode."""
    ids = [v.id for v in sc.mission.vehicles]
    safety = sc.mission.safety
    out: dict[int, tuple[float, str]] = {}
    for ev in sc.faults.vehicle:
        v = ids.index(ev.vehicle) if ev.vehicle else 0
        if v >= n_vehicles:
            continue
        if ev.kind == "link_pause" and ev.duration_s is not None and ev.duration_s > safety.link_lost_wait_s:
            at = (ev.at_s + safety.link_timeout_s + safety.link_lost_wait_s, "link lost")
        elif ev.kind == "low_battery" and ev.battery_pct is not None and ev.battery_pct <= safety.battery_rtl_pct:
            at = (ev.at_s, f"battery {ev.battery_pct:g} %")
        else:
            continue
        if v not in out or at[0] < out[v][0]:
            out[v] = at
    return out
