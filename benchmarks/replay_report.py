"""Replay + report of a long mission: a 5 000-keyframe log through `uavloc replay LOG --out DIR`.

    python benchmarks/replay_report.py                  # 5 000 keyframes, three users among buildings
    python benchmarks/replay_report.py --keyframes 1000 --scenario paper

The log comes from sitl_scenarios.example_log (radio model along survey circles, Δ = 2 m); it is
generated once into --work (default /tmp/uavloc-bench) and reused. The command runs as a
subprocess, as a user would run it, with its stderr (progress bar / progress lines) passed
through; the wall time of the whole command and the report's own time (from its log line) are
printed at the end.
"""

from __future__ import annotations

import argparse
import math
import re
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sitl_scenarios.example_log import generate
from sitl_scenarios.scenario import load_scenario


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keyframes", type=int, default=5000)
    ap.add_argument("--scenario", default="three_users_nlos")
    ap.add_argument("--radius", type=float, default=150.0, help="survey circle radius [m]")
    ap.add_argument("--work", type=Path, default=Path("/tmp/uavloc-bench"))
    args = ap.parse_args()
    sc = load_scenario(args.scenario)
    # keyframes ≈ (climb + out + turns·2πr + back) / Δ
    turns = max(args.keyframes * sc.mission.flight.delta_m / (2 * math.pi * args.radius) - 0.3, 0.2)
    args.work.mkdir(parents=True, exist_ok=True)
    log_path = args.work / f"{sc.name}_{args.keyframes}.jsonl"
    if not log_path.exists():
        t0 = time.perf_counter()
        counts = generate(sc, log_path, radius_m=args.radius, n_turns=turns)
        print(f"generated {log_path}: {counts['rtt']} rtt records, {counts['flown_m']:.0f} m "
              f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    out = args.work / f"report_{sc.name}_{args.keyframes}"
    # baseline, same run and same way: a subprocess that only parses the log (the I/O floor)
    base_cmd = [sys.executable, "-c", "import sys; from mission.log import read_mission_log; "
                "read_mission_log(sys.argv[1])", str(log_path)]
    t0 = time.perf_counter()
    subprocess.run(base_cmd, cwd=Path(__file__).resolve().parents[1], check=True)
    base = time.perf_counter() - t0
    cmd = [sys.executable, "-m", "mission.cli", "replay", str(log_path), "--out", str(out)]
    print("$", " ".join(cmd), file=sys.stderr)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=Path(__file__).resolve().parents[1], stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    sys.stderr.write(proc.stderr)
    if proc.returncode != 0:
        print(f"replay failed with exit code {proc.returncode}", file=sys.stderr)
        return proc.returncode
    m = re.search(r"report: .* \(([0-9.]+) s\)", proc.stderr)
    print(f"replay + report: {wall:.1f} s wall; report alone: {m.group(1) if m else '?'} s; "
          f"files in {out}", file=sys.stderr)
    print(f"baseline (parse the log only): {base:.2f} s; replay + report / baseline: {wall / base:.1f}x")
    verdict = "PASS" if wall <= 20.0 else "FAIL"
    print(f"{verdict}  replay + report of {args.keyframes} keyframes <= 20 s: {wall:.1f} s")
    return 0 if verdict == "PASS" else 1


if __name__ == "__main__":
    raise SystemExit(main())
