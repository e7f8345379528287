"""The Δ-trigger's measurement rounds (mission.control.pipeline) with many users: a round ends
when the UAV has moved Δ, the next goes on with the next user, so the gNB's answers are shared
out without stretching the keyframe spacing (issue 21 #11). The real client against the
simulated gNB; the UAV moves a fixed step per gNB position look-up, so the test is deterministic."""

from __future__ import annotations

import asyncio

import numpy as np

from mission.control.config import MissionUser
from mission.control.pipeline import MeasurementPipeline
from mission.control.state import FlightState
from mission.gnb import GnbConfig, OaiGnbClient
from mission.log import MissionLogWriter
from mission.vehicle.telemetry import TelemetryBuffer
from sitl_scenarios.gnb import SimulatedGnb
from sitl_scenarios.scenario import scenario_from_dict, user_tables

N_USERS = 12
DELTA_M = 2.0
STEP_M = 0.25  # the UAV's move per position look-up of the gNB


def test_rounds_end_after_delta_and_take_the_users_in_turn(tmp_path):
    """Issue 21 #11: 200 users took 3 000 ranges at 15 keyframes over 333 m (every user measured
    at every trigger while the UAV flew on). Each round now stays within Δ of its start, rounds
    follow each other through the users in order, every user is measured, and one event says
    how many users the gNB serves per Δ."""
    users = [{"id": f"ue{k}", "rnti": 0x4601 + k, "east_m": 30.0 * np.cos(k), "north_m": 30.0 * np.sin(k)}
             for k in range(N_USERS)]
    sc = scenario_from_dict({"name": "many", "seed": 3, **user_tables(users), "flight": {"delta_m": DELTA_M}})
    buf = TelemetryBuffer(4096)
    now = {"t": 0.0, "x": 0.0}
    buf.append(0.0, np.array([0.0, 0.0, 30.0]))

    def position() -> np.ndarray:
        now["t"] += 0.05
        now["x"] += STEP_M
        pos = np.array([now["x"], 0.0, 30.0])
        buf.append(now["t"], pos)
        return pos

    events: list[tuple[str, dict]] = []
    flight = FlightState(event=lambda message, **fields: events.append((message, fields)))

    async def main():
        async with SimulatedGnb(sc, position, port=0, clock=lambda: now["t"], seed=3) as gnb, \
                OaiGnbClient(GnbConfig(host="127.0.0.1", port=gnb.port, seed=3, mu=1, request_timeout_s=2.0,
                                       connect_timeout_s=2.0, retries=1, backoff_max_s=0.2)) as client:
            pipe = MeasurementPipeline(client, [MissionUser(u["id"], u["rnti"]) for u in users], DELTA_M, 5.0,
                                       flight, buf, lambda: None, MissionLogWriter(tmp_path / "m.jsonl"),
                                       now=lambda: now["t"], mission_t=lambda t: t)
            rounds = []
            for _ in range(8):
                x0 = buf.latest()[1][0]
                await pipe.measure_round()
                rounds.append(([k for k, *_ in pipe.place_queue.get_nowait()], x0, buf.latest()[1][0]))
            return rounds

    rounds = asyncio.run(main())
    order = [k for ks, _, _ in rounds for k in ks]
    assert order == [i % N_USERS for i in range(len(order))]  # in turn, across rounds
    assert all(1 <= len(ks) < N_USERS for ks, _, _ in rounds), [len(ks) for ks, _, _ in rounds]
    # the UAV moved at most Δ (plus the last measurement's step) during any round
    assert all(x1 - x0 <= DELTA_M + 2 * STEP_M for _, x0, x1 in rounds)
    assert set(order) == set(range(N_USERS))
    told = [f for m, f in events if f.get("kind") == "gnb_rounds"]
    assert len(told) == 1 and told[0]["users"] == N_USERS and told[0]["served"] < N_USERS


def test_the_trigger_measures_at_a_turn_where_the_uav_moves_less_than_delta(tmp_path):
    """A UAV braking to a leg's end and turning back moves less than Δ for seconds (3.5 s without a
    range in a `paper` survey): on a leg the trigger still measures every MAX_RANGE_GAP_S mission
    seconds, longer than replay's grouping window so that replay keeps those rounds apart; off a leg
    (hovering to replan) it does not, and a moving UAV is measured every Δ."""
    from estimator.keyframes import KeyframeSelector
    from mission.control.pipeline import MAX_RANGE_GAP_S
    from mission.replay import GROUP_WINDOW_S

    assert MAX_RANGE_GAP_S > GROUP_WINDOW_S
    sel = KeyframeSelector(2.0)
    assert sel.accept(np.zeros(3)) and not sel.accept(np.array([0.5, 0.0, 0.0]))
    assert sel.accept(np.array([0.5, 0.0, 0.0]), force=True)
    assert not sel.accept(np.array([2.0, 0.0, 0.0])) and sel.accept(np.array([2.6, 0.0, 0.0]))  # from the forced one

    def rounds_at(speed_mps: float, on_leg: bool) -> list[float]:
        buf = TelemetryBuffer(4096)
        now = {"t": 0.0}
        flight = FlightState(event=lambda message, **fields: None)
        flight.on_leg = on_leg
        pipe = MeasurementPipeline(None, [MissionUser("ue0", 0x4601)], DELTA_M, 5.0, flight, buf, lambda: None,
                                   MissionLogWriter(tmp_path / "m.jsonl"), now=lambda: now["t"], mission_t=lambda t: t)
        times: list[float] = []

        async def measure_round() -> None:  # the gNB's part is not what is tested here
            times.append(now["t"])

        pipe.measure_round = measure_round

        async def main():
            trigger = asyncio.create_task(pipe.run_trigger())
            while now["t"] < 10.0:  # 10 mission seconds of fixes, 20 per second
                now["t"] += 0.05
                buf.append(now["t"], np.array([speed_mps * now["t"], 0.0, 30.0]))
                flight.wake.pulse()
                await asyncio.sleep(0)
            trigger.cancel()

        asyncio.run(main())
        return times

    still = rounds_at(0.0, on_leg=True)
    assert len(still) == 7 and np.all(np.diff(still) >= MAX_RANGE_GAP_S - 1e-9)
    assert np.max(np.diff(still)) <= MAX_RANGE_GAP_S + 0.05 + 1e-9
    assert rounds_at(0.0, on_leg=False) == []
    moving = rounds_at(8.0, on_leg=True)  # 80 m at 8 m/s in 0.4 m steps: every Δ = 2 m (5 or 6 steps)
    assert 33 <= len(moving) <= 41 and np.max(np.diff(moving)) < MAX_RANGE_GAP_S


def test_a_round_under_way_when_the_survey_ends_claims_no_user_back(tmp_path):
    """A fleet vehicle's round that is still asking its gNB when the vehicle's survey ends (its
    link lost: a return requested) stops there, and the answer it was waiting for does not make the
    user its own again: the mission released its users for the vehicles still surveying, and a
    claim then kept every other gNB from asking for them until the end (uav1 spent its budget
    exploring, never ranging the west group: the fleet link-loss test, under load)."""
    users = [{"id": f"ue{k}", "rnti": 0x4601 + k, "east_m": 30.0 + 5.0 * k, "north_m": 0.0} for k in range(3)]
    sc = scenario_from_dict({"name": "ending", "seed": 4, **user_tables(users), "flight": {"delta_m": DELTA_M}})
    buf = TelemetryBuffer(4096)
    buf.append(0.0, np.array([0.0, 0.0, 30.0]))
    flight = FlightState(event=lambda message, **fields: None)
    serving = np.array([1, 1, -1])  # vehicle 1's gNB serves ue0 and ue1; ue2 is nobody's
    looked_up = []
    pipe: MeasurementPipeline | None = None

    def position() -> np.ndarray:
        # the gNB looks the UAV up for each answer: the survey ends while the first is on its way
        looked_up.append(len(looked_up))
        if len(looked_up) == 1:
            flight.request_return("vehicle link lost for more than 5 s")
            pipe.release_users()
        return np.array([0.0, 0.0, 30.0])

    async def main():
        nonlocal pipe
        async with SimulatedGnb(sc, position, port=0, clock=lambda: 0.0, seed=4) as gnb, \
                OaiGnbClient(GnbConfig(host="127.0.0.1", port=gnb.port, seed=4, mu=1, request_timeout_s=2.0,
                                       connect_timeout_s=2.0, retries=1, backoff_max_s=0.2)) as client:
            pipe = MeasurementPipeline(client, [MissionUser(u["id"], u["rnti"]) for u in users], DELTA_M, 5.0,
                                       flight, buf, lambda: None, MissionLogWriter(tmp_path / "m.jsonl"),
                                       now=lambda: 0.0, mission_t=lambda t: t, vehicle=1, serving=serving)
            await pipe.measure_round()

    asyncio.run(main())
    assert len(looked_up) == 1, looked_up  # ue1 and ue2 were not asked for after the survey ended
    assert serving.tolist() == [-1, -1, -1]
