"""Campaign scaling: a campaign of fast-mode runs (the planner benchmark's worlds, the mission's
estimator) on 1 and on 2 local workers and on a Dask scheduler started separately; wall time,
runs per minute (per worker: what one run costs; and over all workers), the speed-up against the
1-worker run measured in the same command, and whether every run's record is identical across them.

    python benchmarks/campaign_scaling.py --start-scheduler     # 200 runs: 1 worker, 2 workers, scheduler
    python benchmarks/campaign_scaling.py --runs 30             # a quick look, LocalClusters only
    python benchmarks/campaign_scaling.py --scheduler tcp://127.0.0.1:8786   # also on that cluster

`--start-scheduler` starts `dask scheduler` on 127.0.0.1:20400 and `dask worker --nworkers 2
--nthreads 1` as processes of their own (this repository first on their path) and stops them at the
end. An external cluster is started separately the same way, e.g. (loopback only):

    dask scheduler --host 127.0.0.1 --port 8786 --dashboard-address 127.0.0.1:8787 &
    dask worker tcp://127.0.0.1:8786 --nworkers 2 --nthreads 1 --host 127.0.0.1 --dashboard-address 127.0.0.1:0 &

The runs are the first `--runs` of the planner benchmark campaign over enough worlds (lawnmower,
greedy, casadi by default). Wall time is from the first submission to the last result (cluster
start-up excluded, printed apart). The setups take turns in rounds (`--rounds`, default 1), so that
all meet the same slow and quiet spells of a shared machine; the speed-up is the ratio of the best
wall time of each setup. Identical records: every column but the timing ones (wall time, plan
compute times, worker) equal, NaN equal to NaN. The machine's load (`os.getloadavg`) is printed
before and after each run: on a shared machine the speed-up is only as good as the cores that were free.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from benchmarks.planner import benchmark_campaign  # noqa: E402
from sitl_scenarios.campaign import TIMING_FIELDS, Campaign, quiet_logs, run_campaign, same_value  # noqa: E402


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


#: the scheduler --start-scheduler starts (this benchmark's ports)
SCHEDULER_PORT = 20400


def start_scheduler(log_dir: Path, n_workers: int = 2) -> tuple[str, list[subprocess.Popen]]:
    """`dask scheduler` and `dask worker` (n_workers single-threaded processes) as processes of their
    own on loopback, this repository first on their path; (address, processes)."""
    dask = str(Path(sys.executable).with_name("dask"))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(_HERE.parent), os.environ.get("PYTHONPATH", "")])}
    address = f"tcp://127.0.0.1:{SCHEDULER_PORT}"
    procs = []
    with open(log_dir / "scheduler.log", "wb") as out:
        procs.append(subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(SCHEDULER_PORT),
                                       "--dashboard-address", f"127.0.0.1:{SCHEDULER_PORT + 1}"],
                                      stdout=out, stderr=subprocess.STDOUT, env=env))
    with open(log_dir / "workers.log", "wb") as out:
        procs.append(subprocess.Popen([dask, "worker", address, "--nworkers", str(n_workers), "--nthreads", "1",
                                       "--host", "127.0.0.1", "--dashboard-address", "127.0.0.1:0"],
                                      stdout=out, stderr=subprocess.STDOUT, env=env))
    return address, procs


def stop_processes(procs: list[subprocess.Popen], grace_s: float = 10.0) -> None:
    """SIGTERM the processes (workers first), SIGKILL what is left after grace_s."""
    for p in reversed(procs):
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in reversed(procs):
        try:
            p.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def scaling_campaign(n_runs: int, planners: tuple[str, ...]) -> Campaign:
    """The first n_runs of the planner benchmark campaign over enough worlds for them."""
    campaign = benchmark_campaign(max(1, -(-n_runs // len(planners))), planners)
    return Campaign(campaign.name, campaign.path, campaign.section, campaign.runs[:n_runs])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=200, help="fast-mode runs per setup (default 200)")
    ap.add_argument("--rounds", type=int, default=1, help="setups take turns this many times; best of each")
    ap.add_argument("--planners", default="lawnmower,greedy,casadi")
    ap.add_argument("--scheduler", default=None, help="also run on this existing cluster, e.g. tcp://127.0.0.1:8786")
    ap.add_argument("--start-scheduler", action="store_true",
                    help=f"also run on a scheduler and 2 workers started here as processes of their own "
                         f"(port {SCHEDULER_PORT})")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    quiet_logs(logging.ERROR, logging.ERROR)
    planners = tuple(p.strip() for p in args.planners.split(",") if p.strip())
    campaign = scaling_campaign(args.runs, planners)
    n_worlds = len({r.scenario.name for r in campaign.runs})
    print(f"campaign: {len(campaign.runs)} fast-mode runs ({n_worlds} worlds x {', '.join(planners)}), "
          f"{os.cpu_count()} cores")
    setups = [("LocalCluster, 1 worker", None, 1), ("LocalCluster, 2 workers", None, 2)]
    procs: list[subprocess.Popen] = []
    with contextlib.ExitStack() as stack:
        if args.start_scheduler:
            log_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="uavloc-scaling-dask-")))
            address, procs = start_scheduler(log_dir)
            stack.callback(stop_processes, procs)
            setups.append((f"scheduler apart {address}", address, None))
        if args.scheduler:
            setups.append((f"scheduler {args.scheduler}", args.scheduler, None))
        walls: dict[str, list[float]] = {label: [] for label, _, _ in setups}
        records: dict[str, list[list[dict]]] = {label: [] for label, _, _ in setups}
        costs: dict[str, list[float]] = {label: [] for label, _, _ in setups}
        for rnd in range(args.rounds):
            for label, scheduler, workers in setups:
                before = _load()
                with tempfile.TemporaryDirectory(prefix="uavloc-scaling-") as tmp:
                    t0 = time.perf_counter()
                    done = run_campaign(campaign, tmp, scheduler=scheduler, workers=workers, progress=False)
                    total = time.perf_counter() - t0
                walls[label].append(done.wall_s)
                records[label].append(done.records)
                costs[label].append(done.runs_per_min_per_worker)
                print(f"round {rnd + 1}  {label:<38} {done.workers} workers  runs {done.wall_s:7.1f} s  (setup "
                      f"{done.setup_s:4.1f} s, all {total:6.1f} s)  {done.runs_per_min:6.2f} runs/min, "
                      f"{done.runs_per_min_per_worker:6.2f} runs/min per worker  failed {done.failed}  "
                      f"[{before} -> {_load()}]", flush=True)
    base_label = setups[0][0]
    base = records[base_label][0]
    print()
    ok = True
    for label, _, _ in setups:
        diffs = [d for recs in records[label] for d in differences(base, recs)]
        best = min(walls[label])
        line = (f"{label:<38} best {best:7.1f} s ({60 * len(base) / best:6.2f} runs/min, "
                f"{max(costs[label]):6.2f} per worker)")
        if label != base_label:
            line += f"   speed-up vs 1 worker {min(walls[base_label]) / best:5.2f}x"
        line += f"   records identical to 1 worker: {'yes' if not diffs else 'NO'} ({len(base)} runs)"
        print(line)
        for d in diffs[:10]:
            print("   ", d)
        ok &= not diffs
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
