"""Issue 39: a mission never silently wrong about its speed and its measuring. Whole simulated
missions: one whose simulation is starved (a CPU-bound thread beside it) says it fell behind its
speed-up and by how much; one that keeps up says nothing; and the survey's measuring figures
(`survey_time`) are those of its log, also with a gNB too slow for Δ."""

from __future__ import annotations

import asyncio
import math
import re
from pathlib import Path

import pytest

from mission.control.config import FELL_BEHIND_SHARE
from mission.log import read_mission_log
from mission.status import mission_document
from sitl_scenarios.scenario import scenario_from_dict, user_tables
from sitl_scenarios.sim_runner import SimulatedMission

pytestmark = pytest.mark.sim

DELTA_M = 2.0


def _scenario(n_users: int, gnb_delay_s: float = 0.0, budget_m: float = 300.0):
    users = [{"id": f"ue{k}", "rnti": 0x4601 + k, "east_m": 40.0 + 20.0 * math.cos(k),
              "north_m": 30.0 + 20.0 * math.sin(k)} for k in range(n_users)]
    doc = {"name": "pace", "seed": 3, **user_tables(users),
           "geofence": {"polygon_enu_m": [[-100, -100], [150, -100], [150, 150], [-100, 150]], "max_distance_m": 300},
           "flight": {"delta_m": DELTA_M, "altitude_m": 30.0, "alt_min_m": 20.0, "alt_max_m": 60.0,
                      "budget_m": budget_m, "target_radius_m": 1.0, "leg_max_m": 60.0},
           "vehicle": {"speed_mps": 8.0}}
    if gnb_delay_s:
        doc["faults"] = {"gnb": {"delay_s": gnb_delay_s, "delay_rate": 1.0}}
    return scenario_from_dict(doc)


def _fly(scenario, log_path: Path, speedup: float, spinners: int = 0, timeout_s: float = 240.0):
    """Fly the scenario (lawnmower); `spinners` threads spin in Python in the world's process from the
    survey's start to its end (the interpreter shared with the built-in vehicle, as a busy process
    shares it; the return home is not starved: the pace is the survey's).
    -> (result, behind_s of the built-in vehicle)."""

    async def main():
        async with asyncio.timeout(timeout_s):
            async with SimulatedMission(scenario, log_path, speedup=speedup, planner="lawnmower") as sim:
                async def start_spinning() -> None:
                    while sim.controller.state != "SURVEY":
                        await asyncio.sleep(0.01)
                    await sim.world.starve(spinners)
                    while sim.controller.state == "SURVEY":
                        await asyncio.sleep(0.01)
                    await sim.world.feed()

                spinner = asyncio.get_running_loop().create_task(start_spinning()) if spinners else None
                try:
                    return await sim.run(), sim.vehicle_sim.behind_s
                finally:
                    if spinner is not None:
                        spinner.cancel()

    return asyncio.run(main())


def _events(path: Path, kind: str) -> list[dict]:
    return [e for e in read_mission_log(path).events if e.get("kind") == kind]


def test_a_starved_simulation_says_it_fell_behind_and_by_how_much(tmp_path, caplog):
    """×40 with three threads spinning in the world's process, beside the built-in vehicle: the
    vehicle drops simulated time (its behind_s) and the mission logs `fell_behind` with the requested
    and the achieved speed-up, warns, and its result and --json document carry them."""
    log_path = tmp_path / "m.jsonl"
    with caplog.at_level("WARNING"):
        # a 150 m survey: a minute of a starved simulation's pace is enough to say it
        result, behind_s = _fly(_scenario(1, budget_m=150.0), log_path, 40.0, spinners=3)
    assert behind_s > 0.0  # the simulation really fell behind
    (ev,) = _events(log_path, "fell_behind")
    (survey,) = _events(log_path, "survey_time")
    assert ev["requested_speedup"] == 40.0
    assert ev["achieved_speedup"] < FELL_BEHIND_SHARE * 40.0
    # the achieved speed-up is the survey's mission seconds over its wall seconds
    assert ev["achieved_speedup"] == pytest.approx(survey["survey_s"] / ev["survey_wall_s"], rel=0.02)
    assert ev["message"].startswith(f"asked ×40, ran ×{ev['achieved_speedup']:.1f}: ")
    assert any(r.getMessage() == ev["message"] for r in caplog.records if r.levelname == "WARNING")
    assert result.pace is not None and result.pace.fell_behind
    doc = mission_document(result)["speedup"]
    assert doc["fell_behind"] is True and doc["achieved_speedup"] == ev["achieved_speedup"]


def test_a_simulation_that_keeps_up_says_nothing(tmp_path, caplog):
    """At ×5, which the built-in vehicle keeps beside a second test on 2 cores."""
    log_path = tmp_path / "m.jsonl"
    with caplog.at_level("WARNING"):
        result, behind_s = _fly(_scenario(1, budget_m=150.0), log_path, 5.0)
    assert behind_s == 0.0
    assert _events(log_path, "fell_behind") == []
    assert not any("asked ×" in r.getMessage() for r in caplog.records)
    assert result.pace is not None and not result.pace.fell_behind
    assert result.pace.achieved_speedup == pytest.approx(5.0, rel=1.0 - FELL_BEHIND_SHARE)
    assert mission_document(result)["speedup"]["fell_behind"] is False


def _survey_figures_from_log(log_path: Path) -> tuple[dict, int, int]:
    """(the survey_time event, the rounds and the ranges its log shows before it): a round is the
    rtt records that share one UAV position (how replay groups them into one keyframe)."""
    import numpy as np

    mlog = read_mission_log(log_path)
    (survey,) = [e for e in mlog.events if e.get("kind") == "survey_time"]
    during = mlog.rtt_t_s <= survey["t"]
    rounds = np.unique(mlog.rtt_uav_lla[during], axis=0)
    return survey, len(rounds), int(during.sum())


@pytest.mark.parametrize(("gnb_delay_s", "speedup"), [(0.0, 10.0), (0.06, 20.0)])
def test_the_survey_reports_the_spacing_its_log_shows(tmp_path, gnb_delay_s, speedup):
    """Four users, Δ = 2 m: with a quick gNB (×10, which a machine busy with a second test keeps)
    every user is measured about every Δ·4; at ×20 with a gNB that takes 60 ms (1.2 mission
    seconds, ~10 m flown) per answer, rounds are cut after one
    user and each user is measured every ~40 m (the old `gnb_rounds` claimed every Δ·4 = 8 m).
    The `survey_time` event's rounds, ranges, spacing and rate are the log's; `gnb_rounds` claims
    no spacing."""
    log_path = tmp_path / "m.jsonl"
    n_users = 4
    result, _ = _fly(_scenario(n_users, gnb_delay_s), log_path, speedup)
    survey, rounds, ranges = _survey_figures_from_log(log_path)
    assert abs(survey["rounds"] - rounds) <= 1 and abs(survey["ranges"] - ranges) <= n_users
    # the survey's odometer ran over every fix; the result's (replay's) over the logged telemetry
    assert survey["flown_m"] == pytest.approx(result.flown_m, rel=0.03)
    assert survey["spacing_m"] == pytest.approx(survey["flown_m"] / survey["rounds"], abs=0.011)
    assert survey["user_spacing_m"] == pytest.approx(survey["flown_m"] * n_users / survey["ranges"], abs=0.011)
    # the event holds survey_s rounded to 0.01 s: the rate recomputed from it carries that rounding
    rate = 60.0 * survey["rounds"] / survey["survey_s"]
    assert survey["rounds_per_min"] == pytest.approx(rate, abs=0.006 + rate * 0.005 / survey["survey_s"])
    # the message writes the spacing to 0.1 m from its unrounded value (the field holds it to 0.01 m)
    said = float(re.search(r"one every ([0-9.]+) m", survey["message"]).group(1))
    assert said == pytest.approx(survey["spacing_m"], abs=0.05 + 0.005 + 1e-9)
    for ev in _events(log_path, "gnb_rounds"):
        assert "every" not in ev["message"]
    if gnb_delay_s:
        # the slow gNB: rounds cut after about one user, each user ranged far less often than Δ·K
        assert survey["user_spacing_m"] > 2.0 * DELTA_M * n_users
        assert _events(log_path, "gnb_rounds")
    else:
        assert survey["user_spacing_m"] < 2.0 * DELTA_M * n_users
