"""The reliability soak (issue 21): nothing raises over a wide family of worlds, in fast and full mode.

    python benchmarks/soak.py                       # 300 fast runs + 12 full runs (benchmarks/soak.toml)
    python benchmarks/soak.py --fast 20 --full 2    # the first 20 / 2 worlds of the family
    python benchmarks/soak.py --workers 2 --out soak-out   # an existing folder resumes

The campaign `benchmarks/soak.toml` (1–12 users, fences 60–250 m with notches, 0–5 buildings up to
40 m, NLoS excess up to 40 m, GPS σ 0.3–3 m and τ 0–600 s, UE clock sawtooths up to 20 m, budget
4000 m; lawnmower, greedy, casadi) in fast mode over its first `--fast` worlds, and the same family's
first `--full` worlds in full mode (the built-in MAVLink vehicle and the simulated gNB, as `uavloc
sim` flies them), both through `uavloc campaign`'s code with the mission's estimator. Printed per
mode and planner:

- runs; raised: runs that raised (status "error", the traceback in the results); estimator raised:
  runs whose estimator failed inside and the mission went on without it (the online part dropped,
  a refresh or final solve failed: the `estimator_errors` column);
- reached: runs that ended on the mission's stop rule (every user's 95 % bound within the target
  radius) before the budget;
- inside own bound: users (of the runs that did not raise) whose final true error lies within
  their own final 95 % bound, and the median over runs of the share of estimates inside their
  ellipse during the run.

Exit status 1 when anything raised (either kind), else 0.
"""

from __future__ import annotations

import argparse
import copy
import logging
import math
import sys
import tempfile
import tomllib
from pathlib import Path

import numpy as np

_HERE = Path(__file__).resolve().parent
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from sitl_scenarios.campaign import Campaign, quiet_logs, run_campaign, spec_from_dict  # noqa: E402

SPEC = _HERE / "soak.toml"
#: full mode: simulated seconds per wall second, and the planners it flies
FULL_SPEEDUP = 40.0
FULL_PLANNERS = ("lawnmower", "greedy", "casadi")


def soak_campaigns(n_fast: int, n_full: int, spec: Path = SPEC) -> list[Campaign]:
    """The soak's campaigns: the spec's family over its first n_fast worlds in fast mode and its
    first n_full worlds in full mode (a count of 0 leaves that campaign out)."""
    data = tomllib.loads(spec.read_text(encoding="utf-8"))
    out = []
    if n_fast > 0:
        fast = copy.deepcopy(data)
        fast["families"][0]["count"] = n_fast
        out.append(spec_from_dict(fast, str(spec)))
    if n_full > 0:
        full = copy.deepcopy(data)
        full["campaign"].update(name=f"{data['campaign']['name']}-full", mode="full", speedup=FULL_SPEEDUP,
                                planners=list(FULL_PLANNERS))
        full["families"][0]["count"] = max(1, math.ceil(n_full / len(FULL_PLANNERS)))
        campaign = spec_from_dict(full, str(spec))
        out.append(Campaign(campaign.name, campaign.path, campaign.section, campaign.runs[:n_full]))
    return out


def reached(rec: dict) -> bool:
    """The run ended on the mission's stop rule (fast mode: 'target reached'; full: 'target_reached: ...')."""
    return rec["status"] == "ok" and rec["end"].split(":")[0].replace("_", " ") == "target reached"


def soak_rows(records: list[dict]) -> list[dict]:
    """Per (mode, planner) and for all: runs, raised, estimator raised, reached, users inside their
    own final 95 % bound (of the located users of the runs that did not raise), median inside95."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in records:
        groups.setdefault((r["mode"], r["planner"]), []).append(r)
    for mode in dict.fromkeys(r["mode"] for r in records):
        groups[(mode, "all")] = [r for r in records if r["mode"] == mode]
    rows = []
    for (mode, planner), rs in sorted(groups.items(), key=lambda kv: (kv[0][0] != "fast", kv[0][1] == "all")):
        ok = [r for r in rs if r["status"] == "ok"]
        err = np.array([e for r in ok for e in r["final_error_m"]], float)
        bnd = np.array([b for r in ok for b in r["final_bound95_m"]], float)
        located = np.isfinite(err) & np.isfinite(bnd)
        in95 = [r["inside95"] for r in ok if r["inside95"] is not None and math.isfinite(r["inside95"])]
        rows.append({
            "mode": mode, "planner": planner, "runs": len(rs), "raised": len(rs) - len(ok),
            "estimator_raised": sum(1 for r in ok if (r.get("estimator_errors") or 0) > 0),
            "reached": sum(reached(r) for r in ok),
            "users": int(err.size), "located": int(np.sum(located)),
            "inside_own_bound": int(np.sum(err[located] <= bnd[located])),
            "inside95_median": float(np.median(in95)) if in95 else math.nan,
        })
    return rows


def format_rows(rows: list[dict]) -> str:
    head = (f"{'mode':<5} {'planner':<10} {'runs':>5} {'raised':>6} {'est.raised':>10} {'reached':>8} "
            f"{'inside own bound (final)':>26} {'in95 median':>11}")
    lines = [head, "-" * len(head)]
    for r in rows:
        share = r["inside_own_bound"] / r["located"] if r["located"] else math.nan
        lines.append(f"{r['mode']:<5} {r['planner']:<10} {r['runs']:>5} {r['raised']:>6} {r['estimator_raised']:>10} "
                     f"{r['reached']:>8} {r['inside_own_bound']:>9}/{r['located']:<5} ({100 * share:5.1f} %) "
                     f"{r['inside95_median']:>11.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fast", type=int, default=100, metavar="N",
                    help="fast mode over the family's first N worlds, every planner of the spec (default 100)")
    ap.add_argument("--full", type=int, default=12, metavar="N", help="N full-mode runs (default 12)")
    ap.add_argument("--workers", type=int, default=None, help="LocalCluster workers (default: one per core; 0: none)")
    ap.add_argument("--scheduler", default=None, help="an existing Dask scheduler instead of a LocalCluster")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one; existing: resume)")
    ap.add_argument("-v", "--verbose", action="store_true", help="the campaign's and Dask's INFO lines")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not args.verbose:
        # what the runs log is counted and listed below, not printed as it happens
        quiet_logs(logging.CRITICAL, logging.CRITICAL)
    records: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="uavloc-soak-", dir=None) as tmp:
        for campaign in soak_campaigns(args.fast, args.full):
            out = (args.out or Path(tmp)) / campaign.name
            print(f"{campaign.name}: {len(campaign.runs)} {campaign.section.mode}-mode runs -> {out}", flush=True)
            done = run_campaign(campaign, out, scheduler=args.scheduler, workers=args.workers)
            print(f"  {done.ran} run now on {done.where} in {done.wall_s:.0f} s, {done.skipped} already done; "
                  f"{done.cost_line()}", flush=True)
            records.extend(done.records)
    rows = soak_rows(records)
    print()
    print(format_rows(rows))
    for r in records:
        if r["status"] != "ok":
            print(f"raised: {r['key']}: {r['error'][:200]}")
        elif r.get("estimator_errors"):
            print(f"estimator raised: {r['key']}: {r['first_estimator_error'][:200]}")
    total = {k: sum(r[k] for r in rows if r["planner"] == "all") for k in ("runs", "raised", "estimator_raised")}
    print(f"\nsoak: {total['runs']} runs, {total['raised']} raised, {total['estimator_raised']} with the estimator "
          f"raising inside: {'PASS' if not (total['raised'] or total['estimator_raised']) else 'FAIL'}")
    return 1 if total["raised"] or total["estimator_raised"] else 0


if __name__ == "__main__":
    sys.exit(main())
