"""The survey's own account of its time: hover and the longest stretch without a range."""

from __future__ import annotations

import pytest

from mission.control.state import HOVER_SPEED_MPS, SurveyClock


def test_hover_is_the_time_slower_than_the_threshold_during_the_survey_only():
    c = SurveyClock()
    c.fix(0.0, 0.0)  # before the survey: not counted
    c.t0_s = 10.0
    speeds = [5.0] * 10 + [0.1] * 5 + [5.0] * 5  # 1 s apart: 5 s of hover (the Δt after each slow fix)
    for i, v in enumerate(speeds):
        c.fix(10.0 + i, v)
    c.end(30.0)
    c.fix(31.0, 0.0)  # after it: not counted
    assert c.hover_s == pytest.approx(5.0) and c.survey_s == pytest.approx(20.0)
    assert HOVER_SPEED_MPS == 0.5


def test_fixes_stamped_out_of_order_never_make_hover_exceed_the_survey():
    """Seen under load (`uavloc fly --view` on a loaded machine): fix stamps 87.3 s then 85.9 s, and
    a survey of 60 s said it hovered 102 s (170 %). Going back adds nothing; going forward again
    counts only past the latest fix."""
    c = SurveyClock()
    c.t0_s = 0.0
    for t in (0.0, 10.0, 8.0, 10.5, 9.0, 12.0):
        c.fix(t, 0.0)
    c.end(12.0)
    assert c.hover_s == pytest.approx(12.0) and c.hover_s <= c.survey_s


def test_the_largest_gap_counts_from_the_start_and_to_the_end():
    c = SurveyClock()
    c.t0_s = 100.0
    for t in (101.0, 102.0, 107.5, 108.0):
        c.range_at(t)
    c.range_at(107.9)  # a round timed before the last one does not shrink the gaps
    assert c.largest_gap_s == pytest.approx(5.5)
    c.end(120.0)
    assert c.largest_gap_s == pytest.approx(12.0)
    c.range_at(200.0)  # after the end: ignored
    assert c.largest_gap_s == pytest.approx(12.0)


def test_the_gap_to_the_end_stops_at_the_stop_rule():
    """A three_users_nlos run: the last range 0.06 s before "target reached" at 247.98 s, then 3.2 s
    to confirm the final answer and command RTL: no ranging was due then, so no gap."""
    c = SurveyClock()
    c.t0_s = 100.0
    for t in (101.0, 102.0, 247.92):
        c.range_at(t)
    c.end(251.22, measured_until_s=247.98)
    assert c.largest_gap_s == pytest.approx(145.92)
    c = SurveyClock()
    c.t0_s = 240.0
    for t in (241.0, 242.5, 244.0, 245.5, 247.0, 247.92):
        c.range_at(t)
    c.end(251.22, measured_until_s=247.98)
    assert c.largest_gap_s == pytest.approx(1.5) and c.survey_s == pytest.approx(11.22)


def test_rounds_ranges_and_pace_are_counted_over_the_survey_only():
    from mission.control.config import FELL_BEHIND_SHARE
    from mission.control.state import spacing_m

    c = SurveyClock()
    c.range_at(1.0, 3)  # before the survey: not counted
    c.start(10.0, wall_s=100.0)
    for t in (11.0, 12.0, 13.0):
        c.range_at(t, 2)
    assert c.pace(20.0) is None  # not ended yet
    c.end(70.0, wall_s=106.0)  # 60 mission seconds in 6 wall seconds: ×10
    c.range_at(71.0, 5)  # after the end: ignored
    assert (c.rounds, c.ranges) == (3, 6)
    assert c.rounds_per_min() == pytest.approx(3.0)
    assert spacing_m(30.0, c.rounds) == pytest.approx(10.0) and spacing_m(30.0, 0) is None
    pace = c.pace(20.0)
    assert pace.achieved_speedup == pytest.approx(10.0) and pace.fell_behind
    assert pace.message().startswith("asked ×20, ran ×10.0: ")
    assert not c.pace(10.0 / FELL_BEHIND_SHARE).fell_behind  # exactly at the share: kept up
