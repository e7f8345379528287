"""One geometry: mission/geometry.py (shapely, closed polygons) and the planner's vectorised numpy
geometry checked against it on random seeded non-convex polygons, points and segments."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from shapely.geometry import Point

from mission import geometry
from planner import geometry as pg
from planner.types import PlanningConstraints

SQUARE = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]


def star_polygon(rng: np.random.Generator, center, n: int, r_min: float, r_max: float) -> np.ndarray:
    """A random simple (star-shaped, generally non-convex) polygon (n, 2) around center."""
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    ang += np.arange(n) * 1e-3  # no two vertices on one ray
    r = rng.uniform(r_min, r_max, n)
    return np.asarray(center, float) + np.column_stack([r * np.cos(ang), r * np.sin(ang)])


@pytest.mark.parametrize(
    ("p", "inside"),
    [((5, 5), True), ((0, 5), True), ((10, 10), True), ((10.0 + 1e-9, 5), False), ((-1, 5), False)],
)
def test_polygons_are_closed_sets(p, inside):
    assert geometry.contains_point(SQUARE, p) is inside


@pytest.mark.parametrize(
    ("a", "b", "inside", "meets"),
    [
        ((2, 2), (8, 8), True, True),
        ((0, 0), (10, 0), True, True),       # along an edge: inside the closed square, and touching it
        ((-5, 0), (0, -5), False, False),    # passes by the corner at a distance
        ((-5, 5), (5, -5), False, True),     # through the corner region: enters
        ((-5, 10), (5, 20), False, False),
        ((-5, 15), (15, -5), False, True),   # cuts across the square (east + north = 10)
        ((-5, 0), (0, 0), False, True),      # ends on the corner: touching a no-fly zone enters it
    ],
)
def test_segment_inside_and_meets_table(a, b, inside, meets):
    assert geometry.segment_inside(SQUARE, a, b) is inside
    assert geometry.segment_meets(SQUARE, a, b) is meets


def test_self_intersecting_and_short_rings_are_refused():
    with pytest.raises(geometry.GeometryError, match="not a simple polygon"):
        geometry.polygon([[0, 0], [10, 10], [10, 0], [0, 10]])
    with pytest.raises(geometry.GeometryError, match=">= 3 finite"):
        geometry.polygon([[0, 0], [1, 1]])
    with pytest.raises(geometry.GeometryError, match=">= 3 finite"):
        geometry.polygon([[0, 0], [1, np.nan], [1, 0]])


@pytest.mark.parametrize(
    ("a", "b", "blocked"),
    [
        ((-20, 5, 10), (30, 5, 0), True),
        ((-20, 5, 20), (30, 5, 20), False),   # skims the roof: heights are [0, h)
        ((-20, 0, 5), (30, 0, 5), True),      # grazes the wall at north = 0: the footprint is closed
        ((5, 5, 100), (5, 5, 0), True),       # vertical, through the roof
        ((-20, -1e-6, 5), (30, -1e-6, 5), False),
    ],
)
def test_segment_blocked_by_prism_table(a, b, blocked):
    assert geometry.segment_blocked_by_prism(a, b, SQUARE, 20.0) is blocked


def test_prism_test_agrees_with_dense_sampling_of_the_segment():
    """Reference: 4 001 points along the segment, blocked when one is inside the closed footprint
    below the roof (a random non-convex footprint, 120 seeded segments, both outcomes present)."""
    rng = np.random.default_rng(11)
    fp = star_polygon(rng, (0, 0), 9, 5, 20)
    shp = geometry.polygon(fp)
    outcomes = []
    for _ in range(120):
        a = np.r_[rng.uniform(-40, 40, 2), rng.uniform(0, 40)]
        b = np.r_[rng.uniform(-40, 40, 2), rng.uniform(0, 5)]
        pts = a + np.linspace(0, 1, 4001)[:, None] * (b - a)
        slow = bool(np.any(shapely.covers(shp, shapely.points(pts[:, :2])) & (pts[:, 2] < 12.0)))
        fast = geometry.segment_blocked_by_prism(a, b, fp, 12.0)
        assert fast is slow, (a, b)
        outcomes.append(fast)
    assert 20 <= sum(outcomes) <= 100


# ---------------------------------------------------------------------------------------------
# the planner's vectorised geometry against shapely


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planner_point_in_polygon_agrees_with_shapely(seed):
    rng = np.random.default_rng(seed)
    poly = star_polygon(rng, (0, 0), 12, 20, 100)
    pts = rng.uniform(-110, 110, size=(4000, 2))
    shp = geometry.polygon(poly)
    # the planner's boundary is "either": leave out points within 1e-9 m of an edge
    far = shapely.distance(shp.exterior, shapely.points(pts)) > 1e-9
    expect = shapely.covers(shp, shapely.points(pts))
    got = pg.point_in_polygon(pts, poly)
    assert np.array_equal(got[far], expect[far])
    assert far.sum() > 3900


@pytest.mark.parametrize("seed", [0, 1])
def test_planner_distances_agree_with_shapely(seed):
    rng = np.random.default_rng(100 + seed)
    p = rng.uniform(-50, 50, (500, 2))
    s0, s1 = rng.uniform(-50, 50, (500, 2)), rng.uniform(-50, 50, (500, 2))
    q0, q1 = rng.uniform(-50, 50, (500, 2)), rng.uniform(-50, 50, (500, 2))
    segs = shapely.linestrings(np.stack([s0, s1], axis=1))
    others = shapely.linestrings(np.stack([q0, q1], axis=1))
    np.testing.assert_allclose(pg.point_segment_distance(p, s0, s1), shapely.distance(shapely.points(p), segs),
                               atol=1e-9)
    np.testing.assert_allclose(pg.segment_segment_distance(s0, s1, q0, q1), shapely.distance(segs, others),
                               atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planner_free_space_and_leg_check_agree_with_shapely(seed):
    """in_free_space = inside the closed fence and outside every closed no-fly zone; the leg check's
    `free` = both ends free, end clearance ≥ margin, leg clearance ≥ min(margin, start clearance),
    written with shapely."""
    rng = np.random.default_rng(200 + seed)
    fence = star_polygon(rng, (0, 0), 10, 120, 200)
    zones = (star_polygon(rng, (40, 30), 7, 10, 30), star_polygon(rng, (-50, -40), 6, 8, 25))
    c = PlanningConstraints(home_enu_m=(0, 0, 0), fence_enu_m=fence, no_fly_enu_m=zones, alt_min_m=10,
                            alt_max_m=60, cruise_alt_m=30, leg_max_m=1e4, max_distance_m=1e4, budget_m=1e4,
                            margin_m=3.0)
    shp_fence = geometry.polygon(fence)
    shp_zones = [geometry.polygon(z) for z in zones]
    edges = shapely.union_all([shp_fence.exterior] + [z.exterior for z in shp_zones])

    def free(q) -> bool:
        pt = Point(q)
        return shp_fence.covers(pt) and not any(z.covers(pt) for z in shp_zones)

    pts = rng.uniform(-210, 210, (3000, 2))
    far = shapely.distance(edges, shapely.points(pts)) > 1e-9
    expect = np.array([free(q) for q in pts])
    assert np.array_equal(pg.in_free_space(pts, c)[far], expect[far])

    start_candidates = pts[expect & (shapely.distance(edges, shapely.points(pts)) > 0.5)]
    agree = 0
    for start in start_candidates[:40]:
        ends2 = rng.uniform(-210, 210, (50, 2))
        ends = np.column_stack([ends2, np.full(50, 30.0)])
        got = pg.leg_checks(c, np.r_[start, 30.0], ends, budget_left_m=1e4)["free"]
        start_clear = edges.distance(Point(start))
        legs = shapely.linestrings(np.stack([np.broadcast_to(start, ends2.shape), ends2], axis=1))
        leg_clear = shapely.distance(edges, legs)
        end_clear = shapely.distance(edges, shapely.points(ends2))
        want = (np.array([free(e) for e in ends2]) & (end_clear >= c.margin_m)
                & (leg_clear >= min(c.margin_m, start_clear)))
        # leave out legs whose clearance is within 1e-6 m of a threshold (decided by rounding)
        sharp = (np.abs(end_clear - c.margin_m) > 1e-6) & (np.abs(leg_clear - min(c.margin_m, start_clear)) > 1e-6)
        assert np.array_equal(got[sharp], want[sharp])
        agree += int(sharp.sum())
    assert agree > 1500
