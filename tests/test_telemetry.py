"""Telemetry ring buffer and interpolation to a measurement's time."""

from __future__ import annotations

import numpy as np
import pytest

from mission.telemetry import TelemetryBuffer
from uavloc.errors import MissionError


def _filled(n=50, cap=16):
    buf = TelemetryBuffer(cap)
    for i in range(n):
        buf.append(0.1 * i, np.array([2.0 * i, -1.0 * i, 30.0]))
    return buf


def test_interpolation_is_exact_on_a_straight_constant_speed_track():
    buf = _filled()
    for t in np.linspace(3.5, 4.9, 29):
        assert buf.at(t) == pytest.approx([20.0 * t, -10.0 * t, 30.0], abs=1e-9)


def test_ring_keeps_only_the_newest_fixes():
    buf = _filled(n=50, cap=16)
    assert len(buf) == 16
    assert buf.first_t_s == pytest.approx(3.4)
    assert buf.last_t_s == pytest.approx(4.9)
    with pytest.raises(MissionError, match="older than the oldest"):
        buf.at(3.0)


def test_extrapolation_only_within_the_limit():
    buf = _filled()
    assert buf.at(5.0, max_extrapolate_s=0.2) == pytest.approx([100.0, -50.0, 30.0])
    with pytest.raises(MissionError, match="after the newest"):
        buf.at(5.5, max_extrapolate_s=0.2)
    with pytest.raises(MissionError, match="after the newest"):
        buf.at(4.95)


def test_out_of_order_fix_is_dropped_and_equal_time_replaces():
    buf = TelemetryBuffer(8)
    buf.append(1.0, np.zeros(3))
    buf.append(2.0, np.ones(3))
    buf.append(1.5, np.full(3, 99.0))
    assert len(buf) == 2
    buf.append(2.0, np.full(3, 2.0))
    assert buf.at(2.0) == pytest.approx([2.0, 2.0, 2.0])
    assert buf.at(1.5) == pytest.approx([1.0, 1.0, 1.0])


def test_empty_and_bad_input():
    buf = TelemetryBuffer(4)
    with pytest.raises(MissionError, match="no telemetry"):
        buf.at(0.0)
    with pytest.raises(MissionError):
        buf.append(0.0, np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(MissionError):
        TelemetryBuffer(1)
