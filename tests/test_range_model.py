"""One source of the range model: estimator.factors.range_residuals / range_alpha / range_jacobian
against the one-at-a-time RangeFactor and central differences, and its callers (initialization's
user cost, the planner's predicted information) against slow references built on RangeFactor."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from estimator.factors import RangeFactor, range_alpha, range_jacobian, range_residuals
from estimator.init import user_cost
from estimator.noise import NoiseModel
from estimator.numdiff import numerical_jacobian
from estimator.robust import loss_rho
from estimator.types import SolverParams
from planner.information import Hypotheses, PredictionModel, predicted_information, quadrature_points

NOISE_DD = NoiseModel(sigma_gps_m=1.5, range_s0_m=3.0, range_a_m=0.5, range_b_per_m=0.01)


def _vectorised(x, theta, r_meas, noise, user_dim, with_bias, gain, scale, gps_var):
    """e and [∂e/∂x; ∂e/∂θ] of one range through the vectorised functions (shape (1,) arrays)."""
    u = np.array([theta[0], theta[1], theta[2] if user_dim == 3 else 1.0])
    diff = (x - u)[:, None]
    b = theta[-1] * gain if with_bias else 0.0
    d, sig, _r, e = range_residuals(diff, np.array([r_meas]), b, noise, scale, gps_var)
    alpha = range_alpha(sig)
    jac = range_jacobian(diff, d, alpha, sig, user_dim, with_bias, np.array([gain]) if with_bias else None)
    return float(e[0]), jac[:, 0]


@pytest.mark.parametrize("noise", [NoiseModel(), NOISE_DD], ids=["const-sigma", "sigma-of-d"])
@pytest.mark.parametrize("user_dim,with_bias", [(2, False), (2, True), (3, True)])
@pytest.mark.parametrize("gps_var", [0.0, 2.25], ids=["solver", "uav-at-fix"])
def test_vectorised_range_model_matches_the_factor_and_central_differences(noise, user_dim, with_bias, gps_var):
    rng = np.random.default_rng(2)
    for _ in range(5):
        x = rng.normal(size=3) * 40 + np.array([0, 0, 35])
        theta = np.r_[rng.normal(size=user_dim) * 60, rng.normal(size=1) * 3 if with_bias else []]
        r_meas, gain = 100.0 + rng.uniform(0, 40), rng.uniform(0.2, 1.0)
        scale = rng.uniform(1.0, 2.0)
        e, jac = _vectorised(x, theta, r_meas, noise, user_dim, with_bias, gain, np.array([scale]), gps_var)
        if gps_var == 0.0:
            # the same factor one at a time (σ_k = s σ: s0 and a scaled)
            scaled = replace(noise, range_s0_m=noise.range_s0_m * scale, range_a_m=noise.range_a_m * scale)
            f = RangeFactor(r_meas, scaled, user_dim, 1.0, with_bias, gain)
            assert e == pytest.approx(f.error(x, theta), rel=1e-13)
            jx, jt = f.jacobian(x, theta)
            np.testing.assert_allclose(jac, np.r_[jx, jt], rtol=1e-12, atol=1e-15)

        def err_x(v, theta=theta, r_meas=r_meas, gain=gain, scale=scale):
            return _vectorised(v, theta, r_meas, noise, user_dim, with_bias, gain, np.array([scale]), gps_var)[0]

        def err_t(v, x=x, r_meas=r_meas, gain=gain, scale=scale):
            return _vectorised(x, v, r_meas, noise, user_dim, with_bias, gain, np.array([scale]), gps_var)[0]

        np.testing.assert_allclose(jac[:3], numerical_jacobian(err_x, x)[0], rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(jac[3:], numerical_jacobian(err_t, theta)[0], rtol=1e-6, atol=1e-9)


def test_masked_ranges_have_zero_error_and_jacobian():
    rng = np.random.default_rng(3)
    diff = rng.normal(size=(3, 4, 6)) * 50
    r_meas = np.linalg.norm(diff, axis=0) + 2.0
    mask = rng.random((4, 6)) < 0.6
    d, sig, _r, e = range_residuals(diff, np.where(mask, r_meas, np.nan), 0.5, NOISE_DD, mask=mask)
    alpha = range_alpha(sig, mask)
    jac = range_jacobian(diff, d, alpha, sig, 2, True, mask=mask)
    assert np.all(e[~mask] == 0) and np.all(jac[:, ~mask] == 0)
    assert np.all(np.isfinite(e)) and np.all(e[mask] != 0)


@pytest.mark.parametrize("params", [SolverParams(), SolverParams(loss="huber", estimate_bias=True)],
                         ids=["nlos", "huber-bias"])
def test_user_cost_is_the_range_factor_with_the_gps_folded_in(params):
    rng = np.random.default_rng(4)
    noise = NoiseModel(sigma_gps_m=1.5, range_s0_m=3.0)
    uav = rng.normal(size=(30, 3)) * 50 + np.array([0, 0, 35])
    theta = np.r_[20.0, -10.0, [1.5] if params.estimate_bias else []]
    rng_m = np.linalg.norm(uav - np.array([20.0, -10.0, 0.0]), axis=1) + rng.normal(size=30) * 3
    # σ_eff = √(s0² + σ_gps²): RangeFactor with that s0, one range at a time
    eff = NoiseModel(sigma_gps_m=1.5, range_s0_m=float(np.hypot(3.0, 1.5)))
    f_e = [RangeFactor(float(r), eff, 2, 0.0, params.estimate_bias).error(x, theta)
           for x, r in zip(uav, rng_m, strict=True)]
    sig = eff.range_s0_m
    ref = float(np.sum(loss_rho(np.array(f_e), params.loss, params.loss_scale,
                                (params.nlos_prob, params.nlos_mean_m / sig))))
    if params.estimate_bias:
        ref += 0.5 * (1.5 / params.bias_prior_sigma_m) ** 2
    assert user_cost(uav, rng_m, theta, 0.0, noise, params) == pytest.approx(ref, rel=1e-12)


@pytest.mark.parametrize("bias", [False, True])
@pytest.mark.parametrize("noise", [NoiseModel(), NOISE_DD], ids=["const-sigma", "sigma-of-d"])
def test_planner_information_is_the_sum_of_range_factor_jacobians(bias, noise):
    """I = P + Σ_q n_q J_θ J_θᵀ with J_θ the range factor's Jacobian at a noise-free range, the UAV
    at its fix (σ_eff), computed one quadrature point at a time."""
    rng = np.random.default_rng(5)
    k_n, m_n, p = 2, 3, 2 + bias
    users = np.c_[rng.uniform(-80, 80, (k_n, m_n, 2)), np.zeros((k_n, m_n, 1))]
    scale = np.array([1.0, 1.7])
    hyp = Hypotheses(users_enu_m=users, sample_w=np.full((k_n, m_n), 1 / m_n),
                     prior_info=np.tile(np.eye(p) * 0.1, (k_n, m_n, 1, 1)), user_w=np.ones(k_n),
                     index=np.arange(k_n), bias=bias, noise_scale=scale)
    start = np.array([0.0, 0.0, 30.0])
    way = np.array([[[40.0, 10.0, 30.0], [60.0, 60.0, 45.0]], [[-30.0, 20.0, 25.0], [-50.0, -40.0, 30.0]]])
    info, lengths = predicted_information(start, way, hyp, PredictionModel(noise, 2.0, 4))
    pts, _ = quadrature_points(start, way, 4)
    for c in range(2):
        for k in range(k_n):
            # σ_eff(d)² = (s σ(d))² + σ_gps²: a factor at σ(d) scaled by σ_eff/σ(d) at the same point
            for m in range(m_n):
                ref = hyp.prior_info[k, m].copy()
                for q in range(pts.shape[1]):
                    x = pts[c, q]
                    d = float(np.linalg.norm(x - users[k, m]))
                    sig = scale[k] * float(noise.range_sigma_m(d))
                    eff = float(np.sqrt(sig**2 + noise.sigma_gps_m**2))
                    f = RangeFactor(d, NoiseModel(range_s0_m=eff), 2, 0.0, bias)
                    _, jt = f.jacobian(x, np.r_[users[k, m, :2], [0.0] if bias else []])
                    ref += lengths[c, q // 4] / (2.0 * 4) * np.outer(jt, jt)
                np.testing.assert_allclose(info[c, k, m], ref, rtol=1e-11)
