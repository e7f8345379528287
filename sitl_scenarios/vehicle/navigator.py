"""The navigator of the built-in vehicle (PX4's `navigator` module): stored missions and how they
are flown, and the return to launch. Mixed into :class:`sitl_scenarios.vehicle.autopilot.Autopilot`,
whose state (position, home, mode, parameters) it reads and moves; no sockets, no clocks.

Mission items are MISSION_ITEM_INT fields (x, y: degE7 in global frames). RTL flies PX4's phases
climb -> return -> descend -> loiter -> land at the height of :meth:`Navigator.rtl_return_up_m`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from sitl_scenarios.vehicle.mav import (
    ACCEPTED,
    CMD_CAMERA_FIRST,
    CMD_CAMERA_LAST,
    CMD_DO_CHANGE_SPEED,
    CMD_DO_FIRST,
    CMD_DO_LAST,
    CMD_GIMBAL_FIRST,
    CMD_GIMBAL_LAST,
    CMD_NAV_DELAY,
    CMD_NAV_LAND,
    CMD_NAV_LOITER_TIME,
    CMD_NAV_LOITER_UNLIM,
    CMD_NAV_RETURN_TO_LAUNCH,
    CMD_NAV_TAKEOFF,
    CMD_NAV_WAYPOINT,
    DENIED,
    FRAME_GLOBAL,
    FRAME_GLOBAL_INT,
    MISSION_STATE_ACTIVE,
    MISSION_STATE_COMPLETE,
    MISSION_STATE_NO_MISSION,
    MISSION_STATE_NOT_STARTED,
    MISSION_STATE_PAUSED,
    MISSION_TYPE_FENCE,
    MISSION_TYPE_RALLY,
    SEV_INFO,
)
from sitl_scenarios.vehicle.px4 import FlightMode

NAV_COMMANDS = frozenset({
    CMD_NAV_WAYPOINT, CMD_NAV_LOITER_UNLIM, CMD_NAV_LOITER_TIME, CMD_NAV_RETURN_TO_LAUNCH,
    CMD_NAV_LAND, CMD_NAV_TAKEOFF, CMD_NAV_DELAY,
})


def mission_command_supported(command: int) -> bool:
    """Whether a mission item's command is flown (NAV) or accepted and skipped (DO, camera, gimbal)."""
    return (
        command in NAV_COMMANDS
        or CMD_DO_FIRST <= command <= CMD_DO_LAST  # MAV_CMD_DO_*: accepted, only DO_CHANGE_SPEED has an effect
        or CMD_GIMBAL_FIRST <= command <= CMD_GIMBAL_LAST  # gimbal manager: no gimbal, skipped
        or CMD_CAMERA_FIRST <= command <= CMD_CAMERA_LAST  # camera / video: no camera, skipped
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



@dataclass
class RtlState:
    phase: str = "climb"  # climb -> return -> descend -> loiter -> land
    return_up_m: float = 0.0
    loiter_until_s: float = 0.0


@dataclass
class MissionState:
    items: list[MissionItem] = field(default_factory=list)
    current: int = 0
    started: bool = False
    finished: bool = False
    hold_until_s: float | None = None
    takeoff_first: bool = False



class Navigator:
    """Missions and RTL of :class:`~sitl_scenarios.vehicle.autopilot.Autopilot` (a mixin: the
    autopilot owns the state, `_set_mode`, `_say`, `_deny` and `_cruise_mps`)."""

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

    # --- missions -----------------------------------------------------------------------------
    def set_mission(self, mission_type: int, items: list[MissionItem]) -> None:
        """Replace the stored plan of a type (0 mission, 1 fence, 2 rally)."""
        if mission_type == MISSION_TYPE_FENCE:
            self.fence = items
        elif mission_type == MISSION_TYPE_RALLY:
            self.rally = items
        else:
            self.mission = MissionState(items=items)
            if self.mode is FlightMode.MISSION and not items:
                self._set_mode(FlightMode.HOLD)

    def mission_items(self, mission_type: int) -> list[MissionItem]:
        return {MISSION_TYPE_FENCE: self.fence, MISSION_TYPE_RALLY: self.rally}.get(mission_type, self.mission.items)

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
            e, n = self.nav_pos[0], self.nav_pos[1]
        else:
            e, n, _ = self.lla_to_enu(it.x * 1e-7, it.y * 1e-7, self.origin.alt_m)
        up = self._item_up(it) if math.isfinite(it.z) else self.pos[2]
        return [e, n, max(up, 0.0)]

    def _mission_step(self) -> tuple[list[float] | None, float]:
        """Target and horizontal speed for the current mission item; advances the mission."""
        m = self.mission
        cruise = self._cruise_mps()
        if m.takeoff_first:
            target = [self.nav_pos[0], self.nav_pos[1], self._takeoff_up_m]
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
            if it.command not in NAV_COMMANDS:
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
                target = [self.nav_pos[0], self.nav_pos[1], max(target[2], self.pos[2])] if not self.in_air else target
            nav = self.nav_pos
            dh = math.hypot(target[0] - nav[0], target[1] - nav[1])
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


    # --- return to launch ---------------------------------------------------------------------
    def rtl_return_up_m(self) -> float:
        """Height (ENU up) an RTL started now returns at, PX4's rule (navigator RTL, RTL_TYPE 0):

            d ≤ NAV_ACC_RAD:            h = 2 d
            otherwise:                  h = RTL_RETURN_ALT, or min(RTL_RETURN_ALT, d / tan(RTL_CONE_ANG))
                                        when 0 < RTL_CONE_ANG and d ≤ RTL_MIN_DIST; at least 2 NAV_ACC_RAD
            return height:              max(home + h, current height)   (RTL never descends first)

        d: horizontal distance to home [m]; heights above home [m]."""
        p, home = self.params, self.home
        nav = self.nav_pos
        d = math.hypot(nav[0] - home[0], nav[1] - home[1])
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

    def _rtl_step(self) -> tuple[list[float], float, None, float]:
        r = self._rtl
        p = self.params
        home, v_dn = self.home, p["MPC_Z_V_AUTO_DN"]
        if r.phase == "climb":
            if self.pos[2] >= r.return_up_m - 0.5:
                r.phase = "return"
            else:
                return [self.nav_pos[0], self.nav_pos[1], r.return_up_m], self._cruise_mps(), None, v_dn
        if r.phase == "return":
            target = [home[0], home[1], r.return_up_m]
            nav = self.nav_pos
            if math.hypot(home[0] - nav[0], home[1] - nav[1]) < 1.0:
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
