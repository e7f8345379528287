"""Honesty under load: the same missions on an idle machine and with every core kept busy.

    python benchmarks/load.py                      # the whole table (issue 48): long, hours at ×1
    python benchmarks/load.py --quick              # seeds 1-2 at ×4 and ×10
    python benchmarks/load.py --scenarios paper --seeds 1-3 --speedups 10,20
    python benchmarks/load.py --out runs/        # keeps every run; run again to go on where it stopped

For every scenario × speed-up × seed, `uavloc sim SCENARIO --seed S --speedup X --json --out DIR`
runs twice, one run after the other: on the machine as it is ("idle") and beside 2 × cores busy
loops at nice 0 ("loaded", the companion computer that also runs a gNB). The two runs of a pair
meet the same background load from anything else, so the columns compare like with like.

Per run, from the `--json` document and the mission log it names:

- users inside their own printed 95 % bound (error_m ≤ error_bound_95_m), among those the run
  located (a user with no printed bound, e.g. of a mission that did not take off, claims nothing);
- an honest status: "target_reached" only with every printed bound within the target and every
  error ≤ 1.5 × target (a claim that fails this is counted as `lie`);
- the range residual against the true distance from the logged UAV position,
  C·toa − ‖uav − user‖ [m] (its p99 over the run's ranges; commercial UE sawtooths and NLoS add
  their own share, the same idle and loaded: what load adds is the difference);
- the survey's hover share (hover_s / survey_s) and the achieved speed-up;
- whether the speed-up was kept — the benchmark's own judgement: achieved ≥ 0.8 × asked and a hover
  share ≤ 25 % — against the `fell_behind` the mission said. A run that did not keep its pace and
  did not say so is counted as `unsaid`.

The table gives idle and loaded side by side per scenario and speed-up; the verdicts at the end:
inside their bound ≥ 90 % over all runs (idle and loaded alike), no `lie`, no `unsaid`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

# benchmarks/ holds scripts named like packages (planner.py): the repository root replaces this
# folder on sys.path so that imports find the packages
_HERE = Path(__file__).resolve().parent
REPO = _HERE.parent
sys.path[:] = [str(REPO)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

import numpy as np  # noqa: E402
import pymap3d  # noqa: E402

from sitl_scenarios.px4_sitl import terminate_with_parent  # noqa: E402

C_MPS = 299_792_458.0
SCENARIOS = ("paper", "three_users_nlos", "five_commercial_ues", "two_uavs")
#: the benchmark's own "the speed-up was kept": achieved at least this share of the asked one ...
KEPT_SPEEDUP_SHARE = 0.8
#: ... and the survey hovered at most this share of its time
KEPT_HOVER_SHARE = 0.25
#: "target_reached" must come with every error within this multiple of the target
TARGET_ERROR_FACTOR = 1.5


@dataclass
class Run:
    """One mission's figures (see the module docstring)."""

    scenario: str
    speedup: float
    seed: int
    load: str
    exit_code: int
    wall_s: float
    status: str = "-"
    reason: str = ""
    users: int = 0
    located: int = 0
    inside: int = 0
    lie: bool = False
    residual_p99_m: float = math.nan
    hover_share: float = math.nan
    achieved: float = math.nan
    fell_behind: bool = False
    kept: bool = True
    errors: list[str] = field(default_factory=list)

    @property
    def unsaid(self) -> bool:
        return not self.kept and not self.fell_behind


def range_residuals_m(log_path: Path) -> np.ndarray:
    """C·toa − ‖uav − user‖ [m] of every rtt record of a mission log, against its truth record."""
    truth: dict[str, tuple[float, float, float]] = {}
    rtt: list[dict] = []
    with open(log_path) as fh:
        for line in fh:
            rec = json.loads(line)
            if rec.get("type") == "truth":
                truth = {u["id"]: (u["lat_deg"], u["lon_deg"], u["alt_m"]) for u in rec["users"]}
            elif rec.get("type") == "rtt" and "toa_s" in rec:
                rtt.append(rec)
    out = []
    for rec in rtt:
        if rec["user"] not in truth:
            continue
        lat, lon, alt = truth[rec["user"]]
        u = rec["uav"]
        e, n, up = pymap3d.geodetic2enu(u["lat_deg"], u["lon_deg"], u["alt_m"], lat, lon, alt)
        out.append(C_MPS * rec["toa_s"] - math.sqrt(e * e + n * n + up * up))
    return np.asarray(out, float)


def judge(run: Run, doc: dict, target_m: float) -> None:
    """Fill `run` from the `--json` document of its mission."""
    run.status = doc.get("status", "-")
    run.reason = str(doc.get("reason", ""))
    users = doc.get("users", [])
    run.users = len(users)
    errors = [u.get("error_m") for u in users]
    bounds = [u.get("error_bound_95_m") for u in users]
    # a user without a printed bound (not located, an aborted mission's) makes no claim to judge
    located = [(e, b) for e, b in zip(errors, bounds, strict=True) if e is not None and b is not None
               and math.isfinite(b)]
    run.located = len(located)
    run.inside = sum(1 for e, b in located if e <= b)
    if run.status == "target_reached":
        run.lie = not all(b is not None and b <= target_m + 1e-9 for b in bounds) or not all(
            e is not None and e <= TARGET_ERROR_FACTOR * target_m for e in errors)
    survey_s, hover_s = doc.get("survey_s") or 0.0, doc.get("hover_s") or 0.0
    run.hover_share = hover_s / survey_s if survey_s > 0 else math.nan
    pace = doc.get("speedup") or {}
    run.achieved = float(pace.get("achieved_speedup", math.nan))
    run.fell_behind = bool(pace.get("fell_behind", False))
    run.kept = not (run.achieved < KEPT_SPEEDUP_SHARE * run.speedup
                    or (math.isfinite(run.hover_share) and run.hover_share > KEPT_HOVER_SHARE))
    if doc.get("log") and Path(doc["log"]).exists():
        res = range_residuals_m(Path(doc["log"]))
        if res.size:
            run.residual_p99_m = float(np.percentile(np.abs(res), 99))


def fly(scenario: str, speedup: float, seed: int, load: str, out: Path, timeout_s: float) -> Run:
    """One `uavloc sim` in a subprocess at nice 0."""
    cmd = [sys.executable, "-m", "mission.cli", "sim", scenario, "--seed", str(seed), "--speedup", f"{speedup:g}",
           "--json", "--out", str(out)]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=timeout_s,
                              preexec_fn=terminate_with_parent)
        code, stdout, stderr = proc.returncode, proc.stdout, proc.stderr
    except subprocess.TimeoutExpired as exc:
        code, stdout = -1, ""
        stderr = (exc.stderr or b"").decode(errors="replace") if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        stderr += f"\n(benchmark: no end within {timeout_s:g} s)"
    run = Run(scenario, speedup, seed, load, code, time.perf_counter() - t0)
    try:
        doc = json.loads(stdout) if stdout.strip() else None
    except json.JSONDecodeError:
        doc = None
    if doc is None:
        run.errors.append((stderr.strip().splitlines() or ["no output"])[-1])
        return run
    from sitl_scenarios.scenario import load_scenario

    judge(run, doc, load_scenario(scenario).mission.flight.target_radius_m)
    return run


@contextlib.contextmanager
def busy_loops(n: int):
    """n processes spinning at nice 0 (the other work of a companion computer)."""
    # they die with the benchmark, even when it is killed without running this block's cleanup
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"], preexec_fn=terminate_with_parent)
             for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


#: with --out, every finished run's figures, one JSON line each: a later run with the same --out
#: takes them as done and flies only the rest (the whole table takes hours at ×1)
RESULTS_FILE = "results.jsonl"


def _key(r: Run) -> tuple[str, float, int, str]:
    return r.scenario, r.speedup, r.seed, r.load


def load_results(path: Path) -> dict[tuple[str, float, int, str], Run]:
    """The runs a results file holds, by (scenario, speed-up, seed, load); a damaged line (a run
    killed while writing) is skipped with a word on stderr, and that run is flown again."""
    done: dict[tuple[str, float, int, str], Run] = {}
    if not path.exists():
        return done
    names = {f.name for f in fields(Run)}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        try:
            rec = json.loads(line)
            r = Run(**{k: v for k, v in rec.items() if k in names})
        except (json.JSONDecodeError, TypeError) as exc:
            print(f"{path}:{n}: skipped, not a run's figures ({exc})", file=sys.stderr)
            continue
        done[_key(r)] = r
    return done


def _fly_cells(cells, loads, base: Path, args, runs: list[Run], done: dict, results: Path | None) -> None:
    """Fly every (seed, speed-up, scenario) cell under each load, appending to `runs` and printing
    a line per run; a cell in `done` is taken as it is, a flown one appended to `results`."""
    for seed, x, sc in cells:
        for load in loads:
            out = base / f"{sc}-x{x:g}-s{seed}-{load}"
            r = done.get((sc, x, seed, load))
            if r is None:
                with busy_loops(args.busy if load == "loaded" else 0):
                    r = fly(sc, x, seed, load, out, args.timeout)
                if results is not None:
                    with open(results, "a") as fh:
                        fh.write(json.dumps(asdict(r)) + "\n")
            runs.append(r)
            why = f" ({r.reason[:160]})" if r.status == "aborted" else ""
            words = (f"{r.status}{why}, inside {r.inside}/{r.located} located of {r.users}, "
                     f"res p99 {r.residual_p99_m:.1f} m, "
                     f"hover {100 * r.hover_share:.0f} %, ran ×{r.achieved:.1f}, "
                     f"fell_behind {r.fell_behind}{' LIE' if r.lie else ''}"
                     f"{' UNSAID' if r.unsaid else ''}") if not r.errors else f"exit {r.exit_code}: " \
                f"{r.errors[0]}"
            print(f"  {sc} ×{x:g} seed {seed} {load:<6} ({r.wall_s:.0f} s): {words}", flush=True)


def parse_seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-", 1)
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def summary_rows(runs: list[Run]) -> list[str]:
    keys = sorted({(r.scenario, r.speedup) for r in runs}, key=lambda k: (SCENARIOS.index(k[0])
                                                                          if k[0] in SCENARIOS else 99, k[1]))
    head = (f"{'scenario':<20} {'×':>4} | {'load':<6} {'runs':>4} {'inside':>9} {'reached':>7} {'lie':>3} "
            f"{'res p99 m':>9} {'hover':>6} {'×ran':>6} {'behind':>6} {'unsaid':>6} {'wall s':>7}")
    lines = [head, "-" * len(head)]
    for sc, x in keys:
        for load in ("idle", "loaded"):
            rs = [r for r in runs if r.scenario == sc and r.speedup == x and r.load == load]
            if not rs:
                continue
            users = sum(r.located for r in rs)
            inside = sum(r.inside for r in rs)
            p99 = np.nanmax([r.residual_p99_m for r in rs]) if any(math.isfinite(r.residual_p99_m) for r in rs) \
                else math.nan
            hover = np.nanmedian([r.hover_share for r in rs]) if any(math.isfinite(r.hover_share) for r in rs) \
                else math.nan
            ran = np.nanmedian([r.achieved for r in rs]) if any(math.isfinite(r.achieved) for r in rs) else math.nan
            lines.append(
                f"{sc:<20} {x:>4g} | {load:<6} {len(rs):>4} {f'{inside}/{users}':>9} "
                f"{sum(r.status == 'target_reached' for r in rs):>7} {sum(r.lie for r in rs):>3} {p99:>9.1f} "
                f"{100 * hover:>5.0f}% {ran:>6.1f} {sum(r.fell_behind for r in rs):>6} {sum(r.unsaid for r in rs):>6} "
                f"{np.mean([r.wall_s for r in rs]):>7.0f}")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated (default: the four)")
    ap.add_argument("--seeds", default="1-5", help="e.g. 1-5 or 1,3 (default 1-5)")
    ap.add_argument("--speedups", default="1,4,10", help="comma-separated (default 1,4,10)")
    ap.add_argument("--quick", action="store_true", help="seeds 1-2 at ×4 and ×10")
    ap.add_argument("--busy", type=int, default=2 * (os.cpu_count() or 2), help="busy loops when loaded (2 × cores)")
    ap.add_argument("--loads", default="idle,loaded", help="which conditions (default both, side by side)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="wall seconds one mission may take")
    ap.add_argument("--out", type=Path, help="keep the missions' folders and results.jsonl here; runs already "
                    "there are not flown again (default: a temporary folder)")
    args = ap.parse_args(argv)
    if args.quick:
        args.seeds, args.speedups = "1-2", "4,10"
    scenarios = [s for s in args.scenarios.split(",") if s]
    seeds = parse_seeds(args.seeds)
    speedups = [float(x) for x in args.speedups.split(",")]
    loads = [x for x in args.loads.split(",") if x]
    if any(x not in ("idle", "loaded") for x in loads):
        ap.error("--loads takes idle and/or loaded")
    print(f"{len(scenarios)} scenarios × {len(speedups)} speed-ups × {len(seeds)} seeds × {len(loads)} loads "
          f"({args.busy} busy loops when loaded, {os.cpu_count()} cores); load average now "
          f"{os.getloadavg()[0]:.1f}", flush=True)
    runs: list[Run] = []
    with tempfile.TemporaryDirectory(prefix="uavloc-load-") as tmp:
        base = args.out or Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        results = base / RESULTS_FILE if args.out else None
        done = load_results(results) if results else {}
        if done:
            print(f"{len(done)} runs already in {results}: not flown again", flush=True)
        # seed by seed over every cell: a run cut short still fills the whole table, with fewer seeds
        cells = [(seed, x, sc) for seed in seeds for x in speedups for sc in scenarios]
        # SIGTERM (or Ctrl-C) ends the runs and still prints the table of those done
        signal.signal(signal.SIGTERM, signal.default_int_handler)
        try:
            _fly_cells(cells, loads, base, args, runs, done, results)
        except KeyboardInterrupt:
            print(f"\n(stopped after {len(runs)} runs)", flush=True)
    print()
    print("\n".join(summary_rows(runs)))
    ok = True
    print()
    for load in loads:
        rs = [r for r in runs if r.load == load]
        users, inside = sum(r.located for r in rs), sum(r.inside for r in rs)
        share = inside / users if users else 0.0
        met = share >= 0.9
        ok &= met
        print(f"  [{'PASS' if met else 'FAIL'}] {load}: {inside}/{users} = {100 * share:.0f} % of users inside their "
              f"own 95 % bound among those located (≥ 90 %); {sum(r.status == 'aborted' for r in rs)} runs aborted")
    lies = [r for r in runs if r.lie]
    unsaid = [r for r in runs if r.unsaid]
    failed = [r for r in runs if r.errors]
    print(f"  [{'PASS' if not lies else 'FAIL'}] target_reached only with every bound within the target and every "
          f"error ≤ {TARGET_ERROR_FACTOR:g} × target: {len(lies)} claims that were not")
    print(f"  [{'PASS' if not unsaid else 'FAIL'}] fell_behind said wherever the speed-up was not kept "
          f"(ran < {KEPT_SPEEDUP_SHARE:g} × asked or hover > {100 * KEPT_HOVER_SHARE:.0f} %): {len(unsaid)} unsaid")
    if failed:
        print(f"  [FAIL] {len(failed)} runs gave no result: " + "; ".join(
            f"{r.scenario} ×{r.speedup:g} s{r.seed} {r.load}: {r.errors[0]}" for r in failed[:5]))
    ok = ok and not lies and not unsaid and not failed
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
