"""Fleet size: where a simulated fleet stops scaling on this machine (docs/fleet.md, issue 49).

    python benchmarks/fleet_size.py [--quick] [--speedup 10,20] [--vehicles 1,2,4,8,16] [--users 6]
                                    [--survey-s 40] [--planner greedy]

Each run flies `uavloc sim`'s mission (sitl_scenarios.sim_runner.SimulatedMission) of two_uavs with
N built-in vehicles (each its own simulator thread, MAVSDK server and simulated gNB), a short
survey (`--survey-s` mission seconds at the cruise speed: [flight] budget_m), in a child process under a wall
bound, and prints one row per (speed-up, vehicles):

- wall_s: the run's wall seconds (connect, preflight, take-off, survey, return, landing);
- lag p99: the 99th percentile of the event loop's lag (mission.control.loop) [s];
- r/v/Δ: ranges per vehicle per Δ of flight, measurements / (flown_m / delta_m), flown_m being
  every vehicle's metres together (what each vehicle's gNB gave per keyframe spacing);
- pace: the survey's achieved speed-up over the one asked (1.00: on time);
- the ratios of wall_s, lag and r/v/Δ against the one-vehicle run of the same speed-up, measured in
  the same invocation (the machine's load changes from one invocation to the next).

A run "stops" when it does not end within its bound, ends aborted, never surveys (the time limit
ran out before every vehicle was up), measures nothing, its loop lags more than MAX_LAG_P99_S (99th
percentile), or its survey fell behind its speed-up (pace below
mission.control.config.FELL_BEHIND_SHARE): larger fleets at that speed-up are not run. The last
line is the largest vehicles × speed-up that held, against the limits the CLI enforces
(sitl_scenarios.scenario.MAX_VEHICLE_SPEEDUP, MAX_BUILTIN_VEHICLES).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

# benchmarks/ holds scripts named like packages: the repository root replaces this folder on sys.path
_HERE = Path(__file__).resolve().parent
REPO = _HERE.parent
sys.path[:] = [str(REPO)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]


def scenario_dict(n_vehicles: int, n_users: int, survey_s: float, planner: str) -> dict:
    """two_uavs with `n_vehicles` [[vehicles]], `n_users` users on a ring around the origin, a
    survey of `survey_s` mission seconds."""
    from sitl_scenarios.scenario import SCENARIO_DIR

    d = tomllib.loads((SCENARIO_DIR / "two_uavs.toml").read_text(encoding="utf-8"))
    d["vehicles"] = [{"id": f"uav{i + 1}"} for i in range(n_vehicles)]
    # the users on a ring 90 m around the origin: within a gNB's reach on the ground (~120 m,
    # sitl_scenarios.radio.reach_m), so one vehicle passes its preflight as a fleet does
    users, truth = [], {}
    for k in range(n_users):
        a = 2.0 * np.pi * k / n_users
        uid = f"ue{k + 1}"
        users.append({"id": uid, "rnti": hex(0x4601 + k)})
        truth[uid] = {"east_m": round(90.0 * np.cos(a), 2), "north_m": round(90.0 * np.sin(a), 2)}
    d["users"], d["truth"] = users, truth
    # the survey ends on its budget: survey_s at the cruise speed (the time limit counts from the
    # start, connect and preflight included, which take more mission seconds at a higher speed-up)
    speed = d["vehicle"]["speed_mps"]
    d["flight"] = {**d["flight"], "budget_m": float(survey_s) * speed, "planner": planner}
    return d


def child(args: argparse.Namespace) -> int:
    """One run: print one JSON line with its figures."""
    import asyncio
    import logging

    logging.basicConfig(level=logging.ERROR)
    from sitl_scenarios.scenario import scenario_from_dict
    from sitl_scenarios.sim_runner import SimulatedMission

    sc = scenario_from_dict(scenario_dict(args.n, args.users, args.survey_s, args.planner), "fleet_size")
    out = Path(args.out)

    async def main():
        async with SimulatedMission(sc, out / "mission.jsonl", speedup=args.speedup) as sim:
            return await sim.run()

    t0 = time.monotonic()
    res = asyncio.run(main())
    r = res.result
    delta = sc.mission.flight.delta_m
    # flown_m is every vehicle's metres together: its Δ-steps are each vehicle's summed
    per = r.measurements / (r.flown_m / delta) if r.flown_m > 0 else 0.0
    print(json.dumps({"wall_s": time.monotonic() - t0, "status": r.status, "reason": r.reason,
                      "lag_p99_s": res.loop_lag.get("p99_s", 0.0), "ranges_per_vehicle_per_delta": per,
                      "pace": None if res.pace is None else res.pace.achieved_speedup / res.pace.requested_speedup,
                      "fell_behind": bool(res.pace is not None and res.pace.fell_behind)}))
    return 0


def one_run(n: int, speedup: float, users: int, survey_s: float, planner: str, bound_s: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="fleet_size-") as tmp:
        cmd = [sys.executable, __file__, "--child", "--n", str(n), "--speedup-one", str(speedup), "--users",
               str(users), "--survey-s", str(survey_s), "--planner", planner, "--out", tmp]
        env = dict(os.environ, PYTHONPATH=str(REPO))
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env,
                                start_new_session=True)
        try:
            stdout, _ = proc.communicate(timeout=bound_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)
            proc.communicate()
            return {"wall_s": time.monotonic() - t0, "status": "hung", "reason": f"not ended within {bound_s:g} s"}
        lines = [ln for ln in stdout.splitlines() if ln.startswith("{")]
        if proc.returncode != 0 or not lines:
            return {"wall_s": time.monotonic() - t0, "status": "crashed", "reason": f"exit {proc.returncode}"}
        return json.loads(lines[-1])


#: a loop that lags this long [s] (99th percentile) no longer keeps a vehicle's link or its gNB's timeouts
MAX_LAG_P99_S = 1.0


def held(row: dict) -> bool:
    """The run flew its survey, on time, measured, and its loop kept up (MAX_LAG_P99_S)."""
    return (row.get("status") not in ("hung", "crashed", "aborted") and row.get("pace") is not None
            and not row.get("fell_behind", False) and row.get("ranges_per_vehicle_per_delta", 0.0) > 0.0
            and row.get("lag_p99_s", 0.0) <= MAX_LAG_P99_S)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="vehicles 1, 2, 4, 8 at ×20, a 20 s survey")
    p.add_argument("--vehicles", default="1,2,4,8,16")
    p.add_argument("--speedup", default="10,20")
    p.add_argument("--users", type=int, default=6)
    p.add_argument("--survey-s", type=float, default=40.0)
    p.add_argument("--planner", default="greedy", help="the vehicles' planner (greedy: no kernels to compile)")
    p.add_argument("--bound-s", type=float, default=120.0, help="wall bound of one run [s]")
    # the child's own options
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--n", type=int, help=argparse.SUPPRESS)
    p.add_argument("--speedup-one", type=float, help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        args.speedup = args.speedup_one
        return child(args)
    if args.quick:
        args.vehicles, args.speedup, args.survey_s, args.bound_s = "1,2,4,8", "20", 20.0, 90.0
    from sitl_scenarios.scenario import MAX_BUILTIN_VEHICLES, MAX_VEHICLE_SPEEDUP

    fleet = [int(x) for x in args.vehicles.split(",")]
    speedups = [float(x) for x in args.speedup.split(",")]
    print(f"# {os.cpu_count()} cores, load {' '.join(f'{x:.2f}' for x in os.getloadavg())}; users {args.users}, "
          f"survey {args.survey_s:g} s, planner {args.planner}, bound {args.bound_s:g} s per run")
    print(f"{'speedup':>7} {'vehicles':>8} {'wall_s':>7} {'lag_p99':>8} {'r/v/Δ':>6} {'pace':>5} "
          f"{'wall×':>6} {'lag×':>6} {'r/v/Δ×':>7}  status")
    best = 0.0
    for s in speedups:
        base: dict | None = None
        for n in fleet:
            row = one_run(n, s, args.users, args.survey_s, args.planner, args.bound_s)
            if n == fleet[0]:
                base = row

            def ratio(key: str, row=row, base=base) -> str:
                a, b = row.get(key), (base or {}).get(key)
                return f"{a / b:6.2f}" if isinstance(a, float) and isinstance(b, float) and b > 0 else f"{'-':>6}"

            pace = row.get("pace")
            print(f"{s:7g} {n:8d} {row['wall_s']:7.1f} {row.get('lag_p99_s', float('nan')):8.3f} "
                  f"{row.get('ranges_per_vehicle_per_delta', float('nan')):6.2f} "
                  f"{'-' if pace is None else f'{pace:.2f}':>5} {ratio('wall_s')} {ratio('lag_p99_s')} "
                  f" {ratio('ranges_per_vehicle_per_delta')}  {row['status']}: {row.get('reason', '')[:60]}",
                  flush=True)
            if not held(row):
                print(f"# stops at {n} vehicles × {s:g}", flush=True)
                break
            best = max(best, n * s)
    print(f"# largest vehicles × speed-up that held: {best:g}; the CLI's limits: vehicles × speed-up <= "
          f"{MAX_VEHICLE_SPEEDUP:g} (MAX_VEHICLE_SPEEDUP), at most {MAX_BUILTIN_VEHICLES} vehicles")
    return 0


if __name__ == "__main__":
    sys.exit(main())
