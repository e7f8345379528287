"""The estimator worker: `OnlineEstimator.add_keyframe` off the event loop (a child process, or a
thread), fed from a queue of keyframes."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import time
from collections.abc import Callable

import numpy as np

from estimator.noise import NoiseModel
from estimator.slam import OnlineEstimator
from estimator.types import Estimate, Keyframe, SolverParams
from uavloc.errors import EstimatorError, MissionError

log = logging.getLogger(__name__)


#: the child process's estimator (EstimatorWorker in process mode)
_CHILD_ONLINE: OnlineEstimator | None = None


def _child_init(n_users: int, user_up_m: np.ndarray, noise: NoiseModel, params: SolverParams) -> None:
    global _CHILD_ONLINE
    _die_with_parent()
    _CHILD_ONLINE = OnlineEstimator(n_users, user_up_m, noise, params)


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


def _child_add(kf: Keyframe) -> Estimate:
    return _CHILD_ONLINE.add_keyframe(kf)


class EstimatorWorker:
    """Feeds keyframes from a queue to an online estimator that runs off the event loop.

    `OnlineEstimator.add_keyframe` is numpy work of milliseconds (up to a few hundred when it
    (re)initializes users). mode "process" (default) runs the estimator in a child process (spawn),
    so the event loop neither waits on it nor competes with it for the GIL; mode "thread" runs it
    through `asyncio.to_thread`. Keyframes are solved one at a time in arrival order.
    """

    def __init__(self, n_users: int, user_up_m: np.ndarray, noise: NoiseModel, params: SolverParams,
                 queue: asyncio.Queue | None = None, mode: str = "process"):
        if mode not in ("process", "thread"):
            raise MissionError(f"estimator worker mode must be 'process' or 'thread', got {mode!r}")
        self.args = (int(n_users), np.asarray(user_up_m, float), noise, params)
        self.mode = mode
        self.queue: asyncio.Queue[Keyframe] = queue if queue is not None else asyncio.Queue()
        self.solve_s: list[float] = []
        self.ready = asyncio.Event()
        self.child_pid: int | None = None  # the estimator's process in process mode, once started

    async def run(self, on_estimate: Callable[[Estimate], None],
                  on_error: Callable[[EstimatorError], None] | None = None) -> None:
        """Until cancelled: take a keyframe, solve it off the loop, hand the estimate over.

        If the child process cannot start or dies (e.g. a caller's unguarded `__main__` under
        spawn), the worker falls back to thread mode and re-feeds the keyframes seen so far."""
        from concurrent.futures.process import BrokenProcessPool

        loop = asyncio.get_running_loop()
        pool = None
        fed: list[Keyframe] = []

        def thread_solver(history: list[Keyframe]):
            online = OnlineEstimator(*self.args)

            def replay_then_add(kf: Keyframe) -> Estimate:
                while history:
                    online.add_keyframe(history.pop(0))
                return online.add_keyframe(kf)

            return functools.partial(asyncio.to_thread, replay_then_add)

        if self.mode == "process":
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                       initializer=_child_init, initargs=self.args)
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
                kf = await self.queue.get()
                try:
                    t0 = time.perf_counter()
                    try:
                        est = await solve(kf)
                    except BrokenProcessPool:
                        log.warning("estimator child process died; solving in a thread from now on")
                        pool.shutdown(wait=False, cancel_futures=True)
                        pool, solve, self.mode = None, thread_solver(list(fed)), "thread"
                        est = await solve(kf)
                    fed.append(kf)
                    self.solve_s.append(time.perf_counter() - t0)
                except EstimatorError as exc:
                    if on_error is None:
                        raise
                    on_error(exc)
                    continue
                finally:
                    self.queue.task_done()
                on_estimate(est)
        finally:
            if pool is not None:
                # never block the loop on the child: it finishes its keyframe and exits by itself
                pool.shutdown(wait=False, cancel_futures=True)
