"""The ArduPilot side: the built-in vehicle's ArduCopter personality on the wire and in flight, the
vehicle adapter flying it (mission.vehicle.ardupilot), and whole missions on it.

The recorded real ArduCopter (../shared/data/ardupilot-4.7-sitl/) is what these behaviours come
from; tests/test_ardupilot_conformance.py holds the flight itself to it.
"""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from estimator.geodesy import Origin
from mission.control.config import STATUS_FLOOR, STATUS_TARGET
from mission.log import read_mission_log
from mission.vehicle import MavsdkVehicle, VehicleCommandError, VehicleTimeoutError
from sitl_scenarios.scenario import VehicleConfig, load_scenario, with_autopilot
from sitl_scenarios.sim_runner import SimulatedMission
from sitl_scenarios.vehicle import VehicleSimulator
from sitl_scenarios.vehicle.ardupilot import GUIDED, LAND, LOITER, RTL, STABILIZE, ArduCopter
from sitl_scenarios.vehicle.mav import ACCEPTED, DENIED
from sitl_scenarios.vehicle.params import encode_param_value
from tests.test_mission_e2e import assert_log_replays_to_the_result, ctrl_c_uavloc_sim

HOME = Origin(43.6143, 7.0716, 150.0)
ARDUPILOT = VehicleConfig(autopilot="ardupilot")
REPO = Path(__file__).resolve().parents[1]
M = mavutil.mavlink


def _copter() -> ArduCopter:
    return ArduCopter(HOME, VehicleConfig(gps_sigma_m=0.0, autopilot="ardupilot"), np.random.default_rng(0))


def _until(ap: ArduCopter, cond, limit_s: float = 300.0, dt: float = 0.1) -> None:
    t_end = ap.t_s + limit_s
    while not cond():
        assert ap.t_s < t_end, f"not within {limit_s} s (mode {ap.custom_mode}, pos {ap.pos})"
        ap.step(dt, 0.0)


def test_arducopter_flies_guided_and_lands_in_rtl_as_the_recording():
    ap = _copter()
    assert ap.custom_mode == STABILIZE
    assert ap.guided_takeoff(20.0)[0] == DENIED  # not in GUIDED
    assert ap.arm()[0] == DENIED  # the EKF does not use GPS yet
    _until(ap, lambda: ap.position_valid)
    assert ap.home_set
    assert ap.set_custom_mode(GUIDED)[0] == ACCEPTED
    assert ap.guided_takeoff(20.0)[0] == DENIED  # not armed
    assert ap.arm()[0] == ACCEPTED
    assert ap.guided_takeoff(20.0)[0] == ACCEPTED
    ap.step(2.0, 0.0)
    assert ap.pos[2] == 0.0  # the motors spool up first
    _until(ap, lambda: ap.pos[2] > 19.0)
    assert ap.guided_target([30.0, 0.0, 20.0])
    _until(ap, lambda: math.hypot(ap.nav_pos[0] - 30.0, ap.nav_pos[1]) < 1.0 and math.hypot(*ap.vel[:2]) < 0.3)
    assert ap.set_custom_mode(LOITER)[0] == ACCEPTED
    assert not ap.guided_target([0.0, 30.0, 20.0])  # ArduCopter ignores targets outside GUIDED
    assert ap.set_custom_mode(RTL)[0] == ACCEPTED
    assert ap.rtl_return_up_m() == pytest.approx(20.0, abs=0.5)  # above RTL_ALT (15 m): stays at 20 m
    _until(ap, lambda: not ap.armed)
    assert ap.custom_mode == RTL and math.dist(ap.nav_pos[:2], ap.home[:2]) < 1.0  # disarmed in RTL, at home


def test_gps_loss_in_the_air_is_an_ekf_failsafe_that_lands_at_once():
    ap = _copter()
    _until(ap, lambda: ap.position_valid)
    ap.set_custom_mode(GUIDED)
    ap.arm()
    ap.guided_takeoff(15.0)
    _until(ap, lambda: ap.pos[2] > 14.0)
    ap.messages.clear()
    ap.set_gps_lost(True)
    assert ap.custom_mode == LAND and ap.ekf_failsafe
    assert ap.system_status() == M.MAV_STATE_CRITICAL
    assert any("EKF" in text for _, text in ap.messages)
    # Copter::position_ok() is false in the EKF failsafe: a ground station's RTL (sent before it
    # saw the LAND) is refused, as are GUIDED and AUTO
    assert ap.set_custom_mode(RTL)[0] == DENIED and ap.return_to_launch()[0] == DENIED
    assert ap.set_custom_mode(GUIDED)[0] == DENIED
    _until(ap, lambda: not ap.armed)
    assert ap.custom_mode == LAND


def test_parameters_are_arducopters_and_int32_travel_c_cast():
    ap = _copter()
    assert ap.params["RTL_ALT"] == 1500 and ap.params["WPNAV_SPEED"] == 1000
    assert "MPC_XY_CRUISE" not in ap.params  # PX4's names are not on the wire ...
    assert ap.params["MPC_XY_CRUISE"] == 10.0  # ... but answered from ArduCopter's for the flight
    assert encode_param_value(1500, M.MAV_PARAM_TYPE_INT32, bytewise=False) == 1500.0


def _recv_types(conn, wall_s: float) -> dict[str, object]:
    seen: dict[str, object] = {}
    end = time.monotonic() + wall_s
    while time.monotonic() < end:
        msg = conn.recv_match(blocking=True, timeout=0.1)
        if msg is not None and msg.get_type() != "BAD_DATA":
            seen[msg.get_type()] = msg
    return seen


def test_streams_nothing_but_heartbeat_until_asked():
    with VehicleSimulator(HOME, ARDUPILOT, speedup=10.0, target=None, bind=("127.0.0.1", 0)) as sim:
        conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{sim.local_address[1]}", source_system=255,
                                          dialect="ardupilotmega")
        try:
            conn.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            seen = _recv_types(conn, 1.5)
            assert set(seen) <= {"HEARTBEAT", "STATUSTEXT"}, set(seen)
            hb = seen["HEARTBEAT"]
            assert (hb.autopilot, hb.type, hb.custom_mode) == (M.MAV_AUTOPILOT_ARDUPILOTMEGA, M.MAV_TYPE_QUADROTOR, 0)
            conn.mav.command_long_send(1, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                       M.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 2e5, 0, 0, 0, 0, 0)
            conn.mav.request_data_stream_send(1, 1, M.MAV_DATA_STREAM_POSITION, 5, 1)
            seen = _recv_types(conn, 1.5)
            assert {"EKF_STATUS_REPORT", "GLOBAL_POSITION_INT", "COMMAND_ACK"} <= set(seen), set(seen)
            assert "SYS_STATUS" not in seen and "ATTITUDE" not in seen  # not asked for
        finally:
            conn.close()


def test_the_adapter_detects_ardupilot_and_flies_it_by_its_modes():
    async def fly():
        port = _free_udp_port()
        async with VehicleSimulator(HOME, ARDUPILOT, speedup=20.0, target=("127.0.0.1", port),
                                    bind=("127.0.0.1", 0)) as sim, MavsdkVehicle(f"udpin://127.0.0.1:{port}") as v:
            await v.connect(20.0)
            assert v.state.autopilot == "ardupilot"
            fixes = []
            telemetry = asyncio.create_task(v.run_telemetry(fixes.append))
            home = await v.wait_ready(60.0)
            assert abs(home.lat_deg - HOME.lat_deg) < 1e-5 and abs(home.lon_deg - HOME.lon_deg) < 1e-5
            assert v.state.global_position_ok and v.state.flight_mode == "STABILIZE"
            await v.arm()
            await v.takeoff(10.0)
            await sim.wait_for(lambda s: s.pos_enu_m[2] > 9.0, 30.0)
            await v.set_speed(8.0)
            lat, lon, _ = HOME.enu_to_lla(np.array([20.0, 0.0, 0.0]))
            await v.goto_location(float(lat), float(lon), HOME.alt_m + 10.0)
            await sim.wait_for(lambda s: s.pos_enu_m[0] > 15.0, 30.0)
            await v.return_to_launch()
            await _until_async(lambda: v.state.flight_mode == "RETURN_TO_LAUNCH", 5.0)
            with pytest.raises(VehicleCommandError, match="not GUIDED"):
                await v.goto_location(float(lat), float(lon), HOME.alt_m + 10.0)
            await _until_async(lambda: v.state.armed is False and v.state.landed_state == "ON_GROUND", 60.0)
            telemetry.cancel()
            with pytest.raises(asyncio.CancelledError):
                await telemetry
            return fixes, sim.state()

    fixes, final = asyncio.run(asyncio.wait_for(fly(), 120.0))
    assert fixes and all(abs(f.lat_deg) > 1.0 for f in fixes)  # no 0, 0 fixes passed on
    assert not final.armed and final.mode == "return_to_launch"


def test_not_ready_names_what_ardupilot_reports_when_the_ekf_has_no_gps():
    async def fly():
        port = _free_udp_port()
        async with VehicleSimulator(HOME, ARDUPILOT, speedup=20.0, target=("127.0.0.1", port),
                                    bind=("127.0.0.1", 0)) as sim, MavsdkVehicle(f"udpin://127.0.0.1:{port}") as v:
            sim.lose_gps()
            await v.connect(20.0)
            with pytest.raises(VehicleTimeoutError) as err:
                await v.wait_ready(2.0)
            return str(err.value)

    message = asyncio.run(asyncio.wait_for(fly(), 60.0))
    assert message.startswith("vehicle not ready within 2 s (EKF global position ok: False"), message
    assert "GPS fix type: 1" in message and "flags 0xa7" in message, message


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def _until_async(cond, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.05)


@pytest.mark.sim
@pytest.mark.slow
def test_three_user_mission_on_the_ardupilot_personality_ends_by_its_stop_rule_and_lands(tmp_path):
    """`uavloc sim three_users_nlos --autopilot ardupilot`: the survey ends by its stop rule, RTL by
    ArduCopter's mode, landed and disarmed in RTL, and the log replays to the mission's answer.

    The stop rule's verdict is the target reached or, when a user's bound stalls above it, the floor
    reached (planner.stop.FloorWatch): which one is statistical, not a property of the autopilot.
    On a busy machine the wall-clock timing of the rounds changes the flight, and some runs end with
    the NLoS user ue1 stalled near 5 m (a CI run, target 4 m: 5.89, 5.58, 5.18, 5.14 m at 989, 1235,
    1467 and 1550 m flown). Not asserted either: each user's error against its own 95 %
    bound. Over 11 runs on this personality 6 had every user inside its bound, and one had a user
    7.8 m off (bound 3.2 m); PX4's personality did the same (2 of 4 inside, one user 27 m off): NLoS
    range biases and the estimator, alike on either autopilot (docs/ardupilot.md)."""
    sc = with_autopilot(load_scenario("three_users_nlos"), "ardupilot")
    log_path = tmp_path / "mission.jsonl"

    async def fly():
        async with SimulatedMission(sc, log_path, speedup=20.0) as sim:
            result = await sim.run()
            return result, sim.vehicle_sim.state()

    result, final = asyncio.run(asyncio.wait_for(fly(), 300.0))
    assert result.status in (STATUS_TARGET, STATUS_FLOOR), (result.reason, result.events[-8:])
    assert result.error_m() is not None and len(result.error_m()) == 3
    assert result.rtl_sent and result.landed
    assert not final.armed and final.mode == "return_to_launch"
    kinds = [e.get("kind") for e in read_mission_log(log_path).events]
    for kind in ("home", "arm", "takeoff", "speed", "stop", "rtl", "landed", "end"):
        assert kind in kinds, kind
    assert_log_replays_to_the_result(log_path, result)


@pytest.mark.sim
def test_gps_loss_on_ardupilot_is_its_failsafe_landing_logged_as_events(tmp_path):
    """The EKF failsafe lands the vehicle; the controller logs ArduPilot's texts, sees the position
    lost and the switch to LAND, and sends no RTL over it."""
    sc = with_autopilot(load_scenario("paper"), "ardupilot")
    log_path = tmp_path / "mission.jsonl"

    async def fly():
        async with SimulatedMission(sc, log_path, speedup=20.0, planner="lawnmower") as sim:
            task = asyncio.create_task(sim.run())
            await _until_async(lambda: sim.controller is not None and sim.controller.measurements >= 5, 90.0)
            sim.vehicle_sim.lose_gps()
            result = await task
            await sim.vehicle_sim.wait_for(lambda s: not s.armed, 60.0)
            return result, sim.vehicle_sim.state()

    result, final = asyncio.run(asyncio.wait_for(fly(), 200.0))
    assert final.mode == "land" and not final.armed
    events = read_mission_log(log_path).events
    texts = [e["message"] for e in events if e.get("kind") == "vehicle_text"]
    assert any("EKF" in t for t in texts), texts
    kinds = [e.get("kind") for e in events]
    assert "position_lost" in kinds and "autopilot_land" in kinds, kinds
    assert "LAND" in result.reason or "GPS" in result.reason, result.reason


def test_ctrl_c_on_uavloc_sim_with_ardupilot_sends_rtl(tmp_path):
    """SIGINT to `uavloc sim paper --autopilot ardupilot` → RTL (ArduCopter's mode 6), the log
    flushed, exit code 130."""
    ctrl_c_uavloc_sim(tmp_path, "--autopilot", "ardupilot", "--speedup", "20", wait_s=90.0)
