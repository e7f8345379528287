"""Mission, offboard, parameter and message-interval protocols of the built-in vehicle, driven by
MAVSDK's own plugins (mission, mission_raw, offboard, param, telemetry)."""

from __future__ import annotations

import asyncio
import math
import socket
import time

import pytest
from mavsdk.asyncio.plugins.mission import MissionAsync
from mavsdk.asyncio.plugins.mission_raw import MissionRawAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync
from mavsdk.asyncio.plugins.param import ParamAsync
from mavsdk.plugins.mission import MissionItem, MissionPlan
from mavsdk.plugins.mission_raw import MissionItem as RawItem
from mavsdk.plugins.mission_raw import MissionRawError
from mavsdk.plugins.offboard import PositionGlobalYaw, PositionNedYaw, VelocityNedYaw
from mavsdk.plugins.telemetry import FlightMode, LandedState

from sitl_scenarios.scenario import VehicleConfig
from tests.test_vehicle_mavsdk import ORIGIN, first, horizontal_m, vehicle_link


def _item(north_m: float, east_m: float, alt_m: float, **kw) -> MissionItem:
    lat, lon, _ = ORIGIN.enu_to_lla([east_m, north_m, 0.0])
    args = dict(latitude_deg=float(lat), longitude_deg=float(lon), relative_altitude_m=alt_m,
                speed_m_s=float("nan"), is_fly_through=True, gimbal_pitch_deg=float("nan"),
                gimbal_yaw_deg=float("nan"), camera_action=MissionItem.CameraAction.NONE,
                loiter_time_s=float("nan"), camera_photo_interval_s=float("nan"),
                acceptance_radius_m=float("nan"), yaw_deg=float("nan"),
                camera_photo_distance_m=float("nan"), vehicle_action=MissionItem.VehicleAction.NONE)
    args.update(kw)
    return MissionItem(**args)


def test_mission_upload_download_fly_and_rtl() -> None:
    """Upload 3 waypoints (the second with a speed change), download them back, start on the
    ground (PX4 inserts the takeoff), visit every waypoint in order, return and land."""
    async def run() -> None:
        # like PX4, the vehicle flies its estimated position to a waypoint and the GPS error drifts
        # (Gauss-Markov): a PX4-SITL-sized error keeps the true track within the checks' tolerance
        async with vehicle_link("builtin", speedup=10.0, vehicle=VehicleConfig(gps_sigma_m=0.15)) as link:
            mission = MissionAsync(link.system)
            await link.action.set_return_to_launch_altitude(30.0)
            # a tight acceptance radius: the vehicle brakes into each waypoint, which the polled
            # track below then cannot miss even on a loaded machine
            plan = MissionPlan([
                _item(40.0, 0.0, 15.0, acceptance_radius_m=0.5),
                _item(40.0, 40.0, 15.0, speed_m_s=5.0, acceptance_radius_m=0.5),
                _item(0.0, 40.0, 25.0, acceptance_radius_m=0.5),
            ])
            await mission.set_return_to_launch_after_mission(True)
            await mission.upload_mission(plan)
            back = await mission.download_mission()
            assert len(back.mission_items) == 3
            for a, b in zip(back.mission_items, plan.mission_items, strict=True):
                assert a.latitude_deg == pytest.approx(b.latitude_deg, abs=1e-7)
                assert a.longitude_deg == pytest.approx(b.longitude_deg, abs=1e-7)
                assert a.relative_altitude_m == pytest.approx(b.relative_altitude_m)
            await first(link.telemetry.subscribe_health(), lambda h: h.is_global_position_ok
                        and h.is_home_position_ok, 5.0)
            await link.action.arm()
            await mission.start_mission()
            await first(link.telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.MISSION, 5.0)
            wps = [(0.0, 40.0, 15.0), (40.0, 40.0, 15.0), (40.0, 0.0, 25.0)]  # ENU
            seen: list[int] = []

            async def track() -> None:  # the true track, polled every few simulated centimetres
                while True:
                    pos = link.sim.state().pos_enu_m
                    for k, wp in enumerate(wps):
                        if k not in seen and horizontal_m(pos[:2], wp[:2]) < 2.0 and abs(pos[2] - wp[2]) < 1.0:
                            seen.append(k)
                    await asyncio.sleep(0.002)

            tracker = asyncio.create_task(track())
            try:
                await first(mission.subscribe_mission_progress(), lambda p: p.current == 3, 60.0)
                await first(link.telemetry.subscribe_flight_mode(),
                            lambda m: m == FlightMode.RETURN_TO_LAUNCH, 10.0)
                await first(link.telemetry.subscribe_landed_state(), lambda s: s == LandedState.ON_GROUND,
                            30.0)
            finally:
                tracker.cancel()
                await asyncio.gather(tracker, return_exceptions=True)
            assert seen == [0, 1, 2]
            assert await mission.is_mission_finished()
            await first(link.telemetry.subscribe_armed(), lambda a: not a, 10.0)
            st = link.sim.state()
            assert horizontal_m(st.pos_enu_m[:2], (0.0, 0.0)) < 0.5

            await mission.clear_mission()
            assert len((await mission.download_mission()).mission_items) == 0

    asyncio.run(run())


def test_mission_raw_rejects_unsupported_command() -> None:
    async def run() -> None:
        async with vehicle_link("builtin", speedup=10.0) as link:
            raw = MissionRawAsync(link.system)
            bad = RawItem(seq=0, frame=6, command=31000, current=1, autocontinue=1, param1=0.0,
                          param2=0.0, param3=0.0, param4=0.0, x=0, y=0, z=10.0, mission_type=0)
            with pytest.raises(MissionRawError):
                await raw.upload_mission([bad])
            assert link.sim.state().mode == "hold"

    asyncio.run(run())


def test_offboard_position_setpoints() -> None:
    """MAVSDK offboard: stream a NED position, start offboard, the vehicle flies there; when the
    setpoints stop (offboard.stop), PX4 leaves offboard for Hold."""
    async def run() -> None:
        async with vehicle_link("builtin", speedup=10.0) as link:
            off = OffboardAsync(link.system)
            await first(link.telemetry.subscribe_health(), lambda h: h.is_global_position_ok
                        and h.is_home_position_ok, 5.0)
            await link.action.arm()
            await off.set_position_ned(PositionNedYaw(10.0, -20.0, -15.0, 0.0))
            await off.start()
            await first(link.telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, 5.0)
            await link.sim.wait_for(lambda s: math.dist(s.pos_enu_m, (-20.0, 10.0, 15.0)) < 0.3, 20.0)
            # global setpoints, altitude above home (SET_POSITION_TARGET_GLOBAL_INT, relative frame)
            lat, lon, _ = ORIGIN.enu_to_lla([15.0, -5.0, 0.0])
            await off.set_position_global(PositionGlobalYaw(
                float(lat), float(lon), 12.0, 0.0, PositionGlobalYaw.AltitudeType.REL_HOME))
            await link.sim.wait_for(lambda s: math.dist(s.pos_enu_m, (15.0, -5.0, 12.0)) < 0.3, 20.0)
            # velocity setpoints (NED): 2 m/s east
            await off.set_velocity_ned(VelocityNedYaw(0.0, 2.0, 0.0, 0.0))
            await link.sim.wait_for(lambda s: s.pos_enu_m[0] > 25.0, 20.0)
            assert link.sim.state().vel_enu_mps == pytest.approx([2.0, 0.0, 0.0], abs=1e-6)
            await off.set_position_ned(PositionNedYaw(10.0, -20.0, -15.0, 0.0))
            await link.sim.wait_for(lambda s: math.dist(s.pos_enu_m, (-20.0, 10.0, 15.0)) < 0.3, 20.0)
            await off.stop()
            await first(link.telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 5.0)
            st = link.sim.state()
            assert st.in_air and math.dist(st.pos_enu_m, (-20.0, 10.0, 15.0)) < 1.0

    asyncio.run(run())


def test_params_list_read_set() -> None:
    async def run() -> None:
        async with vehicle_link("builtin", speedup=5.0) as link:
            param = ParamAsync(link.system)
            every = await param.get_all_params()
            names = {p.name for p in every.float_params} | {p.name for p in every.int_params}
            assert {"MIS_TAKEOFF_ALT", "RTL_RETURN_ALT", "MPC_XY_CRUISE", "NAV_ACC_RAD",
                    "COM_DISARM_LAND", "SYS_AUTOSTART"} <= names
            ints = {p.name: p.value for p in every.int_params}
            assert ints["MAV_SYS_ID"] == 1 and ints["SYS_AUTOSTART"] == 4001
            await param.set_param_float("MPC_XY_CRUISE", 7.5)
            assert await param.get_param_float("MPC_XY_CRUISE") == pytest.approx(7.5)
            assert link.sim.param("MPC_XY_CRUISE") == pytest.approx(7.5)
            assert await link.action.get_return_to_launch_altitude() == pytest.approx(30.0)  # PX4 SITL default

    asyncio.run(run())


def test_set_message_interval_changes_the_stream_interval() -> None:
    """Telemetry.set_rate_battery → MAV_CMD_SET_MESSAGE_INTERVAL (vehicle time): the vehicle then
    reports the new interval to MAV_CMD_GET_MESSAGE_INTERVAL from a second ground station, and the
    stream keeps flowing. (That an interval is kept on the wire: test_stream_schedule_*.)"""
    from pymavlink.dialects.v20 import common as mavlink

    def interval_us(gcs: socket.socket, sim_address, msg_id: int) -> int:
        out, parser = mavlink.MAVLink(None, 245, 191), mavlink.MAVLink(None)
        parser.robust_parsing = True
        msg = mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, 0,
                                                   msg_id, 0, 0, 0, 0, 0, 0)
        gcs.sendto(msg.pack(out), sim_address)
        deadline = time.monotonic() + 10.0  # a hang guard
        while time.monotonic() < deadline:
            data, _ = gcs.recvfrom(65535)
            for m in parser.parse_buffer(data) or []:
                if m.get_type() == "MESSAGE_INTERVAL" and m.message_id == msg_id:
                    return m.interval_us
        raise AssertionError("no MESSAGE_INTERVAL answer")

    async def run() -> list[int]:
        seen = []
        async with vehicle_link("builtin", speedup=1.0) as link:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
                gcs.bind(("127.0.0.1", 0))
                gcs.settimeout(10.0)
                address = link.sim.local_address
                bat = mavlink.MAVLINK_MSG_ID_BATTERY_STATUS
                await first(link.telemetry.subscribe_battery(), lambda b: True, 5.0)
                seen.append(await asyncio.to_thread(interval_us, gcs, address, bat))
                await link.telemetry.set_rate_battery(10.0)
                seen.append(await asyncio.to_thread(interval_us, gcs, address, bat))
                await first(link.telemetry.subscribe_battery(), lambda b: True, 5.0)
                await link.telemetry.set_rate_battery(1.0)
                seen.append(await asyncio.to_thread(interval_us, gcs, address, bat))
                await first(link.telemetry.subscribe_battery(), lambda b: True, 5.0)
        return seen

    assert asyncio.run(run()) == [2_000_000, 100_000, 1_000_000]  # PX4's BATTERY_STATUS: 0.5 Hz


def test_raw_link_two_targets_and_malformed_command() -> None:
    """Both targets get the streams before anyone talks; a command with a NaN message id is
    refused (DENIED) instead of taking the vehicle down; REQUEST_MESSAGE answers AUTOPILOT_VERSION
    with PX4's capability bits; an unknown command is UNSUPPORTED."""
    from pymavlink.dialects.v20 import common as mavlink

    from sitl_scenarios.vehicle import VehicleSimulator, px4

    def recv_until(sock, parser, kind: str, timeout_s: float = 5.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            sock.settimeout(max(deadline - time.monotonic(), 0.01))
            data, addr = sock.recvfrom(65535)
            for m in parser.parse_buffer(data) or []:
                if m.get_type() == kind:
                    return m, addr
        raise AssertionError(f"no {kind} within {timeout_s} s")

    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        targets = [s.getsockname() for s in socks]
        with VehicleSimulator(ORIGIN, speedup=5.0, target=targets, bind=("127.0.0.1", 0)) as sim:
            parsers = [mavlink.MAVLink(None, 245, 190) for _ in socks]
            for p in parsers:
                p.robust_parsing = True
            for s, p in zip(socks, parsers, strict=True):
                hb, addr = recv_until(s, p, "HEARTBEAT")
                assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4 and addr == sim.local_address
            gcs, parser = socks[0], parsers[0]
            out = mavlink.MAVLink(None, 245, 190)

            def command(cmd: int, *params: float) -> int:
                msg = mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *params)
                gcs.sendto(msg.pack(out), sim.local_address)
                while True:
                    ack, _ = recv_until(gcs, parser, "COMMAND_ACK")
                    if ack.command == cmd:
                        return ack.result

            nan = float("nan")
            assert command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, nan, 1e5, 0, 0, 0, 0, 0) == mavlink.MAV_RESULT_DENIED
            assert command(31337, 0, 0, 0, 0, 0, 0, 0) == mavlink.MAV_RESULT_UNSUPPORTED
            assert command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                           0, 0, 0, 0, 0, 0) == mavlink.MAV_RESULT_ACCEPTED
            version, _ = recv_until(gcs, parser, "AUTOPILOT_VERSION")
            assert version.capabilities == px4.PX4_CAPABILITIES
            assert version.flight_sw_version >> 24 == 1
            assert sim.state().t_s > 0  # still running
    finally:
        for s in socks:
            s.close()


def test_vehicle_clock_is_speedup_times_the_wall_clock_and_stamps_are_vehicle_time() -> None:
    """The simulation follows a wall clock the test moves (so nothing depends on how fast this
    machine runs): 2 wall seconds at speedup 8 are 16 vehicle seconds, and every stream's stamp is
    vehicle time. The rates on the wire are checked by test_stream_schedule_* (a synthetic clock),
    their wall-clock values measured by `python benchmarks/vehicle.py`."""
    from pymavlink.dialects.v20 import common as mavlink

    from sitl_scenarios.vehicle import VehicleSimulator

    wall = [1000.0]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        # each 0.5 s jump of the clock brings 4 vehicle seconds of every stream at once, read at the
        # end: room for all of them
        gcs.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        gcs.bind(("127.0.0.1", 0))
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        with VehicleSimulator(ORIGIN, speedup=8.0, target=gcs.getsockname(), bind=("127.0.0.1", 0),
                              clock=lambda: wall[0]) as sim:
            for k in range(1, 5):
                wall[0] = 1000.0 + 0.5 * k
                deadline = time.monotonic() + 30.0  # a hang guard, not a bound on speed
                while sim.state().t_s < 8.0 * 0.5 * k - 1e-6:
                    assert time.monotonic() < deadline, "the simulation thread never followed its clock"
                    time.sleep(0.005)
                assert sim.state().t_s == pytest.approx(8.0 * 0.5 * k, abs=1e-6)
            t_end_s = sim.state().t_s
            stamps_ms: dict[str, list[int]] = {"ATTITUDE": [], "SYSTEM_TIME": []}
            gcs.settimeout(0.5)
            while True:
                try:
                    data, _ = gcs.recvfrom(65535)
                except TimeoutError:
                    break
                for m in parser.parse_buffer(data) or []:
                    if m.get_type() in stamps_ms:
                        stamps_ms[m.get_type()].append(m.time_boot_ms)
    assert t_end_s == pytest.approx(16.0, abs=1e-6)
    for kind, ms in stamps_ms.items():
        assert ms == sorted(ms) and ms, kind
        # vehicle time: the last one within a period of the end (ATTITUDE capped at 25 Hz on the
        # wire: every 8 / 25 vehicle seconds; SYSTEM_TIME every second)
        period_ms = {"ATTITUDE": 8.0 / 25.0 * 1e3, "SYSTEM_TIME": 1e3}[kind]
        assert 16000 - period_ms - 1 <= max(ms) <= 16000, kind
        assert min(ms) < 4000, kind  # and the first ones early in vehicle time


def test_failure_in_the_simulation_thread_surfaces_on_stop_and_state() -> None:
    from sitl_scenarios.vehicle import VehicleSimulator
    from uavloc.errors import SimulatorError

    sim = VehicleSimulator(ORIGIN, target=None, bind=("127.0.0.1", 0))

    def broken(now: float) -> None:
        raise RuntimeError("physics exploded")

    sim._tick = broken  # type: ignore[method-assign]
    sim.start()
    with pytest.raises(SimulatorError):
        sim.start()  # already started
    deadline = time.monotonic() + 5.0
    while sim._error is None and time.monotonic() < deadline:
        time.sleep(0.01)
    with pytest.raises(SimulatorError, match="physics exploded"):
        sim.state()
    with pytest.raises(SimulatorError, match="physics exploded"):
        sim.stop()
    sim.stop()  # once reported, stopping again is quiet


def test_bind_failure_is_a_simulator_error() -> None:
    from sitl_scenarios.vehicle import VehicleSimulator
    from uavloc.errors import SimulatorError

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        sim = VehicleSimulator(ORIGIN, target=None, bind=taken.getsockname())
        with pytest.raises(SimulatorError, match="cannot bind"):
            sim.start()


@pytest.mark.parametrize(("parts", "want"), [
    (["udp", "127.0.0.1:14540"], [("127.0.0.1", 14540)]),
    (["udp://10.0.0.2:14550"], [("10.0.0.2", 14550)]),
    (["127.0.0.1:14540", "127.0.0.1:14541"], [("127.0.0.1", 14540), ("127.0.0.1", 14541)]),
    (["udp", ":14600"], [("127.0.0.1", 14600)]),
    (["none"], []),
])
def test_vehicle_cli_targets(parts, want):
    from sitl_scenarios.vehicle.cli import _parse_targets

    assert _parse_targets(parts) == want


@pytest.mark.parametrize("parts", [["udp", "localhost"], ["127.0.0.1:0"], ["127.0.0.1:70000"], ["host:port"]])
def test_vehicle_cli_bad_target_names_it(parts):
    from sitl_scenarios.vehicle.cli import _parse_targets
    from uavloc.errors import SimulatorError

    with pytest.raises(SimulatorError, match="--target must be"):
        _parse_targets(parts)
