"""After the stop rule, the mission's final answer decides what the survey reached
(MissionController._target_confirmed): "target reached" the final answer does not hold sends the
survey on; "floor reached" whose final answer is within the target is the target reached; a
fleet's "its users done" is the target reached, its own users done, or surveying on."""

from __future__ import annotations

import asyncio
import math
from types import SimpleNamespace

import numpy as np

from mission.control.config import STATUS_BUDGET, STATUS_FLOOR, STATUS_TARGET
from mission.control.flight import MissionController
from mission.control.state import FlightState
from mission.estimation import MissionEstimator
from planner.fleet import REASON_USERS_DONE


class _Final:
    """What planner.stop.targets_reached reads of an Estimate: bounds, ambiguity, user count."""

    def __init__(self, bounds_m):
        self.bounds_m = np.asarray(bounds_m, float)
        self.n_users = len(self.bounds_m)
        self.ambiguous = np.zeros(self.n_users, bool)

    def error_bound_95_m(self):
        return self.bounds_m


def _check(stop, final_bounds_m, serving=None, finished=None):
    """(done, the crew's FlightState, event kinds) of vehicle 0's survey ended `stop`, whose final
    answer bounds the users at final_bounds_m; serving: each user's cell (a fleet's; default vehicle
    0's); finished: gets the status of each end of every vehicle's survey (_finish_all)."""
    events = []
    finished = [] if finished is None else finished

    async def drain(_timeout_s):
        return None

    flight = FlightState(event=lambda *a, **k: None)
    flight.finish_survey(*stop, now_s=100.0)
    crew = SimpleNamespace(index=0, flight=flight, pipeline=SimpleNamespace(drain=drain), wall=lambda s: 0.0,
                           event=lambda message, **fields: events.append((message, fields)))

    async def confirmed():
        ctl = SimpleNamespace(
            crews=[crew], _keyframes=[object()] * 12, _confirm_lock=asyncio.Lock(),
            _finish_all=lambda status, reason: finished.append(status),
            serving=np.zeros(len(final_bounds_m), int) if serving is None else np.asarray(serving),
            users=[SimpleNamespace(id=f"ue{k + 1}") for k in range(len(final_bounds_m))],
            # the mission estimator's own rule (MissionEstimator.within_target) over a made-up final answer
            _estimator=SimpleNamespace(final=lambda kfs: _Final(final_bounds_m), within_target=lambda final: (
                MissionEstimator.within_target(SimpleNamespace(target_radius_m=4.0), final))),
            config=SimpleNamespace(flight=SimpleNamespace(target_radius_m=4.0)))
        ctl._users_done_confirmed = lambda *a: MissionController._users_done_confirmed(ctl, *a)
        ctl._serving_now = lambda: ctl.serving.copy()
        return await MissionController._target_confirmed(ctl, crew)

    done = asyncio.run(confirmed())
    for _, fields in events:  # what the mission log can hold: no NaN, no infinity (mission.log)
        assert all(math.isfinite(v) for v in fields.values() if isinstance(v, float)), fields
    return done, flight, [f.get("kind") for _, f in events]


def test_a_floor_the_final_answer_puts_within_the_target_is_the_target_reached():
    # three_users_nlos seed 5: "floor reached" at 1436 m, the final answer 3.57 / 1.17 / 1.68 m
    done, flight, kinds = _check((STATUS_FLOOR, "floor reached"), [3.57, 1.17, 1.68])
    assert done and flight.stop == (STATUS_TARGET, "target reached") and kinds == ["target_in_final_answer"]
    done, flight, kinds = _check((STATUS_FLOOR, "floor reached"), [4.2, 1.23, 0.97])
    assert done and flight.stop == (STATUS_FLOOR, "floor reached") and kinds == []


def test_a_target_the_final_answer_does_not_hold_sends_the_survey_on():
    done, flight, kinds = _check((STATUS_TARGET, "target reached"), [4.84, 2.0, 2.0])
    assert not done and flight.stop is None and flight.stop_s is None and kinds == ["target_unconfirmed"]
    done, flight, kinds = _check((STATUS_TARGET, "target reached"), [3.9, 2.0, 2.0])
    assert done and flight.stop == (STATUS_TARGET, "target reached") and kinds == []


def test_other_ends_are_not_judged_again():
    done, flight, kinds = _check((STATUS_BUDGET, "budget spent"), [1.0, 1.0, 1.0])
    assert done and flight.stop == (STATUS_BUDGET, "budget spent") and kinds == []


def test_a_fleet_vehicle_whose_users_are_done_is_judged_on_the_final_answer():
    """PX4 fleet, the plan made ahead 16 s before the leg's end: "its users done" on bounds of
    3.4 m, the final answer 6.0 m for a user of its cell (tests/test_px4_fleet.py)."""
    users_done = ("no_feasible_leg", REASON_USERS_DONE)
    # every user within the target in the final answer: the target reached, for the whole fleet
    finished = []
    done, flight, kinds = _check(users_done, [3.6, 3.9, 3.5, 3.8], serving=[0, 0, 1, 1], finished=finished)
    assert done and flight.stop == (STATUS_TARGET, "target reached")
    assert kinds == ["target_in_final_answer"] and finished == [STATUS_TARGET]
    # its own users within the target, another cell's user not: its part is done, as the planner said
    done, flight, kinds = _check(users_done, [3.6, 3.9, 6.0, 3.8], serving=[0, 0, 1, 1])
    assert done and flight.stop == users_done and kinds == []
    # a user of its own cell beyond the target: it surveys on
    done, flight, kinds = _check(users_done, [3.6, 6.0, 3.5, 3.8], serving=[0, 0, 1, 1])
    assert not done and flight.stop is None and kinds == ["users_done_unconfirmed"]
    # a user nobody serves (its vehicle went home) beyond the target: it surveys on, for that user
    done, flight, kinds = _check(users_done, [3.6, 3.9, 6.0, 3.8], serving=[0, 0, -1, 1])
    assert not done and flight.stop is None and kinds == ["users_done_unconfirmed"]
    # … or not located at all (seen: a vehicle sent home after 18 ranges left its users unlocated;
    # the event's infinite bound once cost the other vehicle its survey)
    done, flight, kinds = _check(users_done, [3.6, 3.9, np.inf, 3.8], serving=[0, 0, -1, 1])
    assert not done and flight.stop is None and kinds == ["users_done_unconfirmed"]
