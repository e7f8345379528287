"""Event-loop helpers of the controller: a pulse that wakes every waiter, and the loop-lag monitor."""

from __future__ import annotations

import asyncio

import numpy as np


class Pulse:
    """Wake every waiter on the next `pulse()` (a new Event per generation)."""

    def __init__(self) -> None:
        self._event = asyncio.Event()

    def pulse(self) -> None:
        self._event.set()
        self._event = asyncio.Event()

    async def wait(self, timeout_s: float) -> bool:
        try:
            async with asyncio.timeout(timeout_s):
                await self._event.wait()
            return True
        except TimeoutError:
            return False


class LoopLagMonitor:
    """Measures event-loop lag: how late a `sleep(period)` wakes up [s]. Kept as a sample list."""

    def __init__(self, period_s: float = 0.01):
        self.period_s = period_s
        self.lags_s: list[float] = []

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            t = loop.time()
            await asyncio.sleep(self.period_s)
            self.lags_s.append(max(0.0, loop.time() - t - self.period_s))

    def summary(self) -> dict:
        """{"samples", "max_s", "p99_s", "median_s"} (zeros before the first sample)."""
        if not self.lags_s:
            return {"samples": 0, "max_s": 0.0, "p99_s": 0.0, "median_s": 0.0}
        a = np.asarray(self.lags_s)
        return {"samples": len(a), "max_s": float(a.max()), "p99_s": float(np.percentile(a, 99)),
                "median_s": float(np.median(a))}
