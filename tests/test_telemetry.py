"""Telemetry ring buffer and interpolation to a measurement's time."""

from __future__ import annotations

import numpy as np
import pytest

from mission.vehicle.telemetry import TelemetryBuffer
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


def test_mean_of_the_recent_fixes():
    buf = TelemetryBuffer(8)
    assert buf.mean_since(0.0) is None
    for i in range(12):  # the ring keeps fixes 4..11
        buf.append(float(i), np.array([float(i), 2.0 * i, 30.0]))
    np.testing.assert_allclose(buf.mean_since(9.0), [10.0, 20.0, 30.0])  # fixes 9, 10, 11
    np.testing.assert_allclose(buf.mean_since(8.5), [10.0, 20.0, 30.0])
    np.testing.assert_allclose(buf.mean_since(99.0), [11.0, 22.0, 30.0])  # none that recent: the newest
    np.testing.assert_allclose(buf.mean_since(-5.0), [7.5, 15.0, 30.0])  # all the ring holds


def test_empty_and_bad_input():
    buf = TelemetryBuffer(4)
    with pytest.raises(MissionError, match="no telemetry"):
        buf.at(0.0)
    with pytest.raises(MissionError):
        buf.append(0.0, np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(MissionError):
        TelemetryBuffer(1)



def test_odometer_ignores_gps_noise_while_hovering_and_counts_flight():
    from mission.vehicle.telemetry import odometer_dead_band_m, odometer_m

    rng = np.random.default_rng(3)
    band = odometer_dead_band_m(1.0)
    hover = rng.normal(0.0, 1.0, (5000, 3))  # 1 m GPS noise, UAV still
    assert odometer_m(hover, band)[-2] == 0.0  # only the forced last point may count
    # a 2 m band (the old one) counts metres of noise on every few fixes
    assert odometer_m(hover, 2.0)[-1] > 1000.0
    # flight at 10 m/s with 1 m noise at 5 Hz: within 5 % of the true 500 m
    truth = np.c_[np.linspace(0.0, 500.0, 251), np.zeros(251), np.full(251, 30.0)]
    assert odometer_m(truth + rng.normal(0.0, 1.0, truth.shape), band)[-1] == pytest.approx(500.0, rel=0.05)
    assert odometer_m(np.zeros((0, 3)), band).shape == (0,)


def test_odometer_rejects_a_non_positive_band():
    from mission.vehicle.telemetry import Odometer

    with pytest.raises(MissionError, match="dead band"):
        Odometer(0.0)


# --- vehicle clock ------------------------------------------------------------------------------
def test_vehicle_clock_follows_boot_time_at_any_rate_and_is_continuous() -> None:
    from mission.vehicle.telemetry import VehicleClock

    clock = VehicleClock(t0_mono_s=100.0, fallback_rate=1.0)
    assert clock.mission_t(102.0) == pytest.approx(2.0) and not clock.synced
    # a vehicle at 4x (PX4 SITL -s 4), booted 50 s of its time before the first sample
    for k in range(41):
        t = 102.0 + 0.1 * k
        clock.update(t, 50.0 + 4.0 * (t - 102.0))
    assert clock.synced and clock.rate == pytest.approx(4.0)
    assert clock.mission_t(102.0) == pytest.approx(2.0)  # continuous at the first sample
    assert clock.mission_t(107.0) == pytest.approx(2.0 + 4.0 * 5.0)  # vehicle seconds, extrapolated
    clock.update(107.0, float("nan"))  # ignored
    clock.update(107.1, 0.5)  # the vehicle rebooted: no jump back
    assert clock.mission_t(107.1) == pytest.approx(2.0 + 4.0 * 5.1)


def test_vehicle_clock_rejects_a_bad_rate() -> None:
    from mission.vehicle.telemetry import VehicleClock

    with pytest.raises(MissionError):
        VehicleClock(0.0, fallback_rate=0.0)
