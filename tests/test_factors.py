"""Factors: zero error at consistent values, analytic Jacobians against central differences."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.factors import BiasPriorFactor, GpsPriorFactor, MotionFactor, RangeFactor
from estimator.linearize import range_terms
from estimator.noise import NoiseModel
from estimator.numdiff import numerical_jacobian
from estimator.problem import pack_keyframes
from estimator.robust import LOSSES, loss_psi_weight, loss_rho, loss_weight, nlos_terms
from estimator.simulate import simulate
from estimator.types import SolverParams

# a distance-dependent spread so that ∂σ/∂d enters the range Jacobian
NOISE_DD = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0, range_a_m=0.5, range_b_per_m=0.01)


def test_gps_prior_zero_error_at_consistent_values():
    f = GpsPriorFactor(np.array([1.0, 2.0, 30.0]), 1.5)
    np.testing.assert_array_equal(f.error(np.array([1.0, 2.0, 30.0])), np.zeros(3))


def test_gps_prior_jacobian_matches_central_differences():
    f = GpsPriorFactor(np.array([1.0, 2.0, 30.0]), 1.5)
    x = np.array([2.0, -1.0, 33.0])
    np.testing.assert_allclose(f.jacobian(x), numerical_jacobian(f.error, x), atol=1e-8)


@pytest.mark.parametrize("user_dim", [2, 3])
@pytest.mark.parametrize("with_bias", [False, True])
def test_range_zero_error_at_consistent_values(user_dim, with_bias):
    x = np.array([10.0, -20.0, 35.0])
    u = np.array([60.0, 40.0, 1.5])
    b = 2.5 if with_bias else 0.0
    theta = np.r_[u[:user_dim], [b] if with_bias else []]
    f = RangeFactor(float(np.linalg.norm(x - u)) + b, NOISE_DD, user_dim, u[2], with_bias)
    assert abs(f.error(x, theta)) < 1e-12


@pytest.mark.parametrize("noise", [NoiseModel(), NOISE_DD], ids=["const-sigma", "sigma-of-d"])
@pytest.mark.parametrize("user_dim", [2, 3])
@pytest.mark.parametrize("with_bias", [False, True])
def test_range_jacobian_matches_central_differences(noise, user_dim, with_bias):
    rng = np.random.default_rng(7)
    for _ in range(5):
        x = rng.normal(size=3) * 40 + np.array([0, 0, 35])
        theta = np.r_[rng.normal(size=user_dim) * 60, rng.normal(size=1) * 3 if with_bias else []]
        # a residual far from zero, so the r·σ'(d) term of α matters
        f = RangeFactor(100.0 + rng.uniform(0, 40), noise, user_dim, 1.0, with_bias)
        jx, jt = f.jacobian(x, theta)
        num_x = numerical_jacobian(lambda v, f=f, t=theta: f.error(v, t), x)[0]
        num_t = numerical_jacobian(lambda v, f=f, xx=x: f.error(xx, v), theta)[0]
        np.testing.assert_allclose(jx, num_x, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(jt, num_t, rtol=1e-6, atol=1e-9)


def test_bias_prior_jacobian_matches_central_differences():
    f = BiasPriorFactor(10.0)
    assert f.error(0.0) == 0.0
    num = numerical_jacobian(lambda v: f.error(v[0]), np.array([3.0]))[0, 0]
    np.testing.assert_allclose(f.jacobian(3.0), num, rtol=1e-8)


def test_motion_zero_error_and_jacobian_matches_central_differences():
    f = MotionFactor(np.array([2.0, 0.5, -0.1]), 0.1)
    x0 = np.array([1.0, 1.0, 30.0])
    np.testing.assert_allclose(f.error(x0, x0 + f.odom_enu_m), np.zeros(3), atol=1e-12)
    x1 = x0 + np.array([2.3, 0.2, 0.4])
    j0, j1 = f.jacobian(x0, x1)
    np.testing.assert_allclose(j0, numerical_jacobian(lambda v: f.error(v, x1), x0), atol=1e-7)
    np.testing.assert_allclose(j1, numerical_jacobian(lambda v: f.error(x0, v), x1), atol=1e-7)


@pytest.mark.parametrize("estimate_bias", [False, True])
@pytest.mark.parametrize("user_dim", [2, 3])
def test_vectorised_range_jacobian_matches_central_differences(estimate_bias, user_dim):
    """The solver's batched (K, N) residuals and Jacobians, not only the factor objects."""
    sc = simulate(np.random.default_rng(3), n_users=3, n_keyframes=12, p_visible=0.7)
    params = SolverParams(user_dim=user_dim, estimate_bias=estimate_bias)
    prob = pack_keyframes(sc.keyframes, 3, sc.user_up_m, NOISE_DD, params)
    rng = np.random.default_rng(4)
    x = sc.uav_enu_m + rng.normal(size=sc.uav_enu_m.shape)
    theta = np.zeros((3, prob.p))
    theta[:, :user_dim] = sc.users_enu_m[:, :user_dim] + rng.normal(size=(3, user_dim)) * 5
    if estimate_bias:
        theta[:, -1] = rng.normal(size=3)
    mask = prob.mask.T.copy()
    e, _w, _rho, jac, _psi, _w_em = range_terms(prob, x, theta, mask)
    for k in range(3):
        for n in np.flatnonzero(mask[k])[:4]:
            def e_of_x(v, n=n, k=k):
                xx = x.copy()
                xx[n] = v
                return range_terms(prob, xx, theta, mask)[0][k, n]

            def e_of_t(v, k=k, n=n):
                tt = theta.copy()
                tt[k] = v
                return range_terms(prob, x, tt, mask)[0][k, n]

            np.testing.assert_allclose(jac[:3, k, n], numerical_jacobian(e_of_x, x[n])[0], rtol=1e-6, atol=1e-9)
            np.testing.assert_allclose(jac[3:, k, n], numerical_jacobian(e_of_t, theta[k])[0], rtol=1e-6, atol=1e-9)
    assert np.all(e[~mask] == 0) and np.all(jac[:, ~mask] == 0)


@pytest.mark.parametrize("loss", LOSSES)
def test_irls_weight_is_rho_derivative_over_residual(loss):
    e = np.array([-7.0, -2.0, -0.4, 0.3, 1.2, 2.9, 5.0])
    drho = np.array([numerical_jacobian(lambda v: loss_rho(v, loss, 2.5)[0], np.array([ei]))[0, 0] for ei in e])
    rho, psi, w = loss_psi_weight(e, loss, 2.5)
    np.testing.assert_allclose(psi, drho, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(rho, loss_rho(e, loss, 2.5), rtol=1e-14)
    np.testing.assert_allclose(w, loss_weight(e, loss, 2.5), rtol=1e-14)
    assert np.all((w >= 0) & (w <= 1))
    if loss != "nlos":
        np.testing.assert_allclose(w * e, drho, rtol=1e-6, atol=1e-8)
    assert loss_rho(np.array([0.0]), loss, 2.5)[0] == 0.0


@pytest.mark.parametrize("prob, mean_w", [(0.1, 20.0 / 3.0), (0.3, 2.0), (0.02, np.array([1.5, 4.0, 30.0]))])
def test_nlos_loss_is_negative_log_of_the_mixture_density(prob, mean_w):
    """ρ(e) − ρ(0) = −log p(e)/p(0) with p = (1 − π) φ + π (φ ⊛ Exp(m)) by quadrature; ψ = ρ' by
    central differences (also far out, where M(t) is extrapolated); γ = (1 − π) φ / p."""
    from scipy.integrate import quad
    from scipy.stats import norm

    m = np.broadcast_to(mean_w, (3,))
    for e in (-6.0, -1.0, 0.7, 2.5, 4.5, 9.0):
        e3 = np.full(3, e)
        rho, psi, gam = nlos_terms(e3, prob, mean_w)
        for j in range(3):
            def dens(v, mj=m[j]):
                nl = quad(lambda s: norm.pdf(v - s) * np.exp(-s / mj) / mj, 0, np.inf, epsabs=1e-14)[0]
                return (1 - prob) * norm.pdf(v) + prob * nl
            assert rho[j] == pytest.approx(-np.log(dens(e) / dens(0.0)), rel=1e-6, abs=1e-9)
            assert gam[j] == pytest.approx((1 - prob) * norm.pdf(e) / dens(e), rel=1e-6, abs=1e-12)
        fd = (nlos_terms(e3 + 1e-6, prob, mean_w)[0] - nlos_terms(e3 - 1e-6, prob, mean_w)[0]) / 2e-6
        np.testing.assert_allclose(psi, fd, rtol=1e-6, atol=1e-7)
