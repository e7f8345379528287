"""Where `uavloc fly` and `uavloc sim` write their mission log, checked before anything connects."""

from __future__ import annotations

from pathlib import Path

from uavloc.errors import MissionError

#: the mission log's name in an --out folder
LOG_NAME = "mission.jsonl"


def mission_log_path(out_dir: Path | None, log_path: Path | None, default: Path) -> Path:
    """The mission log to write: `log_path`, else `out_dir`/mission.jsonl, else `default`.

    Refused (MissionError naming the path) before the mission starts: an `out_dir` that is not a
    folder, a log path that is a folder, and a log that already holds a mission (a second header
    makes a log unreadable for replay; overwriting loses the first mission and leaves its report
    beside the new log)."""
    if out_dir is not None and out_dir.exists() and not out_dir.is_dir():
        raise MissionError(f"--out {out_dir} is a file, not a folder: give a folder for the mission log and "
                           "report (not taking off)")
    if log_path is None:
        log_path = out_dir / LOG_NAME if out_dir is not None else default
    if log_path.is_dir():
        raise MissionError(f"mission log {log_path} is a folder: give a file name (not taking off)")
    if log_path.exists() and log_path.stat().st_size > 0:
        raise MissionError(f"mission log {log_path} already holds a mission: give another --log or --out, "
                           "or move it away (not taking off)")
    return log_path
