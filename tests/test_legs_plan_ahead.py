"""A leg planned ahead, from the current leg's end, is planned as it will be there: the metres to
that end counted as flown and taken off the energy left (a real PX4 SIH run ended 'budget spent'
at 148 m of a 2500 m budget when the way home was judged from the leg's end but the energy from
its start)."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

import numpy as np
import pytest

from mission.control.legs import LegsDeps, SurveyLegs
from planner.types import PlanResult


@dataclass
class _Flight:
    flown_m: float
    estimate: object = None


class _Planner:
    name = "capture"

    def __init__(self):
        self.states = []

    def plan(self, state):
        self.states.append(state)
        return PlanResult(waypoint_enu_m=state.uav_enu_m, horizon_enu_m=state.uav_enu_m[None], done=False,
                          reason="", objective=0.0, status="test", solve_time_s=0.0)


async def _noop(*_):
    return None


@pytest.mark.parametrize("ahead_m", [0.0, 37.5])
def test_a_plan_made_ahead_counts_the_metres_to_the_leg_end(ahead_m):
    planner = _Planner()
    deps = LegsDeps(config=None, flight=_Flight(flown_m=100.0), gated=None, set_speed=_noop,
                    battery_pct=lambda: 60.0, battery_rtl_pct=25.0, planner=planner, origin=None,
                    journal=None, pos_enu=lambda: np.zeros(3), now=lambda: 30.0, wall=lambda s: s * 0.0,
                    drain=_noop, sigma_gps_m=1.0)
    legs = SurveyLegs(deps)
    legs.battery_start_pct, legs.battery_start_s, legs.leg_speed_mps = 80.0, 10.0, 5.0
    end = np.array([30.0, 40.0, 30.0])
    asyncio.run(legs.plan(end, drain_max_s=0.0, ahead_m=ahead_m))
    (state,) = planner.states
    # (60 − 25) · 20 s / (80 − 60) = 35 s left at the drain so far, 175 m at 5 m/s
    assert state.flown_m == pytest.approx(100.0 + ahead_m)
    assert state.energy_remaining_m == pytest.approx(175.0 - ahead_m)


def test_a_leg_takes_the_longer_of_its_horizontal_and_vertical_flight():
    """A live PX4 leg from 80 m down to 30 m, 57 m across, timed out after 35 s: its time was its
    3-D metres at cruise speed (7.6 s) where the 1.5 m/s descent takes 33 s."""
    from types import SimpleNamespace

    flight = SimpleNamespace(climb_mps=3.0, descent_mps=1.5)
    deps = LegsDeps(config=SimpleNamespace(flight=flight), flight=_Flight(flown_m=0.0), gated=None,
                    set_speed=_noop, battery_pct=lambda: None, battery_rtl_pct=25.0, planner=_Planner(),
                    origin=None, journal=None, pos_enu=lambda: np.zeros(3), now=lambda: 0.0, wall=lambda s: s,
                    drain=_noop, sigma_gps_m=1.0)
    legs = SurveyLegs(deps)
    legs.leg_speed_mps = 10.0
    start, wp = np.array([5.4, 42.7, 79.9]), np.array([29.5, 94.5, 30.3])
    assert legs.leg_time_s(start, wp) == pytest.approx(49.6 / 1.5)
    assert legs.leg_time_s(wp, start) == pytest.approx(49.6 / 3.0)  # climbing
    level = np.array([60.0, 80.0, 30.3])
    assert legs.leg_time_s(wp, level) == pytest.approx(np.hypot(30.5, -14.5) / 10.0)  # level: cruise
