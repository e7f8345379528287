"""The simulated vehicle's true state as the simulator hands it out (a snapshot)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VehicleState:
    """A consistent snapshot of the simulated vehicle's true state.

    t_s: simulated seconds since boot; pos_enu_m, vel_enu_mps: (3,) true position / velocity in the
    origin's ENU frame; lat_deg, lon_deg, alt_m: the same position geodetic (AMSL);
    home_enu_m: (3,) home; battery_pct: 0..100; mode: MAVSDK-style flight-mode name.
    """

    t_s: float
    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    lat_deg: float
    lon_deg: float
    alt_m: float
    home_enu_m: np.ndarray
    home_lat_deg: float
    home_lon_deg: float
    home_alt_m: float
    home_set: bool
    armed: bool
    in_air: bool
    landed_state: int
    mode: str
    battery_pct: float
    gps_ok: bool
    link_up: bool
