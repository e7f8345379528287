"""Faults in the middle of the survey, on real PX4 SITL (`px4` fixture, tests/conftest.py):
GPS lost, battery low (PX4 failure injection through MAVSDK's Param and Failure plugins on the
GCS link), and the vehicle link paused (a UDP relay between PX4 and uavloc stops relaying).
Each must end with the vehicle landed and disarmed and the reason in the mission log.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest
from mavsdk.plugins.failure import FailureError, FailureType, FailureUnit

from mission.control.config import STATUS_RETURNED, STATUS_TARGET
from mission.log import read_mission_log
from sitl_scenarios.px4_sitl import UdpRelay
from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission, free_udp_port
from tests.px4 import GcsClient, wait_until

pytestmark = pytest.mark.px4

SCENARIO = "three_users_nlos"
MISSION_TIMEOUT_S = 400.0
#: measurements before the fault: the vehicle is surveying by then
MEASUREMENTS_BEFORE_FAULT = 30
LANDING_RADIUS_M = 5.0


def _events(path: Path) -> list[dict]:
    return [o for o in map(json.loads, path.read_text().splitlines()) if o.get("type") == "event"]


async def _inject(gcs: GcsClient, unit: FailureUnit) -> str:
    """MAV_CMD_INJECT_FAILURE (unit, OFF) with SYS_FAILURE_EN = 1; returns MAVSDK's result name."""
    await gcs.param.set_param_int("SYS_FAILURE_EN", 1)
    assert await gcs.param.get_param_int("SYS_FAILURE_EN") == 1
    try:
        await gcs.failure.inject(unit, FailureType.OFF, 0)
    except FailureError as exc:
        return exc.result.name
    return "SUCCESS"


async def _fly_with_fault(px4, log_path: Path, fault, connect: str | None = None, **overrides):
    """Fly the scenario; once surveying, `await fault(gcs, sim)`; returns (result, gcs.seen, fault's value)."""
    sc = load_scenario(SCENARIO)
    async with GcsClient(px4.gcs_url) as gcs:
        async with SimulatedMission(sc, log_path, connect=connect or px4.api_url,
                                    controller_overrides=overrides or None) as sim:
            task = asyncio.create_task(sim.run())
            try:
                await wait_until(lambda: sim.controller.measurements >= MEASUREMENTS_BEFORE_FAULT or task.done(),
                                 MISSION_TIMEOUT_S, "survey under way", gcs.describe)
                assert not task.done(), task.result()
                value = await fault(gcs, sim)
                result = await asyncio.wait_for(task, MISSION_TIMEOUT_S)
            finally:
                if not task.done():
                    task.cancel()
        await gcs.wait_for(lambda s: s.landed_disarmed(), 120, "PX4 landed and disarmed")
        return result, gcs.seen, value


def test_gps_lost_in_flight_ends_the_mission_landed_with_the_reason_logged(px4, tmp_path):
    log_path = tmp_path / "mission.jsonl"

    async def lose_gps(gcs, sim):
        answer = await _inject(gcs, FailureUnit.SENSOR_GPS)
        if answer != "SUCCESS":
            # this PX4's SIH GPS (sensor_gps_sim) does not handle MAV_CMD_INJECT_FAILURE (no ACK:
            # MAVSDK reports TIMEOUT); stop the simulated GPS from PX4's console instead, PX4's
            # documented way to simulate a GPS loss
            px4.command("sensor_gps_sim", "stop")
        return answer

    result, seen, _answer = asyncio.run(_fly_with_fault(px4, log_path, lose_gps))
    assert result.status == STATUS_RETURNED, (result.status, result.reason)
    assert result.landed, result.events[-10:]
    # PX4's own failsafe lands where it is (no position to return with)
    assert "LAND" in seen.modes, seen.modes
    events = _events(log_path)
    kinds = [e.get("kind") for e in events]
    assert "position_lost" in kinds, kinds
    assert "global position" in result.reason or "LAND" in result.reason, result.reason
    assert any(e.get("kind") == "vehicle_text" and "failsafe" in e["message"].lower() for e in events), kinds
    assert events[-1]["kind"] == "end"
    read_mission_log(log_path)


def test_battery_low_in_flight_returns_home_with_the_reason_logged(px4, tmp_path):
    log_path = tmp_path / "mission.jsonl"

    async def drain(gcs, sim):
        return await _inject(gcs, FailureUnit.SYSTEM_BATTERY)  # PX4's battery simulator: empty

    result, seen, answer = asyncio.run(_fly_with_fault(px4, log_path, drain))
    assert answer == "SUCCESS"
    assert result.status == STATUS_RETURNED, (result.status, result.reason)
    assert "battery" in result.reason, result.reason
    assert result.landed
    assert seen.text_with("battery"), seen.texts
    events = _events(log_path)
    assert any(e.get("kind") == "vehicle_text" and "battery" in e["message"].lower() for e in events)
    assert events[-1]["kind"] == "end" and events[-1]["status"] == STATUS_RETURNED
    read_mission_log(log_path)


@pytest.mark.parametrize(("pause_s", "link_lost_wait_s", "expect"), [
    # paused for 4 wall s (16 vehicle s at speed 4) with 120 s allowed: the mission resumes
    (4.0, 120.0, "resume"),
    # paused for 8 wall s (32 vehicle s) with 8 s allowed: it returns home once the link is back
    (8.0, 8.0, "rtl"),
], ids=["resume", "rtl"])
def test_vehicle_link_paused_waits_then_resumes_or_returns(px4, tmp_path, pause_s, link_lost_wait_s, expect):
    log_path = tmp_path / "mission.jsonl"
    client_port = free_udp_port()
    marks: dict = {}

    async def pause(gcs, sim):
        ctl = sim.controller
        relay.pause()
        await wait_until(lambda: ctl.flight.link_lost_since is not None, 30, "uavloc sees the link lost")
        await asyncio.sleep(pause_s)
        marks["measurements_at_resume"] = ctl.measurements
        relay.resume()
        return relay.dropped

    with UdpRelay(px4.api_port, client_port) as relay:
        result, seen, dropped = asyncio.run(_fly_with_fault(
            px4, log_path, pause, connect=f"udpin://127.0.0.1:{client_port}", link_lost_wait_s=link_lost_wait_s))
    assert dropped > 0
    events = _events(log_path)
    kinds = [e.get("kind") for e in events]
    assert "link_lost" in kinds and "link_restored" in kinds, kinds
    assert result.landed and result.rtl_sent
    assert seen.home_offset_m() < LANDING_RADIUS_M
    if expect == "resume":
        assert result.status == STATUS_TARGET, (result.status, result.reason)
        assert result.measurements > marks["measurements_at_resume"]  # it went on measuring
    else:
        assert result.status == STATUS_RETURNED, (result.status, result.reason)
        assert f"vehicle link lost for more than {link_lost_wait_s:g} s" in result.reason
    assert events[-1]["kind"] == "end"
    read_mission_log(log_path)
