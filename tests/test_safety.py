"""Safety gate: geofence (non-convex), no-fly zones, distance, altitude band, battery, and the
gate in front of the vehicle."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from estimator.geodesy import Origin
from mission.safety import (
    BreachWatch,
    GatedVehicle,
    SafetyGate,
    SafetyLimits,
    point_in_polygon,
    segment_crosses_boundary,
    segment_enters_polygon,
)
from sitl_scenarios.scenario import bundled_scenarios, load_scenario
from uavloc.errors import SafetyError

# an L-shaped (non-convex) fence: the square 0..100 minus the top-right quadrant 50..100 × 50..100
L_FENCE = np.array([[0, 0], [100, 0], [100, 50], [50, 50], [50, 100], [0, 100]], float)
SQUARE = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)


@pytest.mark.parametrize(
    ("point", "inside"),
    [
        ((25, 25), True), ((75, 25), True), ((25, 75), True), ((75, 75), False),
        ((-1, 50), False), ((101, 25), False), ((50, 50), True),  # reflex vertex: on the boundary
        ((0, 0), True), ((100, 25), True), ((50, 101), False), ((49.9, 99.9), True),
    ],
)
def test_point_in_non_convex_polygon(point, inside):
    assert point_in_polygon(np.array(point, float), L_FENCE) is inside


def test_point_in_polygon_agrees_with_a_dense_grid_of_the_l_shape():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-10, 110, size=(2000, 2))
    expect = ((pts >= 0) & (pts <= 100)).all(axis=1) & ~((pts[:, 0] > 50) & (pts[:, 1] > 50))
    got = np.array([point_in_polygon(p, L_FENCE) for p in pts])
    assert np.array_equal(got, expect)


@pytest.mark.parametrize(
    ("a", "b", "crosses"),
    [
        ((80, 40), (40, 80), True),   # cuts across the missing quadrant
        ((75, 25), (25, 75), False),  # only touches the reflex corner (50, 50)
        ((25, 25), (75, 25), False),
        ((25, 25), (25, 75), False),
        ((10, 90), (90, 10), False),  # through the reflex corner as well
        ((75, 40), (40, 75), True),
    ],
)
def test_leg_between_inside_points_can_leave_a_non_convex_fence(a, b, crosses):
    assert segment_crosses_boundary(np.array(a, float), np.array(b, float), L_FENCE) is crosses


@pytest.mark.parametrize(
    ("a", "b", "enters"),
    [((-5, 5), (15, 5), True), ((-5, -5), (-5, 15), False), ((5, 5), (20, 20), True),
     ((-5, 12), (12, -5), True), ((-5, 20), (20, 12), False)],
)
def test_leg_through_a_no_fly_zone(a, b, enters):
    assert segment_enters_polygon(np.array(a, float), np.array(b, float), SQUARE) is enters


def _gate(**kw) -> SafetyGate:
    base = dict(fence_enu_m=L_FENCE, no_fly_enu_m=(SQUARE + 20,), max_distance_m=120.0,
                alt_min_m=10.0, alt_max_m=60.0, battery_rtl_pct=25.0)
    base.update(kw)
    return SafetyGate(SafetyLimits(**base))


@pytest.mark.parametrize(
    ("target", "current", "reason"),
    [
        ((75, 75, 30), (25, 25, 30), "outside the geofence"),
        ((25, 75, 5), (25, 25, 30), "outside the band"),
        ((25, 75, 70), (25, 25, 30), "outside the band"),
        ((25, 25, 30), (5, 5, 30), "no-fly zone 0"),        # leg through the zone at 20..30
        ((80, 30, 30), (20, 80, 30), "leaves the geofence"),
        ((25, 28, 30), (5, 45, 30), "inside no-fly zone"),
        ((np.nan, 0, 30), None, "finite"),
    ],
)
def test_goto_refused_with_a_reason(target, current, reason):
    with pytest.raises(SafetyError, match=reason):
        _gate().check_goto(np.array(target, float), None if current is None else np.array(current, float))


def test_goto_inside_everything_passes():
    _gate().check_goto(np.array([40.0, 10.0, 30.0]), np.array([5.0, 5.0, 30.0]))


def test_max_distance_from_home():
    gate = _gate(fence_enu_m=None, no_fly_enu_m=(), max_distance_m=50.0)
    with pytest.raises(SafetyError, match="max_distance_m"):
        gate.check_goto(np.array([40.0, 40.0, 30.0]), None)
    gate.check_goto(np.array([30.0, 30.0, 30.0]), None)


def test_return_reason_battery_and_fence():
    gate = _gate()
    assert gate.return_reason(np.array([25.0, 5.0, 30.0]), 80.0) is None
    assert "battery" in gate.return_reason(np.array([25.0, 5.0, 30.0]), 20.0)
    assert "geofence" in gate.return_reason(np.array([80.0, 80.0, 30.0]), 80.0)
    # altitude is not checked while climbing unless asked
    assert gate.return_reason(np.array([25.0, 5.0, 2.0]), 80.0) is None
    assert "band" in gate.return_reason(np.array([25.0, 5.0, 2.0]), 80.0, check_altitude=True)


def test_breach_needs_consecutive_new_fixes_outside():
    """One GPS fix that reads outside the fence (noise) is not a breach; three in a row are; a
    repeated fix (same time) does not count twice; an inside fix resets the count."""
    watch = BreachWatch(_gate(), confirm_fixes=3)
    inside, outside = np.array([25.0, 5.0, 30.0]), np.array([80.0, 80.0, 30.0])
    assert watch.update(0.0, outside) is None
    assert watch.update(0.1, inside) is None  # the lone outlier is forgotten
    assert watch.update(0.2, outside) is None
    assert watch.update(0.2, outside) is None  # not a new fix
    assert watch.update(0.3, outside) is None
    reason = watch.update(0.4, outside)
    assert reason is not None and "geofence" in reason and "3 fixes in a row" in reason
    assert BreachWatch(_gate(), confirm_fixes=1).update(0.0, outside) is not None
    with pytest.raises(SafetyError, match="confirm_fixes"):
        BreachWatch(_gate(), confirm_fixes=0)


def test_breach_watch_against_gps_noise_at_a_fence_and_a_real_crossing():
    """σ = 1 m fixes 3 m inside the fence for 10 minutes at 10 Hz: single fixes read outside
    several times, confirmed breaches never; a vehicle crossing at 5 m/s is caught within
    3 fixes of its first outside fix."""
    rng = np.random.default_rng(7)
    gate = _gate(fence_enu_m=SQUARE * 10.0, no_fly_enu_m=())  # 0..100 m square
    hover = np.array([97.0, 50.0, 30.0])
    fixes = hover + rng.normal(size=(6000, 3)) * np.array([1.0, 1.0, 0.0])
    single = sum(bool(gate.position_violations(f, check_altitude=False)) for f in fixes)
    watch = BreachWatch(gate, confirm_fixes=3)
    confirmed = [watch.update(0.1 * i, f) for i, f in enumerate(fixes)]
    assert single > 3 and not any(confirmed)
    watch = BreachWatch(gate, confirm_fixes=3)
    t = np.arange(0.0, 4.0, 0.1)
    track = np.column_stack([90.0 + 5.0 * t, np.full(t.size, 50.0), np.full(t.size, 30.0)])
    track[:, :2] += rng.normal(size=(t.size, 2))
    caught = next(i for i, (ti, p) in enumerate(zip(t, track, strict=True)) if watch.update(ti, p))
    first_out = next(i for i, p in enumerate(track) if p[0] > 100.0)
    assert caught - first_out <= 4


def test_takeoff_height_in_band():
    _gate().check_takeoff(30.0)
    with pytest.raises(SafetyError, match="takeoff"):
        _gate().check_takeoff(80.0)


@pytest.mark.parametrize("path", bundled_scenarios(), ids=lambda p: p.stem)
def test_every_bundled_scenario_has_users_and_home_inside_its_limits(path):
    sc = load_scenario(path)
    gate = SafetyGate(SafetyLimits.from_mission(sc.mission_config(), sc.origin_geo))
    assert gate.position_violations(np.array([0.0, 0.0, sc.mission.altitude_m])) == []


class RecordingVehicle:
    """A vehicle that records the commands it receives (the real adapter is tested end to end)."""

    def __init__(self):
        self.commands: list[tuple] = []

    async def arm(self):
        self.commands.append(("arm",))

    async def takeoff(self, height_m):
        self.commands.append(("takeoff", height_m))

    async def goto_location(self, lat, lon, alt, yaw):
        self.commands.append(("goto", lat, lon, alt))

    async def return_to_launch(self):
        self.commands.append(("rtl",))

    async def land(self):
        self.commands.append(("land",))


def test_gated_vehicle_refuses_logs_and_never_forwards_a_bad_waypoint():
    home = Origin(47.0, 8.0, 500.0)
    events = []
    veh = RecordingVehicle()
    gv = GatedVehicle(veh, _gate(), home, lambda msg, **f: events.append((msg, f)),
                      position_enu=lambda: np.array([5.0, 5.0, 30.0]))

    async def go():
        with pytest.raises(SafetyError):
            await gv.goto_enu(np.array([75.0, 75.0, 30.0]))
        await gv.goto_enu(np.array([40.0, 10.0, 30.0]))
        await gv.return_to_launch()

    asyncio.run(go())
    assert [c[0] for c in veh.commands] == ["goto", "rtl"]
    _, lat, lon, alt = veh.commands[0]
    assert alt == pytest.approx(530.0, abs=0.01)  # home AMSL + height above home
    e, n, _u = home.lla_to_enu(lat, lon, alt)
    assert (e, n) == pytest.approx((40.0, 10.0), abs=1e-3)
    assert len(events) == 1 and events[0][1]["kind"] == "refused" and gv.refusals == 1
