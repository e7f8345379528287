"""Kinematics of the built-in multicopter: a point mass flying PX4's auto-mode trajectory
(jerk-limited horizontally), stopping point, the tilt a multicopter needs for its acceleration,
Euler angles to a quaternion. Pure functions on ENU lists (metres, m/s, m/s²); no clocks.

Horizontal flight towards a position target, after PX4's FlightTaskAuto: a smoothed trajectory
setpoint sp (PositionSmoothing / VelocitySmoothing) and a vehicle that tracks it through PX4's
position and velocity controllers. Time step dt, d = horizontal distance sp → target:

    stretch = 1 − clip(|sp.p − p| / e_max, 0, 1)        if the vehicle lags behind sp, else 1
    h       = dt · stretch                               the trajectory waits for a lagging vehicle
    v_des   = dir · min(v_max, v_brake(d))               a speed that can still stop at the target
    v_brake(d): v² + (4a²/j)·v − 2·a·d = 0               PX4 TrajMath computeMaxSpeedFromDistance
    e       = v_des − sp.v
    a_des   = ê · min(a, sqrt(2·j·|e|), |e|/τ)          the acceleration from which a ramp at jerk j
                                                         ends at zero acceleration exactly on v_des
    Δa      = clip(a_des − sp.a, |Δa| ≤ j·h)             jerk-limited: |sp.a| ≤ a, |d sp.a/dt| ≤ j
    sp.v   += (sp.a + Δa/2)·h ;  sp.a += Δa ;  sp.p += sp.v·h
    v_sp    = sp.v + K_p·(sp.p − p)                      position controller (MPC_XY_P)
    a_sp    = sp.a + K_v·(v_sp − v) + I − K_d·acc        velocity controller (MPC_XY_VEL_P/D_ACC)
    a_out   = a_sp · min(1, g·tan(θ_max) / |a_sp|)       the tilt limit (MPC_TILTMAX_AIR)
    I      += K_i·((v_sp − v) − (2/K_v)·(a_sp − a_out))·dt   integral (MPC_XY_VEL_I_ACC) with PX4's
                                                         tracking anti-windup
    c_d     = c_1 + c_2·|v|                              drag per m/s of speed, linear + quadratic
    acc    += (a_out − c_d·v − acc)·dt / T_lag           attitude response T_lag
    v      += acc·dt ;  p += v·dt

(a = MPC_ACC_HOR, j = MPC_JERK_AUTO, e_max = MPC_XY_ERR_MAX, τ = max(0.1 s, 2·h) a short linear
zone against chatter; the discrete a_des is the exact form of sqrt(2·j·|e|) for this step, see
:func:`smooth_velocity`; PositionControl.cpp of PX4 for the controller; c_1, c_2 =
:data:`VEHICLE_DRAG_PER_S`, :data:`VEHICLE_DRAG_PER_M` and T_lag = :data:`VEHICLE_LAG_S`). The
drag, which PX4's velocity controller does not feed forward, is what makes PX4 SITL slow on short
legs: its speed follows the smooth trajectory to about 7.5 m/s and then creeps up as the integral
term builds; what that integral holds when the trajectory stops is what carries the vehicle past
its target. A velocity command (offboard) and the vertical axis keep a bounded-acceleration model
without jerk limit, drag or lag:

    v_des = dir · min(v_max, sqrt(2·a·d), d/dt) ;  v += clip(v_des − v, |Δv| ≤ a·dt) ;  p += v·dt
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: longest simulation sub-step [simulated s]
MAX_SUBSTEP_S = 0.05
#: below this height [m] the vehicle is on the ground
GROUND_EPS_M = 0.05
#: gravity [m/s²]
G_MPS2 = 9.81
#: time constant [s] of the acceleration following the velocity controller's command (attitude
#: and thrust response)
VEHICLE_LAG_S = 0.1
#: effective drag, acceleration −(VEHICLE_DRAG_PER_S + VEHICLE_DRAG_PER_M·|v|)·v, that PX4's
#: velocity controller does not feed forward, so that its integral term takes it over slowly:
#: fitted to the recorded PX4 SITL (v1.18-dev SIH quadrotor, ../shared/data/px4-v1.18-sih/legs) on
#: its 15-300 m legs at 10 m/s (tests/test_px4_conformance.py): the overshoot past the target and
#: the time to rest on each. There PX4 reaches about 7.5 m/s in 5 s and creeps up to 10 m/s, the
#: drag then just below what the 45° tilt limit can hold (about 1/s at 10 m/s); the speed bands
#: of that flight show less drag per m/s at low speed (about 0.75/s below 2 m/s)
VEHICLE_DRAG_PER_S = 0.73
VEHICLE_DRAG_PER_M = 0.025


@dataclass(frozen=True)
class Tracking:
    """PX4 parameters of the auto-mode trajectory and its tracking (horizontal)."""

    jerk_mps3: float = 4.0  # MPC_JERK_AUTO
    err_max_m: float = 2.0  # MPC_XY_ERR_MAX
    pos_gain: float = 0.95  # MPC_XY_P [1/s]
    vel_gain: float = 1.8  # MPC_XY_VEL_P_ACC [1/s]
    lag_s: float = VEHICLE_LAG_S
    vel_int: float = 0.4  # MPC_XY_VEL_I_ACC [1/s²]
    vel_d: float = 0.2  # MPC_XY_VEL_D_ACC [m/s² per m/s²]
    tilt_max_rad: float = math.radians(45.0)  # MPC_TILTMAX_AIR
    drag_per_s: float = VEHICLE_DRAG_PER_S
    drag_per_m: float = VEHICLE_DRAG_PER_M


@dataclass
class Setpoint:
    """PX4's smoothed horizontal trajectory setpoint: position, velocity, acceleration, each (2,)
    ENU [m, m/s, m/s²]."""

    pos: list[float]
    vel: list[float] = field(default_factory=lambda: [0.0, 0.0])
    acc: list[float] = field(default_factory=lambda: [0.0, 0.0])
    #: the velocity controller's integral term (2,) [m/s²]
    integ: list[float] = field(default_factory=lambda: [0.0, 0.0])


def max_speed_from_distance(jerk: float, accel: float, distance_m: float, final_speed: float = 0.0) -> float:
    """The largest speed [m/s] from which braking at `accel`, reached after a delay of 2·accel/jerk,
    still arrives at `final_speed` within `distance_m` (PX4 TrajMath computeMaxSpeedFromDistance):

        v² = v_f² + 2·a·(d − v·2a/j)   ⇔   v = (−b + sqrt(b² + 4·(2·a·d + v_f²))) / 2,  b = 4a²/j
    """
    b = 4.0 * accel * accel / jerk
    c = 2.0 * accel * max(distance_m, 0.0) + final_speed * final_speed
    return 0.5 * (-b + math.sqrt(b * b + 4.0 * c))


def smooth_velocity(
    vel: list[float], acc: list[float], v_des: tuple[float, float], a_max: float, j_max: float, dt: float
) -> None:
    """One jerk-limited step of the horizontal velocity (vel, acc: ENU lists, x/y used, in place)
    towards v_des (2,) [m/s]: see the module docstring. |acc| ≤ a_max and |Δacc| ≤ j_max·dt always."""
    ex, ey = v_des[0] - vel[0], v_des[1] - vel[1]
    e = math.hypot(ex, ey)
    tau = max(0.1, 2.0 * dt)
    # a_des = ê · min(a, a_j, |e| / τ), a_j the discrete form of sqrt(2 j |e|): this step's gain
    # (acc·ê + a_j)/2·dt plus the ramp down a_j²/(2j) make |e|, so the ramp never overshoots
    if e > 1e-9:
        a_par = (acc[0] * ex + acc[1] * ey) / e
        jd = 0.5 * j_max * dt
        a_j = -jd + math.sqrt(jd * jd + 2.0 * j_max * max(e - 0.5 * a_par * dt, 0.0))
        k = min(a_max, a_j, e / tau) / e
    else:
        k = 0.0
    dax, day = ex * k - acc[0], ey * k - acc[1]
    da = math.hypot(dax, day)
    lim = j_max * dt
    if da > lim:
        dax, day = dax * lim / da, day * lim / da
    # v += (acc_before + acc_after) / 2 · dt: exact for a linear acceleration ramp
    vel[0] += (acc[0] + 0.5 * dax) * dt
    vel[1] += (acc[1] + 0.5 * day) * dt
    acc[0] += dax
    acc[1] += day


def step_setpoint(
    sp: Setpoint, pos: list[float], target: list[float], v_h: float, a_h: float, trk: Tracking, dt: float
) -> None:
    """Advance the trajectory setpoint sp in place by dt towards target (x, y used): the first
    block of the module docstring (time stretch, v_brake, jerk-limited smoothing)."""
    ex, ey = sp.pos[0] - pos[0], sp.pos[1] - pos[1]
    stretch = 1.0
    if trk.err_max_m > 0 and ex * sp.vel[0] + ey * sp.vel[1] >= 0:
        stretch = 1.0 - min(max(math.hypot(ex, ey) / trk.err_max_m, 0.0), 1.0)
    h = dt * stretch
    if h <= 0:
        return
    dx, dy = target[0] - sp.pos[0], target[1] - sp.pos[1]
    d = math.hypot(dx, dy)
    s = min(v_h, max_speed_from_distance(trk.jerk_mps3, a_h, d)) if d > 1e-6 else 0.0
    v_des = (dx / d * s, dy / d * s) if d > 1e-6 else (0.0, 0.0)
    smooth_velocity(sp.vel, sp.acc, v_des, a_h, trk.jerk_mps3, h)
    sp.pos[0] += sp.vel[0] * h
    sp.pos[1] += sp.vel[1] * h


def move(
    pos: list[float],
    vel: list[float],
    yaw_rad: float,
    dt: float,
    target: list[float] | None,
    v_h: float,
    vel_cmd: list[float] | None,
    v_up: float,
    v_dn: float,
    a_h: float,
    a_up: float,
    a_down: float,
    in_air: bool,
    acc_prev: list[float],
    sp: Setpoint | None,
    trk: Tracking,
) -> tuple[list[float], float, Setpoint | None]:
    """Advance pos, vel (3,) ENU in place by dt towards a position target or at a velocity command.

    target: (3,) ENU position or None with vel_cmd: (3,) ENU velocity; v_h: horizontal speed limit,
    v_up / v_dn: climb / descent limits [m/s]; a_h, a_up, a_down: acceleration limits [m/s²]
    (MPC_ACC_HOR, MPC_ACC_UP_MAX, MPC_ACC_DOWN_MAX); acc_prev: (3,) ENU acceleration of the
    previous step; sp: the trajectory setpoint towards a position target (None: starts at the
    vehicle's state, as PX4 resets it when a flight task starts); trk: its PX4 parameters.
    On the ground a climb starts vertically.
    Returns (acceleration (3,) ENU applied [m/s²], heading [rad] from north clockwise, setpoint:
    None when flying a velocity command or on the ground).
    """
    if not in_air and target is not None and target[2] > GROUND_EPS_M:
        target = [pos[0], pos[1], target[2]] if target[2] - pos[2] > 0.5 else target
    if vel_cmd is not None:
        vh = math.hypot(vel_cmd[0], vel_cmd[1])
        k = min(1.0, v_h / vh) if vh > 0 else 1.0
        des = [vel_cmd[0] * k, vel_cmd[1] * k, min(max(vel_cmd[2], -v_dn), v_up)]
        # v += clip(v_des − v, |Δv| ≤ a dt)
        dvx, dvy = des[0] - vel[0], des[1] - vel[1]
        dvh = math.hypot(dvx, dvy)
        lim = a_h * dt
        if dvh > lim:
            dvx, dvy = dvx * lim / dvh, dvy * lim / dvh
        acc = [dvx / dt, dvy / dt, 0.0]
        vel[0] += dvx
        vel[1] += dvy
        sp = None
    else:
        assert target is not None
        c_d = trk.drag_per_s + trk.drag_per_m * math.hypot(vel[0], vel[1])
        if sp is None:  # the integral term starts holding the drag of the current velocity
            sp = Setpoint([pos[0], pos[1]], [vel[0], vel[1]], [acc_prev[0], acc_prev[1]],
                          [c_d * vel[0], c_d * vel[1]])
        step_setpoint(sp, pos, target, v_h, a_h, trk, dt)
        k = min(1.0, dt / trk.lag_s) if trk.lag_s > 0 else 1.0
        # v_sp = sp.v + K_p (sp.p − p) ; a_sp = sp.a + K_v (v_sp − v) + I − K_d acc
        err = [sp.vel[i] + trk.pos_gain * (sp.pos[i] - pos[i]) - vel[i] for i in range(2)]
        a_sp = [sp.acc[i] + trk.vel_gain * err[i] + sp.integ[i] - trk.vel_d * acc_prev[i] for i in range(2)]
        # a_out = a_sp limited to the tilt; I += K_i ((v_sp − v) − 2/K_v (a_sp − a_out)) dt
        n_sp = math.hypot(a_sp[0], a_sp[1])
        a_max = G_MPS2 * math.tan(trk.tilt_max_rad)
        a_out = [a * a_max / n_sp for a in a_sp] if n_sp > a_max else a_sp
        arw = 2.0 / trk.vel_gain
        acc = [0.0, 0.0, 0.0]
        for i in range(2):
            sp.integ[i] += trk.vel_int * (err[i] - arw * (a_sp[i] - a_out[i])) * dt
            # acc += (a_out − c_d v − acc) · dt / T_lag
            acc[i] = acc_prev[i] + (a_out[i] - c_d * vel[i] - acc_prev[i]) * k
            vel[i] += acc[i] * dt
        dz = target[2] - pos[2]
        # braking a climb needs downward acceleration and vice versa
        a_z = a_down if dz > 0 else a_up
        sz = min(math.sqrt(2 * a_z * abs(dz)), abs(dz) / dt)
        des = [0.0, 0.0, min(sz, v_up) if dz > 0 else -min(sz, v_dn)]
    dvz = des[2] - vel[2]
    lim_z = (a_up if dvz > 0 else a_down) * dt
    dvz = min(max(dvz, -lim_z), lim_z)
    vel[2] += dvz
    acc[2] = dvz / dt
    for k in range(3):
        pos[k] += vel[k] * dt
    if math.hypot(vel[0], vel[1]) > 0.3:
        yaw_rad = math.atan2(vel[0], vel[1])  # heading from north, clockwise
    if pos[2] <= 0.0:
        pos[2] = 0.0
        vel[2] = max(vel[2], 0.0)
        if not in_air:
            vel[0] = vel[1] = 0.0
            acc[0] = acc[1] = 0.0
            sp = None
    return acc, yaw_rad, sp


def stopping_point(pos: list[float], vel: list[float], a_h: float) -> list[float]:
    """Where the vehicle comes to rest braking at a_h [m/s²]: p + v·|v| / (2a), not below ground."""
    vh = math.hypot(vel[0], vel[1])
    k = vh / (2 * a_h) if a_h > 0 else 0.0
    return [pos[0] + vel[0] * k, pos[1] + vel[1] * k, max(pos[2], 0.0)]


def tilt_rad(acc: list[float], yaw_rad: float) -> tuple[float, float]:
    """(roll, pitch) [rad] a multicopter needs for its horizontal acceleration acc (3,) ENU (no
    wind): pitch = −atan(a_forward / g), roll = atan(a_right / g), forward along the heading."""
    s, c = math.sin(yaw_rad), math.cos(yaw_rad)
    a_fwd = acc[1] * c + acc[0] * s
    a_right = -acc[1] * s + acc[0] * c
    return math.atan2(a_right, G_MPS2), -math.atan2(a_fwd, G_MPS2)


def quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the ZYX Euler angles (aerospace convention, body FRD in NED)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def wrap_pi(a: float) -> float:
    """An angle [rad] in [−π, π)."""
    return (a + math.pi) % (2 * math.pi) - math.pi
