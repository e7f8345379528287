"""UE clock sawtooth: the bound of the tracked model (amplitude unknown, shape known) against the
dense Fisher information, and how it compares with the bias-free and the constant-bias bounds."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.crlb import crlb_users
from estimator.factors import dense_normal_equations
from estimator.noise import NoiseModel
from estimator.problem import pack_keyframes
from estimator.simulate import simulate
from estimator.types import SolverParams
from uavloc.errors import EstimatorError

NOISE = NoiseModel(sigma_gps_m=1.0, s0_m=3.0)
BIAS = SolverParams(loss="none", estimate_bias=True, bias_select=False)


def _scene(seed: int = 3, n: int = 60):
    sc = simulate(np.random.default_rng(seed), n_users=3, n_keyframes=n, dt_s=0.4, p_visible=0.9)
    t = np.array([kf.t_s for kf in sc.keyframes])
    phase = np.array([0.1, 0.45, 0.8])
    # saw shape g_nk = frac(t/P + φ_k)
    gain = np.mod(t[:, None] / 15.0 + phase[None, :], 1.0)
    return sc, t, gain


@pytest.mark.parametrize("noise", [NOISE, NoiseModel(sigma_gps_m=1.0, s0_m=3.0, gps_tau_s=60.0)])
def test_crlb_with_a_clock_gain_is_the_inverse_dense_fisher_information(noise):
    sc, t, gain = _scene()
    crlb = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, noise, BIAS, t, bias_gain=gain)
    # noise-free ranges at the truth: the dense normal matrix is the Fisher information
    prob = pack_keyframes(sc.keyframes, 3, sc.user_up_m, noise, BIAS)
    prob.gps_enu_m[:] = sc.uav_enu_m
    d = np.linalg.norm(sc.uav_enu_m[:, None] - sc.users_enu_m[None], axis=2)
    prob.range_m[prob.mask] = d[prob.mask]
    prob.bias_gain = gain
    theta = np.column_stack([sc.users_enu_m[:, :2], np.zeros(3)])
    h, _, _ = dense_normal_equations(prob, sc.uav_enu_m, theta, np.ones(3, dtype=bool))
    n = sc.uav_enu_m.shape[0]
    cov = np.linalg.inv(h)[3 * n :, 3 * n :].reshape(3, 3, 3, 3)[:, :2, :, :2].reshape(6, 6)
    np.testing.assert_allclose(crlb, cov, rtol=1e-9, atol=1e-12)


def test_sawtooth_bound_above_the_bias_free_bound_below_a_constant_bias():
    sc, t, gain = _scene(n=300)
    free = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, SolverParams(estimate_bias=False), t)
    saw = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, BIAS, t, bias_gain=gain)
    const = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, BIAS, t)
    ones = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, BIAS, t, bias_gain=np.ones_like(gain))
    np.testing.assert_allclose(ones, const, rtol=1e-12)
    # one unknown more can only cost information (Loewner order); the sawtooth's ramps and
    # resets tell its amplitude from the position better than a constant bias can be told
    assert np.all(np.linalg.eigvalsh(saw - free) > -1e-12)
    assert np.trace(free) < np.trace(saw) < np.trace(const)


def test_crlb_clock_gain_checked():
    sc, t, gain = _scene()
    with pytest.raises(EstimatorError, match="estimate_bias"):
        crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, SolverParams(estimate_bias=False), t,
                   bias_gain=gain)
    with pytest.raises(EstimatorError, match="bias_gain"):
        crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, BIAS, t, bias_gain=gain[:-1])
    bad = gain.copy()
    bad[0, 0] = np.nan
    with pytest.raises(EstimatorError, match="bias_gain"):
        crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, BIAS, t, bias_gain=bad)
