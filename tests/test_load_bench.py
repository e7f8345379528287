"""benchmarks/load.py keeps what it measured: with --out, every run's figures go to results.jsonl,
and a later call with the same --out takes those runs as done (the whole table takes hours at ×1,
and a session may end before it does)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from tests.bench_module import load_benchmark

REPO = Path(__file__).resolve().parents[1]


def _bench():
    return load_benchmark("load")


def test_runs_already_in_the_results_file_are_not_flown_again_and_fill_the_table(tmp_path, capsys):
    bench = _bench()
    done = bench.Run("paper", 10.0, 1, "idle", 0, 41.0, status="target_reached", users=1, located=1, inside=1,
                     residual_p99_m=15.0, hover_share=0.1, achieved=10.0)
    # the second line: a run killed while its line was written
    (tmp_path / bench.RESULTS_FILE).write_text(json.dumps(asdict(done)) + "\n" + '{"scenario": "pap\n')
    code = bench.main(["--scenarios", "paper", "--seeds", "1", "--speedups", "10", "--loads", "idle",
                       "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    assert code == 0, out
    assert "1 runs already in" in out
    assert "results.jsonl:2: skipped" in err
    row = next(line for line in out.splitlines() if line.startswith("paper"))
    assert row.split() == ["paper", "10", "|", "idle", "1", "1/1", "1", "0", "15.0", "10%", "10.0", "0", "0", "41"]
    # nothing was flown: no mission folder beside the results file
    assert sorted(p.name for p in tmp_path.iterdir()) == [bench.RESULTS_FILE]


def test_a_results_line_round_trips_to_the_same_run(tmp_path):
    bench = _bench()
    run = bench.Run("two_uavs", 4.0, 3, "loaded", 1, 12.5, errors=["no autopilot heartbeat"], fell_behind=True)
    path = tmp_path / bench.RESULTS_FILE
    path.write_text(json.dumps(asdict(run)) + "\n")
    (key, back), = bench.load_results(path).items()
    assert key == ("two_uavs", 4.0, 3, "loaded")
    # NaN figures (no survey, no ranges) compare unequal to themselves: compare the JSON
    assert json.dumps(asdict(back)) == json.dumps(asdict(run))
