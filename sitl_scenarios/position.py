"""Where the simulated gNB's UAV is: a MAVLink stream (GLOBAL_POSITION_INT) or a fixed point.

A PositionSource is a callable returning the true UAV position (3,) [m, ENU] now, or None if
unknown. Used by `sitl_scenarios.gnb` (and re-exported there).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

#: A UAV position source: returns the true UAV position (3,) [m, ENU] now, or None if unknown.
PositionSource = Callable[[], "np.ndarray | None"]


class MavlinkPositionSource:
    """The UAV's position from a MAVLink stream (GLOBAL_POSITION_INT), as a PositionSource.

    url: pymavlink connection string (e.g. "udpin:0.0.0.0:14550"); origin: the ENU origin (None:
    the vehicle's home, from HOME_POSITION or, until that arrives, from the first
    GLOBAL_POSITION_INT as lat/lon and alt − relative_alt). An async context manager owning the
    connection and its polling task. Calling it returns (3,) ENU [m] or None before the first fix.
    """

    def __init__(self, url: str, origin: Origin | None = None, poll_s: float = 0.01) -> None:
        self.url = url
        self.origin = origin
        self._home_from_vehicle = origin is None
        self.poll_s = poll_s
        self._lla: tuple[float, float, float] | None = None
        self._conn: Any = None
        self._tg: asyncio.TaskGroup | None = None
        self._stop = asyncio.Event()
        self.messages = 0

    def __call__(self) -> np.ndarray | None:
        if self._lla is None or self.origin is None:
            return None
        return self.origin.lla_to_enu(*self._lla)

    async def __aenter__(self) -> MavlinkPositionSource:
        from pymavlink import mavutil

        try:
            self._conn = mavutil.mavlink_connection(self.url, source_system=245, source_component=191)
        except OSError as exc:
            raise SimulatorError(f"cannot open MAVLink stream {self.url!r}: {exc}") from exc
        self._tg = asyncio.TaskGroup()
        await self._tg.__aenter__()
        self._tg.create_task(self._poll())
        return self

    async def __aexit__(self, *exc_info) -> None:
        self._stop.set()
        assert self._tg is not None
        await self._tg.__aexit__(*exc_info)
        self._conn.close()

    def handle(self, msg: Any) -> None:
        """Apply one MAVLink message (GLOBAL_POSITION_INT or HOME_POSITION)."""
        mtype = msg.get_type()
        if mtype == "GLOBAL_POSITION_INT":
            lat, lon, alt = msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3
            if self._home_from_vehicle and self.origin is None:
                self.origin = Origin(lat, lon, alt - msg.relative_alt * 1e-3)
                log.info("ENU origin from the first fix: %s", self.origin)
            self._lla = (lat, lon, alt)
            self.messages += 1
        elif mtype == "HOME_POSITION" and self._home_from_vehicle:
            home = Origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            if home != self.origin:
                log.info("ENU origin from HOME_POSITION: %s", home)
            self.origin = home

    async def _poll(self) -> None:
        while not self._stop.is_set():
            for _ in range(1000):  # bounded burst, then yield to the loop
                msg = self._conn.recv_match(type=["GLOBAL_POSITION_INT", "HOME_POSITION"], blocking=False)
                if msg is None:
                    break
                self.handle(msg)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.poll_s):
                    await self._stop.wait()


def static_position(pos_enu_m) -> PositionSource:
    """A PositionSource that always returns the same ENU position (3,) [m]."""
    p = np.asarray(pos_enu_m, float).reshape(3)
    return lambda: p.copy()
