"""The built-in vehicle's horizontal flight model (sitl_scenarios.vehicle.kinematics): PX4's
jerk-limited auto-mode trajectory and the vehicle tracking it. Pure functions, simulated time."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from scipy.optimize import brentq

from sitl_scenarios.vehicle import kinematics as K

A_MPS2, J_MPS3, DT_S = 3.0, 4.0, K.MAX_SUBSTEP_S  # PX4 defaults MPC_ACC_HOR, MPC_JERK_AUTO


def fly_setpoint(target: list[float], v_max: float, t_s: float, sp: K.Setpoint | None = None,
                 switch: tuple[float, list[float]] | None = None) -> tuple[K.Setpoint, list]:
    """The trajectory setpoint alone (a vehicle exactly on it: no time stretch); (t, pos, vel, acc)."""
    sp = sp or K.Setpoint([0.0, 0.0])
    rec = []
    for k in range(round(t_s / DT_S)):
        if switch is not None and k * DT_S >= switch[0]:
            target = switch[1]
        K.step_setpoint(sp, list(sp.pos), target, v_max, A_MPS2, K.Tracking(), DT_S)
        rec.append(((k + 1) * DT_S, list(sp.pos), list(sp.vel), list(sp.acc)))
    return sp, rec


def fly_vehicle(length_m: float, v_max: float, t_s: float) -> tuple[list[float], list]:
    """The vehicle through kinematics.move along east at 20 m; (t, pos, vel)."""
    pos, vel, acc, sp, yaw = [0.0, 0.0, 20.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], None, 0.0
    rec = []
    for k in range(round(t_s / DT_S)):
        acc, yaw, sp = K.move(pos, vel, yaw, DT_S, [length_m, 0.0, 20.0], v_max, None, 3.0, 1.0,
                              A_MPS2, 4.0, 3.0, True, acc, sp, K.Tracking())
        rec.append(((k + 1) * DT_S, list(pos), list(vel)))
    return pos, rec


def test_max_speed_from_distance_solves_pxs_braking_equation() -> None:
    # v² = v_f² + 2a (d − v · 2a/j)
    for d, vf in ((0.0, 0.0), (0.0, 2.0), (1.0, 0.0), (15.0, 0.0), (80.0, 3.0)):
        v = K.max_speed_from_distance(J_MPS3, A_MPS2, d, vf)
        assert v * v == pytest.approx(vf * vf + 2 * A_MPS2 * (d - v * 2 * A_MPS2 / J_MPS3), abs=1e-9)
    assert K.max_speed_from_distance(J_MPS3, A_MPS2, 0.0, 0.0) == 0.0
    assert K.max_speed_from_distance(J_MPS3, A_MPS2, 10.0) < K.max_speed_from_distance(J_MPS3, A_MPS2, 20.0)


def test_long_leg_reaches_the_commanded_speed_and_holds_it() -> None:
    _, rec = fly_setpoint([300.0, 0.0], 10.0, 40.0)
    speeds = [math.hypot(*v) for _, _, v, _ in rec]
    assert max(speeds) <= 10.0 + 2e-3  # discrete steps: 1 mm/s above at most
    assert sum(abs(s - 10.0) < 2e-3 for s in speeds) * DT_S > 15.0  # cruising for > 15 s


@pytest.mark.parametrize("length_m", [5.0, 15.0, 40.0])
def test_short_leg_peak_speed_lies_between_the_closed_form_profiles(length_m: float) -> None:
    """Rest to rest with jerk j and acceleration a. Lower bound: accelerating at full rate until
    PX4's braking curve, s_acc(v) + d_brake(v) = L; upper bound: the time-optimal symmetric
    profile, 2·s_acc(v) = L. s_acc(v) = v²/(2a) + v·a/(2j) (v ≥ a²/j), v·sqrt(v/j) (below);
    d_brake(v) = (v² + 4a²/j·v) / (2a)."""
    a, j = A_MPS2, J_MPS3

    def s_acc(v: float) -> float:
        return v * v / (2 * a) + v * a / (2 * j) if v >= a * a / j else v * math.sqrt(v / j)

    v_low = brentq(lambda v: s_acc(v) + (v * v + 4 * a * a / j * v) / (2 * a) - length_m, 1e-9, 50.0)
    v_high = brentq(lambda v: 2 * s_acc(v) - length_m, 1e-9, 50.0)
    _, rec = fly_setpoint([length_m, 0.0], 12.0, 40.0)
    peak = max(math.hypot(*v) for _, _, v, _ in rec)
    assert v_low < peak < v_high


def test_acceleration_and_jerk_never_exceed_their_limits() -> None:
    # diagonal leg, then the target jumps behind the vehicle at full speed (a reposition)
    _, rec = fly_setpoint([120.0, 90.0], 10.0, 60.0, switch=(12.0, [-50.0, 0.0]))
    prev = [0.0, 0.0]
    for _, _, _, acc in rec:
        assert math.hypot(*acc) <= A_MPS2 + 1e-9
        assert math.hypot(acc[0] - prev[0], acc[1] - prev[1]) / DT_S <= J_MPS3 + 1e-9
        prev = acc
    assert math.dist(rec[-1][1], (-50.0, 0.0)) < 0.01


@pytest.mark.parametrize("length_m", [15.0, 80.0])
def test_setpoint_stops_at_the_target_without_overshoot(length_m: float) -> None:
    sp, rec = fly_setpoint([length_m, 0.0], 10.0, 40.0)
    assert max(p[0] for _, p, _, _ in rec) <= length_m + 0.01
    assert math.dist(sp.pos, (length_m, 0.0)) < 0.01 and math.hypot(*sp.vel) < 0.01


def test_setpoint_waits_for_a_vehicle_lagging_by_mpc_xy_err_max() -> None:
    sp = K.Setpoint([10.0, 0.0], [5.0, 0.0], [0.0, 0.0])
    K.step_setpoint(sp, [10.0 - 2.0, 0.0], [100.0, 0.0], 10.0, A_MPS2, K.Tracking(err_max_m=2.0), DT_S)
    assert sp.pos == [10.0, 0.0] and sp.vel == [5.0, 0.0]
    K.step_setpoint(sp, [10.0 - 1.0, 0.0], [100.0, 0.0], 10.0, A_MPS2, K.Tracking(err_max_m=2.0), DT_S)
    assert sp.pos[0] == pytest.approx(10.0 + 5.0 * DT_S / 2, abs=0.01)  # half time: 1 m of 2 m lag


def test_vehicle_reaches_cruise_on_a_long_leg_and_stops_at_the_target() -> None:
    pos, rec = fly_vehicle(300.0, 10.0, 70.0)
    speeds = [math.hypot(v[0], v[1]) for _, _, v in rec]
    assert max(speeds) == pytest.approx(10.0, abs=0.15)
    assert math.dist(pos[:2], (300.0, 0.0)) < 0.1 and speeds[-1] < 0.05
    # PX4 SITL overshoots its target by about 2 m after 10 m/s (benchmarks/px4_legs.py)
    assert max(p[0] for _, p, _ in rec) - 300.0 < 3.0


def test_vehicle_is_slower_on_short_legs_like_px4() -> None:
    # the recorded PX4 v1.18 SITL's peaks on its 15 / 40 / 80 m legs at 10 m/s (3.9 / 7.3 / 8.5 m/s)
    recorded = json.loads((Path(__file__).parent / "data" / "px4_figures.json").read_text())["legs"]["legs"]
    for length_m, px4_peak in zip((15.0, 40.0, 80.0), (leg["peak"] for leg in recorded), strict=False):
        _, rec = fly_vehicle(length_m, 10.0, 40.0)
        peak = max(math.hypot(v[0], v[1]) for _, _, v in rec)
        assert peak == pytest.approx(px4_peak, rel=0.15)
