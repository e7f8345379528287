"""The floor watch (planner.stop.FloorWatch): bounds that stop shrinking above the target end the
survey as "floor reached", unless the estimate judged has not solved the window's ranges yet."""

from __future__ import annotations

import numpy as np

from planner.stop import FLOOR_MARGIN, FloorWatch


def _watch(floor_m=0.0):
    return FloorWatch(target_radius_m=3.0, floor_m=floor_m, window_m=200.0, delta_m=2.0)


def test_bounds_that_keep_shrinking_are_no_floor():
    w = _watch()
    assert not any(w.update(m, np.array([10.0 * 0.9 ** (m / 50.0)]), keyframes_used=int(m / 2) + 1)
                   for m in np.arange(0.0, 1000.0, 50.0))


def test_bounds_that_stall_over_the_window_are_a_floor():
    w = _watch()
    hits = [w.update(m, np.array([5.0]), keyframes_used=int(m / 2) + 1) for m in np.arange(0.0, 400.0, 50.0)]
    assert hits.index(True) == 4  # the first leg end 200 m after the first record


def test_an_nlos_shift_found_in_the_window_is_no_floor():
    """An NLoS excess found mid-survey widens a bound by its shift (a three_users_nlos survey: 3.7 m
    at 175 m flown, 14.2 m with an 8.1 m shift at 361 m, ended 'floor reached'): the survey goes on
    while the shift grows, and ends at the floor once neither shrinks nor grows for a window."""
    w = _watch()
    track = [(0.0, 3.7, 0.0), (50.0, 4.4, 2.0), (100.0, 7.0, 3.5), (150.0, 14.2, 8.0), (200.0, 14.8, 8.3),
             (250.0, 16.9, 9.6), (300.0, 15.9, 9.0), (350.0, 15.5, 8.6), (400.0, 15.0, 8.4), (450.0, 14.9, 8.2)]
    hits = [m for m, b, sh in track
            if w.update(m, np.array([b]), keyframes_used=int(m / 2) + 1, nlos_shift_m=np.array([sh]))]
    # 350 m: 15.5 against 14.2 at 150 m, its shift 8.6 against 8.0 (grown by less than 5 % of the bound);
    # 400 m: 15.0 against 14.8, 8.4 against 8.3; not 450 m: 14.9 against 16.9 at 250 m, shrinking
    assert hits == [350.0, 400.0]
    # without the shifts it would have ended at 200 m (14.8 against 3.7 did not shrink)
    w = _watch()
    assert next(m for m, b, _ in track if w.update(m, np.array([b]), keyframes_used=int(m / 2) + 1)) == 200.0


def test_a_lagging_estimate_is_no_floor():
    """The same stalled bounds from an estimate that still holds the keyframes of 200 m ago."""
    w = _watch()
    assert not any(w.update(m, np.array([5.0]), keyframes_used=50) for m in np.arange(0.0, 400.0, 50.0))
    # once it catches up (100 = 0.5 · 200 m / Δ keyframes more than then), the stall counts
    assert w.update(400.0, np.array([5.0]), keyframes_used=160)


def test_bounds_within_the_margin_of_the_gps_floor_end_at_once_and_below_target_never():
    w = _watch(floor_m=2.8)
    assert w.update(0.0, np.array([FLOOR_MARGIN * 2.8 - 0.01, 2.0]))
    assert not _watch(floor_m=2.8).update(0.0, np.array([2.9, 2.0]) * 1.0 - 1.0)  # all within target
    assert not _watch(floor_m=2.8).update(0.0, np.array([np.inf, 3.1]))  # an unlocated user


def test_users_near_the_gps_floor_and_a_user_stalled_higher_are_a_floor_together():
    """A target below the GPS floor (a campaign at 1.5 m, floor 2.36 m): three users settle within
    the margin of the floor while the fourth, behind a building, stalls at 5 m. Each is at its own
    floor, so the survey is (a lawnmower run flew to 1306 m of a 2500 m budget when only all-near
    or all-stalled counted)."""
    floor_m = 2.36  # FLOOR_MARGIN · floor = 2.714 m
    w = FloorWatch(target_radius_m=1.5, floor_m=floor_m, window_m=250.0, delta_m=2.0)
    three = [3.2, 3.0, 2.9, 2.80, 2.70, 2.69, 2.68, 2.67]  # within the margin from 200 m on
    hits = [m for m, b in zip(np.arange(0.0, 400.0, 50.0), three, strict=True)
            if w.update(m, np.array([5.0, b, b - 0.01, b - 0.02]), keyframes_used=int(m / 2) + 1)]
    # the stalled user counts once a window lies behind it (250 m), the three near the floor by then
    assert hits == [250.0, 300.0, 350.0]
    # a user still shrinking fast is no floor, whatever the others do
    w = FloorWatch(target_radius_m=1.5, floor_m=floor_m, window_m=250.0, delta_m=2.0)
    assert not any(w.update(m, np.array([8.0 * 0.9 ** (m / 50.0) + 3.0, 2.5]), keyframes_used=int(m / 2) + 1)
                   for m in np.arange(0.0, 700.0, 50.0))
