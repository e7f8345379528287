"""The estimator worker: the mission's estimator (mission.estimation: the online estimator with batch
refreshes, estimator.refresh) off the event loop (a child process, or a thread), fed from a queue of
keyframes."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import time
from collections.abc import Callable

from estimator.refresh import RefreshedEstimator
from estimator.types import Estimate, Keyframe
from mission.estimation import MissionEstimator
from uavloc.errors import EstimatorError, MissionError

log = logging.getLogger(__name__)


#: the child process's estimator and its confirm predicate (EstimatorWorker in process mode)
_CHILD_ESTIMATOR: RefreshedEstimator | None = None
_CHILD_CONFIRM: Callable[[Estimate], bool] | None = None


def _child_init(setup: MissionEstimator, confirm: Callable[[Estimate], bool] | None) -> None:
    global _CHILD_ESTIMATOR, _CHILD_CONFIRM
    _die_with_parent()
    _CHILD_ESTIMATOR = setup.estimator()
    _CHILD_CONFIRM = confirm


def _die_with_parent() -> None:
    """Linux: SIGTERM this process when its parent dies (a crashed or hard-exited uavloc must not
    leave the estimator child behind holding its stdout). Elsewhere a no-op."""
    import ctypes
    import signal
    import sys

    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
        if os.getppid() == 1:  # the parent is already gone
            os._exit(0)


def _child_ping() -> int:
    return os.getpid()


def _child_add(keyframes: list[Keyframe]) -> tuple[Estimate | None, list[EstimatorError]]:
    return _CHILD_ESTIMATOR.add_keyframes(keyframes, _CHILD_CONFIRM)


class EstimatorWorker:
    """Feeds keyframes from a queue to the mission's estimator (`setup.estimator()`,
    mission.estimation), off the event loop.

    `RefreshedEstimator.add_keyframes` is numpy work of milliseconds (up to a few hundred when it
    (re)initializes users or refreshes the batch). With `confirm` (default) the stop rule on the
    online estimate asks for a batch refresh at once (`setup.confirm`, estimator.refresh). mode
    "process" (default) runs the estimator in a child process (spawn), so the event loop neither
    waits on it nor competes with it for the GIL; mode "thread" runs it through `asyncio.to_thread`.
    Keyframes are solved in arrival order; those that queued up while the estimator was busy go
    together, with one estimate for all.
    """

    def __init__(self, setup: MissionEstimator, queue: asyncio.Queue | None = None, mode: str = "process",
                 confirm: bool = True):
        if mode not in ("process", "thread"):
            raise MissionError(f"estimator worker mode must be 'process' or 'thread', got {mode!r}")
        self.setup = setup
        self.confirm = setup.confirm if confirm else None
        self.mode = mode
        self.queue: asyncio.Queue[Keyframe] = queue if queue is not None else asyncio.Queue()
        self.solve_s: list[float] = []
        self.ready = asyncio.Event()
        self.child_pid: int | None = None  # the estimator's process in process mode, once started

    async def run(self, on_estimate: Callable[[Estimate], None],
                  on_error: Callable[[EstimatorError], None] | None = None) -> None:
        """Until cancelled: take the keyframes queued, solve them off the loop, hand the estimate
        over (and each malformed keyframe's EstimatorError to on_error; raised without it).

        If the child process cannot start or dies (e.g. a caller's unguarded `__main__` under
        spawn), the worker falls back to thread mode and re-feeds the keyframes seen so far."""
        from concurrent.futures.process import BrokenProcessPool

        loop = asyncio.get_running_loop()
        pool = None
        fed: list[Keyframe] = []

        def thread_solver(history: list[Keyframe]):
            estimator = self.setup.estimator()

            def replay_then_add(keyframes: list[Keyframe]) -> tuple[Estimate | None, list[EstimatorError]]:
                # the keyframes so far one at a time (a malformed one fails again, quietly), so
                # that the refreshes come where they came in the child when it was fed so
                for kf in history:
                    estimator.add_keyframes([kf])
                history.clear()
                return estimator.add_keyframes(keyframes, self.confirm)

            return functools.partial(asyncio.to_thread, replay_then_add)

        if self.mode == "process":
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                       initializer=_child_init, initargs=(self.setup, self.confirm))
            solve = functools.partial(loop.run_in_executor, pool, _child_add)
        else:
            solve = thread_solver([])
        try:
            if pool is not None:
                try:
                    # start the child now, not at the 1st keyframe
                    self.child_pid = await loop.run_in_executor(pool, _child_ping)
                except BrokenProcessPool:
                    log.warning("estimator child process did not start; solving in a thread instead")
                    pool.shutdown(wait=False, cancel_futures=True)
                    pool, solve, self.mode = None, thread_solver([]), "thread"
            self.ready.set()
            while True:
                batch = [await self.queue.get()]
                while not self.queue.empty():
                    batch.append(self.queue.get_nowait())
                try:
                    t0 = time.perf_counter()
                    try:
                        est, errors = await solve(batch)
                    except BrokenProcessPool:
                        log.warning("estimator child process died; solving in a thread from now on")
                        pool.shutdown(wait=False, cancel_futures=True)
                        pool, solve, self.mode = None, thread_solver(list(fed)), "thread"
                        est, errors = await solve(batch)
                    fed.extend(batch)
                    self.solve_s.append(time.perf_counter() - t0)
                except EstimatorError as exc:  # the solve itself failed
                    est, errors = None, [exc]
                except Exception as exc:  # a bug in the estimator: report it, keep the mission
                    log.exception("estimator failed on %d keyframe(s)", len(batch))
                    est, errors = None, [EstimatorError(f"estimator failed: {type(exc).__name__}: {exc}")]
                finally:
                    for _ in batch:
                        self.queue.task_done()
                for exc in errors:
                    if on_error is None:
                        raise exc
                    on_error(exc)
                if est is not None:
                    on_estimate(est)
        finally:
            if pool is not None:
                # never block the loop on the child: it finishes its keyframe and exits by itself
                pool.shutdown(wait=False, cancel_futures=True)
