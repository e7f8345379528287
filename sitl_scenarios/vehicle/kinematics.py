"""Kinematics of the built-in multicopter: bounded-acceleration point mass, stopping point, the
tilt a multicopter needs for its acceleration, Euler angles to a quaternion. Pure functions on
ENU lists (metres, m/s, m/s²); no clocks.

Flight model (per axis group, time step dt):

    v_des = dir · min(v_max, sqrt(2·a·d), d/dt)      horizontal, d = distance to target
    v    += clip(v_des − v, |Δv| ≤ a·dt)               bounded acceleration
    p    += v·dt

the same vertically with the climb / descent limits.
"""

from __future__ import annotations

import math

#: longest simulation sub-step [simulated s]
MAX_SUBSTEP_S = 0.05
#: below this height [m] the vehicle is on the ground
GROUND_EPS_M = 0.05
#: gravity [m/s²]
G_MPS2 = 9.81


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
) -> tuple[list[float], float]:
    """Advance pos, vel (3,) ENU in place by dt towards a position target or at a velocity command.

    target: (3,) ENU position or None with vel_cmd: (3,) ENU velocity; v_h: horizontal speed limit,
    v_up / v_dn: climb / descent limits [m/s]; a_h, a_up, a_down: acceleration limits [m/s²]
    (MPC_ACC_HOR, MPC_ACC_UP_MAX, MPC_ACC_DOWN_MAX). On the ground a climb starts vertically.
    Returns (acceleration (3,) ENU applied [m/s²], heading [rad] from north, clockwise).
    """
    if not in_air and target is not None and target[2] > GROUND_EPS_M:
        target = [pos[0], pos[1], target[2]] if target[2] - pos[2] > 0.5 else target
    if vel_cmd is not None:
        vh = math.hypot(vel_cmd[0], vel_cmd[1])
        k = min(1.0, v_h / vh) if vh > 0 else 1.0
        des = [vel_cmd[0] * k, vel_cmd[1] * k, min(max(vel_cmd[2], -v_dn), v_up)]
    else:
        assert target is not None
        dx, dy = target[0] - pos[0], target[1] - pos[1]
        d = math.hypot(dx, dy)
        # v_des = dir · min(v_max, sqrt(2 a d), d / dt)
        s = min(v_h, math.sqrt(2 * a_h * d), d / dt) if d > 1e-6 else 0.0
        des = [dx / d * s if d > 1e-6 else 0.0, dy / d * s if d > 1e-6 else 0.0, 0.0]
        dz = target[2] - pos[2]
        # braking a climb needs downward acceleration and vice versa
        a_z = a_down if dz > 0 else a_up
        sz = min(math.sqrt(2 * a_z * abs(dz)), abs(dz) / dt)
        des[2] = min(sz, v_up) if dz > 0 else -min(sz, v_dn)
    # v += clip(v_des − v, |Δv| ≤ a dt)
    dvx, dvy = des[0] - vel[0], des[1] - vel[1]
    dvh = math.hypot(dvx, dvy)
    lim = a_h * dt
    if dvh > lim:
        dvx, dvy = dvx * lim / dvh, dvy * lim / dvh
    vel[0] += dvx
    vel[1] += dvy
    dvz = des[2] - vel[2]
    lim_z = (a_up if dvz > 0 else a_down) * dt
    dvz = min(max(dvz, -lim_z), lim_z)
    vel[2] += dvz
    acc = [dvx / dt, dvy / dt, dvz / dt]
    for k in range(3):
        pos[k] += vel[k] * dt
    if math.hypot(vel[0], vel[1]) > 0.3:
        yaw_rad = math.atan2(vel[0], vel[1])  # heading from north, clockwise
    if pos[2] <= 0.0:
        pos[2] = 0.0
        vel[2] = max(vel[2], 0.0)
        if not in_air:
            vel[0] = vel[1] = 0.0
    return acc, yaw_rad


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
