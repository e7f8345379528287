"""Plane geometry for the planner: polygons, segment distances, the exact leg check, convex cells.

All functions are vectorized numpy on east-north coordinates [m]. The exact check
(:func:`leg_checks`) is the single source of truth on whether a straight leg may be flown; every
planner runs it on its answer. :func:`convex_cell` gives IPOPT a convex, smooth stand-in for the
non-convex free space around a seed leg (the exact check still has the last word).
"""

from __future__ import annotations

import numpy as np

from planner.types import PlanningConstraints

_EPS = 1e-12
#: slack on the exact check [m] (IPOPT's constraint tolerance is far below this).
CHECK_TOL_M = 1e-6


def point_in_polygon(points_m: np.ndarray, polygon_m: np.ndarray) -> np.ndarray:
    """Even-odd rule. points_m: (..., 2); polygon_m: (P, 2) → (...,) bool (boundary: either)."""
    pts = np.asarray(points_m, dtype=float)
    x, y = pts[..., 0:1], pts[..., 1:2]
    x0, y0 = polygon_m[:, 0], polygon_m[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    # an edge crosses the horizontal ray to +x when its ends straddle y and the crossing is right of x
    straddle = (y0 > y) != (y1 > y)
    dy = np.where(y1 - y0 == 0, 1.0, y1 - y0)
    x_cross = x0 + (y - y0) * (x1 - x0) / dy
    return (np.sum(straddle & (x < x_cross), axis=-1) % 2) == 1


def point_segment_distance(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    """Distance from points to segments (broadcast). p, s0, s1: (..., 2) → (...,) [m].

    t* = clip(((p − s0)·(s1 − s0)) / |s1 − s0|², 0, 1);  d = |p − s0 − t*(s1 − s0)|
    """
    v = s1 - s0
    w = p - s0
    t = np.clip(np.sum(w * v, axis=-1) / np.maximum(np.sum(v * v, axis=-1), _EPS), 0.0, 1.0)
    return np.linalg.norm(w - t[..., None] * v, axis=-1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def segment_segment_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Distance between segments a0–a1 and b0–b1 (broadcast over leading axes) → (...,) [m].

    0 when they cross (orientation test); otherwise the smallest of the four end-to-segment distances.
    """
    d = np.minimum(
        np.minimum(point_segment_distance(a0, b0, b1), point_segment_distance(a1, b0, b1)),
        np.minimum(point_segment_distance(b0, a0, a1), point_segment_distance(b1, a0, a1)),
    )
    da, db = a1 - a0, b1 - b0
    o1, o2 = _cross(da, b0 - a0), _cross(da, b1 - a0)
    o3, o4 = _cross(db, a0 - b0), _cross(db, a1 - b0)
    crossing = (o1 * o2 < 0) & (o3 * o4 < 0)
    return np.where(crossing, 0.0, d)


def clearance_m(points_m: np.ndarray, constraints: PlanningConstraints) -> np.ndarray:
    """(...,) distance of east-north points (..., 2) to the nearest fence or no-fly edge (inf: none)."""
    e0, e1 = constraints.edges_enu_m
    pts = np.asarray(points_m, dtype=float)
    if len(e0) == 0:
        return np.full(pts.shape[:-1], np.inf)
    return np.min(point_segment_distance(pts[..., None, :], e0, e1), axis=-1)


def in_free_space(points_m: np.ndarray, constraints: PlanningConstraints) -> np.ndarray:
    """(...,) bool: east-north points inside the fence polygon (if any) and outside every no-fly zone."""
    pts = np.asarray(points_m, dtype=float)
    ok = np.ones(pts.shape[:-1], dtype=bool)
    if len(constraints.fence_enu_m):
        ok &= point_in_polygon(pts, constraints.fence_enu_m)
    for zone in constraints.no_fly_enu_m:
        ok &= ~point_in_polygon(pts, zone)
    return ok


def leg_checks(
    constraints: PlanningConstraints,
    start_enu_m: np.ndarray,
    ends_enu_m: np.ndarray,
    budget_left_m: float,
    energy_m: float = np.inf,
) -> dict[str, np.ndarray]:
    """The exact check of straight legs start → end; each entry (C,) bool, True = satisfied.

    start_enu_m: (3,); ends_enu_m: (C, 3). Checks (c = constraints):
      leg:       |end − start| ≤ min(c.leg_max_m, budget_left_m)
      altitude:  c.alt_min_m ≤ end_up ≤ c.alt_max_m (the start is where the UAV is)
      distance:  |end_en − home_en| ≤ c.max_distance_m (a disc, so the whole leg is inside)
      energy:    |end − start| + c.return_factor·|end − home| ≤ energy_m
      free:      end inside the fence and outside every no-fly zone, with clearance ≥ c.margin_m
                 from every edge, and the leg keeps clearance ≥ min(c.margin_m, clearance(start))
                 from every edge, so it crosses none (a start already closer than the margin,
                 e.g. after a tracking error, may still leave)
    """
    c = constraints
    x = np.asarray(start_enu_m, dtype=float).reshape(3)
    ends = np.atleast_2d(np.asarray(ends_enu_m, dtype=float))
    length = np.linalg.norm(ends - x, axis=1)
    tol = CHECK_TOL_M
    out = {
        "leg": length <= min(c.leg_max_m, budget_left_m) + tol,
        "altitude": (ends[:, 2] >= c.alt_min_m - tol) & (ends[:, 2] <= c.alt_max_m + tol),
        "distance": np.linalg.norm(ends[:, :2] - c.home_enu_m[:2], axis=1) <= c.max_distance_m + tol,
        "energy": length + c.return_factor * np.linalg.norm(ends - c.home_enu_m, axis=1) <= energy_m + tol,
    }
    free = in_free_space(ends[:, :2], c) & bool(in_free_space(x[:2], c))
    e0, e1 = c.edges_enu_m
    if len(e0):
        start_clear = float(np.min(point_segment_distance(x[:2], e0, e1)))
        need_leg = min(c.margin_m, start_clear) - tol
        seg = segment_segment_distance(x[None, None, :2], ends[:, None, :2], e0[None], e1[None])  # (C, E)
        end_clear = np.min(point_segment_distance(ends[:, None, :2], e0[None], e1[None]), axis=1)
        free &= (np.min(seg, axis=1) >= need_leg) & (end_clear >= c.margin_m - tol)
    out["free"] = free
    return out


def legs_feasible(
    constraints: PlanningConstraints,
    start_enu_m: np.ndarray,
    ends_enu_m: np.ndarray,
    budget_left_m: float,
    energy_m: float = np.inf,
) -> np.ndarray:
    """(C,) bool: legs start → ends (C, 3) that pass every check of :func:`leg_checks`."""
    checks = leg_checks(constraints, start_enu_m, ends_enu_m, budget_left_m, energy_m)
    return np.logical_and.reduce(list(checks.values()))


def leg_violations(
    constraints: PlanningConstraints,
    start_enu_m: np.ndarray,
    end_enu_m: np.ndarray,
    budget_left_m: float,
    energy_m: float = np.inf,
) -> list[str]:
    """Names of the checks one leg start → end (3,) fails; empty when it may be flown."""
    checks = leg_checks(constraints, start_enu_m, np.reshape(end_enu_m, (1, 3)), budget_left_m, energy_m)
    return [name for name, ok in checks.items() if not ok[0]]


def _closest_points(a0, a1, b0, b1) -> tuple[np.ndarray, np.ndarray, float]:
    """Closest pair (point on a, point on b, distance) of two non-crossing segments (each (2,))."""
    best = (None, None, np.inf)
    for p, s0, s1, p_on_a in ((a0, b0, b1, True), (a1, b0, b1, True), (b0, a0, a1, False), (b1, a0, a1, False)):
        v = s1 - s0
        t = np.clip(np.dot(p - s0, v) / max(np.dot(v, v), _EPS), 0.0, 1.0)
        q = s0 + t * v
        d = float(np.linalg.norm(p - q))
        if d < best[2]:
            best = (p, q, d) if p_on_a else (q, p, d)
    return best


def convex_cell(
    constraints: PlanningConstraints, a_m: np.ndarray, b_m: np.ndarray, max_planes: int
) -> tuple[np.ndarray, np.ndarray]:
    """Half-planes {x : A x ≤ c} around the free seed segment a → b (east-north, (2,) each).

    For each fence / no-fly edge, nearest first, that the planes so far do not already keep at
    least `margin_m` away: take the closest points s (on the seed) and q (on the edge),
    n = (q − s)/|q − s|, and add  n·x ≤ n·q − m  with m = min(margin_m, |q − s|). The plane through
    q normal to the shortest connecting vector separates the two segments, so the seed stays inside
    and the edge outside; the intersection is convex and crosses no edge, so it lies in the free
    space component of the seed. Returns A (H, 2), c (H,) with H ≤ max_planes (nearest kept first;
    the exact check catches anything beyond).
    """
    e0, e1 = constraints.edges_enu_m
    a, b = np.asarray(a_m, dtype=float), np.asarray(b_m, dtype=float)
    if len(e0) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    dist = segment_segment_distance(a[None], b[None], e0, e1)
    normals, offsets = [], []
    for i in np.argsort(dist):
        if len(normals) >= max_planes:
            break
        if normals:
            A, c = np.array(normals), np.array(offsets)
            # an edge is already excluded when both its ends lie beyond one plane by the margin
            beyond = (A @ e0[i] >= c + constraints.margin_m) & (A @ e1[i] >= c + constraints.margin_m)
            if np.any(beyond):
                continue
        s, q, d = _closest_points(a, b, e0[i], e1[i])
        if d <= _EPS:
            continue  # the seed touches this edge; the exact check will refuse anything crossing it
        n = (q - s) / d
        normals.append(n)
        offsets.append(float(n @ q) - min(constraints.margin_m, d))
    if not normals:
        return np.zeros((0, 2)), np.zeros(0)
    return np.array(normals), np.array(offsets)


def _graph_nodes(constraints: PlanningConstraints) -> np.ndarray:
    """(N, 2) routing nodes: every fence / no-fly vertex pushed off its corner by margin + 1 m along
    both directions of its bisector, kept where free with clearance ≥ margin."""
    c = constraints
    polys = ([c.fence_enu_m] if len(c.fence_enu_m) else []) + list(c.no_fly_enu_m)
    nodes = []
    for poly in polys:
        prev, nxt = np.roll(poly, 1, axis=0), np.roll(poly, -1, axis=0)
        u1 = (prev - poly) / np.maximum(np.linalg.norm(prev - poly, axis=1, keepdims=True), _EPS)
        u2 = (nxt - poly) / np.maximum(np.linalg.norm(nxt - poly, axis=1, keepdims=True), _EPS)
        bis = u1 + u2
        # a straight vertex has no bisector: use the edge normal
        flat = np.linalg.norm(bis, axis=1) < 1e-6
        bis[flat] = np.column_stack([-u2[flat, 1], u2[flat, 0]])
        bis /= np.linalg.norm(bis, axis=1, keepdims=True)
        # far enough that the clearance from both adjacent edges is ≥ margin + 1 m even at sharp corners
        half_angle = np.arccos(np.clip(np.sum(u1 * u2, axis=1), -1.0, 1.0)) / 2
        step = (c.margin_m + 1.0) / np.maximum(np.sin(half_angle), 0.2)
        nodes += [poly + step[:, None] * bis, poly - step[:, None] * bis]
    if not nodes:
        return np.zeros((0, 2))
    pts = np.concatenate(nodes)
    ok = in_free_space(pts, c) & (clearance_m(pts, c) >= c.margin_m)
    ok &= np.linalg.norm(pts - c.home_enu_m[:2], axis=1) <= c.max_distance_m
    return pts[ok]


def route_en(constraints: PlanningConstraints, start_en_m: np.ndarray, goal_en_m: np.ndarray) -> np.ndarray | None:
    """Shortest free polyline start → goal (east-north) on a visibility graph, or None.

    Nodes: start, goal and the pushed-off polygon corners (:func:`_graph_nodes`); an edge is a
    straight segment whose clearance from every fence / no-fly edge is ≥ margin (from the start:
    ≥ min(margin, clearance(start))) and whose ends are inside the distance disc. Dijkstra on
    Euclidean lengths. Returns (P, 2) waypoints after the start, ending at the goal.
    """
    c = constraints
    a, b = np.asarray(start_en_m, dtype=float)[:2], np.asarray(goal_en_m, dtype=float)[:2]
    nodes = np.concatenate([a[None], b[None], _graph_nodes(c)])
    n = len(nodes)
    e0, e1 = c.edges_enu_m
    if len(e0):
        seg = segment_segment_distance(nodes[:, None, None], nodes[None, :, None], e0[None, None], e1[None, None])
        clear = seg.min(axis=2)  # (n, n)
        need = np.full((n, n), c.margin_m - CHECK_TOL_M)
        need[0, :] = need[:, 0] = min(c.margin_m, float(clearance_m(a, c))) - CHECK_TOL_M
        visible = clear >= need
    else:
        visible = np.ones((n, n), dtype=bool)
    length = np.linalg.norm(nodes[:, None] - nodes[None, :], axis=2)
    cost = np.where(visible, length, np.inf)
    np.fill_diagonal(cost, np.inf)
    # Dijkstra (dense, n is a few dozen)
    dist, prev, done = np.full(n, np.inf), np.full(n, -1), np.zeros(n, dtype=bool)
    dist[0] = 0.0
    for _ in range(n):
        i = int(np.argmin(np.where(done, np.inf, dist)))
        if not np.isfinite(dist[i]) or i == 1:
            break
        done[i] = True
        better = dist[i] + cost[i] < dist
        dist[better], prev[better] = dist[i] + cost[i][better], i
    if not np.isfinite(dist[1]):
        return None
    path, i = [], 1
    while i != 0:
        path.append(nodes[i])
        i = int(prev[i])
    return np.array(path[::-1])
