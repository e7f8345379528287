"""Honesty benchmark: is each user's 95 % ellipse true on logs that behave like real hardware?

    python benchmarks/honesty.py            # full table (~10 min of one core)
    python benchmarks/honesty.py --quick    # fewer samples (~3 min)
    python benchmarks/honesty.py --rows tau --samples 400 --workers 2
    python benchmarks/honesty.py --no-table --missions 10   # the whole-mission check (~5 min)

Every row writes seeded `uavloc-mission/1` logs and replays them the way `uavloc replay --json`
does (mission.replay.replay without the online history pass; the header's noise model), next to
GTSAM on the same keyframes (Levenberg–Marquardt, Huber c = 1.5σ, covariance from gtsam.Marginals)
with the same model where GTSAM can express it — the Gauss–Markov GPS chain as a CustomFactor
between consecutive keyframes — and its standard white-noise range model otherwise (no range bias,
no noise scale).

World of a log: UAV at 35 m, 5 m/s, on a circle of 60 m radius around the users' centroid (users
40–110 m from it, on the ground), one trigger every Δ = 2 m (0.4 s), telemetry at 5 Hz with the
autopilot's velocity. GPS error: white N(0, σ²) or Gauss–Markov (σ 1 m, τ), the same process for
the telemetry and the rtt records. Ranges: d + s·N(0, σ(d)²) + saw_k(t) + NLoS, with the UE clock
sawtooth saw(t) = A · frac(t / 15 s + φ_k) on every user when A > 0, NLoS ~ Exp(20 m) with the
given probability, s the factor by which the header understates σ.

Columns: n, the independent samples of the row (below); mean horizontal error [m];
RMSE / √trace(CRLB) (the bound at the truth of the model without the sawtooth: no clock offset,
the true σ, Gauss–Markov GPS when the GPS drifts, LoS ranges); floor (sawtooth rows):
√(trace CRLB_saw / trace CRLB), CRLB_saw the bound of the tracked model, the sawtooth's amplitude
unknown but its period and resets known — the least RMSE/CRLB any unbiased estimator that is not
told the amplitude can reach; mean NEES (2 when honest, 2-D); share of users inside their own
95 % ellipse and its 95 % interval; time per log (process CPU time of the replay / of the GTSAM
solve and marginals).

Sample size. Where the GPS drifts, all users of a log share its drift (the UAV track's offset),
so their errors are correlated: 20 users of one log are worth little more than one. A row's
sample size n is therefore the number of LOGS where the GPS drifts and the number of users where
it is white (users of a log then share only the UAV track, whose white GPS error averages out over
the keyframes). Measured design effects (variance of a log's count inside over the binomial one;
100 logs, 60 for K = 20): white GPS 0.95, 20 % NLoS 0.94 (3.2 effective samples per 3-user log);
GM τ 60 s 1.9 (1.6 per 3-user log), K = 20 13.5 (1.5 per 20-user log). Each row
gets n = 200 independent samples (--quick 60): 200 logs where the GPS drifts, ⌈200/K⌉ logs of K
users otherwise. GTSAM, for comparison only, solves the first 16 logs of a row (4 of N = 2000).

Judging the share inside. The share is pooled over the row's users; its 95 % interval is the
Wilson score interval of a binomial share on n samples (for a drifting row, n logs: a
conservative count, as the users of a log are not wholly correlated). The target "≥ 90 %
inside" FAILS when the whole interval lies below 90 % (the data show, at 95 % confidence, that
fewer than 90 % of the users are inside), and passes otherwise; a share below 90 % whose interval
still reaches it is marked "not significantly". At n = 200 the interval is about ±3 points at
94 % (±5 at 85 %): an honest ellipse (95 % inside) passes with near certainty, and one holding
only 85 % fails with probability 0.61 (0.98 at 80 %). The mean NEES is judged on its value.

RMSE targets: white GPS, LoS: RMSE/CRLB ≤ 1.05. Sawtooth rows: RMSE ≤ 1.15 × the floor. Issue 11
asked RMSE/CRLB ≤ 1.15 against the sawtooth-free CRLB for the 12 m row, but in this geometry the
floor itself is ≈ 1.23 (the amplitude costs the position that much information whatever the
tracking does; with the true period and resets given to the estimator it gets 1.20 on 20 logs,
the tracked estimate 1.20 too), so that target is below what is possible; the table says so.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import math
import multiprocessing
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimator.crlb import crlb_users
from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from estimator.ranging import C_MPS
from estimator.types import CHI2_2DOF_95, CHI2_2DOF_999, SolverParams
from mission.log import MissionLogWriter, read_mission_log
from mission.replay import ReplayOptions, replay

try:  # optional (the `bench` extra)
    import gtsam
    from gtsam_gm import gm_link_factor  # benchmarks/ is this script's folder

    GTSAM_MISSING = ""
except ImportError as exc:  # pragma: no cover
    gtsam = None
    GTSAM_MISSING = str(exc)

ORIGIN = Origin(43.6143, 7.0716, 150.0)
SPEED_MPS = 5.0
DELTA_M = 2.0
TEL_DT_S = 0.2
ALT_M = 35.0
RADIUS_M = 60.0
SAW_PERIOD_S = 15.0
NLOS_MEAN_M = 20.0
VEL_SIGMA_MPS = 0.05
#: independent samples per row (full run, --quick) and logs per row also solved by GTSAM
SAMPLES = 200
SAMPLES_QUICK = 60
GTSAM_LOGS = 16
GTSAM_LOGS_QUICK = 4
#: two-sided 95 % normal quantile
Z_95 = 1.959963984540054


@dataclass(frozen=True)
class Row:
    name: str
    n: int = 400
    k: int = 3
    tau_s: float = 0.0  # GPS correlation time (0: white)
    saw_m: float = 0.0
    p_nlos: float = 0.0
    understate: float = 1.0  # true σ = understate × the header's σ
    tau_in_log: bool = True
    target_ratio: float | None = None  # RMSE/CRLB (sawtooth rows: RMSE over the tracked model's floor)

    @property
    def drifting(self) -> bool:
        """The GPS error drifts (Gauss–Markov): the users of one log share it."""
        return self.tau_s > 0


ROWS = [
    Row("white GPS, LoS", target_ratio=1.05),
    Row("GM GPS tau 60 s", tau_s=60.0),
    Row("GM GPS tau 120 s", tau_s=120.0),
    Row("GM GPS tau 600 s", tau_s=600.0),
    Row("GM 120 s, tau not logged", tau_s=120.0, tau_in_log=False),
    Row("sawtooth 0 m", saw_m=0.0, tau_s=120.0),
    Row("sawtooth 8 m", saw_m=8.0, target_ratio=1.15),
    Row("sawtooth 12 m", saw_m=12.0, target_ratio=1.15),
    Row("20% NLoS", p_nlos=0.2),
    Row("30% NLoS", p_nlos=0.3),
    Row("sigma understated 2x", understate=2.0),
    Row("K = 5", k=5, tau_s=120.0),
    Row("K = 20", k=20, tau_s=120.0),
    Row("N = 2000, white", n=2000),
    Row("N = 2000, GM 120 s", n=2000, tau_s=120.0),
]


def gm_error(rng: np.random.Generator, t_s: np.ndarray, sigma_m: float, tau_s: float) -> np.ndarray:
    """(T, 3) GPS error at times t_s: white, or Gauss–Markov β_i = φ_i β_(i−1) + √(1−φ_i²) σ w_i."""
    w = rng.normal(scale=sigma_m, size=(t_s.size, 3))
    if tau_s <= 0:
        return w
    out = np.empty_like(w)
    out[0] = w[0]
    phi = np.exp(-np.diff(t_s) / tau_s)
    for i in range(1, t_s.size):
        out[i] = phi[i - 1] * out[i - 1] + math.sqrt(1.0 - phi[i - 1] ** 2) * w[i]
    return out


def write_log(path: Path, row: Row, seed: int) -> dict:
    """One seeded log of `row`; returns the truth: users (K, 3), keyframe positions (N, 3), times (N,),
    the sawtooth's shape frac(t/P + φ_k) (N, K)."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, row.k)
    rad = rng.uniform(40.0, 110.0, row.k)
    users = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), np.zeros(row.k)])
    phase = rng.random(row.k)
    noise = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0, gps_tau_s=row.tau_s if row.tau_in_log else None)
    kf_dt = DELTA_M / SPEED_MPS
    per = round(kf_dt / TEL_DT_S)
    t = np.arange(row.n * per) * TEL_DT_S
    # circle around the origin (users are placed around it), angular speed v / R
    a = SPEED_MPS * t / RADIUS_M
    pos = np.column_stack([RADIUS_M * np.cos(a), RADIUS_M * np.sin(a), np.full(t.size, ALT_M)])
    vel = np.column_stack([-SPEED_MPS * np.sin(a), SPEED_MPS * np.cos(a), np.zeros(t.size)])
    gps = pos + gm_error(rng, t, 1.0, row.tau_s)
    lat, lon, alt = ORIGIN.enu_to_lla(gps)
    kf_idx = np.arange(0, t.size, per)
    d = np.linalg.norm(pos[kf_idx, None, :] - users[None], axis=2)
    saw_shape = np.mod(t[kf_idx, None] / SAW_PERIOD_S + phase[None], 1.0)
    saw = row.saw_m * saw_shape
    nlos = (rng.random(d.shape) < row.p_nlos) * rng.exponential(NLOS_MEAN_M, d.shape)
    rng_m = d + row.understate * rng.normal(size=d.shape) * noise.range_sigma_m(d) + saw + nlos
    rng_m = np.maximum(rng_m, 0.0)
    vel_noisy = vel + rng.normal(scale=VEL_SIGMA_MPS, size=vel.shape)
    ids = [f"ue{k + 1}" for k in range(row.k)]
    with MissionLogWriter(path) as w:
        w.write_header(ORIGIN, [{"id": u, "rnti": 0x4601 + k, "ground_alt_m": ORIGIN.alt_m} for k, u in enumerate(ids)],
                       {"mu": 1, "fs_hz": 46.08e6}, noise=noise, config={"generator": "benchmarks/honesty.py"},
                       start_utc="2026-01-01T00:00:00.000+00:00")
        tl, tn, ta = ORIGIN.enu_to_lla(users)
        w.write("truth", 0.0, users=[{"id": u, "lat_deg": float(tl[k]), "lon_deg": float(tn[k]), "alt_m": float(ta[k])}
                                     for k, u in enumerate(ids)])
        j = 0
        for i in range(t.size):
            v = vel_noisy[i]
            w.write("telemetry", t[i], lat_deg=float(lat[i]), lon_deg=float(lon[i]), alt_m=float(alt[i]),
                    vel_ned_mps=[float(v[1]), float(v[0]), float(-v[2])])
            if i % per == 0:
                uav = {"lat_deg": float(lat[i]), "lon_deg": float(lon[i]), "alt_m": float(alt[i])}
                for k, u in enumerate(ids):
                    w.write("rtt", t[i], user=u, uav=uav, toa_s=float(rng_m[j, k] / C_MPS))
                j += 1
    return {"users": users, "uav": pos[kf_idx], "t": t[kf_idx], "noise": noise, "saw_shape": saw_shape}


# --- GTSAM ----------------------------------------------------------------------------------------


def gtsam_solve(keyframes, n_users: int, noise: NoiseModel, tau_s: float, init: np.ndarray):
    """(users (K, 3), cov (K, 2, 2)) from GTSAM LM + Marginals."""
    X, L = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.L
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    huber = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.5),
                                           gtsam.noiseModel.Isotropic.Sigma(1, noise.range_s0_m))
    up = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e4, 1e4, 1e-4]))
    for k in range(n_users):
        graph.add(gtsam.PriorFactorPoint3(L(k), gtsam.Point3(init[k, 0], init[k, 1], 0.0), up))
        values.insert(L(k), gtsam.Point3(init[k, 0], init[k, 1], 0.0))
    sig = noise.sigma_gps_m
    for n, kf in enumerate(keyframes):
        values.insert(X(n), gtsam.Point3(*kf.gps_enu_m))
        if n == 0 or tau_s <= 0:
            gps_m = gtsam.noiseModel.Isotropic.Sigma(3, sig)
            graph.add(gtsam.PriorFactorPoint3(X(n), gtsam.Point3(*kf.gps_enu_m), gps_m))
        else:
            phi = math.exp(-max(kf.t_s - keyframes[n - 1].t_s, 0.0) / tau_s)
            model = gtsam.noiseModel.Isotropic.Sigma(3, sig * math.sqrt(max(1.0 - phi * phi, 1e-4)))
            graph.add(gm_link_factor(X(n - 1), X(n), np.asarray(keyframes[n - 1].gps_enu_m), np.asarray(kf.gps_enu_m),
                                 phi, model))
        for k, r in zip(kf.user_idx, kf.range_m, strict=True):
            graph.add(gtsam.RangeFactor3(X(n), L(int(k)), float(r), huber))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-8)
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    marg = gtsam.Marginals(graph, result)
    users = np.array([result.atPoint3(L(k)) for k in range(n_users)])
    cov = np.array([marg.marginalCovariance(L(k))[:2, :2] for k in range(n_users)])
    return users, cov


# --- the table ------------------------------------------------------------------------------------


def wilson_interval(share: float, n: float, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial share observed on n independent samples:
    (p̂ + z²/2n ± z √(p̂(1 − p̂)/n + z²/4n²)) / (1 + z²/n)."""
    if n <= 0:
        return 0.0, 1.0
    den = 1.0 + z * z / n
    mid = (share + z * z / (2 * n)) / den
    half = z * math.sqrt(share * (1.0 - share) / n + z * z / (4 * n * n)) / den
    return max(mid - half, 0.0), min(mid + half, 1.0)


def n_logs(row: Row, samples: int) -> int:
    """Logs of a row for `samples` independent samples: one per log where the GPS drifts (its
    users share the drift), one per user otherwise."""
    return samples if row.drifting else math.ceil(samples / row.k)


def run_log(row: Row, seed: int, tmp: str, with_gtsam: bool) -> dict:
    """Write, replay and judge one seeded log of `row`; per-user arrays (K,) of ours (and GTSAM's)."""
    path = Path(tmp) / f"{row.name.replace(' ', '_').replace('/', '').replace(',', '')}_{seed}.jsonl"
    truth = write_log(path, row, seed)
    try:
        mlog = read_mission_log(path)
        t0 = time.process_time()
        res = replay(mlog, ReplayOptions(history=False))
        t_ours = time.process_time() - t0
    finally:
        path.unlink()
    est = res.estimate
    users = truth["users"]
    visible = np.ones((row.n, row.k), dtype=bool)
    # CRLB of the sawtooth-free model at the truth (true σ, no clock offset, GM when drifting)
    true_noise = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0 * row.understate, gps_tau_s=row.tau_s)
    crlb = crlb_users(truth["uav"], users, visible, true_noise, SolverParams(estimate_bias=False), truth["t"])
    out = {"tr": np.array([np.trace(crlb[2 * k : 2 * k + 2, 2 * k : 2 * k + 2]) for k in range(row.k)])}
    if row.saw_m > 0:
        # ... and of the tracked sawtooth model: the amplitude unknown, period and resets known
        saw = crlb_users(truth["uav"], users, visible, true_noise, SolverParams(), truth["t"],
                         bias_gain=truth["saw_shape"])
        out["tr_saw"] = np.array([np.trace(saw[2 * k : 2 * k + 2, 2 * k : 2 * k + 2]) for k in range(row.k)])
    out["ours"] = _judge(est.users_enu_m, est.cov_users_m2, users, t_ours)
    if with_gtsam:
        t0 = time.process_time()
        u_gt, c_gt = gtsam_solve(res.keyframes, row.k, mlog.header.noise, row.tau_s if row.tau_in_log else 0.0,
                                 est.users_enu_m)
        out["gtsam"] = _judge(u_gt, c_gt, users, time.process_time() - t0)
    return out


def _judge(users_est: np.ndarray, cov: np.ndarray, users: np.ndarray, t_s: float) -> dict:
    """Per-user horizontal error [m], squared error [m²], NEES (2-D) of an estimate; its time [s]."""
    e = users_est[:, :2] - users[:, :2]
    nees = np.array([ek @ np.linalg.solve(c[:2, :2], ek) for ek, c in zip(e, cov, strict=True)])
    return {"err": np.linalg.norm(e, axis=1), "sq": np.sum(e * e, axis=1), "nees": nees, "time": t_s}


def row_stats(row: Row, logs: list[dict], who: str) -> dict:
    """One row's figures from its logs' per-user results (`who`: "ours" or "gtsam")."""
    logs = [lg for lg in logs if who in lg]
    sq = np.concatenate([lg[who]["sq"] for lg in logs])
    tr = np.concatenate([lg["tr"] for lg in logs])
    nees = np.concatenate([lg[who]["nees"] for lg in logs])
    inside = float(np.mean(nees <= CHI2_2DOF_95))
    # independent samples: logs where the GPS drifts, users where it is white
    n = len(logs) if row.drifting else nees.size
    out = {
        "err": float(np.mean(np.concatenate([lg[who]["err"] for lg in logs]))),
        "ratio": math.sqrt(float(np.sum(sq)) / float(np.sum(tr))), "nees": float(np.mean(nees)),
        "inside": inside, "ci": wilson_interval(inside, n), "n": n, "logs": len(logs),
        "time": float(np.mean([lg[who]["time"] for lg in logs])),
    }
    if row.saw_m > 0:
        # √(trace CRLB_saw / trace CRLB): the best RMSE/CRLB of an estimator not told the amplitude
        out["floor"] = math.sqrt(float(np.sum(np.concatenate([lg["tr_saw"] for lg in logs]))) / float(np.sum(tr)))
    return out


def run_row(row: Row, n: int, gtsam_logs: int, tmp: str, pool) -> tuple[dict, dict | None]:
    """(ours, GTSAM or None) over n seeded logs of `row`, GTSAM on the first gtsam_logs of them."""
    base = 1000 * ROWS.index(row)
    args = [(row, base + s, tmp, s < gtsam_logs) for s in range(n)]
    logs = list(pool.starmap(run_log, args)) if pool is not None else [run_log(*a) for a in args]
    return row_stats(row, logs, "ours"), (row_stats(row, logs, "gtsam") if gtsam_logs > 0 else None)


def verdict(row: Row, r: dict) -> tuple[bool, str]:
    """(met, words) for one row: mean NEES in [1.2, 3.5]; the share inside not significantly below
    90 % (its interval reaches 90 %); RMSE/CRLB where the row has a target (sawtooth rows: RMSE
    over the tracked model's floor)."""
    lo, hi = r["ci"]
    ok = 1.2 <= r["nees"] <= 3.5 and hi >= 0.9
    nees_note = "" if 1.2 <= r["nees"] <= 3.5 else " (outside [1.2, 3.5])"
    words = (f"NEES {r['nees']:.2f}{nees_note}, inside {100 * r['inside']:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}] "
             f"of {r['n']} {'logs' if row.drifting else 'users'}")
    if r["inside"] < 0.9 <= hi:
        words += " (below 90 % but not significantly)"
    if row.target_ratio is not None:
        if "floor" in r:
            eff = r["ratio"] / r["floor"]
            ok = ok and eff <= row.target_ratio
            words += (f", RMSE/CRLB {r['ratio']:.2f} = {eff:.2f} x the floor {r['floor']:.2f} "
                      f"({'<=' if eff <= row.target_ratio else '>'} {row.target_ratio} x the floor)")
        else:
            met = r["ratio"] <= row.target_ratio
            ok = ok and met
            words += f", RMSE/CRLB {r['ratio']:.2f} {'<=' if met else '>'} {row.target_ratio}"
    return ok, words


# --- whole missions -------------------------------------------------------------------------------


def run_missions(scenario: str, seeds: int, speedup: float | None = None) -> bool:
    """Fly `scenario` with the built-in vehicle for seeds 1..seeds (`uavloc sim SCENARIO --seed S
    --json [--speedup X]`, one process each) and count the users whose final error is within their
    own 95 % bound r95 (the stop rule's radius), inside their 95 % ellipse and beyond their 99.9 %
    one, with their mean NEES (2 when honest). True when ≥ 90 % are within r95 (issue 11's
    whole-mission check)."""
    extra = [] if speedup is None else ["--speedup", f"{speedup:g}"]
    print(f"\nWhole missions: uavloc sim {scenario} --seed S --json {' '.join(extra)}, S = 1..{seeds}")
    within = inside = beyond = total = 0
    nees_sum = 0.0
    for seed in range(1, seeds + 1):
        cmd = [sys.executable, "-m", "mission.cli", "sim", scenario, "--seed", str(seed), "--json", *extra]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
        if proc.returncode not in (0, 1) or not proc.stdout.strip():
            print(f"  seed {seed}: exit {proc.returncode}: {proc.stderr.strip().splitlines()[-1:]}")
            return False
        doc = json.loads(proc.stdout)
        words = []
        for u in doc["users"]:
            err, r95 = u.get("error_m"), u.get("error_bound_95_m")
            e = np.asarray(u["enu_m"][:2]) - np.asarray(u["truth"]["enu_m"][:2])
            nees = float(e @ np.linalg.solve(np.asarray(u["cov_en_m2"]), e))
            total += 1
            within += err <= r95
            inside += nees <= CHI2_2DOF_95
            beyond += nees > CHI2_2DOF_999
            nees_sum += nees
            words.append(f"{u['id']} {err:.2f}/{r95:.2f}{'' if err <= r95 else ' OUT'}")
        print(f"  seed {seed:2d} ({doc['status']}, {doc['flown_m']:.0f} m): error/r95 " + ", ".join(words), flush=True)
    lo, hi = wilson_interval(within / total, seeds)
    print(f"  within their own r95: {within}/{total} = {100 * within / total:.0f}% (95 % interval over {seeds} "
          f"missions [{100 * lo:.0f}, {100 * hi:.0f}]); inside their 95 % ellipse: {inside}/{total} "
          f"= {100 * inside / total:.0f}%; beyond their 99.9 % ellipse: {beyond}/{total}; "
          f"mean NEES {nees_sum / total:.2f}")
    return within >= 0.9 * total


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer samples (60) and GTSAM logs (4)")
    ap.add_argument("--samples", type=int, help="independent samples per row: logs where the GPS drifts, "
                    f"users otherwise (default {SAMPLES}, quick {SAMPLES_QUICK})")
    ap.add_argument("--gtsam-logs", type=int, help=f"logs per row also solved by GTSAM (default {GTSAM_LOGS}, "
                    f"quick {GTSAM_LOGS_QUICK}; N = 2000 rows a quarter, at least 1)")
    ap.add_argument("--workers", type=int, default=1, help="processes (default 1: the machine is shared)")
    ap.add_argument("--rows", help="only rows whose name contains this text")
    ap.add_argument("--missions", type=int, default=0, metavar="SEEDS",
                    help="also fly five_commercial_ues (or --scenario) for seeds 1..SEEDS (~30 s each)")
    ap.add_argument("--scenario", default="five_commercial_ues", help="scenario of --missions")
    ap.add_argument("--speedup", type=float, help="--speedup of the missions' built-in vehicle (default uavloc's)")
    ap.add_argument("--no-table", action="store_true", help="skip the table (with --missions)")
    args = ap.parse_args(argv)
    samples = args.samples or (SAMPLES_QUICK if args.quick else SAMPLES)
    g_logs = args.gtsam_logs if args.gtsam_logs is not None else (GTSAM_LOGS_QUICK if args.quick else GTSAM_LOGS)
    if gtsam is None:
        g_logs = 0
    if samples < 1 or samples > 1000:
        ap.error("--samples must be within 1..1000")
    if args.no_table:
        if args.missions < 1:
            ap.error("--no-table needs --missions SEEDS")
        return 0 if run_missions(args.scenario, args.missions, args.speedup) else 1
    print(f"gtsam: {'available' if gtsam is not None else f'cannot import ({GTSAM_MISSING}): GTSAM columns skipped'}")
    print(f"{samples} independent samples per row: logs where the GPS drifts (its users share the drift), users "
          f"where it is white; GTSAM on the first {g_logs} logs of a row (N = 2000: {max(g_logs // 4, 1)})\n")
    head = (f"{'condition':<26} | {'n':>4} {'err m':>6} {'RMSE/CRLB':>9} {'floor':>5} {'NEES':>6} {'in 95%':>6} "
            f"{'95% interval':>13} {'time s':>6}")
    if g_logs:
        head += f" | {'GTSAM err':>9} {'RMSE/CRLB':>9} {'NEES':>6} {'in 95%':>6} {'time s':>6}"
    print(head)
    print("-" * len(head))
    results = []
    t_start = time.perf_counter()
    pool = multiprocessing.get_context("spawn").Pool(args.workers) if args.workers > 1 else None
    try:
        with tempfile.TemporaryDirectory(prefix="honesty-") as tmp:
            for row in ROWS:
                if args.rows and args.rows not in row.name:
                    continue
                gl = g_logs if row.n <= 400 else (max(g_logs // 4, 1) if g_logs else 0)
                ours, gt = run_row(row, n_logs(row, samples), gl, tmp, pool)
                lo, hi = ours["ci"]
                floor = f"{ours['floor']:5.2f}" if "floor" in ours else f"{'-':>5}"
                line = (f"{row.name:<26} | {ours['n']:4d} {ours['err']:6.2f} {ours['ratio']:9.2f} {floor} "
                        f"{ours['nees']:6.2f} {100 * ours['inside']:5.1f}% {f'[{100 * lo:.1f}, {100 * hi:.1f}]':>13} "
                        f"{ours['time']:6.2f}")
                if gt is not None:
                    line += (f" | {gt['err']:9.2f} {gt['ratio']:9.2f} {gt['nees']:6.2f}"
                             f" {100 * gt['inside']:5.0f}% {gt['time']:6.2f}")
                print(line, flush=True)
                results.append((row, ours))
    finally:
        if pool is not None:
            pool.close()
            pool.join()
    print(f"\n({time.perf_counter() - t_start:.0f} s wall)")
    print("Targets (ours): mean NEES in [1.2, 3.5]; share inside the 95 % ellipse >= 90 %, judged on its 95 % "
          "interval (fails when the whole interval lies below 90 %); RMSE/CRLB where given")
    ok_all = True
    for row, r in results:
        ok, words = verdict(row, r)
        ok_all &= ok
        print(f"  [{'PASS' if ok else 'FAIL'}] {row.name}: {words}")
        if row.name == "sawtooth 12 m":
            print(f"         issue 11 asked RMSE/CRLB <= 1.15 against the sawtooth-free CRLB ({r['ratio']:.2f} here: "
                  f"{'met' if r['ratio'] <= 1.15 else 'not met'}); no unbiased estimator that is not told the "
                  f"amplitude gets below {r['floor']:.2f} here (the floor), so the row is judged against the floor")
    if args.missions:
        ok_all &= run_missions(args.scenario, args.missions, args.speedup)
    return 0 if ok_all else 1


if __name__ == "__main__":
    raise SystemExit(main())
