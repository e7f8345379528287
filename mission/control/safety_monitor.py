"""The safety monitor (docs/design.md §7): a pure decision over the mission's state, and a thin loop.

:func:`return_reason` says whether the survey must end and the vehicle return home, from a
:class:`SafetyView` of the mission now: the vehicle link (lost longer than link_lost_wait_s), the
battery (below the RTL threshold), the position (outside the geofence / a no-fly zone / the
altitude band for breach_confirm_fixes fixes in a row, :class:`mission.safety.BreachWatch`), the gNB
(lost longer than gnb_lost_wait_s) and the mission time limit. :func:`energy_remaining_m` is the
battery's range the planner is given in real flights. :class:`SafetyMonitor` samples the view
every `period_s` and reports through the :class:`FlightState`.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mission.control.config import SURVEY, TAKEOFF, ControllerConfig
from mission.control.state import FlightState
from mission.safety import BreachWatch, SafetyGate

#: flight modes an autopilot switches to on its own failsafe (PX4: GPS/position loss → LAND, low
#: battery or data-link loss → RETURN_TO_LAUNCH); the controller never commands LAND
AUTOPILOT_FAILSAFE_MODES = ("LAND", "RETURN_TO_LAUNCH")
#: STATUSTEXT severities copied into the mission log as `vehicle_text` events
LOGGED_TEXT_SEVERITIES = ("WARNING", "ERROR", "CRITICAL", "ALERT", "EMERGENCY")

#: the least wall time [s] a gNB must stay silent to be lost (with gnb_lost_wait_s mission seconds)
GNB_LOST_WALL_MIN_S = 5.0
#: survey mission seconds and battery percent used below which the drain is not yet known
ENERGY_MIN_SURVEY_S = 5.0
ENERGY_MIN_USED_PCT = 1.0


@dataclass(frozen=True)
class SafetyView:
    """The mission now, as the safety monitor sees it. Times in mission seconds.

    now_s; phase; link_lost_since_s / gnb_down_since_s (None: fine); gnb_problem: the gNB's words;
    gnb_down_wall_s: wall seconds the gNB has been down (None: not measured);
    battery_pct (None: unknown); breach: the position limit a confirmed breach broke (None: none);
    position_lost: the vehicle reports no valid global position; flight_mode: a failsafe mode the
    autopilot switched to by itself (None: none); vehicle_text: its last warning (PX4's failsafe message).
    """

    now_s: float
    phase: str
    link_lost_since_s: float | None = None
    gnb_down_since_s: float | None = None
    gnb_problem: str | None = None
    gnb_down_wall_s: float | None = None
    battery_pct: float | None = None
    breach: str | None = None
    position_lost: bool = False
    flight_mode: str | None = None
    vehicle_text: str | None = None


def return_reason(view: SafetyView, cfg: ControllerConfig, gate: SafetyGate) -> str | None:
    """Why the vehicle must return home now, or None. Pure. Only while taking off or surveying."""
    if view.phase not in (TAKEOFF, SURVEY):
        return None
    if view.position_lost:
        return "the vehicle lost its global position (GPS)"
    if view.flight_mode in AUTOPILOT_FAILSAFE_MODES:
        said = f": {view.vehicle_text}" if view.vehicle_text else ""
        return f"the autopilot switched to {view.flight_mode} on its own (failsafe{said})"
    if view.link_lost_since_s is not None and view.now_s - view.link_lost_since_s > cfg.safety.link_lost_wait_s:
        return f"vehicle link lost for more than {cfg.safety.link_lost_wait_s:g} s"
    reason = gate.return_reason(None, view.battery_pct) or view.breach
    if reason:
        return reason
    # the wait is mission seconds (the vehicle's clock) and, for a simulation at a speed-up, at least
    # GNB_LOST_WALL_MIN_S of wall time too: a gNB answers in its own (wall) time, and a busy machine
    # that holds it 2 s is no lost gNB, however many mission seconds ×10 makes of them (loop stalls of
    # 1.4-5.8 s were seen beside busy loops)
    wall_wait_s = min(cfg.safety.gnb_lost_wait_s, GNB_LOST_WALL_MIN_S)
    if (view.gnb_down_since_s is not None and view.now_s - view.gnb_down_since_s > cfg.safety.gnb_lost_wait_s
            and (view.gnb_down_wall_s is None or view.gnb_down_wall_s > wall_wait_s)):
        return f"gNB lost for more than {cfg.safety.gnb_lost_wait_s:g} s: {view.gnb_problem}"
    if view.now_s > cfg.flight.time_limit_s:
        return f"mission time limit {cfg.flight.time_limit_s:g} s reached"
    return None


def energy_remaining_m(survey_s: float, speed_mps: float, battery_start_pct: float | None,
                       battery_pct: float | None, battery_rtl_pct: float) -> float:
    """Survey metres the battery still allows down to the RTL threshold, from the drain so far [m];
    inf while the drain is unknown (no battery reading, < 5 s of survey or < 1 % used).

    A multicopter's power is nearly the same hovering, turning and cruising, so its charge goes by
    the second, not by the metre: the seconds the charge left allows at the drain rate so far, at
    the leg speed,

        m_left = (pct_now − pct_rtl) · survey_s / (pct_start − pct_now) · speed_mps    (≥ 0)

    survey_s: mission seconds since the survey began (pct_start's reading), hover and waits
    included; speed_mps: the speed legs are flown at.
    """
    if battery_pct is None or battery_start_pct is None or survey_s < ENERGY_MIN_SURVEY_S:
        return math.inf
    used = battery_start_pct - battery_pct
    if used < ENERGY_MIN_USED_PCT:
        return math.inf
    return max(0.0, (battery_pct - battery_rtl_pct) * survey_s / used * speed_mps)


class SafetyMonitor:
    """The loop: every period_s, note the link's condition, build the view, request a return when
    :func:`return_reason` gives one.

    vehicle_state: the vehicle's `state` (connected, age_s(), battery_pct); latest_fix: () -> (t_s,
    pos_enu_m (3,)) or None; now: mission seconds."""

    def __init__(self, flight: FlightState, cfg: ControllerConfig, gate: SafetyGate, vehicle_state,
                 latest_fix: Callable[[], tuple[float, np.ndarray] | None], now: Callable[[], float],
                 period_s: float = 0.05):
        self.flight, self.cfg, self.gate = flight, cfg, gate
        self.vehicle_state = vehicle_state
        self.latest_fix, self.now = latest_fix, now
        self.period_s = period_s
        self.breach = BreachWatch(gate, cfg.safety.breach_confirm_fixes)
        self.texts_logged = 0  # vehicle status texts looked at so far
        self.last_text: str | None = None
        self.position_lost = False  # the vehicle reports no valid global position (GPS/estimator)
        self.prev_mode: str | None = None
        self.failsafe_mode: str | None = None  # a failsafe mode the autopilot switched to by itself

    def _vehicle_texts(self) -> None:
        """Copy the vehicle's new warnings and worse (PX4's failsafe messages) into the log."""
        texts = getattr(self.vehicle_state, "texts", ())
        while self.texts_logged < len(texts):
            _, severity, text = texts[self.texts_logged]
            self.texts_logged += 1
            if severity in LOGGED_TEXT_SEVERITIES and text:
                self.last_text = text
                self.flight.event(f"vehicle {severity.lower()}: {text}", kind="vehicle_text", severity=severity)

    def step(self) -> str | None:
        """One look at the mission; the return reason it gave (also requested), or None."""
        f, st, cfg = self.flight, self.vehicle_state, self.cfg
        now = self.now()
        lost = (not st.connected) or st.age_s() > cfg.safety.link_timeout_s
        f.link(now, lost)
        self._vehicle_texts()
        position_ok = bool(getattr(st, "global_position_ok", True))
        if not lost and position_ok == self.position_lost:
            self.position_lost = not position_ok
            f.event("vehicle global position lost (GPS or estimator)" if self.position_lost
                    else "vehicle global position restored",
                    kind="position_lost" if self.position_lost else "position_restored")
        # a switch INTO a failsafe mode is the autopilot's own decision; a vehicle still in the RTL
        # mode of its last landing when this mission starts has decided nothing
        mode = None if lost else getattr(st, "flight_mode", None)
        if mode is not None:
            if mode in AUTOPILOT_FAILSAFE_MODES and self.prev_mode is not None and (
                    self.prev_mode not in AUTOPILOT_FAILSAFE_MODES):
                self.failsafe_mode = mode
            self.prev_mode = mode
        breach = None
        latest = None if lost else self.latest_fix()
        if latest is not None and f.phase in (TAKEOFF, SURVEY):
            breach = self.breach.update(latest[0], latest[1], check_altitude=f.phase == SURVEY,
                                        alt_margin_m=cfg.safety.alt_margin_m)
        view = SafetyView(now_s=now, phase=f.phase, link_lost_since_s=f.link_lost_since,
                          gnb_down_since_s=f.gnb_down_since, gnb_problem=f.gnb_problem,
                          gnb_down_wall_s=(None if f.gnb_down_since_wall is None
                                           else time.monotonic() - f.gnb_down_since_wall),
                          battery_pct=st.battery_pct, breach=breach, position_lost=self.position_lost,
                          flight_mode=self.failsafe_mode, vehicle_text=self.last_text)
        reason = return_reason(view, cfg, self.gate)
        if reason:
            f.request_return(reason)
        return reason

    async def run(self) -> None:
        while True:
            await asyncio.sleep(self.period_s)
            self.step()
