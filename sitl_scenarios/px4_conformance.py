"""The recorded real-PX4 flights as figures, and the same flights flown over MAVLink.

One measuring code for both sides of the conformance tests (tests/test_px4_conformance.py) and of
`benchmarks/px4_legs.py`: :func:`legs_figures` and :func:`gpsloss_figures` read a MAVLink telemetry
log (tlog: what an autopilot sent, each frame after an 8-byte big-endian UNIX time in µs) and
return the figures the built-in vehicle is held to; :func:`fly_legs` and :func:`fly_gpsloss` fly
the recorded procedures (../shared/data/README.md, `px4-v1.18-sih/`) on any MAVLink autopilot
through a pymavlink connection (PX4 SITL, the built-in vehicle), so that connection's own tlog
gives the figures of that flight.

The legs flight: NAV_TAKEOFF to 20 m above home and arm; after the climb, DO_CHANGE_SPEED 10 m/s;
DO_REPOSITION (COMMAND_INT, MAV_FRAME_GLOBAL, 20 m above home) legs of 15 m east, 40 m north, 80 m
east, 300 m north, each from rest at the end of the last (the next one 2 s after the vehicle was
within 1 m of its target and slower than 0.3 m/s); then RTL until disarmed. The GPS-loss flight:
takeoff, DO_CHANGE_SPEED, one DO_REPOSITION 200 m east, the GPS stopped as the vehicle brakes at its end.

Times are the autopilot's (`time_boot_ms`, simulated time in SITL), so figures do not depend on
the speed factor. Heights are above the local origin (-z of LOCAL_POSITION_NED), which is where
the vehicle stood before take-off.

    python -m sitl_scenarios.px4_conformance LEGS.tlog[.gz] GPSLOSS.tlog[.gz] > figures.json
"""

from __future__ import annotations

import argparse
import gzip
import itertools
import json
import math
import shutil
import socket
import struct
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
from pymavlink import mavutil

from estimator.geodesy import Origin
from uavloc.errors import SimulatorError

HEIGHT_M = 20.0
SPEED_MPS = 10.0
#: the recorded legs, ENU displacement of each from the end of the last [m]
LEGS_ENU_M = ((15.0, 0.0), (0.0, 40.0), (80.0, 0.0), (0.0, 300.0))
#: the GPS-loss flight's one leg, ENU [m]
GPSLOSS_LEG_ENU_M = (200.0, 0.0)
SETTLE_DIST_M = 1.0
SETTLE_SPEED_MPS = 0.3
#: a stream is a message sent at least this often [Hz of autopilot time]; rarer ones are answers
STREAM_MIN_HZ = 0.4
#: PX4 custom main mode AUTO and its sub modes (px4_custom_mode.h)
MAIN_AUTO = 4
SUB_TAKEOFF, SUB_LOITER, SUB_RTL, SUB_LAND = 2, 3, 5, 6
#: ArduCopter's RTL custom mode (pymavlink mavutil.mode_mapping_acm)
ARDUCOPTER_RTL = 6


#: the rest criteria of a leg take the speed from the positions over this window [s]
REST_SPEED_WINDOW_S = 1.0


def leg_figures(t_s: np.ndarray, pos_m: np.ndarray, target_m: np.ndarray, length_m: float,
                vel_mps: np.ndarray | None = None) -> dict:
    """t_s (n,), pos_m (n, 2) horizontal, target (2,), vel_mps (n, 2) the reported velocity (None:
    differentiate the positions): peak / p99 ground speed, settle time (within SETTLE_DIST_M of the
    target and at rest: slower than SETTLE_SPEED_MPS), stop time (first at rest after the peak),
    mean speed (length / settle time), overshoot beyond the target along the leg [m].

    "At rest" is judged on the speed the positions themselves show (their displacement over
    REST_SPEED_WINDOW_S): the criteria are then those of the track they are measured on. PX4's
    reported velocity is not: on the slow creep back after an overshoot it reports about twice
    what its positions move (0.35-0.4 against 0.2 m/s on the 80 m leg), right across the
    threshold."""
    v = np.hypot(*(np.gradient(pos_m, t_s, axis=0) if vel_mps is None else vel_mps).T)
    lo = np.searchsorted(t_s, t_s - REST_SPEED_WINDOW_S / 2)
    hi = np.minimum(np.searchsorted(t_s, t_s + REST_SPEED_WINDOW_S / 2), len(t_s) - 1)
    v_rest = np.hypot(*(pos_m[hi] - pos_m[lo]).T) / np.maximum(t_s[hi] - t_s[lo], 1e-9)
    d = np.hypot(*(pos_m - target_m).T)
    settled = np.nonzero((d < SETTLE_DIST_M) & (v_rest < SETTLE_SPEED_MPS))[0]
    t_settle = float(t_s[settled[0]] - t_s[0]) if len(settled) else float("nan")
    beyond_m = np.dot(pos_m - target_m, _unit(target_m - pos_m[0]))
    k_peak = int(np.argmax(v))
    stopped = np.nonzero(v_rest[k_peak:] < SETTLE_SPEED_MPS)[0]
    t_stop = float(t_s[k_peak + stopped[0]] - t_s[0]) if len(stopped) else float("nan")
    return {"peak": float(v.max()), "p99": float(np.percentile(v, 99)), "settle_s": t_settle,
            "stop_s": t_stop, "mean": length_m / t_settle, "overshoot": float(np.max(beyond_m))}


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x)


# --- reading a tlog ----------------------------------------------------------------------------
@dataclass
class Telemetry:
    """What one autopilot sent, in its own time.

    t_s (n,) / pos_ned_m (n, 3) / vel_ned_mps (n, 3): LOCAL_POSITION_NED; gpi_t_s: GLOBAL_POSITION_INT
    times; target_t_s (m,) / target_ne_m (m, 2): POSITION_TARGET_LOCAL_NED's horizontal position,
    where it has one (the position controller's setpoint, in the autopilot's own local frame);
    heartbeats: (t, armed, main mode, sub mode, system status) at each change (ArduPilot: (t, armed,
    custom mode, system status); t NaN for those before the autopilot's first time stamp); fixes:
    (t, fix type) at each change; landed: (t, MAV_LANDED_STATE) at each change; counts: messages
    per type; span_s: autopilot time the log covers; autopilot: the HEARTBEAT's MAV_AUTOPILOT.
    """

    t_s: np.ndarray
    pos_ned_m: np.ndarray
    vel_ned_mps: np.ndarray
    gpi_t_s: np.ndarray
    target_t_s: np.ndarray = field(default_factory=lambda: np.empty(0))
    target_ne_m: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    heartbeats: list[tuple[float, bool, int, int, int]] = field(default_factory=list)
    fixes: list[tuple[float, int]] = field(default_factory=list)
    landed: list[tuple[float, int]] = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)
    span_s: float = 0.0
    autopilot: int = mavutil.mavlink.MAV_AUTOPILOT_PX4

    @property
    def height_m(self) -> np.ndarray:
        return -self.pos_ned_m[:, 2]

    @property
    def ground_speed_mps(self) -> np.ndarray:
        return np.hypot(self.vel_ned_mps[:, 0], self.vel_ned_mps[:, 1])

    def index(self, t_s: float) -> int:
        """The first LOCAL_POSITION_NED sample at or after t_s."""
        return int(np.searchsorted(self.t_s, t_s))


def _open_tlog(path: Path) -> tuple[Path, tempfile.TemporaryDirectory | None]:
    if path.suffix != ".gz":
        return path, None
    tmp = tempfile.TemporaryDirectory(prefix="uavloc-tlog-")
    out = Path(tmp.name) / path.stem
    with gzip.open(path, "rb") as src, open(out, "wb") as dst:
        shutil.copyfileobj(src, dst)
    return out, tmp


def read_telemetry(path: Path) -> Telemetry:
    """The autopilot's messages of a tlog (plain or .gz); ignores other senders."""
    path = Path(path)
    if not path.is_file():
        raise SimulatorError(f"{path}: no such tlog")
    plain, tmp = _open_tlog(path)
    try:
        m = mavutil.mavlink_connection(str(plain), dialect="common")
        t_now = None
        lp_t, lp_p, lp_v, gpi_t, sp_t, sp_ne = [], [], [], [], [], []
        tel = Telemetry(np.empty(0), np.empty((0, 3)), np.empty((0, 3)), np.empty(0))
        sysid = None
        t_first = None
        while True:
            msg = m.recv_match()
            if msg is None:
                break
            kind = msg.get_type()
            if kind == "BAD_DATA":
                continue
            if sysid is None:
                if kind == "HEARTBEAT" and msg.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID:
                    sysid = msg.get_srcSystem()
                    tel.autopilot = msg.autopilot
                else:
                    continue
            if msg.get_srcSystem() != sysid or msg.get_srcComponent() != 1:
                continue
            boot_ms = getattr(msg, "time_boot_ms", None)
            if boot_ms is not None and kind in ("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "ATTITUDE"):
                t_now = boot_ms * 1e-3
                t_first = t_now if t_first is None else t_first
            if t_now is None:  # before the autopilot's first time stamp: only its heartbeat counts
                if kind == "HEARTBEAT" and msg.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID:
                    _note_heartbeat(tel, math.nan, msg)  # (a late ground station's first message)
                continue
            tel.counts[kind] += 1
            if kind == "LOCAL_POSITION_NED":
                lp_t.append(t_now)
                lp_p.append((msg.x, msg.y, msg.z))
                lp_v.append((msg.vx, msg.vy, msg.vz))
            elif kind == "GLOBAL_POSITION_INT":
                gpi_t.append(t_now)
            elif kind == "POSITION_TARGET_LOCAL_NED" and math.isfinite(msg.x) and math.isfinite(msg.y):
                sp_t.append(t_now)
                sp_ne.append((msg.x, msg.y))
            elif kind == "HEARTBEAT" and msg.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID:
                _note_heartbeat(tel, t_now, msg)
            elif kind == "GPS_RAW_INT":
                if not tel.fixes or tel.fixes[-1][1] != msg.fix_type:
                    tel.fixes.append((t_now, msg.fix_type))
            elif kind == "EXTENDED_SYS_STATE" and (not tel.landed or tel.landed[-1][1] != msg.landed_state):
                tel.landed.append((t_now, msg.landed_state))
        m.close()
    finally:
        if tmp is not None:
            tmp.cleanup()
    if not lp_t:
        raise SimulatorError(f"{path}: no LOCAL_POSITION_NED from an autopilot")
    tel.t_s, tel.pos_ned_m, tel.vel_ned_mps = np.array(lp_t), np.array(lp_p), np.array(lp_v)
    tel.gpi_t_s = np.array(gpi_t)
    if sp_t:
        tel.target_t_s, tel.target_ne_m = np.array(sp_t), np.array(sp_ne)
    tel.span_s = float(t_now - t_first)
    return tel


def _mode_fields(hb) -> tuple[int, ...]:
    """A HEARTBEAT's mode: PX4's (main mode, sub mode) of its custom mode, ArduPilot's custom mode."""
    if hb.autopilot == mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return (hb.custom_mode,)
    return (hb.custom_mode >> 16) & 0xFF, (hb.custom_mode >> 24) & 0xFF


def _is_rtl(tel: Telemetry) -> Callable[[tuple], bool]:
    """Whether a heartbeat of `tel` (Telemetry.heartbeats) is in RTL: PX4's sub mode, ArduCopter's mode."""
    if tel.autopilot == mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return lambda h: h[2] == ARDUCOPTER_RTL
    return lambda h: h[3] == SUB_RTL


def _note_heartbeat(tel: Telemetry, t_s: float, msg) -> None:
    """Add an autopilot HEARTBEAT to tel.heartbeats when its [armed, mode (_mode_fields), system
    status] changed (t_s: NaN before the autopilot's first time stamp)."""
    hb = (bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED), *_mode_fields(msg), msg.system_status)
    if not tel.heartbeats or tel.heartbeats[-1][1:] != hb:
        tel.heartbeats.append((t_s, *hb))


# --- figures -----------------------------------------------------------------------------------
def stream_rates_hz(tel: Telemetry) -> dict[str, float]:
    """{message type: rate [Hz of autopilot time]} of the messages sent at least STREAM_MIN_HZ."""
    rates = {k: n / tel.span_s for k, n in tel.counts.items()}
    return {k: round(r, 3) for k, r in sorted(rates.items()) if r >= STREAM_MIN_HZ}


def mode_sequence(tel: Telemetry) -> list[list]:
    """[armed, main mode, sub mode, system status] at each change, from the first STANDBY on (the
    boot before it is the autopilot's own business)."""
    seq = [list(h[1:]) for h in tel.heartbeats]
    first = next((k for k, h in enumerate(seq) if h[-1] == mavutil.mavlink.MAV_STATE_STANDBY), 0)
    return seq[first:]


def _first_hb(tel: Telemetry, pred: Callable[[tuple], bool], after_s: float = -math.inf) -> float:
    return next((h[0] for h in tel.heartbeats if h[0] >= after_s and pred(h)), math.nan)


def _smoothed_speed(tel: Telemetry, window_s: float = 1.0) -> np.ndarray:
    """3-D speed [m/s] averaged over window_s of samples ending at each sample (SITL's estimate
    wanders by a few tenths of a m/s while hovering)."""
    v = np.linalg.norm(tel.vel_ned_mps, axis=1)
    c = np.concatenate(([0.0], np.cumsum(v)))
    lo = np.searchsorted(tel.t_s, tel.t_s - window_s)
    n = np.arange(1, len(v) + 1)
    return (c[n] - c[lo]) / np.maximum(n - lo, 1)


def _rest_after(tel: Telemetry, k0: int) -> int:
    """The first sample from k0 on where the last second's mean speed is below SETTLE_SPEED_MPS."""
    slow = np.nonzero(_smoothed_speed(tel)[k0:] < SETTLE_SPEED_MPS)[0]
    return k0 + int(slow[0]) if len(slow) else len(tel.t_s) - 1


def _motion_start(tel: Telemetry, k0: int, moved_m: float = 1.0) -> int:
    """Where the vehicle started to leave its position at k0: the first sample `moved_m` away (3-D),
    walked back over the samples faster than SETTLE_SPEED_MPS (the acceleration)."""
    d = np.linalg.norm(tel.pos_ned_m[k0:] - tel.pos_ned_m[k0], axis=1)
    out = np.nonzero(d > moved_m)[0]
    if not len(out):
        return len(tel.t_s) - 1
    k = k0 + int(out[0])
    v = np.linalg.norm(tel.vel_ned_mps, axis=1)
    while k > k0 and v[k - 1] > SETTLE_SPEED_MPS:
        k -= 1
    return k


def takeoff_figures(tel: Telemetry) -> tuple[dict, int]:
    """The climb: time from leaving the ground to 50 / 90 % of the take-off height, the peak climb
    rate and the height reached; and the sample where the vehicle rests at that height."""
    h = tel.height_m
    ground = float(np.median(h[: max(5, tel.index(tel.t_s[0] + 1.0))]))
    k_up = _motion_start(tel, 0)
    k_rest = _rest_after(tel, k_up + int(np.argmax(h[k_up:] > ground + 0.9 * HEIGHT_M)))
    top = float(np.median(h[k_rest:tel.index(tel.t_s[k_rest] + 1.0)]))
    climb = top - ground

    def t_frac(f: float) -> float:
        return float(tel.t_s[k_up + int(np.argmax(h[k_up:] >= ground + f * climb))] - tel.t_s[k_up])

    figs = {"height_m": climb, "t50_s": t_frac(0.5), "t90_s": t_frac(0.9),
            "peak_climb_mps": float(np.max(-tel.vel_ned_mps[k_up:k_rest, 2]))}
    return figs, k_rest


#: where the log has the autopilot's setpoints, a leg starts when its setpoint has moved this far
#: [m] along the way from where it rested SETPOINT_REST_S before the vehicle was 1 m along
SETPOINT_MOVED_M, SETPOINT_REST_S = 0.05, 3.0


def _leaves(tel: Telemetry, k0: int, origin_ne: np.ndarray, toward_ne: np.ndarray, by_m: float = 1.0) -> int:
    """The sample from k0 on where the vehicle set off from origin_ne toward toward_ne. Where the log
    has the autopilot's setpoints (POSITION_TARGET_LOCAL_NED): where its setpoint set off, the
    command's first effect (SETPOINT_MOVED_M, SETPOINT_REST_S); else the first sample `by_m` along
    that way, walked back over the samples faster than SETTLE_SPEED_MPS. The setpoint is the robust
    one: PX4's estimated speed wanders by 0.3-0.4 m/s at rest, which walks a leg's start back by
    up to a second before its command."""
    way = _unit(toward_ne - origin_ne)
    along = (tel.pos_ned_m[k0:, :2] - origin_ne) @ way
    out = np.nonzero(along > by_m)[0]
    if not len(out):
        raise SimulatorError(f"the vehicle never set off toward {toward_ne} (NE) after {tel.t_s[k0]:.1f} s")
    k = k0 + int(out[0])
    t_out = tel.t_s[k]
    j_rest = int(np.searchsorted(tel.target_t_s, t_out - SETPOINT_REST_S))
    j_out = int(np.searchsorted(tel.target_t_s, t_out))
    if tel.target_t_s.size and j_rest > 0 and tel.target_t_s[j_rest - 1] >= tel.t_s[k0]:
        sp_along = (tel.target_ne_m[j_rest:j_out] - origin_ne) @ way
        resting = np.nonzero(sp_along <= sp_along[0] + SETPOINT_MOVED_M)[0]
        return max(k0, min(k, tel.index(tel.target_t_s[j_rest + int(resting[-1])])))
    while k > k0 and tel.ground_speed_mps[k - 1] > SETTLE_SPEED_MPS:
        k -= 1
    return k


#: a leg's target is the autopilot's position setpoint this long before the leg's end [s]: the
#: trajectory has come to its end by then, and the next command is not yet there (it comes at most
#: about a second before the vehicle sets off; a leg's start walks back over the acceleration)
TARGET_BEFORE_END_S = 2.0


def _leg_target_ne(tel: Telemetry, t_start_s: float, t_end_s: float, commanded_ne: np.ndarray) -> np.ndarray:
    """Where the autopilot flew a leg to, NE [m] in its own local frame: its position setpoint
    (POSITION_TARGET_LOCAL_NED) TARGET_BEFORE_END_S before the leg's end; the commanded point where
    the log has none. PX4 maps the commanded latitude and longitude with its own projection (a
    sphere) and origin: its setpoint is 0.1-0.3 m from the command's WGS-84 ENU on these legs."""
    k = int(np.searchsorted(tel.target_t_s, t_end_s - TARGET_BEFORE_END_S)) - 1
    if k < 0 or tel.target_t_s[k] < t_start_s:
        return commanded_ne
    return tel.target_ne_m[k]


def legs_figures(path: Path) -> dict:
    """The figures of a legs flight's tlog (see the module docstring). Each leg's geometry is the
    commanded one (the take-off point plus the legs so far, LEGS_ENU_M); its target, from which
    the settle time and the overshoot are measured, is the autopilot's own (:func:`_leg_target_ne`).
    A leg runs from the vehicle setting off toward it until it sets off toward the next one (or
    the RTL's climb)."""
    tel = read_telemetry(path)
    takeoff, k = takeoff_figures(tel)
    ground_ne = np.median(tel.pos_ned_m[: max(5, tel.index(tel.t_s[0] + 1.0)), :2], axis=0)
    points = [ground_ne]
    for east, north in LEGS_ENU_M:
        points.append(points[-1] + np.array([north, east]))
    # the first leg may start before the climb has come to rest (ArduCopter's recording)
    k_top = int(np.argmax(tel.height_m > tel.height_m[0] + 0.9 * HEIGHT_M))
    starts = []
    for a_ne, b_ne in itertools.pairwise(points):
        starts.append(_leaves(tel, min(k, k_top) if not starts else starts[-1] + 1, a_ne, b_ne))
    t_rtl_hb = _first_hb(tel, _is_rtl(tel), after_s=tel.t_s[starts[-1]])
    if not math.isfinite(t_rtl_hb):
        raise SimulatorError(f"{path}: no RTL after the legs")
    k_rtl = _motion_start(tel, tel.index(t_rtl_hb - 1.5))
    legs = []
    for i, (east, north) in enumerate(LEGS_ENU_M):
        k0, k_end = starts[i], (starts[i + 1] if i + 1 < len(starts) else k_rtl)
        sl = slice(k0, k_end)
        target_en = _leg_target_ne(tel, tel.t_s[k0], tel.t_s[k_end], points[i + 1])[::-1]
        pos_en, vel_en = tel.pos_ned_m[sl][:, [1, 0]], tel.vel_ned_mps[sl][:, [1, 0]]
        legs.append({key: round(v, 4) for key, v in
                     leg_figures(tel.t_s[sl], pos_en, target_en, math.hypot(east, north), vel_en).items()})
    rtl = rtl_figures(tel, k_rtl, t_rtl_hb)
    out = {"takeoff": _rounded(takeoff), "legs": legs, "rtl": _rounded(rtl), "rates_hz": stream_rates_hz(tel),
           "modes": mode_sequence(tel)}
    hover = tel.pos_ned_m[k:starts[0], :2]  # resting after the take-off, before the first leg
    if len(hover):
        out["hover_wander_m"] = round(float(np.percentile(np.hypot(*(hover - np.median(hover, axis=0)).T), 95)), 4)
    return out


def rtl_figures(tel: Telemetry, k_rest: int, t_rtl_hb: float) -> dict:
    """The return from sample k_rest (its start): the highest point above the take-off ground, the
    p99 ground speed of the return, the peak and mean descent rate over the home position, and the
    time from RTL to landed."""
    k0 = k_rest
    h = tel.height_m
    ground = float(np.median(h[: max(5, tel.index(tel.t_s[0] + 1.0))]))
    t_landed = next((t for t, s in tel.landed if t > tel.t_s[k0] and s == mavutil.mavlink.MAV_LANDED_STATE_ON_GROUND),
                    math.nan)
    if not tel.landed:  # no EXTENDED_SYS_STATE (ArduPilot's streams): landed once the status leaves ACTIVE
        t_landed = _first_hb(tel, lambda h: h[-1] != mavutil.mavlink.MAV_STATE_ACTIVE, after_s=tel.t_s[k0])
    k_land = min(tel.index(t_landed), len(h) - 1)
    home_d = np.hypot(*tel.pos_ned_m[:, :2].T)
    over_home = k0 + int(np.argmax(home_d[k0:] < 1.0))
    k_top = over_home + int(np.argmax(h[over_home:k_land]))
    k_dn = k_top + int(np.argmax(tel.vel_ned_mps[k_top:, 2] > 0.1))  # descending
    k_ground = k_dn + int(np.argmax(h[k_dn:] < ground + 0.1))
    return {"height_m": float(np.max(h[k0:k_land]) - ground),
            "return_p99_mps": float(np.percentile(tel.ground_speed_mps[k0:over_home], 99)),
            "descent_peak_mps": float(np.max(tel.vel_ned_mps[k_dn:k_ground, 2])),
            "descent_mean_mps": float((h[k_dn] - h[k_ground]) / (tel.t_s[k_ground] - tel.t_s[k_dn])),
            "to_landed_s": float(t_landed - tel.t_s[k0])}


def gpsloss_figures(path: Path) -> dict:
    """The figures of a GPS-loss flight's tlog: from the fix's loss (GPS_RAW_INT fix type below 3)
    to the failsafe's descent, the position published meanwhile and after (GLOBAL_POSITION_INT rate,
    how far the dead-reckoned position moved), the blind descent and the landing."""
    tel = read_telemetry(path)
    t_loss = next((t for t, f in tel.fixes[1:] if f < 3), math.nan)
    if not math.isfinite(t_loss):
        raise SimulatorError(f"{path}: the GPS fix is never lost")
    k_loss = tel.index(t_loss)
    k_dn = k_loss + int(np.argmax(tel.vel_ned_mps[k_loss:, 2] > 0.3))
    t_landed = next((t for t, s in tel.landed if t > tel.t_s[k_dn] and s == mavutil.mavlink.MAV_LANDED_STATE_ON_GROUND),
                    math.nan)
    t_disarmed = _first_hb(tel, lambda h: not h[1], after_s=tel.t_s[k_dn])
    h = tel.height_m
    ground = float(np.median(h[: max(5, tel.index(tel.t_s[0] + 1.0))]))
    gpi = tel.gpi_t_s
    t_dn = float(tel.t_s[k_dn])

    def drift(after_s: float) -> float:
        k = tel.index(t_loss + after_s)
        return float(np.hypot(*(tel.pos_ned_m[k, :2] - tel.pos_ned_m[k_loss, :2])))

    ground_ne = np.median(tel.pos_ned_m[: max(5, tel.index(tel.t_s[0] + 1.0)), :2], axis=0)
    k_top = int(np.argmax(h > ground + 0.9 * HEIGHT_M))
    leg_start = _leaves(tel, k_top, ground_ne, ground_ne + np.array(GPSLOSS_LEG_ENU_M[::-1]))
    return {"loss_after_leg_start_s": round(float(t_loss - tel.t_s[leg_start]), 3),
            "speed_at_loss_mps": round(float(tel.ground_speed_mps[k_loss]), 3),
            "loss_to_descent_s": t_dn - t_loss,
            "drift_at_descent_m": drift(t_dn - t_loss),
            "gpi_hz_dead_reckoning": float(np.sum((gpi >= t_loss) & (gpi < t_dn)) / (t_dn - t_loss)),
            "gpi_hz_descent": float(np.sum((gpi >= t_dn) & (gpi < t_landed)) / (t_landed - t_dn)),
            "descent_height_m": float(h[k_dn] - ground),
            "descent_s": float(t_landed - t_dn),
            "landed_to_disarmed_s": float(t_disarmed - t_landed),
            "modes_after_loss": [list(hb[1:]) for hb in tel.heartbeats if hb[0] >= t_loss]}


def _rounded(d: dict) -> dict:
    return {k: round(v, 4) for k, v in d.items()}


# --- flying the recorded procedures ------------------------------------------------------------
class Flight:
    """Commands to one autopilot over a pymavlink connection, waiting on what it reports.

    conn: a pymavlink connection; tlog: a binary file that gets every message received, as a tlog
    (pymavlink's UDP connections write none themselves); timeout_s: wall seconds per wait. `home`
    is where the vehicle stands (its first GLOBAL_POSITION_INT). Subclasses fly another autopilot's
    primitives (sitl_scenarios.ardupilot_conformance); DIALECT: the pymavlink dialect they need.
    """

    DIALECT = "common"

    def __init__(self, conn, timeout_s: float = 120.0, tlog: BinaryIO | None = None):
        self.conn = conn
        self.tlog = tlog
        self.timeout_s = timeout_s
        self.lp = None  # the last LOCAL_POSITION_NED
        self.hb = None  # the last autopilot HEARTBEAT
        self.home: Origin | None = None

    def _pump(self, blocking: bool = True):
        msg = self.conn.recv_match(blocking=blocking, timeout=0.5)
        if msg is None:
            return None
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return None
        if self.tlog is not None:
            self.tlog.write(struct.pack(">Q", int(time.time() * 1e6)) + msg.get_msgbuf())
        if kind == "LOCAL_POSITION_NED":
            self.lp = msg
        elif kind == "HEARTBEAT" and msg.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID:
            self.hb = msg
        elif kind == "GLOBAL_POSITION_INT" and self.home is None:
            self.home = Origin(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3 - msg.relative_alt * 1e-3)
        return msg

    def wait(self, cond: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + self.timeout_s
        while not cond():
            if time.monotonic() > deadline:
                raise SimulatorError(f"not within {self.timeout_s:g} s: {what}")
            self._pump()

    def sleep(self, wall_s: float) -> None:
        end = time.monotonic() + wall_s
        while time.monotonic() < end:
            self._pump()

    def armed(self) -> bool:
        return self.hb is not None and bool(self.hb.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def command_long(self, cmd: int, *p: float) -> None:
        p = list(p) + [0.0] * (7 - len(p))
        self.conn.mav.command_long_send(self.conn.target_system, self.conn.target_component, cmd, 0, *p)

    def start(self) -> None:
        """Until the autopilot is ready (HEARTBEAT system status STANDBY: its pre-arm checks pass)
        and streams its local position and home (its first global position)."""
        self.conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        self.wait(lambda: self.hb is not None, "a heartbeat")
        self.conn.target_system, self.conn.target_component = self.conn.target_system or 1, 1
        self.wait(lambda: self.lp is not None and self.home is not None
                  and self.hb.system_status == mavutil.mavlink.MAV_STATE_STANDBY, "ready, position and home")

    def takeoff(self) -> None:
        """NAV_TAKEOFF to HEIGHT_M above home, arm, wait for the climb, DO_CHANGE_SPEED."""
        self.command_long(mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, math.nan, 0, 0, math.nan, math.nan, math.nan,
                          self.home.alt_m + HEIGHT_M)
        self.sleep(0.5)
        self.command_long(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        self.wait(lambda: -self.lp.z > HEIGHT_M - 1.0 and abs(self.lp.vz) < 0.1 and self.armed(),
                  f"the climb to {HEIGHT_M:g} m")
        self.sleep(1.0)
        self.command_long(mavutil.mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, SPEED_MPS, -1)

    def reposition(self, east_m: float, north_m: float) -> tuple[float, float]:
        """DO_REPOSITION to (east, north) ENU [m] of home at HEIGHT_M; returns the target NE."""
        lat, lon, _ = self.home.enu_to_lla(np.array([east_m, north_m, 0.0]))
        self.conn.mav.command_int_send(self.conn.target_system, self.conn.target_component,
                                       mavutil.mavlink.MAV_FRAME_GLOBAL, mavutil.mavlink.MAV_CMD_DO_REPOSITION,
                                       0, 0, -1, 1, 0, math.nan, round(lat * 1e7), round(lon * 1e7),
                                       self.home.alt_m + HEIGHT_M)
        return north_m, east_m

    def settle(self, target_ne: tuple[float, float]) -> None:
        self.wait(lambda: math.hypot(self.lp.x - target_ne[0], self.lp.y - target_ne[1]) < SETTLE_DIST_M
                  and math.hypot(self.lp.vx, self.lp.vy) < SETTLE_SPEED_MPS, f"at rest at {target_ne}")

    def rtl(self) -> None:
        self.command_long(mavutil.mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH)
        self.wait(lambda: not self.armed(), "landed and disarmed after RTL")
        self.sleep(1.0)


def fly_legs(conn, timeout_s: float = 120.0, tlog: BinaryIO | None = None,
             flight: type[Flight] = Flight) -> None:
    """The recorded legs flight (module docstring) on the autopilot at the other end of conn
    (tlog: see :class:`Flight`; flight: whose primitives). The 2 s pause between legs is wall time,
    as in the recording."""
    f = flight(conn, timeout_s, tlog)
    f.start()
    f.takeoff()
    east = north = 0.0
    for de, dn in LEGS_ENU_M:
        east, north = east + de, north + dn
        target = f.reposition(east, north)
        f.settle(target)
        f.sleep(2.0)
    f.rtl()


def fly_gpsloss(conn, lose_gps_below: Callable[[float], None], loss_below_mps: float, timeout_s: float = 120.0,
                tlog: BinaryIO | None = None) -> None:
    """The recorded GPS-loss flight: takeoff, DO_CHANGE_SPEED, a DO_REPOSITION 200 m east, and the
    GPS lost where the recorded one lost it, braking at the leg's end: once the vehicle has flown
    faster than half of SPEED_MPS, `lose_gps_below(loss_below_mps)` has the autopilot's side drop
    the fix as the vehicle slows to that ground speed [m/s]; then until the autopilot disarmed by
    itself. The moment is the flight's phase, not a time: what the published position does after
    the loss hinges on how fast the vehicle still goes then."""
    f = Flight(conn, timeout_s, tlog)
    f.start()
    f.takeoff()
    f.reposition(*GPSLOSS_LEG_ENU_M)
    f.wait(lambda: math.hypot(f.lp.vx, f.lp.vy) > SPEED_MPS / 2, "the leg's cruise")
    lose_gps_below(loss_below_mps)
    f.wait(lambda: not f.armed(), "the failsafe's landing and disarm")
    f.sleep(1.0)


#: where the recorded PX4 stood (SIH_LOC_*: lat, lon [deg], alt AMSL [m])
RECORDED_HOME = (43.6143, 7.0716, 150.0)
#: the receive buffer asked for the built-in vehicle's link [bytes]
RECEIVE_BUFFER_BYTES = 4 << 20


def fly_builtin(flight: str, tlog: Path, speedup: float = 4.0, gps_loss_below_mps: float | None = None,
                vehicle=None, timeout_s: float = 120.0, primitives: type[Flight] = Flight) -> Path:
    """Fly the recorded `flight` ("legs" or "gpsloss") on the built-in vehicle at the recorded
    home, over MAVLink from pymavlink; returns `tlog`, what the vehicle sent. The streams run at
    their simulated rates (the simulator's wall-clock cap and tick raised to carry 50 Hz at this
    speedup). vehicle: its VehicleConfig (default: PX4's defaults, no GPS error: the recorded
    SIH's estimate is smooth). gps_loss_below_mps: the GPS-loss flight's moment of the loss
    (:func:`fly_gpsloss`), judged by the simulator on its vehicle's speed at each step.
    primitives: the :class:`Flight` (sub)class whose commands fly the legs."""
    from sitl_scenarios.scenario import VehicleConfig
    from sitl_scenarios.vehicle import VehicleSimulator

    if flight not in ("legs", "gpsloss"):
        raise SimulatorError(f"unknown recorded flight {flight!r} (legs, gpsloss)")
    home = Origin(*RECORDED_HOME)
    sim = VehicleSimulator(home, vehicle or VehicleConfig(gps_sigma_m=0.0), speedup=speedup, target=None,
                           bind=("127.0.0.1", 0), tick_wall_s=min(0.01, 0.01 / speedup),
                           max_stream_wall_hz=60.0 * speedup)
    with sim:
        conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{sim.local_address[1]}", source_system=255,
                                          dialect=primitives.DIALECT)
        # room for a few seconds of the 50 Hz streams: a busy machine may hold this thread back for a
        # while, and the vehicle's datagrams must wait in the socket, not be dropped (the kernel
        # caps the size at net.core.rmem_max)
        conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        try:
            with open(tlog, "wb") as fh:
                if flight == "legs":
                    fly_legs(conn, timeout_s, fh, primitives)
                else:
                    def lose_gps_below(v_mps: float) -> None:
                        sim.lose_gps_when(lambda st: math.hypot(st.vel_enu_mps[0], st.vel_enu_mps[1]) <= v_mps)

                    fly_gpsloss(conn, lose_gps_below, gps_loss_below_mps or 0.0, timeout_s, fh)
        finally:
            conn.close()
    return tlog


def figures_main(module: str, description: str, extractors: dict[str, Callable[[Path], dict]],
                 argv: list[str] | None = None) -> int:
    """A conformance module's command line: one tlog argument per flight of `extractors`
    ({flight: its figures from a tlog}), the figures as JSON on stdout; exit 1 with the message on a
    tlog that cannot be read."""
    ap = argparse.ArgumentParser(prog=f"python -m {module}", description=description)
    for flight in extractors:
        ap.add_argument(flight, type=Path, help=f"the {flight} flight's tlog (.gz too)")
    args = ap.parse_args(argv)
    try:
        out: dict = {"source": {flight: getattr(args, flight).name for flight in extractors}}
        out.update({flight: figures(getattr(args, flight)) for flight, figures in extractors.items()})
    except SimulatorError as exc:
        print(f"{module.rsplit('.', 1)[-1]}: {exc}", file=sys.stderr)
        return 1
    json.dump(out, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    return figures_main("sitl_scenarios.px4_conformance", __doc__.splitlines()[0],
                        {"legs": legs_figures, "gpsloss": lambda p: _rounded_tree(gpsloss_figures(p))}, argv)


def _rounded_tree(d: dict) -> dict:
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in d.items()}


if __name__ == "__main__":
    raise SystemExit(main())
