"""Run a campaign on Dask distributed, writing results as runs finish, skipping runs already done.

Where the runs go:
- `scheduler=None` (default): a `distributed.LocalCluster` of `workers` single-threaded worker
  processes (default: one per core), on a free port, no dashboard; it ends with the campaign.
- `scheduler="tcp://host:8786"`: an existing cluster (`dask scheduler` + `dask worker`, or one
  started by dask-jobqueue on SLURM/PBS, or on Kubernetes); its workers need this package installed.
- `workers=0`: no Dask at all, the runs one after the other in this process (debugging, baselines).

Each run is `task.run_one(RunSpec)`, a pure task returning one record. A run that raises inside is
recorded by the task itself; a task that dies with its worker (KilledWorker, a lost connection) is
recorded here with that error; either way the campaign goes on.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from sitl_scenarios.campaign.results import ResultsStore
from sitl_scenarios.campaign.spec import Campaign, RunSpec
from sitl_scenarios.campaign.task import error_record, run_one
from uavloc.errors import CampaignError

log = logging.getLogger(__name__)

#: the loggers of a campaign's own runs (what a run logs — a degraded estimator, a planner exploring,
#: a caught failure — is in its record)
RUN_LOGGERS = ("sitl_scenarios", "mission", "estimator", "planner")


def quiet_logs(dask_level: int = logging.WARNING, runs_level: int | None = None) -> None:
    """Keep Dask's INFO lines (workers starting and closing) out of a user's terminal: the
    "distributed" loggers at `dask_level`, and the runs' own loggers at `runs_level` (None: as
    they are). Importing distributed configures its loggers (at INFO), so it is imported first."""
    import distributed  # noqa: F401

    logging.getLogger("distributed").setLevel(dask_level)
    if runs_level is not None:
        for name in RUN_LOGGERS:
            logging.getLogger(name).setLevel(runs_level)


@dataclass
class CampaignRun:
    """What `run_campaign` did: records of this campaign's runs (old and new), counts and wall time.

    records: one per run of the spec that has a result, in the spec's order; ran / skipped / failed:
    runs executed now, runs found done, runs (now or before) with status "error"; wall_s: from the
    first submission to the last result [s]; setup_s: starting or reaching the cluster [s];
    workers: worker processes that took part; where: "local", "LocalCluster(N)" or the address;
    run_s: the runs' own wall times summed over the runs executed now (what one worker spends) [s].
    """

    records: list[dict] = field(default_factory=list)
    ran: int = 0
    skipped: int = 0
    failed: int = 0
    wall_s: float = 0.0
    setup_s: float = 0.0
    workers: int = 0
    where: str = ""
    run_s: float = 0.0

    @property
    def runs_per_min_per_worker(self) -> float:
        """A run's cost as throughput: 60 / (mean wall time of one run) [runs/min], NaN before any run."""
        return 60.0 * self.ran / self.run_s if self.run_s > 0 else math.nan

    @property
    def runs_per_min(self) -> float:
        """The campaign's throughput over all its workers: runs executed now per minute of wall time."""
        return 60.0 * self.ran / self.wall_s if self.wall_s > 0 else math.nan

    def cost_line(self) -> str:
        """One line: runs per minute per worker (a run's cost) and over the campaign's workers."""
        return (f"cost: {self.runs_per_min_per_worker:.2f} runs/min per worker (a run takes "
                f"{self.run_s / max(self.ran, 1):.2f} s), {self.runs_per_min:.2f} runs/min on {self.workers} "
                f"worker(s), {self.ran} runs")


class _Flusher:
    """Buffers finished records and writes a Parquet part every `every_s` seconds or `every_n` records."""

    def __init__(self, store: ResultsStore, every_n: int = 50, every_s: float = 5.0):
        self.store, self.every_n, self.every_s = store, every_n, every_s
        self.buf: list[dict] = []
        self.last = time.monotonic()

    def add(self, rec: dict) -> None:
        self.buf.append(rec)
        if len(self.buf) >= self.every_n or time.monotonic() - self.last >= self.every_s:
            self.flush()

    def flush(self) -> None:
        if self.buf:
            self.store.append(self.buf)
            self.buf = []
        self.last = time.monotonic()


def _progress(total: int, label: str, enabled: bool):
    from tqdm import tqdm

    # disable=None: drawn on a terminal only; False/True force it
    return tqdm(total=total, desc=label, unit="run", file=sys.stderr, dynamic_ncols=True,
                disable=(None if enabled else True))


def run_campaign(campaign: Campaign, out_dir: str | Path, *, scheduler: str | None = None,
                 workers: int | None = None, progress: bool = True, retry_failed: bool = False,
                 on_record: Callable[[dict], None] | None = None) -> CampaignRun:
    """Run every run of `campaign` not yet in `out_dir`'s results (see the module docstring).

    retry_failed: run again the runs whose stored record has status "error". on_record: called with
    each new record as it arrives (in the driver). Returns a :class:`CampaignRun`; the results stay in
    `out_dir/results/`.
    """
    if workers is not None and workers < 0:
        raise CampaignError(f"--workers must be >= 0, got {workers}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    store = ResultsStore(out)
    stored = {r["key"]: r for r in store.read_records()}
    wanted = {r.key for r in campaign.runs}
    done = {k for k, r in stored.items() if k in wanted and (r["status"] == "ok" or not retry_failed)}
    todo = [r for r in campaign.runs if r.key not in done]
    result = CampaignRun(skipped=len(done))
    if done:
        log.info("%s: %d of %d runs already in %s, %d to run", campaign.name, len(done), len(campaign.runs),
                 store.dir, len(todo))
    flusher = _Flusher(store)
    bar = _progress(len(todo), campaign.name, progress)

    def arrived(rec: dict) -> None:
        stored[rec["key"]] = rec
        flusher.add(rec)
        result.ran += 1
        if math.isfinite(rec.get("wall_s", math.nan)):
            result.run_s += rec["wall_s"]
        bar.update(1)
        if rec["status"] != "ok":
            bar.set_postfix_str(f"{sum(r['status'] != 'ok' for r in stored.values() if r['key'] in wanted)} failed")
        if on_record is not None:
            on_record(rec)

    try:
        if todo:
            if workers == 0:
                result.where, result.workers = "local", 1
                t0 = time.perf_counter()
                for run in todo:
                    arrived(run_one(run))
                result.wall_s = time.perf_counter() - t0
            else:
                _run_dask(todo, scheduler, workers, arrived, result)
    finally:
        flusher.flush()
        bar.close()
    if len(store.parts()) > 1:  # the campaign is complete: one part is easier to share
        store.compact()
    result.records = [stored[r.key] for r in campaign.runs if r.key in stored]
    result.failed = sum(r["status"] != "ok" for r in result.records)
    return result


def _run_dask(todo: list[RunSpec], scheduler: str | None, workers: int | None,
              arrived: Callable[[dict], None], result: CampaignRun) -> None:
    from distributed import Client, LocalCluster, as_completed

    t_setup = time.perf_counter()
    cluster = None
    if scheduler is None:
        n = workers or os.cpu_count() or 1
        # one single-threaded process per worker: the estimator and IPOPT hold the GIL. Every port is
        # chosen by the OS on loopback: no dashboard, and the scheduler's and workers' HTTP endpoints
        # (health, metrics) on 127.0.0.1:0 rather than 8787 on all interfaces
        # the worker processes log on their own stderr: unless Dask's logs were asked for
        # (quiet_logs below WARNING), they keep even their ERROR lines to themselves, such as a
        # heartbeat that meets the scheduler already closed as the cluster shuts down (a run that
        # is lost is reported by run_campaign itself)
        dask_level = logging.getLogger("distributed").getEffectiveLevel()
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, scheduler_port=0,
                               dashboard_address=None, scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                               worker_dashboard_address="127.0.0.1:0",
                               silence_logs=logging.CRITICAL if dask_level >= logging.WARNING else dask_level)
        result.where = f"LocalCluster({n})"
    else:
        result.where = scheduler
    try:
        try:
            client = Client(cluster if cluster is not None else scheduler, timeout=30)
        except (OSError, TimeoutError) as exc:
            raise CampaignError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from exc
        with client:
            if scheduler is not None:
                if workers:
                    log.info("--workers is ignored with --scheduler (the cluster has its own workers)")
                client.wait_for_workers(1, timeout=60)
            result.workers = len(client.scheduler_info()["workers"])
            result.setup_s = time.perf_counter() - t_setup
            log.info("campaign on %s: %d workers, %d runs", result.where, result.workers, len(todo))
            t0 = time.perf_counter()
            futures = {}
            for run in todo:
                fut = client.submit(run_one, run, pure=False, key=f"run-{run.key.rsplit('#', 1)[1]}-{id(run):x}")
                futures[fut] = run
            for fut in as_completed(futures):
                run = futures.pop(fut)
                try:
                    rec = fut.result()
                except Exception as exc:  # the task died with its worker, or could not be unpickled
                    log.warning("run %s lost: %s: %s", run.key, type(exc).__name__, exc)
                    rec = error_record(run, exc)
                fut.release()
                arrived(rec)
            result.wall_s = time.perf_counter() - t0
    except OSError as exc:  # the scheduler went away mid-campaign (CommClosedError is an OSError)
        raise CampaignError(f"lost the Dask cluster at {result.where}: {exc}; the results so far are saved, "
                            "run the same spec again to resume") from exc
    finally:
        if cluster is not None:
            cluster.close()
