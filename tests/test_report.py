"""Mission report: the files written open, have the expected size and content, and are fast."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from estimator.types import CHI2_2DOF_95, Estimate
from mission.report import FIG_DPI, FIG_SIZE_IN, FIGURES, ReportInputs, ellipse_en_m, range_errors, write_report
from mission.result import build_result

ORIGIN = Origin(47.397742, 8.545594, 488.0)


def make_inputs(n_kf: int = 300, truth: bool = True, history: bool = True, seed: int = 3) -> ReportInputs:
    """Two users, a circle flown at 30 m, ranges = distance + bias + sawtooth + N(0, σ(d)²)."""
    rng = np.random.default_rng(seed)
    noise = NoiseModel(sigma_gps_m=1.0, range_s0_m=2.0, range_a_m=0.2, range_b_per_m=0.01)
    truth_enu = np.array([[40.0, 10.0, 0.0], [-25.0, 45.0, 1.0]])
    ang = np.linspace(0, 2 * np.pi, n_kf)
    gps = np.c_[80 * np.cos(ang), 80 * np.sin(ang), np.full(n_kf, 30.0)]
    t = np.arange(n_kf) * 0.2
    meas_user = np.tile([0, 1], n_kf)
    meas_t = np.repeat(t, 2)
    meas_uav = np.repeat(gps, 2, axis=0)
    d = np.linalg.norm(meas_uav - truth_enu[meas_user], axis=1)
    saw = 4.0 * ((meas_t / 20.0) % 1.0)
    r = d + saw + rng.normal(0, 1, d.size) * noise.range_sigma_m(d)
    cov = np.array([[[1.0, 0.3], [0.3, 0.5]], [[2.0, -0.4], [-0.4, 1.2]]])
    est = truth_enu + np.array([[0.8, -0.5, 0.0], [-1.0, 0.7, 0.0]])
    h_flown = np.linspace(0, 500, n_kf)
    cov3 = np.zeros((2, 3, 3))
    cov3[:, :2, :2] = cov
    cov3[:, 2, 2] = 1.0
    estimate = Estimate(users_enu_m=est, cov_users_m2=cov3, info_users=np.eye(6), bias_m=np.array([2.0, 2.1]),
                        uav_enu_m=gps + 0.3, ambiguous=np.array([False, False]), mirror_enu_m=np.full((2, 3), np.nan),
                        n_ranges=np.array([n_kf, n_kf]))
    result = build_result(status="target_reached", reason="target reached", user_ids=["ue1", "ue2"],
                          estimate=estimate, origin=ORIGIN, truth_enu_m=truth_enu if truth else None, flown_m=500.0,
                          measurements=len(r), keyframes=n_kf, duration_s=float(t[-1]) + 30.0)
    return ReportInputs(
        result=result, noise=noise,
        kf_t_s=t, kf_gps_enu_m=gps, meas_t_s=meas_t, meas_user=meas_user, meas_range_m=r,
        meas_uav_enu_m=meas_uav,
        uav_enu_m=gps + 0.3,
        hist_flown_m=h_flown if history else None,
        hist_bound_95_m=np.c_[50 / (1 + h_flown / 20), 60 / (1 + h_flown / 20)] if history else None,
        hist_error_m=np.c_[20 / (1 + h_flown / 30), 25 / (1 + h_flown / 30)] if (history and truth) else None,
        title="test mission",
    )


def test_every_png_decodes_with_the_figure_size(tmp_path):
    from PIL import Image

    paths = write_report(make_inputs(), tmp_path)
    w, h = int(FIG_SIZE_IN[0] * FIG_DPI), int(FIG_SIZE_IN[1] * FIG_DPI)
    for name in FIGURES:
        with Image.open(paths[name]) as im:
            im.load()  # decodes the whole image, not just the header
            assert im.format == "PNG"
            assert im.size == (w, h), name
            # not a blank canvas: a drawn figure has many distinct colours
            assert len(im.getcolors(maxcolors=1 << 20) or []) > 20, name


def test_report_json_has_users_noise_and_figures(tmp_path):
    inp = make_inputs()
    paths = write_report(inp, tmp_path)
    doc = json.loads(paths["report.json"].read_text())
    # the result document as it is, and the report's own sections beside it
    assert {k: v for k, v in doc.items() if k in inp.result.to_document()} == inp.result.to_document()
    assert doc["status"] == "target_reached" and doc["reason"] == "target reached"
    assert doc["measurements"] == len(inp.meas_range_m)
    assert doc["keyframes"] == len(inp.kf_t_s)
    assert doc["noise"]["range_sigma_m"] == {"range_s0_m": 2.0, "range_a_m": 0.2, "range_b_per_m": 0.01}
    assert set(doc["figures"]) == set(FIGURES)
    u1 = doc["users"][0]
    assert u1["id"] == "ue1"
    lat, lon, alt = ORIGIN.enu_to_lla(inp.users_enu_m[0])
    assert u1["lat_deg"] == pytest.approx(float(lat), abs=1e-9)
    assert u1["lon_deg"] == pytest.approx(float(lon), abs=1e-9)
    assert u1["alt_m"] == pytest.approx(float(alt), abs=1e-6)
    assert u1["error_m"] == pytest.approx(np.hypot(0.8, 0.5))
    assert u1["sigma_east_m"] == pytest.approx(1.0)
    assert u1["error_bound_95_m"] == pytest.approx(np.sqrt(CHI2_2DOF_95 * np.linalg.eigvalsh(inp.cov_en_m2[0])[-1]))
    assert u1["bias_m"] == 2.0
    stats = doc["range_statistics"]["ue1"]
    assert stats["reference"] == "true" and stats["ranges"] == 300
    assert stats["mean_m"] == pytest.approx(2.0, abs=0.5)  # the 4 m sawtooth's mean


def test_html_is_self_contained_and_embeds_the_pngs(tmp_path):
    paths = write_report(make_inputs(), tmp_path)
    page = paths["report.html"].read_text()
    assert "<img" in page and 'src="http' not in page and "src='http" not in page
    blobs = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(blobs) == len(FIGURES)
    embedded = {base64.b64decode(b) for b in blobs}
    assert embedded == {paths[name].read_bytes() for name in FIGURES}
    assert "ue1" in page and "ue2" in page


def test_report_without_truth_or_history_uses_estimates(tmp_path):
    inp = make_inputs(truth=False, history=False)
    paths = write_report(inp, tmp_path, exports=False)
    doc = json.loads(paths["report.json"].read_text())
    assert "error_m" not in doc["users"][0]
    assert doc["range_statistics"]["ue1"]["reference"] == "estimated"
    _d, _e, which = range_errors(inp)
    assert which == "estimated"
    assert "geojson" not in paths


def test_range_errors_against_truth_recover_the_injected_bias():
    inp = make_inputs(n_kf=2000)
    d, e, which = range_errors(inp)
    assert which == "true"
    # mean of the 4 m sawtooth is 2 m
    assert np.mean(e) == pytest.approx(2.0, abs=0.3)
    assert np.all(d > 25)


def test_ellipse_ring_is_the_95_percent_contour_and_counter_clockwise():
    cov = np.array([[4.0, 1.5], [1.5, 2.0]])
    ring = ellipse_en_m(np.array([10.0, -3.0, 0.0]), cov)
    assert np.array_equal(ring[0], ring[-1])
    rel = ring - [10.0, -3.0]
    m2 = np.einsum("ij,jk,ik->i", rel, np.linalg.inv(cov), rel)
    np.testing.assert_allclose(m2, CHI2_2DOF_95, rtol=1e-9)
    x, y = ring[:, 0], ring[:, 1]
    assert 0.5 * np.sum(x[:-1] * y[1:] - x[1:] * y[:-1]) > 0  # shoelace: positive = counter-clockwise


def test_bad_figure_name_is_an_error(tmp_path):
    from uavloc.errors import MissionError

    with pytest.raises(MissionError, match="unknown report figure"):
        write_report(make_inputs(n_kf=10), tmp_path, figures=("top_view", "nope"))


@pytest.mark.slow
def test_report_of_5000_keyframes_is_complete(tmp_path):
    """A long mission's report has every figure and every keyframe counted. How fast it is written
    is measured by `python benchmarks/replay_report.py` (5 000 keyframes), not asserted here."""
    inp = make_inputs(n_kf=5000)
    paths = write_report(inp, tmp_path)
    doc = json.loads(paths["report.json"].read_text())
    assert doc["keyframes"] == 5000 and doc["measurements"] == len(inp.meas_range_m)
    assert set(doc["figures"]) == set(FIGURES) and all(paths[name].stat().st_size > 0 for name in FIGURES)
