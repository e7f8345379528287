"""The information objective, the CasADi/IPOPT planner, greedy and oracle."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.noise import NoiseModel
from estimator.types import ModelState
from planner import REASON_TARGET, PlanningConstraints, PlanningState, make_planner
from planner import active as active_mod
from planner.active import _Layout, objective_function, pack_params
from planner.geometry import convex_cell, in_free_space, leg_violations, point_in_polygon
from planner.information import (
    PRIOR_EPS_PER_M2,
    PredictionModel,
    hypotheses_from_estimate,
    joint_prior_info,
    objective_values,
    position_information,
    predicted_information,
    prior_value,
    quadrature_points,
)
from planner.objective import E_GAP_EPS, Shape, goal_values
from tests.test_planner import fake_estimate, u_constraints
from uavloc.errors import PlannerError

NOISE = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0, range_a_m=0.4, range_b_per_m=0.008)


def _estimate_two_users(ambiguous: bool = True):
    return fake_estimate(
        [[-70, 60, 0], [70, 40, 0]],
        np.array([[[30.0, 8.0], [8.0, 6.0]], [[4.0, 0.0], [0.0, 9.0]]]),
        ambiguous=[ambiguous, False],
        mirror=[[-50, 75, 0], [np.nan] * 3],
    )


def with_bias(est, joint_blocks, bias_m=None, active=None):
    """`est` with range biases estimated: (Ka, d+1, d+1) joint covariance blocks of the active users
    (position block = est.cov_users_m2[k], bias last) laid out as the estimator's cov_theta_joint,
    with a cross-user covariance between consecutive active users so per-user blocks are picked."""
    from dataclasses import replace

    blocks = np.asarray(joint_blocks, dtype=float)
    na, p = blocks.shape[0], blocks.shape[1]
    active = np.ones(est.n_users, bool) if active is None else np.asarray(active, bool)
    assert active.sum() == na
    joint = np.zeros((na * p, na * p))
    for j in range(na):
        joint[j * p:(j + 1) * p, j * p:(j + 1) * p] = blocks[j]
        if j:
            joint[j * p, (j - 1) * p] = joint[(j - 1) * p, j * p] = 0.1  # a small cross-user term
    for j, k in enumerate(np.flatnonzero(active)):
        np.testing.assert_allclose(blocks[j, :p - 1, :p - 1], est.cov_users_m2[k])
    bias = np.where(active, 4.0, np.nan) if bias_m is None else np.asarray(bias_m, dtype=float)
    return replace(est, bias_m=bias, state=ModelState(active=active, cov_theta_joint=joint,
                                                       noise_scale=np.ones(est.n_users)))


def _estimate_two_users_bias(ambiguous: bool = True):
    est = _estimate_two_users(ambiguous)
    b0 = np.block([[est.cov_users_m2[0], np.array([[6.0], [-3.0]])], [np.array([[6.0, -3.0, 25.0]])]])
    b1 = np.block([[est.cov_users_m2[1], np.array([[1.5], [4.0]])], [np.array([[1.5, 4.0, 9.0]])]])
    return with_bias(est, [b0, b1])


def _casadi_objective(planner, state, hyp, lam, n_planes=0):
    goal = planner.goal(hyp)
    lay = _Layout(Shape(hyp.dim, hyp.bias, planner.criterion, 1, planner.n_quad), hyp.sample_w.size,
                  planner.max_planes, goal=goal is not None)
    fun = objective_function(lay)
    c = planner.constraints
    par = pack_params(lay, state.uav_enu_m, hyp, planner.noise, c.delta_m, prior_value(hyp, planner.criterion, goal),
                      lam, np.zeros((0, 2)), np.zeros(0), c.home_enu_m, c.return_factor, goal)
    return lambda p: tuple(np.asarray(v, dtype=float).ravel() for v in fun(p, par))


@pytest.mark.parametrize("criterion", ["A", "D", "E"])
@pytest.mark.parametrize("ambiguous", [True, False])
@pytest.mark.parametrize("bias", [False, True])
def test_casadi_objective_and_gradient_match_the_numpy_reference(criterion, ambiguous, bias):
    planner = make_planner("casadi", u_constraints(), NOISE, criterion=criterion)
    est = _estimate_two_users_bias(ambiguous) if bias else _estimate_two_users(ambiguous)
    state = PlanningState([0.0, -60.0, 30.0], est)
    hyp = planner.hypotheses(state)
    assert hyp.bias is bias and hyp.n_par == 2 + bias
    lam = 0.003
    f = _casadi_objective(planner, state, hyp, lam)
    rng = np.random.default_rng(7)
    for _ in range(5):
        p = state.uav_enu_m + rng.uniform([-50, -30, -15], [50, 50, 25])
        value, grad = f(p)
        ref = planner.evaluate(state, p[None], hyp, lam)[0]
        assert value[0] == pytest.approx(ref, rel=1e-9)
        # central differences of the numpy reference
        h = 1e-4
        ev = lambda q: planner.evaluate(state, q[None], hyp, lam)[0]  # noqa: E731
        fd = [(ev(p + e) - ev(p - e)) / (2 * h) for e in np.eye(3) * h]
        np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("criterion", ["A", "D"])
@pytest.mark.parametrize("bias", [False, True])
def test_three_dimensional_users_objective_matches_reference(criterion, bias):
    est = fake_estimate([[10, 40, 0]], np.eye(2))
    cov3 = np.diag([4.0, 2.0, 9.0])[None]
    from dataclasses import replace

    est3 = replace(est, cov_users_m2=cov3, info_users=np.linalg.inv(cov3[0]))
    if bias:
        joint = np.array([[4.0, 0, 0, 1.0], [0, 2.0, 0, 0.5], [0, 0, 9.0, -2.0], [1.0, 0.5, -2.0, 16.0]])
        est3 = with_bias(est3, [joint])
    planner = make_planner("casadi", u_constraints(), NOISE, criterion=criterion)
    state = PlanningState([0.0, -60.0, 30.0], est3)
    hyp = planner.hypotheses(state)
    assert hyp.dim == 3 and hyp.n_par == 3 + bias
    f = _casadi_objective(planner, state, hyp, 0.0)
    p = np.array([30.0, -20.0, 20.0])
    value, grad = f(p)
    assert value[0] == pytest.approx(planner.evaluate(state, p[None], hyp, 0.0)[0], rel=1e-9)
    ev = lambda q: planner.evaluate(state, q[None], hyp, 0.0)[0]  # noqa: E731
    fd = [(ev(p + e) - ev(p - e)) / 2e-4 for e in np.eye(3) * 1e-4]
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("ambiguous", [True, False])
def test_bias_prior_is_the_inverse_joint_block_and_its_schur_complement_the_position_information(ambiguous):
    est = _estimate_two_users_bias(ambiguous)
    hyp = hypotheses_from_estimate(est)
    p = 3
    joint = est.state.cov_theta_joint
    for k in range(2):
        block = joint[k * p:(k + 1) * p, k * p:(k + 1) * p]
        np.testing.assert_allclose(joint_prior_info(est, k), np.linalg.inv(block) + PRIOR_EPS_PER_M2 * np.eye(3),
                                   rtol=1e-9)
        # the position information of the prior is the estimator's position marginal (up to ε)
        pos = position_information(hyp.prior_info[k, 0], True)
        np.testing.assert_allclose(pos, np.linalg.inv(est.cov_users_m2[k]), rtol=0, atol=3 * PRIOR_EPS_PER_M2)
    if ambiguous:
        # the mirror's prior: positions reflected, the bias not
        n = (est.mirror_enu_m[0] - est.users_enu_m[0])[:2]
        n /= np.linalg.norm(n)
        R = np.eye(3)
        R[:2, :2] -= 2 * np.outer(n, n)
        np.testing.assert_allclose(hyp.prior_info[0, 3], R @ hyp.prior_info[0, 0] @ R.T, rtol=1e-12)


def test_bias_prior_follows_the_active_layout_and_falls_back_without_a_joint_covariance():
    from dataclasses import replace

    base = fake_estimate([[-70, 60, 0], [0, 0, 0], [70, 40, 0]], np.diag([4.0, 9.0]))
    base = replace(base, users_enu_m=np.array([[-70, 60, 0], [np.nan] * 3, [70, 40, 0]]),
                   cov_users_m2=np.array([np.diag([4.0, 9.0]), np.full((2, 2), np.inf), np.diag([4.0, 9.0])]))
    blocks = [np.diag([4.0, 9.0, 16.0]), np.array([[4.0, 0, 2.0], [0, 9.0, -1.0], [2.0, -1.0, 25.0]])]
    est = with_bias(base, blocks, active=[True, False, True])
    hyp = hypotheses_from_estimate(est)
    assert hyp.index.tolist() == [0, 2] and hyp.bias
    np.testing.assert_allclose(hyp.prior_info[1, 0], np.linalg.inv(blocks[1]) + PRIOR_EPS_PER_M2 * np.eye(3))
    # no joint covariance: the position marginal's information, ε for the bias, uncorrelated
    bare = replace(est, state=None)
    P = joint_prior_info(bare, 2)
    np.testing.assert_allclose(P[:2, :2], np.diag([1 / 4, 1 / 9]) + PRIOR_EPS_PER_M2 * np.eye(2))
    assert P[2, 2] == PRIOR_EPS_PER_M2 and np.all(P[:2, 2] == 0)
    assert np.isfinite(prior_value(hypotheses_from_estimate(bare), "E"))


def _dense_bias_objective(start, path, hyp, criterion, n_quad, delta=2.0, smooth_e=True, coverage_m=np.inf):
    """Brute force: per user and sample, the full joint (position, bias) information from explicit
    Jacobians [−g; 1], inverted densely; f of the position block of the covariance. Beyond the
    cell's reach R a point's ranges count c(d) = 1 / (1 + exp((d − R)/10 m))."""
    pts, lengths = quadrature_points(start, path[None], n_quad)
    n_meas = np.repeat(lengths[0] / (delta * n_quad), n_quad)
    K, M = hyp.sample_w.shape
    total = 0.0
    for k in range(K):
        for m in range(M):
            if hyp.sample_w[k, m] == 0.0:
                continue
            J = hyp.prior_info[k, m].copy()
            for q, pt in enumerate(pts[0]):
                diff = pt - hyp.users_enu_m[k, m]
                dist = np.sqrt(diff @ diff + 1e-9)
                h = np.array([*(-diff[:2] / dist), 1.0])
                cut = 1.0 if not np.isfinite(coverage_m) else 1.0 / (1.0 + np.exp((dist - coverage_m) / 10.0))
                J += cut * n_meas[q] * np.outer(h, h) / (NOISE.range_sigma_m(dist) ** 2 + NOISE.sigma_gps_m**2)
            cov = np.linalg.inv(J)[:2, :2]
            if criterion == "E" and smooth_e:
                # the planner's E: 1/sqrt(λ_min) of the position information with the gap smoothed by
                # E_GAP_EPS·tr² (λ_min = (tr − gap)/2, gap = λ_max − λ_min)
                lam = np.linalg.eigvalsh(np.linalg.inv(cov))
                tr, gap = lam.sum(), lam[1] - lam[0]
                f = {"E": 1 / np.sqrt(0.5 * (tr - np.sqrt(gap**2 + E_GAP_EPS * tr**2)))}
            else:
                f = {"A": np.trace(cov), "D": np.linalg.slogdet(cov)[1], "E": np.sqrt(np.linalg.eigvalsh(cov)[-1])}
            total += hyp.user_w[k] * hyp.sample_w[k, m] * f[criterion]
    return total


@pytest.mark.parametrize("coverage_m", [np.inf, 90.0])
@pytest.mark.parametrize("criterion", ["A", "D", "E"])
def test_bias_objective_equals_a_brute_force_dense_computation(criterion, coverage_m):
    hyp = hypotheses_from_estimate(_estimate_two_users_bias(True))
    start = np.array([0.0, -60.0, 30.0])
    rng = np.random.default_rng(3)
    model = PredictionModel(NOISE, 2.0, 8, coverage_m)
    for _ in range(4):
        path = start + rng.uniform([-50, -30, -15], [50, 50, 25], size=(2, 3)).cumsum(axis=0)
        got = objective_values(start, path[None], hyp, model, criterion)[0]
        assert got == pytest.approx(_dense_bias_objective(start, path, hyp, criterion, 8, coverage_m=coverage_m),
                                    rel=1e-9)
        # the reference prediction (planner.information) cuts the same ranges
        info, _ = predicted_information(start, path[None], hyp, model)
        pos = position_information(info[0], hyp.bias)
        ref = sum(hyp.user_w[k] * hyp.sample_w[k, m] * _reference_criterion(pos[k, m], criterion)
                  for k in range(pos.shape[0]) for m in range(pos.shape[1]) if hyp.sample_w[k, m] > 0)
        assert got == pytest.approx(ref, rel=1e-6)
        if not np.isfinite(coverage_m):
            continue
        assert got != pytest.approx(objective_values(start, path[None], hyp, PredictionModel(NOISE, 2.0, 8),
                                                     criterion)[0], rel=1e-6)
        assert prior_value(hyp, criterion) == pytest.approx(
            _dense_bias_objective(start, np.repeat(start[None], 2, axis=0), hyp, criterion, 8), rel=1e-9)
        if criterion == "E":  # and the unsmoothed semi-major axis sqrt(λ_max(Σ_pos)) to ~1e-5
            assert got == pytest.approx(_dense_bias_objective(start, path, hyp, "E", 8, smooth_e=False,
                                                              coverage_m=coverage_m), rel=1e-5)


@pytest.mark.parametrize("criterion", ["A", "D", "E"])
def test_with_a_bias_a_leg_over_the_user_beats_a_leg_at_constant_distance(criterion):
    """A user well known east-west, poorly north-south, with an unknown range bias. A 40 m leg
    60 m north of it (all ranges nearly along north at nearly the same distance) would measure its
    north coordinate well if there were no bias; with one, a shift north is almost a constant range
    change, i.e. a bias, so it learns little. A 40 m leg passing right over it (distances 30–36 m,
    ranges from both sides and from above) separates the two."""
    est = fake_estimate([[0, 0, 0]], np.diag([1.0, 25.0]))
    est_b = with_bias(est, [np.diag([1.0, 25.0, 25.0])])
    planner = make_planner("casadi", u_constraints(), NOISE, criterion=criterion)
    far = (np.array([-20.0, 60.0, 30.0]), np.array([[20.0, 60.0, 30.0]]))
    over = (np.array([0.0, -20.0, 30.0]), np.array([[0.0, 20.0, 30.0]]))

    def value(est_, leg):
        state = PlanningState(leg[0], est_)
        return planner.evaluate(state, leg[1], planner.hypotheses(state), 0.0)[0]

    assert value(est_b, over) < value(est_b, far)
    assert value(est, far) < value(est, over)
    # the far leg gains much less with the bias than without
    assert 1 - value(est_b, far) < 0.5 * (1 - value(est, far))


def test_plans_with_a_bias_estimate_and_caches_a_bias_layout():
    c = u_constraints()
    planner = make_planner("casadi", c, NOISE)
    state = PlanningState([0.0, -60.0, 30.0], _estimate_two_users_bias())
    r = planner.plan(state)
    assert not r.done and np.isfinite(r.objective) and r.status.startswith(("ipopt", "ring"))
    assert leg_violations(c, state.uav_enu_m, r.waypoint_enu_m, c.budget_m) == []
    assert any(lay.shape.bias for lay in active_mod._SOLVERS)


def test_quadrature_matches_a_dense_sum_of_measurements():
    """Q = 8 quadrature points are within 1 % of summing ℓ/Δ = 30 evenly spread measurements (at
    (i − ½)Δ; where along the leg the Δ-trigger fires depends on the previous leg)."""
    est = fake_estimate([[20, 30, 0]], np.eye(2) * 1e6)
    hyp = hypotheses_from_estimate(est, sigma_points="none")
    start, end = np.array([-30.0, 0.0, 25.0]), np.array([30.0, 0.0, 25.0])
    info, _ = predicted_information(start, end[None, None], hyp, PredictionModel(NOISE, 2.0, 8))
    length = np.linalg.norm(end - start)
    s = (np.arange(1, int(length / 2.0) + 1) - 0.5) * 2.0
    pts = start + (end - start) * (s / length)[:, None]
    diff = pts - hyp.users_enu_m[0, 0]
    d = np.linalg.norm(diff, axis=1)
    g = diff[:, :2] / d[:, None]
    dense = hyp.prior_info[0, 0] + np.einsum("n,ni,nj->ij", 1 / (NOISE.range_sigma_m(d) ** 2 + 1.0), g, g)
    np.testing.assert_allclose(info[0, 0, 0], dense, rtol=0.01)


def test_mirror_hypotheses_share_the_weight():
    hyp = hypotheses_from_estimate(_estimate_two_users(True))
    np.testing.assert_allclose(hyp.sample_w.sum(axis=1), 1.0)
    # user 0: its mean and its mirror each carry half; user 1 (not ambiguous) has no second set
    assert hyp.users_enu_m.shape[1] == 6
    assert hyp.sample_w[0, :3].sum() == pytest.approx(0.5) and hyp.sample_w[0, 3:].sum() == pytest.approx(0.5)
    np.testing.assert_allclose(hyp.users_enu_m[0, 3], [-50, 75, 0])
    assert hyp.sample_w[1, 3:].sum() == 0.0


def _random_setting(seed: int):
    """A random non-convex fence (U or L) with 0–2 no-fly squares, a free start and an estimate."""
    rng = np.random.default_rng(seed)
    w, h = rng.uniform(120, 200, 2)
    a, notch_w = rng.uniform(-0.3, 0.1) * w, rng.uniform(30, 60)
    fence = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [a + notch_w, h / 2],
                      [a + notch_w, rng.uniform(-0.2, 0.2) * h], [a, rng.uniform(-0.2, 0.2) * h], [a, h / 2],
                      [-w / 2, h / 2]])
    zones = []
    for _ in range(rng.integers(0, 3)):
        centre, side = rng.uniform(-0.4, 0.4, 2) * [w, h], rng.uniform(10, 30)
        zones.append(centre + side / 2 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]))
    c = PlanningConstraints(home_enu_m=np.zeros(3), fence_enu_m=fence, no_fly_enu_m=tuple(zones), alt_min_m=10.0,
                            alt_max_m=60.0, cruise_alt_m=30.0, leg_max_m=rng.uniform(30, 70),
                            max_distance_m=rng.uniform(80, 150), budget_m=5000.0)
    while True:
        x = np.array([*rng.uniform(-0.5, 0.5, 2) * [w, h], rng.uniform(10, 60)])
        if in_free_space(x[:2], c) and np.linalg.norm(x[:2]) < c.max_distance_m:
            break
    users = np.column_stack([rng.uniform(-0.5, 0.5, (3, 2)) * [w, h], np.zeros(3)])
    est = fake_estimate(users, np.diag(rng.uniform(1, 40, 2)), ambiguous=[True, False, False],
                        mirror=[users[0] + [15, -10, 0], [np.nan] * 3, [np.nan] * 3])
    return c, x, est


def _free_along(c: PlanningConstraints, a: np.ndarray, b: np.ndarray) -> bool:
    """Independent dense check: every 0.2 m of the leg inside the fence and outside the zones."""
    t = np.linspace(0, 1, int(np.linalg.norm(b - a) / 0.2) + 2)[:, None]
    pts = a[:2] + t * (b[:2] - a[:2])
    ok = point_in_polygon(pts, c.fence_enu_m).all()
    return bool(ok and not any(point_in_polygon(pts, z).any() for z in c.no_fly_enu_m))


@pytest.mark.parametrize("seed", range(12))
def test_constraints_hold_on_randomized_non_convex_scenarios(seed):
    c, x, est = _random_setting(seed)
    planner = make_planner("casadi", c, NOISE, rng_seed=seed)
    flown = 0.0
    for _ in range(3):
        r = planner.plan(PlanningState(x, est, flown, energy_remaining_m=4000.0))
        if r.done:
            break
        wp = r.waypoint_enu_m
        assert leg_violations(c, x, wp, c.budget_m - flown, 4000.0) == []
        assert _free_along(c, x, wp)
        assert np.linalg.norm(wp - x) <= c.leg_max_m + 1e-6
        assert c.alt_min_m - 1e-9 <= wp[2] <= c.alt_max_m + 1e-9
        assert np.linalg.norm(wp[:2] - c.home_enu_m[:2]) <= c.max_distance_m + 1e-6
        flown += float(np.linalg.norm(wp - x))
        x = wp


def test_convex_cells_of_random_scenarios_stay_free():
    for seed in range(6):
        c, x, _ = _random_setting(seed)
        rng = np.random.default_rng(seed)
        seed_end = x[:2] + rng.normal(size=2) * 3
        if not _free_along(c, np.array([*x[:2], 0]), np.array([*seed_end, 0])):
            continue
        A, off = convex_cell(c, x[:2], seed_end, max_planes=64)
        pts = x[:2] + rng.uniform(-80, 80, size=(400, 2))
        for p in pts[np.all(pts @ A.T <= off, axis=1)][:40]:
            assert _free_along(c, np.array([*x[:2], 0]), np.array([*p, 0]))


def _ring_best_setting(seed: int):
    """A one-waypoint casadi planner on a random setting, with its hypotheses, cost per metre and
    the best objective among the feasible ring candidates."""
    c, x, est = _random_setting(seed)
    planner = make_planner("casadi", c, NOISE, horizon=1)
    state = PlanningState(x, est, 0.0)
    hyp = planner.hypotheses(state)
    ring = planner.feasible_ring(state)
    unc = planner.uncertainty(state, ring, hyp)
    lam = planner.cost_per_m(unc)
    return planner, state, hyp, lam, float(np.min(unc + lam * np.linalg.norm(ring - x, axis=1)))


@pytest.mark.parametrize("seed", range(6))
def test_choice_is_at_least_as_good_as_the_best_ring_candidate(seed):
    planner, state, hyp, lam, ring_best = _ring_best_setting(100 + seed)
    r = planner.plan(state)
    chosen = planner.evaluate(state, r.waypoint_enu_m[None], hyp, lam)[0]
    assert chosen <= ring_best + 1e-12
    assert r.objective == pytest.approx(chosen)


def test_ipopt_improves_on_the_ring_somewhere():
    """The continuous solve must beat the coarse ring strictly in most random settings."""
    better = 0
    for seed in range(6):
        planner, state, _, _, ring_best = _ring_best_setting(200 + seed)
        r = planner.plan(state)
        better += r.status == "ipopt" and r.objective < ring_best - 1e-6
    assert better >= 4


def test_ipopt_failure_falls_back_to_the_best_feasible_ring_candidate(monkeypatch):
    c = u_constraints()
    planner = make_planner("casadi", c, NOISE, horizon=1)

    def broken(*args, **kwargs):
        raise RuntimeError("simulated IPOPT crash")

    monkeypatch.setattr(planner, "_ipopt", broken)
    state = PlanningState([0.0, -60.0, 30.0], _estimate_two_users())
    r = planner.plan(state)
    assert r.status == "ring" and not r.done
    assert leg_violations(c, state.uav_enu_m, r.waypoint_enu_m, c.budget_m) == []
    hyp = planner.hypotheses(state)
    ring = planner.feasible_ring(state)
    unc = planner.uncertainty(state, ring, hyp)
    lam = planner.cost_per_m(unc)
    assert r.objective == pytest.approx(np.min(unc + lam * np.linalg.norm(ring - state.uav_enu_m, axis=1)))


def test_an_infeasible_ipopt_answer_is_never_returned(monkeypatch):
    c = u_constraints()
    planner = make_planner("casadi", c, NOISE)
    monkeypatch.setattr(planner, "_ipopt", lambda *a, **k: (np.array([[0.0, 0.0, 30.0]]), "Solve_Succeeded"))
    state = PlanningState([0.0, -60.0, 30.0], _estimate_two_users())
    r = planner.plan(state)
    assert not np.allclose(r.waypoint_enu_m, [0.0, 0.0, 30.0])  # (0, 0) is in the notch of the U
    assert leg_violations(c, state.uav_enu_m, r.waypoint_enu_m, c.budget_m) == []


def test_explores_with_turning_legs_before_any_user_is_initialised():
    c = u_constraints()
    planner = make_planner("casadi", c, NOISE)
    x0 = np.array([0.0, -60.0, 30.0])
    r1 = planner.plan(PlanningState(x0, None))
    r2 = planner.plan(PlanningState(r1.waypoint_enu_m, None, 60.0))
    assert r1.status == r2.status == "explore"
    d1, d2 = (r1.waypoint_enu_m - x0)[:2], (r2.waypoint_enu_m - r1.waypoint_enu_m)[:2]
    cos = d1 @ d2 / np.linalg.norm(d1) / np.linalg.norm(d2)
    assert cos < np.cos(np.radians(45))  # the second leg turns: no collinear track, no mirror


def test_done_when_every_user_meets_the_target():
    c = u_constraints(target_radius_m=1.0)
    est = fake_estimate([[-70, 60, 0]], np.eye(2) * 0.01)
    r = make_planner("casadi", c, NOISE).plan(PlanningState([0.0, -60.0, 30.0], est))
    assert r.done and r.reason == REASON_TARGET


def test_oracle_needs_truth_and_plans_at_it():
    c = u_constraints()
    with pytest.raises(PlannerError, match="true_users_enu_m"):
        make_planner("oracle", c, NOISE)
    oracle = make_planner("oracle", c, NOISE, true_users_enu_m=[[-70, 60, 0], [70, 40, 0]])
    r = oracle.plan(PlanningState([0.0, -60.0, 30.0], None))
    assert r.status in ("ipopt", "ring") and not r.done


def test_greedy_picks_the_best_full_leg_heading():
    c = u_constraints()
    greedy = make_planner("greedy", c, NOISE)
    state = PlanningState([0.0, -60.0, 30.0], _estimate_two_users(False))
    r = greedy.plan(state)
    assert np.linalg.norm(r.waypoint_enu_m - state.uav_enu_m) == pytest.approx(c.leg_max_m, rel=1e-6)
    hyp = greedy.hypotheses(state)
    theta = np.radians(np.arange(0, 360, 5))
    ends = state.uav_enu_m + c.leg_max_m * np.column_stack([np.cos(theta), np.sin(theta), 0 * theta])
    ok = np.array([not leg_violations(c, state.uav_enu_m, e, c.budget_m) for e in ends])
    fine = objective_values(state.uav_enu_m, ends[ok], hyp, PredictionModel(NOISE, c.delta_m, greedy.n_quad))
    # the 15° ring is within a few percent of a 5° search
    assert r.objective <= 1.05 * fine.min() / prior_value(hyp)


def test_solver_cache_is_reused():
    planner = make_planner("casadi", u_constraints(), NOISE)
    state = PlanningState([0.0, -60.0, 30.0], _estimate_two_users())
    planner.plan(state)
    n = len(active_mod._SOLVERS)
    planner.plan(state)
    assert len(active_mod._SOLVERS) == n


def test_a_diverged_user_estimate_is_ignored_and_the_leg_stays_feasible():
    c = u_constraints()
    noise = NoiseModel(range_s0_m=3.0, range_a_m=0.3, range_b_per_m=0.01)  # exp(b·d) overflows at the diverged user
    est = fake_estimate([[-70, 60, 0], [33772.8, 98530.2, 0]], np.eye(2) * 50.0, ambiguous=[True, False],
                        mirror=[[28915.1, -3836.9, 0], [np.nan] * 3])
    planner = make_planner("casadi", c, noise)
    state = PlanningState([0.0, -60.0, 30.0], est)
    hyp = planner.hypotheses(state)
    assert hyp.index.tolist() == [0] and hyp.users_enu_m.shape[1] == 3  # no far user, no far mirror
    r = planner.plan(state)
    assert not r.done and np.isfinite(r.objective)
    assert leg_violations(c, state.uav_enu_m, r.waypoint_enu_m, c.budget_m) == []


@pytest.mark.parametrize("name", ["casadi", "greedy", "lawnmower", "circle", "random"])
def test_no_fence_and_little_energy_left(name):
    c = u_constraints(fence_enu_m=np.zeros((0, 2)), no_fly_enu_m=())
    x = np.array([80.0, 40.0, 30.0])
    energy = 1.2 * np.linalg.norm(x - c.home_enu_m) + 40.0  # 40 m to spare beyond the way home
    r = make_planner(name, c, NOISE).plan(PlanningState(x, _estimate_two_users(), 0.0, energy_remaining_m=energy))
    assert not r.done
    wp = r.waypoint_enu_m
    assert leg_violations(c, x, wp, c.budget_m, energy) == []
    assert np.linalg.norm(wp - x) + c.return_factor * np.linalg.norm(wp - c.home_enu_m) <= energy + 1e-6


@pytest.mark.parametrize("bias", [False, True])
def test_horizon_objective_gradient_and_feasibility(bias):
    c = u_constraints()
    planner = make_planner("casadi", c, NOISE, horizon=3, criterion="E")
    state = PlanningState([0.0, -60.0, 30.0], _estimate_two_users_bias() if bias else _estimate_two_users())
    hyp = planner.hypotheses(state)
    goal = planner.goal(hyp)
    assert goal is not None
    lay = _Layout(Shape(hyp.dim, hyp.bias, "E", 3, planner.n_quad), hyp.sample_w.size, planner.max_planes, goal=True)
    fun = objective_function(lay)
    par = pack_params(lay, state.uav_enu_m, hyp, NOISE, c.delta_m, prior_value(hyp, "E", goal), 0.002,
                      np.zeros((0, 2)), np.zeros(0), c.home_enu_m, c.return_factor, goal)
    path = np.array([[-30.0, -70.0, 20.0], [-70.0, -40.0, 25.0], [-70.0, 10.0, 15.0]])
    value, grad = (np.asarray(v, dtype=float).ravel() for v in fun(path.ravel(), par))
    ev = lambda z: planner.evaluate(state, z.reshape(1, 3, 3), hyp, 0.002)[0]  # noqa: E731
    assert value[0] == pytest.approx(ev(path.ravel()), rel=1e-9)
    fd = [(ev(path.ravel() + e) - ev(path.ravel() - e)) / 2e-4 for e in np.eye(9) * 1e-4]
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-9)
    r = planner.plan(state)
    assert r.horizon_enu_m.shape == (3, 3) and np.allclose(r.horizon_enu_m[0], r.waypoint_enu_m)
    prev = state.uav_enu_m
    for wp in r.horizon_enu_m:
        assert _free_along(c, prev, wp) and np.linalg.norm(wp - prev) <= c.leg_max_m + 1e-6
        prev = wp
    # never worse than its own greedy ring-seeded horizon
    unc = planner.uncertainty(state, planner.feasible_ring(state), hyp)
    lam = planner.cost_per_m(unc)
    ring = planner.feasible_ring(state)
    vals = unc + lam * np.linalg.norm(ring - state.uav_enu_m, axis=1)
    seed = planner._extend(state, planner._seed_ends(state, ring, vals)[0], hyp, lam)
    assert r.objective <= planner.evaluate(state, seed[None], hyp, lam)[0] + 1e-12


def test_three_dimensional_users_fall_back_to_a_optimal():
    from dataclasses import replace

    est = fake_estimate([[10, 40, 0]], np.eye(2))
    cov3 = np.diag([4.0, 2.0, 9.0])[None]
    planner = make_planner("casadi", u_constraints(), NOISE)  # default criterion "E"
    r = planner.plan(PlanningState([0.0, -60.0, 30.0], replace(est, cov_users_m2=cov3, info_users=cov3[0])))
    assert planner.criterion == "A" and not r.done


def test_predicted_information_uses_each_users_noise_scale():
    """A user the estimator found 2× noisier than σ(d) gains information at (2σ)² + σ_gps²."""
    from dataclasses import replace

    est = fake_estimate([[20, 30, 0]], np.eye(2) * 1e6)
    est = replace(est, state=ModelState(active=np.ones(1, dtype=bool), cov_theta_joint=None,
                                        noise_scale=np.array([2.0])))
    hyp = hypotheses_from_estimate(est, sigma_points="none")
    assert hyp.noise_scale is not None and hyp.noise_scale[0] == 2.0
    start, end = np.array([-30.0, 0.0, 25.0]), np.array([30.0, 0.0, 25.0])
    info, _ = predicted_information(start, end[None, None], hyp, PredictionModel(NOISE, 2.0, 8))
    plain, _ = predicted_information(start, end[None, None], replace(hyp, noise_scale=None),
                                     PredictionModel(NOISE, 2.0, 8))
    pts = start + (end - start) * np.linspace(0, 1, 50)[:, None]
    d = np.linalg.norm(pts - hyp.users_enu_m[0, 0], axis=1)
    ratio = np.mean((NOISE.range_sigma_m(d) ** 2 + 1.0) / (4.0 * NOISE.range_sigma_m(d) ** 2 + 1.0))
    gain, gain_plain = info[0, 0, 0] - hyp.prior_info[0, 0], plain[0, 0, 0] - hyp.prior_info[0, 0]
    assert np.trace(gain) == pytest.approx(ratio * np.trace(gain_plain), rel=0.05)


def _reference_criterion(info: np.ndarray, criterion: str) -> float:
    """f of a position information by eigenvalues (the obvious way; E with the planner's smoothing)."""
    lam = np.linalg.eigvalsh(info)
    if criterion == "A":
        return float(np.sum(1 / lam))
    if criterion == "D":
        return float(-np.sum(np.log(lam)))
    tr, gap = lam.sum(), lam[-1] - lam[0]
    return float(1 / np.sqrt(0.5 * (tr - np.sqrt(gap**2 + E_GAP_EPS * tr**2))))


@pytest.mark.parametrize("criterion", ["A", "D", "E"])
@pytest.mark.parametrize("bias", [False, True])
def test_ipopts_objective_is_the_numpy_prediction_with_noise_scales(criterion, bias):
    """One objective: the function IPOPT minimises (its nlp_f), the planner's numpy prediction
    (`evaluate`) and the range factor's predicted information (planner.information's reference,
    estimator.factors' range model) agree to 1e-9, with a noise scale per user."""
    from dataclasses import replace

    est = _estimate_two_users_bias(True) if bias else _estimate_two_users(True)
    scale = np.array([2.5, 0.7])
    est = replace(est, state=replace(est.state, noise_scale=scale) if est.state is not None else
                  ModelState(active=np.ones(2, dtype=bool), cov_theta_joint=None, noise_scale=scale))
    planner = make_planner("casadi", u_constraints(), NOISE, criterion=criterion)
    state = PlanningState([0.0, -60.0, 30.0], est)
    hyp = planner.hypotheses(state)
    assert hyp.bias is bias and np.allclose(hyp.noise_scale, [2.5, 0.7])
    lam, c = 0.003, planner.constraints
    goal = planner.goal(hyp)
    assert (goal is not None) is (criterion == "E")
    lay = _Layout(Shape(hyp.dim, hyp.bias, criterion, planner.horizon, planner.n_quad), hyp.sample_w.size,
                  planner.max_planes, goal=goal is not None)
    norm = prior_value(hyp, criterion, goal)
    nlp_f = active_mod._solver(lay).get_function("nlp_f")
    par = pack_params(lay, state.uav_enu_m, hyp, NOISE, c.delta_m, norm, lam, np.zeros((0, 2)), np.zeros(0),
                      c.home_enu_m, c.return_factor, goal)
    rng = np.random.default_rng(11)
    for _ in range(4):
        path = state.uav_enu_m + rng.uniform([-50, -30, -15], [50, 50, 25], size=(planner.horizon, 3)).cumsum(axis=0)
        ipopt_f = float(nlp_f(x=path.ravel(), p=par)["f"])
        numpy_f = float(planner.evaluate(state, path[None], hyp, lam)[0])
        info, lengths = predicted_information(state.uav_enu_m, path[None], hyp, planner.prediction)
        pos = position_information(info[0], bias)
        K, M = hyp.sample_w.shape
        ref = sum(hyp.user_w[k] * hyp.sample_w[k, m] * goal_values(_reference_criterion(pos[k, m], criterion), goal)
                  for k in range(K) for m in range(M)) / norm + lam * lengths.sum()
        assert ipopt_f == pytest.approx(numpy_f, rel=1e-9, abs=1e-12)
        assert numpy_f == pytest.approx(ref, rel=1e-9)
    # the noise scale matters: without it the prediction differs
    plain = planner.evaluate(state, path[None], replace(hyp, noise_scale=None), lam)[0]
    assert abs(plain - numpy_f) > 1e-3 * abs(numpy_f)


def test_compiled_kernels_equal_the_interpreted_ones_and_the_reference_planner_agrees():
    """The compiled objective is the interpreted one (planner.objective), and the fast planner's first
    waypoint is the slow reference configuration's (casadi_reference) on a two-user state."""
    state = PlanningState([0.0, -60.0, 30.0], _estimate_two_users_bias(True))
    fast = make_planner("casadi", u_constraints(), NOISE)
    slow = make_planner("casadi_reference", u_constraints(), NOISE)
    assert (fast.compiled, fast.ipopt_seeds, slow.compiled, slow.ipopt_seeds, slow.max_iter) == (True, 1, False, 0, 60)
    hyp = fast.hypotheses(state)
    ring = fast.feasible_ring(state)
    np.testing.assert_allclose(fast.uncertainty(state, ring, hyp), slow.uncertainty(state, ring, hyp), rtol=1e-12)
    a, b = fast.plan(state), slow.plan(state)
    assert a.objective <= b.objective * (1 + 1e-3)
    assert np.linalg.norm(a.waypoint_enu_m - b.waypoint_enu_m) < 1.0


def test_precompile_builds_the_kernels_a_plan_needs_before_the_first_plan():
    from planner import objective

    planner = make_planner("casadi", u_constraints(), NOISE, precompile=True)
    for bias in (False, True):
        shape = Shape(2, bias, planner.criterion, planner.horizon, planner.n_quad)
        assert ("vgh", shape, True) in objective._KERNELS and ("value", shape, True) in objective._KERNELS
    built = set(objective._KERNELS)
    planner.plan(PlanningState([0.0, -60.0, 30.0], _estimate_two_users_bias(True)))
    assert {k for k in objective._KERNELS if k[0] != "prior"} == {k for k in built if k[0] != "prior"}


def test_the_mission_compiles_planner_kernels_outside_the_working_folder(tmp_path, monkeypatch):
    """CasADi's JIT keeps its C source in the current directory while a kernel lives (and leaves
    it there when the process is killed): not in the user's folder; in the kernel cache, or with
    the cache off in the system's temporary folder."""
    import casadi as ca

    from mission.kernel_cache import use_kernel_cache
    from planner import objective

    work, cache = tmp_path / "work", tmp_path / "cache"
    work.mkdir()
    monkeypatch.chdir(work)
    for setting in (str(cache), "off"):
        monkeypatch.setattr(objective, "compile_hook", objective.jit_function)
        monkeypatch.setenv("UAVLOC_KERNEL_CACHE", setting)
        assert use_kernel_cache() == (cache if setting != "off" else None)
        x = ca.SX.sym("x", 2)
        f = objective.compile_hook("uavloc_test_kernel", [x], [ca.sumsqr(x)])
        assert float(f([1.0, 2.0])) == 5.0
        assert list(work.iterdir()) == []
    # the library and its size and hash beside it (mission.kernel_cache)
    assert sorted(p.suffix for p in cache.iterdir() if not p.name.startswith(".")) == [".sha256", ".so"]


def test_a_campaign_spec_compiles_planner_kernels_outside_the_working_folder(tmp_path, monkeypatch):
    """Loading a spec builds each planner to check its options; with `precompile = true` that
    compiles the kernels, which must not land in the user's folder either (they did: 18 files in
    the working folder for as long as a campaign ran)."""
    from planner import objective
    from sitl_scenarios.campaign import load_spec

    monkeypatch.setattr(objective, "compile_hook", objective.jit_function)
    monkeypatch.setattr(objective, "_KERNELS", {})  # built anew, not taken from this process's cache
    monkeypatch.chdir(tmp_path)
    (tmp_path / "spec.toml").write_text(
        '[campaign]\nname = "jit"\nmode = "fast"\nseeds = [1]\nplanners = ["casadi"]\n\n'
        "[planner_options.casadi]\nprecompile = true\n\n"
        '[[scenarios]]\nfile = "three_users_nlos"\n'
    )
    load_spec(tmp_path / "spec.toml")
    assert objective._KERNELS, "the spec check compiled no kernel: the test tests nothing"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.toml"]
