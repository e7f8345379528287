"""Event records are stamped in the order they happen: the vehicle clock's mapping of the
monotonic clock is refitted as fixes arrive, and a refit between two events once stamped an
`rtl` 31 ms before the `return` that caused it (tests/test_mission_failures.py, in a loaded run)."""

from __future__ import annotations

import json

from mission.control.journal import MissionJournal
from mission.log import MissionLogWriter


def test_an_event_is_never_stamped_before_the_event_written_before_it(tmp_path):
    times = iter([128.021508, 127.990654, 130.0])  # "now" as a refitted clock gave it
    path = tmp_path / "m.jsonl"
    writer = MissionLogWriter(path)
    writer.open()
    journal = MissionJournal(writer, [], now=lambda: next(times), phase=lambda: "RETURN")
    for kind in ("return", "rtl", "landed"):
        journal.event(kind, kind=kind)
    recs = [json.loads(line) for line in path.read_text().splitlines()]
    assert [(r["kind"], r["t"]) for r in recs] == [("return", 128.021508), ("rtl", 128.021508),
                                                   ("landed", 130.0)]
