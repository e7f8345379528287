"""Where `uavloc fly` and `uavloc sim` write their mission log, checked before anything connects."""

from __future__ import annotations

import logging
import os
from datetime import UTC, datetime
from pathlib import Path

from uavloc.errors import MissionError

#: the mission log's name in an --out folder
LOG_NAME = "mission.jsonl"
#: where a mission without --out (or --log) keeps its log and report: $UAVLOC_RUNS, else this
RUNS_ENV = "UAVLOC_RUNS"
DEFAULT_RUNS = "~/uavloc-runs"

log = logging.getLogger(__name__)


def default_out_dir(command: str, name: str) -> Path:
    """A fresh folder for a mission flown without --out: $UAVLOC_RUNS (default ~/uavloc-runs) /
    <UTC>-<command>-<name>; a mission is never lost for want of an --out. Said on stderr."""
    root = Path(os.environ.get(RUNS_ENV) or DEFAULT_RUNS).expanduser()
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "mission"
    out = root / f"{stamp}-{command}-{safe}"
    n = 1
    while out.exists():
        n += 1
        out = root / f"{stamp}-{command}-{safe}-{n}"
    try:
        out.mkdir(parents=True)
    except OSError as exc:
        raise MissionError(f"cannot make {out} for the mission log ({exc.strerror or exc}): give --out DIR, "
                           f"or set {RUNS_ENV} (not taking off)") from None
    log.warning("no --out: the mission log and report go to %s", out)
    return out


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
