"""Write a report: figures, report.json, report.html and the exports into one directory."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

from mission.report.document import report_document
from mission.report.exports import write_exports
from mission.report.figures import FIG_DPI, FIGURE_FUNCS, FIGURES, figure_title
from mission.report.html import html_page
from mission.report.inputs import ReportInputs, inputs_from_replay
from uavloc.errors import MissionError

log = logging.getLogger(__name__)


def write_report(result_or_inputs: Any, out_dir: str | Path, figures: tuple[str, ...] = FIGURES,
                 exports: bool = True) -> dict[str, Path]:
    """Write the figures, report.json and report.html into `out_dir` (created), and with `exports`
    also mission.geojson, mission.kml and mission.plan (see mission/report/exports.py). Accepts a
    :class:`ReportInputs` or a replay result. Returns {name: path} of every file written."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    inp = result_or_inputs if isinstance(result_or_inputs, ReportInputs) else inputs_from_replay(result_or_inputs)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MissionError(f"cannot create report directory {out}: {exc}") from exc
    unknown = sorted(set(figures) - set(FIGURE_FUNCS))
    if unknown:
        raise MissionError(f"unknown report figure(s) {unknown}; known: {', '.join(FIGURES)}")
    t0 = time.perf_counter()
    paths: dict[str, Path] = {}
    pngs: dict[str, bytes] = {}
    for name in figures:
        fig = FIGURE_FUNCS[name](plt, inp)
        try:
            path = out / f"{name}.png"
            fig.savefig(path, dpi=FIG_DPI)
        except OSError as exc:
            raise MissionError(f"cannot write {out / name}.png: {exc}") from exc
        finally:
            plt.close(fig)
        paths[name] = path
        pngs[name] = path.read_bytes()
    doc = report_document(inp, {name: p.name for name, p in paths.items()})
    try:
        (out / "report.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        captions = {name: figure_title(name, inp) for name in pngs}
        (out / "report.html").write_text(html_page(doc, pngs, captions), encoding="utf-8")
    except OSError as exc:
        raise MissionError(f"cannot write the report into {out}: {exc}") from exc
    paths["report.json"] = out / "report.json"
    paths["report.html"] = out / "report.html"
    if exports:
        paths.update(write_exports(inp, out))
    log.info("report: %d figures, report.json, report.html in %s (%.1f s)", len(figures), out,
             time.perf_counter() - t0)
    return paths
