"""SLAM estimator: Schur solve vs dense reference, online vs batch, statistics vs CRLB, robustness,
mirror ambiguity, bad input. All problems are simulated with fixed seeds (estimator.simulate)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from estimator.batch import solve_batch
from estimator.crlb import crlb_users
from estimator.factors import dense_normal_equations
from estimator.init import (
    LINEAR_INIT_MAX_COST,
    REFINE_COST_TOL,
    _grid_cost,
    _grid_starts,
    _linear_starts,
    _refine_starts,
    _search_box,
    _truncated_terms,
    init_user,
    init_users,
    mirror_test,
    mirror_tests,
    refine_user,
    refine_users,
    user_cost,
    users_cost,
)
from estimator.linearize import linearize
from estimator.noise import NoiseModel
from estimator.online import OnlineEstimator, check_due, full_update
from estimator.online_marginal import marginalize_block, marginalize_oldest
from estimator.problem import pack_keyframes
from estimator.schur import schur_solve
from estimator.simulate import simulate
from estimator.types import Keyframe, SolverParams
from uavloc.errors import EstimatorError

NOISE = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0)
NOISE_DD = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0, range_a_m=0.5, range_b_per_m=0.01)


def _user_errors(est, sc):
    return np.linalg.norm(est.users_enu_m[:, :2] - sc.users_enu_m[:, :2], axis=1)


def _nees(est, sc):
    err = est.users_enu_m[:, :2] - sc.users_enu_m[:, :2]
    return np.array([e @ np.linalg.solve(c, e) for e, c in zip(err, est.cov_users_m2, strict=True)])


# --- Schur complement against the dense normal equations ---------------------------------------


def _dense_from_blocks(lin, n, pu):
    """Assemble the full normal matrix from the solver's blocks (to check linearize itself)."""
    h = np.zeros((3 * n + pu, 3 * n + pu))
    for i in range(n):
        h[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = lin.hxx[i]
        h[3 * i : 3 * i + 3, 3 * n :] = lin.hxu[i]
        if lin.off is not None and i + 1 < n:
            h[3 * i : 3 * i + 3, 3 * i + 3 : 3 * i + 6] = np.eye(3) * lin.off[i]
    h[3 * n :, : 3 * n] = h[: 3 * n, 3 * n :].T
    h[3 * n + 3 * 0 :, 3 * n :] = lin.huu
    h[: 3 * n, : 3 * n] = np.triu(h[: 3 * n, : 3 * n]) + np.triu(h[: 3 * n, : 3 * n], 1).T
    g = np.concatenate([lin.gx.ravel(), lin.gu])
    return h, g


@pytest.mark.parametrize(
    "params,noise",
    [
        (SolverParams(loss="none"), NOISE),
        (SolverParams(loss="huber"), NOISE_DD),
        (SolverParams(loss="cauchy", estimate_bias=True), NOISE),
        (SolverParams(loss="huber", motion_sigma_m=0.2), NOISE),
        (SolverParams(loss="huber", user_dim=3, estimate_bias=True, motion_sigma_m=0.3), NOISE_DD),
        (SolverParams(), NOISE),
        (SolverParams(), NOISE_DD),
    ],
    ids=["plain", "huber-sigma-of-d", "cauchy-bias", "huber-motion", "3d-bias-motion", "nlos", "nlos-sigma-of-d"],
)
@pytest.mark.parametrize("lam", [0.0, 1e-2])
@pytest.mark.parametrize("p_visible", [0.8, 1.0], ids=["gaps", "every-range"])
def test_schur_solve_and_covariance_match_dense_reference(params, noise, lam, p_visible):
    sc = simulate(np.random.default_rng(11), n_users=3, n_keyframes=25, p_visible=p_visible, p_nlos=0.2,
                  noise=noise, odom_sigma_m=0.1)
    prob = pack_keyframes(sc.keyframes, 3, sc.user_up_m, noise, params)
    rng = np.random.default_rng(12)
    x = sc.uav_enu_m + rng.normal(size=sc.uav_enu_m.shape)
    theta = np.zeros((3, prob.p))
    theta[:, : prob.user_dim] = sc.users_enu_m[:, : prob.user_dim] + rng.normal(size=(3, prob.user_dim)) * 3
    if params.estimate_bias:
        theta[:, -1] = rng.normal(size=3)
    active = np.ones(3, dtype=bool)
    lin = linearize(prob, x, theta, active)
    h_ref, g_ref, cost_ref = dense_normal_equations(prob, x, theta, active)
    n, pu = prob.n_keyframes, 3 * prob.p
    h_blk, g_blk = _dense_from_blocks(lin, n, pu)
    scale = np.max(np.abs(h_ref))
    np.testing.assert_allclose(h_blk, h_ref, rtol=1e-9, atol=1e-12 * scale)
    np.testing.assert_allclose(g_blk, g_ref, rtol=1e-9, atol=1e-12 * np.max(np.abs(g_ref)))
    assert lin.cost == pytest.approx(cost_ref, rel=1e-12)

    dx, du, s = schur_solve(lin.hxx, lin.off, lin.hxu, lin.huu, lin.gx, lin.gu, lam)
    h_damped = h_ref.copy()
    h_damped[np.diag_indices(3 * n + pu)] *= 1.0 + lam
    step_ref = np.linalg.solve(h_damped, g_ref)
    np.testing.assert_allclose(np.concatenate([dx.ravel(), du]), step_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.linalg.inv(s), np.linalg.inv(h_damped)[3 * n :, 3 * n :], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("indefinite", [False, True], ids=["cholesky", "cofactor-fallback"])
def test_schur_solve_block_diagonal_paths_match_dense_solve(indefinite):
    """Block-diagonal H_xx: the Cholesky path (every 3×3 block positive definite) and the cofactor
    inverse it falls back to (a block indefinite, as the observed information can make one)
    both give the dense solve of the whole system and its Schur complement."""
    rng = np.random.default_rng(5)
    n, p = 30, 7
    a = rng.normal(size=(n, 3, 3))
    hxx = a @ a.transpose(0, 2, 1) + 0.5 * np.eye(3)
    if indefinite:
        hxx[4] = np.diag([2.0, -1.0, 3.0])
    hxu = rng.normal(size=(n, 3, p)) * 0.1
    b = rng.normal(size=(p, p))
    huu = b @ b.T + 50.0 * np.eye(p)
    gx, gu = rng.normal(size=(n, 3)), rng.normal(size=p)
    h = np.zeros((3 * n + p, 3 * n + p))
    for i in range(n):
        h[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = hxx[i]
        h[3 * i : 3 * i + 3, 3 * n :] = hxu[i]
    h[3 * n :, : 3 * n] = h[: 3 * n, 3 * n :].T
    h[3 * n :, 3 * n :] = huu
    dx, du, s = schur_solve(hxx, None, hxu, huu, gx, gu)
    step = np.linalg.solve(h, np.concatenate([gx.ravel(), gu]))
    np.testing.assert_allclose(np.concatenate([dx.ravel(), du]), step, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.linalg.inv(s), np.linalg.inv(h)[3 * n :, 3 * n :], rtol=1e-9, atol=1e-14)
    np.testing.assert_array_equal(s, s.T)


@pytest.mark.parametrize("pattern,n", [("circle", 200), ("lawnmower", 400)])
def test_solve_stops_within_step_tol_sigma_of_the_optimum(pattern, n):
    """The default stop (step still to go below 0.001 σ in the users' Mahalanobis norm) lands
    within a few thousandths of a σ of the tightly converged optimum, and saves iterations."""
    sc = simulate(np.random.default_rng(37), n_users=4, n_keyframes=n, pattern=pattern, p_nlos=0.1)
    default = SolverParams()
    tight = SolverParams(step_tol_m=1e-12, step_tol_uav_m=1e-12, step_tol_sigma=0.0)
    est = solve_batch(sc.keyframes, 4, sc.user_up_m, NOISE, default)
    opt = solve_batch(sc.keyframes, 4, sc.user_up_m, NOISE, tight)
    dth = (est.users_enu_m[:, :2] - opt.users_enu_m[:, :2]).ravel()
    assert float(np.sqrt(dth @ opt.info_users @ dth)) < 3 * default.step_tol_sigma
    assert est.iterations < opt.iterations


def test_reported_covariance_is_inverse_of_dense_normal_matrix_at_solution():
    sc = simulate(np.random.default_rng(5), n_users=3, n_keyframes=40)
    params = SolverParams(step_tol_m=1e-10, step_tol_uav_m=1e-10, step_tol_sigma=0.0, estimate_bias=False,
                          estimate_noise_scale=False)
    est = solve_batch(sc.keyframes, 3, sc.user_up_m, NOISE, params)
    prob = pack_keyframes(sc.keyframes, 3, sc.user_up_m, NOISE, params)
    prob.nlos_prob_k = est.state.nlos_prob_k  # the per-user NLoS probability the solve ended with
    theta = est.users_enu_m[:, :2]
    h, _, _ = dense_normal_equations(prob, est.uav_enu_m, theta, np.ones(3, dtype=bool))
    cov_ref = np.linalg.inv(h)[3 * 40 :, 3 * 40 :]
    for k in range(3):
        np.testing.assert_allclose(est.cov_users_m2[k], cov_ref[2 * k : 2 * k + 2, 2 * k : 2 * k + 2], rtol=1e-6)
    np.testing.assert_allclose(est.info_users, np.linalg.inv(cov_ref), rtol=1e-6, atol=1e-9)


# --- online against batch -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "params",
    [SolverParams(estimate_noise_scale=False),
     SolverParams(estimate_bias=True, bias_select=False, motion_sigma_m=0.2, estimate_noise_scale=False)],
    ids=["default", "bias-motion"],
)
def test_online_equals_batch_without_marginalization(params):
    sc = simulate(np.random.default_rng(21), n_users=4, n_keyframes=80, odom_sigma_m=0.1, p_visible=0.9)
    # a full re-solve at every keyframe (no information-filter steps), nothing marginalized
    tight = SolverParams(**{**params.__dict__, "window": 1000, "step_tol_m": 1e-10, "step_tol_uav_m": 1e-10,
                            "step_tol_sigma": 0.0, "online_step_tol_m": 1e-10,
                            "online_resolve_every": 1})
    batch = solve_batch(sc.keyframes, 4, sc.user_up_m, NOISE, tight)
    on = OnlineEstimator(4, sc.user_up_m, NOISE, tight)
    for kf in sc.keyframes:
        est = on.add_keyframe(kf)
    assert on.estimate is est
    np.testing.assert_allclose(est.users_enu_m, batch.users_enu_m, atol=1e-6)
    np.testing.assert_allclose(est.uav_enu_m, batch.uav_enu_m, atol=1e-6)
    np.testing.assert_allclose(est.cov_users_m2, batch.cov_users_m2, rtol=1e-5)
    np.testing.assert_array_equal(est.n_ranges, batch.n_ranges)


@pytest.mark.parametrize(
    "params, noise, p_visible",
    [
        (SolverParams(), NOISE, 1.0),
        (SolverParams(), NOISE, 0.6),
        (SolverParams(loss="huber", estimate_bias=True), NOISE_DD, 1.0),
        (SolverParams(loss="huber", estimate_bias=True), NOISE_DD, 0.6),
        (SolverParams(loss="cauchy", user_dim=3), NOISE, 0.7),
        (SolverParams(nlos_adapt=False, nlos_prob=0.2), NOISE_DD, 1.0),
    ],
    ids=["nlos", "nlos-some-users", "huber-bias-dd", "huber-bias-dd-some-users", "cauchy-3d", "nlos-fixed-dd"],
)
def test_online_filter_step_matches_dense_elimination_of_the_new_keyframe(params, noise, p_visible):
    """One information-filter step against the dense reference: variables z = [x_n (3), θ (K·p)],
    H = blockdiag(I/σ_gps², S) + Σ w JᵀJ, g = −Σ ψ J over the new keyframe's ranges (RangeFactor
    objects, linearized at the GPS fix and the previous θ), Δz = H⁻¹ g; the new S is the Schur
    complement of H over x_n and the reported covariance its inverse."""
    from estimator.factors import RangeFactor
    from estimator.robust import loss_psi_weight

    sc = simulate(np.random.default_rng(31), n_users=3, n_keyframes=60, noise=noise, p_nlos=0.1, p_visible=p_visible)
    params = SolverParams(**{**params.__dict__, "online_resolve_every": 1000, "window": 1000,
                             "online_max_step_m": 100.0, "estimate_noise_scale": False})
    # the new keyframe ranges every user, or (p_visible < 1) some of them
    j = next(i for i in range(40, 60) if p_visible == 1.0 or 0 < sc.keyframes[i].user_idx.size < 3)
    on = OnlineEstimator(3, sc.user_up_m, noise, params)
    for kf in sc.keyframes[:j]:
        est = on.add_keyframe(kf)
    assert est.state.active.all()
    # force a full solve, then take its state as the linearization point
    last = sc.keyframes[j - 1]
    st = on.state
    full_update(st, st.n - 1, last.gps_enu_m, last.user_idx, last.range_m, None)
    theta0, s0, pi = st.theta.copy(), st.s.copy(), st.nlos_pi.copy()
    kf = sc.keyframes[j]
    est = on.add_keyframe(kf)
    assert est.state.filter_step
    p, k_all = st.p, 3
    dim = 3 + k_all * p
    h = np.zeros((dim, dim))
    g = np.zeros(dim)
    h[:3, :3] = np.eye(3) / noise.sigma_gps_m**2
    h[3:, 3:] = s0
    x0 = kf.gps_enu_m
    for k, r in zip(kf.user_idx, kf.range_m, strict=True):
        f = RangeFactor(float(r), noise, params.user_dim, float(sc.user_up_m[k]), params.estimate_bias)
        e = f.error(x0, theta0[k])
        jx, jt = f.jacobian(x0, theta0[k])
        sig = f.sigma_m
        _, psi, w = loss_psi_weight(np.array([e]), params.loss, params.loss_scale, (pi[k], params.nlos_mean_m / sig))
        j = np.zeros(dim)
        j[:3] = jx
        j[3 + k * p : 3 + (k + 1) * p] = jt
        h += w[0] * np.outer(j, j)
        g -= psi[0] * j
    dz = np.linalg.solve(h, g)
    np.testing.assert_allclose(st.theta.ravel() - theta0.ravel(), dz[3:], rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(est.uav_enu_m[-1], x0 + dz[:3], rtol=1e-9, atol=1e-11)
    s_ref = h[3:, 3:] - h[3:, :3] @ np.linalg.solve(h[:3, :3], h[:3, 3:])
    np.testing.assert_allclose(st.s, s_ref, rtol=1e-9, atol=1e-12 * np.abs(s_ref).max())
    cov_ref = np.linalg.inv(s_ref).reshape(k_all, p, k_all, p)
    for k in range(k_all):
        d = params.user_dim
        np.testing.assert_allclose(est.cov_users_m2[k], cov_ref[k, :d, k, :d], rtol=1e-9, atol=1e-12)


def test_online_filter_steps_stay_close_to_full_resolves():
    """Default online (filter steps between window solves) against re-solving at every keyframe:
    users within a small fraction of their standard deviation, covariances within 10 %."""
    sc = simulate(np.random.default_rng(23), n_users=4, n_keyframes=200, p_nlos=0.2)
    plain = SolverParams(estimate_bias=False, estimate_noise_scale=False)
    fast = OnlineEstimator(4, sc.user_up_m, NOISE, plain)
    full = OnlineEstimator(4, sc.user_up_m, NOISE, replace(plain, online_resolve_every=1))
    n_filter = 0
    for i, kf in enumerate(sc.keyframes):
        a, b = fast.add_keyframe(kf), full.add_keyframe(kf)
        n_filter += bool(a.state.filter_step)
        if i >= 60 and np.all(b.state.active):
            sd = np.sqrt(np.trace(b.cov_users_m2, axis1=1, axis2=2))
            assert np.all(np.linalg.norm(a.users_enu_m - b.users_enu_m, axis=1) < 0.3 * sd), i
            diff = np.linalg.norm(a.cov_users_m2 - b.cov_users_m2, axis=(1, 2))
            rel = diff / np.linalg.norm(b.cov_users_m2, axis=(1, 2))
            assert np.all(rel < 0.1), (i, rel)
    assert n_filter > 0.6 * len(sc.keyframes)


def test_online_with_marginalization_stays_close_to_batch_with_bounded_window():
    sc = simulate(np.random.default_rng(22), n_users=4, n_keyframes=300)
    params = SolverParams(window=40, estimate_bias=False, estimate_noise_scale=False)
    batch = solve_batch(sc.keyframes, 4, sc.user_up_m, NOISE, params)
    on = OnlineEstimator(4, sc.user_up_m, NOISE, params)
    for kf in sc.keyframes:
        est = on.add_keyframe(kf)
        assert est.uav_enu_m.shape[0] <= params.window + params.online_resolve_every
    sigma = np.sqrt(np.trace(batch.cov_users_m2, axis1=1, axis2=2))
    assert np.all(np.linalg.norm(est.users_enu_m - batch.users_enu_m, axis=1) < 0.2 * sigma)
    np.testing.assert_allclose(est.cov_users_m2, batch.cov_users_m2, rtol=0.1)
    assert est.n_ranges.sum() == sum(len(kf.range_m) for kf in sc.keyframes)


# --- statistics ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_monte_carlo_rmse_close_to_crlb_on_los():
    sq_err, trace_crlb, nees = [], [], []
    for seed in range(20):
        sc = simulate(np.random.default_rng(100 + seed), n_users=5, n_keyframes=120)
        est = solve_batch(sc.keyframes, 5, sc.user_up_m, NOISE)
        # the default estimator (bias selection, noise scale) against the bound of the bias-free model
        crlb = crlb_users(sc.uav_enu_m, sc.users_enu_m, sc.visible, NOISE, SolverParams(estimate_bias=False))
        sq_err.extend(_user_errors(est, sc) ** 2)
        trace_crlb.extend(np.trace(crlb[2 * k : 2 * k + 2, 2 * k : 2 * k + 2]) for k in range(5))
        nees.extend(_nees(est, sc))
    ratio = np.sqrt(np.mean(sq_err) / np.mean(trace_crlb))
    assert 0.85 < ratio < 1.12, ratio
    assert 1.5 < np.mean(nees) < 2.6, np.mean(nees)


@pytest.mark.slow
def test_robust_loss_resists_twenty_percent_nlos():
    err = {"none": [], "huber": [], "cauchy": [], "tukey": [], "nlos": []}
    nees = []
    nees_nlos = []
    for seed in range(8):
        sc = simulate(np.random.default_rng(200 + seed), n_users=5, n_keyframes=150, pattern="lawnmower",
                      p_nlos=0.2, nlos_mean_m=20.0)
        for loss in err:
            params = SolverParams(loss=loss, loss_scale=3.0 if loss == "tukey" else 1.5, estimate_bias=False)
            est = solve_batch(sc.keyframes, 5, sc.user_up_m, NOISE, params)
            err[loss].extend(_user_errors(est, sc))
            if loss == "tukey":
                nees.extend(_nees(est, sc))
            if loss == "nlos":
                nees_nlos.extend(_nees(est, sc))
    mean = {k: float(np.mean(v)) for k, v in err.items()}
    assert mean["none"] > 2.0, mean
    assert mean["huber"] < 0.5 * mean["none"], mean
    assert mean["cauchy"] < 0.5 * mean["none"], mean
    # the redescending loss rejects outliers outright: smaller error, and an honest covariance
    assert mean["tukey"] < mean["huber"], mean
    assert 1.4 < np.mean(nees) < 3.5, np.mean(nees)
    # the LoS/NLoS mixture (the default) models the one-sided excess: best of all, honest covariance
    assert mean["nlos"] < min(mean["huber"], mean["cauchy"], mean["tukey"]), mean
    assert 1.4 < np.mean(nees_nlos) < 3.0, np.mean(nees_nlos)


def test_nlos_probability_is_the_maximum_likelihood_mixing_weight():
    """nlos_prob_update against a brute-force maximum of Σ log((1 − π) φ(e) + π f(e)) over π on a
    fine grid, per user, for users with no, some and many NLoS ranges."""
    from scipy.integrate import quad
    from scipy.stats import norm

    from estimator.problem import Problem
    from estimator.robust import loss_weight
    from estimator.solve import NLOS_PROB_MAX, NLOS_PROB_MIN, nlos_prob_update

    rng = np.random.default_rng(3)
    m_w = 20.0 / 3.0
    e = rng.normal(size=(3, 300))
    for k, frac in enumerate((0.0, 0.15, 0.4)):
        e[k] += (rng.uniform(size=300) < frac) * rng.exponential(m_w, size=300)
    mask = np.ones((300, 3), dtype=bool)
    prob = Problem(np.zeros((300, 3)), np.zeros((300, 3)), mask, np.zeros((300, 3)), np.zeros(300, dtype=bool),
                   np.zeros(3), NOISE, SolverParams(), np.array([0.1, 0.1, 0.1]))
    gamma = loss_weight(e, "nlos", 1.0, (np.array([[0.1], [0.1], [0.1]]), m_w))
    pi = nlos_prob_update(prob, gamma, np.ones(3, dtype=bool))
    f = np.array([[quad(lambda s, v=v: norm.pdf(v - s) * np.exp(-s / m_w) / m_w, 0, np.inf)[0] for v in row]
                  for row in e])
    grid = np.linspace(NLOS_PROB_MIN, NLOS_PROB_MAX, 4001)
    for k in range(3):
        ll = np.log((1 - grid[:, None]) * norm.pdf(e[k])[None, :] + grid[:, None] * f[k][None, :]).sum(axis=1)
        assert pi[k] == pytest.approx(grid[np.argmax(ll)], abs=2e-4), (k, pi[k])
    assert pi[0] == NLOS_PROB_MIN and 0.08 < pi[1] < 0.25 and 0.3 < pi[2] < 0.5


# --- mirror ambiguity ---------------------------------------------------------------------------


def test_straight_line_flagged_ambiguous_with_mirror_across_the_line():
    sc = simulate(np.random.default_rng(31), n_users=4, n_keyframes=100, pattern="line")
    est = solve_batch(sc.keyframes, 4, sc.user_up_m, NOISE, SolverParams(estimate_bias=False))
    assert est.ambiguous.all()
    # the line is the east axis: the mirror is the estimate with north negated, and one of the two
    # is the truth
    np.testing.assert_allclose(est.mirror_enu_m[:, 1], -est.users_enu_m[:, 1], atol=2.0)
    near = np.minimum(
        np.linalg.norm(est.users_enu_m[:, :2] - sc.users_enu_m[:, :2], axis=1),
        np.linalg.norm(est.mirror_enu_m[:, :2] - sc.users_enu_m[:, :2], axis=1),
    )
    assert np.all(near < 3.0), near


@pytest.mark.parametrize(
    "pattern,params,noise",
    [
        ("line", SolverParams(), NOISE),
        ("circle", SolverParams(), NOISE_DD),
        ("lawnmower", SolverParams(loss="huber", estimate_bias=True), NOISE),
        ("line", SolverParams(loss="cauchy", user_dim=3), NOISE_DD),
    ],
    ids=["line", "circle-sigma-of-d", "lawnmower-bias", "line-3d"],
)
def test_grouped_mirror_tests_equal_one_user_at_a_time(pattern, params, noise):
    """mirror_tests (users sharing their fixes, one pass) against mirror_test per user: the same
    verdicts and numbers, whether a user takes the one-pass shortcut or the full test; with
    estimates both near the truth and at the truth's reflection."""
    sc = simulate(np.random.default_rng(34), n_users=4, n_keyframes=150, pattern=pattern, noise=noise,
                  p_nlos=0.1)
    rng = np.random.default_rng(35)
    p = params.user_dim + (1 if params.estimate_bias else 0)
    theta = np.zeros((4, p))
    theta[:, : params.user_dim] = sc.users_enu_m[:, : params.user_dim] + rng.normal(size=(4, params.user_dim))
    theta[1, 1] = -theta[1, 1]  # a user at (about) its reflection across the east axis
    theta[2, :2] = sc.uav_enu_m[20, :2]  # a user on the track: no reflection to test
    if params.estimate_bias:
        theta[:, -1] = rng.normal(size=4)
    uav = np.array([kf.gps_enu_m for kf in sc.keyframes])
    rng_m = np.array([kf.range_m for kf in sc.keyframes])
    got = mirror_tests(uav, rng_m, theta, sc.user_up_m, noise, params, params.ambiguity_chi2)
    for k in range(4):
        ref = mirror_test(uav, rng_m[:, k], theta[k], float(sc.user_up_m[k]), noise, params, params.ambiguity_chi2)
        assert got[k].ambiguous == ref.ambiguous
        assert got[k].linearity == pytest.approx(ref.linearity, rel=1e-12)
        assert got[k].delta_chi2 == pytest.approx(ref.delta_chi2, rel=1e-9, abs=1e-9)
        assert got[k].separation_chi2 == pytest.approx(ref.separation_chi2, rel=1e-9, abs=1e-9)
        if ref.mirror_theta is None:
            assert got[k].mirror_theta is None
        else:
            np.testing.assert_allclose(got[k].mirror_theta, ref.mirror_theta, rtol=1e-12, atol=1e-9)
    if pattern == "line":
        assert any(t.mirror_theta is not None for t in got)  # the full test ran for some user
    else:
        assert any(t.mirror_theta is None and np.isinf(t.separation_chi2) for t in got)  # the shortcut did


@pytest.mark.parametrize(
    "params,noise",
    [
        (SolverParams(), NOISE),
        (SolverParams(), NOISE_DD),
        (SolverParams(loss="huber", estimate_bias=False), NOISE),
        (SolverParams(loss="cauchy", user_dim=3), NOISE_DD),
        (SolverParams(loss="tukey", loss_scale=3.0), NOISE),
    ],
    ids=["nlos", "nlos-sigma-of-d", "huber-no-bias", "cauchy-3d", "tukey"],
)
def test_refine_users_equal_refine_user_one_at_a_time(params, noise):
    """refine_users (users sharing their fixes, one pass) against refine_user per user and
    users_cost against user_cost, from starts near the truth, far off (several halvings) and at
    a user's reflection; and a user whose start is on its optimum already stops at once."""
    # (a lawnmower: on a line, 3-D users have a flat valley of rotations about it, along which
    # both wander by rounding-level decisions)
    sc = simulate(np.random.default_rng(36), n_users=6, n_keyframes=120, pattern="lawnmower", noise=noise,
                  p_nlos=0.15)
    rng = np.random.default_rng(37)
    p = params.user_dim + (1 if params.estimate_bias else 0)
    theta = np.zeros((6, p))
    d_u = params.user_dim
    theta[:, :d_u] = sc.users_enu_m[:, :d_u] + rng.normal(scale=3.0, size=(6, d_u))
    theta[1, :2] += 60.0  # far off
    theta[2, 1] = -theta[2, 1]  # near the reflection across the east axis
    if params.estimate_bias:
        theta[:, -1] = rng.normal(size=6)
    uav = np.array([kf.gps_enu_m for kf in sc.keyframes])
    rng_m = np.array([kf.range_m for kf in sc.keyframes])
    theta[3] = refine_user(uav, rng_m[:, 3], theta[3], float(sc.user_up_m[3]), noise, params, 50).theta
    costs = users_cost(uav, rng_m, theta, sc.user_up_m, noise, params)
    got = refine_users(uav, rng_m, theta, sc.user_up_m, noise, params, 15)
    for k in range(6):
        up = float(sc.user_up_m[k])
        assert costs[k] == pytest.approx(user_cost(uav, rng_m[:, k], theta[k], up, noise, params), rel=1e-12)
        ref = refine_user(uav, rng_m[:, k], theta[k], up, noise, params, 15)
        np.testing.assert_allclose(got[k].theta, ref.theta, rtol=1e-10, atol=1e-9)
        assert got[k].cost == pytest.approx(ref.cost, rel=1e-10)
    assert np.linalg.norm(got[1].theta[:2] - theta[1, :2]) > 10.0  # the far start moved
    # a start on its optimum (to REFINE_COST_TOL) gains less than that again (it may still slide
    # by centimetres along the flat valleys of a line: a 3-D user's rotation, a bias's bearing)
    assert 0.0 <= costs[3] - got[3].cost < REFINE_COST_TOL


@pytest.mark.parametrize("noise", [NOISE, NOISE_DD], ids=["sigma", "sigma-of-d"])
def test_grid_search_of_several_users_equals_one_at_a_time(noise):
    """_grid_starts searches all users' grids in one pass; each user's starts and costs must be the
    ones it gets alone (heights differ, so do the search boxes), and the best start within a few
    metres of the truth (a coarse cell is ~6 m, the zoom a third of it) with 20 % NLoS ranges."""
    sc = simulate(np.random.default_rng(36), n_users=5, n_keyframes=160, noise=noise, p_nlos=0.2)
    uav = np.array([kf.gps_enu_m for kf in sc.keyframes])[::4]
    rng_m = np.array([kf.range_m for kf in sc.keyframes]).T[:, ::4]
    up = sc.user_up_m + np.array([0.0, 1.5, 0.0, -2.0, 0.0])
    starts, costs = _grid_starts(uav, rng_m, up, noise, 3)
    for k in range(5):
        s1, c1 = _grid_starts(uav, rng_m[k : k + 1], up[k : k + 1], noise, 3)
        np.testing.assert_array_equal(starts[k], s1[0])
        np.testing.assert_array_equal(costs[k], c1[0])
    starts, costs = _grid_starts(uav, rng_m, sc.user_up_m, noise, 3)
    best = starts[np.arange(5), np.argmin(costs, axis=1)]
    err = np.linalg.norm(best - sc.users_enu_m[:, :2], axis=1)
    assert np.all(err < 4.0), err


def test_linear_start_is_exact_on_noise_free_ranges_and_refuses_a_line():
    """The closed-form multilateration recovers users exactly from exact ranges (any heights), and
    gives nothing for fixes along a line (the mirror ambiguity needs the grid)."""
    rng = np.random.default_rng(38)
    for pattern in ("circle", "lawnmower"):
        sc = simulate(rng, n_users=4, n_keyframes=150, pattern=pattern,
                      noise=NoiseModel(sigma_gps_m=1e-9, range_s0_m=1e-9))
        uav = sc.uav_enu_m
        users = sc.users_enu_m + np.array([[0, 0, 0.0], [0, 0, 2.0], [0, 0, -1.0], [0, 0, 5.0]])
        exact = np.linalg.norm(uav[None, :, :] - users[:, None, :], axis=2)
        np.testing.assert_allclose(_linear_starts(uav, exact, users[:, 2]), users[:, :2], atol=1e-8)
    line = simulate(rng, n_users=2, n_keyframes=60, pattern="line")
    assert _linear_starts(line.uav_enu_m, np.full((2, 60), 50.0), np.zeros(2)) is None


@pytest.mark.parametrize("noise", [NOISE, NOISE_DD], ids=["sigma", "sigma-of-d"])
def test_init_users_takes_the_linear_start_or_searches_and_matches_one_at_a_time(noise):
    """init_users: on clean (LoS) ranges the closed-form start passes its fit test; with 30 % NLoS
    the users whose linear fit is dragged go to the grid. Either way each user's start equals the
    one it gets alone, and lies within the truncated cost's reach of the truth."""
    for p_nlos, seed in ((0.0, 39), (0.3, 40)):
        sc = simulate(np.random.default_rng(seed), n_users=5, n_keyframes=150, noise=noise, p_nlos=p_nlos)
        uav = np.array([kf.gps_enu_m for kf in sc.keyframes])
        rng_m = np.array([kf.range_m for kf in sc.keyframes])
        params = SolverParams()
        fits = init_users(uav, rng_m, sc.user_up_m, noise, params)
        for k, fit in enumerate(fits):
            alone = init_user(uav, rng_m[:, k], float(sc.user_up_m[k]), noise, params)
            np.testing.assert_allclose(fit.theta, alone.theta, rtol=0, atol=1e-9)
        err = np.linalg.norm(np.array([f.theta[:2] for f in fits]) - sc.users_enu_m[:, :2], axis=1)
        assert np.all(err < 3.0), (p_nlos, err)
        # which path each user took: the linear fit's test, as init_users applies it
        lin = _linear_starts(uav, rng_m.T, sc.user_up_m)
        lin_cost = _truncated_terms(uav, rng_m.T, sc.user_up_m, lin, noise)[0] / uav.shape[0]
        if p_nlos == 0.0:
            assert np.all(lin_cost <= LINEAR_INIT_MAX_COST), lin_cost
        else:
            assert np.any(lin_cost > LINEAR_INIT_MAX_COST), lin_cost


def test_a_far_off_start_gets_no_credit_from_distance_dependent_noise():
    """σ(d) = s0 + a·exp(b·d) grows without bound: judged with σ at the candidate's own distances,
    a start kilometres away would see tiny whitened residuals and pass as a good fit (the online
    estimator once started an edge-of-coverage user 10⁷ m away and never recovered). σ comes from
    the measured ranges, so such a start saturates the truncated cost, and a linear start outside
    the search box is not kept."""
    noise = NoiseModel(sigma_gps_m=1.0, range_s0_m=2.5, range_a_m=0.1, range_b_per_m=0.01)
    sc = simulate(np.random.default_rng(42), n_users=1, n_keyframes=120, noise=noise,
                  users_enu_m=np.array([[280.0, 170.0, 0.0]]))
    uav = np.array([kf.gps_enu_m for kf in sc.keyframes])
    rng_m = np.array([kf.range_m for kf in sc.keyframes]).T
    far = sc.users_enu_m[:, :2] + 1e5
    cost = _truncated_terms(uav, rng_m, sc.user_up_m, far, noise)[0]
    assert cost[0] == pytest.approx(uav.shape[0] * 4.0)  # every range beyond c = 2
    near = _truncated_terms(uav, rng_m, sc.user_up_m, sc.users_enu_m[:, :2], noise)[0]
    assert near[0] < 1.5 * uav.shape[0]
    fit = init_users(uav, rng_m.T, sc.user_up_m, noise, SolverParams())[0]
    lo, hi = _search_box(uav, rng_m, sc.user_up_m, noise)
    assert np.all(fit.theta[:2] >= lo[0] - 5.0) and np.all(fit.theta[:2] <= hi[0] + 5.0)
    # 330 m from a 60 m circle, σ ≈ 5 m there: the start is a few σ off across the line of sight
    assert np.linalg.norm(fit.theta[:2] - sc.users_enu_m[0, :2]) < 20.0


WIDE_NOISE = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0, range_a_m=0.3, range_b_per_m=0.01)


def test_the_solver_cost_rises_as_a_user_moves_away_under_distance_dependent_noise():
    """The solver's range factor weighs a range by σ at the measured range: its cost grows
    quadratically as a user moves away. With σ at the estimate's own distance, e = r/σ(d) → 0 as
    d → ∞: a user 1 km off cost 1e-5 against 45 at the truth, and wide worlds sent users tens of
    kilometres away until σ(d) overflowed (issue 21)."""
    sc = simulate(np.random.default_rng(5), n_users=1, n_keyframes=80, noise=WIDE_NOISE,
                  users_enu_m=np.array([[200.0, 120.0, 0.0]]))
    prob = pack_keyframes(sc.keyframes, 1, sc.user_up_m, WIDE_NOISE, SolverParams(estimate_bias=False))
    x = np.array([kf.gps_enu_m for kf in sc.keyframes])
    costs = [linearize(prob, x, sc.users_enu_m[:, :2] + off, np.ones(1, dtype=bool)).cost
             for off in (0.0, 1e3, 1e5)]
    assert np.all(np.isfinite(costs)) and np.all(np.diff(costs) > 0)


@pytest.mark.parametrize("seed", range(3))
def test_online_in_a_wide_world_with_distance_dependent_noise_stays_near_the_users(seed):
    """Six users up to 350 m from a lawnmower over the centre, σ(d) = 3 + 0.3·exp(0.01·d) m, 30 %
    NLoS: every keyframe is taken without an exception and every user ends within 15 m (the
    online estimator raised OverflowError in its filter step on seeds 0 and 1 before σ came from
    the measured range; on a nearby seed it left three users 37 km away)."""
    rng = np.random.default_rng(seed + 1)
    users = np.column_stack([rng.uniform(-250, 250, 6), rng.uniform(-250, 250, 6), np.zeros(6)])
    sc = simulate(np.random.default_rng(101 + seed), n_users=6, n_keyframes=300, noise=WIDE_NOISE,
                  users_enu_m=users, pattern="lawnmower", p_nlos=0.3, nlos_mean_m=30.0)
    on = OnlineEstimator(6, sc.user_up_m, WIDE_NOISE, SolverParams())
    for kf in sc.keyframes:
        est = on.add_keyframe(kf)
    assert np.all(np.linalg.norm(est.users_enu_m[:, :2] - users[:, :2], axis=1) < 15.0)


def test_start_refinement_lowers_the_truncated_cost_and_reaches_the_truth_on_exact_ranges():
    sc = simulate(np.random.default_rng(41), n_users=4, n_keyframes=120,
                  noise=NoiseModel(sigma_gps_m=1e-6, range_s0_m=1e-3))
    uav = sc.uav_enu_m
    exact = np.linalg.norm(uav[None, :, :] - sc.users_enu_m[:, None, :], axis=2)
    start = sc.users_enu_m[:, :2] + np.array([[3.0, -2.0], [-2.5, 1.0], [0.5, 3.0], [-1.0, -1.0]])
    out = _refine_starts(uav, exact, sc.user_up_m, start, NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0), iterations=8)
    np.testing.assert_allclose(out, sc.users_enu_m[:, :2], atol=1e-6)


def test_grid_init_with_fixes_at_the_users_height():
    """Candidates on the fixes themselves with no height difference: the squared distances of the
    single-precision grid round to (slightly negative) zero there and must not become NaN."""
    uav = np.column_stack([np.linspace(-50, 50, 60), np.full(60, 10.0), np.zeros(60)])
    uav[::2, 1] -= 3.0  # not a line: no mirror
    truth = np.array([5.0, -20.0, 0.0])
    fit = init_user(uav, np.linalg.norm(uav - truth, axis=1), 0.0, NOISE, SolverParams())
    assert np.all(np.isfinite(fit.theta)) and np.isfinite(fit.cost)
    assert np.linalg.norm(fit.theta[:2] - truth[:2]) < 2.0
    rng_m = np.linalg.norm(uav - truth, axis=1)[None, :]
    on_fixes = _grid_cost(uav, rng_m, np.zeros((1, 60)), uav[None, :, :2] + 1e-4, NOISE)
    assert np.all(np.isfinite(on_fixes))


@pytest.mark.parametrize("pattern", ["circle", "lawnmower"])
def test_curved_flight_not_ambiguous(pattern):
    sc = simulate(np.random.default_rng(32), n_users=4, n_keyframes=150, pattern=pattern)
    est = solve_batch(sc.keyframes, 4, sc.user_up_m, NOISE, SolverParams(estimate_bias=False))
    assert not est.ambiguous.any()
    assert np.all(np.isnan(est.mirror_enu_m))
    assert np.all(_user_errors(est, sc) < 3.0)


def test_online_reports_ambiguity_on_a_straight_line():
    sc = simulate(np.random.default_rng(33), n_users=3, n_keyframes=60, pattern="line")
    on = OnlineEstimator(3, sc.user_up_m, NOISE)
    for kf in sc.keyframes:
        est = on.add_keyframe(kf)
    assert est.ambiguous.all()


# --- other states -------------------------------------------------------------------------------


def test_range_bias_is_estimated():
    sc = simulate(np.random.default_rng(41), n_users=3, n_keyframes=200, bias_m=np.array([4.0, 6.0, 2.0]))
    est = solve_batch(sc.keyframes, 3, sc.user_up_m, NOISE, SolverParams(estimate_bias=True, bias_select=False))
    # within 3σ of the reported bias uncertainty (joint covariance of θ_k = [e, n, b])
    sigma_b = np.sqrt(np.diag(est.state.cov_theta_joint)[2::3])
    assert np.all(np.abs(est.bias_m - [4.0, 6.0, 2.0]) < 3 * sigma_b), (est.bias_m, sigma_b)
    assert np.all(sigma_b < 2.5)
    assert np.all(_user_errors(est, sc) < 2.0)
    assert est.info_users.shape == (6, 6)


def test_motion_factors_tighten_the_track():
    sc = simulate(np.random.default_rng(42), n_users=3, n_keyframes=150, odom_sigma_m=0.05)
    plain = solve_batch(sc.keyframes, 3, sc.user_up_m, NOISE)
    moto = solve_batch(sc.keyframes, 3, sc.user_up_m, NOISE, SolverParams(motion_sigma_m=0.05))
    err_plain = np.sqrt(np.mean((plain.uav_enu_m - sc.uav_enu_m) ** 2))
    err_moto = np.sqrt(np.mean((moto.uav_enu_m - sc.uav_enu_m) ** 2))
    assert err_moto < 0.5 * err_plain, (err_moto, err_plain)


def test_user_without_ranges_gives_nan_row_and_infinite_covariance():
    sc = simulate(np.random.default_rng(43), n_users=3, n_keyframes=60)
    kfs = [Keyframe(kf.gps_enu_m, kf.user_idx[kf.user_idx != 2], kf.range_m[kf.user_idx != 2]) for kf in sc.keyframes]
    est = solve_batch(kfs, 3, sc.user_up_m, NOISE)
    assert np.all(np.isnan(est.users_enu_m[2])) and np.all(np.isfinite(est.users_enu_m[:2]))
    assert np.all(np.isinf(est.cov_users_m2[2])) and np.all(np.isfinite(est.cov_users_m2[:2]))
    assert est.n_ranges[2] == 0 and not est.ambiguous[2]
    on = OnlineEstimator(3, sc.user_up_m, NOISE)
    first = on.add_keyframe(kfs[0])
    assert np.all(np.isnan(first.users_enu_m))
    for kf in kfs[1:]:
        est = on.add_keyframe(kf)
    assert np.all(np.isnan(est.users_enu_m[2])) and np.all(np.isinf(est.error_bound_95_m()[2]))


# --- bad input ----------------------------------------------------------------------------------


def _kf(**kw):
    base = {"gps_enu_m": np.array([0.0, 0.0, 30.0]), "user_idx": np.array([0, 1]), "range_m": np.array([50.0, 60.0])}
    base.update(kw)
    return Keyframe(**base)


@pytest.mark.parametrize(
    "kf,match",
    [
        (_kf(range_m=np.array([np.nan, 60.0])), "nan"),
        (_kf(range_m=np.array([50.0, np.inf])), "inf"),
        (_kf(range_m=np.array([-3.0, 60.0])), "-3.0"),
        (_kf(gps_enu_m=np.array([0.0, 0.0])), r"\(2,\)"),
        (_kf(gps_enu_m=np.array([0.0, np.nan, 1.0])), "nan"),
        (_kf(user_idx=np.array([0, 5])), "user index 5"),
        (_kf(user_idx=np.array([1, 1])), "twice"),
        (_kf(user_idx=np.array([0]), range_m=np.array([1.0, 2.0])), "equal length"),
        (_kf(odom_enu_m=np.array([1.0, np.inf, 0.0])), "odom"),
    ],
    ids=["nan-range", "inf-range", "negative-range", "gps-shape", "gps-nan", "user-index", "duplicate", "length",
         "odom"],
)
def test_bad_keyframe_rejected_with_offending_value(kf, match):
    with pytest.raises(EstimatorError, match=match):
        solve_batch([_kf(), kf], 2, np.zeros(2), NOISE)
    on = OnlineEstimator(2, np.zeros(2), NOISE)
    with pytest.raises(EstimatorError, match=match):
        on.add_keyframe(kf)


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: solve_batch([], 2, np.zeros(2), NOISE), "at least one keyframe"),
        (lambda: solve_batch([_kf()], 2, np.zeros(3), NOISE), r"shape \(2,\)"),
        (lambda: solve_batch([_kf()], 0, np.zeros(0), NOISE), "n_users"),
        (lambda: solve_batch([_kf()], 2, np.zeros(2), NOISE, SolverParams(loss="bisquare")), "bisquare"),
        (lambda: solve_batch([_kf()], 2, np.zeros(2), NOISE, SolverParams(user_dim=4)), "user_dim"),
        (lambda: solve_batch([_kf()], 2, np.zeros(2), NOISE, init_users_enu_m=np.zeros((3, 3))), r"\(3, 3\)"),
        (lambda: OnlineEstimator(2, np.array([0.0, np.nan]), NOISE), "nan"),
        (lambda: OnlineEstimator(2, np.zeros(2), NOISE, SolverParams(window=1)), "window"),
        (lambda: crlb_users(np.zeros((4, 2)), np.zeros((2, 3)), np.ones((4, 2), bool), NOISE), r"\(N, 3\)"),
        (lambda: solve_batch([_kf()], 2, np.zeros(2), NOISE, SolverParams(step_tol_sigma=-1e-3)), "step_tol_sigma"),
        (lambda: solve_batch([_kf()], 2, np.zeros(2), NOISE, SolverParams(step_tol_sigma=np.nan)), "step_tol_sigma"),
    ],
    ids=["empty", "up-shape", "no-users", "loss", "user-dim", "init-shape", "online-up", "window", "crlb-shape",
         "tol-sigma-negative", "tol-sigma-nan"],
)
def test_bad_arguments_rejected(call, match):
    with pytest.raises(EstimatorError, match=match):
        call()


def test_given_initial_users_are_used():
    sc = simulate(np.random.default_rng(44), n_users=2, n_keyframes=80)
    init = sc.users_enu_m + np.array([3.0, -2.0, 0.0])
    est = solve_batch(sc.keyframes, 2, sc.user_up_m, NOISE, SolverParams(estimate_bias=False), init_users_enu_m=init)
    assert np.all(_user_errors(est, sc) < 2.0)


@pytest.mark.parametrize("seed", [0, 3])
def test_online_on_a_line_with_nlos_and_gaps_stays_on_truth_or_flagged_mirror(seed):
    """Regression: an early start from few ranges must not lock a user in a wrong basin, and the
    online mirror test must not flip between the two sides on likelihood noise."""
    sc = simulate(np.random.default_rng(seed), n_users=4, n_keyframes=300, pattern="line", p_nlos=0.2,
                  p_visible=0.6)
    on = OnlineEstimator(4, sc.user_up_m, NOISE)
    for kf in sc.keyframes:
        est = on.add_keyframe(kf)
    assert est.ambiguous.all()
    err = np.minimum(_user_errors(est, sc), np.linalg.norm(est.mirror_enu_m[:, :2] - sc.users_enu_m[:, :2], axis=1))
    assert np.all(err < 10.0), err


def test_online_block_marginalization_equals_one_keyframe_at_a_time():
    """Unlinked keyframes (white GPS, no odometry) folded into the prior at once give the prior
    of folding them one by one at the same point (a prior already present, users with and
    without ranges in the dropped keyframes)."""
    import copy

    sc = simulate(np.random.default_rng(44), n_users=4, n_keyframes=160, p_visible=0.8, p_nlos=0.1)
    params = SolverParams(window=60, online_resolve_every=7)
    on = OnlineEstimator(4, sc.user_up_m, NOISE, params)
    for kf in sc.keyframes[:130]:
        on.add_keyframe(kf)
    assert on.state.prior is not None and on.state.n > 60
    m = on.state.n - 60
    seq, blk = copy.deepcopy(on.state), copy.deepcopy(on.state)
    for _ in range(m):
        marginalize_oldest(seq)
    assert marginalize_block(blk, m)
    ps, pb = seq.prior, blk.prior
    for a, b in ((ps.info, pb.info), (ps.grad, pb.grad), (ps.z0, pb.z0)):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9 * np.abs(a).max())
    assert seq.n == blk.n == 60
    np.testing.assert_array_equal(seq.win_count, blk.win_count)
    np.testing.assert_array_equal(seq.x[:60], blk.x[:60])
    np.testing.assert_array_equal(seq.range_m[:60], blk.range_m[:60])


def _nlos_problem(seed: int, p_nlos: float, params: SolverParams = SolverParams()):  # noqa: B008
    """A 6-user N = 200 circle with NLoS on users 0–2 (3–5 LoS): the scenario and fresh() -> (the
    packed problem, the grid starts)."""
    from estimator.batch import grid_init

    rng = np.random.default_rng(seed)
    sc = simulate(rng, n_users=6, n_keyframes=200, noise=NOISE, p_nlos=p_nlos)
    # users 3..5 LoS: their ranges redrawn without NLoS excess
    kfs = []
    for n, kf in enumerate(sc.keyframes):
        r = kf.range_m.copy()
        los = kf.user_idx >= 3
        d = np.linalg.norm(sc.uav_enu_m[n] - sc.users_enu_m[kf.user_idx[los]], axis=1)
        r[los] = d + rng.normal(scale=NOISE.range_s0_m, size=d.size)
        kfs.append(replace(kf, range_m=r))

    def fresh():
        prob = pack_keyframes(kfs, 6, sc.user_up_m, NOISE, params)
        theta = np.zeros((6, prob.p))
        for k, th in grid_init(prob, prob.gps_enu_m, range(6)).items():
            theta[k] = th
        return prob, theta

    return sc, fresh


def test_newton_steps_reach_the_em_weighted_optimum_in_fewer_iterations():
    """levenberg_marquardt with newton steps (the observed information) against the EM-weighted
    iteration, the slow reference: the same optimum to 1e-6 m, the same EM-weighted S after
    em_information, fewer iterations; at fixed π on and off its floor."""
    from estimator.lm import em_information, levenberg_marquardt

    # converged tightly: no σ-relative stop, keyframes to the same tolerance
    params = SolverParams(step_tol_sigma=0.0, step_tol_uav_m=1e-9, max_iterations=500)
    _, fresh = _nlos_problem(60, 0.2, params)
    tight = dict(step_tol_m=1e-9)
    for pi in (np.full(6, 0.005), np.array([0.2, 0.15, 0.25, 0.005, 0.005, 0.005])):
        prob, theta = fresh()
        prob.nlos_prob_k = pi
        active = np.ones(6, dtype=bool)
        ref = levenberg_marquardt(prob, prob.gps_enu_m.copy(), theta, active, **tight)
        got = levenberg_marquardt(prob, prob.gps_enu_m.copy(), theta, active, newton=True, **tight)
        assert got.observed and not ref.observed
        np.testing.assert_allclose(got.theta, ref.theta, atol=1e-6)
        np.testing.assert_allclose(got.x, ref.x, atol=1e-6)
        assert got.iterations < ref.iterations
        em = em_information(prob, got, active)
        np.testing.assert_allclose(em.s, ref.s, rtol=1e-5, atol=1e-8)
        np.testing.assert_allclose(em.lin.w, ref.lin.w, atol=1e-6)
        assert em.lin.cost == pytest.approx(ref.lin.cost, rel=1e-9)


@pytest.mark.parametrize("k,scale,saves", [(20, None, True), (5, 1.6, False)], ids=["benchmark-fluke", "noisy-user"])
def test_noise_scale_taken_midway_matches_the_re_solve(monkeypatch, k, scale, saves):
    """A per-user noise scale that moves by more than NOISE_SCALE_RESOLVE is taken on the solve's
    way (levenberg_marquardt's `rescale`, near the optimum) instead of by a second solve from the
    optimum, the slow reference (lm.RESCALE_STEP_SIGMA = 0: never offered): the same users to a
    few hundredths of their σ, the same covariances and noise scales to 1 %, with fewer
    linearizations. The benchmark's N = 200, K = 20 problem (seed 7) has a white user whose scale
    comes out at 1.13 by chance; a user 1.6× noisier than assumed first looks NLoS, and the NLoS
    rounds (solve_loss) re-estimate its scale with its π: no iteration saved there."""
    import estimator.lm as lm_mod

    noise = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0)
    kw = {} if scale is None else {"noise_scale": np.r_[scale, np.ones(k - 1)]}
    sc = simulate(np.random.default_rng(7), n_users=k, n_keyframes=200, noise=noise, **kw)
    calls = {"n": 0}
    real = lm_mod.linearize

    def counting(*args, **kwargs):
        calls["n"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(lm_mod, "linearize", counting)
    out = {}
    for name, sigma in (("reference", 0.0), ("midway", lm_mod.RESCALE_STEP_SIGMA)):
        monkeypatch.setattr(lm_mod, "RESCALE_STEP_SIGMA", sigma)
        calls["n"] = 0
        out[name] = (solve_batch(sc.keyframes, k, sc.user_up_m, noise, SolverParams()), calls["n"])
    (ref, n_ref), (got, n_got) = out["reference"], out["midway"]
    assert np.max(ref.state.noise_scale) > 1.0 + 0.1  # the re-solve's case
    assert n_got < n_ref if saves else n_got <= n_ref
    for k_ in range(k):
        d = got.users_enu_m[k_, :2] - ref.users_enu_m[k_, :2]
        assert float(np.sqrt(d @ np.linalg.solve(ref.cov_users_m2[k_], d))) < 0.05
    np.testing.assert_allclose(got.cov_users_m2, ref.cov_users_m2, rtol=0.01)
    np.testing.assert_allclose(got.state.noise_scale, ref.state.noise_scale, rtol=0.01)


def test_nlos_rounds_by_user_reach_the_joint_em_fixed_point():
    """solve_loss's partial rounds on the NLoS users alone (keyframes and LoS users held) against
    the joint partial rounds and against the slow reference, joint EM of full tight solves until π
    stops moving: the same positions (to 1 mm, ~0.003 σ), the same π (to 2e-4), with fewer joint
    linearizations than the joint rounds."""
    import estimator.lm as lm_mod
    from estimator.lm import levenberg_marquardt
    from estimator.solve import nlos_prob_update, solve_loss

    _, fresh = _nlos_problem(61, 0.25)
    active = np.ones(6, dtype=bool)
    # the reference: full EM-weighted solves to 1e-9 m, π re-estimated, until it moves < 1e-10
    prob, theta = fresh()
    prob.nlos_prob_k = np.full(6, 0.1)
    x = prob.gps_enu_m.copy()
    for _ in range(300):
        res = levenberg_marquardt(prob, x, theta, active, step_tol_m=1e-9)
        pi = nlos_prob_update(prob, res.lin.w, active)
        done = np.max(np.abs(pi - prob.nlos_prob_k)) < 1e-10
        prob.nlos_prob_k, x, theta = pi, res.x, res.theta
        if done:
            break
    ref_theta, ref_pi = res.theta, prob.nlos_prob_k
    assert np.all(ref_pi[:3] > 0.05) and np.all(ref_pi[3:] <= 0.0051)  # NLoS users and LoS users
    counts = {}
    calls = []
    orig = lm_mod.linearize

    def counting(prob, *a, **kw):
        calls.append(prob.n_users)
        return orig(prob, *a, **kw)

    for conditional in (True, False):
        prob, theta = fresh()
        calls.clear()
        lm_mod.linearize = counting
        try:
            got = solve_loss(prob, prob.gps_enu_m.copy(), theta, active, conditional=conditional)
        finally:
            lm_mod.linearize = orig
        counts[conditional] = sum(1 for k in calls if k == 6)
        np.testing.assert_allclose(got.theta[:, :2], ref_theta[:, :2], atol=1e-3)
        np.testing.assert_allclose(prob.nlos_prob_k, ref_pi, atol=2e-4)
        assert not got.observed  # S is the EM-weighted one
    assert counts[True] < counts[False]


@pytest.mark.parametrize("k_all,p,d", [(20, 3, 2), (5, 2, 2), (4, 4, 3)])
def test_covariances_from_cholesky_equal_the_inverse_of_s(k_all, p, d):
    """marginals._covariances (S⁻¹ from its Cholesky factor, the position information as the
    Schur complement of S over the biases) against the slow reference: np.linalg.inv of S and
    of the covariance's position block; with every user active and one inactive, and with S⁻¹
    handed in. An indefinite S gives no covariance."""
    from estimator.marginals import user_covariances

    rng = np.random.default_rng(70)
    a = rng.normal(size=(k_all * p, k_all * p))
    s = a @ a.T + k_all * p * np.eye(k_all * p)
    some = np.ones(k_all, dtype=bool)
    some[1] = False
    for active in (np.ones(k_all, dtype=bool), some):
        sel = np.repeat(active, p)
        ref = np.linalg.inv(s[np.ix_(sel, sel)])
        na = int(active.sum())
        r4 = ref.reshape(na, p, na, p)
        ref_info = np.linalg.inv(r4[:, :d, :, :d].reshape(na * d, na * d))
        ka = np.flatnonzero(active)
        ip = (ka[:, None] * d + np.arange(d)).ravel()
        for given in (None, ref if active.all() else None):
            cov, info, joint = user_covariances(s, active, k_all, p, d, given)
            np.testing.assert_allclose(joint, ref, rtol=1e-10, atol=1e-14)
            np.testing.assert_allclose(cov[ka], r4[np.arange(na), :d, np.arange(na), :d], rtol=1e-10, atol=1e-14)
            np.testing.assert_allclose(info[np.ix_(ip, ip)], ref_info, rtol=1e-9, atol=1e-9)
            assert np.all(np.isinf(cov[~active]))
    bad = s.copy()
    bad[0, 0] = -1.0
    cov, _, joint = user_covariances(bad, np.ones(k_all, dtype=bool), k_all, p, d)
    assert joint is None and np.all(np.isinf(cov))


def test_a_noise_scale_moving_within_its_standard_errors_does_not_call_the_checks_back():
    """The checks' back-off (online.check_due) returns to online_check_every when a user's noise
    scale moved by more than 3 of its standard errors 1/√(2 n) since the last check: with 100
    ranges in the window a 15 % move is noise, a 30 % one is evidence."""
    from estimator.online import ONLINE_SCALE_EVIDENCE_Z

    sc = simulate(np.random.default_rng(5), n_users=2, n_keyframes=130, pattern="circle", noise=NOISE)
    on = OnlineEstimator(2, sc.user_up_m, NOISE, SolverParams())
    for kf in sc.keyframes:
        on.add_keyframe(kf)
    st = on.state
    assert st.check_state is not None and np.all(st.win_count >= 100)
    every = SolverParams().online_check_every
    scale0, pi0, _ = st.check_state
    tol = ONLINE_SCALE_EVIDENCE_Z / np.sqrt(2.0 * st.win_count[0])
    for move, resets in ((0.7 * tol, False), (1.3 * tol, True)):
        st.check_interval = 4 * every
        st.noise_scale = scale0 * np.array([1.0 + move, 1.0])
        st.nlos_pi = pi0.copy()
        check_due(st, np.zeros(2, dtype=bool))
        assert (st.check_interval == every) == resets, move


def test_the_online_estimators_state_is_one_slotted_object():
    """OnlineEstimator carries nothing but its OnlineState (estimator.online_state), a slotted
    dataclass: every step is a function of it, and a copy of it is a copy of the estimator."""
    import copy

    from estimator.online_state import OnlineState

    sc = simulate(np.random.default_rng(9), n_users=3, n_keyframes=40, noise=NOISE)
    on = OnlineEstimator(3, sc.user_up_m, NOISE)
    for kf in sc.keyframes[:30]:
        on.add_keyframe(kf)
    assert vars(on) == {"state": on.state} and isinstance(on.state, OnlineState)
    assert not hasattr(on.state, "__dict__")
    twin = OnlineEstimator(3, sc.user_up_m, NOISE)
    twin.state = copy.deepcopy(on.state)
    for kf in sc.keyframes[30:]:
        a, b = on.add_keyframe(kf), twin.add_keyframe(kf)
        np.testing.assert_array_equal(a.users_enu_m, b.users_enu_m)
    assert on.n_keyframes_seen == twin.n_keyframes_seen == 40
