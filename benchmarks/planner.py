"""Planner benchmark: metres and mission seconds until the users are located, for every planner (issues 6, 22,
23, 39).

    python benchmarks/planner.py                 # 30 seeded scenarios × 2 conditions, every planner
    python benchmarks/planner.py --quick         # 8 scenarios per condition
    python benchmarks/planner.py --workers 1     # on one core, as before the campaign engine
    python benchmarks/planner.py --scheduler tcp://127.0.0.1:8786   # on an existing Dask cluster

It is the campaign `benchmarks/planner_campaign.toml` (sitl_scenarios.campaign, fast mode: a
kinematic vehicle and channel with the REAL estimator, window 40, and the REAL planners in the
loop), run through the same code as `uavloc campaign`; this script only picks the number of
scenarios and planners, and prints the comparison and its targets. Two conditions on the same
geometry (1–5 users, rectangular or notched fences, no-fly squares, buildings, σ = 3 m, Δ = 2 m,
legs ≤ 60 m, altitude band 15–80 m, cruise 30 m, budget 3000 m):
- "hardware" (the default world, that of the recorded flights): commercial-UE clock sawtooths of
  0–12 m, GPS drifting with τ 40–300 s, NLoS excess behind buildings;
- "ideal": white GPS (σ 1 m), no sawtooth, no NLoS — labelled, next to it.
Ranges come from the simulated gNB's radio model (TA and SRS quantization included), GPS from the
vehicle simulator's error model.

Planners: lawnmower, circle, random, greedy, casadi, casadi_reference (the active planner before its
speed-ups: interpreted kernels, IPOPT from every seed, 60 iterations — the slow baseline, measured
in the same run) and oracle.

Recorded per run: metres flown and mission seconds of the survey (hover included) when the mean
over users of the 95 % error bound (Estimate.error_bound_95_m) first reaches each target (runs that
never do count the 3000 m budget and its seconds at their own pace; the ambiguity flag is not required to be
clear — it flickers with a 40-keyframe window — so
the table also gives the mean true error at the 1.0 m crossing), each plan() call's compute time,
each user's final error and 95 % bound, and constraint violations found by an independent check
(legs sampled every 0.25 m against the fence, no-fly zones, altitude band, distance from home, leg
length), the seconds the vehicle stood waiting for a plan (hover) and the GPS floor (the 95 % bound
the drifting GPS leaves however a run flies, mission.config.gps_floor_m), printed beside each target
as the runs whose floor lies above it.

--distance-noise sets σ(d) = 3 + 0.3·e^(0.01 d) m in half of the scenarios.

--worlds measures what each real effect costs the planners instead (no checks): lawnmower, casadi
and oracle on the hardware scenarios with one effect taken out at a time (GPS drift, sawtooths,
NLoS), with the GPS error held constant over the flight, and in the ideal world to 3.0, 2.0 and
1.5 m. A drifting GPS leaves every user an offset of the track that no geometry removes; the
metres it costs are added to every planner's, so casadi's ratio to lawnmower moves towards 1.

Accuracy targets (mean 95 % bound): 3.0 m, 1.0 m, 0.6 m. The hardware world's bounds level off at
1.5–2.5 m, so its missions stop at 3.0 m and its 1.0 / 0.6 m columns read the budget; the ideal
world's stop at 0.6 m.

Checks: casadi ≤ 0.65 × lawnmower's metres and ≤ 0.75 × its mission seconds at 3.0 m in the
hardware world; ≥ 90 % of users inside
their own 95 % bound at the end for every planner (hardware world); casadi within 1.1 × oracle at
1.0 and 0.6 m (ideal world); casadi's replan median ≤ 30 ms and p95 ≤ 100 ms; casadi's metres within 3 % of
casadi_reference's in each condition; zero violations.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
import tomllib
from pathlib import Path

# this file is benchmarks/planner.py: put the repository root in place of its folder on sys.path so
# that `import planner` is the package, not this script
_HERE = Path(__file__).resolve().parent
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

import numpy as np  # noqa: E402

from sitl_scenarios.campaign import Campaign, quiet_logs, run_campaign, spec_from_dict  # noqa: E402
from sitl_scenarios.campaign.summary import metres_or_budget, seconds_or_survey  # noqa: E402

SPEC = _HERE / "planner_campaign.toml"


def _campaign(data: dict, n_scenarios: int | None, planners: tuple[str, ...] | None) -> Campaign:
    """The campaign of the spec `data` (planner_campaign.toml's, families already chosen) with the
    number of scenarios per family and the planners replaced (None: the spec's)."""
    if n_scenarios is not None:
        for fam in data["families"]:
            fam["count"] = n_scenarios
    if planners is not None:
        data["campaign"]["planners"] = list(planners)
        # the options of the planners left out go with them (a spec refuses options of a planner it
        # does not run)
        if "planner_options" in data:
            data["planner_options"] = {k: v for k, v in data["planner_options"].items() if k in planners}
    return spec_from_dict(data, str(SPEC), base_dir=_HERE, path=SPEC)


def benchmark_campaign(n_scenarios: int | None = None, planners: tuple[str, ...] | None = None,
                       distance_noise: bool = False) -> Campaign:
    """The spec of planner_campaign.toml, with the number of scenarios (per condition) and the
    planners replaced."""
    data = tomllib.loads(SPEC.read_text(encoding="utf-8"))
    if distance_noise:
        for fam in data["families"]:
            fam["distance_noise_share"] = 0.5
    return _campaign(data, n_scenarios, planners)


#: --worlds: the hardware family with one effect changed (name, the family keys replaced)
WORLDS = (
    ("hardware", {}),
    ("no-gps-drift", {"gps_tau_s": 0.0}),
    ("no-sawtooth", {"sawtooth_amplitude_m": 0.0}),
    ("no-nlos", {"nlos_excess_mean_m": 0.0}),
    ("gps-constant", {"gps_tau_s": 1e5}),
)
WORLDS_PLANNERS = ("lawnmower", "casadi", "oracle")
#: --worlds: the targets [m]; the ideal world flies to the last, the others stop at the first
WORLDS_TARGETS_M = (3.0, 2.0, 1.5)


def worlds_campaign(n_scenarios: int | None = None) -> Campaign:
    """The --worlds campaign: the spec's hardware family in each of WORLDS, and its ideal family
    flown to WORLDS_TARGETS_M[-1], with WORLDS_PLANNERS (the same geometry draws in every world)."""
    data = tomllib.loads(SPEC.read_text(encoding="utf-8"))
    fams = {f["name"]: f for f in data["families"]}
    ideal = {**fams["ideal"], "mission": {**fams["ideal"]["mission"], "target_radius_m": WORLDS_TARGETS_M[-1]}}
    data["families"] = [{**fams["hardware"], **changes, "name": name} for name, changes in WORLDS] + [ideal]
    data["campaign"]["targets_m"] = list(WORLDS_TARGETS_M)
    return _campaign(data, n_scenarios, WORLDS_PLANNERS)


def summarise_worlds(records: list[dict]) -> str:
    """The --worlds table: per world and target, each planner's mean metres (the budget when never
    reached), casadi's and oracle's ratios to lawnmower, and the share of users inside their own
    final 95 % bound."""
    ok_recs = [r for r in records if r["status"] == "ok"]
    head = (f"{'world':<14} {'to':>5}" + "".join(f" {p:>10}" for p in WORLDS_PLANNERS)
            + f" {'casadi/lawn':>12} {'oracle/lawn':>12}" + "".join(f" {'in95 ' + p[:6]:>12}" for p in WORLDS_PLANNERS))
    lines = [head, "-" * len(head)]
    worlds = list(dict.fromkeys(r["condition"] for r in records))
    for w in worlds:
        by = {p: [r for r in ok_recs if r["condition"] == w and r["planner"] == p] for p in WORLDS_PLANNERS}
        for i, t in enumerate(WORLDS_TARGETS_M):
            if w != "ideal" and i > 0:
                break  # the hardware worlds stop at the first target
            m = {p: float(np.mean([metres_or_budget(r, i) for r in rs])) if rs else np.nan for p, rs in by.items()}
            row = f"{w:<14} {format(t, 'g') + ' m':>5}" + "".join(f" {m[p]:>10.0f}" for p in WORLDS_PLANNERS)
            row += f" {m['casadi'] / m['lawnmower']:>12.2f} {m['oracle'] / m['lawnmower']:>12.2f}"
            row += "".join(f" {_inside_share(by[p]):>12.2f}" for p in WORLDS_PLANNERS)
            lines.append(row)
    failed = [r for r in records if r["status"] != "ok"]
    lines.append("")
    lines.append("to: the target (mean 95 % bound, as the stop rule reads it); planner columns: mean metres flown "
                 "to it (the 3000 m budget when never); in95: share of users inside their own final 95 % bound. "
                 f"Runs that raised: {len(failed)}")
    for r in failed:
        lines.append(f"  {r['key']}: {r['error']}")
    return "\n".join(lines)


def _inside_share(rs: list[dict]) -> float:
    """Share of users (over runs) whose final true error lies inside their own final 95 % bound."""
    pairs = [(e, b) for r in rs for e, b in zip(r["final_error_m"], r["final_bound95_m"], strict=True)]
    return float(np.mean([e <= b for e, b in pairs])) if pairs else np.nan


def _times_ms(rs: list[dict]) -> np.ndarray:
    return np.array([t for r in rs for t in r["plan_times_s"]]) * 1e3


def _mean(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else np.nan


def _median(values: list[float]) -> float:
    finite = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(finite)) if finite else np.nan


def summarise(records: list[dict], planners: tuple[str, ...], targets_m: tuple[float, ...]) -> tuple[str, bool]:
    """The benchmark's table per condition (means of metres and mission seconds to each target,
    ratios to lawnmower, casadi_reference and oracle, hover seconds, the GPS floor, users inside
    their bound) and its target checks."""
    ok_recs = [r for r in records if r["status"] == "ok"]
    conditions = list(dict.fromkeys(r["condition"] for r in records))
    by = {(c, p): [r for r in ok_recs if r["planner"] == p and r["condition"] == c] for c in conditions
          for p in planners}
    mean = {(c, p, t): float(np.mean([metres_or_budget(r, i) for r in by[(c, p)]])) if by[(c, p)] else np.nan
            for c in conditions for p in planners for i, t in enumerate(targets_m)}
    # mission (survey) seconds to each target, hover included; never reached: the budget's seconds at the run's pace
    mean_s = {(c, p, t): _mean([seconds_or_survey(r, i) for r in by[(c, p)]])
              for c in conditions for p in planners for i, t in enumerate(targets_m)}
    t1 = targets_m[0]
    head = f"{'condition':<9} {'planner':<16}"
    for t in targets_m:
        head += (f" {'reach' + format(t, 'g'):>8} {'m@' + format(t, 'g'):>7} {'/lawn':>6} {'/ref':>6} {'/orac':>6}"
                 f" {'s@' + format(t, 'g'):>7} {'s/lawn':>6} {'flr>' + format(t, 'g'):>7}")
    head += (f" {'hover s':>7} {'floor m':>7} {'err@' + format(t1, 'g'):>7} {'in95':>5} {'med ms':>7} {'p95 ms':>7}"
             f" {'viol':>5}")
    lines = [head, "-" * len(head)]
    for c in conditions:
        for p in planners:
            rs = by[(c, p)]
            times = _times_ms(rs)
            row = f"{c:<9} {p:<16}"
            for i, t in enumerate(targets_m):
                n = sum(np.isfinite(r["metres_to_m"][i]) for r in rs)
                m = mean[(c, p, t)]
                ratios = [m / mean.get((c, q, t), np.nan) for q in ("lawnmower", "casadi_reference", "oracle")]
                row += f" {n:>4}/{len(rs):<3} {m:>7.0f}" + "".join(f" {v:>6.2f}" for v in ratios)
                above = sum(r.get("floor_m", np.nan) > t for r in rs)  # NaN (an old record) counts as not
                s_t = mean_s[(c, p, t)]
                row += f" {s_t:>7.0f} {s_t / mean_s.get((c, 'lawnmower', t), np.nan):>6.2f} {above:>3}/{len(rs):<3}"
            errs = [r["error_at_m"][0] for r in rs if np.isfinite(r["error_at_m"][0])]
            row += (f" {_mean([r.get('hover_s', np.nan) for r in rs]):>7.1f}"
                    f" {_median([r.get('floor_m', np.nan) for r in rs]):>7.2f}")
            row += f" {np.mean(errs) if errs else np.nan:>7.2f} {_inside_share(rs):>5.2f}"
            med, p95 = (np.median(times), np.percentile(times, 95)) if len(times) else (np.nan, np.nan)
            row += f" {med:>7.1f} {p95:>7.1f} {sum(r['violations'] for r in rs):>5}"
            lines.append(row)
    failed = [r for r in records if r["status"] != "ok"]
    lines.append("")
    lines.append(f"m@T: mean metres flown until the mean 95 % error bound ≤ T m as the stop rule reads it (without "
                 f"the NLoS shift no survey shrinks; the 3000 m budget when never); "
                 f"/lawn, /ref, /orac: ratio of mean metres to lawnmower / casadi_reference / oracle; "
                 f"s@T: mean mission seconds of the survey until then, hover included (never: the budget's "
                 f"seconds at the run's own pace); s/lawn: its ratio to lawnmower's; flr>T: runs whose GPS floor "
                 f"(the 95 % bound the GPS "
                 f"error leaves however a run flies) is above T; hover s: mean survey seconds standing while a "
                 f"plan is computed; floor m: median GPS floor over the runs; "
                 f"err@{t1:g}: mean true error [m] at the {t1:g} m crossing; in95: share of users whose final "
                 f"error is inside their own final 95 % bound. Runs that raised: {len(failed)}")
    for r in failed:
        lines.append(f"  {r['key']}: {r['error']}")
    ok = not failed
    checks = []
    hw = "hardware" if "hardware" in conditions else conditions[0]
    if {"casadi", "lawnmower"} <= set(planners):
        ratio = mean[(hw, "casadi", t1)] / mean[(hw, "lawnmower", t1)]
        checks.append((f"{hw}: casadi >= 35 % fewer metres than lawnmower at {t1:g} m", ratio <= 0.65,
                       f"ratio {ratio:.2f}"))
        ratio_s = mean_s[(hw, "casadi", t1)] / mean_s[(hw, "lawnmower", t1)]
        checks.append((f"{hw}: casadi's mission seconds <= 0.75 x lawnmower's at {t1:g} m", ratio_s <= 0.75,
                       f"ratio {ratio_s:.2f} ({mean_s[(hw, 'casadi', t1)]:.0f} s / "
                       f"{mean_s[(hw, 'lawnmower', t1)]:.0f} s)"))
    for p in planners:
        share = _inside_share(by[(hw, p)])
        checks.append((f"{hw}: >= 90 % of users inside their own 95 % bound ({p})", share >= 0.9, f"{share:.2f}"))
    if {"casadi", "oracle"} <= set(planners) and "ideal" in conditions:
        checks += [(f"ideal: casadi within 1.1x oracle at {t:g} m",
                    mean[("ideal", "casadi", t)] <= 1.1 * mean[("ideal", "oracle", t)],
                    f"ratio {mean[('ideal', 'casadi', t)] / mean[('ideal', 'oracle', t)]:.2f}")
                   for t in targets_m[1:] or targets_m]
    if "casadi" in planners:
        cas = _times_ms([r for r in ok_recs if r["planner"] == "casadi"])
        checks += [("casadi replan median <= 30 ms", np.median(cas) <= 30, f"{np.median(cas):.1f} ms"),
                   ("casadi replan p95 <= 100 ms", np.percentile(cas, 95) <= 100, f"{np.percentile(cas, 95):.1f} ms")]
    if {"casadi", "casadi_reference"} <= set(planners):
        ref = _times_ms([r for r in ok_recs if r["planner"] == "casadi_reference"])
        cas = _times_ms([r for r in ok_recs if r["planner"] == "casadi"])
        lines.append(f"casadi_reference replan median {np.median(ref):.1f} ms, p95 {np.percentile(ref, 95):.1f} ms: "
                     f"casadi is {np.median(ref) / np.median(cas):.1f}x faster (median), "
                     f"{np.percentile(ref, 95) / np.percentile(cas, 95):.1f}x (p95)")
        for c in conditions:
            for t in targets_m:
                r = mean[(c, "casadi", t)] / mean[(c, "casadi_reference", t)]
                checks.append((f"{c}: casadi's metres within 3 % of casadi_reference at {t:g} m", abs(r - 1) <= 0.03,
                               f"ratio {r:.3f}"))
    checks.append(("zero constraint violations (all planners)", all(not r["violations"] for r in ok_recs),
                   f"{sum(r['violations'] for r in ok_recs)}"))
    lines.append("")
    for name, passed, detail in checks:
        lines.append(f"{'PASS' if passed else 'FAIL'}  {name}: {detail}")
        ok &= bool(passed)
    return "\n".join(lines), ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="8 scenarios per condition instead of 30")
    ap.add_argument("--scenarios", type=int, default=None, help="scenarios per condition (default 30, quick 8)")
    ap.add_argument("--distance-noise", action="store_true",
                    help="σ(d) = 3 + 0.3·e^(0.01 d) m in half of the scenarios (see the module docstring)")
    ap.add_argument("--planners", default=None, help="comma-separated planner names (default: the spec's)")
    ap.add_argument("--workers", type=int, default=None,
                    help="LocalCluster worker processes (default one per core; 0: in this process)")
    ap.add_argument("--scheduler", default=None, help="an existing Dask scheduler, e.g. tcp://127.0.0.1:8786")
    ap.add_argument("--out", type=Path, default=None,
                    help="campaign output folder (default: a fresh temporary one; an existing one resumes)")
    ap.add_argument("--worlds", action="store_true",
                    help="what each real effect costs lawnmower, casadi and oracle (see the module docstring)")
    args = ap.parse_args(argv)
    if args.worlds and (args.planners or args.distance_noise):
        ap.error("--worlds runs its own planners and noise: not with --planners or --distance-noise")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    quiet_logs()
    n = args.scenarios or (8 if args.quick else None)
    planners = tuple(p.strip() for p in args.planners.split(",") if p.strip()) if args.planners else None
    campaign = worlds_campaign(n) if args.worlds else benchmark_campaign(n, planners, args.distance_noise)
    planners = tuple(campaign.section.planners)
    with tempfile.TemporaryDirectory(prefix="uavloc-planner-bench-") as tmp:
        out = args.out or Path(tmp)
        t0 = time.perf_counter()
        done = run_campaign(campaign, out, scheduler=args.scheduler, workers=args.workers)
        total_s = time.perf_counter() - t0
    n_sc = len({(r.condition, r.scenario.name) for r in campaign.runs})
    print(f"\nplanner benchmark: {n_sc} scenarios, {len(planners)} planners, {len(campaign.runs)} runs on {done.where} "
          f"({done.workers} workers): {done.wall_s:.0f} s of runs, {total_s:.0f} s in all"
          + (f", {done.skipped} runs resumed from {args.out}" if done.skipped else "") + "\n")
    if args.worlds:
        print(summarise_worlds(done.records))
        return 0
    table, ok = summarise(done.records, planners, campaign.targets_m)
    print(table)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
