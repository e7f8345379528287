"""Honest estimates: Gauss–Markov GPS factors, per-user range bias and noise scale.

Jacobians against central differences, the vectorised GPS chain against the factor objects, the
Schur solve and covariance against the dense normal equations to 1e-9, online equal to batch
when nothing is marginalized, and the covariance honest (NEES) on drifting GPS and noisy UEs.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from estimator.batch import solve_batch
from estimator.clock import undetected_sawtooth_bias
from estimator.crlb import crlb_users
from estimator.factors import dense_normal_equations
from estimator.gps import GpsFactor, gps_chain_terms, gps_phi
from estimator.linearize import linearize
from estimator.noise import NoiseModel
from estimator.numdiff import numerical_jacobian
from estimator.online import OnlineEstimator
from estimator.online_marginal import marginalize_chain, marginalize_oldest
from estimator.problem import pack_keyframes
from estimator.schur import schur_solve
from estimator.simulate import gps_error_m, simulate
from estimator.types import SolverParams
from uavloc.errors import EstimatorError

GM = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0, gps_tau_s=60.0)
GM_DD = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0, range_a_m=0.5, range_b_per_m=0.01, gps_tau_s=30.0)
#: fixed model (no bias selection, no noise-scale rounds): the solve is one smooth problem
FIXED = SolverParams(estimate_bias=True, bias_select=False, estimate_noise_scale=False, track_clock=False)


def test_gps_factor_zero_error_at_consistent_values_and_white_limit():
    f = GpsFactor(np.array([1.0, 2.0, 30.0]), 1.5, 0.8, np.array([0.0, 1.0, 29.0]))
    np.testing.assert_allclose(f.error(np.array([1.0, 2.0, 30.0]), np.array([0.0, 1.0, 29.0])), 0.0)
    white = GpsFactor(np.array([1.0, 2.0, 30.0]), 1.5)
    np.testing.assert_allclose(white.error(np.array([2.5, 2.0, 30.0])), [1.0, 0.0, 0.0])


def test_gps_factor_jacobian_matches_central_differences():
    f = GpsFactor(np.array([1.0, 2.0, 30.0]), 1.5, 0.7, np.array([0.5, 1.0, 29.0]))
    x, xp = np.array([2.0, -1.0, 33.0]), np.array([0.0, 0.5, 31.0])
    jx, jp = f.jacobian()
    np.testing.assert_allclose(jx, numerical_jacobian(lambda v: f.error(v, xp), x), atol=1e-8)
    np.testing.assert_allclose(jp, numerical_jacobian(lambda v: f.error(x, v), xp), atol=1e-8)


@pytest.mark.parametrize("first", [True, False])
def test_gps_chain_terms_equal_the_sum_of_factor_objects(first):
    rng = np.random.default_rng(3)
    n = 7
    x, gps = rng.normal(size=(n, 3)) * 3, rng.normal(size=(n, 3)) * 3
    t = np.cumsum(rng.uniform(0.2, 2.0, n))
    phi = gps_phi(t, 5.0)
    terms = gps_chain_terms(x, gps, phi, 1.3, first)
    h = np.zeros((3 * n, 3 * n))
    g = np.zeros(3 * n)
    cost = 0.0
    for i in range(n):
        if i == 0 and not first:
            continue
        f = GpsFactor(gps[i], 1.3, float(phi[i]), gps[i - 1] if i else None)
        e = f.error(x[i], x[i - 1] if i else None)
        jx, jp = f.jacobian()
        j = np.zeros((3, 3 * n))
        j[:, 3 * i : 3 * i + 3] = jx
        if i:
            j[:, 3 * i - 3 : 3 * i] += jp
        h += j.T @ j
        g += j.T @ e
        cost += 0.5 * e @ e
    assert terms.cost == pytest.approx(cost, rel=1e-12)
    np.testing.assert_allclose(terms.grad.ravel(), g, rtol=1e-12, atol=1e-12)
    for i in range(n):
        np.testing.assert_allclose(h[3 * i : 3 * i + 3, 3 * i : 3 * i + 3], terms.diag[i] * np.eye(3), rtol=1e-12)
        if i < n - 1:
            np.testing.assert_allclose(h[3 * i : 3 * i + 3, 3 * i + 3 : 3 * i + 6], terms.off[i] * np.eye(3),
                                       rtol=1e-12, atol=1e-15)


def test_gps_phi_white_and_links():
    t = np.array([0.0, 1.0, 3.0, 3.0])
    np.testing.assert_array_equal(gps_phi(t, 0.0), 0.0)
    phi = gps_phi(t, 10.0)
    assert phi[0] == 0.0
    np.testing.assert_allclose(phi[1:3], np.exp(-np.array([1.0, 2.0]) / 10.0))
    assert phi[3] < 1.0  # two fixes at the same time: floored q, finite weight


@pytest.mark.parametrize("noise, scale, gain, held", [
    (GM, None, False, False), (GM_DD, np.array([1.0, 1.7, 2.5]), False, False),
    (GM, np.array([1.2, 1.0, 1.0]), True, False), (GM, None, False, True)],
    ids=["gm", "gm-dd-scale", "gm-clock-gain", "gm-held-sawtooth"])
def test_gm_bias_scale_solve_and_covariance_match_dense_reference(noise, scale, gain, held):
    """At one linearization point: the Schur step and S⁻¹ against np.linalg on the dense normal
    equations built from the factor objects (GPS chain, ranges with bias and noise scale, bias
    prior; `held`: user 0's bias held under bias_held "sawtooth"'s prior, mean 1.09 m)."""
    sc = simulate(np.random.default_rng(7), n_users=3, n_keyframes=30, noise=noise, gps_tau_s=noise.gps_tau_s,
                  bias_m=np.array([0.0, 4.0, 2.0]), p_visible=0.8)
    params = replace(FIXED, loss="huber")
    prob = pack_keyframes(sc.keyframes, 3, sc.user_up_m, noise, params)
    prob.noise_scale_k = scale
    prob.bias_sigma_k = np.array([1e-3, 10.0, 10.0])
    if held:
        mean, sd = undetected_sawtooth_bias(3.0)
        prob.bias_sigma_k[0] = sd
        prob.bias_mean_k = np.array([mean, 0.0, 0.0])
    rng = np.random.default_rng(8)
    if gain:
        # user 1's bias is a clock sawtooth's amplitude: r̂ = d + b g, g = frac(t/P − φ)
        prob.bias_gain = np.ones((30, 3))
        prob.bias_gain[:, 1] = np.mod(prob.t_s / 7.0 + 0.2, 1.0)
    x = sc.uav_enu_m + rng.normal(size=sc.uav_enu_m.shape) * 0.5
    theta = np.column_stack([sc.users_enu_m[:, :2] + rng.normal(size=(3, 2)), [0.1, 3.0, 1.0]])
    active = np.ones(3, dtype=bool)
    lin = linearize(prob, x, theta, active)
    assert lin.off is not None  # the Gauss–Markov links make the keyframe block tridiagonal
    dx, du, s = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu)
    h, g, cost = dense_normal_equations(prob, x, theta, active)
    dz = np.linalg.solve(h, g)
    assert lin.cost == pytest.approx(cost, rel=1e-12)
    np.testing.assert_allclose(dx.ravel(), dz[: 3 * 30], rtol=1e-9, atol=1e-9 * np.abs(dz).max())
    np.testing.assert_allclose(du, dz[3 * 30 :], rtol=1e-9, atol=1e-9 * np.abs(dz).max())
    cov_ref = np.linalg.inv(h)[3 * 30 :, 3 * 30 :]
    np.testing.assert_allclose(np.linalg.inv(s), cov_ref, rtol=1e-9, atol=1e-9 * np.abs(cov_ref).max())


def test_batch_covariance_is_the_dense_inverse_at_its_linearization_point():
    sc = simulate(np.random.default_rng(9), n_users=3, n_keyframes=40, noise=GM, gps_tau_s=60.0,
                  bias_m=np.array([6.0, 0.0, 0.0]))
    params = replace(FIXED, step_tol_m=1e-11, step_tol_uav_m=1e-11, step_tol_sigma=0.0)
    est = solve_batch(sc.keyframes, 3, sc.user_up_m, GM, params)
    prob = pack_keyframes(sc.keyframes, 3, sc.user_up_m, GM, params)
    prob.nlos_prob_k = est.state.nlos_prob_k
    theta = np.column_stack([est.users_enu_m[:, :2], est.bias_m])
    h, g, _ = dense_normal_equations(prob, est.uav_enu_m, theta, np.ones(3, dtype=bool))
    assert np.abs(g).max() < 1e-6  # a stationary point
    cov_ref = np.linalg.inv(h)[3 * 40 :, 3 * 40 :].reshape(3, 3, 3, 3)
    for k in range(3):
        np.testing.assert_allclose(est.cov_users_m2[k], cov_ref[k, :2, k, :2], rtol=1e-9)


@pytest.mark.parametrize("noise", [GM, NoiseModel(gps_tau_s=None)], ids=["gm", "tau-unknown"])
def test_online_equals_batch_with_gauss_markov_gps_when_nothing_is_marginalized(noise):
    sc = simulate(np.random.default_rng(21), n_users=3, n_keyframes=60, noise=noise, gps_tau_s=60.0,
                  bias_m=np.array([5.0, 0.0, 0.0]), p_visible=0.9)
    tight = replace(FIXED, window=1000, step_tol_m=1e-10, step_tol_uav_m=1e-10, step_tol_sigma=0.0,
                    online_step_tol_m=1e-10, online_resolve_every=1)
    batch = solve_batch(sc.keyframes, 3, sc.user_up_m, noise, tight)
    on = OnlineEstimator(3, sc.user_up_m, noise, tight)
    for kf in sc.keyframes:
        est = on.add_keyframe(kf)
    np.testing.assert_allclose(est.users_enu_m, batch.users_enu_m, atol=1e-6)
    np.testing.assert_allclose(est.uav_enu_m, batch.uav_enu_m, atol=1e-6)
    np.testing.assert_allclose(est.bias_m, batch.bias_m, atol=1e-6)
    np.testing.assert_allclose(est.cov_users_m2, batch.cov_users_m2, rtol=1e-5)


def test_online_marginalization_with_gauss_markov_links_stays_close_to_batch():
    """The link from the oldest keyframe to the next is folded into the prior, not lost: with a
    window of 50 the online estimate stays near the batch one and keeps its (larger) covariance."""
    sc = simulate(np.random.default_rng(22), n_users=3, n_keyframes=200, noise=GM, gps_tau_s=60.0)
    params = SolverParams(window=50, estimate_bias=False, estimate_noise_scale=False)
    batch = solve_batch(sc.keyframes, 3, sc.user_up_m, GM, params)
    on = OnlineEstimator(3, sc.user_up_m, GM, params)
    for kf in sc.keyframes:
        est = on.add_keyframe(kf)
        assert est.uav_enu_m.shape[0] <= params.window + params.online_resolve_every
    sigma = np.sqrt(np.trace(batch.cov_users_m2, axis1=1, axis2=2))
    assert np.all(np.linalg.norm(est.users_enu_m - batch.users_enu_m, axis=1) < 0.2 * sigma)
    np.testing.assert_allclose(est.cov_users_m2, batch.cov_users_m2, rtol=0.1)
    white = solve_batch(sc.keyframes, 3, sc.user_up_m, replace(GM, gps_tau_s=0.0), params)
    assert np.all(np.trace(batch.cov_users_m2, axis1=1, axis2=2) > 1.5 * np.trace(white.cov_users_m2, axis1=1, axis2=2))


def _nees(est, sc) -> np.ndarray:
    d = est.users_enu_m[:, :2] - sc.users_enu_m[:, :2]
    return np.einsum("ki,kij,kj->k", d, np.linalg.inv(est.cov_users_m2), d)


def test_covariance_honest_on_drifting_gps_and_a_noisier_ue():
    """Gauss–Markov GPS (τ 120 s) and one UE twice as noisy as assumed: mean NEES near 2 with the
    model, far above it with the white model and no noise scale."""
    nees, nees_white, scale = [], [], []
    for seed in range(6):
        sc = simulate(np.random.default_rng(300 + seed), n_users=3, n_keyframes=150, gps_tau_s=120.0, dt_s=0.4,
                      noise_scale=np.array([1.0, 1.0, 2.0]))
        est = solve_batch(sc.keyframes, 3, sc.user_up_m, NoiseModel(gps_tau_s=120.0))
        nees.extend(_nees(est, sc))
        scale.append(est.state.noise_scale[2])
        plain = SolverParams(estimate_bias=False, estimate_noise_scale=False)
        nees_white.extend(_nees(solve_batch(sc.keyframes, 3, sc.user_up_m, NoiseModel(), plain), sc))
    assert 1.2 < np.mean(nees) < 3.5, np.mean(nees)
    assert np.mean(nees_white) > 6.0, np.mean(nees_white)
    assert 1.6 < np.mean(scale) < 2.4, scale


def test_crlb_with_gauss_markov_gps_is_larger_and_needs_times():
    sc = simulate(np.random.default_rng(2), n_users=2, n_keyframes=100)
    t = np.arange(100) * 0.5
    white = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NoiseModel(), SolverParams(estimate_bias=False), t)
    gm = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, GM, SolverParams(estimate_bias=False), t)
    assert np.trace(gm) > 2.0 * np.trace(white)
    with pytest.raises(EstimatorError, match="t_s"):
        crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, GM, SolverParams(), t[:5])


def test_gps_error_model_statistics():
    err = gps_error_m(np.random.default_rng(1), 20000, 2.0, 50.0, 1.0)
    assert np.std(err) == pytest.approx(2.0, rel=0.1)
    lag1 = np.mean(err[1:] * err[:-1]) / np.mean(err * err)
    assert lag1 == pytest.approx(np.exp(-1.0 / 50.0), abs=0.02)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), True, "60"])
def test_bad_gps_tau_rejected(bad):
    with pytest.raises(EstimatorError, match="gps_tau_s"):
        NoiseModel(gps_tau_s=bad)


def test_noise_log_dict_round_trip_and_unknown_tau():
    n = NoiseModel(sigma_gps_m=0.8, gps_tau_s=120.0)
    assert NoiseModel.from_log_dict(n.to_log_dict()) == n
    unknown = NoiseModel.from_log_dict({"sigma_gps_m": 1.0})
    assert unknown.gps_tau_s is None and unknown.gps_tau_used_s > 0
    with pytest.raises(EstimatorError, match="gps_tau_s"):
        NoiseModel.from_log_dict({"gps_tau_s": "slow"})


# --- UE clock sawtooth ----------------------------------------------------------------------------


def test_fit_sawtooth_recovers_period_phase_and_drift():
    from estimator.clock import SawtoothFit, fit_sawtooth

    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(3.0, 163.0, 400))
    truth = SawtoothFit(15.0, 0.3, 12.0, 0.0, 1.0)
    fit = fit_sawtooth(t, truth.value_m(t) + 2.0 + rng.normal(scale=3.0, size=t.size))
    assert fit is not None
    assert fit.period_s == pytest.approx(15.0, rel=0.01)
    assert fit.amplitude_m == pytest.approx(12.0, abs=1.5)
    # the fitted sawtooth follows the true one (phase included) up to the noise
    assert np.sqrt(np.mean((fit.value_m(t) + fit.offset_m - truth.value_m(t) - 2.0) ** 2)) < 1.0


@pytest.mark.parametrize("seed", range(5))
def test_fit_sawtooth_rejects_white_noise(seed):
    from estimator.clock import fit_sawtooth

    rng = np.random.default_rng(seed)
    t = np.arange(400) * 0.4
    assert fit_sawtooth(t, rng.normal(scale=3.0, size=t.size)) is None


def test_batch_tracks_a_clock_sawtooth_and_stays_honest():
    """Three UEs, one with a 12 m / 15 s sawtooth: the solver finds it, and that user ends near
    the truth inside its bound; no sawtooth is invented for the others."""
    sc = simulate(np.random.default_rng(61), n_users=3, n_keyframes=400, dt_s=0.4)
    t = np.array([kf.t_s for kf in sc.keyframes])
    saw = 12.0 * np.mod(t / 15.0 + 0.37, 1.0)
    kfs = [replace(kf, range_m=kf.range_m + np.where(kf.user_idx == 1, saw[i], 0.0))
           for i, kf in enumerate(sc.keyframes)]
    est = solve_batch(kfs, 3, sc.user_up_m, NoiseModel())
    clock = est.state.clock
    assert clock[0] is None and clock[2] is None
    assert clock[1] is not None and clock[1].period_s == pytest.approx(15.0, rel=0.01)
    nees = _nees(est, sc)
    assert np.all(nees < 9.0), nees
    assert np.linalg.norm(est.users_enu_m[1, :2] - sc.users_enu_m[1, :2]) < 1.5
    plain = solve_batch(kfs, 3, sc.user_up_m, NoiseModel(), SolverParams(track_clock=False, estimate_bias=False))
    assert np.linalg.norm(plain.users_enu_m[1, :2] - sc.users_enu_m[1, :2]) > 3.0


def test_range_factor_with_a_clock_gain_jacobian_matches_central_differences():
    from estimator.factors import RangeFactor

    f = RangeFactor(95.0, GM_DD, 2, 1.5, True, bias_gain=0.37)
    x, theta = np.array([10.0, -20.0, 35.0]), np.array([60.0, 40.0, 8.0])
    jx, jt = f.jacobian(x, theta)
    np.testing.assert_allclose(jx, numerical_jacobian(lambda v: f.error(v, theta), x)[0], atol=1e-8)
    np.testing.assert_allclose(jt, numerical_jacobian(lambda v: f.error(x, v), theta)[0], atol=1e-8)


def _mixture_nll(e: float, pi: float, m: float) -> float:
    """−log of the LoS/NLoS mixture density of a whitened residual, written out with scipy.stats
    (independent of estimator.robust): (1 − π) φ(e) + π (1/m) exp(1/(2m²) − e/m) Φ(e − 1/m)."""
    from scipy.stats import norm

    f = math.exp(1.0 / (2 * m * m) - e / m) * norm.cdf(e - 1.0 / m) / m
    return -math.log((1.0 - pi) * norm.pdf(e) + pi * f)


def test_nlos_covariance_is_the_observed_information_with_pi_estimated_dense_reference():
    """Under NLoS the users' S is the observed information of the mixture likelihood with every
    user's NLoS probability π_k estimated too: against the dense Hessian in (x, θ, π) of
    Σ GPS + Σ −log p(e; π) (second derivatives in e and π by central differences of the density
    above, range Jacobians from RangeFactor objects), θ's block of its inverse."""
    from estimator.factors import RangeFactor
    from estimator.solve import NLOS_PROB_MAX, NLOS_PROB_MIN

    noise = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0)
    n, k_all = 60, 2
    sc = simulate(np.random.default_rng(8), n_users=k_all, n_keyframes=n, noise=noise, p_nlos=0.3)
    params = SolverParams(estimate_bias=False, estimate_noise_scale=False, track_clock=False,
                          step_tol_m=1e-10, step_tol_uav_m=1e-10, step_tol_sigma=0.0)
    est = solve_batch(sc.keyframes, k_all, sc.user_up_m, noise, params)
    pi = est.state.nlos_prob_k
    assert np.all((pi > NLOS_PROB_MIN) & (pi < NLOS_PROB_MAX)), pi  # both π free
    dim = 3 * n + 2 * k_all + k_all
    h = np.zeros((dim, dim))
    h[: 3 * n, : 3 * n] = np.eye(3 * n) / noise.sigma_gps_m**2
    m = params.nlos_mean_m / noise.range_s0_m
    de, dp = 1e-4, 1e-5
    for i, kf in enumerate(sc.keyframes):
        x = est.uav_enu_m[i]
        for k, r in zip(kf.user_idx, kf.range_m, strict=True):
            f = RangeFactor(float(r), noise, 2, float(sc.user_up_m[k]))
            th = est.users_enu_m[k, :2]
            e = f.error(x, th)
            jx, jt = f.jacobian(x, th)
            p_k = float(pi[k])

            def nll(ee, pp):
                return _mixture_nll(ee, pp, m)

            d2e = (nll(e + de, p_k) - 2 * nll(e, p_k) + nll(e - de, p_k)) / de**2
            dep = (nll(e + de, p_k + dp) - nll(e + de, p_k - dp) - nll(e - de, p_k + dp)
                   + nll(e - de, p_k - dp)) / (4 * de * dp)
            d2p = (nll(e, p_k + dp) - 2 * nll(e, p_k) + nll(e, p_k - dp)) / dp**2
            j = np.zeros(dim)
            j[3 * i : 3 * i + 3] = jx
            j[3 * n + 2 * k : 3 * n + 2 * k + 2] = jt
            ip = 3 * n + 2 * k_all + int(k)
            h += d2e * np.outer(j, j)
            h[ip, :] += dep * j
            h[:, ip] += dep * j
            h[ip, ip] += d2p
    cov_ref = np.linalg.inv(h)[3 * n : 3 * n + 2 * k_all, 3 * n : 3 * n + 2 * k_all]
    for k in range(k_all):
        np.testing.assert_allclose(est.cov_users_m2[k], cov_ref[2 * k : 2 * k + 2, 2 * k : 2 * k + 2], rtol=2e-4)
    # and it is larger than the EM-weight covariance of the same solution (π known, γ weights)
    prob = pack_keyframes(sc.keyframes, k_all, sc.user_up_m, noise, params)
    prob.nlos_prob_k = pi
    lin = linearize(prob, est.uav_enu_m, est.users_enu_m[:, :2], np.ones(k_all, dtype=bool))
    _, _, s_em = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, 0.0)
    cov_em = np.linalg.inv(s_em)
    for k in range(k_all):
        assert np.trace(est.cov_users_m2[k]) > 1.05 * np.trace(cov_em[2 * k : 2 * k + 2, 2 * k : 2 * k + 2])


@pytest.mark.parametrize("pi, m", [(0.2, 20.0 / 3.0), (0.05, 3.0), (0.4, 10.0)])
def test_nlos_curvature_is_the_derivative_of_psi(pi, m):
    from estimator.robust import nlos_curvature, nlos_terms

    e = np.linspace(-4.0, 60.0, 801)
    h = 1e-5
    fd = (nlos_terms(e + h, pi, m)[1] - nlos_terms(e - h, pi, m)[1]) / (2 * h)
    c = nlos_curvature(e, pi, m)
    np.testing.assert_allclose(c, fd, atol=1e-8)
    assert c.min() < 0.0  # ranges the mixture cannot classify carry negative curvature
    # the one-pass form (robust.nlos_terms_curvature, the solver's Newton steps): ρ' = ψ by finite
    # differences, and γ the posterior LoS probability (1 − π)φ / ((1 − π)φ + π f) of the module
    # docstring's mixture, with f evaluated by quadrature of the convolution
    from scipy import integrate, stats

    from estimator.robust import nlos_terms_curvature

    _, psi, gamma, _ = nlos_terms_curvature(e, pi, m)
    fd_rho = (nlos_terms_curvature(e + h, pi, m)[0] - nlos_terms_curvature(e - h, pi, m)[0]) / (2 * h)
    np.testing.assert_allclose(psi, fd_rho, atol=1e-7)
    for ei in (-2.0, 0.5, 3.0, 8.0):
        f = integrate.quad(lambda x, ei=ei: stats.norm.pdf(ei - x) * np.exp(-x / m) / m, 0, np.inf)[0]
        los = (1 - pi) * stats.norm.pdf(ei)
        assert nlos_terms_curvature(np.array([ei]), pi, m)[2][0] == pytest.approx(los / (los + pi * f), rel=1e-7)
    assert gamma.shape == e.shape


@pytest.mark.parametrize("seed", range(6))
def test_fft_periodogram_peak_matches_the_direct_sum(seed):
    """estimator.clock.peak_frequency_hz (FFT on a uniform grid) against the direct periodogram
    sum on a 4×-oversampled grid: the same peak within a quarter of the resolution 1/span."""
    from estimator.clock import peak_frequency_hz, periodogram

    rng = np.random.default_rng(seed)
    n = int(rng.integers(150, 2500))
    t = np.cumsum(rng.uniform(0.2, 0.6, n))
    t -= t[0]
    x = rng.uniform(4, 14) * np.mod(t / rng.uniform(5, 40) - rng.uniform(), 1) + rng.normal(scale=3.0, size=n)
    x -= x.mean()
    span = float(t.max())
    f_min, f_max = 2.0 / span, 1.0 / (4.0 * float(np.median(np.diff(t))))
    freqs = np.linspace(f_min, f_max, math.ceil(4.0 * (f_max - f_min) * span) + 1)
    f_direct = freqs[int(np.argmax(periodogram(t, x, freqs)))]
    assert abs(peak_frequency_hz(t, x, f_min, f_max) - f_direct) * span <= 0.25 + 1e-9


def _dense_window_information(lin) -> np.ndarray:
    """The window's normal matrix (3N + P, 3N + P) from its blocks, keyframe-major then Θ."""
    n, p_all = lin.hxu.shape[0], lin.huu.shape[0]
    h = np.zeros((3 * n + p_all, 3 * n + p_all))
    for i in range(n):
        h[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = lin.hxx[i]
        if lin.off is not None and i < n - 1:
            h[3 * i : 3 * i + 3, 3 * i + 3 : 3 * i + 6] = h[3 * i + 3 : 3 * i + 6, 3 * i : 3 * i + 3] = (
                np.eye(3) * lin.off[i])
    h[: 3 * n, 3 * n :] = lin.hxu.reshape(3 * n, p_all)
    h[3 * n :, : 3 * n] = h[: 3 * n, 3 * n :].T
    h[3 * n :, 3 * n :] = lin.huu
    return h


def test_last_keyframe_information_equals_the_dense_marginal():
    """Ŝ of the Gauss–Markov filter steps: the information of [x_last, Θ] with every other
    keyframe eliminated, against inverting the dense window matrix."""
    from estimator.online_chain import last_keyframe_information

    sc = simulate(np.random.default_rng(21), n_users=3, n_keyframes=60, noise=GM, gps_tau_s=60.0)
    prob = pack_keyframes(sc.keyframes[:40], 3, sc.user_up_m, GM, FIXED)
    theta = np.column_stack([sc.users_enu_m[:, :2], np.zeros(3)])
    lin = linearize(prob, prob.gps_enu_m, theta, np.ones(3, dtype=bool))
    s = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu)[2]
    h = _dense_window_information(lin)
    n = prob.n_keyframes
    sel = np.r_[3 * n - 3 : h.shape[0]]
    ref = np.linalg.inv(np.linalg.inv(h)[np.ix_(sel, sel)])
    got = last_keyframe_information(lin, s)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize("loss", ["nlos", "huber"])
def test_online_gauss_markov_filter_step_matches_dense_elimination(loss):
    """One filter step with a Gauss–Markov GPS link against the dense reference
    (tests.dense_filter): v = [x_l (3), x_n (3), Θ (K·p)], H = Ŝ on (x_l, Θ) + the GPS factor
    (GpsFactor) and the new ranges (RangeFactor) linearized at the Gauss–Markov prediction
    x_n⁰ = x̂_n + φ (x_l − x̂_l) and the previous Θ, Δv = H⁻¹ g; the new Ŝ is the Schur
    complement over x_l."""
    from tests.dense_filter import add_ranges, assert_step_matches, step_to_dense

    sc = simulate(np.random.default_rng(31), n_users=3, n_keyframes=60, noise=GM, gps_tau_s=60.0, p_visible=0.8)
    params = SolverParams(loss=loss, online_resolve_every=1000, window=1000, online_max_step_m=100.0,
                          estimate_noise_scale=False)
    j = next(i for i in range(40, 60) if 0 < sc.keyframes[i].user_idx.size < 3)
    on = OnlineEstimator(3, sc.user_up_m, GM, params)
    est, theta0, pi, x_l, h, g = step_to_dense(on, sc.keyframes, j)
    kf, g_l = sc.keyframes[j], sc.keyframes[j - 1].gps_enu_m
    phi = float(gps_phi(np.array([sc.keyframes[j - 1].t_s, kf.t_s]), GM.gps_tau_s)[1])
    x0 = kf.gps_enu_m + phi * (x_l - g_l)
    gf = GpsFactor(kf.gps_enu_m, GM.sigma_gps_m, phi, g_l)
    np.testing.assert_allclose(gf.error(x0, x_l), 0.0, atol=1e-12)
    jn, jl = gf.jacobian()
    jg = np.zeros((3, h.shape[0]))
    jg[:, 0:3], jg[:, 3:6] = jl, jn
    h += jg.T @ jg
    add_ranges(h, g, on, kf, x0, theta0, pi, sc.user_up_m)
    assert_step_matches(on, est, h, g, theta0, x_l, x0)


@pytest.mark.parametrize("params", [FIXED, SolverParams(), replace(FIXED, motion_sigma_m=0.2)],
                         ids=["fixed", "default", "motion"])
def test_online_chain_block_marginalization_equals_one_keyframe_at_a_time(params):
    """Folding m Gauss–Markov-linked keyframes (and motion links) into the prior at once gives the
    prior that m single-keyframe marginalizations at the same point give (and the same window)."""
    import copy

    sc = simulate(np.random.default_rng(23), n_users=3, n_keyframes=80, noise=GM, gps_tau_s=60.0, p_visible=0.8,
                  odom_sigma_m=0.1)
    on = OnlineEstimator(3, sc.user_up_m, GM, replace(params, window=1000))
    for kf in sc.keyframes[:50]:
        on.add_keyframe(kf)
    st = on.state
    marginalize_oldest(st)  # a prior that already holds a keyframe
    one = copy.deepcopy(st)
    assert marginalize_chain(st, 7)
    for _ in range(7):
        marginalize_oldest(one)
    assert st.n == one.n and st.prior.has_x and one.prior.has_x
    np.testing.assert_allclose(st.prior.z0, one.prior.z0, rtol=0, atol=1e-12)
    scale = np.abs(one.prior.info).max()
    np.testing.assert_allclose(st.prior.info, one.prior.info, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(st.prior.grad, one.prior.grad, rtol=1e-7, atol=1e-9 * scale)
    np.testing.assert_array_equal(st.win_count, one.win_count)
    np.testing.assert_array_equal(st.x[: st.n], one.x[: one.n])
    np.testing.assert_array_equal(st.odom_sigma_m[: st.n], one.odom_sigma_m[: one.n])


def _bursty_times(rng: np.random.Generator) -> np.ndarray:
    """Measurement times of one user as a simulated mission has them: bursts of 6–9 ranges
    0.3–1.1 s apart, 6–16 s between bursts, over 140 s."""
    t, tt = [], 30.0
    while tt < 170.0:
        for _ in range(int(rng.integers(6, 10))):
            tt += rng.uniform(0.3, 1.1)
            t.append(tt)
        tt += rng.uniform(6.0, 16.0)
    return np.array(t)


@pytest.mark.parametrize("seed", [8, 19, 32, 34, 35, 36, 38, 39])
def test_fit_sawtooth_finds_the_fundamental_when_a_harmonic_outshines_it(seed):
    """A 12 m, 15 s sawtooth sampled in bursts (σ 3 m): in these draws the periodogram's highest
    peak is a harmonic (7.5 s, 5 s), and the fit still finds the 15 s fundamental among the
    peaks' subharmonics."""
    from estimator.clock import SawtoothFit, fit_sawtooth, peak_frequency_hz

    rng = np.random.default_rng(seed)
    t = _bursty_times(rng)
    truth = SawtoothFit(15.0, rng.uniform(), 12.0, 0.0, 1.0)
    r = truth.value_m(t) + rng.normal(scale=3.0, size=t.size)
    span, dt = t.max() - t.min(), np.median(np.diff(t))
    peak_s = 1.0 / peak_frequency_hz(t - t.min(), r - r.mean(), 2.0 / span, 1.0 / (4.0 * dt))
    assert peak_s < 10.0, "the draw does not exercise the subharmonic search"
    fit = fit_sawtooth(t, r)
    assert fit is not None
    assert fit.period_s == pytest.approx(15.0, abs=0.3)
    # sd(A) ≈ σ √(12 / n) ≈ 1.3 m here
    assert fit.amplitude_m == pytest.approx(12.0, abs=4.0)


def test_fit_sawtooth_takes_back_what_the_position_absorbed():
    """Residuals of a solve that moved the user to absorb part of a sawtooth: the sawtooth plus a
    linear combination of the range's gradient in the user's position (the UAV circling it). Given
    that gradient as nuisance columns, the fit recovers the sawtooth (its amplitude within 1 m, the
    fitted sawtooth within 1 m RMS of the true one)."""
    from estimator.clock import SawtoothFit, fit_sawtooth

    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(0.0, 160.0, 150))
    heading = 2.0 * np.pi * t / 70.0
    grad = np.column_stack([np.cos(heading), np.sin(heading)])
    truth = SawtoothFit(15.0, 0.4, 12.0, 0.0, 1.0)
    r = truth.value_m(t) + grad @ np.array([-4.0, 3.0]) + rng.normal(scale=1.0, size=t.size)
    fit = fit_sawtooth(t, r, grad)
    assert fit is not None
    assert fit.period_s == pytest.approx(15.0, abs=0.2)
    assert fit.amplitude_m == pytest.approx(12.0, abs=1.0)
    d = fit.value_m(t) - truth.value_m(t)
    assert np.sqrt(np.mean((d - d.mean()) ** 2)) < 1.0


def test_refine_sawtooth_moves_a_stale_fit_to_the_data():
    """A warm refresh's sawtooth found by a cold solve on the first 80 s (15.15 s, its resets
    right at 40 s, the middle of those data) refined on 160 s of a 15 s, 12 m sawtooth: back
    within 0.05 s and 0.01 cycles of the truth at the samples' middle, the amplitude within 1 m."""
    from estimator.clock import SawtoothFit, refine_sawtooth

    rng = np.random.default_rng(9)
    t = np.sort(rng.uniform(0.0, 160.0, 400))
    truth = SawtoothFit(15.0, 0.3, 12.0, 0.0, 1.0)
    r = truth.value_m(t) + rng.normal(scale=3.0, size=t.size)
    # frac(40/15.15 − φ) = frac(40/15 − 0.3)
    stale = SawtoothFit(15.15, (40.0 / 15.15 - 40.0 / 15.0 + 0.3) % 1.0, 10.0, 0.0, 0.5)
    fit = refine_sawtooth(t, r, stale)
    assert fit.period_s == pytest.approx(15.0, abs=0.05)
    assert fit.amplitude_m == pytest.approx(12.0, abs=1.0)
    # the resets where the truth has them: frac(t/P − φ) agrees at the samples' middle time
    tm = 80.0
    assert abs(((tm / fit.period_s - fit.phase) - (tm / 15.0 - 0.3) + 0.5) % 1.0 - 0.5) < 0.01
    assert refine_sawtooth(t[:10], r[:10], stale) is stale


@pytest.mark.parametrize("seed", range(5))
def test_sawtooth_grid_by_prefix_sums_matches_the_dense_grid(seed):
    """estimator.clock._fit_grid (sorted phases and prefix sums) against _fit_grid_dense (frac on
    the whole (P, Φ, n) grid): the same residual sum of squares and the same fitted sawtooth at
    the samples (phases between two samples' phases tie: either is the fit), without and with
    nuisance columns."""
    from estimator.clock import _fit_grid, _fit_grid_dense

    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 800))
    t = np.sort(rng.uniform(0.0, 300.0, n))
    period = rng.uniform(5.0, 40.0)
    r = rng.uniform(3.0, 12.0) * np.mod(t / period - rng.uniform(), 1.0) + rng.normal(scale=3.0, size=n) + 2.0
    periods = 1.0 / np.linspace(1.0 / (1.05 * period), 1.0 / (0.95 * period), 31)

    def fitted(res):
        _, p, ph, a, c, _ = res
        u = t / p - ph
        return c + a * (u - np.floor(u))

    nuisance = rng.normal(size=(n, 2)) + np.column_stack([np.cos(t / 9.0), np.sin(t / 9.0)])
    for z in (None, nuisance):
        for phases in (np.arange(48) / 48, rng.uniform() + np.linspace(-1.0, 1.0, 21) / 48):
            fast, dense = _fit_grid(t, r, periods, phases, z), _fit_grid_dense(t, r, periods, phases, z)
            assert fast[0] == pytest.approx(dense[0], rel=1e-9)
            np.testing.assert_allclose(fitted(fast), fitted(dense), atol=1e-9)
