"""Campaign results on disk: Parquet parts in `<out>/results/`, one row per run, written as runs finish.

Each flush writes a new part file atomically (written beside, then renamed), so a campaign killed at
any moment leaves only whole files, and the next run of the same spec reads them to skip the runs
already done (resume). Reading merges the parts; a key present twice (a retried run) keeps its
last record.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from uavloc.errors import CampaignError

_f, _i, _s = pa.float64(), pa.int64(), pa.string()
_fl = pa.list_(pa.float64())

#: one row per run (task.run_one's record); list columns are aligned with `targets_m` or with the users;
#: parts written before a column existed read it as null (n_vehicles: those runs flew one vehicle)
SCHEMA = pa.schema([
    ("key", _s), ("condition", _s), ("scenario", _s), ("planner", _s), ("estimator", _s), ("n_vehicles", _i),
    ("seed", _i),
    ("mode", _s), ("source", _s),
    ("users", _i), ("buildings", _i), ("no_fly", _i), ("fence_vertices", _i), ("gps_sigma_m", _f),
    ("gps_tau_s", _f), ("sawtooth_max_m", _f), ("nlos_excess_mean_m", _f), ("range_s0_m", _f), ("range_a_m", _f),
    ("status", _s), ("error", _s), ("traceback", _s), ("end", _s),
    ("targets_m", _fl), ("budget_m", _f), ("metres_to_m", _fl), ("seconds_to_s", _fl),
    ("error_at_m", _fl), ("hover_s", _f), ("survey_s", _f), ("floor_m", _f),
    ("flown_m", _f), ("keyframes", _i), ("replans", _i), ("plan_times_s", _fl), ("plan_median_s", _f),
    ("plan_p95_s", _f), ("final_error_m", _fl), ("final_bound95_m", _fl), ("final_nees", _fl),
    ("mean_error_m", _f), ("max_error_m", _f), ("inside95", _f), ("nlos_share", _f), ("violations", _i),
    ("first_violation", _s), ("estimator_errors", _i), ("first_estimator_error", _s),
    ("wall_s", _f), ("worker", _s),
])


def records_to_table(records: list[dict]) -> pa.Table:
    """Records → a table of SCHEMA (missing fields null; an unknown field is a programming error)."""
    names = set(SCHEMA.names)
    for r in records:
        extra = set(r) - names
        if extra:
            raise CampaignError(f"record {r.get('key')!r} has fields outside the results schema: {sorted(extra)}")
    cols = {name: [r.get(name) for r in records] for name in SCHEMA.names}
    return pa.table(cols, schema=SCHEMA)


class ResultsStore:
    """The Parquet parts of one output folder (`<out_dir>/results/part-*.parquet`)."""

    def __init__(self, out_dir: str | Path):
        self.dir = Path(out_dir) / "results"

    def parts(self) -> list[Path]:
        return sorted(self.dir.glob("part-*.parquet")) if self.dir.is_dir() else []

    def append(self, records: list[dict]) -> Path | None:
        """Write records as a new part (atomically); returns its path (None for no records)."""
        if not records:
            return None
        self.dir.mkdir(parents=True, exist_ok=True)
        path = self.dir / f"part-{time.time_ns():020d}-{os.getpid()}.parquet"
        tmp = path.with_suffix(".tmp")
        pq.write_table(records_to_table(records), tmp)
        os.replace(tmp, path)
        return path

    def read_records(self) -> list[dict]:
        """Every record of every part, the last one of each key kept, in part order."""
        by_key: dict[str, dict] = {}
        for part in self.parts():
            try:
                table = pq.read_table(part, schema=SCHEMA)
            except (pa.ArrowInvalid, OSError) as exc:
                raise CampaignError(f"{part}: not a readable results part: {exc}") from exc
            for rec in table.to_pylist():
                by_key[rec["key"]] = rec
        return list(by_key.values())

    def compact(self) -> None:
        """Merge the parts into one (write the merged part first, then remove the old ones)."""
        old = self.parts()
        if len(old) <= 1:
            return
        self.append(self.read_records())
        for p in old:
            p.unlink()


def same_value(a, b, rel: float = 0.0) -> bool:
    """Equality of record values with NaN equal to NaN (lists element-wise); floats within `rel`
    of each other (relative) count as equal."""
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same_value(x, y, rel) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float):
        if math.isnan(a) and math.isnan(b):
            return True
        return a == b or abs(a - b) <= rel * max(abs(a), abs(b))
    return a == b
