"""`uavloc campaign SPEC.toml [--scheduler ADDRESS] [--workers N] [--out DIR]`: a Monte-Carlo campaign
(scenarios × planners × estimators × fleet sizes × seeds) on Dask, with results, a summary table and figures."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

HELP = "run a Monte-Carlo campaign (scenarios x planners x seeds) on Dask; results as Parquet, summary, figures"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", metavar="SPEC.toml", type=Path, help="campaign spec (strict TOML)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask scheduler, e.g. tcp://host:8786 (default: a LocalCluster here)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="LocalCluster worker processes (default: one per core; 0: no Dask, runs one by one here)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output folder: results/ (Parquet), summary.csv/.txt, figures (default: campaign-<name>)")
    p.add_argument("--retry-failed", action="store_true", help="run again the runs recorded with an error")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from sitl_scenarios.campaign import load_spec, run_campaign, write_summary
    from sitl_scenarios.campaign.summary import summary_text

    if args.workers != 0:
        # Dask's own INFO lines (workers starting, closing) drown the rest unless asked for (-v)
        from sitl_scenarios.campaign.execute import quiet_logs

        quiet_logs(logging.INFO if getattr(args, "verbose", 0) else logging.WARNING)
    campaign = load_spec(args.spec)
    out = args.out if args.out is not None else Path(f"campaign-{campaign.name}")
    log.info("campaign %s: %d runs (%s mode) -> %s", campaign.name, len(campaign.runs), campaign.section.mode, out)
    done = run_campaign(campaign, out, scheduler=args.scheduler, workers=args.workers,
                        progress=not args.no_progress, retry_failed=args.retry_failed)
    write_summary(done.records, campaign.targets_m, out)
    print(summary_text(done.records, campaign.targets_m))
    print(f"\ncampaign {campaign.name}: {len(campaign.runs)} runs, {done.ran} run now on {done.where} "
          f"({done.workers} workers) in {done.wall_s:.1f} s (+{done.setup_s:.1f} s setup), {done.skipped} already "
          f"done, {done.failed} failed; results in {out}/results, summary and figures in {out}")
    if done.ran:
        print(done.cost_line())
    return 1 if done.failed else 0
