"""One name and one set of defaults for each noise parameter: σ(d) = s0 + a·exp(b·d) is
range_s0_m, range_a_m, range_b_per_m in a mission file, on NoiseModel and in a log header; logs
written before still read with s0, a, b."""

from __future__ import annotations

import dataclasses

import pytest

from estimator.noise import NoiseModel
from mission.config import NoiseConfig
from uavloc.errors import EstimatorError


def test_the_mission_file_and_the_noise_model_share_names_and_defaults():
    cfg, model = NoiseConfig(), NoiseModel()
    for name in ("sigma_gps_m", "range_s0_m", "range_a_m", "range_b_per_m"):
        assert getattr(cfg, name) == getattr(model, name), name
    assert {f.name for f in dataclasses.fields(NoiseModel)} >= {"range_s0_m", "range_a_m", "range_b_per_m"}
    noise = NoiseConfig(range_s0_m=2.5, range_a_m=0.1, range_b_per_m=0.01).noise_model()
    assert (noise.range_s0_m, noise.range_a_m, noise.range_b_per_m) == (2.5, 0.1, 0.01)


def test_the_header_writes_the_one_names_and_reads_the_old_ones():
    noise = NoiseModel(sigma_gps_m=1.5, range_s0_m=2.5, range_a_m=0.1, range_b_per_m=0.01, gps_tau_s=30.0)
    section = noise.to_log_dict()
    assert section["range_sigma_m"] == {"range_s0_m": 2.5, "range_a_m": 0.1, "range_b_per_m": 0.01}
    assert NoiseModel.from_log_dict(section) == noise
    old = {"sigma_gps_m": 1.5, "gps_tau_s": 30.0, "range_sigma_m": {"s0": 2.5, "a": 0.1, "b": 0.01}}
    assert NoiseModel.from_log_dict(old) == noise
    # absent parameters take the defaults; both spellings of one is refused
    assert NoiseModel.from_log_dict({"range_sigma_m": {"s0": 4.0}}) == NoiseModel(range_s0_m=4.0, gps_tau_s=None)
    with pytest.raises(EstimatorError, match="both 'range_s0_m' and its old name 's0'"):
        NoiseModel.from_log_dict({"range_sigma_m": {"s0": 4.0, "range_s0_m": 4.0}})
