"""`uavloc replay LOG --json` on a 2 000-keyframe log against a plain GTSAM script on the same log.

    python benchmarks/replay_process.py                 # 2 000 keyframes, Gauss–Markov GPS
    python benchmarks/replay_process.py --keyframes 5000

Both run as processes, as a user would run them, and are timed by their process CPU time (user +
system, from the OS: getrusage of the reaped child), imports and parsing included:

- ours: `python -m mission.cli replay LOG --json` (batch solve with the header's noise model:
  Gauss–Markov GPS chain, range biases selected, clock test, NLoS mixture, mirror tests,
  marginals; no history pass);
- baseline: this file with `--gtsam LOG`, a plain script: json, pymap3d and GTSAM only. It groups
  the rtt records into keyframes, chains the GPS fixes by the same Gauss–Markov factor
  (a CustomFactor from benchmarks/gtsam_gm.py, as in honesty.py's GTSAM column), adds one Huber
  range factor per measurement, starts the users at their true positions (the `truth` record:
  fewer iterations than a real start, which favours the baseline), and runs Levenberg–Marquardt
  and Marginals.

The log is benchmarks/honesty.py's (UAV on a 60 m circle, 3 users, GPS Gauss–Markov τ 120 s,
velocity logged), written once into --work. Each command runs --repeat times; the best time of
each is compared. Target (issue 11): ours ≤ 1.5 × that baseline.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGET_RATIO = 1.5


def gtsam_script(log_path: str, white: bool = False) -> None:
    """The plain GTSAM script (the baseline): prints the users' positions and covariances as JSON.
    white: GTSAM's standard GPS model (a prior per fix) instead of the Gauss–Markov chain."""
    import gtsam
    import numpy as np
    import pymap3d
    from gtsam_gm import gm_link_factor  # benchmarks/ is this script's folder

    header, truth, rtt = None, None, []
    with open(log_path, encoding="utf-8") as fh:
        for line in fh:
            rec = json.loads(line)
            kind = rec.get("type")
            if kind == "header":
                header = rec
            elif kind == "truth":
                truth = rec
            elif kind == "rtt":
                rtt.append(rec)
    org = header["origin"]
    ids = [u["id"] for u in header["users"]]
    sigma_gps, tau = header["noise"]["sigma_gps_m"], header["noise"].get("gps_tau_s") or 0.0
    spread = header["noise"]["range_sigma_m"]
    s0 = spread["range_s0_m"] if "range_s0_m" in spread else spread["s0"]  # logs written before: "s0"
    # keyframes: consecutive rtt records at the same UAV position
    kfs: list[tuple[float, tuple, list]] = []
    for rec in rtt:
        uav = (rec["uav"]["lat_deg"], rec["uav"]["lon_deg"], rec["uav"]["alt_m"])
        if not kfs or kfs[-1][1] != uav:
            kfs.append((rec["t"], uav, []))
        kfs[-1][2].append((ids.index(rec["user"]), rec["toa_s"] * 299_792_458.0))
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    huber = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.5),
                                           gtsam.noiseModel.Isotropic.Sigma(1, s0))
    ground = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e4, 1e4, 1e-4]))
    for k, u in enumerate(truth["users"]):
        e, n, _ = pymap3d.geodetic2enu(u["lat_deg"], u["lon_deg"], u["alt_m"], org["lat_deg"], org["lon_deg"],
                                       org["alt_m"])
        p = gtsam.Point3(e, n, 0.0)
        graph.add(gtsam.PriorFactorPoint3(L(k), p, ground))
        values.insert(L(k), p)
    gps_prev = None
    for i, (t, uav, ranges) in enumerate(kfs):
        gps = np.array(pymap3d.geodetic2enu(*uav, org["lat_deg"], org["lon_deg"], org["alt_m"]))
        values.insert(X(i), gtsam.Point3(*gps))
        if i == 0 or tau <= 0 or white:
            graph.add(gtsam.PriorFactorPoint3(X(i), gtsam.Point3(*gps), gtsam.noiseModel.Isotropic.Sigma(3, sigma_gps)))
        else:
            phi = math.exp(-max(t - kfs[i - 1][0], 0.0) / tau)
            model = gtsam.noiseModel.Isotropic.Sigma(3, sigma_gps * math.sqrt(max(1.0 - phi * phi, 1e-4)))

            graph.add(gm_link_factor(X(i - 1), X(i), gps_prev, gps, phi, model))
        for k, r in ranges:
            graph.add(gtsam.RangeFactor3(X(i), L(k), float(r), huber))
        gps_prev = gps
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-8)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    marg = gtsam.Marginals(graph, result)
    print(json.dumps({"users": [list(result.atPoint3(L(k))) for k in range(len(ids))],
                      "cov_en_m2": [marg.marginalCovariance(L(k))[:2, :2].tolist() for k in range(len(ids))]}))


def cpu_s(cmd: list[str]) -> float:
    """Process CPU time (user + system) [s] of one run of `cmd` (the change in this process's
    reaped children's usage: the runs are sequential); raises when it fails."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(cmd, capture_output=True, env=env, cwd=ROOT, check=False)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.decode()[-2000:]}")
    json.loads(proc.stdout)  # both print one JSON document
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keyframes", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--work", type=Path, default=Path("/tmp/uavloc-bench-replay"))
    ap.add_argument("--gtsam", metavar="LOG", help=argparse.SUPPRESS)
    ap.add_argument("--gtsam-white", metavar="LOG", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.gtsam or args.gtsam_white:
        gtsam_script(args.gtsam or args.gtsam_white, white=bool(args.gtsam_white))
        return 0
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from honesty import Row, write_log

    args.work.mkdir(parents=True, exist_ok=True)
    log_path = args.work / f"gm120_{args.keyframes}.jsonl"
    if not log_path.exists():
        write_log(log_path, Row("replay", n=args.keyframes, tau_s=120.0), seed=1)
        print(f"generated {log_path}")
    ours_cmd = [sys.executable, "-m", "mission.cli", "-q", "replay", str(log_path), "--json"]
    base_cmd = [sys.executable, str(Path(__file__).resolve()), "--gtsam", str(log_path)]
    white_cmd = [sys.executable, str(Path(__file__).resolve()), "--gtsam-white", str(log_path)]
    ours, base, white = [], [], []
    for _ in range(args.repeat):  # taking turns: all meet the same slow and fast spells
        ours.append(cpu_s(ours_cmd))
        base.append(cpu_s(base_cmd))
        white.append(cpu_s(white_cmd))
    t_ours, t_base, t_white = min(ours), min(base), min(white)

    def runs(xs):
        return ", ".join(f"{x:.2f}" for x in xs)

    print(f"{args.keyframes} keyframes, best of {args.repeat} (process CPU time)")
    print(f"  uavloc replay --json                     {t_ours:7.2f} s   (runs: {runs(ours)})")
    print(f"  plain GTSAM script, Gauss-Markov chain   {t_base:7.2f} s   (runs: {runs(base)}; "
          f"ours / it: {t_ours / t_base:.2f} x)")
    print(f"  plain GTSAM script, white GPS priors     {t_white:7.2f} s   (runs: {runs(white)}; "
          f"ours / it: {t_ours / t_white:.2f} x)")
    # judged against the faster of the two scripts (GTSAM's chain is a Python CustomFactor)
    ratio = t_ours / min(t_base, t_white)
    ok = ratio <= TARGET_RATIO
    print(f"{'PASS' if ok else 'FAIL'}  replay --json <= {TARGET_RATIO} x the faster plain GTSAM script: {ratio:.2f} x")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
