"""Synthetic ranging problems for tests and benchmarks (pure numpy, seeded by the caller).

Geometry: a UAV at `altitude_m` flies a circle, a lawnmower or a straight line with keyframes
`delta_m` apart over users placed 40–110 m (horizontally) from the flight centre, at ground height
0. Measurements follow the estimator's model:

    x̂_n = x_n + β_n,  β white N(0, σ_gps² I), or Gauss–Markov with correlation time gps_tau_s:
          β_n = φ β_(n−1) + N(0, σ_gps² (1 − φ²) I), φ = exp(−dt_s/τ), β_0 ~ N(0, σ_gps² I)
    r̂_nk = ||x_n − u_k|| + b_k + s_k·N(0, σ(d)²) + NLoS,  s_k = noise_scale (per user or scalar),
           NLoS ~ Exp(mean) with probability p_nlos (only where the UAV's bearing from the user,
           counter-clockwise from east, lies in nlos_sector_deg = (start, width) when given: a
           building on that side of every user);  keyframe n at t_n = n·dt_s
    ô_n = x_n − x_(n−1) + N(0, σ_odom² I)    (when odom_sigma_m is given)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator.noise import NoiseModel
from estimator.types import Keyframe
from uavloc.errors import EstimatorError


@dataclass(frozen=True)
class Scenario:
    """A simulated problem: keyframes plus the truth they were drawn from."""

    keyframes: list[Keyframe]
    users_enu_m: np.ndarray  # (K, 3) true user positions [m, ENU]
    user_up_m: np.ndarray  # (K,) ground heights [m]
    uav_enu_m: np.ndarray  # (N, 3) true keyframe positions [m, ENU]
    visible: np.ndarray  # (N, K) which ranges exist
    nlos: np.ndarray  # (N, K) which ranges carry an NLoS excess


def trajectory(pattern: str, n_keyframes: int, delta_m: float = 2.0, altitude_m: float = 35.0,
               radius_m: float = 60.0) -> np.ndarray:
    """(N, 3) UAV keyframe positions [m, ENU], consecutive ones `delta_m` apart along the path."""
    s = np.arange(n_keyframes) * delta_m
    if pattern == "circle":
        ang = s / radius_m
        xy = np.stack([radius_m * np.cos(ang), radius_m * np.sin(ang)], axis=1)
    elif pattern == "line":
        xy = np.stack([s - s[-1] / 2.0, np.zeros_like(s)], axis=1)
    elif pattern == "lawnmower":
        leg, gap = 160.0, 40.0
        period = 2 * (leg + gap)
        t = np.mod(s, 4 * (leg + gap))
        xy = np.zeros((n_keyframes, 2))
        for i, ti in enumerate(t):
            lap, rem = divmod(ti, period)
            y0 = -60.0 + 2 * gap * lap
            if rem < leg:
                xy[i] = (-leg / 2 + rem, y0)
            elif rem < leg + gap:
                xy[i] = (leg / 2, y0 + rem - leg)
            elif rem < 2 * leg + gap:
                xy[i] = (leg / 2 - (rem - leg - gap), y0 + gap)
            else:
                xy[i] = (-leg / 2, y0 + gap + (rem - 2 * leg - gap))
    else:
        raise EstimatorError(f"unknown trajectory pattern {pattern!r}")
    return np.column_stack([xy, np.full(n_keyframes, altitude_m)])


def gps_error_m(rng: np.random.Generator, n: int, sigma_m: float, tau_s: float = 0.0,
                dt_s: float = 1.0) -> np.ndarray:
    """(n, 3) GPS errors at fixes dt_s apart: white (τ = 0) or stationary Gauss–Markov.

        β_0 ~ N(0, σ² I),  β_i = φ β_(i−1) + N(0, σ² (1 − φ²) I),  φ = exp(−dt/τ)
    """
    w = rng.normal(scale=sigma_m, size=(n, 3))
    if tau_s <= 0.0:
        return w
    phi = np.exp(-dt_s / tau_s)
    out = np.empty((n, 3))
    out[0] = w[0]
    q = np.sqrt(1.0 - phi * phi)
    for i in range(1, n):
        out[i] = phi * out[i - 1] + q * w[i]
    return out


def simulate(
    rng: np.random.Generator, n_users: int = 5, n_keyframes: int = 200, pattern: str = "circle",
    noise: NoiseModel | None = None, delta_m: float = 2.0, altitude_m: float = 35.0,
    p_nlos: float = 0.0, nlos_mean_m: float = 20.0, bias_m: np.ndarray | float = 0.0,
    p_visible: float = 1.0, odom_sigma_m: float | None = None, users_enu_m: np.ndarray | None = None,
    gps_tau_s: float = 0.0, dt_s: float = 1.0, noise_scale: np.ndarray | float = 1.0,
    nlos_sector_deg: tuple[float, float] | None = None,
) -> Scenario:
    """Draw one problem. All randomness comes from `rng`; see the module docstring."""
    noise = NoiseModel() if noise is None else noise
    uav = trajectory(pattern, n_keyframes, delta_m, altitude_m)
    if users_enu_m is None:
        ang = rng.uniform(0, 2 * np.pi, n_users)
        rad = rng.uniform(40.0, 110.0, n_users)
        users = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), np.zeros(n_users)])
        if pattern == "line":
            users[:, 0] = rng.uniform(-0.3, 0.3, n_users) * max(uav[-1, 0] - uav[0, 0], 1.0)
            users[:, 1] = rng.choice([-1.0, 1.0], n_users) * rng.uniform(30.0, 90.0, n_users)
    else:
        users = np.asarray(users_enu_m, float)
        n_users = users.shape[0]
    bias = np.broadcast_to(np.asarray(bias_m, float), (n_users,))
    d = np.linalg.norm(uav[:, None, :] - users[None, :, :], axis=2)
    visible = rng.uniform(size=d.shape) < p_visible
    nlos = rng.uniform(size=d.shape) < p_nlos
    if nlos_sector_deg is not None:
        start_deg, width_deg = nlos_sector_deg
        rel = uav[:, None, :2] - users[None, :, :2]
        bearing_deg = np.degrees(np.arctan2(rel[..., 1], rel[..., 0]))
        nlos &= np.mod(bearing_deg - start_deg, 360.0) < width_deg
    scale = np.broadcast_to(np.asarray(noise_scale, float), (n_users,))
    ranges = d + bias[None, :] + rng.normal(size=d.shape) * noise.range_sigma_m(d) * scale[None, :]
    ranges = ranges + nlos * rng.exponential(nlos_mean_m, size=d.shape)
    ranges = np.maximum(ranges, 0.0)
    gps = uav + gps_error_m(rng, n_keyframes, noise.sigma_gps_m, gps_tau_s, dt_s)
    odom = None
    if odom_sigma_m is not None:
        odom = np.diff(uav, axis=0, prepend=uav[:1]) + rng.normal(scale=odom_sigma_m, size=uav.shape)
    kfs = []
    for n in range(n_keyframes):
        idx = np.flatnonzero(visible[n])
        kfs.append(
            Keyframe(
                gps_enu_m=gps[n], user_idx=idx, range_m=ranges[n, idx],
                odom_enu_m=None if (odom is None or n == 0) else odom[n], t_s=float(n * dt_s),
            )
        )
    return Scenario(kfs, users, users[:, 2].copy(), uav, visible, nlos & visible)
