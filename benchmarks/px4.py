"""The same mission on real PX4 SITL and on the built-in vehicle, side by side.

    UAVLOC_PX4=.../PX4-Autopilot/build/px4_sitl_default \
        python benchmarks/px4.py [--scenario three_users_nlos] [--seed N] [--speed 4] [--instance 1]

One scenario and seed, flown twice by the same controller: against the user's PX4 SITL build
(`UAVLOC_PX4`, SIH quadrotor, speed factor `--speed`, started as `make px4_sitl sihsim_quadx` does,
see sitl_scenarios.px4_sitl) and against the built-in vehicle (sitl_scenarios.vehicle) at the same
speed factor. Per run: status, survey metres flown, measurements per metre, cruise speed (the top
ground speed reached on the survey legs: 99th percentile of the horizontal ground speed while
surveying, from the log's telemetry) and the mean survey ground speed, RTL height
(highest point above home after the RTL command), each user's error and 95 % bound, mission and
wall time. The last column is the ratio built-in / PX4 (PX4 is the baseline); PASS/FAIL lines say
whether the two agree within 20 % on measurements per metre, cruise speed and RTL height.
Exit code 0 when all three agree, 1 otherwise.
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import sys
import tempfile
import time
from pathlib import Path

# benchmarks/ holds scripts named like packages (planner.py): the repository root replaces this
# folder on sys.path so that imports find the packages
_HERE = Path(__file__).resolve().parent
REPO = _HERE.parent
sys.path[:] = [str(REPO)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

import numpy as np  # noqa: E402

from mission.log import read_mission_log  # noqa: E402
from sitl_scenarios.px4_sitl import Px4Sitl, build_from_env, instance_busy, missing_requirement  # noqa: E402
from sitl_scenarios.scenario import load_scenario  # noqa: E402
from sitl_scenarios.sim_runner import SimulatedMission  # noqa: E402

#: relative agreement asked of the built-in vehicle against PX4
TOLERANCE = 0.20


def flight_figures(log_path: Path) -> dict:
    """Cruise speed and RTL height from a mission log.

    cruise_mps: 99th percentile of the horizontal ground speed ‖(v_n, v_e)‖ of the telemetry
    between the first and the last `rtt` record (the survey): the speed legs are flown at once
    accelerated; mean_mps: its mean (accelerating, braking and hovering to replan included);
    rtl_height_m: highest telemetry point above the origin (home) after the `rtl` event (NaN
    without one).
    """
    mlog = read_mission_log(log_path)
    t, alt = mlog.tel_t_s, mlog.tel_lla[:, 2]
    vel = mlog.tel_vel_ned_mps if mlog.tel_vel_ned_mps is not None else np.full((len(t), 3), np.nan)
    v = np.hypot(vel[:, 0], vel[:, 1])  # NaN where a record has no velocity
    rtt_t = mlog.rtt_t_s
    t_rtl = next((e["t"] for e in mlog.events if e.get("kind") == "rtl"), None)
    origin = mlog.header.origin
    survey = (t >= rtt_t.min()) & (t <= rtt_t.max()) & np.isfinite(v) if len(rtt_t) else np.zeros(len(t), bool)
    cruise = float(np.percentile(v[survey], 99)) if survey.any() else float("nan")
    mean = float(np.mean(v[survey])) if survey.any() else float("nan")
    after = t >= t_rtl if t_rtl is not None else np.zeros(len(t), bool)
    rtl_height = float(np.max(alt[after]) - origin.alt_m) if after.any() else float("nan")
    return {"cruise_mps": cruise, "mean_mps": mean, "rtl_height_m": rtl_height}


async def fly(scenario, seed: int, log_path: Path, connect: str | None, speedup: float) -> dict:
    t0 = time.monotonic()
    async with SimulatedMission(scenario, log_path, seed=seed, speedup=speedup, connect=connect) as sim:
        result = await sim.run()
    wall_s = time.monotonic() - t0
    fig = flight_figures(log_path)
    err = result.error_m()
    bound = result.estimate.error_bound_95_m() if result.estimate is not None else None
    return {"status": result.status, "flown_m": result.flown_m, "measurements": result.measurements,
            "meas_per_m": result.measurements / result.flown_m if result.flown_m > 0 else float("nan"),
            "cruise_mps": fig["cruise_mps"], "mean_mps": fig["mean_mps"], "rtl_height_m": fig["rtl_height_m"],
            "error_m": None if err is None else [float(x) for x in err],
            "bound95_m": None if bound is None else [float(x) for x in bound],
            "mission_s": result.result.duration_s, "wall_s": wall_s, "users": result.result.user_ids}


def run_px4(scenario, seed: int, speed: float, instance: int, work: Path) -> dict:
    build = build_from_env()
    why = missing_requirement(build)
    if why is not None:
        raise SystemExit(f"px4 benchmark: {why}")
    while instance_busy(instance):
        instance += 1
    px4 = Px4Sitl(build, instance, speed, work / "px4-work", output=work / "px4.log")
    px4.start()
    try:
        if not px4.wait_ready(90.0):
            raise SystemExit("px4 benchmark: PX4 did not print 'Ready for takeoff!' within 90 s:\n"
                             + "".join(px4.lines[-10:]))
        return asyncio.run(fly(scenario, seed, work / "px4.jsonl", px4.api_url, 1.0))
    finally:
        px4.stop()


def _fmt(x, spec: str = ".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="three_users_nlos")
    ap.add_argument("--seed", type=int, help="default: the scenario's")
    ap.add_argument("--speed", type=float, default=4.0, help="PX4 speed factor and built-in speedup (default 4)")
    ap.add_argument("--instance", type=int, default=1, help="PX4 instance (the next free one is taken)")
    ap.add_argument("--keep", type=Path, metavar="DIR", help="keep both mission logs and PX4's output here")
    args = ap.parse_args(argv)
    sc = load_scenario(args.scenario)
    seed = sc.seed if args.seed is None else args.seed
    with tempfile.TemporaryDirectory(prefix="uavloc-bench-px4-") as tmp:
        work = Path(tmp)
        px4 = run_px4(sc, seed, args.speed, args.instance, work)
        builtin = asyncio.run(fly(sc, seed, work / "builtin.jsonl", None, args.speed))
        if args.keep is not None:
            args.keep.mkdir(parents=True, exist_ok=True)
            for name in ("px4.jsonl", "builtin.jsonl", "px4.log"):
                shutil.copy(work / name, args.keep / name)

    print(f"scenario {sc.name}, seed {seed}, speed factor {args.speed:g} (PX4 SITL = baseline)")
    print(f"{'':24s}{'PX4 SITL':>15s}{'built-in':>15s}{'ratio':>9s}")
    rows = [("status", "status", None), ("metres flown", "flown_m", ".1f"),
            ("measurements", "measurements", "d"), ("measurements per m", "meas_per_m", ".3f"),
            ("cruise speed [m/s]", "cruise_mps", ".2f"), ("mean survey speed [m/s]", "mean_mps", ".2f"),
            ("RTL height [m]", "rtl_height_m", ".1f"),
            ("mission time [s]", "mission_s", ".1f"), ("wall time [s]", "wall_s", ".1f")]
    for label, key, spec in rows:
        a, b = px4[key], builtin[key]
        if spec is None:
            print(f"{label:24s}{a:>15s}{b:>15s}")
            continue
        ratio = b / a if isinstance(a, int | float) and a else float("nan")
        print(f"{label:24s}{_fmt(a, spec):>15s}{_fmt(b, spec):>15s}{_fmt(ratio, '.2f'):>9s}")
    for k, user in enumerate(px4["users"]):
        for what, key in (("error", "error_m"), ("95 % bound", "bound95_m")):
            a = px4[key][k] if px4[key] else None
            b = builtin[key][k] if builtin[key] else None
            print(f"{user + ' ' + what + ' [m]':24s}{_fmt(a):>15s}{_fmt(b):>15s}")
    ok = True
    for label, key in (("measurements per metre", "meas_per_m"), ("cruise speed", "cruise_mps"),
                       ("RTL height", "rtl_height_m")):
        a, b = px4[key], builtin[key]
        rel = abs(b - a) / abs(a) if a else float("inf")
        good = bool(np.isfinite(rel) and rel <= TOLERANCE)
        ok &= good
        print(f"{'PASS' if good else 'FAIL'}: {label} agrees within {TOLERANCE:.0%} "
              f"(PX4 {_fmt(a, '.3f')}, built-in {_fmt(b, '.3f')}, difference {_fmt(100 * rel, '.1f')} %)")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
