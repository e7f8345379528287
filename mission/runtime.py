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
  (exit code 130), after the last resort below. Left to their default action, SIGTERM and SIGHUP
  would end the process with the vehicle still flying its last setpoint;
- the signals are received by a watchdog thread, not by the event loop: asyncio's own signal
  handling writes each signal into the loop's self-pipe, which `call_soon_threadsafe` from the
  vehicle library's threads also fills; a loop too busy to drain it (50 vehicles at x20) lost
  every signal ("Exception ignored when trying to write to the signal wakeup fd:
  BlockingIOError"). Here the signal's byte goes to a pipe of the watchdog's own
  (`signal.set_wakeup_fd`), which nothing else writes, and the watchdog asks the loop to cancel
  the mission (`call_soon_threadsafe`). When the loop has not run that request within
  `answer_timeout_s`, or not ended within `signal_grace_s`, the watchdog calls the mission's
  :attr:`BoundedRun.last_resort` itself (RTL to every vehicle that may be in the air through the
  vehicle library's blocking calls, the log's end record: mission.control.last_resort), bounded by
  `last_resort_timeout_s`, and exits with code 130 (`os._exit`);
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
import select
import signal
import sys
import threading
import time
from collections.abc import Callable, Coroutine
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

    def __init__(self, shutdown_timeout_s: float = 3.0, max_workers: int = 16, answer_timeout_s: float = 5.0,
                 signal_grace_s: float = 15.0, last_resort_timeout_s: float = 5.0):
        self.shutdown_timeout_s = float(shutdown_timeout_s)
        self.max_workers = int(max_workers)
        #: wall seconds the loop has to run the cancellation an ending signal asks for, and to
        #: end the mission after it, before the watchdog acts alone (module docstring)
        self.answer_timeout_s = float(answer_timeout_s)
        self.signal_grace_s = float(signal_grace_s)
        #: wall seconds the last resort may take before the process exits anyway
        self.last_resort_timeout_s = float(last_resort_timeout_s)
        #: the mission's last resort, set by the command once its controller exists: called with a
        #: reason from the watchdog thread while the event loop does not answer; it must not need
        #: the loop (mission.control.last_resort)
        self.last_resort: Callable[[str], None] | None = None
        self.interrupts = 0
        self.stuck = False
        #: exit code of a second ending signal (exits at once): 130, or the mission's own once
        #: the mission had ended (:meth:`wait_for_ending_signal`)
        self.late_exit_code = EXIT_INTERRUPTED
        self._waiting: asyncio.Future[int] | None = None
        self._mission_over = False  # the command waits for a signal after the mission (the live view)
        self._answered = threading.Event()  # the loop ran the cancellation a signal asked for
        self._loop_done = threading.Event()  # the mission's coroutine has ended

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
        self._loop_done.clear()
        watch = _SignalWatch(self, loop, task) if threading.current_thread() is threading.main_thread() else None
        try:
            return loop.run_until_complete(task)
        finally:
            self._loop_done.set()
            if watch is not None:
                # until the process ends, a signal after the first one exits at once
                watch.stop(self._on_late_signal)
            self._close_loop(loop, executor)
            if watch is not None and self.interrupts == 0 and not self.stuck:
                watch.restore()  # a clean run leaves the signals as they were

    async def wait_for_ending_signal(self, exit_code: int) -> int:
        """After the mission has ended (the live view kept serving it): wait until SIGINT, SIGTERM
        or SIGHUP and return its number. Such a signal ends this wait instead of cancelling the
        mission; a second one exits at once with `exit_code` (the mission's). Outside the main
        thread no signal handler is installed: only a cancellation ends the wait."""
        self.late_exit_code = exit_code
        self._mission_over = True
        self._waiting = asyncio.get_running_loop().create_future()
        try:
            return await self._waiting
        finally:
            self._waiting = None

    def _on_signal(self, task: asyncio.Task, signum: int) -> None:
        """In the event loop, asked by the watchdog (:class:`_SignalWatch`): the first ending signal."""
        self._answered.set()
        label = signal_label(signum)
        if self._waiting is not None and not self._waiting.done():
            print(f"\n{label}: closing the live view; the mission had already ended", file=sys.stderr, flush=True)
            self._waiting.set_result(signum)
            return
        print(f"\n{label}: ending the mission (RTL, log closed); Ctrl-C again exits at once",
              file=sys.stderr, flush=True)
        task.cancel()

    def _act_alone(self, why: str) -> None:
        """In the watchdog thread, the loop not answering (or a second signal): the mission's last
        resort, bounded, then exit. Never returns."""
        code = self.late_exit_code
        # whatever blocks below (a wedged vehicle library, a full stderr pipe), the process ends
        threading.Thread(target=_exit_after, args=(self.last_resort_timeout_s + 3.0, code),
                         name="uavloc-reaper", daemon=True).start()
        _say(f"{why}: exiting now")
        if not self._mission_over and not self._loop_done.is_set():
            resort = self.last_resort
            if resort is None:
                _say("no vehicle was connected: nothing to send home")
            else:
                th = threading.Thread(target=_call_logged, args=(resort, why), name="uavloc-last-resort", daemon=True)
                th.start()
                th.join(self.last_resort_timeout_s)
                if th.is_alive():
                    _say(f"the last resort did not finish within {self.last_resort_timeout_s:g} s")
        _hard_exit(code)

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


class _SignalWatch:
    """The watchdog of ending signals (module docstring): a thread reading the signal numbers that
    Python's C-level handler writes into a pipe of its own (`signal.set_wakeup_fd`), so a signal
    is received however busy the event loop, and acted on by :class:`BoundedRun`."""

    def __init__(self, runner: BoundedRun, loop: asyncio.AbstractEventLoop, task: asyncio.Task):
        self.runner, self.loop, self.task = runner, loop, task
        self._read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._write_fd, False)
        self.previous = {signum: signal.getsignal(signum) for signum in ENDING_SIGNALS}
        # a Python handler makes the C-level one write the signal's number into the wakeup fd;
        # the work is the watchdog's, whatever the main thread is doing
        for signum in ENDING_SIGNALS:
            signal.signal(signum, _ignore)
        self._old_wakeup_fd = signal.set_wakeup_fd(self._write_fd, warn_on_full_buffer=False)
        self.thread = threading.Thread(target=self._watch, name="uavloc-signals", daemon=True)
        self.thread.start()

    def stop(self, late_handler: Callable[[int, Any], None]) -> None:
        """The mission's coroutine has ended: later signals go to `late_handler` (main thread)."""
        for signum in ENDING_SIGNALS:
            signal.signal(signum, late_handler)
        signal.set_wakeup_fd(self._old_wakeup_fd)
        os.close(self._write_fd)  # the watchdog reads the end of its pipe and ends
        self.thread.join(1.0)

    def restore(self) -> None:
        for signum, previous in self.previous.items():
            signal.signal(signum, previous)

    def _watch(self) -> None:
        r = self.runner
        answer_by = deadline = None
        try:
            while True:
                now = time.monotonic()
                if deadline is not None and not r._loop_done.is_set():
                    if not r._answered.is_set() and now >= answer_by:
                        r._act_alone(f"the event loop did not answer the signal within {r.answer_timeout_s:g} s")
                    if now >= deadline:
                        r._act_alone(f"the mission did not end within {r.signal_grace_s:g} s of the signal")
                wait_s = None
                if deadline is not None:
                    wake_at = deadline if r._answered.is_set() else answer_by
                    wait_s = max(0.05, wake_at - now)
                ready, _, _ = select.select([self._read_fd], [], [], wait_s)
                if not ready:
                    continue
                data = os.read(self._read_fd, 64)
                if not data:
                    return  # stop(): the mission's coroutine has ended
                for signum in data:
                    if signum not in ENDING_SIGNALS or r._loop_done.is_set():
                        continue
                    r.interrupts += 1
                    if r.interrupts == 1:
                        now = time.monotonic()
                        answer_by, deadline = now + r.answer_timeout_s, now + r.signal_grace_s
                        try:
                            self.loop.call_soon_threadsafe(r._on_signal, self.task, signum)
                        except RuntimeError:  # the loop is closed: the mission has ended
                            return
                    else:
                        r._act_alone(f"{signal_label(signum)} again")
        finally:
            os.close(self._read_fd)


def _forget_wakeup_fd() -> None:
    """In a forked child (the watchdog's pipe inherited): its signals are not the parent's."""
    with contextlib.suppress(ValueError, OSError):
        signal.set_wakeup_fd(-1)


# a fork (not used by uavloc's own children, which are spawned or exec'd) would otherwise write its
# signals into the parent's watchdog pipe
os.register_at_fork(after_in_child=_forget_wakeup_fd)


def _ignore(signum: int, frame: Any) -> None:
    """The Python-level handler of an ending signal while the watchdog receives them."""


def _say(message: str) -> None:
    """A line on stderr from the watchdog: one write, no lock the main thread may hold."""
    with contextlib.suppress(OSError):
        os.write(2, f"\n{message}\n".encode())


def _call_logged(fn: Callable[[str], None], why: str) -> None:
    try:
        fn(why)
    except Exception as exc:  # the last resort is reported, never raised in a bare thread
        _say(f"the last resort failed: {type(exc).__name__}: {exc}")


def _exit_after(delay_s: float, code: int) -> None:
    time.sleep(delay_s)
    os._exit(code)


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
