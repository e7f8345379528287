"""Run a mission's event loop with a bounded end, whatever the vehicle library does (issue 10).

MAVSDK's asyncio binding runs every request as a blocking call in the event loop's default
executor. When MAVSDK 4.1 wedges (PX4 answers a COMMAND_INT with MAV_RESULT 9: MAVSDK reports
UNKNOWN, its callback thread blocks, telemetry stops), those calls never return, `Mavsdk.destroy()`
never returns, and `asyncio.run` waits for the executor for ever on exit (Python 3.11 has no
timeout there), with Ctrl-C ignored. :class:`BoundedRun` replaces `asyncio.run` for `uavloc sim`
and `uavloc fly`:

- the default executor is its own thread pool, shut down without waiting; after the mission it
  gives stuck calls `shutdown_timeout_s` wall seconds, then reports them (:attr:`stuck`);
- SIGINT, SIGTERM, SIGHUP (Ctrl-C, a `kill`, a dropped terminal; :data:`ENDING_SIGNALS`): the
  first cancels the mission (the controller sends RTL within its bounded safe end, logs and closes
  the log), the command ends with exit code 130 as after Ctrl-C; a second exits the process at once
  (exit code 130). Left to their default action, SIGTERM and SIGHUP would end the process with
  the vehicle still flying its last setpoint;
- :meth:`wait_for_ending_signal` (`--view` after the mission ended): the first such signal ends
  that wait instead, and the command exits with the mission's own exit code;
- :meth:`exit_if_stuck`: after the command printed its result, a process with stuck vehicle-library
  threads ends with `os._exit` (the interpreter's exit would wait for them for ever).

Bound after the mission ends: the vehicle adapter's close (``MavsdkVehicle.close_timeout_s``) plus
`shutdown_timeout_s`, plus the final batch estimate.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Coroutine
from concurrent.futures import ThreadPoolExecutor
from typing import Any

log = logging.getLogger(__name__)

#: exit code of a process ended by Ctrl-C (128 + SIGINT), also used after SIGTERM and SIGHUP
EXIT_INTERRUPTED = 130

#: the signals that end a mission the way Ctrl-C does (RTL, end record, exit code 130)
ENDING_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def signal_label(signum: int) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


class BoundedRun:
    """`asyncio.run` with a bounded shutdown and a two-stage Ctrl-C (or SIGTERM, SIGHUP). See the
    module docstring."""

    def __init__(self, shutdown_timeout_s: float = 3.0, max_workers: int = 16):
        self.shutdown_timeout_s = float(shutdown_timeout_s)
        self.max_workers = int(max_workers)
        self.interrupts = 0
        self.stuck = False
        #: exit code of a second ending signal (exits at once): 130, or the mission's own once
        #: the mission had ended (:meth:`wait_for_ending_signal`)
        self.late_exit_code = EXIT_INTERRUPTED
        self._waiting: asyncio.Future[int] | None = None

    def run(self, coro: Coroutine[Any, Any, Any]) -> Any:
        """Run `coro` to completion; re-raises its exception (CancelledError after a Ctrl-C).
        A project error (`UavlocError`) with stuck vehicle-library threads is reported here and
        ends the process with exit code 1 (the CLI's error code), since the interpreter's exit
        would hang."""
        from uavloc.errors import UavlocError

        try:
            return self._run(coro)
        except UavlocError as exc:
            if self.stuck:
                log.error("%s", exc)
                _hard_exit(1)
            raise

    def _run(self, coro: Coroutine[Any, Any, Any]) -> Any:
        loop = asyncio.new_event_loop()
        executor = ThreadPoolExecutor(self.max_workers, thread_name_prefix="uavloc-io")
        loop.set_default_executor(executor)
        task = loop.create_task(coro)
        handled: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for signum in ENDING_SIGNALS:
                previous = signal.getsignal(signum)
                with contextlib.suppress(NotImplementedError, RuntimeError):
                    loop.add_signal_handler(signum, self._on_signal, task, signum)
                    handled[signum] = previous
        try:
            return loop.run_until_complete(task)
        finally:
            for signum in handled:
                loop.remove_signal_handler(signum)
                # until the process ends, a signal after the first one exits at once
                signal.signal(signum, self._on_late_signal)
            self._close_loop(loop, executor)
            if self.interrupts == 0 and not self.stuck:
                for signum, previous in handled.items():
                    signal.signal(signum, previous)  # a clean run leaves the signals as they were

    async def wait_for_ending_signal(self, exit_code: int) -> int:
        """After the mission has ended (the live view kept serving it): wait until SIGINT, SIGTERM
        or SIGHUP and return its number. Such a signal ends this wait instead of cancelling the
        mission; a second one exits at once with `exit_code` (the mission's). Outside the main
        thread no signal handler is installed: only a cancellation ends the wait."""
        self.late_exit_code = exit_code
        self._waiting = asyncio.get_running_loop().create_future()
        try:
            return await self._waiting
        finally:
            self._waiting = None

    def _on_signal(self, task: asyncio.Task, signum: int) -> None:
        self.interrupts += 1
        label = signal_label(signum)
        if self._waiting is not None and not self._waiting.done():
            print(f"\n{label}: closing the live view; the mission had already ended", file=sys.stderr, flush=True)
            self._waiting.set_result(signum)
            return
        if self.interrupts == 1:
            print(f"\n{label}: ending the mission (RTL, log closed); Ctrl-C again exits at once",
                  file=sys.stderr, flush=True)
            task.cancel()
            return
        print(f"\n{label} again: exiting now", file=sys.stderr, flush=True)
        _hard_exit(self.late_exit_code)

    def _on_late_signal(self, signum: int, frame: Any) -> None:
        """An ending signal once the mission's loop has ended (shutdown, result printing)."""
        self.interrupts += 1
        if self.interrupts >= 2 or self.stuck:
            print(f"\n{signal_label(signum)} again: exiting now", file=sys.stderr, flush=True)
            _hard_exit(self.late_exit_code)
        raise KeyboardInterrupt

    def _close_loop(self, loop: asyncio.AbstractEventLoop, executor: ThreadPoolExecutor) -> None:
        t_end = time.monotonic() + self.shutdown_timeout_s
        try:
            pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
            for t in pending:
                t.cancel()
            if pending:
                loop.run_until_complete(asyncio.wait(pending, timeout=self.shutdown_timeout_s))
            with contextlib.suppress(TimeoutError):
                loop.run_until_complete(asyncio.wait_for(loop.shutdown_asyncgens(),
                                                         max(0.1, t_end - time.monotonic())))
        finally:
            executor.shutdown(wait=False, cancel_futures=True)
            for th in list(getattr(executor, "_threads", ())):
                th.join(max(0.0, t_end - time.monotonic()))
            busy = [th.name for th in getattr(executor, "_threads", ()) if th.is_alive()]
            if busy:
                self.stuck = True
                log.error("the vehicle library left %d call(s) stuck (%s): they are abandoned",
                          len(busy), ", ".join(busy))
            from mission.vehicle import vehicle_library_wedged

            if vehicle_library_wedged():
                self.stuck = True
            loop.close()

    def exit_if_stuck(self, code: int) -> None:
        """End the process now with `code` when vehicle-library threads are stuck (after the
        command printed its result): Python's own exit would wait for them for ever."""
        if self.stuck:
            log.warning("exiting without waiting for the stuck vehicle library")
            _hard_exit(code)


def _hard_exit(code: int) -> None:
    """End child processes (the estimator's worker would otherwise outlive us holding our stdout),
    flush what can be flushed and end the process at once."""
    import multiprocessing

    children = multiprocessing.active_children()
    for child in children:
        with contextlib.suppress(Exception):
            child.terminate()
    for child in children:
        with contextlib.suppress(Exception):
            child.join(1.0)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    logging.shutdown()
    os._exit(code)
