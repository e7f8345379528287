"""The autopilot behind the built-in vehicle: PX4-like flight modes, a kinematic multicopter,
GPS errors and a battery (DESIGN.md §9).

No sockets and no clocks: :class:`Autopilot` advances when :meth:`Autopilot.step` is called with a
simulated time step, and answers commands with MAV_RESULT codes. The MAVLink side lives in
`sitl_scenarios/vehicle.py`. Positions are ENU metres from the origin (the vehicle starts there);
"up" is height above the origin, and the ground is flat at up = 0.

Flight model (per axis group, time step dt):

    v_des = dir · min(v_max, sqrt(2·a·d), d/dt)      horizontal, d = distance to target
    v    += clip(v_des − v, |Δv| ≤ a·dt)               bounded acceleration
    p    += v·dt

the same vertically with the climb / descent limits. Speeds and limits are PX4 parameters
(MPC_XY_CRUISE, MPC_Z_V_AUTO_UP, ...), so a ground station that sets them changes the flight.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from estimator.geodesy import Origin
from sitl_scenarios.mavlink_px4 import FlightMode, ParamStore, px4_params
from sitl_scenarios.scenario import VehicleConfig

log = logging.getLogger(__name__)

# MAV_RESULT
ACCEPTED = 0
TEMPORARILY_REJECTED = 1
DENIED = 2
UNSUPPORTED = 3
FAILED = 4

# MAV_SEVERITY
SEV_CRITICAL = 2
SEV_WARNING = 4
SEV_NOTICE = 5
SEV_INFO = 6

# MAV_LANDED_STATE
LANDED_ON_GROUND = 1
LANDED_IN_AIR = 2
LANDED_TAKEOFF = 3
LANDED_LANDING = 4

# MAV_BATTERY_CHARGE_STATE
CHARGE_OK = 1
CHARGE_LOW = 2
CHARGE_CRITICAL = 3
CHARGE_EMERGENCY = 4

# MAV_CMD used in missions
CMD_NAV_WAYPOINT = 16
CMD_NAV_LOITER_UNLIM = 17
CMD_NAV_LOITER_TIME = 19
CMD_NAV_RETURN_TO_LAUNCH = 20
CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_NAV_DELAY = 93
CMD_DO_CHANGE_SPEED = 178

# MAV_FRAME of mission items and position targets
FRAME_GLOBAL = 0
FRAME_LOCAL_NED = 1
FRAME_MISSION = 2
FRAME_GLOBAL_RELATIVE_ALT = 3
FRAME_GLOBAL_INT = 5
FRAME_GLOBAL_RELATIVE_ALT_INT = 6
FRAME_GLOBAL_TERRAIN_ALT = 10
FRAME_GLOBAL_TERRAIN_ALT_INT = 11

# MISSION_CURRENT.mission_state (MISSION_STATE)
MISSION_STATE_NO_MISSION = 1
MISSION_STATE_NOT_STARTED = 2
MISSION_STATE_ACTIVE = 3
MISSION_STATE_PAUSED = 4
MISSION_STATE_COMPLETE = 5

_NAV_COMMANDS = {
    CMD_NAV_WAYPOINT, CMD_NAV_LOITER_UNLIM, CMD_NAV_LOITER_TIME, CMD_NAV_RETURN_TO_LAUNCH,
    CMD_NAV_LAND, CMD_NAV_TAKEOFF, CMD_NAV_DELAY,
}

MAX_SUBSTEP_S = 0.05
GROUND_EPS_M = 0.05


def mission_command_supported(command: int) -> bool:
    """Whether a mission item's command is flown (NAV) or accepted and skipped (DO, camera, gimbal)."""
    return (
        command in _NAV_COMMANDS
        or 176 <= command <= 252  # MAV_CMD_DO_*: accepted, only DO_CHANGE_SPEED has an effect
        or 1000 <= command <= 1001  # gimbal manager: no gimbal, skipped
        or 2000 <= command <= 2600  # camera / video: no camera, skipped
    )


@dataclass
class MissionItem:
    """A stored mission item, with the fields of MISSION_ITEM_INT (x, y: degE7 in global frames)."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = 0


@dataclass(frozen=True)
class VehicleState:
    """A consistent snapshot of the simulated vehicle's true state.

    t_s: simulated seconds since boot; pos_enu_m, vel_enu_mps: (3,) true position / velocity in the
    origin's ENU frame; lat_deg, lon_deg, alt_m: the same position geodetic (AMSL);
    home_enu_m: (3,) home; battery_pct: 0..100; mode: MAVSDK-style flight-mode name.
    """

    t_s: float
    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    lat_deg: float
    lon_deg: float
    alt_m: float
    home_enu_m: np.ndarray
    home_lat_deg: float
    home_lon_deg: float
    home_alt_m: float
    home_set: bool
    armed: bool
    in_air: bool
    landed_state: int
    mode: str
    battery_pct: float
    gps_ok: bool
    link_up: bool


class GpsError:
    """Position error of the vehicle's GPS/EKF solution, isotropic in 3-D, σ per axis.

    tau_s = 0: independent per fix (the estimator's model, DESIGN.md §5). tau_s > 0: first-order
    Gauss-Markov, e_k = φ·e_{k-1} + sqrt(1 − φ²)·σ·w, φ = exp(−Δt/τ), stationary σ per axis.
    """

    def __init__(self, sigma_m: float, tau_s: float, rng: np.random.Generator) -> None:
        self.sigma_m = float(sigma_m)
        self.tau_s = float(tau_s)
        self._rng = rng
        self._e = rng.normal(0.0, self.sigma_m, 3) if self.sigma_m > 0 else np.zeros(3)
        self._t_s: float | None = None

    def sample(self, t_s: float) -> np.ndarray:
        """Error (3,) [m] ENU at simulated time t_s; the same value for the same t_s."""
        if self._t_s is not None and t_s == self._t_s:
            return self._e
        if self.sigma_m <= 0:
            self._e = np.zeros(3)
        elif self.tau_s <= 0 or self._t_s is None:
            self._e = self._rng.normal(0.0, self.sigma_m, 3)
        else:
            # e_k = φ e_{k-1} + sqrt(1 − φ²) σ w
            phi = math.exp(-max(t_s - self._t_s, 0.0) / self.tau_s)
            self._e = phi * self._e + math.sqrt(1.0 - phi * phi) * self.sigma_m * self._rng.normal(size=3)
        self._t_s = t_s
        return self._e


@dataclass
class _RtlState:
    phase: str = "climb"  # climb -> return -> descend -> loiter -> land
    return_up_m: float = 0.0
    loiter_until_s: float = 0.0


@dataclass
class _MissionState:
    items: list[MissionItem] = field(default_factory=list)
    current: int = 0
    started: bool = False
    finished: bool = False
    hold_until_s: float | None = None
    takeoff_first: bool = False


class Autopilot:
    """PX4-flavoured flight logic of a multicopter. Not thread-safe: the owner serializes calls.

    Commands return (MAV_RESULT, reason). :attr:`messages` collects (severity, text) for STATUSTEXT
    and :attr:`reached` the mission sequence numbers reached; the owner drains both.
    """

    def __init__(
        self,
        origin: Origin,
        vehicle: VehicleConfig,
        rng: np.random.Generator,
        gps_fix_delay_s: float = 2.0,
    ) -> None:
        self.origin = origin
        self.config = vehicle
        self.params = ParamStore(
            px4_params(vehicle.speed_mps, vehicle.climb_mps, vehicle.descent_mps, vehicle.accel_mps2)
        )
        self.gps_error = GpsError(vehicle.gps_sigma_m, vehicle.gps_tau_s, rng)
        self.t_s = 0.0
        self.pos = [0.0, 0.0, 0.0]
        self.vel = [0.0, 0.0, 0.0]
        self.acc = [0.0, 0.0, 0.0]  # last commanded acceleration, ENU [m/s²]
        self.yaw_rad = 0.0
        self.armed = False
        self.in_air = False
        self.landed_state = LANDED_ON_GROUND
        self.mode = FlightMode.HOLD
        self.home = [0.0, 0.0, 0.0]
        self.home_set = False
        self.battery_pct = float(vehicle.battery_start_pct)
        self.gps_lost = False
        self.gps_fix_delay_s = gps_fix_delay_s
        self.messages: list[tuple[int, str]] = []
        self.reached: list[int] = []
        self.mission = _MissionState()
        self.fence: list[MissionItem] = []
        self.rally: list[MissionItem] = []
        self._hold = [0.0, 0.0, 0.0]
        self._speed_override_mps: float | None = None  # DO_CHANGE_SPEED / reposition speed
        self._takeoff_up_m = 0.0
        self._land_xy: tuple[float, float] | None = None
        self._rtl = _RtlState()
        self._landed_since_s: float | None = None  # armed and on the ground since
        self._has_flown = False  # left the ground since arming
        self._battery_level = CHARGE_OK
        self._offboard_pos: list[float] | None = None
        self._offboard_vel: list[float] | None = None
        self._offboard_wall_s: float | None = None
        self._wall_s = 0.0

    # --- derived state ------------------------------------------------------------------------
    @property
    def gps_ok(self) -> bool:
        """A 3-D fix and a valid global position estimate."""
        return not self.gps_lost and self.t_s >= self.gps_fix_delay_s

    @property
    def charge_state(self) -> int:
        frac = self.battery_pct / 100.0
        if frac <= self.params["BAT_EMERGEN_THR"]:
            return CHARGE_EMERGENCY
        if frac <= self.params["BAT_CRIT_THR"]:
            return CHARGE_CRITICAL
        if frac <= self.params["BAT_LOW_THR"]:
            return CHARGE_LOW
        return CHARGE_OK

    @property
    def mission_state(self) -> int:
        m = self.mission
        if not m.items:
            return MISSION_STATE_NO_MISSION
        if m.finished:
            return MISSION_STATE_COMPLETE
        if not m.started:
            return MISSION_STATE_NOT_STARTED
        return MISSION_STATE_ACTIVE if self.mode is FlightMode.MISSION else MISSION_STATE_PAUSED

    def enu_to_lla(self, pos_enu_m) -> tuple[float, float, float]:
        lat, lon, alt = self.origin.enu_to_lla(np.asarray(pos_enu_m, float))
        return float(lat), float(lon), float(alt)

    def lla_to_enu(self, lat_deg: float, lon_deg: float, alt_m: float) -> list[float]:
        return [float(v) for v in self.origin.lla_to_enu(lat_deg, lon_deg, alt_m)]

    def estimated_position(self) -> np.ndarray:
        """What the vehicle's estimator believes: true position + GPS error, (3,) ENU [m]."""
        return np.asarray(self.pos) + self.gps_error.sample(self.t_s)

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

    def tilt_rad(self) -> tuple[float, float]:
        """(roll, pitch) [rad] a multicopter needs for its horizontal acceleration (no wind):
        pitch = −atan(a_forward / g), roll = atan(a_right / g), forward along the heading."""
        g = 9.81
        s, c = math.sin(self.yaw_rad), math.cos(self.yaw_rad)
        a_fwd = self.acc[1] * c + self.acc[0] * s
        a_right = -self.acc[1] * s + self.acc[0] * c
        return math.atan2(a_right, g), -math.atan2(a_fwd, g)

    def _say(self, severity: int, text: str) -> None:
        log.info("vehicle: %s", text)
        self.messages.append((severity, text[:50]))

    def _cruise_mps(self) -> float:
        v = self._speed_override_mps or self.params["MPC_XY_CRUISE"]
        return max(0.1, min(v, self.params["MPC_XY_VEL_MAX"]))

    def _stopping_point(self) -> list[float]:
        """Where the vehicle comes to rest braking at MPC_ACC_HOR: p + v·|v| / (2a)."""
        a = self.params["MPC_ACC_HOR"]
        vh = math.hypot(self.vel[0], self.vel[1])
        k = vh / (2 * a) if a > 0 else 0.0
        return [self.pos[0] + self.vel[0] * k, self.pos[1] + self.vel[1] * k, max(self.pos[2], 0.0)]

    def _need_position(self, what: str) -> tuple[int, str] | None:
        if not self.gps_ok:
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
        if not self.in_air:
            self.home = [self.pos[0], self.pos[1], 0.0]  # PX4 sets home where it arms
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
        self._landed_since_s = None
        if self.in_air:  # forced disarm in the air: it falls; here it is put on the ground
            self.in_air = False
            self.pos[2] = 0.0
        self.vel = [0.0, 0.0, 0.0]
        self.landed_state = LANDED_ON_GROUND
        self._say(SEV_INFO, text)

    def takeoff(self, alt_amsl_m: float = math.nan) -> tuple[int, str]:
        """MAV_CMD_NAV_TAKEOFF: param7 AMSL altitude, NaN → home + MIS_TAKEOFF_ALT (PX4)."""
        if not self.armed:
            return self._deny("Takeoff denied: disarmed")
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
        self._hold = [self.pos[0], self.pos[1], self._takeoff_up_m]
        self._set_mode(FlightMode.TAKEOFF)
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
            self.home = [self.pos[0], self.pos[1], self.pos[2]]
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
            self._hold = [self.pos[0], self.pos[1], self._takeoff_up_m]
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

    def rtl_return_up_m(self) -> float:
        """Height (ENU up) an RTL started now returns at, PX4's rule (navigator RTL, RTL_TYPE 0):

            d ≤ NAV_ACC_RAD:            h = 2 d
            otherwise:                  h = RTL_RETURN_ALT, or min(RTL_RETURN_ALT, d / tan(RTL_CONE_ANG))
                                        when 0 < RTL_CONE_ANG and d ≤ RTL_MIN_DIST; at least 2 NAV_ACC_RAD
            return height:              max(home + h, current height)   (RTL never descends first)

        d: horizontal distance to home [m]; heights above home [m]."""
        p, home = self.params, self.home
        d = math.hypot(self.pos[0] - home[0], self.pos[1] - home[1])
        acc = p["NAV_ACC_RAD"]
        if d <= acc:
            h = 2.0 * d
        else:
            h = p["RTL_RETURN_ALT"]
            cone = p["RTL_CONE_ANG"]
            if cone > 0 and d <= p["RTL_MIN_DIST"]:
                h = min(h, d / math.tan(math.radians(min(max(cone, 1.0), 89.0))))
            h = max(h, 2.0 * acc)
        return max(home[2] + h, self.pos[2])

    def _set_mode(self, mode: FlightMode, keep_hold: bool = False) -> None:
        if mode is not self.mode:
            log.debug("vehicle mode %s -> %s", self.mode.value, mode.value)
        if mode is FlightMode.RTL and self.mode is not FlightMode.RTL:
            self._rtl = _RtlState(return_up_m=self.rtl_return_up_m())
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

    # --- missions -----------------------------------------------------------------------------
    def set_mission(self, mission_type: int, items: list[MissionItem]) -> None:
        """Replace the stored plan of a type (0 mission, 1 fence, 2 rally)."""
        if mission_type == 1:
            self.fence = items
        elif mission_type == 2:
            self.rally = items
        else:
            self.mission = _MissionState(items=items)
            if self.mode is FlightMode.MISSION and not items:
                self._set_mode(FlightMode.HOLD)

    def mission_items(self, mission_type: int) -> list[MissionItem]:
        return {1: self.fence, 2: self.rally}.get(mission_type, self.mission.items)

    def set_mission_current(self, seq: int) -> bool:
        if not 0 <= seq < len(self.mission.items):
            return False
        self.mission.current = seq
        self.mission.finished = False
        self.mission.hold_until_s = None
        return True

    def mission_start(self, first: int = 0) -> tuple[int, str]:
        if not self.mission.items:
            return self._deny("Mission start denied: no mission")
        if first > 0 and not self.set_mission_current(first):
            return DENIED, f"no mission item {first}"
        return self.set_mode(FlightMode.MISSION) if self.mode is not FlightMode.MISSION else (ACCEPTED, "ok")

    def _mission_begin(self) -> None:
        m = self.mission
        if m.finished:
            m.current, m.finished = 0, False
        m.started = True
        m.hold_until_s = None
        first = m.items[m.current] if m.current < len(m.items) else None
        m.takeoff_first = not self.in_air and (first is None or first.command != CMD_NAV_TAKEOFF)
        if m.takeoff_first:
            up = self.params["MIS_TAKEOFF_ALT"]
            for it in m.items[m.current:]:
                if it.command in (CMD_NAV_WAYPOINT, CMD_NAV_LOITER_TIME, CMD_NAV_LOITER_UNLIM):
                    up = max(up, self._item_up(it))
                    break
            self._takeoff_up_m = up

    def _item_up(self, it: MissionItem) -> float:
        if it.frame in (FRAME_GLOBAL, FRAME_GLOBAL_INT):
            return it.z - self.origin.alt_m
        return self.home[2] + it.z  # relative (and terrain: flat ground at home height)

    def _item_target(self, it: MissionItem) -> list[float]:
        if it.x == 0 and it.y == 0:
            e, n = self.pos[0], self.pos[1]
        else:
            e, n, _ = self.lla_to_enu(it.x * 1e-7, it.y * 1e-7, self.origin.alt_m)
        up = self._item_up(it) if math.isfinite(it.z) else self.pos[2]
        return [e, n, max(up, 0.0)]

    def _mission_step(self) -> tuple[list[float] | None, float]:
        """Target and horizontal speed for the current mission item; advances the mission."""
        m = self.mission
        cruise = self._cruise_mps()
        if m.takeoff_first:
            target = [self.pos[0], self.pos[1], self._takeoff_up_m]
            if abs(self.pos[2] - self._takeoff_up_m) < self.params["NAV_MC_ALT_RAD"]:
                m.takeoff_first = False
            return target, cruise
        while m.current < len(m.items):
            it = m.items[m.current]
            if it.command == CMD_DO_CHANGE_SPEED:
                if it.param2 > 0:
                    self._speed_override_mps = it.param2
                self._advance()
                continue
            if it.command not in _NAV_COMMANDS:
                self._advance()
                continue
            if it.command == CMD_NAV_RETURN_TO_LAUNCH:
                self._advance()
                m.finished = True
                self._set_mode(FlightMode.RTL)
                return None, cruise
            if it.command == CMD_NAV_LAND:
                target = self._item_target(it)
                self._land_xy = (target[0], target[1])
                self._advance()
                m.finished = True
                self._set_mode(FlightMode.LAND)
                return None, cruise
            if it.command == CMD_NAV_DELAY:
                target = list(self._hold)
                if m.hold_until_s is None:
                    m.hold_until_s = self.t_s + max(it.param1, 0.0)
                if self.t_s >= m.hold_until_s:
                    self._advance()
                    continue
                return target, cruise
            target = self._item_target(it)
            if it.command == CMD_NAV_TAKEOFF:
                target = [self.pos[0], self.pos[1], max(target[2], self.pos[2])] if not self.in_air else target
            dh = math.hypot(target[0] - self.pos[0], target[1] - self.pos[1])
            acc = it.param2 if it.command == CMD_NAV_WAYPOINT and it.param2 > 0 else self.params["NAV_ACC_RAD"]
            arrived = dh <= acc and abs(target[2] - self.pos[2]) <= self.params["NAV_MC_ALT_RAD"]
            if it.command == CMD_NAV_TAKEOFF:
                arrived = abs(target[2] - self.pos[2]) <= self.params["NAV_MC_ALT_RAD"]
            if not arrived and m.hold_until_s is None:
                return target, cruise
            if m.hold_until_s is None:
                if it.command == CMD_NAV_LOITER_UNLIM:
                    self._hold = target
                    return target, cruise
                wait = it.param1 if it.command in (CMD_NAV_WAYPOINT, CMD_NAV_LOITER_TIME) else 0.0
                m.hold_until_s = self.t_s + max(wait, 0.0)
                self.reached.append(it.seq)
            if self.t_s < m.hold_until_s:
                return target, cruise
            self._hold = target
            self._advance()
        if not m.finished:
            m.finished = True
            self._say(SEV_INFO, "Mission finished, loitering")
        return list(self._hold), cruise

    def _advance(self) -> None:
        m = self.mission
        m.current += 1
        m.hold_until_s = None
        if m.current >= len(m.items):
            m.current = max(len(m.items) - 1, 0)
            m.finished = True

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
        if lost == self.gps_lost:
            return
        self.gps_lost = lost
        if lost:
            self._say(SEV_CRITICAL, "GPS lost: no global position")
            if self.in_air and self.mode is not FlightMode.LAND:
                self._say(SEV_CRITICAL, "Failsafe: no position, descending")
                sp = self._stopping_point()
                self._land_xy = (sp[0], sp[1])
                self._set_mode(FlightMode.LAND)
        else:
            self._say(SEV_INFO, "GPS fix regained")

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
        if not self.home_set and self.gps_ok:
            self.home = [self.pos[0], self.pos[1], 0.0]
            self.home_set = True
            self._say(SEV_INFO, "Home position set")
        self._battery(dt)
        if not self.armed:
            return
        target, v_h, vel_cmd, v_dn = self._guidance()
        self._move(dt, target, v_h, vel_cmd, v_dn)
        self._land_detector()

    def _battery(self, dt: float) -> None:
        if self.armed:
            rate = 100.0 / self.config.battery_capacity_s  # % per second of flight
            self.battery_pct = max(self.battery_pct - rate * dt * (1.0 if self.in_air else 0.1), 0.0)
        level = self.charge_state
        if level > self._battery_level:
            text = {CHARGE_LOW: "Low battery level! Return advised",
                    CHARGE_CRITICAL: "Critical battery level!",
                    CHARGE_EMERGENCY: "Emergency battery level! Landing"}[level]
            self._say(SEV_CRITICAL if level > CHARGE_LOW else SEV_WARNING, text)
            act = int(self.params["COM_LOW_BAT_ACT"])
            if self.in_air and self.armed:
                if level == CHARGE_EMERGENCY and act in (2, 3) and self.mode is not FlightMode.LAND:
                    self.land()
                elif level >= CHARGE_CRITICAL and act in (1, 3) and self.mode not in (
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
            xy = self._land_xy or (self.pos[0], self.pos[1])
            return [xy[0], xy[1], -1.0], self._cruise_mps(), None, self._land_speed()
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

    def _rtl_step(self) -> tuple[list[float], float, None, float]:
        r = self._rtl
        p = self.params
        home, v_dn = self.home, p["MPC_Z_V_AUTO_DN"]
        if r.phase == "climb":
            if self.pos[2] >= r.return_up_m - 0.5:
                r.phase = "return"
            else:
                return [self.pos[0], self.pos[1], r.return_up_m], self._cruise_mps(), None, v_dn
        if r.phase == "return":
            target = [home[0], home[1], r.return_up_m]
            if math.hypot(home[0] - self.pos[0], home[1] - self.pos[1]) < 1.0:
                r.phase = "descend"
            else:
                return target, self._cruise_mps(), None, v_dn
        if r.phase == "descend":
            down_up = min(r.return_up_m, home[2] + p["RTL_DESCEND_ALT"])
            target = [home[0], home[1], down_up]
            if abs(self.pos[2] - down_up) < 0.5:
                r.phase = "loiter"
                r.loiter_until_s = self.t_s + p["RTL_LAND_DELAY"]
            else:
                return target, self._cruise_mps(), None, v_dn
        if r.phase == "loiter":
            target = [home[0], home[1], min(r.return_up_m, home[2] + p["RTL_DESCEND_ALT"])]
            if p["RTL_LAND_DELAY"] < 0 or self.t_s < r.loiter_until_s:
                return target, self._cruise_mps(), None, v_dn
            r.phase = "land"
            self._say(SEV_INFO, "RTL: landing at home")
        return [home[0], home[1], -1.0], self._cruise_mps(), None, self._land_speed()

    def _move(
        self, dt: float, target: list[float] | None, v_h: float, vel_cmd: list[float] | None, v_dn: float
    ) -> None:
        p = self.params
        a_h = p["MPC_ACC_HOR"]
        v_up = p["MPC_TKO_SPEED"] if self.mode is FlightMode.TAKEOFF else p["MPC_Z_V_AUTO_UP"]
        if not self.in_air and target is not None and target[2] > GROUND_EPS_M:
            target = [self.pos[0], self.pos[1], target[2]] if target[2] - self.pos[2] > 0.5 else target
        if vel_cmd is not None:
            vh = math.hypot(vel_cmd[0], vel_cmd[1])
            k = min(1.0, v_h / vh) if vh > 0 else 1.0
            des = [vel_cmd[0] * k, vel_cmd[1] * k, min(max(vel_cmd[2], -v_dn), v_up)]
        else:
            assert target is not None
            dx, dy = target[0] - self.pos[0], target[1] - self.pos[1]
            d = math.hypot(dx, dy)
            # v_des = dir · min(v_max, sqrt(2 a d), d / dt)
            s = min(v_h, math.sqrt(2 * a_h * d), d / dt) if d > 1e-6 else 0.0
            des = [dx / d * s if d > 1e-6 else 0.0, dy / d * s if d > 1e-6 else 0.0, 0.0]
            dz = target[2] - self.pos[2]
            # braking a climb needs downward acceleration and vice versa
            a_z = p["MPC_ACC_DOWN_MAX"] if dz > 0 else p["MPC_ACC_UP_MAX"]
            sz = min(math.sqrt(2 * a_z * abs(dz)), abs(dz) / dt)
            des[2] = min(sz, v_up) if dz > 0 else -min(sz, v_dn)
        # v += clip(v_des − v, |Δv| ≤ a dt)
        dvx, dvy = des[0] - self.vel[0], des[1] - self.vel[1]
        dvh = math.hypot(dvx, dvy)
        lim = a_h * dt
        if dvh > lim:
            dvx, dvy = dvx * lim / dvh, dvy * lim / dvh
        self.vel[0] += dvx
        self.vel[1] += dvy
        dvz = des[2] - self.vel[2]
        lim_z = (p["MPC_ACC_UP_MAX"] if dvz > 0 else p["MPC_ACC_DOWN_MAX"]) * dt
        dvz = min(max(dvz, -lim_z), lim_z)
        self.vel[2] += dvz
        self.acc = [dvx / dt, dvy / dt, dvz / dt]
        for k in range(3):
            self.pos[k] += self.vel[k] * dt
        if math.hypot(self.vel[0], self.vel[1]) > 0.3:
            self.yaw_rad = math.atan2(self.vel[0], self.vel[1])  # heading from north, clockwise
        if self.pos[2] <= 0.0:
            self.pos[2] = 0.0
            self.vel[2] = max(self.vel[2], 0.0)
            if not self.in_air:
                self.vel[0] = self.vel[1] = 0.0

    def _land_detector(self) -> None:
        descending_mode = self.mode is FlightMode.LAND or (
            self.mode is FlightMode.RTL and self._rtl.phase == "land"
        )
        if self.in_air:
            if self.pos[2] <= GROUND_EPS_M and self.vel[2] >= -1e-3:
                self.in_air = False
                self.vel = [0.0, 0.0, 0.0]
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
                self._landed_since_s = self.t_s
            wait = self.params["COM_DISARM_LAND"] if self._has_flown else self.params["COM_DISARM_PRFLT"]
            if wait >= 0 and self.t_s - self._landed_since_s >= wait:
                self._disarm("Disarmed after landing" if self._has_flown else "Disarmed: no takeoff")
