"""Geodetic <-> local ENU (docs/design.md §3), through pymap3d (WGS-84)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pymap3d

from uavloc.errors import EstimatorError


@dataclass(frozen=True)
class Origin:
    """Mission origin: the ENU frame's (0, 0, 0). Altitude AMSL [m] (treated as ellipsoidal)."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.lat_deg) and -90 <= self.lat_deg <= 90):
            raise EstimatorError(f"origin latitude must be in [-90, 90] deg, got {self.lat_deg!r}")
        if not (np.isfinite(self.lon_deg) and -180 <= self.lon_deg <= 180):
            raise EstimatorError(f"origin longitude must be in [-180, 180] deg, got {self.lon_deg!r}")
        if not np.isfinite(self.alt_m):
            raise EstimatorError(f"origin altitude must be finite, got {self.alt_m!r}")

    def lla_to_enu(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        """Geodetic (any matching shapes) -> ENU [m], shape (..., 3)."""
        e, n, u = pymap3d.geodetic2enu(
            np.asarray(lat_deg, float), np.asarray(lon_deg, float), np.asarray(alt_m, float),
            self.lat_deg, self.lon_deg, self.alt_m, deg=True,
        )
        return np.stack(np.broadcast_arrays(e, n, u), axis=-1)

    def enu_to_lla(self, pos_enu_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ENU [m] of shape (..., 3) -> (lat_deg, lon_deg, alt_m), each of shape (...)."""
        p = np.asarray(pos_enu_m, float)
        lat, lon, alt = pymap3d.enu2geodetic(
            p[..., 0], p[..., 1], p[..., 2], self.lat_deg, self.lon_deg, self.alt_m, deg=True
        )
        return np.asarray(lat), np.asarray(lon), np.asarray(alt)

    def to_dict(self) -> dict:
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "alt_m": self.alt_m}
