"""Helpers of the `px4` tests: a second MAVLink client on PX4's GCS link that watches the vehicle
(flight mode, landed state, position, PX4's status texts) and sets parameters and injects failures
through MAVSDK's Param and Failure plugins, while uavloc flies PX4 over the API link.

The fixtures (tests/conftest.py) start PX4 itself from the user's build (UAVLOC_PX4,
sitl_scenarios.px4_sitl).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.failure import FailureAsync
from mavsdk.asyncio.plugins.param import ParamAsync
from mavsdk.asyncio.plugins.shell import ShellAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

from estimator.geodesy import Origin

#: PX4 speed factor of the tests (simulated seconds per wall second)
PX4_SPEED = 4.0
#: wall seconds PX4 gets to print "Ready for takeoff!" before a test is skipped
READY_TIMEOUT_S = 90.0


@dataclass
class Observed:
    """What the GCS-link client saw (updated in place)."""

    texts: list[str] = field(default_factory=list)
    modes: list[str] = field(default_factory=list)
    flight_mode: str = "UNKNOWN"
    landed_state: str = "UNKNOWN"
    armed: bool | None = None
    in_air_seen: bool = False
    lat_lon_alt: tuple[float, float, float] | None = None
    rel_alt_m: float | None = None
    home: Origin | None = None
    battery_pct: float | None = None

    def home_offset_m(self) -> float:
        """Horizontal distance of the last position from home [m] (inf when unknown)."""
        if self.home is None or self.lat_lon_alt is None:
            return math.inf
        e, n, _ = self.home.lla_to_enu(*self.lat_lon_alt)
        return float(math.hypot(e, n))

    def landed_disarmed(self) -> bool:
        return self.in_air_seen and self.landed_state == "ON_GROUND" and self.armed is False

    def text_with(self, fragment: str) -> str | None:
        for t in self.texts:
            if fragment.lower() in t.lower():
                return t
        return None


class GcsClient:
    """MAVSDK on PX4's GCS link (`udpout://127.0.0.1:18570+i`), as an async context manager."""

    def __init__(self, url: str):
        self.url = url
        self.seen = Observed()
        self._mav: Mavsdk | None = None
        self._tasks: list[asyncio.Task] = []
        self.param: ParamAsync | None = None
        self.failure: FailureAsync | None = None
        self.shell: ShellAsync | None = None
        self._system = None
        self._tel: TelemetryAsync | None = None

    async def __aenter__(self) -> GcsClient:
        self._mav = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        await self._mav.add_any_connection(self.url)
        system = await self._mav.first_autopilot(timeout_s=30.0)
        assert system is not None, f"no PX4 heartbeat on {self.url}"
        self._system = system
        self._tel = tel = TelemetryAsync(system)
        self.param, self.failure = ParamAsync(system), FailureAsync(system)
        self.shell = ShellAsync(system)
        s = self.seen

        def on_text(t) -> None:
            s.texts.append(f"{getattr(t.type, 'name', t.type)}: {t.text}")

        def on_mode(m) -> None:
            s.flight_mode = m.name
            if not s.modes or s.modes[-1] != m.name:
                s.modes.append(m.name)

        def on_landed(x) -> None:
            s.landed_state = x.name
            if x.name == "IN_AIR":
                s.in_air_seen = True

        def on_armed(a) -> None:
            s.armed = bool(a)

        def on_pos(p) -> None:
            s.lat_lon_alt = (p.latitude_deg, p.longitude_deg, p.absolute_altitude_m)
            s.rel_alt_m = p.relative_altitude_m

        def on_home(h) -> None:
            if math.isfinite(h.latitude_deg):
                s.home = Origin(h.latitude_deg, h.longitude_deg, h.absolute_altitude_m)

        def on_battery(b) -> None:
            s.battery_pct = b.remaining_percent

        for gen, fn in ((tel.subscribe_status_text(), on_text), (tel.subscribe_flight_mode(), on_mode),
                        (tel.subscribe_landed_state(), on_landed), (tel.subscribe_armed(), on_armed),
                        (tel.subscribe_position(), on_pos), (tel.subscribe_home(), on_home),
                        (tel.subscribe_battery(), on_battery)):
            self._tasks.append(asyncio.create_task(_follow(gen, fn)))
        return self

    async def __aexit__(self, *exc: object) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        self._tasks.clear()
        if self._mav is not None:
            mav, self._mav = self._mav, None
            await asyncio.to_thread(mav.destroy)

    async def wait_for(self, predicate: Callable[[Observed], bool], timeout_s: float, what: str) -> None:
        """Until predicate(seen) holds; fails the test after timeout_s wall seconds."""
        await wait_until(lambda: predicate(self.seen), timeout_s, what, lambda: self.describe())

    def describe(self) -> str:
        s = self.seen
        return (f"mode {s.flight_mode} (modes {s.modes}), landed {s.landed_state}, armed {s.armed}, "
                f"{s.home_offset_m():.1f} m from home, rel alt {s.rel_alt_m}, battery {s.battery_pct}; "
                f"PX4 said: {s.texts[-12:]}")


async def _follow(gen, fn) -> None:
    async with contextlib.aclosing(gen) as it:
        async for item in it:
            fn(item)


async def wait_until(cond: Callable[[], bool], timeout_s: float, what: str,
                     describe: Callable[[], str] | None = None) -> None:
    """Poll cond every 0.1 s; an AssertionError naming `what` after timeout_s wall seconds."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"not seen within {timeout_s:g} s: {what}"
                                 + (f" ({describe()})" if describe else ""))
        await asyncio.sleep(0.1)
