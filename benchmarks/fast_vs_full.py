"""Fast mode against full mode (issue 22): do a campaign's figures equal a mission's?

    python benchmarks/fast_vs_full.py                        # five_commercial_ues, seeds 1-20, lawnmower
    python benchmarks/fast_vs_full.py --seeds 5 --planner casadi --scenario three_users_nlos

The same scenario file flown with the same planner and seeds, once in fast mode (kinematic vehicle
and channel) and once in full mode (the built-in MAVLink vehicle and the simulated gNB, as `uavloc
sim`), both through `uavloc campaign`'s code with the mission's estimator. Per mode:

- inside own bound: the share of users (over all runs) whose final true error lies within their
  own final 95 % bound, with its 95 % Wilson interval;
- median final error: the median over users of the final true horizontal error [m], with its
  distribution-free 95 % interval (order statistics of Binomial(n, 1/2));
- metres flown (median), runs that raised.

The two modes agree when each pair of intervals overlaps. Exit status 0 when both agree and
nothing raised, else 1.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy import stats

_HERE = Path(__file__).resolve().parent
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from sitl_scenarios.campaign import quiet_logs, run_campaign, spec_from_dict  # noqa: E402
from sitl_scenarios.scenario import load_scenario, resolve_scenario_path  # noqa: E402

Z95 = 1.959963984540054


def wilson95(k: int, n: int) -> tuple[float, float]:
    """95 % Wilson score interval of a share k / n."""
    if n == 0:
        return math.nan, math.nan
    p = k / n
    half = Z95 * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n))
    centre = p + Z95**2 / (2 * n)
    den = 1 + Z95**2 / n
    return (centre - half) / den, (centre + half) / den


def median95(values: np.ndarray) -> tuple[float, float, float]:
    """(median, lo, hi): the order statistics x_(j) ≤ median ≤ x_(k) that cover it with ≥ 95 %
    (j, k from Binomial(n, 1/2) quantiles), distribution-free."""
    v = np.sort(np.asarray(values, float))
    n = len(v)
    if n == 0:
        return math.nan, math.nan, math.nan
    j = int(stats.binom.ppf(0.025, n, 0.5))
    k = int(stats.binom.isf(0.025, n, 0.5))
    return float(np.median(v)), float(v[max(j - 1, 0)]), float(v[min(k, n - 1)])


def figures(records: list[dict]) -> dict:
    ok = [r for r in records if r["status"] == "ok"]
    err = np.array([e for r in ok for e in r["final_error_m"]], float)
    bnd = np.array([b for r in ok for b in r["final_bound95_m"]], float)
    located = np.isfinite(err) & np.isfinite(bnd)
    k, n = int(np.sum(err[located] <= bnd[located])), int(err.size)  # a user never located is not inside
    return {"runs": len(records), "raised": len(records) - len(ok),
            "estimator_raised": sum(1 for r in ok if (r.get("estimator_errors") or 0) > 0),
            "inside": (k, n, *wilson95(k, n)), "error": median95(err[np.isfinite(err)]),
            "flown_m": float(np.median([r["flown_m"] for r in ok])) if ok else math.nan}


def overlap(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return a[0] <= b[1] and b[0] <= a[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="five_commercial_ues", help="a scenario file or bundled name")
    ap.add_argument("--planner", default="lawnmower")
    ap.add_argument("--seeds", type=int, default=20, help="seeds 1..N in each mode (default 20)")
    ap.add_argument("--speedup", type=float, default=20.0, help="full mode: simulated seconds per wall second")
    ap.add_argument("--workers", type=int, default=None, help="LocalCluster workers (default: one per core; 0: none)")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)
    if not args.verbose:
        quiet_logs(logging.CRITICAL, logging.CRITICAL)
    sc = load_scenario(resolve_scenario_path(args.scenario))
    result = {}
    with tempfile.TemporaryDirectory(prefix="uavloc-fast-vs-full-") as tmp:
        for mode in ("fast", "full"):
            spec = {"campaign": {"name": f"fast-vs-full-{mode}", "mode": mode, "seeds": list(range(1, args.seeds + 1)),
                                 "planners": [args.planner], "targets_m": [sc.mission.flight.target_radius_m],
                                 "speedup": args.speedup},
                    "scenarios": [{"file": args.scenario}]}
            done = run_campaign(spec_from_dict(spec, "fast_vs_full"), Path(tmp) / mode, workers=args.workers)
            result[mode] = figures(done.records)
            print(f"{mode}: {done.ran} runs on {done.where} in {done.wall_s:.0f} s; {done.cost_line()}", flush=True)
    print(f"\n{sc.name}, {args.planner}, seeds 1-{args.seeds}")
    print(f"{'mode':<5} {'runs':>4} {'raised':>6} {'est.raised':>10} {'inside own bound [95 %]':>32} "
          f"{'median final error m [95 %]':>30} {'flown m':>8}")
    for mode, f in result.items():
        k, n, lo, hi = f["inside"]
        med, elo, ehi = f["error"]
        print(f"{mode:<5} {f['runs']:>4} {f['raised']:>6} {f['estimator_raised']:>10} {k:>5}/{n:<4} "
              f"{k / max(n, 1):5.2f} [{lo:.2f}, {hi:.2f}]       {med:8.2f} [{elo:5.2f}, {ehi:5.2f}]        "
              f"{f['flown_m']:8.0f}")
    fa, fu = result["fast"], result["full"]
    share_ok = overlap(fa["inside"][2:], fu["inside"][2:])
    error_ok = overlap(fa["error"][1:], fu["error"][1:])
    clean = not any(f["raised"] or f["estimator_raised"] for f in result.values())
    print(f"\ninside own bound: intervals {'overlap (agree)' if share_ok else 'DISJOINT'}; median final error: "
          f"intervals {'overlap (agree)' if error_ok else 'DISJOINT'}; {'nothing raised' if clean else 'RAISED'}")
    return 0 if share_ok and error_ok and clean else 1


if __name__ == "__main__":
    sys.exit(main())
