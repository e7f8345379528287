"""`uavloc calibrate LOG [LOG ...] [--users ID=LAT,LON,ALT ...]`: fit the range-noise model
σ(d) = s0 + a·exp(b·d) and a range bias per user from missions whose user positions are known
(a `truth` line, or positions on the command line), and print a `noise` section ready for a
scenario (TOML) or a log header (JSON). The fit itself is estimator/calibration.py."""

from __future__ import annotations

import argparse
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

HELP = "fit the range noise model sigma(d) and per-user range bias from logs with known user positions"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("logs", nargs="+", type=Path, metavar="LOG", help="mission log(s) (uavloc-mission/1)")
    p.add_argument("--users", nargs="+", metavar="ID=LAT,LON,ALT",
                   help="known user positions (override or complete the logs' truth lines)")
    p.add_argument("--format", choices=("toml", "json"), default="toml",
                   help="toml: [radio] section for a scenario; json: `noise` section for a log header")
    p.add_argument("-o", "--out", type=Path, help="write the section here (default: stdout)")
    p.add_argument("--sigma-gps", type=float, metavar="M",
                   help="per-axis noise of the logged UAV positions [m], taken out of the range spread "
                        "(default: the first log header's sigma_gps_m; 0 to keep it in)")
    p.add_argument("--min-points", type=int, default=30, help="fewest ranges for any fit (default 30)")
    p.add_argument("--sawtooth", action="store_true",
                   help="model each user's residuals as a UE clock sawtooth plus Gaussian noise (keeps the "
                        "sawtooth's spread out of sigma; bias = sawtooth mean)")
    p.add_argument("--outlier-sigma", type=float, default=5.0,
                   help="drop residuals beyond this many sigma (NLoS) and refit; 0 keeps all (default 5)")


@dataclass(frozen=True)
class CalibrationData:
    """Residuals of all logs against the known user positions.

    user_ids: K ids (union over the logs, first-seen order); distance_m, residual_m, user_idx: (M,);
    sigma_gps_m: from the first header; missing: users with ranges but no known position.
    """

    user_ids: list[str]
    distance_m: Any
    residual_m: Any
    user_idx: Any
    sigma_gps_m: float
    missing: list[str]


def calibration_data(mlogs: list, users_lla: dict[str, tuple[float, float, float]] | None = None) -> CalibrationData:
    """Pool the ranges of parsed mission logs: d = ||uav − user||, e = C·toa − d (ENU of each log's
    origin). Positions from `users_lla` win over a log's truth line. Ranges of users without a known
    position are left out (listed in `missing`)."""
    import numpy as np

    from estimator.calibration import range_residuals
    from estimator.ranging import C_MPS

    users_lla = users_lla or {}
    ids: list[str] = []
    d_all, e_all, k_all = [], [], []
    missing: set[str] = set()
    for mlog in mlogs:
        origin = mlog.header.origin
        log_ids = [u.id for u in mlog.header.users]
        known = np.full((len(log_ids), 3), np.nan)
        for j, uid in enumerate(log_ids):
            if uid in users_lla:
                known[j] = origin.lla_to_enu(*users_lla[uid])
            elif mlog.truth_lla is not None and np.all(np.isfinite(mlog.truth_lla[j])):
                t = mlog.truth_lla[j]
                known[j] = origin.lla_to_enu(t[0], t[1], t[2])
        for uid in log_ids:
            if uid not in ids:
                ids.append(uid)
        if len(mlog.rtt_t_s) == 0:
            continue
        has = np.all(np.isfinite(known[mlog.rtt_user]), axis=1)
        for j in np.unique(mlog.rtt_user[~has]):
            missing.add(log_ids[j])
        sel = np.flatnonzero(has)
        if not sel.size:
            continue
        uav = origin.lla_to_enu(mlog.rtt_uav_lla[sel, 0], mlog.rtt_uav_lla[sel, 1], mlog.rtt_uav_lla[sel, 2])
        d, e = range_residuals(uav, np.nan_to_num(known), mlog.rtt_user[sel], C_MPS * mlog.rtt_toa_s[sel])
        d_all.append(d)
        e_all.append(e)
        k_all.append(np.array([ids.index(log_ids[j]) for j in mlog.rtt_user[sel]], int))

    def cat(xs: list, dt: type):
        return np.concatenate(xs) if xs else np.zeros(0, dt)

    return CalibrationData(ids, cat(d_all, float), cat(e_all, float), cat(k_all, int),
                           float(mlogs[0].header.noise.sigma_gps_m), sorted(missing))


def _g(x: float, digits: int = 6) -> str:
    return "nan" if not math.isfinite(x) else f"{x:.{digits}g}"


def noise_json(res, user_ids: list[str], sigma_gps_m: float) -> dict:
    """`{"noise": {...header section...}, "range_bias_m": {...}, "fit": {...}}`."""
    def num(x):
        return float(x) if math.isfinite(float(x)) else None

    return {
        "noise": res.noise_model(sigma_gps_m).to_log_dict(),
        "range_bias_m": {uid: num(res.bias_m[k]) for k, uid in enumerate(user_ids)},
        "fit": {
            "model": res.model,
            "s0_std_m": num(res.s0_std_m), "a_std_m": num(res.a_std_m), "b_std_per_m": num(res.b_std_per_m),
            "range_bias_std_m": {uid: num(res.bias_std_m[k]) for k, uid in enumerate(user_ids)},
            "points": {uid: int(res.n_points[k]) for k, uid in enumerate(user_ids)},
            "outliers": res.n_outliers,
            "distance_m": [res.distance_min_m, res.distance_max_m],
            "likelihood_ratio": num(res.lr_statistic),
            "sigma_gps_removed_m": res.sigma_gps_m,
            "messages": res.messages,
            **({"sawtooth_amplitude_m": {uid: num(res.sawtooth_amplitude_m[k]) for k, uid in enumerate(user_ids)}}
               if res.sawtooth_amplitude_m is not None else {}),
        },
    }


def noise_toml(res, user_ids: list[str], sigma_gps_m: float) -> str:
    """TOML for a scenario: `[radio]` s0_m, a_m, b_per_m, `[mission]` sigma_gps_m, and the biases
    as comments with the sawtooth amplitude that has that mean (bias = amplitude / 2)."""
    lines = [
        f"# uavloc calibrate: {int(res.n_points.sum())} ranges, distances {res.distance_min_m:.0f}-"
        f"{res.distance_max_m:.0f} m, model {res.model}",
        f"# s0 = {_g(res.s0_m, 4)} ± {_g(res.s0_std_m, 2)} m, a = {_g(res.a_m, 4)} ± {_g(res.a_std_m, 2)} m, "
        f"b = {_g(res.b_per_m, 4)} ± {_g(res.b_std_per_m, 2)} /m",
        *(f"# note: {m}" for m in res.messages),
        "[radio]",
        f"s0_m = {res.s0_m:.6g}",
        f"a_m = {res.a_m:.6g}",
        f"b_per_m = {res.b_per_m:.6g}",
        "",
        "[mission]",
        f"sigma_gps_m = {sigma_gps_m:.6g}",
        "",
        "# range bias per user (the mean of a UE clock sawtooth is sawtooth_amplitude_m / 2):",
    ]
    for k, uid in enumerate(user_ids):
        b = float(res.bias_m[k])
        if math.isfinite(b):
            amp = f", sawtooth_amplitude_m = {2 * b:.4g}" if b > 0 else ""
            if res.sawtooth_amplitude_m is not None:
                amp = f", fitted sawtooth_amplitude_m = {float(res.sawtooth_amplitude_m[k]):.4g}"
            lines.append(f"#   {uid}: bias {b:.4g} ± {_g(float(res.bias_std_m[k]), 2)} m{amp}")
        else:
            lines.append(f"#   {uid}: not enough ranges for a bias")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    import tomllib

    from estimator.calibration import CalibrationParams, fit_range_noise
    from mission.commands.importer import parse_positions
    from mission.log import read_mission_log
    from uavloc.errors import EstimatorError, MissionLogError

    if args.min_points < 3:
        raise EstimatorError(f"--min-points must be at least 3, got {args.min_points}")
    if not (args.outlier_sigma >= 0 and math.isfinite(args.outlier_sigma)):
        raise EstimatorError(f"--outlier-sigma must be >= 0, got {args.outlier_sigma}")
    if args.sigma_gps is not None and not (args.sigma_gps >= 0 and math.isfinite(args.sigma_gps)):
        raise EstimatorError(f"--sigma-gps must be >= 0, got {args.sigma_gps}")
    users = parse_positions(args.users, "--users")
    mlogs = [read_mission_log(p) for p in args.logs]
    data = calibration_data(mlogs, users)
    unknown = sorted(set(users) - set(data.user_ids))
    if unknown:
        raise MissionLogError(f"--users names user(s) not in the logs: {unknown}; logs have {data.user_ids}")
    if data.missing:
        log.warning("no known position for %s: their ranges are left out (give --users ID=LAT,LON,ALT)",
                    ", ".join(data.missing))
    if data.distance_m.size == 0:
        raise EstimatorError(
            "cannot calibrate: no range to a user with a known position (the logs have no truth line; give "
            "--users ID=LAT,LON,ALT)"
        )
    sigma_gps = data.sigma_gps_m if args.sigma_gps is None else args.sigma_gps
    params = CalibrationParams(min_points=args.min_points, sigma_gps_m=sigma_gps, outlier_sigma=args.outlier_sigma,
                               sawtooth=args.sawtooth)
    res = fit_range_noise(data.distance_m, data.residual_m, data.user_idx, len(data.user_ids), params)
    for m in res.messages:
        log.warning("calibrate: %s", m)
    log.info("calibrate: %d ranges, model %s: s0 = %s m, a = %s m, b = %s /m", int(res.n_points.sum()), res.model,
             _g(res.s0_m, 4), _g(res.a_m, 4), _g(res.b_per_m, 4))
    header_sigma = data.sigma_gps_m
    if args.format == "json":
        text = json.dumps(noise_json(res, data.user_ids, header_sigma), indent=2) + "\n"
    else:
        text = noise_toml(res, data.user_ids, header_sigma)
        tomllib.loads(text)  # what we print must be valid TOML
    if args.out is not None:
        try:
            args.out.write_text(text, encoding="utf-8")
        except OSError as exc:
            raise MissionLogError(f"cannot write {args.out}: {exc}") from exc
        log.info("calibrate: wrote %s", args.out)
    else:
        print(text, end="")
    return 0
