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
    with pytest.raises(SafetyError, match="within 15 m .* of another vehicle's leg$"):
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


def test_two_close_legs_are_named_in_the_plural():
    gate = _gate()
    others = [np.array([[0.0, -100.0, 40.0], [0.0, 100.0, 40.0]]), np.array([[5.0, -100.0, 40.0], [5.0, 100.0, 40.0]])]
    with pytest.raises(SafetyError, match="of 2 other vehicles' legs$"):
        gate.check_goto(np.array([50.0, 0.0, 40.0]), np.array([-50.0, 0.0, 40.0]), others)


def test_a_vehicles_home_is_held_to_the_fence_the_zones_and_the_distance_from_the_origin():
    """Issue 49: a fleet's other vehicles are held to what vehicle 0's home is (fly's second vehicle
    50 km away took off 49 999 m outside the fence)."""
    zone = np.array([[100.0, 100.0], [150.0, 100.0], [150.0, 150.0], [100.0, 150.0]])
    gate = SafetyGate(SafetyLimits(fence_enu_m=FENCE, no_fly_enu_m=(zone,), max_distance_m=560.0))
    assert gate.home_violations() == [] and gate.home_violations(np.array([20.0, 0.0, 3.0])) == []
    far = gate.home_violations(np.array([50_000.0, 0.0, 0.0]))
    assert far == ["50000.0 m from the mission's origin exceeds max_distance_m 560",
                   "home (50000.0, 0.0) m is outside the geofence polygon"]
    assert gate.home_violations(np.array([120.0, 120.0, 0.0])) == ["home (120.0, 120.0) m is inside no-fly zone 0"]
    assert gate.home_violations(np.array([400.0, 400.0, 0.0])) == [
        "565.7 m from the mission's origin exceeds max_distance_m 560"]


def test_a_return_requested_during_the_survey_is_logged_after_its_survey_time():
    """Issue 49: a vehicle's log reads survey_time, then return; the vehicle's part still ended on
    the return (the flight returns its return reason over a stop)."""
    from mission.control.config import SURVEY, TAKEOFF
    from mission.control.state import FlightState

    events: list[dict] = []
    f = FlightState(event=lambda message, **kw: events.append({"message": message, **kw}))
    f.set_phase(SURVEY)
    f.request_return("battery low")
    f.request_return("second reason")  # the first wins
    assert events == []
    events.append({"message": "survey 10 s", "kind": "survey_time", "survey_s": 10.0})
    f.log_return()
    f.log_return()  # once
    assert [e["kind"] for e in events] == ["survey_time", "return"]
    assert events[1]["in_survey"] is True and events[1]["reason"] == "battery low"
    vehicles, _ = vehicles_of_events(["uav1"], events)
    assert vehicles[0].ended == "return requested: battery low" and vehicles[0].survey_s == 10.0
    # outside the survey: logged at once
    g = FlightState(event=lambda message, **kw: events.append({"message": message, **kw}))
    g.set_phase(TAKEOFF)
    g.request_return("link lost")
    assert events[-1]["kind"] == "return" and "in_survey" not in events[-1]
    # a return on the way home, after a survey that ended on its stop rule, changes nothing
    log = [{"kind": "stop", "reason": "target reached"}, {"kind": "survey_time", "survey_s": 5.0},
           {"kind": "return", "reason": "battery low"}]
    assert vehicles_of_events(["uav1"], log)[0][0].ended == "survey done: target reached"
