"""Safety gate: nothing reaches the vehicle that it did not pass (docs/design.md §7).

Checks in the local ENU frame whose origin is home (`up` = height above home), with the plane
geometry of mission/geometry.py (shapely; polygons are closed sets):

- geofence inclusion polygon (may be non-convex), no-fly exclusion polygons, maximum horizontal
  distance from home, altitude band above home, battery threshold → RTL;
- a goto is refused when its target or the straight leg from the current position leaves the fence
  or enters a no-fly zone;
- in a fleet (docs/fleet.md), a goto is refused when its leg comes within the separation of
  another vehicle's leg (planner.fleet.legs_separated: horizontally, or by altitude layers), as the
  fence is: the fleet's planner keeps legs apart, the gate makes sure.

:class:`SafetyGate` answers with reasons (strings) and raises :class:`SafetyError`; it does no I/O.
The controller's :class:`GatedVehicle` (below) puts the gate in front of every command and logs
every refusal as an event.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from estimator.geodesy import Origin
from mission import geometry
from planner.fleet import Separation, legs_separated
from uavloc.errors import SafetyError

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# geometry (east, north) [m]: the gate's names for mission.geometry (one boundary rule: polygons
# are closed, a point on the boundary belongs to the polygon)


def point_in_polygon(p_en_m: np.ndarray, poly_en_m: np.ndarray) -> bool:
    """True when the point (2,) lies inside the polygon (P, 2) or on its boundary."""
    return geometry.contains_point(poly_en_m, p_en_m)


def point_on_boundary(p_en_m: np.ndarray, poly_en_m: np.ndarray, tol_m: float = 1e-9) -> bool:
    """True when the point (2,) lies within tol_m of one of the polygon's edges."""
    return geometry.boundary_distance_m(poly_en_m, p_en_m) <= tol_m


def segment_crosses_boundary(a_en_m: np.ndarray, b_en_m: np.ndarray, poly_en_m: np.ndarray) -> bool:
    """True when some point of the segment a–b lies outside the polygon (a straight leg between two
    inside points of a non-convex fence can still leave it; running along the edge does not)."""
    return not geometry.segment_inside(poly_en_m, a_en_m, b_en_m)


def segment_enters_polygon(a_en_m: np.ndarray, b_en_m: np.ndarray, poly_en_m: np.ndarray) -> bool:
    """True when any point of the closed segment a–b lies inside the polygon or on its boundary."""
    return geometry.segment_meets(poly_en_m, a_en_m, b_en_m)


# ---------------------------------------------------------------------------------------------
# limits and gate


@dataclass(frozen=True)
class SafetyLimits:
    """Limits in the home ENU frame.

    fence_enu_m: (P, 2) inclusion polygon or None; no_fly_enu_m: tuple of (Q, 2) exclusion polygons;
    max_distance_m: horizontal distance from home; alt_min_m/alt_max_m: band of height above home
    while surveying; battery_rtl_pct: return home below this remaining charge [%]; separation: how
    far apart a fleet's vehicles stay (None: one vehicle).
    """

    fence_enu_m: np.ndarray | None = None
    no_fly_enu_m: tuple[np.ndarray, ...] = field(default_factory=tuple)
    max_distance_m: float = 500.0
    alt_min_m: float = 10.0
    alt_max_m: float = 120.0
    battery_rtl_pct: float = 25.0
    separation: Separation | None = None

    @classmethod
    def from_mission(cls, mission, home: Origin, vehicle: int | None = None) -> SafetyLimits:
        """From a :class:`mission.config.MissionConfig` once home is known (geodetic polygons of
        the mission file become home-ENU). vehicle: a fleet's vehicle, in its own altitude band
        (mission.vehicle_band_m), kept apart from the others (`[safety] separation_m`)."""
        fence, zones = mission.geofence.polygons_enu_m(home)
        lo, hi = mission.flight.alt_min_m, mission.flight.alt_max_m
        separation = None
        if vehicle is not None:
            lo, hi = mission.vehicle_band_m(vehicle)
            if mission.fleet_size > 1:
                separation = Separation(mission.safety.separation_m, mission.safety.separation_vertical_m)
        return cls(fence_enu_m=fence, no_fly_enu_m=zones, max_distance_m=mission.geofence.max_distance_m,
                   alt_min_m=lo, alt_max_m=hi, battery_rtl_pct=mission.safety.battery_rtl_pct,
                   separation=separation)


def home_violations(polygons_enu_m: tuple[np.ndarray | None, tuple[np.ndarray, ...]]) -> list[str]:
    """:meth:`SafetyGate.home_violations` of a fence and no-fly zones in the home ENU frame, as
    `GeofenceConfig.polygons_enu_m` gives them: (fence (P, 2) or None, zones ((Q, 2), ...))."""
    fence, zones = polygons_enu_m
    return SafetyGate(SafetyLimits(fence_enu_m=fence, no_fly_enu_m=tuple(zones))).home_violations()


class SafetyGate:
    """Checks commands and states against :class:`SafetyLimits`. Pure: no I/O, no clock."""

    def __init__(self, limits: SafetyLimits):
        self.limits = limits
        try:
            self._fence = (None if limits.fence_enu_m is None
                           else geometry.polygon(limits.fence_enu_m, "geofence polygon"))
            self._no_fly = tuple(geometry.polygon(z, f"no-fly zone {i}") for i, z in enumerate(limits.no_fly_enu_m))
        except geometry.GeometryError as exc:
            raise SafetyError(str(exc)) from exc

    def position_violations(self, pos_enu_m: np.ndarray, check_altitude: bool = True,
                            alt_margin_m: float = 0.0) -> list[str]:
        """Every limit the position (3,) [m, ENU from home] breaks, as messages (empty: fine).
        `alt_margin_m` widens the altitude band (for measured heights, which wander)."""
        lim = self.limits
        p = np.asarray(pos_enu_m, float)
        out = []
        d = float(np.hypot(p[0], p[1]))
        if d > lim.max_distance_m:
            out.append(f"{d:.1f} m from home exceeds max_distance_m {lim.max_distance_m:g}")
        if self._fence is not None and not geometry.contains_point(self._fence, p[:2]):
            out.append(f"position ({p[0]:.1f}, {p[1]:.1f}) m is outside the geofence polygon")
        for i, zone in enumerate(self._no_fly):
            if geometry.contains_point(zone, p[:2]):
                out.append(f"position ({p[0]:.1f}, {p[1]:.1f}) m is inside no-fly zone {i}")
        if check_altitude and len(p) > 2 and not lim.alt_min_m - alt_margin_m <= p[2] <= lim.alt_max_m + alt_margin_m:
            out.append(f"height {p[2]:.1f} m above home is outside the band "
                       f"[{lim.alt_min_m:g}, {lim.alt_max_m:g}] m")
        return out

    def home_violations(self, home_enu_m: np.ndarray | None = None) -> list[str]:
        """Every limit a vehicle's home (where it takes off and lands) breaks, as messages (empty:
        fine): outside the fence polygon, inside a no-fly zone, or farther from the ENU origin than
        max_distance_m. home_enu_m: (3,) [m] in the limits' frame (a fleet's: the mission's origin,
        vehicle 0's home); None: the origin itself."""
        if home_enu_m is None or float(np.hypot(*np.asarray(home_enu_m, float)[:2])) < 1e-3:  # at the origin
            return [m.replace("position (0.0, 0.0) m", "home", 1)
                    for m in self.position_violations(np.zeros(3), check_altitude=False)]
        h = np.asarray(home_enu_m, float)
        where = f"position ({h[0]:.1f}, {h[1]:.1f}) m"
        return [m.replace(where, f"home {where[len('position '):]}", 1).replace(
                    "m from home exceeds", "m from the mission's origin exceeds", 1)
                for m in self.position_violations(h, check_altitude=False)]

    def check_goto(self, target_enu_m: np.ndarray, current_enu_m: np.ndarray | None,
                   others: Sequence[np.ndarray] = ()) -> None:
        """Raise :class:`SafetyError` unless the target (3,) and the straight leg from the current
        position to it stay inside every limit. others: the (2, 3) legs [from; to] the other
        vehicles of a fleet fly or hold, which the leg must stay apart from (limits.separation)."""
        t = np.asarray(target_enu_m, float)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise SafetyError(f"waypoint must be 3 finite ENU numbers, got {target_enu_m!r}")
        problems = self.position_violations(t)
        if current_enu_m is not None and not problems:
            c = np.asarray(current_enu_m, float)
            if self._fence is not None and not geometry.segment_inside(self._fence, c[:2], t[:2]):
                problems.append("the leg from the current position leaves the geofence polygon")
            for i, zone in enumerate(self._no_fly):
                if geometry.segment_meets(zone, c[:2], t[:2]):
                    problems.append(f"the leg from the current position crosses no-fly zone {i}")
        sep = self.limits.separation
        if current_enu_m is not None and sep is not None and not problems:
            leg = np.array([np.asarray(current_enu_m, float), t])
            close = sum(1 for o in others if not legs_separated(leg, np.asarray(o, float), sep))
            if close:
                whose = "another vehicle's leg" if close == 1 else f"{close} other vehicles' legs"
                problems.append(f"the leg comes within {sep.horizontal_m:g} m (and {sep.vertical_m:g} m in "
                                f"altitude) of {whose}")
        if problems:
            raise SafetyError(
                f"waypoint ({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}) m refused: " + "; ".join(problems)
            )

    def check_takeoff(self, height_m: float) -> None:
        """Raise unless the takeoff height is inside the altitude band."""
        lim = self.limits
        if not lim.alt_min_m <= height_m <= lim.alt_max_m:
            raise SafetyError(
                f"takeoff height {height_m:g} m refused: outside the band [{lim.alt_min_m:g}, {lim.alt_max_m:g}] m"
            )

    def return_reason(self, pos_enu_m: np.ndarray | None, battery_pct: float | None,
                      check_altitude: bool = False, alt_margin_m: float = 0.0) -> str | None:
        """Why the vehicle must return home now (battery low, out of the fence…), or None."""
        if battery_pct is not None and np.isfinite(battery_pct) and battery_pct < self.limits.battery_rtl_pct:
            return f"battery {battery_pct:.0f} % below battery_rtl_pct {self.limits.battery_rtl_pct:g} %"
        if pos_enu_m is not None:
            problems = self.position_violations(pos_enu_m, check_altitude=check_altitude,
                                                alt_margin_m=alt_margin_m)
            if problems:
                return "; ".join(problems)
        return None


class BreachWatch:
    """Position limits (fence, no-fly zones, distance, altitude band) judged on consecutive fixes.

    One GPS fix with σ = 1 m per axis lies 3 m off once in a few hundred, so a single fix just
    inside a fence can read outside it. A breach is confirmed when `confirm_fixes` consecutive
    new fixes (distinct times) all violate a limit — with white noise the chance that three fixes
    do so by noise alone is that single-fix chance cubed, while a vehicle that really crosses
    keeps reading outside and is caught `confirm_fixes` − 1 fixes later (a fraction of a second at
    telemetry rates). Pure: the caller feeds fixes and their times.
    """

    def __init__(self, gate: SafetyGate, confirm_fixes: int = 3):
        if int(confirm_fixes) < 1:
            raise SafetyError(f"confirm_fixes must be >= 1, got {confirm_fixes!r}")
        self.gate = gate
        self.confirm_fixes = int(confirm_fixes)
        self._last_t: float | None = None
        self._streak = 0

    def update(self, t_s: float, pos_enu_m: np.ndarray, check_altitude: bool = False,
               alt_margin_m: float = 0.0) -> str | None:
        """The confirmed breach (messages joined) after the fix at t_s, or None. A fix with the
        time of the previous one is not new and changes nothing."""
        if self._last_t is not None and t_s <= self._last_t:
            return None
        self._last_t = t_s
        reason = self.gate.return_reason(pos_enu_m, None, check_altitude=check_altitude, alt_margin_m=alt_margin_m)
        self._streak = self._streak + 1 if reason else 0
        if reason and self._streak >= self.confirm_fixes:
            return f"{reason} ({self._streak} fixes in a row)"
        return None


# ---------------------------------------------------------------------------------------------
# the gate in front of the vehicle

EventSink = Callable[..., None]


class GatedVehicle:
    """The only path from the controller to the vehicle: every command passes the gate first.

    Goto targets are ENU from home (`up` = height above home; a fleet's: the mission's ENU origin,
    vehicle 0's home) and become
    goto_location(lat, lon, alt AMSL = home AMSL + height). RTL and land are always allowed (they
    are the safe commands). A refusal is logged as an `event` (kind "refused") through `event` and
    raised as :class:`SafetyError`.
    """

    def __init__(self, vehicle, gate: SafetyGate, home: Origin, event: EventSink,
                 position_enu: Callable[[], np.ndarray | None],
                 others: Callable[[], Sequence[np.ndarray]] | None = None):
        self.vehicle = vehicle
        self.gate = gate
        self.home = home
        self._event = event
        self._position_enu = position_enu
        self._others = others
        self.refusals = 0

    def _refuse(self, exc: SafetyError, **fields) -> None:
        self.refusals += 1
        log.warning("safety gate: %s", exc)
        self._event(str(exc), kind="refused", **fields)

    async def arm(self) -> None:
        await self.vehicle.arm()

    async def takeoff(self, height_m: float) -> None:
        try:
            self.gate.check_takeoff(height_m)
        except SafetyError as exc:
            self._refuse(exc, command="takeoff")
            raise
        await self.vehicle.takeoff(height_m)

    async def goto_enu(self, target_enu_m: np.ndarray, yaw_deg: float = float("nan")) -> None:
        try:
            self.gate.check_goto(target_enu_m, self._position_enu(), self._others() if self._others else ())
        except SafetyError as exc:
            self._refuse(exc, command="goto", target_enu_m=[float(x) for x in np.ravel(target_enu_m)])
            raise
        lat, lon, alt = self.home.enu_to_lla(np.asarray(target_enu_m, float))
        # alt AMSL = home AMSL + height above home (ENU up from the home origin, to first order)
        await self.vehicle.goto_location(float(lat), float(lon), float(alt), yaw_deg)

    async def return_to_launch(self) -> None:
        await self.vehicle.return_to_launch()

    async def land(self) -> None:
        await self.vehicle.land()
