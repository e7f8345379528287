"""Straight legs at a commanded speed on PX4 SITL and on the built-in vehicle, side by side.

    UAVLOC_PX4=.../build/px4_sitl_default \
        python benchmarks/px4_legs.py [--legs 15 40 80 300] [--speed-mps 10] [--speed 4] [--instance 1]

Both vehicles take off to 20 m, get DO_CHANGE_SPEED (`--speed-mps`) and then one DO_REPOSITION per
leg, each leg starting from rest at the end of the previous one. Per leg: the peak horizontal ground
speed (PX4: LOCAL_POSITION_NED at 20 Hz vehicle time; built-in: its state every 0.05 s), the 99th
percentile of the ground speed, the time from the command until the vehicle is within 1 m of the
target and slower than 0.3 m/s, and leg length / that time. PX4 is flown over MAVLink (pymavlink);
the built-in vehicle's autopilot (sitl_scenarios.vehicle.autopilot) is stepped directly, with no
link, so its figures are its guidance and flight model alone. Ratio = built-in / PX4.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
REPO = _HERE.parent
sys.path[:] = [str(REPO)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

import numpy as np  # noqa: E402
from pymavlink import mavutil  # noqa: E402

from estimator.geodesy import Origin  # noqa: E402
from sitl_scenarios.px4_conformance import HEIGHT_M, leg_figures  # noqa: E402
from sitl_scenarios.px4_sitl import Px4Sitl, build_from_env, instance_busy, missing_requirement  # noqa: E402
from sitl_scenarios.scenario import load_scenario  # noqa: E402
from sitl_scenarios.vehicle.autopilot import Autopilot  # noqa: E402

PARAMS = ("MPC_ACC_HOR", "MPC_ACC_HOR_MAX", "MPC_JERK_AUTO", "MPC_JERK_MAX", "MPC_XY_CRUISE",
          "MPC_XY_VEL_MAX", "NAV_ACC_RAD", "MPC_XY_TRAJ_P", "MPC_XY_ERR_MAX", "MPC_XY_P", "MPC_YAW_MODE")


def _leg_targets(legs: list[float]) -> list[np.ndarray]:
    """East-west zigzag: leg k ends at (±…, 0) ENU relative to the take-off point."""
    out, e = [], 0.0
    for k, length in enumerate(legs):
        e += length if k % 2 == 0 else -length
        out.append(np.array([e, 0.0]))
    return out


# --- built-in ---------------------------------------------------------------------------------
def run_builtin(legs: list[float], speed_mps: float) -> list[dict]:
    sc = load_scenario("three_users_nlos")
    origin = sc.origin_geo
    ap = Autopilot(origin, sc.vehicle, np.random.default_rng(0))
    ap.step(3.0, 0.0)
    ap.arm()
    ap.takeoff(origin.alt_m + HEIGHT_M)
    while ap.pos[2] < HEIGHT_M - 0.1 or ap.mode.value != "hold":
        ap.step(0.05, 0.0)
    ap.step(2.0, 0.0)
    ap.change_speed(speed_mps)
    out = []
    for length, tgt in zip(legs, _leg_targets(legs), strict=True):
        lat, lon, alt = ap.enu_to_lla([tgt[0], tgt[1], HEIGHT_M])
        ap.reposition(lat, lon, alt)
        ts, ps = [], []
        t0 = ap.t_s
        while ap.t_s - t0 < 60 + length / 2:
            ts.append(ap.t_s)
            ps.append(ap.pos[:2])
            ap.step(0.05, 0.0)
            if math.hypot(ap.pos[0] - tgt[0], ap.pos[1] - tgt[1]) < 0.05 and math.hypot(*ap.vel[:2]) < 0.02:
                break
        out.append(leg_figures(np.array(ts), np.array(ps), tgt, length))
    return out


# --- PX4 ---------------------------------------------------------------------------------------
def _cmd_long(m, cmd: int, *p: float) -> None:
    p = list(p) + [0.0] * (7 - len(p))
    m.mav.command_long_send(m.target_system, m.target_component, cmd, 0, *p)


def run_px4(legs: list[float], speed_mps: float, speed: float, instance: int, work: Path,
            dump: Path | None = None) -> tuple[list[dict], dict]:
    build = build_from_env()
    why = missing_requirement(build)
    if why is not None:
        raise SystemExit(f"px4 legs: {why}")
    while instance_busy(instance):
        instance += 1
    px4 = Px4Sitl(build, instance, speed, work / "px4-work", output=work / "px4.log")
    px4.start()
    try:
        if not px4.wait_ready(90.0):
            raise SystemExit("px4 legs: PX4 not ready within 90 s")
        m = mavutil.mavlink_connection(f"udpin:127.0.0.1:{px4.api_port}", source_system=255)
        m.wait_heartbeat(timeout=30)
        params = {}
        for name in PARAMS:
            m.mav.param_request_read_send(m.target_system, m.target_component, name.encode(), -1)
            msg = m.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
            while msg is not None and msg.param_id != name:
                msg = m.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
            params[name] = None if msg is None else msg.param_value
        _cmd_long(m, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                  mavutil.mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50000 / speed)
        gp = m.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=10)
        home = Origin(gp.lat * 1e-7, gp.lon * 1e-7, gp.alt * 1e-3)
        _cmd_long(m, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        time.sleep(1.0)
        _cmd_long(m, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, math.nan, 0, 0, math.nan, math.nan, math.nan,
                  home.alt_m + HEIGHT_M)
        climbed = False
        t_takeoff_ms = None
        while True:
            lp = m.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=10)
            if lp is None:
                raise SystemExit("px4 legs: no LOCAL_POSITION_NED")
            t_takeoff_ms = lp.time_boot_ms if t_takeoff_ms is None else t_takeoff_ms
            if lp.time_boot_ms - t_takeoff_ms > 120_000:
                raise SystemExit(f"px4 legs: not at {HEIGHT_M:g} m after 120 s (at {-lp.z:.1f} m)")
            if -lp.z > HEIGHT_M - 1.0 and abs(lp.vz) < 0.1:
                break
            if not climbed and -lp.z > 1.5 and abs(lp.vz) < 0.1:  # takeoff done below HEIGHT_M
                climbed = True
                m.mav.command_int_send(m.target_system, m.target_component, mavutil.mavlink.MAV_FRAME_GLOBAL_INT,
                                       mavutil.mavlink.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, math.nan,
                                       round(home.lat_deg * 1e7), round(home.lon_deg * 1e7),
                                       home.alt_m + HEIGHT_M)
        t_end = lp.time_boot_ms + 3000
        while lp.time_boot_ms < t_end:
            lp = m.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=10)
        p0 = np.array([lp.y, lp.x])  # ENU from PX4's local NED
        _cmd_long(m, mavutil.mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, speed_mps, -1)
        out = []
        for length, tgt in zip(legs, _leg_targets(legs), strict=True):
            tgt_abs = p0 + tgt
            lat, lon, _ = home.enu_to_lla(np.array([tgt_abs[0], tgt_abs[1], 0.0]))
            m.mav.command_int_send(m.target_system, m.target_component, mavutil.mavlink.MAV_FRAME_GLOBAL_INT,
                                   mavutil.mavlink.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, math.nan,
                                   round(lat * 1e7), round(lon * 1e7), home.alt_m + HEIGHT_M)
            ts, ps = [], []
            t0 = None
            quiet = 0
            while True:
                lp = m.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=10)
                if lp is None:
                    raise SystemExit("px4 legs: no LOCAL_POSITION_NED")
                t0 = lp.time_boot_ms if t0 is None else t0
                ts.append(lp.time_boot_ms * 1e-3)
                ps.append([lp.y, lp.x])
                moved = math.hypot(lp.y - ps[0][0], lp.x - ps[0][1]) > 0.8 * length
                close = moved and math.hypot(lp.vx, lp.vy) < 0.05
                quiet = quiet + 1 if close else 0
                if quiet > 20 or lp.time_boot_ms - t0 > (60 + length / 2) * 1e3:
                    break
            # PX4's local origin is near, not at, `home`: where it came to rest is the target
            out.append(leg_figures(np.array(ts), np.array(ps), np.array(ps[-1]), length))
            if dump is not None:
                np.savez(dump / f"px4_leg_{length:g}.npz", t_s=np.array(ts), pos_m=np.array(ps))
        return out, params
    finally:
        px4.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--legs", type=float, nargs="+", default=[15.0, 40.0, 80.0, 300.0])
    ap.add_argument("--speed-mps", type=float, default=10.0, help="commanded ground speed (DO_CHANGE_SPEED)")
    ap.add_argument("--speed", type=float, default=4.0, help="PX4 speed factor (default 4)")
    ap.add_argument("--instance", type=int, default=1)
    ap.add_argument("--builtin-only", action="store_true")
    ap.add_argument("--dump", type=Path, metavar="DIR", help="save PX4's per-leg (t, position) here (.npz)")
    args = ap.parse_args(argv)
    builtin = run_builtin(args.legs, args.speed_mps)
    if args.builtin_only:
        px4, params = [None] * len(args.legs), {}
    else:
        with tempfile.TemporaryDirectory(prefix="uavloc-bench-legs-") as tmp:
            px4, params = run_px4(args.legs, args.speed_mps, args.speed, args.instance, Path(tmp), args.dump)
        print("PX4 parameters: " + ", ".join(f"{k}={v:g}" for k, v in params.items() if v is not None))
    print(f"legs at {args.speed_mps:g} m/s commanded (PX4 SITL = baseline, ratio built-in / PX4)")
    print(f"{'leg [m]':>8s} {'figure':22s}{'PX4 SITL':>10s}{'built-in':>10s}{'ratio':>8s}")
    for length, a, b in zip(args.legs, px4, builtin, strict=True):
        for label, key in (("peak speed [m/s]", "peak"), ("p99 speed [m/s]", "p99"),
                           ("time to settle [s]", "settle_s"), ("leg / time [m/s]", "mean"),
                           ("overshoot [m]", "overshoot")):
            va = a[key] if a else float("nan")
            r = b[key] / va if va and np.isfinite(va) else float("nan")
            print(f"{length:8.0f} {label:22s}{va:10.2f}{b[key]:10.2f}{r:8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
