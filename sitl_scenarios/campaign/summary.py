"""Summary table and figures of a campaign's records.

Per (condition, planner, fleet size, estimator): runs, failures, and for each accuracy target the runs that
reached it and the median and 95 % interval (2.5th–97.5th percentile) of the metres flown to it
(a run that never reached it counts its budget, so a planner that fails is not flattered); the same
statistics of the final mean true error, the share of estimates inside their own 95 % ellipse, the
share of users inside their own final 95 % ellipse and the users beyond their final 99.9 % one, the
median replan and run times, and the runs whose estimator reported a failure.
Written to `summary.csv` and `summary.txt`; figures `metres_to_target.png`
(metres to each target per planner and condition) and `error_vs_bound.png` (each user's final true
error against its 95 % bound). The text table has a `fleet` column, and the figures' series read
"casadi ×2", only when some run flew more than one vehicle (summary.csv always has `n_vehicles`).

With more than one fleet size, also the fleet speed-up (:func:`fleet_speedup_rows`, in summary.txt
after the table and in `fleet_speedup.csv`): per condition, planner, estimator, fleet size N and
target, the ratio of survey seconds to the target with N vehicles over one vehicle on the same
scenario and seed.
"""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path

import numpy as np

from estimator.types import CHI2_2DOF_95, CHI2_2DOF_999

log = logging.getLogger(__name__)


def _stats(values: list[float]) -> tuple[float, float, float]:
    """(median, 2.5th percentile, 97.5th percentile) of the finite values, NaN when none."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], float)
    if not len(v):
        return math.nan, math.nan, math.nan
    return float(np.median(v)), float(np.percentile(v, 2.5)), float(np.percentile(v, 97.5))


def metres_or_budget(rec: dict, i: int) -> float:
    """Metres flown to target i, or the run's budget when it never got there."""
    m = rec["metres_to_m"][i]
    return rec["budget_m"] if m is None or not math.isfinite(m) else m


def seconds_or_survey(rec: dict, i: int) -> float:
    """Survey seconds to target i; when the run never got there, as :func:`metres_or_budget` counts
    its budget, the seconds its budget takes at the run's own pace (hover included):

        s = survey_s · budget_m / flown_m

    (a run that ended early, at its floor, is not cheaper than one that flew on; records written
    before seconds_to_s: NaN)."""
    s = (rec.get("seconds_to_s") or [None] * (i + 1))[i]
    if s is None or not math.isfinite(s):
        total, flown = rec.get("survey_s"), rec.get("flown_m")
        if total is None or flown is None or not flown > 0.0:
            return math.nan
        return float(total) * float(rec["budget_m"]) / float(flown)
    return float(s)


def fleet_size(rec: dict) -> int:
    """The vehicles a run flew (records written before n_vehicles: one)."""
    n = rec.get("n_vehicles")
    return 1 if n is None else int(n)


def series_label(rec: dict, fleets: bool) -> str:
    """A figure's name for the run's series: its planner, with its fleet size ("casadi ×2") when
    `fleets` (some run of the campaign flew more than one vehicle)."""
    return f"{rec['planner']} ×{fleet_size(rec)}" if fleets else rec["planner"]


def summary_rows(records: list[dict], targets_m: tuple[float, ...]) -> list[dict]:
    """One row per (condition, planner, fleet size, estimator), in the order they first appear."""
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        groups.setdefault((r["condition"], r["planner"], fleet_size(r), r["estimator"]), []).append(r)
    rows = []
    for (cond, planner, n_vehicles, est), rs in groups.items():
        ok = [r for r in rs if r["status"] == "ok"]
        row = {"condition": cond, "planner": planner, "n_vehicles": n_vehicles, "estimator": est, "runs": len(rs),
               "failed": len(rs) - len(ok)}
        for i, t in enumerate(targets_m):
            row[f"reached@{t:g}"] = sum(math.isfinite(r["metres_to_m"][i]) for r in ok)
            med, lo, hi = _stats([metres_or_budget(r, i) for r in ok])
            row.update({f"m@{t:g}_median": med, f"m@{t:g}_lo95": lo, f"m@{t:g}_hi95": hi})
            row[f"s@{t:g}_median"] = _stats([seconds_or_survey(r, i) for r in ok])[0]
        row["floor_m_median"] = _stats([r.get("floor_m", math.nan) for r in ok])[0]
        row["floor_reached"] = sum("floor reached" in (r.get("end") or "") for r in ok)
        row["hover_s_median"] = _stats([r.get("hover_s", math.nan) for r in ok])[0]
        med, lo, hi = _stats([r["mean_error_m"] for r in ok])
        row.update({"error_median_m": med, "error_lo95_m": lo, "error_hi95_m": hi})
        row["inside95_median"] = _stats([r["inside95"] for r in ok])[0]
        # the final NEES of every located user (records written before final_nees: none)
        nees = np.array([v for r in ok for v in (r.get("final_nees") or []) if v is not None and math.isfinite(v)])
        row["final_users"] = len(nees)
        row["final_inside95"] = float(np.mean(nees <= CHI2_2DOF_95)) if len(nees) else math.nan
        row["final_beyond999"] = int(np.sum(nees > CHI2_2DOF_999))
        row["replan_median_ms"] = _stats([1e3 * t for r in ok for t in r["plan_times_s"]])[0]
        row["run_median_s"] = _stats([r.get("wall_s", math.nan) for r in rs])[0]
        row["estimator_errors"] = sum(r.get("estimator_errors") or 0 for r in ok)
        row["violations"] = sum(r["violations"] for r in ok)
        rows.append(row)
    return rows


def format_table(rows: list[dict], targets_m: tuple[float, ...]) -> str:
    """A fixed-width text table of summary_rows (a `fleet` column when some row flew more than one vehicle)."""
    fleets = any(r.get("n_vehicles", 1) != 1 for r in rows)
    head = f"{'condition':<14} {'planner':<10}" + (f" {'fleet':>5}" if fleets else "")
    head += f" {'estimator':<10} {'runs':>4} {'fail':>4}"
    for t in targets_m:
        head += f" {'reach@' + format(t, 'g'):>9} {'m@' + format(t, 'g') + ' median [95 %]':>24}"
        head += f" {'s@' + format(t, 'g'):>7}"
    head += f" {'floor m':>7} {'@floor':>6} {'hover s':>7}"
    head += (f" {'error m median [95 %]':>24} {'in95':>5} {'end95':>5} {'>99.9':>5} {'replan ms':>9} {'run s':>6}"
             f" {'viol':>4} {'est!':>4}")
    lines = [head, "-" * len(head)]
    for r in rows:
        line = f"{r['condition']:<14} {r['planner']:<10}" + (f" {r['n_vehicles']:>5}" if fleets else "")
        line += f" {r['estimator']:<10} {r['runs']:>4} {r['failed']:>4}"
        for t in targets_m:
            k = f"m@{t:g}"
            ok = r["runs"] - r["failed"]
            line += f" {r[f'reached@{t:g}']:>5}/{ok:<3} {r[k + '_median']:>7.0f} [{r[k + '_lo95']:>6.0f}, " \
                    f"{r[k + '_hi95']:>6.0f}]"
            line += f" {r[f's@{t:g}_median']:>7.0f}"
        line += f" {r['floor_m_median']:>7.2f} {r['floor_reached']:>6} {r['hover_s_median']:>7.1f}"
        line += f" {r['error_median_m']:>7.2f} [{r['error_lo95_m']:>5.2f}, {r['error_hi95_m']:>6.2f}]"
        line += (f" {r['inside95_median']:>5.2f} {r['final_inside95']:>5.2f} {r['final_beyond999']:>5}"
                 f" {r['replan_median_ms']:>9.1f} {r['run_median_s']:>6.2f}"
                 f" {r['violations']:>4} {r['estimator_errors']:>4}")
        lines.append(line)
    lines.append("")
    lines.append("m@T: metres flown until every user's printed 95 % error bound <= T m, as the stop rule reads it "
                 "(a run that never gets there counts its budget); [95 %]: 2.5th-97.5th percentile over runs; "
                 "s@T: median survey seconds to the same, hover included (never there: its budget at its own pace);")
    lines.append("floor m: the 95 % bound the GPS error leaves however a run flies (median over runs); @floor: runs "
                 "that ended 'floor reached'; hover s: median survey seconds spent waiting;")
    lines.append("error: final mean true error per run; in95: median share of estimates inside their own 95 % "
                 "ellipse; fail: runs that raised (see the results' error column);")
    lines.append("end95: share of users inside their own final 95 % ellipse; >99.9: users beyond their final 99.9 % "
                 "ellipse;")
    lines.append("run s: median wall time of a run; est!: runs whose estimator reported a failure and went on "
                 "(first_estimator_error column)" + ("; fleet: vehicles per run." if fleets else "."))
    return "\n".join(lines)


def fleet_speedup_rows(records: list[dict], targets_m: tuple[float, ...]) -> list[dict]:
    """The fleet speed-up: one row per (condition, planner, estimator, fleet size N > 1) and target,
    in the order they first appear.

    Each run with N vehicles is paired with the one-vehicle run of the same condition, scenario,
    planner, estimator and seed (the same world and noise seed); the pair's ratio is

        ratio = seconds_to_s with N vehicles / seconds_to_s with one

    (survey seconds until every user's 95 % bound <= T, hover included; < 1: the fleet got there
    sooner). pairs: the successful N-vehicle runs with a successful one-vehicle partner;
    both_reached: those pairs where both runs reached T, over which ratio_median and ratio_max are
    taken (NaN when none). Empty unless the records hold more than one fleet size."""
    if len({fleet_size(r) for r in records}) < 2:
        return []
    ok = [r for r in records if r["status"] == "ok"]

    def pair_key(r: dict) -> tuple:
        return r["condition"], r["scenario"], r["planner"], r["estimator"], r["seed"]

    solo = {pair_key(r): r for r in ok if fleet_size(r) == 1}
    groups: dict[tuple, list[tuple[dict, dict]]] = {}
    for r in ok:
        one = solo.get(pair_key(r))
        if fleet_size(r) != 1 and one is not None:
            groups.setdefault((r["condition"], r["planner"], r["estimator"], fleet_size(r)), []).append((r, one))

    def seconds_to(r: dict, i: int) -> float:
        s = (r.get("seconds_to_s") or [None] * (i + 1))[i]
        return math.nan if s is None else float(s)

    rows = []
    for (cond, planner, est, n), pairs in groups.items():
        for i, t in enumerate(targets_m):
            ratios = [a / b for a, b in ((seconds_to(r, i), seconds_to(one, i)) for r, one in pairs)
                      if math.isfinite(a) and math.isfinite(b) and b > 0.0]
            rows.append({"condition": cond, "planner": planner, "estimator": est, "n_vehicles": n, "target_m": t,
                         "pairs": len(pairs), "both_reached": len(ratios),
                         "ratio_median": float(np.median(ratios)) if ratios else math.nan,
                         "ratio_max": float(np.max(ratios)) if ratios else math.nan})
    return rows


def format_fleet_speedup(rows: list[dict]) -> str:
    """A fixed-width text table "fleet speed-up" of fleet_speedup_rows."""
    head = (f"{'condition':<14} {'planner':<10} {'estimator':<10} {'fleet':>5} {'target':>6} {'both/pairs':>10}"
            f" {'median':>7} {'max':>7}")
    lines = ["fleet speed-up: survey seconds to each target, N vehicles / one vehicle", head, "-" * len(head)]
    for r in rows:
        both = f"{r['both_reached']}/{r['pairs']}"
        lines.append(f"{r['condition']:<14} {r['planner']:<10} {r['estimator']:<10} {r['n_vehicles']:>5}"
                     f" {r['target_m']:>6g} {both:>10} {r['ratio_median']:>7.2f} {r['ratio_max']:>7.2f}")
    if not rows:
        lines.append("(no pairs: no successful N-vehicle run has a successful one-vehicle run of the same scenario "
                     "and seed)")
    lines.append("")
    lines.append("ratio: s@T with N vehicles over s@T with one, per pair of runs on the same scenario, seed, planner "
                 "and estimator (< 1: the fleet got there sooner); median and max over the pairs where both reached "
                 "T (both); pairs: N-vehicle runs with their one-vehicle run.")
    return "\n".join(lines)


def summary_text(records: list[dict], targets_m: tuple[float, ...]) -> str:
    """The summary as printed and in summary.txt: the table, then the fleet speed-up when the records
    hold more than one fleet size."""
    text = format_table(summary_rows(records, targets_m), targets_m)
    if len({fleet_size(r) for r in records}) > 1:
        text += "\n\n" + format_fleet_speedup(fleet_speedup_rows(records, targets_m))
    return text


def write_summary(records: list[dict], targets_m: tuple[float, ...], out_dir: str | Path) -> dict[str, Path]:
    """summary.csv, summary.txt, fleet_speedup.csv (more than one fleet size) and the two figures in
    out_dir; returns their paths."""
    out = Path(out_dir)
    rows = summary_rows(records, targets_m)
    paths = {"csv": out / "summary.csv", "txt": out / "summary.txt"}
    _write_csv(paths["csv"], rows)
    speedup = fleet_speedup_rows(records, targets_m)
    if speedup:
        paths["fleet_speedup"] = out / "fleet_speedup.csv"
        _write_csv(paths["fleet_speedup"], speedup)
    paths["txt"].write_text(summary_text(records, targets_m) + "\n", encoding="utf-8")
    paths.update(write_figures(records, targets_m, out))
    return paths


def _write_csv(path: Path, rows: list[dict]) -> None:
    if rows:
        with open(path, "w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


def write_figures(records: list[dict], targets_m: tuple[float, ...], out: Path) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in records if r["status"] == "ok"]
    if not ok:
        return {}
    # one series per planner (and fleet size, when some run flew more than one vehicle)
    fleets = any(fleet_size(r) != 1 for r in records)  # as the table's fleet column
    planners = list(dict.fromkeys(series_label(r, fleets) for r in ok))
    conditions = list(dict.fromkeys(r["condition"] for r in ok))
    paths = {}

    fig, axes = plt.subplots(1, len(targets_m), figsize=(max(6, 2.2 * len(planners) * len(targets_m)), 4.5),
                             squeeze=False)
    width = 0.8 / max(len(conditions), 1)
    for ax, (i, t) in zip(axes[0], enumerate(targets_m), strict=True):
        for j, cond in enumerate(conditions):
            data = [[metres_or_budget(r, i) for r in ok if series_label(r, fleets) == p and r["condition"] == cond]
                    for p in planners]
            pos = np.arange(len(planners)) + (j - (len(conditions) - 1) / 2) * width
            keep = [k for k, d in enumerate(data) if d]
            if keep:
                bp = ax.boxplot([data[k] for k in keep], positions=pos[keep], widths=width * 0.9,
                                patch_artist=True, showfliers=True)
                for box in bp["boxes"]:
                    box.set_facecolor(f"C{j}")
                    box.set_alpha(0.6)
                ax.plot([], [], "s", color=f"C{j}", label=cond)
        ax.set_xticks(np.arange(len(planners)), planners, rotation=30)
        ax.set_ylabel(f"metres flown to every 95 % bound <= {t:g} m")
        ax.grid(True, axis="y", alpha=0.3)
    axes[0][-1].legend(title="condition", fontsize=8)
    fig.tight_layout()
    paths["metres_to_target"] = out / "metres_to_target.png"
    fig.savefig(paths["metres_to_target"], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5.5, 5))
    top = 0.0
    for j, p in enumerate(planners):
        err = np.array([e for r in ok if series_label(r, fleets) == p for e in r["final_error_m"]], float)
        bnd = np.array([b for r in ok if series_label(r, fleets) == p for b in r["final_bound95_m"]], float)
        m = np.isfinite(err) & np.isfinite(bnd)
        if np.any(m):
            ax.scatter(bnd[m], err[m], s=10, alpha=0.6, color=f"C{j}", label=p)
            top = max(top, float(np.max(bnd[m])), float(np.max(err[m])))
    ax.plot([0, top], [0, top], "k--", lw=1, label="error = 95 % bound")
    ax.set_xlabel("final 95 % error bound of a user [m]")
    ax.set_ylabel("final true error of the user [m]")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    paths["error_vs_bound"] = out / "error_vs_bound.png"
    fig.savefig(paths["error_vs_bound"], dpi=110)
    plt.close(fig)
    return paths
