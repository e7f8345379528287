"""Honesty on real PX4 SITL: status and printed bounds agree, users inside their bounds (issue 48).

    UAVLOC_PX4=.../PX4-Autopilot/build/px4_sitl_default python benchmarks/px4_honesty.py
    python benchmarks/px4_honesty.py --homes reykjavik --skip-five --keep /tmp/px4-honesty

Flies, each as the user would type it, against fresh PX4 SITL instances of the user's build
(`UAVLOC_PX4`; SIH quadrotors, speed factor `--speed` 4, started as `make px4_sitl sihsim_quadx`
does: sitl_scenarios.px4_sitl; instances 1-8 chosen free and their ports with them, as the `px4`
tests choose them):

- `uavloc sim two_uavs --connect URL0,URL1 --json --out DIR` at each of three homes the tests never
  use (`HOMES`: high north latitude and west longitude, the equator, the southern hemisphere at a
  far-east longitude), the second vehicle PAIR_EAST_M east of the first, as the `px4_pair` fixture
  places it (tests/conftest.py);
- `uavloc sim five_commercial_ues --connect URL --json --out DIR` on one PX4 at the first home.

The scenario positions are offsets from vehicle 0's home (docs/fleet.md#px4), so the same scenario
flies at every home. Then `uavloc replay LOG --json` of each flight's log.

Per run: exit code, status and the status its log's `end` record holds (status_logged), every
user's error against its printed 95 % bound (`in` / `OUT`), whether every printed bound is within
the target when the status is target_reached, replay's status and bounds against the flight's
(the largest difference of a bound), the GPS τ the flight logged (event gps_tau), the range
residual C·toa − ‖uav − user‖ against the logged UAV position (p50/p99 of |·|: for PX4 the
simulated gNB ranges from PX4's reported position, so this is the timing of the range against
PX4's clock plus the scenario's UE clock and NLoS), wall time, achieved speed-up and fell_behind.

Verdicts (PASS/FAIL lines at the end): every run gave a result; every user inside its bound;
target_reached only with every printed bound within the target; replay prints the flight's status
and bounds (within BOUND_AGREE_M). Exit 0 when all pass, 1 otherwise. Without UAVLOC_PX4 it prints
why and exits 0 (skipped).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

# benchmarks/ holds scripts named like packages (planner.py): the repository root replaces this
# folder on sys.path so that imports find the packages
_HERE = Path(__file__).resolve().parent
REPO = _HERE.parent
sys.path[:] = [str(REPO)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

import numpy as np  # noqa: E402

from benchmarks.load import range_residuals_m  # noqa: E402
from estimator.geodesy import Origin  # noqa: E402
from sitl_scenarios.px4_sitl import Px4Sitl, build_from_env, instance_busy, missing_requirement  # noqa: E402
from sitl_scenarios.scenario import load_scenario  # noqa: E402

#: homes no test uses (lat_deg, lon_deg, alt_amsl_m): the tests fly at SIH's default (Zurich)
HOMES: dict[str, tuple[float, float, float]] = {
    "reykjavik": (64.1466, -21.9426, 30.0),    # 64° N, west of Greenwich
    "singapore": (1.3521, 103.8198, 15.0),     # the equator
    "auckland": (-36.8485, 174.7633, 40.0),    # southern hemisphere, far east
}
#: how far east of the first the second vehicle takes off [m] (tests/conftest.py PX4_PAIR_EAST_M)
PAIR_EAST_M = 20.0
#: PX4 instances the benchmark may use (stock ports for 1-9: sitl_scenarios.px4_sitl)
INSTANCES = range(1, 9)
#: a replay's bound agrees with the flight's within this [m] (both are the same computation)
BOUND_AGREE_M = 1e-6
C_MPS = 299_792_458.0


@dataclass
class Run:
    """One flight's figures (module docstring)."""

    name: str
    home: str
    scenario: str
    target_m: float
    exit_code: int = -1
    wall_s: float = math.nan
    status: str = "-"
    status_logged: str | None = None
    reason: str = ""
    users: list[tuple[str, float | None, float | None]] = field(default_factory=list)  # id, error, bound
    #: users the answer does not locate: no estimate, or a mirror position explains the ranges as well
    #: (`ambiguous`; printed "[mirror ambiguity unresolved]", the command exits 1 naming them)
    not_located: list[str] = field(default_factory=list)
    replay_status: str = "-"
    replay_bounds: list[float | None] = field(default_factory=list)
    bound_diff_m: float = math.nan
    gps_tau_s: float | None = None
    residual_p50_m: float = math.nan
    residual_p99_m: float = math.nan
    timing_s: float = math.nan
    timing_rms_m: tuple[float, float] = (math.nan, math.nan)
    achieved: float = math.nan
    fell_behind: bool | None = None
    survey_s: float | None = None
    hover_s: float | None = None
    errors: list[str] = field(default_factory=list)
    #: reasons of the earlier attempts of this run that aborted before take-off (flown again)
    takeoff_aborts: list[str] = field(default_factory=list)

    @property
    def hover_share_text(self) -> str:
        return f"{100 * self.hover_s / self.survey_s:.0f} %" if self.survey_s and self.hover_s is not None else "-"

    @property
    def aborted_before_takeoff(self) -> bool:
        return self.status == "aborted" and self.reason.startswith("not taking off")

    @property
    def outside(self) -> list[str]:
        """Located users whose error exceeds their printed 95 % bound."""
        return [u for u, e, b in self.users if u not in self.not_located and not (e is not None and b is not None
                                                                                  and e <= b)]

    def verdict(self, user: str, error_m: float | None, bound_m: float | None) -> str:
        if user in self.not_located:
            return "not located" + (" (mirror ambiguity)" if bound_m is not None else "")
        return "in" if error_m is not None and bound_m is not None and error_m <= bound_m else "OUT"

    @property
    def claim_holds(self) -> bool:
        """target_reached only with every printed bound within the target."""
        return self.status != "target_reached" or all(b is not None and b <= self.target_m + 1e-9
                                                      for _, _, b in self.users)

    @property
    def replay_agrees(self) -> bool:
        return (self.replay_status == self.status and len(self.replay_bounds) == len(self.users)
                and math.isfinite(self.bound_diff_m) and self.bound_diff_m <= BOUND_AGREE_M)


def _cli(args: list[str], timeout_s: float, stdout_file: Path, stderr_file: Path) -> tuple[int, str]:
    """`python -m mission ARGS` of this tree; (exit code, stdout). -1 on timeout (SIGTERM, then SIGKILL)."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    with open(stdout_file, "w") as out, open(stderr_file, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "mission", *args], stdout=out, stderr=err, cwd=REPO, env=env,
                                start_new_session=True)
        code = -1
        try:
            code = proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            pass
        finally:  # a timeout, or the benchmark itself stopped: the command's whole process group goes
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
                try:
                    proc.wait(30)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
    return code, stdout_file.read_text()


def _free_instances(n: int) -> list[int]:
    picked: list[int] = []
    for i in INSTANCES:
        if len(picked) == n:
            break
        if not instance_busy(i):
            picked.append(i)
    if len(picked) < n:
        raise SystemExit(f"px4 honesty: {n} free PX4 instances of {INSTANCES.start}-{INSTANCES.stop - 1} needed, "
                         f"found {picked}")
    return picked


def _last_line(path: Path) -> str:
    lines = [x for x in path.read_text(errors="replace").splitlines() if x.strip()]
    return lines[-1] if lines else "no output"


def range_timing_s(log_path: Path) -> tuple[float, float, float]:
    """How late the logged UAV positions of a log's ranges are: (Δt [s], RMS residual before,
    after the fit [m]).

    The simulated gNB of a PX4 flight ranges from PX4's reported position when it answers; the
    mission places the range at its own stamp on the logged telemetry. A stamp Δt early or late
    leaves a residual that follows the range rate ṙ = v · (uav − user) / ‖uav − user‖:

        C·toa − ‖uav(t) − user‖ ≈ b_k + ṙ(t) · Δt

    b_k a constant per user (the UE's clock, s0). Fitted by least squares over the log's ranges
    (v: the logged velocity of the range's vehicle, interpolated at its time); Δt > 0: the range is
    from where the UAV was Δt after the logged position's time. NaN without velocities or truth.
    """
    from mission.log import read_mission_log

    mlog = read_mission_log(log_path)
    if mlog.truth_lla is None or mlog.tel_vel_ned_mps is None or len(mlog.rtt_t_s) < 10:
        return math.nan, math.nan, math.nan
    origin = mlog.header.origin
    truth = origin.lla_to_enu(mlog.truth_lla[:, 0], mlog.truth_lla[:, 1], mlog.truth_lla[:, 2])
    uav = origin.lla_to_enu(mlog.rtt_uav_lla[:, 0], mlog.rtt_uav_lla[:, 1], mlog.rtt_uav_lla[:, 2])
    # ENU velocity (v_e, v_n, −v_d) of each range's vehicle at the range's time
    vel = np.full((len(mlog.rtt_t_s), 3), np.nan)
    for v in np.unique(mlog.rtt_vehicle):
        sel, tsel = mlog.rtt_vehicle == v, mlog.tel_vehicle == v
        ok = tsel & np.all(np.isfinite(mlog.tel_vel_ned_mps), axis=1)
        if ok.sum() < 2:
            continue
        ned = [np.interp(mlog.rtt_t_s[sel], mlog.tel_t_s[ok], mlog.tel_vel_ned_mps[ok, i]) for i in range(3)]
        vel[sel] = np.column_stack([ned[1], ned[0], -ned[2]])
    los = uav - truth[mlog.rtt_user]
    d = np.linalg.norm(los, axis=1)
    res = C_MPS * mlog.rtt_toa_s - d
    rdot = np.sum(vel * los, axis=1) / d
    good = np.isfinite(res) & np.isfinite(rdot)
    users = np.unique(mlog.rtt_user[good])
    a = np.column_stack([(mlog.rtt_user[good] == k).astype(float) for k in users] + [rdot[good]])
    y = res[good]
    keep = np.ones(len(y), bool)
    for _ in range(2):  # once more without the residuals beyond 3σ of the first fit (NLoS)
        x, *_ = np.linalg.lstsq(a[keep], y[keep], rcond=None)
        fit = y - a @ x
        keep = np.abs(fit) <= 3.0 * np.std(fit[keep])
    before = y - a[:, :-1] @ np.linalg.lstsq(a[keep, :-1], y[keep], rcond=None)[0]
    return float(x[-1]), float(np.sqrt(np.mean(before[keep] ** 2))), float(np.sqrt(np.mean(fit[keep] ** 2)))


def judge(run: Run, doc: dict, replayed: dict | None, log_path: Path) -> None:
    """Fill `run` from the flight's `--json` document, its replay's and its log."""
    run.status = doc.get("status", "-")
    run.status_logged = doc.get("status_logged")
    run.reason = str(doc.get("reason", ""))
    run.users = [(u["id"], u.get("error_m"), u.get("error_bound_95_m")) for u in doc.get("users", [])]
    run.not_located = [u["id"] for u in doc.get("users", []) if u.get("enu_m") is None or u.get("ambiguous")]
    run.survey_s, run.hover_s = doc.get("survey_s"), doc.get("hover_s")
    if vehicles := doc.get("vehicles"):  # a fleet: hovering over surveying, every vehicle's seconds summed
        run.survey_s = sum(v.get("survey_s") or 0.0 for v in vehicles)
        run.hover_s = sum(v.get("hover_s") or 0.0 for v in vehicles)
    pace = doc.get("speedup") or {}
    run.achieved = float(pace.get("achieved_speedup", math.nan))
    run.fell_behind = pace.get("fell_behind")
    if replayed is not None:
        run.replay_status = replayed.get("status", "-")
        run.replay_bounds = [u.get("error_bound_95_m") for u in replayed.get("users", [])]
        if len(run.replay_bounds) == len(run.users):
            diffs = [abs(a - b) if a is not None and b is not None else (0.0 if a is b else math.inf)
                     for (_, _, a), b in zip(run.users, run.replay_bounds, strict=True)]
            run.bound_diff_m = max(diffs, default=0.0)
    if log_path.exists():
        res = range_residuals_m(log_path)
        if res.size:
            run.residual_p50_m = float(np.percentile(np.abs(res), 50))
            run.residual_p99_m = float(np.percentile(np.abs(res), 99))
        run.timing_s, *rms = range_timing_s(log_path)
        run.timing_rms_m = (rms[0], rms[1])
        with open(log_path) as fh:
            for line in fh:
                if '"gps_tau"' in line:
                    rec = json.loads(line)
                    if rec.get("kind") == "gps_tau":
                        run.gps_tau_s = rec.get("gps_tau_s")


def fly(run: Run, sitls: list[Px4Sitl], out: Path, timeout_s: float) -> None:
    """`uavloc sim SCENARIO --connect ... --json --out OUT`, then `uavloc replay LOG --json`."""
    connect = ",".join(s.api_url for s in sitls)
    t0 = time.monotonic()
    run.exit_code, stdout = _cli(["sim", run.scenario, "--connect", connect, "--json", "--out", str(out)],
                                 timeout_s, out.with_suffix(".stdout"), out.with_suffix(".stderr"))
    run.wall_s = time.monotonic() - t0
    try:
        doc = json.loads(stdout) if stdout.strip() else None
    except json.JSONDecodeError:
        doc = None
    if doc is None:
        why = f"no end within {timeout_s:g} s" if run.exit_code == -1 else _last_line(out.with_suffix(".stderr"))
        run.errors.append(f"sim exit {run.exit_code}: {why}")
        return
    log_path = Path(doc["log"]) if doc.get("log") else out / "mission.jsonl"
    replayed = None
    if not doc.get("measurements"):  # nothing measured (aborted before take-off): nothing to replay
        judge(run, doc, None, log_path)
        return
    code, rstdout = _cli(["replay", str(log_path), "--json"], 600.0, out.with_name(out.name + "-replay.stdout"),
                         out.with_name(out.name + "-replay.stderr"))
    try:
        replayed = json.loads(rstdout) if rstdout.strip() else None
    except json.JSONDecodeError:
        replayed = None
    if replayed is None:
        run.errors.append(f"replay exit {code}: {_last_line(out.with_name(out.name + '-replay.stderr'))}")
    judge(run, doc, replayed, log_path)


def with_px4(build: Path, homes: list[tuple[float, float, float]], speed: float, work: Path, tag: str,
             ready_s: float, body) -> None:
    """Start one PX4 per home (free instances), wait until each is ready, run body(sitls), stop them all."""
    instances = _free_instances(len(homes))
    sitls = [Px4Sitl(build, inst, speed, work / f"{tag}-px4-work-{k}", home=home, output=work / f"{tag}-px4-{k}.log")
             for k, (inst, home) in enumerate(zip(instances, homes, strict=True))]
    try:
        for s in sitls:
            s.start()
        for s in sitls:
            if not s.wait_ready(ready_s):
                raise RuntimeError(f"PX4 instance {s.instance} did not print 'Ready for takeoff!' within "
                                   f"{ready_s:g} s: {''.join(s.lines[-4:]).strip()}")
        body(sitls)
    finally:
        for s in sitls:
            s.stop()


def _f(x, spec: str = ".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def describe(run: Run) -> list[str]:
    if run.errors and run.status == "-":
        return [f"{run.name}: {'; '.join(run.errors)} ({_f(run.wall_s, '.0f')} s wall)"]
    hover = run.hover_share_text
    lines = [f"{run.name}: exit {run.exit_code}, status {run.status} (logged {run.status_logged}), "
             f"replay {run.replay_status}, max |Δbound| {_f(run.bound_diff_m, '.2g')} m; "
             f"τ {_f(run.gps_tau_s, '.0f')} s, "
             f"|range residual| p50 {_f(run.residual_p50_m, '.1f')} p99 {_f(run.residual_p99_m, '.1f')} m, "
             f"timing Δt {_f(run.timing_s, '+.3f')} s (RMS {_f(run.timing_rms_m[0], '.2f')} → "
             f"{_f(run.timing_rms_m[1], '.2f')} m); "
             f"wall {_f(run.wall_s, '.0f')} s, survey {_f(run.survey_s, '.0f')} s, hover {hover}, "
             f"ran ×{_f(run.achieved, '.1f')}, fell_behind {run.fell_behind}",
             f"    reason: {run.reason[:200]}"]
    lines += [f"    {u}: error {_f(e)} m, bound {_f(b)} m, replay bound {_f(rb)} m: "
              f"{run.verdict(u, e, b)}"
              for (u, e, b), rb in zip(run.users, run.replay_bounds or [None] * len(run.users), strict=True)]
    if run.status == "target_reached":
        lines.append(f"    target_reached with every bound ≤ {run.target_m:g} m: {'yes' if run.claim_holds else 'NO'}")
    lines += [f"    error: {e}" for e in run.errors]
    lines += [f"    an earlier attempt aborted before take-off: {a[:240]}" for a in run.takeoff_aborts]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--homes", default=",".join(HOMES), help=f"comma-separated of {', '.join(HOMES)} (default: all)")
    ap.add_argument("--fleet-scenario", default="two_uavs",
                    help="the two-vehicle scenario (default two_uavs; tests/data/px4_two_uavs.toml is the tests' "
                         "smaller one)")
    ap.add_argument("--single-scenario", default="five_commercial_ues", help="the one-vehicle scenario")
    ap.add_argument("--skip-fleet", action="store_true")
    ap.add_argument("--skip-single", action="store_true")
    ap.add_argument("--speed", type=float, default=4.0, help="PX4_SIM_SPEED_FACTOR (default 4)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="wall seconds one flight may take (default 1800)")
    ap.add_argument("--ready-timeout", type=float, default=180.0, help="wall seconds PX4 gets to be ready")
    ap.add_argument("--retries", type=int, default=2,
                    help="fly a run again (fresh PX4s) this many times when it aborts before take-off (default 2)")
    ap.add_argument("--keep", type=Path, metavar="DIR", help="keep the flights' folders and PX4's output here")
    args = ap.parse_args(argv)
    build = build_from_env()
    why = missing_requirement(build)
    if why is not None:
        print(f"px4 honesty benchmark skipped: {why}")
        return 0
    homes = [h for h in args.homes.split(",") if h]
    if unknown := [h for h in homes if h not in HOMES]:
        ap.error(f"--homes: unknown {', '.join(unknown)} (known: {', '.join(HOMES)})")
    fleet_target = load_scenario(args.fleet_scenario).mission.flight.target_radius_m
    single_target = load_scenario(args.single_scenario).mission.flight.target_radius_m
    print(f"PX4 SITL {build}, speed factor {args.speed:g}; {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f}", flush=True)
    runs: list[Run] = []
    with tempfile.TemporaryDirectory(prefix="uavloc-px4-honesty-") as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        plan: list[tuple[Run, list[tuple[float, float, float]]]] = []
        for h in homes if not args.skip_fleet else ():
            home = HOMES[h]
            lat, lon, alt = Origin(*home).enu_to_lla([PAIR_EAST_M, 0.0, 0.0])
            plan.append((Run(f"{args.fleet_scenario} @ {h}", h, args.fleet_scenario, fleet_target),
                         [home, (float(lat), float(lon), float(alt))]))
        if not args.skip_single:
            plan.append((Run(f"{args.single_scenario} @ {homes[0]}", homes[0], args.single_scenario, single_target),
                         [HOMES[homes[0]]]))
        for k, (planned, run_homes) in enumerate(plan):
            aborts: list[str] = []
            for attempt in range(1 + args.retries):
                run = replace(planned, takeoff_aborts=list(aborts), errors=[])
                tag = f"{k}-{Path(run.scenario).stem}-{run.home}-{attempt}"
                out = work / tag
                try:
                    with_px4(build, run_homes, args.speed, work, tag, args.ready_timeout,
                             lambda sitls, run=run, out=out: fly(run, sitls, out, args.timeout))
                except RuntimeError as exc:
                    run.errors.append(str(exc))
                if not run.aborted_before_takeoff:
                    break
                if attempt == args.retries:
                    run.errors.append(f"aborted before take-off in all {1 + args.retries} attempts")
                    break
                aborts.append(run.reason)
                print(f"{run.name}: aborted before take-off, flown again: {run.reason[:240]}", flush=True)
            runs.append(run)
            print("\n".join(describe(run)), f"  (load average {os.getloadavg()[0]:.1f})", flush=True)
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)

    print()
    head = (f"{'run':<32} {'status':<15} {'logged':<15} {'replay':<15} {'in/loc/all':>10} {'claim':>5} "
            f"{'Δbound':>7} {'τ s':>5} {'res p99':>7} {'wall s':>6} {'×ran':>5} {'behind':>6} {'hover':>6} {'Δt s':>6}")
    print(head)
    print("-" * len(head))
    for r in runs:
        n_loc = len(r.users) - len(r.not_located)
        n_in = n_loc - len(r.outside)
        print(f"{r.name:<32} {r.status:<15} {r.status_logged!s:<15} {r.replay_status:<15} "
              f"{f'{n_in}/{n_loc}/{len(r.users)}':>10} {'ok' if r.claim_holds else 'LIE':>5} "
              f"{_f(r.bound_diff_m, '.0e'):>7} "
              f"{_f(r.gps_tau_s, '.0f'):>5} {_f(r.residual_p99_m, '.1f'):>7} {_f(r.wall_s, '.0f'):>6} "
              f"{_f(r.achieved, '.1f'):>5} {r.fell_behind!s:>6} {r.hover_share_text:>6} {_f(r.timing_s, '+.2f'):>6}")
    print()
    failed = [r for r in runs if r.errors]
    outside = [(r, u) for r in runs for u in r.outside]
    lies = [r for r in runs if not r.claim_holds]
    disagree = [r for r in runs if r.status != "-" and not r.replay_agrees]
    total = sum(len(r.users) for r in runs)
    located = total - sum(len(r.not_located) for r in runs)
    verdicts = [
        (not failed, f"every run gave a result ({len(runs) - len(failed)}/{len(runs)})"
         + ("" if not failed else ": " + "; ".join(f"{r.name}: {r.errors[0]}" for r in failed))),
        (located == total, f"every user located ({located}/{total})" + ("" if located == total else ": not "
         + "; ".join(f"{', '.join(r.not_located)} of {r.name} ({r.status}: {r.reason[:100]})"
                     for r in runs if r.not_located))),
        (not outside, f"every located user inside its printed 95 % bound ({located - len(outside)}/{located})"
         + ("" if not outside else ": outside " + ", ".join(f"{u} of {r.name}" for r, u in outside))),
        (not lies, "target_reached only with every printed bound within the target"
         + ("" if not lies else ": not in " + ", ".join(r.name for r in lies))),
        (not disagree, f"replay prints the flight's status and bounds (within {BOUND_AGREE_M:g} m)"
         + ("" if not disagree else ": not in " + ", ".join(
             f"{r.name} ({r.replay_status} vs {r.status}, Δ {_f(r.bound_diff_m, '.2g')} m)" for r in disagree))),
    ]
    for ok, text in verdicts:
        print(f"{'PASS' if ok else 'FAIL'}: {text}")
    if aborts := sum(len(r.takeoff_aborts) for r in runs):
        print(f"NOTE: {aborts} attempt(s) aborted before take-off and were flown again: "
              + "; ".join(f"{r.name}: {a[:160]}" for r in runs for a in r.takeoff_aborts))
    return 0 if all(ok for ok, _ in verdicts) else 1


if __name__ == "__main__":
    # stopped (SIGTERM): unwind, so that every PX4 and every command started is stopped
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    raise SystemExit(main())
