"""Checks of the mission log reader (mission.log.read_mission_log) that hold across records.

:class:`LineError` is a record's fault (the reader adds the file and line); :class:`RangeRecords`
keeps each rtt record's (vehicle, user, time), so a range counts once (docs/design.md §10).
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)


class LineError(Exception):
    """What is wrong with one record; mission.log.read_mission_log raises it as a
    MissionLogError naming the file and the line."""


class RangeRecords:
    """The rtt records seen, by (vehicle, user, t): one measurement has one value. An exact repeat
    of an earlier record (a line written twice, a log concatenated with itself) is dropped and
    counted, never counted again as evidence (it would shrink the bound); a record of the same
    user, vehicle and time with another range or position contradicts the earlier one: refused."""

    def __init__(self, path: Path):
        self.path = path
        self.seen: dict[tuple[int, int, float], tuple[int, tuple]] = {}
        self.dropped = 0
        self.first_dropped_line: int | None = None
        self.first_of: int | None = None

    def first(self, lineno: int, key: tuple[int, int, float], values: tuple) -> bool:
        """True for a record not seen before; False for an exact repeat (counted); raises on a contradiction."""
        prev = self.seen.setdefault(key, (lineno, values))
        if prev[0] == lineno:
            return True
        if prev[1] != values:
            raise LineError(f"rtt record of the same user and vehicle at the same time (t = {key[2]:g} s) as the one "
                            f"on line {prev[0]}, with another range or position: one measurement has one value "
                            "(refused)")
        self.dropped += 1
        if self.first_dropped_line is None:
            self.first_dropped_line, self.first_of = lineno, prev[0]
        return False

    def warn(self) -> None:
        if self.dropped:
            log.warning("%s: dropped %d duplicate rtt record(s), first on line %d (a repeat of line %d: same user, "
                        "vehicle, time and values); each measurement counts once", self.path, self.dropped,
                        self.first_dropped_line, self.first_of)

