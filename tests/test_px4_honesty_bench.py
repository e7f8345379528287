"""benchmarks/px4_honesty.py without PX4: it skips naming UAVLOC_PX4, and its range-timing fit
recovers a known lag of the logged positions behind the ranges (an example log whose rtt records
carry the position the UAV had Δt before the range)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sitl_scenarios.example_log import generate
from sitl_scenarios.scenario import load_scenario
from tests.bench_module import load_benchmark

REPO = Path(__file__).resolve().parents[1]


def _bench():
    return load_benchmark("px4_honesty")


def test_without_a_px4_build_it_says_which_variable_and_exits_0(monkeypatch, capsys):
    monkeypatch.delenv("UAVLOC_PX4", raising=False)
    assert _bench().main([]) == 0
    out = capsys.readouterr().out
    assert "skipped" in out and "UAVLOC_PX4" in out


def _lagged(src: Path, dst: Path, lag_s: float) -> None:
    """dst: src with each rtt record's UAV position replaced by the telemetry's lag_s before it
    (interpolated), as a range stamped lag_s late onto the track would be logged."""
    records = [json.loads(line) for line in src.read_text().splitlines()]
    tel = [r for r in records if r["type"] == "telemetry"]
    t = np.array([r["t"] for r in tel])
    cols = {k: np.array([r[k] for r in tel]) for k in ("lat_deg", "lon_deg", "alt_m")}
    with open(dst, "w") as fh:
        for r in records:
            if r["type"] == "rtt":
                r["uav"] = {k: float(np.interp(r["t"] - lag_s, t, v)) for k, v in cols.items()}
            fh.write(json.dumps(r) + "\n")


@pytest.mark.parametrize("lag_s", [0.0, 1.0])
def test_the_timing_fit_recovers_the_lag_of_the_logged_positions(tmp_path, lag_s):
    src, dst = tmp_path / "example.jsonl", tmp_path / "lagged.jsonl"
    generate(load_scenario("paper"), src, seed=3)
    _lagged(src, dst, lag_s)
    dt_s, rms_before_m, rms_after_m = _bench().range_timing_s(dst)
    assert dt_s == pytest.approx(lag_s, abs=0.2), (dt_s, rms_before_m, rms_after_m)
    assert rms_after_m <= rms_before_m + 1e-9
