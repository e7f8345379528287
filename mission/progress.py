"""Progress on stderr for long work: a redrawn bar on a terminal, a log line every 10 % otherwise."""

from __future__ import annotations

import logging
import sys
import time
from typing import TextIO

log = logging.getLogger(__name__)


class Progress:
    """Call `update(done)` as work advances and `close()` at the end.

    `total` steps; nothing is shown for fewer than `min_total` steps. On a TTY the bar is redrawn
    at most every 0.1 s; otherwise an INFO log line is written at each 10 % step.
    """

    def __init__(self, label: str, total: int, stream: TextIO | None = None, min_total: int = 200):
        self.label = label
        self.total = max(int(total), 0)
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = self.total >= min_total
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_draw = 0.0
        self._last_decile = -1
        self._t0 = time.monotonic()

    def update(self, done: int) -> None:
        if not self.enabled:
            return
        frac = min(max(done / self.total, 0.0), 1.0)
        if self.tty:
            now = time.monotonic()
            if now - self._last_draw < 0.1 and done < self.total:
                return
            self._last_draw = now
            width = 30
            bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
            self.stream.write(f"\r{self.label} [{bar}] {done}/{self.total} ({frac:4.0%})")
            self.stream.flush()
        else:
            decile = int(frac * 10)
            if decile > self._last_decile:
                self._last_decile = decile
                log.info("%s: %d/%d (%d%%)", self.label, done, self.total, decile * 10)

    def close(self) -> None:
        if self.enabled and self.tty:
            self.stream.write(f"\r{self.label}: {self.total}/{self.total} done in "
                              f"{time.monotonic() - self._t0:.1f} s" + " " * 20 + "\n")
            self.stream.flush()
