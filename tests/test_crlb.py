"""CRLB: equals the dense Fisher information at the truth, shrinks with data, handles blind users."""

from __future__ import annotations

import numpy as np

from estimator.crlb import crlb_users
from estimator.factors import dense_normal_equations
from estimator.noise import NoiseModel
from estimator.problem import pack_keyframes
from estimator.simulate import simulate
from estimator.types import SolverParams

NOISE = NoiseModel()


def test_crlb_equals_inverse_dense_fisher_information_at_truth():
    sc = simulate(np.random.default_rng(1), n_users=3, n_keyframes=30, p_visible=0.8)
    params = SolverParams(loss="none", estimate_bias=False)
    crlb = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, params)
    # noise-free measurements at the truth: zero residuals, the normal matrix is the Fisher information
    prob = pack_keyframes(sc.keyframes, 3, sc.user_up_m, NOISE, params)
    prob.gps_enu_m[:] = sc.uav_enu_m
    d = np.linalg.norm(sc.uav_enu_m[:, None] - sc.users_enu_m[None], axis=2)
    prob.range_m[prob.mask] = d[prob.mask]
    h, _, _ = dense_normal_equations(prob, sc.uav_enu_m, sc.users_enu_m[:, :2], np.ones(3, dtype=bool))
    np.testing.assert_allclose(crlb, np.linalg.inv(h)[90:, 90:], rtol=1e-9, atol=1e-12)


def test_crlb_shrinks_with_more_keyframes_and_motion_factors():
    sc = simulate(np.random.default_rng(2), n_users=2, n_keyframes=200)
    short = crlb_users(sc.uav_enu_m[:50], sc.users_enu_m, sc.visible[:50], NOISE)
    full = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE)
    moto = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, SolverParams(motion_sigma_m=0.05))
    assert np.trace(full) < np.trace(short)
    assert np.trace(moto) < np.trace(full)
    assert np.all(np.linalg.eigvalsh(short - full) > -1e-12)


def test_crlb_with_bias_is_larger_and_blind_user_is_infinite():
    sc = simulate(np.random.default_rng(3), n_users=3, n_keyframes=100)
    vis = sc.visible.copy()
    vis[:, 2] = False
    plain = crlb_users(sc.uav_enu_m, sc.users_enu_m, vis, NOISE, SolverParams(estimate_bias=False))
    biased = crlb_users(sc.uav_enu_m, sc.users_enu_m, vis, NOISE, SolverParams(estimate_bias=True))
    assert np.trace(biased[:4, :4]) > np.trace(plain[:4, :4])
    assert np.all(np.isinf(np.diag(plain)[4:]))
    assert plain.shape == (6, 6)
