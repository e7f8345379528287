"""`uavloc replay LOG [--json] [--out DIR]`: re-run the estimator over a recorded mission."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)

HELP = "re-run the estimator over a recorded mission log and print where the users are"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", type=Path, help="mission log (uavloc-mission/1, JSON Lines)")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    p.add_argument("--out", type=Path, metavar="DIR", help="write a report (figures, report.json/html) here")
    p.add_argument("--loss", metavar="NAME",
                   help="robust loss on range factors: none, huber, cauchy, ... (default: the mission's, as "
                        "logged in the header, else the estimator's default)")
    p.add_argument("--loss-scale", type=float, metavar="C", help="robust loss threshold in sigmas")
    p.add_argument("--delta", type=float, metavar="M",
                   help="re-select keyframes every M metres (default: every trigger in the log)")
    p.add_argument("--bias", action=argparse.BooleanOptionalAction, default=None,
                   help="estimate a range bias per user (default: as the mission did)")
    p.add_argument("--sigma-gps", type=float, metavar="M", help="override the header's GPS sigma [m]")
    p.add_argument("--no-velocity", action="store_true",
                   help="ignore the telemetry's velocity (by default consecutive keyframes are linked by the "
                        "displacement integrated from vel_ned_mps where the log has it)")
    p.add_argument("--no-history", action="store_true",
                   help="with --out: skip the online pass (faster; no history figure); without --out there is none")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from estimator.robust import check_loss
    from mission.log import read_mission_log
    from mission.progress import Progress
    from mission.replay import ReplayOptions, replay, result_of_replay, solver_params_from_header
    from mission.status import print_result
    from uavloc.errors import MissionLogError

    for name in ("loss_scale", "delta", "sigma_gps"):
        v = getattr(args, name)
        if v is not None and not (v > 0 and v < float("inf")):
            raise MissionLogError(f"--{name.replace('_', '-')} must be a positive number, got {v}")
    mlog = read_mission_log(args.log)
    noise = mlog.header.noise
    if args.sigma_gps is not None:
        noise = replace(noise, sigma_gps_m=args.sigma_gps)
    params = solver_params_from_header(mlog)
    overrides = {"loss": args.loss, "loss_scale": args.loss_scale, "estimate_bias": args.bias}
    params = replace(params, **{k: v for k, v in overrides.items() if v is not None})
    check_loss(params.loss, params.loss_scale)
    # the online pass feeds only the report's history figure
    options = ReplayOptions(params=params, delta_m=args.delta, noise=noise,
                            history=args.out is not None and not args.no_history, velocity=not args.no_velocity)
    log.info("replaying %s: %d users, %d rtt records", args.log, mlog.n_users, len(mlog.rtt_t_s))
    bar = Progress("replay", len(mlog.rtt_t_s) // max(mlog.n_users, 1) + 1, min_total=1000)
    try:
        result = replay(mlog, options, progress=lambda done, total: (setattr(bar, "total", total), bar.update(done)))
    finally:
        bar.close()
    if args.out is not None:
        from mission.report import write_report

        paths = write_report(result, args.out)
        log.info("report written to %s: %s", args.out, ", ".join(sorted(p.name for p in paths.values())))
    # the same document and lines as the mission printed (mission.result.Result)
    print_result(result_of_replay(result), args.json)
    return 0
