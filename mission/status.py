"""What `uavloc fly` and `uavloc sim` print at the end of a mission, and the report they write.

The JSON document is docs/design.md §11 (plus `reason`, `keyframes`, `log`, and `speedup`: the
survey's requested and achieved speed-up, mission.control.state.SurveyPace); the human-readable lines
use the same per-user table as `uavloc replay`. `--out DIR` writes the report of the mission's own
log (replayed, so the report shows exactly what replay would).
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import TextIO

from mission.control.config import MissionResult

log = logging.getLogger(__name__)


def mission_document(result: MissionResult) -> dict:
    """The docs/design.md §11 document of a mission result."""
    doc = result.to_document()
    doc["keyframes"] = result.keyframes
    doc["log"] = str(result.log_path) if result.log_path is not None else None
    doc["speedup"] = result.pace.to_dict() if result.pace is not None else None
    return doc


def print_result(result: MissionResult, as_json: bool, stream: TextIO | None = None) -> dict:
    """Print the result on stdout: one JSON document with `as_json`, else a short table."""
    from mission.replay import format_users_table

    out = stream or sys.stdout
    doc = mission_document(result)
    if as_json:
        json.dump(doc, out, indent=2)
        out.write("\n")
    else:
        out.write(f"mission {result.status} ({result.reason}): {result.measurements} ranges, "
                  f"{result.keyframes} keyframes, {result.flown_m:.0f} m flown\n")
        users = []
        for u in doc["users"]:
            u = dict(u)
            u.setdefault("measurements", 0)
            u.setdefault("ambiguous", False)
            u.setdefault("error_bound_95_m", None)
            users.append(u)
        out.write(format_users_table({"users": users}) + "\n")
        if result.log_path is not None:
            out.write(f"mission log: {result.log_path}\n")
    missing = result.not_located()
    if missing and result.status != "interrupted":
        log.error("not located: %s (the mission exits non-zero)", ", ".join(missing))
    out.flush()
    return doc


def write_report(log_path: str | Path, out_dir: str | Path) -> dict[str, Path]:
    """Replay the mission log and write the report (figures, report.json/html, exports) to out_dir."""
    from mission.log import read_mission_log
    from mission.replay import ReplayOptions, replay
    from mission.report import write_report as _write

    mlog = read_mission_log(log_path)
    paths = _write(replay(mlog, ReplayOptions()), out_dir)
    log.info("report written to %s", out_dir)
    return paths
