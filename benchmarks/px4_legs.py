"""The recorded legs flight on the user's PX4 SITL, on the built-in vehicle and as recorded, side by side.

    UAVLOC_PX4=.../PX4-Autopilot/build/px4_sitl_default \\
        python benchmarks/px4_legs.py [--speed 4] [--instance 1] [--builtin-speedup 8] [--keep DIR]

All three fly the recorded procedure of `../shared/data/px4-v1.18-sih/legs` (sitl_scenarios.
px4_conformance.fly_legs: take-off to 20 m, DO_CHANGE_SPEED 10 m/s, DO_REPOSITION legs of 15 m
east, 40 m north, 80 m east, 300 m north from rest, RTL), and each one's telemetry log is measured
by the same code (legs_figures): the take-off climb, per leg the peak / p99 ground speed, stop and
settle time and overshoot, the RTL. Columns: the recording (tests/data/px4_figures.json), the
user's PX4 SITL (`--speed` factor; left out with `--builtin-only` or when UAVLOC_PX4 is unset) and
the built-in vehicle over MAVLink at `--builtin-speedup`; ratio = built-in / live PX4 (or / the
recording without one). Also PX4's parameters that shape the legs.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

_HERE = Path(__file__).resolve().parent
REPO = _HERE.parent
sys.path[:] = [str(REPO)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from pymavlink import mavutil  # noqa: E402

from sitl_scenarios.px4_conformance import RECORDED_HOME, fly_builtin, fly_legs, legs_figures  # noqa: E402
from sitl_scenarios.px4_sitl import Px4Sitl, build_from_env, instance_busy, missing_requirement  # noqa: E402

PARAMS = ("MPC_ACC_HOR", "MPC_ACC_HOR_MAX", "MPC_JERK_AUTO", "MPC_JERK_MAX", "MPC_XY_CRUISE",
          "MPC_XY_VEL_MAX", "NAV_ACC_RAD", "MPC_XY_TRAJ_P", "MPC_XY_ERR_MAX", "MPC_XY_P", "MPC_TKO_SPEED",
          "MPC_Z_V_AUTO_UP", "RTL_RETURN_ALT")
RECORDED = REPO / "tests" / "data" / "px4_figures.json"


def _params(conn) -> dict[str, float | None]:
    out = {}
    for name in PARAMS:
        conn.mav.param_request_read_send(conn.target_system, conn.target_component, name.encode(), -1)
        msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
        while msg is not None and msg.param_id != name:
            msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
        out[name] = None if msg is None else msg.param_value
    return out


def run_px4(speed: float, instance: int, work: Path) -> tuple[dict, dict]:
    """The legs flight on the user's PX4 SITL (SIH, at the recorded home): (figures, parameters)."""
    build = build_from_env()
    why = missing_requirement(build)
    if why is not None:
        raise SystemExit(f"px4 legs: {why}")
    while instance_busy(instance):
        instance += 1
    px4 = Px4Sitl(build, instance, speed, work / "px4-work", home=RECORDED_HOME, output=work / "px4.log")
    px4.start()
    try:
        if not px4.wait_ready(90.0):
            raise SystemExit("px4 legs: PX4 not ready within 90 s:\n" + "".join(px4.lines[-10:]))
        conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{px4.api_port}", source_system=255, dialect="common")
        conn.wait_heartbeat(timeout=30)
        params = _params(conn)
        with open(work / "px4_legs.tlog", "wb") as fh:
            fly_legs(conn, timeout_s=300.0, tlog=fh)
        conn.close()
        return legs_figures(work / "px4_legs.tlog"), params
    finally:
        px4.stop()


def _rows(fig: dict | None) -> dict[str, float]:
    if fig is None:
        return {}
    out = {f"take-off {k}": v for k, v in fig["takeoff"].items()}
    for name, leg in zip(("15 m E", "40 m N", "80 m E", "300 m N"), fig["legs"], strict=True):
        out.update({f"leg {name} {k}": v for k, v in leg.items() if k != "mean"})
    out.update({f"RTL {k}": v for k, v in fig["rtl"].items()})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, default=4.0, help="PX4 speed factor (default 4)")
    ap.add_argument("--instance", type=int, default=1)
    ap.add_argument("--builtin-speedup", type=float, default=8.0)
    ap.add_argument("--builtin-only", action="store_true", help="no live PX4: the recording is the baseline")
    ap.add_argument("--keep", type=Path, metavar="DIR", help="keep the telemetry logs here")
    args = ap.parse_args(argv)
    recorded = json.loads(RECORDED.read_text())["legs"]
    with tempfile.TemporaryDirectory(prefix="uavloc-bench-legs-") as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        live, params = (None, {})
        if not args.builtin_only:
            live, params = run_px4(args.speed, args.instance, work)
        builtin = legs_figures(fly_builtin("legs", work / "builtin_legs.tlog", speedup=args.builtin_speedup))
    if params:
        print("PX4 parameters: " + ", ".join(f"{k}={v:g}" for k, v in params.items() if v is not None))
    rec, px4, b = _rows(recorded), _rows(live), _rows(builtin)
    base = "live PX4" if live else "the recording"
    print(f"recorded legs flight (ratio = built-in / {base})")
    print(f"{'figure':34s}{'recorded':>10s}{'PX4 SITL':>10s}{'built-in':>10s}{'ratio':>8s}")
    for key, v in b.items():
        p = px4.get(key, float("nan"))
        ref = p if live else rec[key]
        print(f"{key:34s}{rec[key]:10.2f}{p:10.2f}{v:10.2f}{v / ref if ref else float('nan'):8.2f}")
    print(f"modes: built-in {'=' if builtin['modes'] == recorded['modes'] else '!='} recorded"
          + (f", live PX4 {'=' if live['modes'] == recorded['modes'] else '!='} recorded" if live else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
