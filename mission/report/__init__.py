"""Mission report (docs/design.md §11 `--out DIR`): figures in the spirit of the paper, `report.json`,
a self-contained `report.html`, and GeoJSON / KML / QGroundControl exports.

One direction, no cycle: `inputs` (what is drawn: :class:`ReportInputs`, the log header's shapes)
← `statistics` (ellipses, range errors) ← `figures`, `document` (report.json, through the one
per-user result builder of mission/result.py), `exports` ← `html` ← `write` (:func:`write_report`).
"""

from mission.report.document import report_document
from mission.report.figures import FIG_DPI, FIG_SIZE_IN, FIGURES
from mission.report.inputs import (
    MissionShapes,
    ReportInputs,
    inputs_from_replay,
    shapes_from_header,
    waypoints_from_log,
)
from mission.report.statistics import ellipse_en_m, range_errors
from mission.report.write import write_report

__all__ = [
    "FIGURES",
    "FIG_DPI",
    "FIG_SIZE_IN",
    "MissionShapes",
    "ReportInputs",
    "ellipse_en_m",
    "inputs_from_replay",
    "range_errors",
    "report_document",
    "shapes_from_header",
    "waypoints_from_log",
    "write_report",
]
