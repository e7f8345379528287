"""The content of report.json: summary, the per-user result document (mission.result) with the
report's range statistics, the noise model and the figure files."""

from __future__ import annotations

import numpy as np

from mission.report.inputs import ReportInputs
from mission.report.statistics import range_errors
from mission.result import finite_or_none, user_entries


def report_document(inp: ReportInputs, figures: dict[str, str] | None = None) -> dict:
    """The content of report.json: summary, users, noise model, range statistics, figure files."""
    _d, e, which = range_errors(inp)
    users = user_entries(inp.user_ids, inp.origin, inp.users_enu_m, inp.cov_en_m2,
                         measurements=[int(np.sum(inp.meas_user == k)) for k in range(inp.n_users)],
                         ambiguous=inp.ambiguous, bias_m=inp.bias_m, truth_enu_m=inp.truth_enu_m)
    for k, entry in enumerate(users):
        sel = inp.meas_user == k
        entry["range_error_mean_m"] = finite_or_none(np.mean(e[sel])) if sel.any() else None
        entry["range_error_std_m"] = finite_or_none(np.std(e[sel])) if sel.sum() > 1 else None
    return {
        "title": inp.title,
        "status": inp.status,
        "origin": inp.origin.to_dict(),
        "flown_m": finite_or_none(inp.flown_m),
        "keyframes": len(inp.kf_t_s),
        "measurements": len(inp.meas_range_m),
        "duration_s": finite_or_none(inp.kf_t_s[-1] - inp.kf_t_s[0]) if len(inp.kf_t_s) else None,
        "noise": inp.noise.to_log_dict(),
        "range_error_reference": which,
        "users": users,
        "figures": figures or {},
        **({"extra": inp.extra} if inp.extra else {}),
    }
