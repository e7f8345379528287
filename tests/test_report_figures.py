"""Issue 40, the report's figures: the estimated track through RTL, axes fitted to the flight (not
the fence), legends inside the figure, σ(d) written readably, the mission named in the title."""

from __future__ import annotations

from dataclasses import replace

import matplotlib
import numpy as np
import pytest

from estimator.noise import NoiseModel
from mission.report.figures import AFTER_LAST_LABEL, FIGURE_FUNCS, FIGURES, figure_title
from mission.report.inputs import MissionFacts, facts_from_header
from mission.report.statistics import estimated_track, fit_limits_m, ring_in_view, sigma_text
from tests.test_report import make_inputs
from tests.test_report_shapes import inputs_with_shapes

matplotlib.use("Agg", force=True)
import matplotlib.pyplot as plt


def test_estimated_track_goes_on_after_the_last_keyframe_shifted_by_its_correction():
    kf_t = np.array([10.0, 11.0, 12.0])
    gps = np.array([[0.0, 0, 30], [5, 0, 30], [10, 0, 30]])
    uav = gps + np.array([[0.5, 0, 0], [0.6, -0.1, 0], [1.0, -2.0, 0.5]])
    tel_t = np.array([9.0, 10.0, 11.0, 12.0, 13.0, 14.0])
    tel = np.array([[0.0, 0, 20], [0, 0, 30], [5, 0, 30], [10, 0, 30], [12, 0, 30], [14, 0, 20]])
    est = estimated_track(kf_t, gps, uav, tel_t, tel)
    np.testing.assert_allclose(est.keyframes_enu_m, uav)
    # joined to the last keyframe, then the telemetry + its correction (1, -2, 0.5)
    np.testing.assert_allclose(est.after_enu_m, [uav[-1], [13, -2, 30.5], [15, -2, 20.5]])
    np.testing.assert_allclose(est.before_enu_m, [[0.5, 0, 20], uav[0]])
    assert estimated_track(kf_t, gps, None, tel_t, tel) is None
    assert len(estimated_track(kf_t, gps, uav, None, None).after_enu_m) == 0


def test_axes_fit_the_flight_with_a_margin_and_the_fence_only_where_near():
    lo, hi = fit_limits_m(np.array([[0.0, 0.0], [100.0, 10.0], [np.nan, 1e6]]), margin_frac=0.1, min_span_m=20)
    np.testing.assert_allclose(lo, [-10.0, -7.0])
    np.testing.assert_allclose(hi, [110.0, 17.0])
    ring = np.array([[-500.0, -500], [500, -500], [500, 500], [-500, 500], [-500, -500]])
    assert not ring_in_view(ring, np.array([-100.0, -100]), np.array([100.0, 100]))
    assert ring_in_view(ring, np.array([-100.0, -100]), np.array([600.0, 100]))


def test_top_view_limits_are_the_flights_not_the_geofences():
    inp = inputs_with_shapes()  # a circle of 80 m radius inside a fence to 200 m
    fig = FIGURE_FUNCS["top_view"](plt, inp)
    try:
        ax = fig.axes[0]
        x0, x1 = ax.get_xlim()
        y0, y1 = ax.get_ylim()
        assert -110 < x0 < -80 and 80 < x1 < 110 and -110 < y0 < -80 and 80 < y1 < 110
    finally:
        plt.close(fig)


@pytest.mark.parametrize("name", FIGURES)
def test_legends_lie_inside_the_figure(name):
    inp = inputs_with_shapes()
    inp = replace(inp, tel_t_s=np.r_[inp.kf_t_s, inp.kf_t_s[-1] + np.arange(1, 40)],
                  tel_enu_m=np.r_[inp.kf_gps_enu_m, np.linspace(inp.kf_gps_enu_m[-1], [0, 0, 0], 39)])
    fig = FIGURE_FUNCS[name](plt, inp)
    try:
        fig.canvas.draw()
        w, h = fig.bbox.width, fig.bbox.height
        legends = fig.legends + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
        assert legends, name
        for leg in legends:
            b = leg.get_window_extent()
            assert b.x0 >= 0 and b.y0 >= 0 and b.x1 <= w and b.y1 <= h, (name, b, w, h)
        labels = [t.get_text() for leg in legends for t in leg.get_texts()]
        if name in ("top_view", "side_view_east", "side_view_north", "view_3d"):
            assert AFTER_LAST_LABEL in labels, labels
        assert fig.get_suptitle().startswith(inp.title)
    finally:
        plt.close(fig)


def test_view_titles_carry_each_users_error_as_the_summary_prints_it():
    inp = make_inputs()
    errs = [f"{u.id} {u.error_m:.2f} m" for u in inp.result.users]
    assert errs == ["ue1 0.94 m", "ue2 1.22 m"]
    for name in ("top_view", "side_view_east", "side_view_north", "view_3d"):
        assert all(e in figure_title(name, inp) for e in errs), figure_title(name, inp)
    no_truth = make_inputs(truth=False)
    assert "error" not in figure_title("top_view", no_truth)


def test_sigma_text_omits_a_zero_exponential_term():
    assert sigma_text(NoiseModel(range_s0_m=3.0, range_a_m=0.0, range_b_per_m=0.0)) == "σ(d) = 3.00 m"
    assert sigma_text(NoiseModel(range_s0_m=2.0, range_a_m=0.5, range_b_per_m=0.0)) == "σ(d) = 2.50 m"
    assert sigma_text(NoiseModel(range_s0_m=2.0, range_a_m=0.2, range_b_per_m=0.01)) == \
        "σ(d) = 2.00 + 0.2·exp(0.01·d) m"


def test_mission_facts_title_the_report_and_old_logs_stay_readable():
    new = facts_from_header({"command": "sim", "scenario": "three_users_nlos", "mission": "three_users_nlos",
                             "seed": 3, "planner": "casadi", "command_line": "uavloc sim three_users_nlos"},
                            "2026-01-01T00:00:00.000+00:00", "mission.jsonl", "0.1.0")
    assert new.title() == "uavloc sim three_users_nlos, seed 3, casadi"
    assert new.to_dict()["start_utc"] == "2026-01-01T00:00:00.000+00:00"
    old = facts_from_header({"generator": "sitl_scenarios.example_log", "scenario": "paper", "seed": 1}, "",
                            "example.jsonl", "0.1.0")
    assert old.title() == "paper, seed 1" and old.command_line is None and old.start_utc is None
    bad = facts_from_header({"seed": "x", "planner": 3}, None, "m.jsonl", "0.1.0")
    assert bad == MissionFacts(log_file="m.jsonl", uavloc_version="0.1.0")
    assert bad.title() == "mission log m.jsonl"
