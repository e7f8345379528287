"""Campaign scaling: the planner benchmark campaign on 1 and on 2 local workers (and optionally on an
existing Dask cluster), wall time, speed-up against the 1-worker run measured in the same command,
and whether every run's record is identical across them.

    python benchmarks/campaign_scaling.py                       # 4 scenarios × lawnmower, greedy, casadi
    python benchmarks/campaign_scaling.py --scenarios 30 --planners lawnmower,circle,random,greedy,casadi,oracle
    python benchmarks/campaign_scaling.py --scheduler tcp://127.0.0.1:8786   # also on that cluster

The external cluster is started separately, e.g. (from this repository's venv, loopback only):

    dask scheduler --host 127.0.0.1 --port 8786 --dashboard-address 127.0.0.1:8787 &
    dask worker tcp://127.0.0.1:8786 --nworkers 2 --nthreads 1 --host 127.0.0.1 --dashboard-address 127.0.0.1:0 &

Wall time is from the first submission to the last result (cluster start-up excluded, printed
apart). The setups take turns in rounds (`--rounds`, default 3: 1 worker, 2 workers, [cluster], then
again), so that all meet the same slow and quiet spells of a shared machine; the speed-up is the
ratio of the best wall time of each setup, and every round's time is printed. Identical records:
every column but the timing ones (wall time, plan compute times, worker) equal, NaN equal to NaN.
The machine's load (`os.getloadavg`) is printed before and after each run: on a shared machine the
speed-up is only as good as the cores that were free.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from benchmarks.planner import benchmark_campaign  # noqa: E402
from sitl_scenarios.campaign import TIMING_FIELDS, run_campaign, same_value  # noqa: E402


def _load() -> str:
    return "load {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def differences(a: list[dict], b: list[dict]) -> list[str]:
    """Keys and columns where two campaigns' records differ (timing columns left out)."""
    out = []
    bb = {r["key"]: r for r in b}
    for ra in a:
        rb = bb.get(ra["key"])
        if rb is None:
            out.append(f"{ra['key']}: missing")
            continue
        for col in ra:
            if col not in TIMING_FIELDS and not same_value(ra[col], rb[col]):
                out.append(f"{ra['key']}: {col} {ra[col]!r} != {rb[col]!r}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", type=int, default=4)
    ap.add_argument("--rounds", type=int, default=3, help="setups take turns this many times; best of each")
    ap.add_argument("--planners", default="lawnmower,greedy,casadi")
    ap.add_argument("--scheduler", default=None, help="also run on this existing cluster, e.g. tcp://127.0.0.1:8786")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    logging.getLogger("distributed").setLevel(logging.ERROR)
    planners = tuple(p.strip() for p in args.planners.split(",") if p.strip())
    campaign = benchmark_campaign(args.scenarios, planners)
    print(f"campaign: {args.scenarios} scenarios × {len(planners)} planners = {len(campaign.runs)} fast-mode runs, "
          f"{os.cpu_count()} cores")
    setups = [("LocalCluster, 1 worker", None, 1), ("LocalCluster, 2 workers", None, 2)]
    if args.scheduler:
        setups.append((f"scheduler {args.scheduler}", args.scheduler, None))
    walls: dict[str, list[float]] = {label: [] for label, _, _ in setups}
    records: dict[str, list[list[dict]]] = {label: [] for label, _, _ in setups}
    for rnd in range(args.rounds):
        for label, scheduler, workers in setups:
            before = _load()
            with tempfile.TemporaryDirectory(prefix="uavloc-scaling-") as tmp:
                t0 = time.perf_counter()
                done = run_campaign(campaign, tmp, scheduler=scheduler, workers=workers, progress=False)
                total = time.perf_counter() - t0
            walls[label].append(done.wall_s)
            records[label].append(done.records)
            cpu = sum(r["wall_s"] for r in done.records)
            print(f"round {rnd + 1}  {label:<38} {done.workers} workers  runs {done.wall_s:7.1f} s  (setup "
                  f"{done.setup_s:4.1f} s, all {total:6.1f} s, sum of run times {cpu:7.1f} s)  failed {done.failed}  "
                  f"[{before} -> {_load()}]", flush=True)
    base_label = setups[0][0]
    base = records[base_label][0]
    print()
    ok = True
    for label, _, _ in setups:
        diffs = [d for recs in records[label] for d in differences(base, recs)]
        line = f"{label:<38} best {min(walls[label]):7.1f} s of {', '.join(f'{w:.1f}' for w in walls[label])}"
        if label != base_label:
            line += f"   speed-up vs 1 worker (best/best) {min(walls[base_label]) / min(walls[label]):5.2f}x"
        line += f"   records identical to round 1 on 1 worker: {'yes' if not diffs else 'NO'} ({len(base)} runs)"
        print(line)
        for d in diffs[:10]:
            print("   ", d)
        ok &= not diffs
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
