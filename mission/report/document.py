"""The content of report.json: the mission's result document (mission.result.Result.to_document,
the same as `--json` prints) and the report's own sections, which never redefine one of its keys:
title, the mission (command, scenario, seed, planner, date, version: the log header's), the noise
model, the range statistics per user, the figure files."""

from __future__ import annotations

import numpy as np

from mission.report.inputs import ReportInputs
from mission.report.statistics import range_errors
from mission.result import finite_or_none
from uavloc.errors import MissionError


def report_document(inp: ReportInputs, figures: dict[str, str] | None = None) -> dict:
    """report.json: the result document, and `title`, `mission` (ReportInputs.facts, when the
    inputs come from a log: MissionFacts.to_dict), `noise` (the estimator's model, as the log
    header writes it), `range_statistics` ({user id: {reference, mean_m, std_m}}: the range error
    r̂ − d against the true users when known, else the estimated ones), `figures` ({name: file})
    and `extra` when the inputs carry any."""
    doc = inp.result.to_document()
    _d, e, which = range_errors(inp)
    stats = {}
    for k, uid in enumerate(inp.user_ids):
        sel = inp.meas_user == k
        stats[uid] = {"reference": which, "ranges": int(np.sum(sel)),
                      "mean_m": finite_or_none(np.mean(e[sel])) if sel.any() else None,
                      "std_m": finite_or_none(np.std(e[sel])) if sel.sum() > 1 else None}
    report = {"title": inp.title, **({"mission": inp.facts.to_dict()} if inp.facts is not None else {}),
              "noise": inp.noise.to_log_dict(), "range_statistics": stats,
              "figures": figures or {}, **({"extra": inp.extra} if inp.extra else {})}
    clash = sorted(set(report) & set(doc))
    if clash:
        raise MissionError(f"report sections would redefine the result's {clash}")
    return {**doc, **report}
