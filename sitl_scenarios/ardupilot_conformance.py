"""The recorded real ArduCopter flight as figures, and the same flight flown over MAVLink.

The ArduPilot side of the conformance tests (tests/test_ardupilot_conformance.py): the figures are
measured by the PX4 conformance code (:func:`sitl_scenarios.px4_conformance.legs_figures`, which
reads either autopilot's heartbeats), and :class:`ArduPilotFlight` flies the recorded procedure
(../shared/data/README.md, `ardupilot-4.7-sitl/legs`) with ArduCopter's primitives:

    REQUEST_DATA_STREAM (all, 10 Hz); wait for the EKF to use GPS (EKF_STATUS_REPORT), a 3-D fix
    and a position; DO_SET_MODE GUIDED (custom mode 4); arm; NAV_TAKEOFF to 20 m above home; once
    above 19 m, DO_CHANGE_SPEED 10 m/s; SET_POSITION_TARGET_GLOBAL_INT (relative altitude 20 m)
    legs of 15 m east, 40 m north, 80 m east, 300 m north, each from rest at the end of the last
    (2 s wall after within 1 m and slower than 0.3 m/s); DO_SET_MODE RTL (6) until disarmed.

    python -m sitl_scenarios.ardupilot_conformance LEGS.tlog[.gz] > figures.json
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pymavlink import mavutil

from sitl_scenarios.px4_conformance import HEIGHT_M, SPEED_MPS, Flight, figures_main, fly_builtin, legs_figures

#: ArduCopter's custom modes used (pymavlink mavutil.mode_mapping_acm)
GUIDED, RTL = 4, 6
#: EKF_STATUS_REPORT flags of a usable global position (ardupilotmega.xml EKF_STATUS_FLAGS)
EKF_POS_HORIZ_ABS, EKF_CONST_POS_MODE = 16, 128
#: position only: velocity, acceleration, yaw and yaw rate ignored (POSITION_TARGET_TYPEMASK)
POSITION_ONLY_MASK = 0x0DF8
#: the recorded flight's streams: REQUEST_DATA_STREAM all at this rate [Hz of autopilot time]
STREAM_HZ = 10


class ArduPilotFlight(Flight):
    """The legs flight's primitives as ArduCopter flies them (module docstring)."""

    DIALECT = "ardupilotmega"

    def __init__(self, conn, timeout_s: float = 120.0, tlog=None):
        super().__init__(conn, timeout_s, tlog)
        self.ekf_flags = 0
        self.fix_type = 0
        self.gpi = None

    def _pump(self, blocking: bool = True):
        msg = super()._pump(blocking)
        if msg is not None:
            kind = msg.get_type()
            if kind == "EKF_STATUS_REPORT":
                self.ekf_flags = msg.flags
            elif kind == "GPS_RAW_INT":
                self.fix_type = msg.fix_type
            elif kind == "GLOBAL_POSITION_INT":
                self.gpi = msg
        return msg

    def ready(self) -> bool:
        return (self.hb is not None and self.lp is not None and self.gpi is not None and self.fix_type >= 3
                and self.ekf_flags & EKF_POS_HORIZ_ABS and not self.ekf_flags & EKF_CONST_POS_MODE)

    def start(self) -> None:
        self.conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        self.wait(lambda: self.hb is not None, "a heartbeat")
        self.conn.target_system, self.conn.target_component = self.conn.target_system or 1, 1
        self.conn.mav.request_data_stream_send(self.conn.target_system, self.conn.target_component,
                                               mavutil.mavlink.MAV_DATA_STREAM_ALL, STREAM_HZ, 1)
        self.wait(self.ready, "the EKF using GPS, a 3-D fix and a position")
        self.home = None  # where the vehicle stands now the EKF has its global position
        self.wait(lambda: self.home is not None, "a global position")

    def set_mode(self, custom_mode: int) -> None:
        self.command_long(mavutil.mavlink.MAV_CMD_DO_SET_MODE, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                          custom_mode)
        self.wait(lambda: self.hb.custom_mode == custom_mode, f"mode {custom_mode}")

    def takeoff(self) -> None:
        """GUIDED, arm, NAV_TAKEOFF to HEIGHT_M above home, DO_CHANGE_SPEED near the top."""
        self.set_mode(GUIDED)
        self.command_long(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        self.wait(self.armed, "armed")
        self.command_long(mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, HEIGHT_M)
        self.wait(lambda: -self.lp.z > HEIGHT_M - 1.0, f"the climb to {HEIGHT_M:g} m")
        self.command_long(mavutil.mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, SPEED_MPS, -1)

    def reposition(self, east_m: float, north_m: float) -> tuple[float, float]:
        """SET_POSITION_TARGET_GLOBAL_INT to (east, north) ENU [m] of home, HEIGHT_M above it."""
        lat, lon, _ = self.home.enu_to_lla(np.array([east_m, north_m, 0.0]))
        self.conn.mav.set_position_target_global_int_send(
            0, self.conn.target_system, self.conn.target_component,
            mavutil.mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, POSITION_ONLY_MASK, round(lat * 1e7), round(lon * 1e7),
            HEIGHT_M, 0, 0, 0, 0, 0, 0, 0, 0)
        return north_m, east_m

    def rtl(self) -> None:
        self.set_mode(RTL)
        self.wait(lambda: not self.armed(), "landed and disarmed after RTL")
        self.sleep(1.0)


def fly_builtin_legs(tlog: Path, speedup: float = 4.0, timeout_s: float = 120.0, vehicle=None) -> Path:
    """The recorded legs flight on the built-in vehicle in its ArduCopter personality (no GPS error:
    ArduPilot SITL's estimate is smooth); returns `tlog`, what the vehicle sent."""
    from sitl_scenarios.scenario import VehicleConfig

    vehicle = vehicle or VehicleConfig(gps_sigma_m=0.0, autopilot="ardupilot")
    return fly_builtin("legs", tlog, speedup=speedup, vehicle=vehicle, timeout_s=timeout_s,
                       primitives=ArduPilotFlight)


def main(argv: list[str] | None = None) -> int:
    return figures_main("sitl_scenarios.ardupilot_conformance", __doc__.splitlines()[0], {"legs": legs_figures}, argv)


if __name__ == "__main__":
    raise SystemExit(main())
