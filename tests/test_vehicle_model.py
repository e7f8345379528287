"""The built-in vehicle's autopilot without a link: PX4 encodings, flight-model bounds, RTL,
refusals, failsafes, battery and GPS noise. Pure and fast: simulated time only."""

from __future__ import annotations

import math
import socket
import subprocess
import sys

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from estimator.geodesy import Origin
from sitl_scenarios.scenario import VehicleConfig
from sitl_scenarios.vehicle import px4
from sitl_scenarios.vehicle.autopilot import Autopilot
from sitl_scenarios.vehicle.kinematics import MAX_SUBSTEP_S
from sitl_scenarios.vehicle.mav import ACCEPTED, DENIED, LANDED_ON_GROUND
from sitl_scenarios.vehicle.params import PARAM_TYPE_INT32, decode_param_value, encode_param_value
from sitl_scenarios.vehicle.px4 import FlightMode
from sitl_scenarios.vehicle.sensors import GpsError

ORIGIN = Origin(43.6143, 7.0716, 150.0)


def make(vehicle: VehicleConfig | None = None, seed: int = 0) -> Autopilot:
    ap = Autopilot(ORIGIN, vehicle or VehicleConfig(), np.random.default_rng(seed), gps_fix_delay_s=1.0)
    ap.step(1.5, 0.0)  # GPS fix, home set
    return ap


def run(ap: Autopilot, sim_s: float, record: list | None = None) -> None:
    """Advance sim_s seconds in substeps; record (t, pos, vel) after each: the position the
    autopilot navigates on (its estimate horizontally, Autopilot.nav_pos)."""
    n = round(sim_s / MAX_SUBSTEP_S)
    for _ in range(n):
        ap.step(MAX_SUBSTEP_S, 0.0)
        if record is not None:
            record.append((ap.t_s, list(ap.nav_pos), list(ap.vel)))


def fly_to_altitude(ap: Autopilot, up_m: float) -> None:
    ap.params.set("MIS_TAKEOFF_ALT", up_m)
    assert ap.arm()[0] == ACCEPTED
    assert ap.takeoff()[0] == ACCEPTED
    run(ap, up_m / ap.params["MPC_TKO_SPEED"] + 10)
    assert ap.mode is FlightMode.HOLD and abs(ap.pos[2] - up_m) < 0.1


# --- encodings --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("mode", "custom_mode"),
    [
        (FlightMode.HOLD, 0x03040000),
        (FlightMode.TAKEOFF, 0x02040000),
        (FlightMode.MISSION, 0x04040000),
        (FlightMode.RTL, 0x05040000),
        (FlightMode.LAND, 0x06040000),
        (FlightMode.OFFBOARD, 0x00060000),
        (FlightMode.POSCTL, 0x00030000),
    ],
)
def test_px4_custom_mode_table_and_round_trip(mode: FlightMode, custom_mode: int) -> None:
    assert px4.px4_custom_mode(mode) == custom_mode
    assert px4.mode_from_px4(*px4.px4_main_sub(custom_mode)) is mode


def test_modes_without_sticks_are_not_flown() -> None:
    assert px4.mode_from_px4(px4.MAIN_MANUAL, 0) is None
    assert px4.mode_from_px4(px4.MAIN_ACRO, 0) is None
    assert px4.mode_from_px4(px4.MAIN_AUTO, 0) is FlightMode.HOLD


def test_base_mode_flags() -> None:
    armed = px4.px4_base_mode(FlightMode.HOLD, armed=True)
    assert armed & px4.MODE_FLAG_SAFETY_ARMED and armed & px4.MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not px4.px4_base_mode(FlightMode.HOLD, armed=False) & px4.MODE_FLAG_SAFETY_ARMED


@pytest.mark.parametrize("value", [0, 1, -1, 4001, 2**31 - 1, -(2**31)])
def test_int32_params_travel_bytewise(value: int) -> None:
    wire = encode_param_value(value, PARAM_TYPE_INT32)
    assert np.float32(wire).tobytes() == np.int32(value).tobytes()
    assert decode_param_value(wire, PARAM_TYPE_INT32) == value


def test_autopilot_version_numbers() -> None:
    assert px4.px4_sw_version(1, 15, 4) == 0x010F04FF
    assert px4.PX4_CAPABILITIES & px4.CAP_MISSION_INT and px4.PX4_CAPABILITIES & px4.CAP_COMMAND_INT
    assert not px4.PX4_CAPABILITIES & mavlink.MAV_PROTOCOL_CAPABILITY_FTP  # not implemented


# --- flight model -----------------------------------------------------------------------------
def test_takeoff_and_leg_respect_speed_climb_and_acceleration_limits() -> None:
    # no GPS error: the flight model's own limits (with one, the true track carries it)
    cfg = VehicleConfig(speed_mps=8.0, climb_mps=3.0, accel_mps2=2.0, gps_sigma_m=0.0)
    ap = make(cfg)
    rec: list = []
    ap.params.set("MIS_TAKEOFF_ALT", 20.0)
    ap.arm()
    ap.takeoff()
    run(ap, 25.0, rec)
    assert ap.mode is FlightMode.HOLD
    # PX4 (the recorded legs flight): MPC_TKO_SPEED up to MPC_LAND_ALT1, MPC_Z_V_AUTO_UP above
    low = [v[2] for _, p, v in rec if p[2] < ap.params["MPC_LAND_ALT1"] - 0.5]
    assert max(low) <= ap.params["MPC_TKO_SPEED"] + 1e-9
    assert max(v[2] for _, _, v in rec) <= ap.params["MPC_Z_V_AUTO_UP"] + 1e-9
    lat, lon, alt = ORIGIN.enu_to_lla([0.0, 100.0, 20.0])
    assert ap.change_speed(8.0)[0] == ACCEPTED  # DO_CHANGE_SPEED, as the mission controller commands it
    assert ap.reposition(float(lat), float(lon), float(alt))[0] == ACCEPTED
    rec.clear()
    run(ap, 60.0, rec)
    vh = np.array([math.hypot(v[0], v[1]) for _, _, v in rec])
    assert vh.max() <= 8.0 + 0.05
    assert vh.max() > 0.8 * 8.0  # close to cruise on a 100 m leg (PX4 SITL: 8.6 of 10 m/s on 80 m)
    assert math.dist(ap.nav_pos, (0.0, 100.0, 20.0)) < 0.1
    # never faster than the time-optimal jerk-limited profile: t ≥ d/v + v/a + a/j = 12.5 + 4 + 0.5 s
    t_arrive = next(t for t, p, _ in rec if math.dist(p, (0.0, 100.0, 20.0)) < 0.5)
    assert t_arrive - rec[0][0] > 17.0


def test_cruise_speed_follows_the_px4_parameter() -> None:
    ap = make()
    fly_to_altitude(ap, 10.0)
    ap.params.set("MPC_XY_CRUISE", 4.0)
    lat, lon, alt = ORIGIN.enu_to_lla([200.0, 0.0, 10.0])
    ap.reposition(float(lat), float(lon), float(alt))
    rec: list = []
    run(ap, 40.0, rec)
    assert max(math.hypot(v[0], v[1]) for _, _, v in rec) == pytest.approx(4.0, abs=0.1)


def test_without_a_speed_command_the_vehicle_flies_px4s_default_cruise() -> None:
    ap = make(VehicleConfig(speed_mps=10.0))
    fly_to_altitude(ap, 10.0)
    lat, lon, alt = ORIGIN.enu_to_lla([200.0, 0.0, 10.0])
    ap.reposition(float(lat), float(lon), float(alt))
    rec: list = []
    run(ap, 40.0, rec)
    assert max(math.hypot(v[0], v[1]) for _, _, v in rec) == pytest.approx(5.0, abs=0.1)  # MPC_XY_CRUISE


def test_commanded_speed_is_held_over_the_next_repositions() -> None:
    ap = make()
    fly_to_altitude(ap, 10.0)
    assert ap.change_speed(10.0)[0] == ACCEPTED
    for east in (300.0, 0.0):
        lat, lon, alt = ORIGIN.enu_to_lla([east, 0.0, 10.0])
        ap.reposition(float(lat), float(lon), float(alt))
        rec: list = []
        run(ap, 50.0, rec)
        assert max(math.hypot(v[0], v[1]) for _, _, v in rec) == pytest.approx(10.0, abs=0.2)


@pytest.mark.parametrize(("east_m", "up_m", "expected_up_m"), [
    (200.0, 20.0, 30.0),   # far: RTL_RETURN_ALT
    (200.0, 45.0, 45.0),   # above it: never descends first
    (6.0, 3.0, 6.0),       # inside RTL_MIN_DIST: the 45° cone, d / tan(45°)
    (3.0, 1.0, 4.0),       # ... at least 2 NAV_ACC_RAD
])
def test_rtl_return_height_follows_px4s_rule(east_m: float, up_m: float, expected_up_m: float) -> None:
    ap = make()
    fly_to_altitude(ap, up_m)
    # put its estimate east_m east of home (the autopilot judges distances on its estimate)
    ap.pos[0] += ap.home[0] + east_m - ap.nav_pos[0]
    ap.pos[1] += ap.home[1] - ap.nav_pos[1]
    assert ap.rtl_return_up_m() == pytest.approx(ap.home[2] + max(expected_up_m, ap.pos[2] - ap.home[2]))


def test_rtl_climbs_returns_lands_and_disarms() -> None:
    ap = make(VehicleConfig(gps_sigma_m=0.0))
    fly_to_altitude(ap, 10.0)
    lat, lon, alt = ORIGIN.enu_to_lla([50.0, 50.0, 10.0])
    ap.reposition(float(lat), float(lon), float(alt))
    run(ap, 40.0)
    ap.params.set("RTL_RETURN_ALT", 25.0)
    assert ap.return_to_launch()[0] == ACCEPTED
    rec: list = []
    run(ap, 120.0, rec)
    ups = [p[2] for _, p, _ in rec]
    assert max(ups) == pytest.approx(25.0, abs=0.1)
    # it climbed before it left: still above the start point when reaching 24.5 m
    t_climb = next(i for i, u in enumerate(ups) if u > 24.5)
    assert math.dist(rec[t_climb][1][:2], (50.0, 50.0)) < 0.5
    assert not ap.armed and not ap.in_air and ap.landed_state == LANDED_ON_GROUND
    assert math.dist(ap.nav_pos[:2], ap.home[:2]) < 0.05 and ap.pos[2] == 0.0
    assert any("Disarmed after landing" in text for _, text in ap.messages)


def test_land_descends_slower_near_the_ground() -> None:
    ap = make()
    fly_to_altitude(ap, 30.0)
    ap.land()
    rec: list = []
    run(ap, 60.0, rec)
    v_high = min(v[2] for _, p, v in rec if p[2] > 15.0)
    v_low = min(v[2] for _, p, v in rec if 0.5 < p[2] < 4.0)
    assert v_high == pytest.approx(-ap.params["MPC_Z_V_AUTO_DN"], abs=1e-6)
    assert v_low == pytest.approx(-ap.params["MPC_LAND_SPEED"], abs=1e-6)
    assert not ap.armed


# --- refusals and failsafes -------------------------------------------------------------------
def test_px4_refusals() -> None:
    ap = Autopilot(ORIGIN, VehicleConfig(), np.random.default_rng(0), gps_fix_delay_s=5.0)
    assert ap.arm()[0] == DENIED  # no GPS fix yet
    assert ap.takeoff()[0] == DENIED  # disarmed
    ap.step(6.0, 0.0)
    # disarmed, PX4 selects takeoff mode and climbs once armed (the recorded legs flight)
    assert ap.takeoff()[0] == ACCEPTED and ap.mode is FlightMode.TAKEOFF and not ap.in_air
    assert ap.arm()[0] == ACCEPTED
    assert ap.reposition(43.6144, 7.0716, 170.0)[0] == DENIED  # on the ground
    ap.params.set("MIS_TAKEOFF_ALT", 10.0)
    ap.takeoff()
    run(ap, 3.0)
    assert ap.in_air
    assert ap.disarm()[0] == DENIED  # in the air
    assert ap.disarm(force=True)[0] == ACCEPTED


def _run_at(ap: Autopilot, sim_s: float, speedup: float) -> None:
    """Advance sim_s simulated seconds with the wall clock running at 1/speedup of them."""
    for _ in range(round(sim_s / 0.1)):
        ap.step(0.1, ap.t_s / speedup)


@pytest.mark.parametrize("speedup", [1.0, 0.5])
def test_armed_without_takeoff_disarms_after_com_disarm_prflt(speedup) -> None:
    ap = make()
    ap.arm()
    _run_at(ap, ap.params["COM_DISARM_PRFLT"] - 0.5, speedup)
    assert ap.armed
    _run_at(ap, 1.0, speedup)
    assert not ap.armed
    assert ap.messages[-1][1] == "Disarmed: no takeoff"


def test_the_preflight_disarm_waits_for_the_ground_station_at_x200() -> None:
    """Issue 49: at x200 COM_DISARM_PRFLT's 10 simulated seconds are 0.05 wall seconds, less than
    the ground station's arm-then-take-off round trips: the vehicle disarmed before the take-off
    command came. It waits COM_DISARM_PRFLT on the wall clock too, then takes off when told."""
    ap = make()
    ap.arm()
    wait_s = ap.params["COM_DISARM_PRFLT"]
    _run_at(ap, 100 * wait_s, 200.0)  # 1000 simulated s, 5 wall s: the take-off is on its way
    assert ap.armed
    ap.takeoff()
    run(ap, 3.0)
    assert ap.in_air


def test_the_preflight_disarm_still_comes_at_x200() -> None:
    """...and a vehicle left armed on the ground disarms once COM_DISARM_PRFLT passed on both clocks."""
    ap = make()
    ap.arm()
    wait_s = ap.params["COM_DISARM_PRFLT"]
    _run_at(ap, 200 * wait_s + 1.0, 200.0)  # 10 wall s
    assert not ap.armed


def test_gps_loss_in_flight_dead_reckons_then_lands_blind_and_blocks_arming() -> None:
    """PX4 (the recorded gpsloss flight): the position is kept from dead reckoning for
    DEAD_RECKONING_S, drifting, then the failsafe lands where the vehicle is."""
    from sitl_scenarios.vehicle.sensors import DEAD_RECKONING_S

    ap = make()
    fly_to_altitude(ap, 15.0)
    mode = ap.mode
    ap.set_gps_lost(True)
    run(ap, DEAD_RECKONING_S - 0.2)
    assert ap.mode is mode and ap.position_valid and ap.position_published
    assert 0.0 < np.hypot(*(ap.estimated_position() - np.array(ap.pos))[:2]) < 4.0  # drifting (σ 1 m)
    run(ap, 0.4)
    assert ap.mode is FlightMode.LAND and ap.position_failsafe and not ap.position_valid
    assert ap.position_published  # PX4 keeps publishing its (invalid) position
    run(ap, 60.0)
    assert not ap.armed and not ap.in_air
    assert ap.arm()[0] == DENIED
    ap.set_gps_lost(False)
    assert ap.arm()[0] == ACCEPTED


@pytest.mark.parametrize(("action", "pct", "mode"), [(0, 6.0, FlightMode.HOLD), (1, 6.0, FlightMode.RTL),
                                                      (3, 4.0, FlightMode.LAND), (2, 6.0, FlightMode.HOLD)])
def test_low_battery_action(action: int, pct: float, mode: FlightMode) -> None:
    ap = make()
    ap.params.set("COM_LOW_BAT_ACT", action)
    fly_to_altitude(ap, 10.0)
    ap.set_battery_pct(pct)
    run(ap, 0.1)
    assert ap.mode is mode


def test_battery_drains_with_flight_time() -> None:
    ap = make(VehicleConfig(battery_capacity_s=600.0))
    fly_to_altitude(ap, 5.0)
    before, t0 = ap.battery_pct, ap.t_s
    run(ap, 60.0)
    assert before - ap.battery_pct == pytest.approx(100.0 * (ap.t_s - t0) / 600.0, rel=1e-6)


def test_offboard_needs_setpoints_and_falls_back_to_hold_when_they_stop() -> None:
    ap = make()
    fly_to_altitude(ap, 10.0)
    assert ap.set_mode(FlightMode.OFFBOARD)[0] == DENIED
    ap.offboard_setpoint([5.0, 5.0, 12.0], None, wall_s=0.0)
    ap.step(0.05, 0.1)
    assert ap.set_mode(FlightMode.OFFBOARD)[0] == ACCEPTED
    ap.step(1.0, 0.5)
    assert ap.mode is FlightMode.OFFBOARD
    ap.step(0.05, 2.0)  # wall time passed COM_OF_LOSS_T without a setpoint
    assert ap.mode is FlightMode.HOLD


# --- GPS error --------------------------------------------------------------------------------
def test_gps_error_white_has_sigma_and_is_seeded() -> None:
    a = GpsError(1.5, 0.0, np.random.default_rng(3))
    e = np.array([a.sample(0.1 * k) for k in range(4000)])
    assert e.std(axis=0) == pytest.approx([1.5] * 3, rel=0.06)
    assert abs(np.corrcoef(e[:-1, 0], e[1:, 0])[0, 1]) < 0.05
    b = GpsError(1.5, 0.0, np.random.default_rng(3))
    assert np.array_equal(e[:10], np.array([b.sample(0.1 * k) for k in range(10)]))
    assert np.array_equal(a.sample(a._t_s), a.sample(a._t_s))  # one value per instant


def test_gps_error_gauss_markov_correlation() -> None:
    g = GpsError(1.0, 10.0, np.random.default_rng(5))
    e = np.array([g.sample(0.5 * k) for k in range(20000)])
    # lag-1 correlation of an OU process sampled every Δt: exp(−Δt/τ)
    assert np.corrcoef(e[:-1, 0], e[1:, 0])[0, 1] == pytest.approx(math.exp(-0.05), abs=0.01)
    assert e.std() == pytest.approx(1.0, rel=0.15)


# --- standalone entry point -------------------------------------------------------------------
def test_standalone_module_sends_px4_heartbeats() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        s.settimeout(10.0)
        port = s.getsockname()[1]
        proc = subprocess.Popen(
            [sys.executable, "-m", "sitl_scenarios.vehicle", "--scenario", "paper", "--speedup", "5",
             "--target", "udp", f"127.0.0.1:{port}", "--bind", "127.0.0.1:0", "--duration", "3"],
            stderr=subprocess.PIPE, text=True)
        try:
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = True
            heartbeat = None
            while heartbeat is None:
                data, _ = s.recvfrom(65535)
                for m in parser.parse_buffer(data) or []:
                    if m.get_type() == "HEARTBEAT":
                        heartbeat = m
            assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_PX4
            assert heartbeat.type == mavlink.MAV_TYPE_QUADROTOR
            assert heartbeat.get_srcSystem() == 1 and heartbeat.get_srcComponent() == 1
            assert px4.mode_from_px4(*px4.px4_main_sub(heartbeat.custom_mode)) is FlightMode.HOLD
        finally:
            _, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err


def test_attitude_tilts_into_the_acceleration() -> None:
    ap = make(VehicleConfig(gps_sigma_m=0.0))
    fly_to_altitude(ap, 10.0)
    lat, lon, alt = ORIGIN.enu_to_lla([0.0, 80.0, 10.0])
    ap.reposition(float(lat), float(lon), float(alt))
    run(ap, 1.0)
    roll, pitch = ap.tilt_rad()
    # accelerating north while heading north: nose down by atan(a/g), no roll
    assert ap.acc[1] > 1.0
    assert pitch == pytest.approx(-math.atan2(ap.acc[1], 9.81), abs=1e-6)
    assert roll == pytest.approx(0.0, abs=1e-6)
    run(ap, 60.0)
    assert ap.tilt_rad() == pytest.approx((0.0, 0.0), abs=1e-3)


@pytest.mark.parametrize(("rpy", "q"), [
    ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)),
    ((0.0, 0.0, math.pi / 2), (math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))),
    ((math.pi / 2, 0.0, 0.0), (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0)),
    ((0.0, -math.pi / 2, 0.0), (math.sqrt(0.5), 0.0, -math.sqrt(0.5), 0.0)),
])
def test_euler_to_quaternion_table(rpy: tuple, q: tuple) -> None:
    from sitl_scenarios.vehicle import _quaternion

    assert _quaternion(*rpy) == pytest.approx(q, abs=1e-12)


@pytest.mark.parametrize(
    ("speedup", "heartbeats", "attitudes"),
    [
        (8.0, 16, 50),  # heartbeat 1 Hz vehicle time = 8 Hz wall; ATTITUDE 50 Hz x 8 capped at 25 Hz
        (0.5, 2, 50),  # heartbeat 0.5 Hz wall raised to 1 Hz wall; ATTITUDE 50 Hz x 0.5 = 25 Hz
    ],
)
def test_stream_schedule_rates_follow_vehicle_time_with_wall_caps(
    speedup: float, heartbeats: int, attitudes: int
) -> None:
    """Two wall seconds of 10 ms steps on a synthetic clock: streams are timed in vehicle time,
    capped at 25 Hz on the wire, the heartbeat at least once per wall second."""
    from collections import Counter

    from sitl_scenarios.vehicle.streams import StreamSchedule

    sched = StreamSchedule(speedup, max_wall_hz=25.0)
    sent = Counter(m for k in range(200) for m in sched.due(k * 0.01 * speedup, k * 0.01))
    assert sent[mavlink.MAVLINK_MSG_ID_HEARTBEAT] == heartbeats
    assert sent[mavlink.MAVLINK_MSG_ID_ATTITUDE] == attitudes
    assert sent[mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION] == 0  # only on request


def test_stream_schedule_set_interval_stop_and_default() -> None:
    """SET_MESSAGE_INTERVAL semantics (vehicle time): a positive interval [µs] is kept on the
    synthetic clock, -1 stops the stream, 0 restores the default; unknown messages are refused."""
    from sitl_scenarios.vehicle.mav import ACCEPTED, UNSUPPORTED
    from sitl_scenarios.vehicle.streams import DEFAULT_INTERVALS_S, StreamSchedule

    bat = mavlink.MAVLINK_MSG_ID_BATTERY_STATUS
    sched = StreamSchedule(1.0, max_wall_hz=25.0)

    def count(t0_s: float) -> int:
        return sum(bat in sched.due(t0_s + k * 0.01, t0_s + k * 0.01) for k in range(100))  # one second

    assert sched.set_interval(bat, 100_000) == ACCEPTED and sched.interval_us(bat) == 100_000
    assert count(0.0) == 10
    assert sched.set_interval(bat, -1) == ACCEPTED and sched.interval_us(bat) == -1
    assert count(1.0) == 0
    assert sched.set_interval(bat, 0) == ACCEPTED
    assert sched.intervals_s[bat] == DEFAULT_INTERVALS_S[bat] == 2.0  # PX4's BATTERY_STATUS, 0.5 Hz
    assert count(2.0) == 1
    assert sched.set_interval(31337, 100_000) == UNSUPPORTED
    assert sched.set_interval(bat, math.nan) == UNSUPPORTED
