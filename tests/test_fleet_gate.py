"""The safety gate keeps a fleet's vehicles apart as it keeps them inside the fence (docs/fleet.md):
a goto whose leg comes within the separation of another vehicle's leg is refused and logged."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from estimator.geodesy import Origin
from mission.result import vehicles_of_events
from mission.safety import GatedVehicle, SafetyGate, SafetyLimits
from planner.fleet import Separation
from uavloc.errors import SafetyError

SEP = Separation(horizontal_m=15.0, vertical_m=10.0)
FENCE = np.array([[-500.0, -500.0], [500.0, -500.0], [500.0, 500.0], [-500.0, 500.0]])


def _gate(separation=SEP) -> SafetyGate:
    return SafetyGate(SafetyLimits(fence_enu_m=FENCE, alt_min_m=20.0, alt_max_m=80.0, separation=separation))


def test_a_leg_crossing_another_vehicles_leg_is_refused_like_one_leaving_the_fence():
    gate = _gate()
    other = np.array([[0.0, -100.0, 40.0], [0.0, 100.0, 40.0]])  # flying north along east = 0
    with pytest.raises(SafetyError, match="within 15 m .* of 1 other vehicle"):
        gate.check_goto(np.array([50.0, 0.0, 40.0]), np.array([-50.0, 0.0, 40.0]), [other])
    # 16 m beside it, or 10 m above it (an altitude layer), is apart
    gate.check_goto(np.array([-16.0, 50.0, 40.0]), np.array([-16.0, -50.0, 40.0]), [other])
    gate.check_goto(np.array([50.0, 0.0, 50.0]), np.array([-50.0, 0.0, 50.0]), [other])
    # one vehicle (no separation in its limits): the others are not its business
    _gate(None).check_goto(np.array([50.0, 0.0, 40.0]), np.array([-50.0, 0.0, 40.0]), [other])


def test_the_gated_vehicle_asks_for_the_other_legs_at_each_goto_and_logs_a_refusal():
    sent, events = [], []

    class Vehicle:
        async def goto_location(self, *args):
            sent.append(args)

    others = [np.array([[0.0, -100.0, 40.0], [0.0, 100.0, 40.0]])]
    gated = GatedVehicle(Vehicle(), _gate(), Origin(43.6, 7.07, 150.0), lambda m, **f: events.append(f),
                         lambda: np.array([-50.0, 0.0, 40.0]), others=lambda: others)
    with pytest.raises(SafetyError):
        asyncio.run(gated.goto_enu(np.array([50.0, 0.0, 40.0])))
    assert gated.refusals == 1 and events[0]["kind"] == "refused" and not sent
    others.clear()  # the other vehicle landed: the same leg is free
    asyncio.run(gated.goto_enu(np.array([50.0, 0.0, 40.0])))
    assert len(sent) == 1


def test_each_vehicles_part_and_the_breaches_are_read_from_the_events():
    events = [
        {"kind": "rtl", "vehicle": 1, "message": "uav2: RTL: x"},
        {"kind": "return", "vehicle": 1, "reason": "vehicle link lost for more than 20 s"},
        {"kind": "separation_lost", "least_m": 12.0},
        {"kind": "survey_time", "vehicle": 1, "flown_m": 100.0, "survey_s": 50.0, "hover_s": 1.0},
        {"kind": "landed", "vehicle": 1},
        {"kind": "stop", "vehicle": 0, "reason": "floor reached"},
        {"kind": "target_in_final_answer", "vehicle": 0},  # the final answer made it the target
        {"kind": "survey_time", "vehicle": 0, "flown_m": 400.0, "survey_s": 90.0, "hover_s": 0.5},
        {"kind": "rtl", "vehicle": 0},
        {"kind": "return", "vehicle": 0, "reason": "battery low on the way home changes nothing"},
        {"kind": "rtl", "vehicle": 7},  # no such vehicle: ignored
    ]
    vehicles, breaches = vehicles_of_events(["uav1", "uav2"], events)
    assert breaches == 1
    assert vehicles[0].ended == "survey done: target reached" and vehicles[0].rtl_sent and not vehicles[0].landed
    assert vehicles[0].flown_m == 400.0
    assert vehicles[1].ended == "return requested: vehicle link lost for more than 20 s"
    assert vehicles[1].rtl_sent and vehicles[1].landed and vehicles[1].survey_s == 50.0
