"""Noise-model calibration: σ(d) = s0 + a·exp(b·d) and per-user bias recovered from simulated logs
with known truth; clear messages when the data cannot support the fit."""

from __future__ import annotations

import json
import re
import tomllib

import numpy as np
import pytest

from estimator.calibration import CalibrationParams, fit_range_noise, range_residuals
from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from estimator.ranging import C_MPS
from mission.cli import main
from mission.log import MissionLogWriter
from uavloc.errors import EstimatorError

ORIGIN = Origin(47.397742, 8.545594, 488.0)
TRUE = {"s0": 2.0, "a": 0.3, "b": 0.009}
USERS_ENU = np.array([[0.0, 0.0, 0.0], [30.0, -20.0, 1.0]])
BIAS = np.array([3.0, 5.0])
SIGMA_GPS = 1.0


def simulate(seed: int, m: int, bias=BIAS, s0=TRUE["s0"], a=TRUE["a"], b=TRUE["b"], r_max=480.0):
    """UAV at 40 m anywhere within r_max of the first user; r̂ = d + β_k + N(0, σ(d)²); the logged
    UAV position is the true one plus N(0, σ_gps²) per axis. Returns (gps (m,3), user_idx, range)."""
    rng = np.random.default_rng(seed)
    r = r_max * np.sqrt(rng.uniform(0.002, 1.0, m))
    th = rng.uniform(0, 2 * np.pi, m)
    uav = np.c_[r * np.cos(th), r * np.sin(th), np.full(m, 40.0)]
    k = rng.integers(0, len(USERS_ENU), m)
    d = np.linalg.norm(uav - USERS_ENU[k], axis=1)
    rng_m = d + np.asarray(bias)[k] + rng.normal(0, 1, m) * (s0 + a * np.exp(b * d))
    return uav + rng.normal(0, SIGMA_GPS, uav.shape), k, rng_m


def write_log(path, seed: int, m: int, truth: bool = True, **kw):
    gps, k, r = simulate(seed, m, **kw)
    lat, lon, alt = ORIGIN.enu_to_lla(gps)
    tl = ORIGIN.enu_to_lla(USERS_ENU)
    ids = ["ue1", "ue2"]
    with MissionLogWriter(path) as w:
        users = [{"id": i, "rnti": 0x4601 + j, "ground_alt_m": float(tl[2][j])} for j, i in enumerate(ids)]
        w.write_header(ORIGIN, users, {"mu": 1, "fs_hz": 46.08e6}, noise=NoiseModel(sigma_gps_m=SIGMA_GPS))
        if truth:
            w.write("truth", 0.0, users=[{"id": i, "lat_deg": float(tl[0][j]), "lon_deg": float(tl[1][j]),
                                          "alt_m": float(tl[2][j])} for j, i in enumerate(ids)])
        for i in range(m):
            w.write("rtt", 0.1 * i, user=ids[k[i]], uav={"lat_deg": float(lat[i]), "lon_deg": float(lon[i]),
                                                          "alt_m": float(alt[i])}, toa_s=float(r[i] / C_MPS))
    return path


@pytest.fixture(scope="module")
def three_logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("cal")
    return [write_log(d / f"log{s}.jsonl", seed=s, m=20_000) for s in (1, 2, 3)]


def test_calibrate_recovers_s0_a_b_and_bias_within_10_percent(three_logs, tmp_path):
    out = tmp_path / "noise.json"
    assert main(["calibrate", *map(str, three_logs), "--format", "json", "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    rs = doc["noise"]["range_sigma_m"]
    assert doc["fit"]["model"] == "exponential"
    for key in ("s0", "a", "b"):
        assert rs[f"range_{key}_m" if key != "b" else "range_b_per_m"] == pytest.approx(TRUE[key], rel=0.10), (key, rs)
    assert doc["range_bias_m"]["ue1"] == pytest.approx(BIAS[0], rel=0.10)
    assert doc["range_bias_m"]["ue2"] == pytest.approx(BIAS[1], rel=0.10)
    assert doc["noise"]["sigma_gps_m"] == SIGMA_GPS
    assert doc["fit"]["points"] == {"ue1": pytest.approx(30_000, rel=0.05), "ue2": pytest.approx(30_000, rel=0.05)}
    # the noise section is what a log header takes
    nm = NoiseModel.from_log_dict(doc["noise"])
    assert nm.range_s0_m == rs["range_s0_m"] and nm.range_b_per_m == rs["range_b_per_m"]


def test_toml_output_is_a_scenario_radio_section(three_logs, capsys):
    assert main(["calibrate", str(three_logs[0])]) == 0
    text = capsys.readouterr().out
    doc = tomllib.loads(text)
    assert set(doc) == {"radio", "mission"}
    assert doc["radio"]["s0_m"] == pytest.approx(TRUE["s0"], rel=0.2)
    assert doc["radio"]["b_per_m"] == pytest.approx(TRUE["b"], rel=0.2)
    m = re.search(r"ue2: bias ([0-9.]+)", text)
    assert m and float(m.group(1)) == pytest.approx(BIAS[1], rel=0.1)


def test_positions_on_the_command_line_replace_a_missing_truth_line(tmp_path, capsys):
    log = write_log(tmp_path / "notruth.jsonl", seed=4, m=3000, truth=False)
    assert main(["calibrate", str(log)]) == 1
    assert "no truth line" in capsys.readouterr().err
    tl = ORIGIN.enu_to_lla(USERS_ENU)
    users = [f"ue{j + 1}={tl[0][j]:.9f},{tl[1][j]:.9f},{tl[2][j]:.3f}" for j in range(2)]
    assert main(["calibrate", str(log), "--format", "json", "--users", *users]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["range_bias_m"]["ue2"] == pytest.approx(BIAS[1], rel=0.1)
    # the sawtooth model through the CLI: the bias is still the mean of the residuals
    assert main(["calibrate", str(log), "--format", "json", "--sawtooth", "--users", *users]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["range_bias_m"]["ue2"] == pytest.approx(BIAS[1], rel=0.1)
    assert set(doc["fit"]["sawtooth_amplitude_m"]) == {"ue1", "ue2"}
    assert main(["calibrate", str(log), "--users", "nobody=47,8,500"]) == 1
    assert "not in the logs" in capsys.readouterr().err


def test_too_few_points_is_an_error_that_says_so():
    gps, k, r = simulate(5, 20)
    d, e = range_residuals(gps, USERS_ENU, k, r)
    with pytest.raises(EstimatorError, match="cannot calibrate: 20 usable range measurements"):
        fit_range_noise(d, e, k, 2)


def test_no_distance_spread_falls_back_to_a_constant_sigma_and_says_so():
    gps, k, r = simulate(6, 3000, r_max=20.0)  # everything within 20 m: distances 40-45 m
    d, e = range_residuals(gps, USERS_ENU, k, r)
    res = fit_range_noise(d, e, k, 2, CalibrationParams(sigma_gps_m=SIGMA_GPS))
    assert res.model == "constant" and res.a_m == 0.0
    assert any("cannot show how σ grows with distance" in m for m in res.messages)
    # constant σ: s0 ≈ σ(≈45 m) = 2 + 0.3·e^0.4 ≈ 2.45 m
    assert res.s0_m == pytest.approx(TRUE["s0"] + TRUE["a"] * np.exp(TRUE["b"] * 43), rel=0.1)
    np.testing.assert_allclose(res.bias_m, BIAS, rtol=0.1)


def test_constant_noise_is_not_mistaken_for_an_exponential():
    gps, k, r = simulate(7, 4000, a=0.0, b=0.0, s0=3.0)
    d, e = range_residuals(gps, USERS_ENU, k, r)
    res = fit_range_noise(d, e, k, 2, CalibrationParams(sigma_gps_m=SIGMA_GPS))
    assert res.model == "constant"
    assert any("not supported by the data" in m for m in res.messages)
    assert res.s0_m == pytest.approx(3.0, rel=0.05)


def test_nlos_outliers_are_left_out():
    gps, k, r = simulate(8, 5000)
    rng = np.random.default_rng(9)
    bad = rng.random(r.size) < 0.02
    r = r + bad * rng.exponential(80.0, r.size) + bad * 30.0
    d, e = range_residuals(gps, USERS_ENU, k, r)
    res = fit_range_noise(d, e, k, 2, CalibrationParams(sigma_gps_m=SIGMA_GPS))
    assert res.n_outliers >= 0.7 * bad.sum()
    assert res.s0_m == pytest.approx(TRUE["s0"], rel=0.25)
    np.testing.assert_allclose(res.bias_m, BIAS, rtol=0.1)
    kept = fit_range_noise(d, e, k, 2, CalibrationParams(sigma_gps_m=SIGMA_GPS, outlier_sigma=0))
    assert kept.n_outliers == 0 and kept.s0_m > 1.5 * res.s0_m


def test_sawtooth_model_separates_the_clock_drift_from_sigma():
    """Ranges from the simulated gNB's radio model with UE clock sawtooths (amplitudes 6 and 10 m):
    a Gaussian fit folds the sawtooth's spread into s0; the sawtooth model does not, and its bias
    is the sawtooth's mean A/2."""
    from estimator.ranging import range_m_from_raw
    from sitl_scenarios.radio import RadioModel
    from sitl_scenarios.scenario import scenario_from_dict, user_tables

    amps = (6.0, 10.0)
    sc = scenario_from_dict({
        "name": "cal-saw", "seed": 0,
        **user_tables([{"id": f"ue{j + 1}", "rnti": 0x4601 + j, "east_m": float(USERS_ENU[j, 0]),
                        "north_m": float(USERS_ENU[j, 1]), "up_m": float(USERS_ENU[j, 2]),
                        "sawtooth_amplitude_m": amps[j], "sawtooth_period_s": 17.0 + 6 * j} for j in range(2)]),
        "radio": {"s0_m": 2.0, "a_m": 0.2, "b_per_m": 0.008, "coverage_m": 3000.0, "nlos_excess_mean_m": 0.0},
    })
    radio = RadioModel(sc, np.random.default_rng(1))
    gps, k, _ = simulate(0, 6000)
    uav = gps  # the radio measures from here; GPS noise below
    t = np.sort(np.random.default_rng(2).uniform(0, 3000, len(k)))
    r = np.array([range_m_from_raw(x.ta, x.mu, x.srs_peak, x.fs_hz)
                  for x in (radio.measure(int(kk), p, tt) for kk, p, tt in zip(k, uav, t, strict=True))])
    gps = uav + np.random.default_rng(3).normal(0, SIGMA_GPS, uav.shape)
    d, e = range_residuals(gps, USERS_ENU, k, r)
    gauss = fit_range_noise(d, e, k, 2, CalibrationParams(sigma_gps_m=SIGMA_GPS))
    saw = fit_range_noise(d, e, k, 2, CalibrationParams(sigma_gps_m=SIGMA_GPS, sawtooth=True))
    assert gauss.s0_m > 1.3 * 2.0  # the sawtooth's spread A²/12 inflates a Gaussian σ
    assert saw.s0_m == pytest.approx(2.0, rel=0.15)
    assert saw.b_per_m == pytest.approx(0.008, rel=0.10)
    np.testing.assert_allclose(saw.sawtooth_amplitude_m, amps, rtol=0.2)
    np.testing.assert_allclose(saw.bias_m, np.array(amps) / 2, rtol=0.1)
