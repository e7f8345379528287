"""What `uavloc fly` and `uavloc sim` print at the end of a mission, and the report they write.

Both are renderings of the mission's one :class:`mission.result.Result`: the JSON document is
:meth:`Result.to_document` (docs/design.md §11), the human-readable lines
:func:`mission.result.format_result`, as `uavloc replay` prints them. `--out DIR` writes the report
of the mission's own log (replayed, so the report shows exactly what replay would).
The JSON document of a mission adds `speedup`: the survey's requested and achieved speed-up
(mission.control.config.SurveyPace), a fact of the run, not of its log.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import TextIO

from mission.control.config import STATUS_INTERRUPTED, MissionResult
from mission.result import Result, format_result

log = logging.getLogger(__name__)


def mission_document(result: MissionResult) -> dict:
    """The JSON document of a mission: its Result's, with the survey's `speedup` when it had one."""
    doc = result.result.to_document()
    if result.pace is not None:
        doc["speedup"] = result.pace.to_dict()
    return doc


def print_result(result: MissionResult | Result, as_json: bool, stream: TextIO | None = None) -> dict:
    """Print the result on stdout: its JSON document with `as_json`, else the short summary."""
    res = result.result if isinstance(result, MissionResult) else result
    out = stream or sys.stdout
    doc = mission_document(result) if isinstance(result, MissionResult) else res.to_document()
    if as_json:
        json.dump(doc, out, indent=2, allow_nan=False)
        out.write("\n")
    else:
        out.write(format_result(res) + "\n")
    note = res.status_note()
    if note is not None:
        log.warning("%s", note)
    missing = res.not_located()
    if missing and res.status != STATUS_INTERRUPTED and isinstance(result, MissionResult):
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
