"""The one plane geometry of fences, no-fly zones and buildings, on shapely (GEOS).

The safety gate (mission/safety.py) and the simulated radio's line-of-sight test
(sitl_scenarios/radio.py) both ask these functions, so there is one boundary rule:

    **a polygon is a closed set: a point on its boundary belongs to it.**

So a vehicle on the fence line is inside the fence (allowed), a vehicle on a no-fly zone's edge is
inside the zone (refused), a leg that runs along the fence stays inside, a leg that touches a no-fly
zone's corner enters it, and a line of sight that grazes a building's wall below its roof is
blocked. Heights are the exception, and say so: a building occupies heights [0, height_m), so a
line of sight that skims the roof exactly is clear.

Coordinates are east-north metres in one local frame (home ENU for the safety gate, the scenario's
ENU for the radio). Rings are open ([[e, n], ...], the closing edge implied), ≥ 3 vertices, and
must be simple (no self-intersection); anything else is a :class:`GeometryError`.

The planner keeps its own vectorised numpy geometry (planner/geometry.py: planner code stays free
of shapely); tests/test_geometry.py checks it against these functions on random seeded polygons.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import shapely
from shapely.geometry import LineString, Point, Polygon

from uavloc.errors import MissionError


class GeometryError(MissionError):
    """A polygon that cannot be used (too few vertices, not finite, self-intersecting)."""


def polygon(ring_en_m: Sequence[Sequence[float]] | np.ndarray, name: str = "polygon") -> Polygon:
    """A shapely polygon from an open ring (P, 2) [m]; prepared for repeated predicates."""
    ring = np.asarray(ring_en_m, dtype=float)
    if ring.ndim != 2 or ring.shape[1] != 2 or ring.shape[0] < 3 or not np.all(np.isfinite(ring)):
        raise GeometryError(f"{name} needs >= 3 finite [east, north] vertices, got {np.asarray(ring_en_m).tolist()!r}")
    poly = Polygon(ring)
    if not poly.is_valid:
        raise GeometryError(f"{name} is not a simple polygon ({shapely.is_valid_reason(poly)}): {ring.tolist()!r}")
    shapely.prepare(poly)
    return poly


@functools.lru_cache(maxsize=256)
def _cached_polygon(ring: tuple[tuple[float, float], ...]) -> Polygon:
    return polygon(ring)


def _poly(p: Polygon | Sequence | np.ndarray) -> Polygon:
    """A polygon given as shapely or as a ring; rings are built (and validated) once per content."""
    if isinstance(p, Polygon):
        return p
    return _cached_polygon(tuple(map(tuple, np.asarray(p, dtype=float).tolist())))


def _segment(a_en_m, b_en_m):
    a = np.asarray(a_en_m, dtype=float)[:2]
    b = np.asarray(b_en_m, dtype=float)[:2]
    return Point(a) if np.array_equal(a, b) else LineString([a, b])


def contains_point(poly: Polygon | Sequence | np.ndarray, p_en_m) -> bool:
    """True when the point (2,) [m] is inside the polygon or on its boundary."""
    return bool(_poly(poly).covers(Point(np.asarray(p_en_m, dtype=float)[:2])))


def boundary_distance_m(poly: Polygon | Sequence | np.ndarray, p_en_m) -> float:
    """Distance [m] from the point (2,) to the polygon's boundary (its edges), inside or out."""
    return float(_poly(poly).exterior.distance(Point(np.asarray(p_en_m, dtype=float)[:2])))


def segment_inside(poly: Polygon | Sequence | np.ndarray, a_en_m, b_en_m) -> bool:
    """True when every point of the closed segment a–b (each (2,)) is inside the polygon or on its
    boundary (a straight leg between two inside points of a non-convex fence can still leave it)."""
    return bool(_poly(poly).covers(_segment(a_en_m, b_en_m)))


def segment_meets(poly: Polygon | Sequence | np.ndarray, a_en_m, b_en_m) -> bool:
    """True when some point of the closed segment a–b (each (2,)) is inside the polygon or on its
    boundary (a leg that enters, or touches, a no-fly zone)."""
    return bool(_poly(poly).intersects(_segment(a_en_m, b_en_m)))


def segment_blocked_by_prism(a_enu_m, b_enu_m, footprint: Polygon | Sequence | np.ndarray, height_m: float) -> bool:
    """Does the 3-D segment a → b (each (3,) ENU [m]) pass through the prism footprint × [0, height_m)?

    The segment's plan view meets the closed footprint in points and pieces; along the segment the
    height is linear, z(s) = a_u + s·(b_u − a_u) with s = (p − a)·(b − a)/|b − a|² in the plan
    view, so the lowest point of each piece is at one of its ends: blocked when that is below the
    roof.
    """
    a3 = np.asarray(a_enu_m, dtype=float)
    b3 = np.asarray(b_enu_m, dtype=float)
    fp = _poly(footprint)
    h = float(height_m)
    ab = b3[:2] - a3[:2]
    L2 = float(ab @ ab)
    if L2 < 1e-18:  # vertical segment
        return contains_point(fp, a3[:2]) and bool(min(a3[2], b3[2]) < h)
    meet = fp.intersection(LineString([a3[:2], b3[:2]]))
    for piece in shapely.get_parts(meet):
        ends = np.asarray(piece.coords, dtype=float)
        if len(ends) == 0:
            continue
        s = np.clip((ends - a3[:2]) @ ab / L2, 0.0, 1.0)
        z = a3[2] + s * (b3[2] - a3[2])
        if float(np.min(z)) < h - 1e-9:
            return True
    return False
