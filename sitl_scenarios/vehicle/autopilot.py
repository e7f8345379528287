"""The autopilot behind the built-in vehicle: PX4-like arming, flight modes, failsafes and guidance
of a multicopter (docs/design.md §9), PX4's `commander` and position controller in small.

No sockets and no clocks: :class:`Autopilot` advances when :meth:`Autopilot.step` is called with a
simulated time step, and answers commands with MAV_RESULT codes. The MAVLink side lives in
:mod:`sitl_scenarios.vehicle.simulator`. Positions are ENU metres from the origin (the vehicle
starts there); "up" is height above the origin, and the ground is flat at up = 0.

Missions and RTL: :mod:`~sitl_scenarios.vehicle.navigator`; the flight model:
:mod:`~sitl_scenarios.vehicle.kinematics`; GPS error and battery: :mod:`~sitl_scenarios.vehicle.sensors`.
Speeds and limits are PX4 parameters (MPC_XY_CRUISE, MPC_Z_V_AUTO_UP, ...), so a ground station
that sets them changes the flight.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from estimator.geodesy import Origin
from sitl_scenarios.scenario import VehicleConfig
from sitl_scenarios.vehicle import kinematics
from sitl_scenarios.vehicle.kinematics import GROUND_EPS_M, MAX_SUBSTEP_S
from sitl_scenarios.vehicle.mav import (
    ACCEPTED,
    CHARGE_CRITICAL,
    CHARGE_EMERGENCY,
    CHARGE_LOW,
    CHARGE_OK,
    DENIED,
    LANDED_IN_AIR,
    LANDED_LANDING,
    LANDED_ON_GROUND,
    LANDED_TAKEOFF,
    SEV_CRITICAL,
    SEV_INFO,
    SEV_WARNING,
)
from sitl_scenarios.vehicle.navigator import MissionItem, MissionState, Navigator, RtlState
from sitl_scenarios.vehicle.params import ParamStore, px4_params
from sitl_scenarios.vehicle.px4 import FlightMode
from sitl_scenarios.vehicle.sensors import (
    BATTERY_WARNINGS,
    DEAD_RECKONING_S,
    DeadReckoning,
    GpsError,
    VelocityError,
    charge_state,
    drained_pct,
)
from sitl_scenarios.vehicle.state import VehicleState

log = logging.getLogger(__name__)

#: from touchdown to "Landing detected" [s]: PX4 v1.18's land detector (SIH quadrotor) took 3.7 s
#: (gpsloss recording) to 7 s (legs recording, RTL) to report the vehicle on the ground
LAND_DETECT_S = 5.0
#: PX4's take-off (legs recording): the climb rate ramps up over MPC_TKO_RAMP_T (3 s), and the last
#: metres are approached at about 0.55 m/s per metre to go
TAKEOFF_RAMP_S = 3.0
TAKEOFF_APPROACH_PER_S = 0.55
#: COM_LOW_BAT_ACT values (PX4 parameter) that return at a critical / land at an emergency charge
_LOW_BAT_RTL = (1, 3)
_LOW_BAT_LAND = (2, 3)

class Autopilot(Navigator):
    """PX4-flavoured flight logic of a multicopter. Not thread-safe: the owner serializes calls.

    Commands return (MAV_RESULT, reason). :attr:`messages` collects (severity, text) for STATUSTEXT
    and :attr:`reached` the mission sequence numbers reached; the owner drains both.

    The class attributes are what another autopilot's personality changes (a subclass:
    :class:`sitl_scenarios.vehicle.ardupilot.ArduCopter`).
    """

    #: the mode the vehicle starts in, and the one it is put in once disarmed after landing in LAND
    #: or RTL (PX4: LOITER in both recordings; None: it stays in that mode)
    INITIAL_MODE: FlightMode = FlightMode.HOLD
    MODE_AFTER_LANDING: FlightMode | None = FlightMode.HOLD
    #: from touchdown to landed [s]
    LAND_DETECT_S: float = LAND_DETECT_S
    #: INT32 parameters travel byte-wise (PX4) or C-cast (ArduPilot)
    PARAM_BYTEWISE: bool = True

    def __init__(
        self,
        origin: Origin,
        vehicle: VehicleConfig,
        rng: np.random.Generator,
        gps_fix_delay_s: float = 2.0,
    ) -> None:
        self.origin = origin
        self.config = vehicle
        self.params = self._param_store(vehicle)
        self.gps_error = GpsError(vehicle.gps_sigma_m, vehicle.gps_tau_s, rng)
        self.vel_error = VelocityError(rng)
        self.dead_reckoning = DeadReckoning(rng)
        self.gps_error_at_loss: np.ndarray | None = None  # the GPS error frozen when the fix went
        self.position_failsafe = False  # blind land after the dead reckoning ran out
        self.t_s = 0.0
        self.pos = [0.0, 0.0, 0.0]
        self.vel = [0.0, 0.0, 0.0]
        self.acc = [0.0, 0.0, 0.0]  # last commanded acceleration, ENU [m/s²]
        self._setpoint: kinematics.Setpoint | None = None  # PX4's smoothed trajectory setpoint
        self._position_target: list[float] | None = None  # what the guidance flies to, ENU [m]
        self.yaw_rad = 0.0
        self.armed = False
        self.in_air = False
        self.landed_state = LANDED_ON_GROUND
        self.mode = self.INITIAL_MODE
        self.home = [0.0, 0.0, 0.0]
        self.home_set = False
        self.battery_pct = float(vehicle.battery_start_pct)
        self.gps_lost = False
        self.gps_fix_delay_s = gps_fix_delay_s
        self.messages: list[tuple[int, str]] = []
        self.reached: list[int] = []
        self.mission = MissionState()
        self.fence: list[MissionItem] = []
        self.rally: list[MissionItem] = []
        self._hold = [0.0, 0.0, 0.0]
        self._speed_override_mps: float | None = None  # DO_CHANGE_SPEED / reposition speed
        self._takeoff_up_m = 0.0
        self._land_xy: tuple[float, float] | None = None
        self._rtl = RtlState()
        self._landed_since_s: float | None = None  # armed and on the ground since
        self._landed_since_wall_s = 0.0  # the same instant on the wall clock
        self._touchdown_s: float | None = None  # on the ground, landing not yet detected, since
        self._takeoff_from_s: float | None = None  # a take-off's climb started
        self._has_flown = False  # left the ground since arming
        self._battery_level = CHARGE_OK
        self._offboard_pos: list[float] | None = None
        self._offboard_vel: list[float] | None = None
        self._offboard_wall_s: float | None = None
        self._wall_s = 0.0

    @staticmethod
    def _param_store(vehicle: VehicleConfig) -> ParamStore:
        return ParamStore(px4_params(vehicle.speed_mps, vehicle.climb_mps, vehicle.descent_mps, vehicle.accel_mps2))

    # --- derived state ------------------------------------------------------------------------
    @property
    def gps_ok(self) -> bool:
        """A 3-D fix and a valid global position estimate."""
        return not self.gps_lost and self.t_s >= self.gps_fix_delay_s

    @property
    def position_valid(self) -> bool:
        """A global position estimate the autopilot flies on: GPS, or dead reckoning for
        DEAD_RECKONING_S after the fix went (PX4's EKF2 keeps the position that long)."""
        if self.gps_ok:
            return True
        since = self.dead_reckoning.since_s
        return since is not None and self.t_s - since < DEAD_RECKONING_S

    @property
    def position_published(self) -> bool:
        """PX4 keeps publishing its (dead-reckoned, drifting) position after GPS went, even once
        invalid; nothing before the first fix."""
        return self.gps_ok or self.dead_reckoning.since_s is not None

    @property
    def charge_state(self) -> int:
        return charge_state(self.battery_pct, self.params)

    def enu_to_lla(self, pos_enu_m) -> tuple[float, float, float]:
        lat, lon, alt = self.origin.enu_to_lla(np.asarray(pos_enu_m, float))
        return float(lat), float(lon), float(alt)

    def lla_to_enu(self, lat_deg: float, lon_deg: float, alt_m: float) -> list[float]:
        return [float(v) for v in self.origin.lla_to_enu(lat_deg, lon_deg, alt_m)]

    def gps_position(self) -> np.ndarray:
        """What the GPS receiver reports, (3,) ENU [m]: true position + the GPS error (GPS_RAW_INT)."""
        return np.asarray(self.pos) + self.gps_error.sample(self.t_s)

    def estimated_position(self) -> np.ndarray:
        """What the vehicle's estimator believes, (3,) ENU [m] (GLOBAL_POSITION_INT): true position +
        the GPS error horizontally; the navigation height vertically, as PX4's EKF2 and ArduPilot's
        EKF3 take their height from the barometer by default (EKF2_HGT_REF, EK3_SRC1_POSZ), hold it
        and report it, so a reported height arrives at its setpoint. Without GPS, the GPS error it had
        then + the dead-reckoning drift since (sensors.DeadReckoning)."""
        if self.gps_error_at_loss is not None:
            return np.asarray(self.pos) + self.gps_error_at_loss + self.dead_reckoning.offset_m(self.t_s)
        return np.asarray(self.nav_pos, dtype=float)

    @property
    def nav_pos(self) -> list[float]:
        """Where the vehicle navigates from, (3,) ENU [m]: its estimate horizontally (PX4 and
        ArduPilot fly setpoints, hold and judge arrival on their EKF output, so the true track
        carries the GPS error), the true height (the flight model's ground contact and climb rates
        are held to the recorded flights). Without GPS the failsafe flies on what it has: the truth
        here (the blind landing of the gpsloss recording)."""
        if self.gps_error_at_loss is not None:
            return list(self.pos)
        e = self.gps_error.sample(self.t_s)
        return [self.pos[0] + float(e[0]), self.pos[1] + float(e[1]), self.pos[2]]

    def _to_true(self, target: list[float] | None) -> list[float] | None:
        """A navigation-frame target in the flight model's (true) frame: less the estimate's
        horizontal error."""
        if target is None:
            return None
        nav = self.nav_pos
        return [target[0] - (nav[0] - self.pos[0]), target[1] - (nav[1] - self.pos[1]), target[2]]

    def estimated_velocity(self) -> np.ndarray:
        """What the vehicle's estimator reports as velocity: true velocity + a small EKF error, (3,) ENU
        [m/s] (zero on the ground, where PX4 reports the vehicle at rest)."""
        if not self.in_air:
            return np.asarray(self.vel, dtype=float)
        return np.asarray(self.vel) + self.vel_error.sample(self.t_s) + self.dead_reckoning.velocity_mps(self.t_s)

    def snapshot(self, link_up: bool) -> VehicleState:
        lat, lon, alt = self.enu_to_lla(self.pos)
        hlat, hlon, halt = self.enu_to_lla(self.home)
        return VehicleState(
            t_s=self.t_s, pos_enu_m=np.array(self.pos), vel_enu_mps=np.array(self.vel),
            lat_deg=lat, lon_deg=lon, alt_m=alt, home_enu_m=np.array(self.home),
            home_lat_deg=hlat, home_lon_deg=hlon, home_alt_m=halt, home_set=self.home_set,
            armed=self.armed, in_air=self.in_air, landed_state=self.landed_state,
            mode=self.mode.value, battery_pct=self.battery_pct, gps_ok=self.gps_ok, link_up=link_up,
        )

    def trajectory_setpoint(self) -> tuple[list[float], list[float], list[float]] | None:
        """What the position controller tracks now (PX4's vehicle_local_position_setpoint), each (3,)
        ENU: position, velocity, acceleration of the smoothed horizontal trajectory
        (kinematics.Setpoint) with the target height and the vertical velocity and acceleration;
        None when it tracks no position (disarmed, on the ground, a velocity command)."""
        t, sp = self._position_target, self._setpoint
        if t is None or sp is None or not self.armed:
            return None
        nav = self.nav_pos  # the smoothed trajectory runs in the flight model's frame: report it in the estimate's
        ex, ey = nav[0] - self.pos[0], nav[1] - self.pos[1]
        return ([sp.pos[0] + ex, sp.pos[1] + ey, t[2]], [sp.vel[0], sp.vel[1], self.vel[2]],
                [sp.acc[0], sp.acc[1], self.acc[2]])

    def tilt_rad(self) -> tuple[float, float]:
        """(roll, pitch) [rad] a multicopter needs for its horizontal acceleration (no wind)."""
        return kinematics.tilt_rad(self.acc, self.yaw_rad)

    def _say(self, severity: int, text: str) -> None:
        log.info("vehicle: %s", text)
        self.messages.append((severity, text[:50]))

    def _cruise_mps(self) -> float:
        v = self._speed_override_mps or self.params["MPC_XY_CRUISE"]
        return max(0.1, min(v, self.params["MPC_XY_VEL_MAX"]))

    def _stopping_point(self) -> list[float]:
        """Where the vehicle comes to rest braking at MPC_ACC_HOR: p + v·|v| / (2a)."""
        return kinematics.stopping_point(self.nav_pos, self.vel, self.params["MPC_ACC_HOR"])


    def _need_position(self, what: str) -> tuple[int, str] | None:
        if not self.position_valid:
            reason = f"{what} denied: no global position"
            self._say(SEV_CRITICAL, reason)
            return DENIED, reason
        return None

    # --- commands -----------------------------------------------------------------------------
    def arm(self, force: bool = False) -> tuple[int, str]:
        if self.armed:
            return ACCEPTED, "already armed"
        if not force:
            if not self.gps_ok:
                return self._deny("Arming denied: no global position")
            if not self.home_set:
                return self._deny("Arming denied: home not set")
            if self.charge_state >= CHARGE_CRITICAL:
                return self._deny("Arming denied: battery critical")
            if self.mode is FlightMode.OFFBOARD and not self._offboard_fresh():
                return self._deny("Arming denied: no offboard setpoints")
            if self.mode is FlightMode.MISSION and not self.mission.items:
                return self._deny("Arming denied: no valid mission")
        self.armed = True
        self._has_flown = self.in_air
        self._landed_since_s = self.t_s if not self.in_air else None
        self._landed_since_wall_s = self._wall_s
        if not self.in_air:
            self.home = [self.nav_pos[0], self.nav_pos[1], 0.0]  # PX4 sets home where it arms (its estimate)
            self.home_set = True
        self._hold = self._stopping_point()
        if self.mode is FlightMode.MISSION:
            self._mission_begin()
        self._say(SEV_INFO, "Armed by external command")
        return ACCEPTED, "armed"

    def disarm(self, force: bool = False) -> tuple[int, str]:
        if not self.armed:
            return ACCEPTED, "already disarmed"
        if self.in_air and not force:
            return self._deny("Disarming denied: not landed")
        self._disarm("Disarmed by external command")
        return ACCEPTED, "disarmed"

    def _deny(self, text: str) -> tuple[int, str]:
        self._say(SEV_CRITICAL, text)
        return DENIED, text

    def _disarm(self, text: str) -> None:
        self.armed = False
        self.position_failsafe = False
        self._landed_since_s = None
        if self.in_air:  # forced disarm in the air: it falls; here it is put on the ground
            self.in_air = False
            self.pos[2] = 0.0
        self.vel = [0.0, 0.0, 0.0]
        self.acc = [0.0, 0.0, 0.0]
        self._setpoint = None
        self.landed_state = LANDED_ON_GROUND
        self._say(SEV_INFO, text)

    def takeoff(self, alt_amsl_m: float = math.nan) -> tuple[int, str]:
        """MAV_CMD_NAV_TAKEOFF: param7 AMSL altitude, NaN → home + MIS_TAKEOFF_ALT (PX4). Disarmed,
        PX4 selects takeoff mode with that height and climbs once armed (the legs recording)."""
        denied = self._need_position("Takeoff")
        if denied:
            return denied
        if math.isfinite(alt_amsl_m):
            up = alt_amsl_m - self.origin.alt_m
        else:
            up = self.home[2] + self.params["MIS_TAKEOFF_ALT"]
        if up < self.pos[2] + 1.0 and self.in_air:
            up = self.pos[2]
        self._takeoff_up_m = max(up, 1.0)
        self._hold = [self.nav_pos[0], self.nav_pos[1], self._takeoff_up_m]
        self._set_mode(FlightMode.TAKEOFF)
        if not self.armed:
            return ACCEPTED, f"takeoff mode selected, to {self._takeoff_up_m:.1f} m once armed"
        return ACCEPTED, f"takeoff to {self._takeoff_up_m:.1f} m"

    def land(self, lat_deg: float = math.nan, lon_deg: float = math.nan) -> tuple[int, str]:
        if math.isfinite(lat_deg) and math.isfinite(lon_deg) and (lat_deg, lon_deg) != (0.0, 0.0):
            e, n, _ = self.lla_to_enu(lat_deg, lon_deg, self.origin.alt_m)
            self._land_xy = (e, n)
        else:
            sp = self._stopping_point()
            self._land_xy = (sp[0], sp[1])
        self._set_mode(FlightMode.LAND)
        return ACCEPTED, "landing"

    def return_to_launch(self) -> tuple[int, str]:
        denied = self._need_position("RTL")
        if denied:
            return denied
        if not self.home_set:
            return self._deny("RTL denied: no home position")
        self._set_mode(FlightMode.RTL)
        return ACCEPTED, "returning"

    def reposition(
        self, lat_deg: float, lon_deg: float, alt_amsl_m: float, speed_mps: float = -1.0
    ) -> tuple[int, str]:
        """MAV_CMD_DO_REPOSITION (MAVSDK goto_location): fly there in Hold. NaN keeps a coordinate."""
        if not self.armed or not self.in_air:
            return self._deny("Reposition denied: not flying")
        denied = self._need_position("Reposition")
        if denied:
            return denied
        target = list(self._hold if self.mode is FlightMode.HOLD else self._stopping_point())
        if math.isfinite(lat_deg) and math.isfinite(lon_deg):
            e, n, _ = self.lla_to_enu(lat_deg, lon_deg, self.origin.alt_m)
            target[0], target[1] = e, n
        if math.isfinite(alt_amsl_m):
            target[2] = max(alt_amsl_m - self.origin.alt_m, 0.0)
        if math.isfinite(speed_mps) and speed_mps > 0:
            self._speed_override_mps = speed_mps
        self._set_mode(FlightMode.HOLD, keep_hold=True)
        self._hold = target
        return ACCEPTED, "repositioning"

    def change_speed(self, speed_mps: float) -> tuple[int, str]:
        """MAV_CMD_DO_CHANGE_SPEED: ground speed for the current flight; ≤ 0 → cruise default."""
        if not math.isfinite(speed_mps):
            return DENIED, "speed must be finite"
        self._speed_override_mps = speed_mps if speed_mps > 0 else None
        return ACCEPTED, "speed changed"

    def set_home(self, use_current: bool, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> tuple[int, str]:
        if use_current:
            if not self.gps_ok:
                return self._deny("Set home denied: no global position")
            self.home = list(self.nav_pos)
        else:
            if not all(math.isfinite(v) for v in (lat_deg, lon_deg, alt_amsl_m)):
                return DENIED, "home coordinates must be finite"
            self.home = self.lla_to_enu(lat_deg, lon_deg, alt_amsl_m)
        self.home_set = True
        return ACCEPTED, "home set"

    def set_mode(self, mode: FlightMode) -> tuple[int, str]:
        """MAV_CMD_DO_SET_MODE with a PX4 custom mode the simulator flies."""
        if mode is self.mode:
            return ACCEPTED, "mode unchanged"
        if mode in (FlightMode.MISSION, FlightMode.RTL, FlightMode.TAKEOFF, FlightMode.OFFBOARD):
            denied = self._need_position(f"Switching to {mode.value}")
            if denied:
                return denied
        if mode is FlightMode.RTL:
            return self.return_to_launch()
        if mode is FlightMode.LAND:
            return self.land()
        if mode is FlightMode.TAKEOFF:
            if self.armed:
                return self.takeoff()
            self._takeoff_up_m = self.home[2] + self.params["MIS_TAKEOFF_ALT"]
            self._hold = [self.nav_pos[0], self.nav_pos[1], self._takeoff_up_m]
            self._set_mode(FlightMode.TAKEOFF)
            return ACCEPTED, "takeoff mode selected"
        if mode is FlightMode.OFFBOARD and not self._offboard_fresh():
            return self._deny("Switching to offboard denied: no setpoints")
        if mode is FlightMode.MISSION:
            if not self.mission.items:
                return self._deny("Switching to mission denied: no mission")
            self._set_mode(FlightMode.MISSION)
            if self.armed:
                self._mission_begin()
            return ACCEPTED, "mission"
        self._set_mode(mode)
        return ACCEPTED, mode.value


    def _set_mode(self, mode: FlightMode, keep_hold: bool = False) -> None:
        if mode is not self.mode:
            log.debug("vehicle mode %s -> %s", self.mode.value, mode.value)
            self._setpoint = None  # a new flight task starts its trajectory at the vehicle's state
        if mode is FlightMode.RTL and self.mode is not FlightMode.RTL:
            self._rtl = RtlState(return_up_m=self.rtl_return_up_m())
            if not self.in_air:
                self._rtl.phase = "land"
            else:
                above = self._rtl.return_up_m - self.home[2]
                self._say(SEV_INFO, f"RTL: start return at {self.origin.alt_m + self._rtl.return_up_m:.0f} m "
                                    f"({above:.0f} m above destination)")
        if mode in (FlightMode.HOLD, FlightMode.POSCTL) and not keep_hold:
            self._hold = self._stopping_point()
        if mode is not FlightMode.HOLD and self.mode is FlightMode.HOLD:
            self._speed_override_mps = None if mode is not FlightMode.MISSION else self._speed_override_mps
        self.mode = mode

    # --- offboard -----------------------------------------------------------------------------
    def offboard_setpoint(
        self, pos_enu_m: list[float] | None, vel_enu_mps: list[float] | None, wall_s: float
    ) -> None:
        """A SET_POSITION_TARGET_*: position (ENU) or velocity (ENU) setpoint; wall_s: receive time."""
        self._offboard_pos = pos_enu_m
        self._offboard_vel = vel_enu_mps if pos_enu_m is None else None
        self._offboard_wall_s = wall_s

    def _offboard_fresh(self) -> bool:
        # setpoints arrive in wall time; COM_OF_LOSS_T is applied to wall time (see README)
        return (
            self._offboard_wall_s is not None
            and self._wall_s - self._offboard_wall_s <= self.params["COM_OF_LOSS_T"]
        )

    # --- faults -------------------------------------------------------------------------------
    def set_gps_lost(self, lost: bool) -> None:
        """The receiver loses (regains) its fix. Like PX4 (gpsloss recording): the EKF dead-reckons
        for DEAD_RECKONING_S, the vehicle flying on as commanded while its position drifts; then the
        position is invalid and, in the air, the failsafe lands blind where it is
        (:meth:`_position_failsafe`). The position is published all along."""
        if lost == self.gps_lost:
            return
        self.gps_lost = lost
        if lost:
            if self.t_s >= self.gps_fix_delay_s:
                self.gps_error_at_loss = np.array(self.gps_error.sample(self.t_s))
                self.dead_reckoning.start(self.t_s)
            self._say(SEV_CRITICAL, "GPS lost: dead reckoning")
        else:
            self.gps_error_at_loss = None
            self.dead_reckoning.stop()
            self._say(SEV_INFO, "GPS fix regained")

    def _position_failsafe(self) -> None:
        """PX4's mc_pos_control without a valid position: "invalid setpoints", "Failsafe: blind
        land": descend at MPC_LAND_SPEED where it is, no horizontal position control."""
        if self.position_failsafe or self.position_valid or not (self.in_air and self.armed):
            return
        self.position_failsafe = True
        self._say(SEV_WARNING, "invalid setpoints")
        self._say(SEV_CRITICAL, "Failsafe: blind land")
        sp = self._stopping_point()
        self._land_xy = (sp[0], sp[1])
        self._set_mode(FlightMode.LAND)

    def set_battery_pct(self, pct: float) -> None:
        self.battery_pct = min(max(float(pct), 0.0), 100.0)

    # --- simulation ---------------------------------------------------------------------------
    def step(self, dt_s: float, wall_s: float) -> None:
        """Advance the simulation by dt_s simulated seconds (sub-stepped); wall_s: wall clock now."""
        self._wall_s = wall_s
        while dt_s > 1e-9:
            h = min(dt_s, MAX_SUBSTEP_S)
            self._substep(h)
            dt_s -= h

    def _substep(self, dt: float) -> None:
        self.t_s += dt
        if not self.home_set and self._home_ready():
            self.home = [self.nav_pos[0], self.nav_pos[1], 0.0]
            self.home_set = True
            self._say(SEV_INFO, "Home position set")
        self._battery(dt)
        if not self.armed:
            return
        self._position_failsafe()
        target, v_h, vel_cmd, v_dn = self._guidance()
        self._move(dt, target, v_h, vel_cmd, v_dn)
        self._land_detector()

    def _home_ready(self) -> bool:
        """PX4 sets home at its first fix."""
        return self.gps_ok

    def _battery(self, dt: float) -> None:
        self.battery_pct = drained_pct(self.battery_pct, dt, self.config.battery_capacity_s, self.armed, self.in_air)
        level = self.charge_state
        if level > self._battery_level:
            self._say(SEV_CRITICAL if level > CHARGE_LOW else SEV_WARNING, BATTERY_WARNINGS[level])
            act = int(self.params["COM_LOW_BAT_ACT"])
            if self.in_air and self.armed:
                if level == CHARGE_EMERGENCY and act in _LOW_BAT_LAND and self.mode is not FlightMode.LAND:
                    self.land()
                elif level >= CHARGE_CRITICAL and act in _LOW_BAT_RTL and self.mode not in (
                    FlightMode.RTL, FlightMode.LAND
                ):
                    self.return_to_launch()
        self._battery_level = level

    def _land_speed(self) -> float:
        """Descent rate when landing: MPC_Z_V_AUTO_DN above LAND_ALT1, MPC_LAND_SPEED below ALT2."""
        h = self.pos[2] - self.home[2]
        v_fast, v_slow = self.params["MPC_Z_V_AUTO_DN"], self.params["MPC_LAND_SPEED"]
        a1, a2 = self.params["MPC_LAND_ALT1"], self.params["MPC_LAND_ALT2"]
        if h >= a1:
            return v_fast
        if h <= a2 or a1 <= a2:
            return v_slow
        return v_slow + (v_fast - v_slow) * (h - a2) / (a1 - a2)

    def _guidance(self) -> tuple[list[float] | None, float, list[float] | None, float]:
        """(position target ENU or None, horizontal speed, velocity command or None, descent rate)."""
        v_dn = self.params["MPC_Z_V_AUTO_DN"]
        mode = self.mode
        if mode is FlightMode.OFFBOARD:
            if not self._offboard_fresh():
                self._say(SEV_CRITICAL, "Failsafe: offboard setpoints lost, holding")
                self._set_mode(FlightMode.HOLD)
                return self._hold, self._cruise_mps(), None, v_dn
            if self._offboard_pos is not None:
                return list(self._offboard_pos), self.params["MPC_XY_VEL_MAX"], None, v_dn
            return None, self.params["MPC_XY_VEL_MAX"], list(self._offboard_vel or [0, 0, 0]), v_dn
        if mode is FlightMode.TAKEOFF:
            target = [self._hold[0], self._hold[1], self._takeoff_up_m]
            if self.in_air and abs(self.pos[2] - self._takeoff_up_m) < 0.1:
                self._say(SEV_INFO, "Takeoff finished, holding")
                self._set_mode(FlightMode.HOLD, keep_hold=True)
                self._hold = target
            return target, self._cruise_mps(), None, v_dn
        if mode is FlightMode.LAND:
            xy = self._land_xy or (self.nav_pos[0], self.nav_pos[1])
            v_land = self.params["MPC_LAND_SPEED"] if self.position_failsafe else self._land_speed()
            return [xy[0], xy[1], -1.0], self._cruise_mps(), None, v_land
        if mode is FlightMode.RTL:
            return self._rtl_step()
        if mode is FlightMode.MISSION:
            if not self.mission.started:
                self._mission_begin()
            target, v = self._mission_step()
            if target is None:  # switched to RTL / LAND
                return self._guidance()
            return target, v, None, v_dn
        return self._hold, self._cruise_mps(), None, v_dn  # HOLD, POSCTL

    def _takeoff_climb_mps(self) -> float:
        """PX4's take-off climb (legs recording): ramped up over TAKEOFF_RAMP_S from leaving the
        ground, MPC_TKO_SPEED up to MPC_LAND_ALT1 above home, MPC_Z_V_AUTO_UP above, and from there
        an approach slowing as v = TAKEOFF_APPROACH_PER_S · (height to go)."""
        p = self.params
        h = self.pos[2] - self.home[2]
        if not self.in_air or self._takeoff_from_s is None:
            self._takeoff_from_s = self.t_s
        v = p["MPC_TKO_SPEED"] if h < p["MPC_LAND_ALT1"] else p["MPC_Z_V_AUTO_UP"]
        v *= min(1.0, max(self.t_s - self._takeoff_from_s, 0.05) / TAKEOFF_RAMP_S)
        return max(0.1, min(v, TAKEOFF_APPROACH_PER_S * (self._takeoff_up_m - self.pos[2])))

    def _move(
        self, dt: float, target: list[float] | None, v_h: float, vel_cmd: list[float] | None, v_dn: float
    ) -> None:
        p = self.params
        v_up = self._takeoff_climb_mps() if self.mode is FlightMode.TAKEOFF else p["MPC_Z_V_AUTO_UP"]
        self._position_target = None if target is None else list(target)
        target = self._to_true(target)
        trk = kinematics.Tracking(p["MPC_JERK_AUTO"], p["MPC_XY_ERR_MAX"], p["MPC_XY_P"], p["MPC_XY_VEL_P_ACC"],
                                  vel_int=p["MPC_XY_VEL_I_ACC"], vel_d=p["MPC_XY_VEL_D_ACC"],
                                  tilt_max_rad=math.radians(p["MPC_TILTMAX_AIR"]))
        self.acc, self.yaw_rad, self._setpoint = kinematics.move(
            self.pos, self.vel, self.yaw_rad, dt, target, v_h, vel_cmd, v_up, v_dn,
            p["MPC_ACC_HOR"], p["MPC_ACC_UP_MAX"], p["MPC_ACC_DOWN_MAX"], self.in_air,
            self.acc, self._setpoint, trk)

    def _land_detector(self) -> None:
        descending_mode = self.mode is FlightMode.LAND or (
            self.mode is FlightMode.RTL and self._rtl.phase == "land"
        )
        if self.in_air:
            on_ground = self.pos[2] <= GROUND_EPS_M and self.vel[2] >= -1e-3
            if not on_ground:
                self._touchdown_s = None
            elif self._touchdown_s is None:
                self._touchdown_s = self.t_s
            if on_ground and self.t_s - self._touchdown_s >= self.LAND_DETECT_S:
                self._touchdown_s = None
                self.in_air = False
                self.vel = [0.0, 0.0, 0.0]
                self.acc = [0.0, 0.0, 0.0]
                self._setpoint = None
                self.landed_state = LANDED_ON_GROUND
                self._landed_since_s = self.t_s
                self._say(SEV_INFO, "Landing detected")
            elif descending_mode:
                self.landed_state = LANDED_LANDING
            elif self.mode is FlightMode.TAKEOFF or (self.mode is FlightMode.MISSION and self.mission.takeoff_first):
                self.landed_state = LANDED_TAKEOFF
            else:
                self.landed_state = LANDED_IN_AIR
        else:
            if self.pos[2] > GROUND_EPS_M:
                self.in_air = True
                self._has_flown = True
                self._landed_since_s = None
                self.landed_state = LANDED_TAKEOFF
                return
            if self._landed_since_s is None:
                self._landed_since_s, self._landed_since_wall_s = self.t_s, self._wall_s
            wait = self.params["COM_DISARM_LAND"] if self._has_flown else self.params["COM_DISARM_PRFLT"]
            # the pre-flight disarm waits for the ground station's take-off command, whose round
            # trips take wall time: COM_DISARM_PRFLT must also pass on the wall clock (at x200 its
            # 10 simulated s are 0.05 wall s, less than one command's round trip; the vehicle
            # disarmed before the take-off came). Never sooner in wall time than at x1.
            wall_ok = self._has_flown or self._wall_s - self._landed_since_wall_s >= wait
            if wait >= 0 and self.t_s - self._landed_since_s >= wait and wall_ok:
                after = self.MODE_AFTER_LANDING
                if self._has_flown and after is not None and self.mode in (FlightMode.LAND, FlightMode.RTL):
                    self._set_mode(after)
                self._disarm("Disarmed after landing" if self._has_flown else "Disarmed: no takeoff")


__all__ = ["Autopilot", "VehicleState"]
