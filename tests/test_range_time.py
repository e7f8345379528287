"""Every range is placed by when it was measured (issue 48): the timing rule, the placer dropping
and counting a range timed too loosely, the gNB clock offset's estimator on synthetic stamps and
against the simulated gNB's offset clock, and the survey saying at once that it falls behind."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging

import numpy as np
import pytest

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from mission.control.config import HOVER_SHARE_MAX, MissionUser, SurveyPace
from mission.control.pipeline import MeasurementPipeline
from mission.control.state import PACE_JUDGE_AFTER_S, FlightState, SurveyClock
from mission.control.timing import judge_range_timing, speed_around_mps
from mission.gnb import GnbConfig, OaiGnbClient
from mission.gnb.clock_offset import ClockOffset
from mission.gnb.oai import RttSample
from mission.log import MissionLogWriter, read_mission_log
from mission.vehicle.telemetry import TelemetryBuffer
from sitl_scenarios.gnb import SimulatedGnb, static_position
from sitl_scenarios.scenario import scenario_from_dict, user_tables
from uavloc.errors import GnbNoMeasurementError

NOISE = NoiseModel(range_s0_m=3.0)


# --- the rule ------------------------------------------------------------------------------------

@pytest.mark.parametrize(("half_s", "speed_mps", "keep"), [
    (0.0, 8.0, True),       # a stamp: exact
    (0.05, 8.0, True),      # a quick telnet answer at ×10 (10 ms wall): 0.23 m
    (2.0, 0.0, True),       # hovering: wherever in the interval, the UAV was here
    (0.6, 8.0, True),       # e = 8·0.6/√3 = 2.77 m ≤ 3 m
    (0.7, 8.0, False),      # 3.23 m > 3 m
    (5.0, 8.0, False),      # a loaded loop at ×10: 23 m
    (float("nan"), 8.0, False),
])
def test_a_range_is_kept_when_its_timing_costs_less_than_its_own_spread(half_s, speed_mps, keep):
    v = judge_range_timing(100.0, half_s, speed_mps, NOISE)
    assert v.keep is keep and v.sigma_m == 3.0


def test_the_speed_around_an_interval_is_the_largest_logged_one_or_the_nearest():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    v = np.array([[1.0, 0, 0], [0, 5.0, 0], [3.0, 4.0, 0], [0, 0, 0]])
    assert speed_around_mps(t, v, 0.5, 2.5) == pytest.approx(5.0)
    assert speed_around_mps(t, v, 10.0, 11.0) == 0.0  # nearest: t = 3
    assert speed_around_mps(t[:0], v[:0], 0.0, 1.0) is None


# --- the placer ------------------------------------------------------------------------------------

def test_a_range_timed_too_loosely_at_speed_is_dropped_counted_and_said(tmp_path):
    """Two users of one round at 8 m/s: one answered within ±0.01 s, the other within ±2 s (a loop
    that lagged): the first is logged with its t_unc_s, the second dropped, counted in the survey
    clock and the pipeline, and said in a `range_timing_dropped` event."""
    origin = Origin(43.6143, 7.0716, 150.0)
    users = [MissionUser("ue1", 0x4601), MissionUser("ue2", 0x4602)]
    path = tmp_path / "m.jsonl"
    events: list[dict] = []

    async def fly():
        writer = MissionLogWriter(path)
        writer.open()
        buf = TelemetryBuffer(256)
        flight = FlightState(event=lambda message, **kw: events.append({"message": message, **kw}))
        flight.clock.start(0.0, 0.0)
        pipe = MeasurementPipeline(None, users, 2.0, 1.0, flight, buf, lambda: origin, writer,
                                   now=lambda: 0.0, mission_t=lambda t: t)
        writer.write_header(origin, [{"id": u.id, "rnti": u.rnti, "ground_alt_m": 150.0} for u in users],
                            {"mu": 1, "fs_hz": 46.08e6}, noise=NOISE)
        for i in range(40):  # 8 m/s east, logged with velocity
            t = 0.2 * i
            pos = np.array([8.0 * t, 0.0, 40.0])
            buf.append(t, pos)
            lat, lon, alt = (float(x) for x in origin.enu_to_lla(pos))
            writer.write("telemetry", t, lat_deg=lat, lon_deg=lon, alt_m=alt, vel_ned_mps=[0.0, 8.0, 0.0])
        samples = [(0, RttSample(0x4601, 100, 1, 3.5, 46.08e6, None, 3e-7, 3.0, t_unc_s=0.01), 3.0, 0.01),
                   (1, RttSample(0x4602, 100, 1, 3.5, 46.08e6, None, 4e-7, 3.1, t_unc_s=2.0), 3.1, 2.0)]
        await pipe.place(samples)
        writer.close()
        return pipe, flight

    pipe, flight = asyncio.run(fly())
    assert list(read_mission_log(path).rtt_t_s) == [3.0]
    (rtt,) = [r for r in map(json.loads, path.read_text().splitlines()) if r["type"] == "rtt"]
    assert rtt["user"] == "ue1" and rtt["t_unc_s"] == 0.01
    assert pipe.timing_dropped == 1 and flight.clock.late_dropped == 1 and flight.measurements == 1
    (ev,) = [e for e in events if e.get("kind") == "range_timing_dropped"]
    assert ev["user"] == "ue2" and ev["error_m"] > ev["sigma_m"] == 3.0
    assert "ue2 dropped" in ev["message"]


# --- the gNB host's clock --------------------------------------------------------------------------

def test_the_offset_is_the_low_envelope_of_arrival_minus_stamp():
    """gNB clock 2 s ahead (θ = −2 s), latencies 1 ms + exponential 20 ms: θ̂ within 2 ms above θ."""
    rng = np.random.default_rng(4)
    est = ClockOffset()
    for i in range(200):
        stamp = 1000.0 + 0.01 * i + 2.0
        est.add(stamp - 2.0 + 0.001 + rng.exponential(0.02), stamp)
    e = est.estimate()
    assert e is not None and e.bounded and e.samples == 200
    assert -2.0 < e.offset_s < -2.0 + 0.002 and 0.0 <= e.spread_s < 0.02


def test_an_offset_is_not_bounded_on_too_few_or_too_scattered_stamps_and_follows_a_step():
    est = ClockOffset(min_samples=5, max_spread_s=0.5, horizon_s=10.0)
    assert est.estimate() is None and "no time-stamped" in est.why_unbounded(None)
    for i in range(3):
        est.add(100.0 + i, 100.0 + i)
    e = est.estimate()
    assert e is not None and not e.bounded and "only 3" in est.why_unbounded(e)
    wild = ClockOffset(min_samples=5, max_spread_s=0.5)
    for i, lat in enumerate([0.0, 3.0, 2.5, 4.0, 3.5, 5.0, 2.8, 3.1]):
        wild.add(100.0 + i + lat, 100.0 + i)
    assert not wild.estimate().bounded
    # a clock stepped by 1 s (NTP): after the horizon the envelope is the new one
    for i in range(20):
        est.add(200.0 + i, 200.0 + i - 1.0)
    assert est.estimate().offset_s == pytest.approx(1.0)


def test_nonfinite_items_are_ignored():
    est = ClockOffset(min_samples=1)
    est.add(float("nan"), 1.0)
    est.add(5.0, float("inf"))
    assert est.estimate() is None


@pytest.mark.parametrize("offset_s", [2.0, -2.0])
def test_a_gnb_whose_clock_is_off_by_2_s_is_measured_in_our_time(offset_s):
    """The simulated gNB's T trace stamped 2 s ahead of (or behind) our clock: the client estimates
    the offset within 50 ms, logs it through clock_offset(), and places each trace range at our
    time of the SRS occasion (not 2 s off; behind by 2 s the uncorrected stamp was older than
    trace_max_age_s and every range refused)."""
    users = [{"id": "u0", "rnti": "0x4601", "east_m": 120.0, "north_m": 80.0}]
    sc = scenario_from_dict({"name": "offset", "seed": 3, **user_tables(users), "radio": {"s0_m": 1e-3}})

    async def main():
        async with SimulatedGnb(sc, static_position((30.0, -40.0, 40.0)), port=0, t_port=0,
                                clock_offset_s=offset_s) as gnb:
            cfg = GnbConfig(port=gnb.port, t_port=gnb.t_port, mode="trace", fs_hz=sc.radio.fs_hz)
            async with OaiGnbClient(cfg) as client:
                got = []
                for _ in range(100):
                    await client.tracer.wait_for_events(0.2)
                    with contextlib.suppress(GnbNoMeasurementError):
                        s = await client.measure(0x4601)
                        got.append((s, client.clock()))
                    if len(got) >= 3:
                        break
                return got, client.clock_offset()

    got, est = asyncio.run(main())
    assert est is not None and est.bounded
    assert est.offset_s == pytest.approx(-offset_s, abs=0.05)
    assert len(got) >= 3
    for s, now in got:
        assert 0.0 <= now - s.t_mono_s < 0.3 and s.t_unc_s < 0.05


# --- falling behind ---------------------------------------------------------------------------------

def test_a_survey_hovering_most_of_its_time_fell_behind_though_its_clock_kept_pace():
    """The issue's `paper --speedup 100`: the clock ran at the speed asked, but 60 % of the survey
    was hovering: fell_behind, and the message says why."""
    pace = SurveyPace(100.0, 553.0 / 8.0 / 0.4, 553.0 / 8.0 / 0.4 / 100.0, hover_s=0.6 * 553.0 / 8.0 / 0.4,
                      largest_gap_s=10.0, ranges=21)
    assert pace.achieved_speedup == pytest.approx(100.0) and pace.hover_share > HOVER_SHARE_MAX
    assert pace.fell_behind and "hovered 60 %" in pace.message()
    assert pace.to_dict()["fell_behind"] is True and pace.to_dict()["hover_share"] == 0.6
    assert not SurveyPace(10.0, 300.0, 30.0, hover_s=10.0, largest_gap_s=3.0, ranges=100).fell_behind
    assert SurveyPace(10.0, 300.0, 30.0, ranges=80, late_dropped=20).fell_behind
    assert not SurveyPace(10.0, 60.0, 6.0, ranges=0, late_dropped=1).fell_behind  # one range says nothing yet


def test_the_flight_says_at_once_when_its_survey_falls_behind(caplog):
    """A survey record with a large hover share: the warning and the `falling_behind` event come
    the first fix the pace is judged on (after PACE_JUDGE_AFTER_S), once."""
    events: list[dict] = []
    flight = FlightState(event=lambda message, **kw: events.append({"message": message, **kw}))
    clock: SurveyClock = flight.clock
    clock.start(0.0, 0.0)
    said = []
    with caplog.at_level(logging.WARNING):
        for i in range(1, 200):
            t = 0.5 * i
            clock.fix(t, 0.1 if i % 3 else 8.0)  # two fixes in three hovering
            said.append(flight.check_pace(10.0, t, t / 10.0))
    first = next(i for i, p in enumerate(said) if p is not None)
    assert 0.5 * (first + 1) == pytest.approx(PACE_JUDGE_AFTER_S, abs=0.5)
    assert sum(p is not None for p in said) == 1
    (ev,) = [e for e in events if e.get("kind") == "falling_behind"]
    assert ev["fell_behind"] is True and ev["hover_share"] > HOVER_SHARE_MAX
    assert any(r.levelname == "WARNING" and "falling behind" in r.getMessage() for r in caplog.records)


def test_a_survey_said_to_fall_behind_while_flying_fell_behind_though_it_caught_up():
    """The console said "falling behind" mid-survey (6 of 53 ranges dropped late); by the end the
    share was under the limit: the result still says fell_behind, with what was said."""
    caught_up = SurveyPace(10.0, 100.0, 9.8, hover_s=1.0, ranges=90, late_dropped=6)
    assert not caught_up.fell_behind
    said = SurveyPace(10.0, 60.0, 5.9, ranges=47, late_dropped=6).reasons()
    assert said
    from dataclasses import replace

    final = replace(caught_up, said_while_flying=tuple(said))
    assert final.fell_behind and final.to_dict()["fell_behind"] is True
    assert final.reasons() == [f"while surveying: {said[0]}"]
