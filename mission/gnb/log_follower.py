"""The gNB log as the stock modes read it: followed like `tail -f`, every line fed to
:class:`mission.gnb.oai_ra.RaTracker`, and what the lines proved kept per UE (docs/design.md §8).

:class:`StockLog` is what :class:`mission.gnb.OaiGnbClient` owns in stock mode: the RNTI changes
a log line proved (and only those), the random accesses it proved, and the round-trip ones not yet
returned as measurements. No sockets; the file is read when asked.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable
from pathlib import Path

from mission.gnb.clock_offset import ClockOffset
from mission.gnb.oai import Msg2Record, RttSample, sample_from_msg2
from mission.gnb.oai_ra import RandomAccess, RaTracker, RntiChange, parse_stamp
from uavloc.errors import GnbError, GnbNoMeasurementError, GnbProtocolError

log = logging.getLogger(__name__)

#: the log stamps that are the gNB host's wall time
WALL_STAMPS = ("wall_clock", "utc_time")
#: stamped log lines needed before the log's clock offset counts as bounded (a random access
#: writes three or more)
LOG_OFFSET_MIN_SAMPLES = 3


class LogFollower:
    """Follow a growing log file like `tail -f` (polling, no threads).

    Handles a file that does not exist yet, and truncation/rotation (restarts from the beginning).
    """

    def __init__(self, path: Path, poll_s: float = 0.01) -> None:
        self.path = Path(path)
        self.poll_s = poll_s
        self.position = 0
        self._partial = b""

    def _size(self) -> int:
        try:
            return self.path.stat().st_size
        except FileNotFoundError:
            return 0

    def mark(self) -> None:
        """Forget everything written so far: later reads start at the current end of the file."""
        self.position = self._size()
        self._partial = b""

    def read_lines(self) -> list[str]:
        """Complete lines appended since the last read (a partial last line is kept for later)."""
        size = self._size()
        if size < self.position:  # truncated or rotated
            log.info("gNB log %s shrank (%d < %d): reading from the start", self.path, size, self.position)
            self.position, self._partial = 0, b""
        if size == self.position:
            return []
        try:
            with self.path.open("rb") as fh:
                fh.seek(self.position)
                data = fh.read(min(size - self.position, 1 << 22))
        except OSError as exc:
            raise GnbError(f"cannot read the gNB log {self.path}: {exc}") from exc
        self.position += len(data)
        data = self._partial + data
        *complete, self._partial = data.split(b"\n")
        return [ln.decode("utf-8", errors="replace") for ln in complete]


class StockLog:
    """What a gNB log proved so far (stock modes).

    path: the gNB log; poll_s: polling period of the follower [s]; history: read the log from its
    start (else from its end at start()). rnti_alias: an RNTI -> the RNTI that UE has now (proven
    by a `Reestablishment RNTI <new> req C-RNTI <old>` line); rnti_changes: those proofs;
    recent: every random access proven, newest last; stamps: time-stamp kinds seen; offset: the
    gNB host's clock against `wall`, from every wall-clock-stamped line's arrival − stamp
    (mission.gnb.clock_offset; not for a log read from its start, whose lines did not arrive when
    written).
    """

    def __init__(self, path: Path, poll_s: float = 0.01, history: bool = False,
                 wall: Callable[[], float] = time.time) -> None:
        self.path = Path(path)
        self.follower = LogFollower(self.path, poll_s)
        self.history = history
        self.tracker = RaTracker()
        self._started = False
        #: round-trip random accesses not yet returned, by the UE's RNTI at that access
        self._fresh: dict[int, list[RandomAccess]] = {}
        self.recent: collections.deque[RandomAccess] = collections.deque(maxlen=256)
        self.rnti_changes: list[RntiChange] = []
        self.rnti_alias: dict[int, int] = {}
        self.wall = wall
        self.offset = ClockOffset(min_samples=LOG_OFFSET_MIN_SAMPLES)

    def start(self) -> None:
        """Begin following (at the end of the file unless `history`); later calls do nothing."""
        if not self._started:
            if not self.history:
                self.follower.mark()
            self._started = True

    @property
    def stamps(self) -> dict[str, int]:
        return dict(self.tracker.stamps)

    def current_rnti(self, rnti: int) -> int:
        """The RNTI the UE first known as `rnti` has now (through proven RNTI changes only)."""
        seen = {rnti}
        while (nxt := self.rnti_alias.get(rnti)) is not None and nxt not in seen:
            seen.add(nxt)
            rnti = nxt
        return rnti

    def feed(self) -> list[RandomAccess | RntiChange]:
        """Read the new lines and return what they proved. A malformed random-access line is
        logged and skipped: the lines after it still count."""
        self.start()
        out: list[RandomAccess | RntiChange] = []
        lines = self.follower.read_lines()
        if lines and not self.history:
            arrival = self.wall()
            for line in lines:
                t_s, kind = parse_stamp(line)
                if t_s is not None and kind in WALL_STAMPS:
                    self.offset.add(arrival, t_s)
        for line in lines:
            try:
                events = self.tracker.feed(line)
            except GnbProtocolError as exc:
                log.warning("skipping a malformed gNB log line: %s", exc)
                continue
            for ev in events:
                if isinstance(ev, RntiChange):
                    log.info("UE %04x is now %04x (%s)", ev.old, ev.new, ev.proof)
                    self.rnti_changes.append(ev)
                    self.rnti_alias[ev.old] = ev.new
                else:
                    log.debug("random access: %s", ev.describe())
                    self.recent.append(ev)
                    if ev.round_trip:
                        self._fresh.setdefault(ev.tc_rnti, []).append(ev)
                out.append(ev)
        return out

    def take_fresh(self, rnti: int) -> list[RandomAccess]:
        """The round-trip accesses of the UE whose RNTI at the access was `rnti`, not yet taken."""
        return self._fresh.pop(rnti, [])

    def forget(self, ra: RandomAccess) -> None:
        """Mark one access as taken."""
        lst = self._fresh.get(ra.tc_rnti, [])
        if ra in lst:
            lst.remove(ra)

    def sample(self, ra: RandomAccess, rnti: int, mu: int, clock: Callable[[], float],
               wall: Callable[[], float], require_wall: bool) -> RttSample:
        """A coarse RttSample of the UE `rnti` from a proven random access.

        Timed by the Msg2 line's wall_clock (or utc_time) stamp, mapped to the monotonic clock:
        t_mono = clock() − (wall() − t_log). Without such a stamp the sample is timed when read,
        or, with require_wall (passive mode: the access may be old), refused.
        """
        rec = Msg2Record(ra.tc_rnti, ra.frame, ra.slot, ra.timing_offset, None, ra.preamble)
        now = clock()
        if ra.t_s is not None and ra.stamp in WALL_STAMPS:
            if self.history:  # a log read from its start: its stamps taken at face value
                return sample_from_msg2(rec, rnti, mu, now - max(0.0, wall() - ra.t_s), ra.t_s)
            est = self.offset.estimate(self.wall())
            if est is None or not est.bounded:
                self.offset.refused += 1
                raise GnbNoMeasurementError(
                    f"the random access of UE {rnti:04x} at {ra.t_s:.3f} (gNB clock) cannot be placed in time: "
                    f"the gNB host's clock offset is not bounded ({self.offset.why_unbounded(est)})")
            # the stamp in our wall time: s + θ̂ (mission.gnb.clock_offset)
            t_mono = now - max(0.0, wall() - (ra.t_s + est.offset_s))
            return sample_from_msg2(rec, rnti, mu, t_mono, ra.t_s, t_unc_s=est.spread_s)
        if require_wall:
            raise GnbNoMeasurementError(
                f"the gNB log {self.path} has no wall_clock time stamps (found {ra.stamp!r}): a passive "
                f"random access cannot be placed in time; run the gNB with "
                f"--log_config.global_log_options level,nocolor,wall_clock")
        return sample_from_msg2(rec, rnti, mu, now, t_unc_s=self.follower.poll_s)


__all__ = ["LogFollower", "StockLog"]
