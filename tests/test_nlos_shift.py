"""The position shift of a one-sided NLoS excess (estimator.nlos_shift)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from estimator.batch import solve_batch
from estimator.nlos_shift import nlos_shift_cov, nlos_shift_m
from estimator.noise import NoiseModel
from estimator.problem import check_params, pack_keyframes
from estimator.simulate import simulate
from estimator.solve import NLOS_PROB_MIN
from estimator.types import CHI2_2DOF_95, SolverParams
from uavloc.errors import EstimatorError

#: the 99.9 % point of χ² with 2 degrees of freedom
CHI2_2DOF_999 = 13.82


@pytest.mark.parametrize(("share", "elevation_deg"), [(0.05, 0.0), (0.125, 20.0), (0.25, 35.0), (0.5, 10.0)])
def test_a_sectors_excess_moves_the_user_by_its_first_harmonic(share, elevation_deg):
    """The equation above the code, against least squares itself: views at bearings all around a
    user, each range's Jacobian (−c cos β, −c sin β, 1) on (east, north, bias), an excess μ_e on a
    sector covering `share` of them. The least-squares shift of the position is
    (2 μ_e / π) sin(π f) / c, and at most the bound 2 f μ_e / c the module reports."""
    mu_e, n = 10.0, 7200
    beta = (np.arange(n) + 0.5) * 2 * np.pi / n
    c = np.cos(np.radians(elevation_deg))
    jac = np.column_stack([-c * np.cos(beta), -c * np.sin(beta), np.ones(n)])
    excess = np.where(np.mod(beta - 1.0, 2 * np.pi) < 2 * np.pi * share, mu_e, 0.0)
    shift = np.linalg.lstsq(jac, excess, rcond=None)[0]
    expected = 2 * mu_e / np.pi * np.sin(np.pi * share) / c
    assert np.linalg.norm(shift[:2]) == pytest.approx(expected, rel=1e-3)
    assert np.linalg.norm(shift[:2]) <= 2 * share * mu_e / c
    assert shift[2] == pytest.approx(share * mu_e, rel=1e-3)  # the mean is the bias's


def test_the_covariance_of_a_shift_in_an_unknown_direction():
    """½ |δ|² per horizontal axis: the mean of δδᵀ over directions uniform on the circle."""
    ang = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
    d = 2.5 * np.column_stack([np.cos(ang), np.sin(ang)])
    np.testing.assert_allclose(nlos_shift_cov(2.5, 3)[:2, :2], d.T @ d / len(ang), atol=1e-12)
    assert np.all(nlos_shift_cov(2.5, 3)[2] == 0.0)


def _circle_users(seed: int, params: SolverParams, p_nlos: float):
    """Three users inside a circle flown around them; p_nlos > 0: a building east of every
    user (NLoS from a 90° sector of bearings, Exp(10 m) excess)."""
    rng = np.random.default_rng(seed)
    users = np.column_stack([rng.uniform(-25, 25, 3), rng.uniform(-25, 25, 3), np.zeros(3)])
    sc = simulate(rng, n_keyframes=190, noise=NoiseModel(), p_nlos=p_nlos, nlos_mean_m=10.0,
                  users_enu_m=users, nlos_sector_deg=(-45.0, 90.0))
    est = solve_batch(sc.keyframes, 3, sc.user_up_m, NoiseModel(), params)
    err = est.users_enu_m[:, :2] - sc.users_enu_m[:, :2]
    nees = np.array([e @ np.linalg.solve(est.cov_en_m2(k), e) for k, e in enumerate(err)])
    return est, nees


def test_users_behind_a_building_are_inside_their_bounds_only_with_the_shift():
    """Users seen from all around, NLoS from the east: the mixture absorbs part of the excess as a
    position shift west; with the shift in the covariance they are inside their bounds."""
    base = SolverParams(bias_held="zero")
    without, with_shift = [], []
    for seed in range(12):
        without.append(_circle_users(seed, base, 1.0)[1])
        with_shift.append(_circle_users(seed, replace(base, nlos_shift=True), 1.0)[1])
    without, with_shift = np.concatenate(without), np.concatenate(with_shift)
    assert np.mean(without <= CHI2_2DOF_95) < 0.8
    assert np.mean(with_shift <= CHI2_2DOF_95) >= 0.9
    assert np.all(with_shift <= CHI2_2DOF_999)


def test_users_without_nlos_keep_their_covariance():
    """LoS only: the EM leaves π_k at its floor and the covariance is the model's, bit for bit."""
    base = SolverParams(bias_held="zero")
    at_floor = 0
    for seed in range(4):
        est0, _ = _circle_users(seed, base, 0.0)
        est1, _ = _circle_users(seed, replace(base, nlos_shift=True), 0.0)
        floor = est1.state.nlos_prob_k <= NLOS_PROB_MIN
        at_floor += int(floor.sum())
        np.testing.assert_array_equal(est0.cov_users_m2[floor], est1.cov_users_m2[floor])
    assert at_floor >= 10


def test_shift_is_zero_without_the_mixture_loss_or_active_users():
    sc = simulate(np.random.default_rng(3), n_users=2, n_keyframes=60, p_nlos=0.3, nlos_mean_m=10.0)
    params = SolverParams(loss="huber")
    prob = pack_keyframes(sc.keyframes, 2, sc.user_up_m, NoiseModel(), params)
    assert np.all(nlos_shift_m(prob, sc.uav_enu_m, sc.users_enu_m, np.ones(2, bool)) == 0.0)
    prob = pack_keyframes(sc.keyframes, 2, sc.user_up_m, NoiseModel(), SolverParams())
    prob.nlos_prob_k = np.array([0.2, 0.2])
    out = nlos_shift_m(prob, sc.uav_enu_m, sc.users_enu_m, np.array([True, False]))
    assert out[0] > 0.0 and out[1] == 0.0


def test_nlos_shift_must_be_a_bool():
    with pytest.raises(EstimatorError, match="nlos_shift"):
        check_params(SolverParams(nlos_shift="yes"))


def test_the_result_document_gives_each_users_shift():
    """The estimate's shifts reach the per-user result entries (mission.result)."""
    from estimator.geodesy import Origin
    from mission.result import user_entries_of_estimate

    origin = Origin(43.6, 7.07, 150.0)
    est, _ = _circle_users(0, SolverParams(bias_held="zero", nlos_shift=True), 1.0)
    shift = est.state.nlos_shift_m
    assert shift is not None and np.all(shift > 0.0)
    entries = user_entries_of_estimate(est, origin, ["a", "b", "c"])
    assert [e["nlos_shift_m"] for e in entries] == pytest.approx(shift.tolist())
    from mission.result import format_users_table, users_of_estimate

    table = format_users_table(users_of_estimate(est, origin, ["a", "b", "c"]))
    assert table.count("NLoS from one side") == 3
    # no NLoS asked for: no key
    est0, _ = _circle_users(0, SolverParams(bias_held="zero"), 1.0)
    assert est0.state.nlos_shift_m is None
    assert "nlos_shift_m" not in user_entries_of_estimate(est0, origin, ["a", "b", "c"])[0]


def _estimate_with_shift(cov_en_m2: np.ndarray, shift_m: np.ndarray):
    from estimator.types import Estimate, ModelState

    k = len(shift_m)
    cov = np.asarray(cov_en_m2, float)
    return Estimate(users_enu_m=np.zeros((k, 3)), cov_users_m2=cov, info_users=np.eye(2 * k), bias_m=None,
                    uav_enu_m=np.zeros((1, 3)), ambiguous=np.zeros(k, bool), mirror_enu_m=np.full((k, 3), np.nan),
                    n_ranges=np.full(k, 50), cost=0.0, iterations=1, converged=True,
                    state=ModelState(active=np.ones(k, bool), cov_theta_joint=None, noise_scale=np.ones(k),
                                     nlos_shift_m=np.asarray(shift_m, float)))


def test_the_stop_rule_judges_the_printed_bound_shift_included():
    """A user whose bound is above the target only by its NLoS shift keeps the survey going: the
    bound the stop rule judges is the one printed, shift included."""
    from planner.stop import reported_bound_95_m, targets_reached

    shift = np.array([3.0, 0.0])
    # ue0: 0.5² m² of range uncertainty + ½·3² of shift; ue1: 1 m² and no shift
    cov = np.array([np.eye(2) * (0.25 + 4.5), np.eye(2)])
    est = _estimate_with_shift(cov, shift)
    r95 = np.sqrt(CHI2_2DOF_95)
    np.testing.assert_allclose(est.error_bound_95_m(), [r95 * np.sqrt(4.75), r95])
    np.testing.assert_array_equal(reported_bound_95_m(est), est.error_bound_95_m())
    assert not targets_reached(est, 2.5) and not targets_reached(est, 5.3)
    assert targets_reached(est, 5.4)


def test_the_campaign_counts_metres_to_the_target_as_the_stop_rule_does():
    """AccuracyTrack: the metres and seconds to T by every user's printed bound (shift included)."""
    from sitl_scenarios.campaign.outcome import AccuracyTrack, Outcome

    track = AccuracyTrack(np.zeros((2, 3)), (3.0,))
    # ue0 inside 3 m, ue1 at 5.3 m with its shift: not yet
    cov = np.array([np.eye(2) * 0.25, np.eye(2) * 4.75])
    track.update(np.zeros((2, 2)), cov, 10.0, 2.0)
    assert 3.0 not in track.metres_to
    track.update(np.zeros((2, 2)), np.array([np.eye(2) * 0.25, np.eye(2) * 1.0]), 20.0, 4.0)
    out = track.fill(Outcome())
    assert out.metres_to == {3.0: 20.0} and out.seconds_to == {3.0: 4.0}
    assert out.final_bound95_m == pytest.approx([np.sqrt(CHI2_2DOF_95 * 0.25), np.sqrt(CHI2_2DOF_95)])



@pytest.mark.parametrize("bad", [-1.0, "2", True, float("nan")])
def test_a_log_with_a_bad_nlos_shift_is_refused_naming_it(tmp_path, bad):
    import json
    from pathlib import Path

    from mission.log import read_mission_log
    from uavloc.errors import MissionLogError

    example = Path(__file__).resolve().parents[1] / "sitl_scenarios" / "data" / "example_paper.jsonl"
    header = example.read_text(encoding="utf-8").splitlines()[0]
    h = json.loads(header)
    o = h["origin"]
    user = {"id": h["users"][0]["id"], "lat_deg": o["lat_deg"], "lon_deg": o["lon_deg"], "alt_m": o["alt_m"],
            "cov_en_m2": [[1.0, 0.0], [0.0, 1.0]], "nlos_shift_m": bad}
    good = dict(user, nlos_shift_m=1.5)
    path = tmp_path / "mission.jsonl"
    path.write_text(header + "\n" + json.dumps({"type": "estimate", "t": 1.0, "users": [good]}) + "\n",
                    encoding="utf-8")
    read_mission_log(path)
    path.write_text(header + "\n" + json.dumps({"type": "estimate", "t": 1.0, "users": [user]}) + "\n",
                    encoding="utf-8")
    with pytest.raises(MissionLogError, match="nlos_shift_m"):
        read_mission_log(path)


def test_the_planners_prior_leaves_out_the_shift():
    """The planner predicts what flying can shrink: its prior information is that of the
    covariance without the shift; its samples still span the whole covariance."""
    from planner.information import PRIOR_EPS_PER_M2, hypotheses_from_estimate

    cov = np.array([np.diag([0.25 + 4.5, 1.0 + 4.5]), np.diag([2.0, 3.0])])
    hyp = hypotheses_from_estimate(_estimate_with_shift(cov, np.array([3.0, 0.0])))
    np.testing.assert_allclose(hyp.prior_info[0, 0], np.diag([4.0, 1.0]) + PRIOR_EPS_PER_M2 * np.eye(2), rtol=1e-9)
    np.testing.assert_allclose(hyp.prior_info[1, 0], np.diag([0.5, 1 / 3]) + PRIOR_EPS_PER_M2 * np.eye(2), rtol=1e-9)
    # the major-axis sigma points of user 0 lie ±sqrt(3 · 5.5) m north
    np.testing.assert_allclose(np.abs(hyp.users_enu_m[0, 1:3, 1]), np.sqrt(3 * 5.5), rtol=1e-9)
