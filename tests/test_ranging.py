"""Ranging: TA + SRS peak -> ToA -> range (docs/design.md §4), table of known values and bad input."""

from __future__ import annotations

import math

import pytest

from estimator import ranging
from uavloc.errors import RangingError


@pytest.mark.parametrize(
    ("mu", "step_ns", "one_way_m"),
    [(0, 520.83, 78.07), (1, 260.42, 39.03), (2, 130.21, 19.52), (3, 65.10, 9.76)],
)
def test_ta_step_matches_3gpp_table(mu, step_ns, one_way_m):
    assert ranging.ta_step_s(mu) * 1e9 == pytest.approx(step_ns, abs=0.01)
    assert ranging.one_way_m_per_ta_step(mu) == pytest.approx(one_way_m, abs=0.01)


def test_tc_is_basic_nr_time_unit():
    assert pytest.approx(0.5086e-9, rel=1e-3) == ranging.TC_S


@pytest.mark.parametrize(("fs_hz", "m_per_sample"), [(61.44e6, 2.44), (46.08e6, 3.25)])
def test_one_sample_of_rtt_in_one_way_metres(fs_hz, m_per_sample):
    assert ranging.one_way_m_per_sample(fs_hz) == pytest.approx(m_per_sample, abs=0.01)


def test_range_composes_coarse_and_refined_rtt():
    ta, mu, peak, fs = 3, 1, 5.25, 46.08e6
    rtt = 3 * 16 * 64 * ranging.TC_S / 2 + 5.25 / 46.08e6
    assert ranging.rtt_s(ta, mu, peak, fs) == pytest.approx(rtt, rel=1e-12)
    assert ranging.toa_s_from_raw(ta, mu, peak, fs) == pytest.approx(rtt / 2, rel=1e-12)
    assert ranging.range_m_from_raw(ta, mu, peak, fs) == pytest.approx(ranging.C_MPS * rtt / 2, rel=1e-12)


def test_round_trip_from_distance_through_ta_and_peak():
    d_m, mu, fs = 123.4, 1, 46.08e6
    rtt = 2 * d_m / ranging.C_MPS
    ta = math.floor(rtt / ranging.ta_step_s(mu))
    peak = (rtt - ta * ranging.ta_step_s(mu)) * fs
    assert ranging.range_m_from_raw(ta, mu, peak, fs) == pytest.approx(d_m, abs=1e-9)


def test_mac_ce_is_relative_with_31_meaning_no_change():
    assert ranging.apply_mac_ce(100, 31) == 100
    assert ranging.apply_mac_ce(100, 33) == 102
    assert ranging.apply_mac_ce(100, 0) == 69
    with pytest.raises(RangingError, match="out of"):
        ranging.apply_mac_ce(3840, 63)


@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((3847, 1), "0..3846"),
        ((-1, 1), "0..3846"),
        ((1.5, 1), "integer"),
        ((float("nan"), 1), "integer"),
        ((True, 1), "integer"),
        (("12", 1), "integer"),
        ((10, 4), "numerology"),
        ((10, -1), "numerology"),
        ((10, 1, float("nan"), 46.08e6), "finite"),
        ((0, 1, -0.5, 46.08e6), "negative round trip"),
        ((10, 1, 1.0, 0.0), "positive"),
        ((10, 1, 1.0, float("inf")), "finite"),
        ((10, 1, "x", 46.08e6), "number"),
    ],
)
def test_bad_gnb_numbers_are_rejected_with_the_value(args, match):
    with pytest.raises(RangingError, match=match):
        ranging.range_m_from_raw(*args)


@pytest.mark.parametrize("toa", [float("nan"), float("inf"), -1e-9])
def test_bad_toa_is_rejected(toa):
    with pytest.raises(RangingError):
        ranging.range_m_from_toa(toa)
