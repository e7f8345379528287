"""Replay on logs that behave like hardware: gps_tau_s in the header or estimated from the
telemetry velocity, no online pass for --json without --out, per-user noise scale and bias."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import mission.replay as replay_mod
from estimator.geodesy import Origin
from estimator.gps import estimate_gps_tau_s
from estimator.noise import NoiseModel
from estimator.ranging import C_MPS
from estimator.simulate import gps_error_m
from mission.cli import main
from mission.log import MissionLogWriter, read_mission_log
from mission.replay import ReplayOptions, replay, resolve_gps_tau, result_of_replay
from uavloc.errors import MissionLogError

ORIGIN = Origin(43.6143, 7.0716, 150.0)


def _write(path: Path, noise: NoiseModel, tau_true_s: float, with_vel: bool = True, n: int = 300,
           scale: tuple = (1.0, 1.0), seed: int = 3) -> np.ndarray:
    """A circle at 5 m/s, telemetry at 5 Hz (velocity when asked), two users, every other record
    a trigger. Returns the users' truth (2, 3)."""
    rng = np.random.default_rng(seed)
    users = np.array([[40.0, 20.0, 0.0], [-30.0, -50.0, 0.0]])
    t = np.arange(2 * n) * 0.2
    a = 5.0 * t / 60.0
    pos = np.column_stack([60 * np.cos(a), 60 * np.sin(a), np.full(t.size, 35.0)])
    vel = np.column_stack([-5 * np.sin(a), 5 * np.cos(a), np.zeros(t.size)])
    gps = pos + gps_error_m(rng, t.size, 1.0, tau_true_s, 0.2)
    lat, lon, alt = ORIGIN.enu_to_lla(gps)
    with MissionLogWriter(path) as w:
        w.write_header(ORIGIN, [{"id": f"u{k}", "rnti": 0x4601 + k, "ground_alt_m": 150.0} for k in range(2)],
                       {"mu": 1, "fs_hz": 46.08e6}, noise=noise)
        tl, tn, ta = ORIGIN.enu_to_lla(users)
        w.write("truth", 0.0, users=[{"id": f"u{k}", "lat_deg": float(tl[k]), "lon_deg": float(tn[k]),
                                      "alt_m": float(ta[k])} for k in range(2)])
        for i in range(t.size):
            extra = {"vel_ned_mps": [float(vel[i, 1]), float(vel[i, 0]), 0.0]} if with_vel else {}
            w.write("telemetry", t[i], lat_deg=float(lat[i]), lon_deg=float(lon[i]), alt_m=float(alt[i]), **extra)
            if i % 2 == 0:
                uav = {"lat_deg": float(lat[i]), "lon_deg": float(lon[i]), "alt_m": float(alt[i])}
                for k in range(2):
                    r = np.linalg.norm(pos[i] - users[k]) + scale[k] * 3.0 * rng.normal()
                    w.write("rtt", t[i], user=f"u{k}", uav=uav, toa_s=float(r / C_MPS))
    return users


def test_gps_tau_in_header_round_trips(tmp_path):
    p = tmp_path / "a.jsonl"
    _write(p, NoiseModel(gps_tau_s=120.0), 120.0)
    mlog = read_mission_log(p)
    assert mlog.header.noise.gps_tau_s == 120.0
    assert resolve_gps_tau(mlog, mlog.header.noise).gps_tau_s == 120.0
    assert np.isfinite(mlog.tel_vel_ned_mps).all()


@pytest.mark.parametrize("tau_true", [0.0, 120.0])
def test_gps_tau_estimated_from_velocity_when_the_header_lacks_it(tmp_path, tau_true):
    p = tmp_path / "b.jsonl"
    _write(p, NoiseModel(gps_tau_s=None), tau_true)
    mlog = read_mission_log(p)
    assert mlog.header.noise.gps_tau_s is None
    tau = resolve_gps_tau(mlog, mlog.header.noise).gps_tau_s
    if tau_true == 0.0:
        assert tau == 0.0
    else:
        assert 40.0 < tau < 400.0, tau


def test_gps_tau_default_without_velocity(tmp_path):
    p = tmp_path / "c.jsonl"
    _write(p, NoiseModel(gps_tau_s=None), 120.0, with_vel=False)
    mlog = read_mission_log(p)
    assert np.isnan(mlog.tel_vel_ned_mps).all()
    assert resolve_gps_tau(mlog, mlog.header.noise).gps_tau_s is None


def test_estimate_gps_tau_needs_enough_pairs():
    t = np.arange(5.0)
    assert estimate_gps_tau_s(t, np.zeros((5, 3)), np.zeros((5, 3)), 1.0) is None


@pytest.mark.parametrize("bad", ['"fast"', "[1, 2]", "[1, 2, null]", "[1e9, 0, 0]", "[true, 0, 0]"])
def test_bad_velocity_is_an_error_with_a_line_number(tmp_path, bad):
    p = tmp_path / "d.jsonl"
    _write(p, NoiseModel(), 0.0, n=30)
    lines = p.read_text().splitlines()
    i = next(j for j, ln in enumerate(lines) if '"telemetry"' in ln)
    obj = json.loads(lines[i])
    lines[i] = json.dumps({**obj, "vel_ned_mps": json.loads(bad)})
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(MissionLogError, match=rf":{i + 1}: vel_ned_mps"):
        read_mission_log(p)


@pytest.mark.parametrize("bad", ['"slow"', "-5", "true"])
def test_bad_gps_tau_in_header_is_an_error(tmp_path, bad):
    p = tmp_path / "e.jsonl"
    _write(p, NoiseModel(), 0.0, n=30)
    lines = p.read_text().splitlines()
    obj = json.loads(lines[0])
    obj["noise"]["gps_tau_s"] = json.loads(bad)
    lines[0] = json.dumps(obj)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(MissionLogError, match=":1: .*gps_tau_s"):
        read_mission_log(p)


def test_json_without_out_runs_no_online_pass(tmp_path, capsys, monkeypatch):
    p = tmp_path / "f.jsonl"
    _write(p, NoiseModel(gps_tau_s=60.0), 60.0, n=100)
    seen = []
    real = replay_mod.replay
    monkeypatch.setattr(replay_mod, "replay", lambda mlog, options, progress=None: (
        seen.append(options.history), real(mlog, options, progress))[1])
    assert main(["replay", str(p), "--json"]) == 0
    assert seen == [False]
    doc = json.loads(capsys.readouterr().out)
    assert doc["status"] == "ok"


def test_noisier_ue_reported_with_its_noise_scale_and_an_honest_bound(tmp_path):
    p = tmp_path / "g.jsonl"
    truth = _write(p, NoiseModel(gps_tau_s=0.0), 0.0, scale=(1.0, 2.5), n=400)
    res = replay(read_mission_log(p), ReplayOptions(history=False))
    doc = result_of_replay(res).to_document()
    scales = [u["noise_scale"] for u in doc["users"]]
    assert scales[0] < 1.3 and 2.0 < scales[1] < 3.0, scales
    assert all(u["bias_m"] == 0.0 for u in doc["users"])  # no clock offset: selected off
    err = np.linalg.norm(res.estimate.users_enu_m[:, :2] - truth[:, :2], axis=1)
    assert np.all(err < res.estimate.error_bound_95_m() * 1.5)
    assert math.isfinite(doc["users"][1]["error_bound_95_m"])
