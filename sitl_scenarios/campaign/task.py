"""The per-run task: one RunSpec in, one record (a flat dict, a row of the results table) out.

`run_one` is what a Dask worker executes. It is a pure function of its RunSpec except for the
timing columns (TIMING_FIELDS: wall time, plan compute times, worker): the same RunSpec gives the
same record on any worker, in any process, in any order. It never raises for a failure of the
run itself: the record then has status "error" and the error text, and the campaign goes on.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import time
import traceback

import numpy as np

from mission.config import gps_floor_m
from sitl_scenarios.campaign.outcome import Outcome
from sitl_scenarios.campaign.spec import RunSpec

log = logging.getLogger(__name__)

#: columns that depend on the machine and its load, not on the run's definition
TIMING_FIELDS = ("wall_s", "plan_times_s", "plan_median_s", "plan_p95_s", "worker")


def _base_record(run: RunSpec) -> dict:
    rec = {
        "key": run.key, "condition": run.condition, "scenario": run.scenario.name, "planner": run.planner,
        "estimator": run.estimator, "n_vehicles": int(run.n_vehicles), "seed": int(run.seed), "mode": run.mode,
        "targets_m": [float(t) for t in run.targets_m], "budget_m": float(run.scenario.mission.flight.budget_m),
        # the 95 % bound the GPS error leaves however the run flies (the mission as flown: τ known)
        "floor_m": float(gps_floor_m(run.scenario.mission_config())),
    }
    rec.update(run.scenario_params)
    return rec


def _outcome_fields(out: Outcome, targets_m: tuple[float, ...]) -> dict:
    times = np.asarray(out.plan_times_s, float)
    err = np.asarray(out.final_error_m, float)
    return {
        "status": "ok", "error": "", "traceback": "", "end": out.end,
        "metres_to_m": [float(out.metres_to.get(t, math.nan)) for t in targets_m],
        "seconds_to_s": [float(out.seconds_to.get(t, math.nan)) for t in targets_m],
        "hover_s": float(out.hover_s), "survey_s": float(out.survey_s),
        "error_at_m": [float(out.error_at.get(t, math.nan)) for t in targets_m],
        "flown_m": float(out.flown_m), "keyframes": int(out.keyframes), "replans": len(times),
        "plan_times_s": [float(v) for v in times],
        "plan_median_s": float(np.median(times)) if len(times) else math.nan,
        "plan_p95_s": float(np.percentile(times, 95)) if len(times) else math.nan,
        "final_error_m": [float(v) for v in out.final_error_m],
        "final_bound95_m": [float(v) for v in out.final_bound95_m],
        "final_nees": [float(v) for v in out.final_nees],
        "mean_error_m": float(np.mean(err)) if len(err) else math.nan,
        "max_error_m": float(np.max(err)) if len(err) else math.nan,
        "inside95": float(out.inside95), "nlos_share": float(out.nlos_share),
        "violations": len(out.violations), "first_violation": out.violations[0] if out.violations else "",
        "estimator_errors": len(out.estimator_errors),
        "first_estimator_error": out.estimator_errors[0][:500] if out.estimator_errors else "",
    }


def error_record(run: RunSpec, exc: BaseException, wall_s: float = math.nan, worker: str = "") -> dict:
    """The record of a run that raised: the run's identity, status "error" and what went wrong."""
    rec = _base_record(run)
    rec.update({"status": "error", "error": f"{type(exc).__name__}: {exc}",
                "traceback": "".join(traceback.format_exception(exc))[-4000:], "wall_s": wall_s,
                "worker": worker})
    return rec


def run_one(run: RunSpec) -> dict:
    """Fly one run (fast or full mode) and return its record; a failure becomes an error record."""
    worker = f"{socket.gethostname()}:{os.getpid()}"
    t0 = time.perf_counter()
    try:
        if run.mode == "fast":
            from sitl_scenarios.campaign.fast import fly_fast

            out = fly_fast(run.scenario, run.planner, run.params, run.seed, run.targets_m, run.planner_opts,
                           n_vehicles=run.n_vehicles)
        else:
            from sitl_scenarios.campaign.full import fly_full

            out = fly_full(run.scenario, run.planner, run.params, run.seed, run.targets_m, run.speedup,
                           gnb_transport=run.gnb_transport, gnb_mode=run.gnb_mode)
    except Exception as exc:  # recorded, not raised: the campaign goes on (the error text says what)
        log.warning("run %s failed: %s: %s", run.key, type(exc).__name__, exc)
        return error_record(run, exc, time.perf_counter() - t0, worker)
    rec = _base_record(run)
    rec.update(_outcome_fields(out, run.targets_m))
    rec.update({"wall_s": time.perf_counter() - t0, "worker": worker})
    return rec
