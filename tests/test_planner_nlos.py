"""The planner's objective sees the NLoS shift (planner.objective, planner.information): the bearing
profile's fit against a slow reference, the objective against a dense computation, and a user seen
in NLoS from one side drawing the vehicle to its other side."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import minimize

from estimator.nlos_shift import NLOS_BEARING_RIDGE, nlos_bearing_logit
from estimator.types import ModelState
from planner import PlanningState, make_planner
from planner import active as active_mod
from planner.active import _Layout, pack_params
from planner.information import (
    PredictionModel,
    hypotheses_from_estimate,
    objective_values,
    position_information,
    predicted_information,
    predicted_nlos_var_m2,
    prior_value,
)
from planner.objective import E_GAP_EPS, Shape
from tests.test_planner import fake_estimate, u_constraints
from tests.test_planner_active import NOISE

#: NLoS from the west: p(β) = σ(−1 − 4 cos β), ~0.95 seen from due west, ~0.007 from due east
WEST_LOGIT = np.array([-1.0, -4.0, 0.0])


def _with_nlos(est, shift_m, pi0, logit):
    """`est` whose users carry an NLoS shift |δ| (K,), share π₀ (K,) and NLoS profile (K, 3) by
    bearing or (K, 4) by bearing and elevation (est's covariance holds the shift's ½ |δ|² on each
    horizontal axis, as the estimator's does)."""
    k = est.n_users
    st = est.state or ModelState(active=np.ones(k, dtype=bool), cov_theta_joint=None, noise_scale=np.ones(k))
    return replace(est, state=replace(st, nlos_shift_m=np.asarray(shift_m, float), nlos_prob_k=np.asarray(pi0, float),
                                      nlos_bearing_logit=np.asarray(logit, float).reshape(k, -1)))


def _one_user_west_nlos():
    est = fake_estimate([[0.0, 40.0, 0.0]], np.diag([22.0, 22.0]))  # 4 m² + ½ 6²
    return _with_nlos(est, [6.0], [0.3], [WEST_LOGIT])


def test_bearing_profile_fit_equals_a_general_purpose_minimiser():
    """Newton's method on the ridge-penalised logistic loss reaches scipy's BFGS minimum."""
    from estimator.problem import Problem

    rng = np.random.default_rng(5)
    n = 120
    bearing = rng.uniform(-np.pi, np.pi, n)
    run_m, up_m = rng.uniform(20.0, 150.0, n), rng.uniform(15.0, 80.0, n)
    x = np.column_stack([run_m * np.cos(bearing), run_m * np.sin(bearing), up_m])
    users = np.zeros((1, 3))
    sin_elev = up_m / np.hypot(run_m, up_m)
    # posterior NLoS probabilities high to the west and seen low (a blocker's shadow), noisy
    y = np.clip(1 / (1 + np.exp(-(1.0 - 3 * np.cos(bearing) - 4 * sin_elev))) + rng.normal(0, 0.05, n), 0, 1)
    prob = type("P", (), {"n_users": 1, "mask": np.ones((n, 1), bool)})()
    assert not isinstance(prob, Problem)  # only n_users and mask are read
    got = nlos_bearing_logit(prob, x, users, (1 - y)[None], np.array([2.0]))[0]

    phi = np.column_stack([np.ones(n), np.cos(bearing), np.sin(bearing), sin_elev])

    def loss(a):
        p = 1 / (1 + np.exp(-(phi @ a)))
        return -np.sum(y * np.log(p) + (1 - y) * np.log(1 - p)) + NLOS_BEARING_RIDGE * a @ a

    ref = minimize(loss, np.zeros(4), method="BFGS", options={"gtol": 1e-10}).x
    np.testing.assert_allclose(got, ref, atol=1e-5)
    assert got[1] < -1.0  # NLoS to the west: the cos β coefficient is strongly negative
    assert got[3] < -1.0  # ... and from low: the sin ε coefficient too
    # a user without a shift gets no profile
    assert np.all(nlos_bearing_logit(prob, x, users, (1 - y)[None], np.array([0.0])) == 0.0)


def _dense(start, path, hyp, model, criterion):
    """Σ w c f(I⁻¹ + v P_h) from the reference information and the reference shift variance."""
    info, _ = predicted_information(start, path[None], hyp, model)
    pos = position_information(info[0], hyp.bias)
    v = predicted_nlos_var_m2(start, path[None], hyp, model)[0]
    K, M = hyp.sample_w.shape
    total = 0.0
    for k in range(K):
        for m in range(M):
            cov = np.linalg.inv(pos[k, m]) + v[k, m] * np.eye(2)
            lam = np.linalg.eigvalsh(cov)
            if criterion == "E":
                # the planner's E: sqrt(1/λ_min(I) + v), λ_min with the gap smoothed by E_GAP_EPS·tr²
                li = np.linalg.eigvalsh(pos[k, m])
                tr, gap = li.sum(), li[1] - li[0]
                f = np.sqrt(1.0 / (0.5 * (tr - np.sqrt(gap**2 + E_GAP_EPS * tr**2))) + v[k, m])
            else:
                f = {"A": np.trace(cov), "D": np.sum(np.log(lam))}[criterion]
            total += hyp.user_w[k] * hyp.sample_w[k, m] * f
    return total


@pytest.mark.parametrize("criterion", ["A", "D", "E"])
def test_objective_with_an_nlos_shift_equals_a_dense_computation(criterion):
    est = _with_nlos(fake_estimate([[-70, 60, 0], [70, 40, 0]], np.array([np.diag([21.5, 16.5]), np.diag([3.0, 6.0])])),
                     [5.0, 0.0], [0.25, 0.0], [[*WEST_LOGIT, -3.0], np.zeros(4)])
    hyp = hypotheses_from_estimate(est, sigma_points="all")
    assert hyp.nlos is not None and np.all(hyp.nlos[1] == 0.0) and np.allclose(hyp.nlos[0, :, 5], 5.0 / 0.25)
    assert np.allclose(hyp.nlos[0, :, 6], -3.0)
    model = PredictionModel(NOISE, 2.0, 8)
    start = np.array([0.0, -60.0, 30.0])
    rng = np.random.default_rng(3)
    for _ in range(4):
        path = start + rng.uniform([-50, -30, -15], [50, 50, 25], size=(2, 3)).cumsum(axis=0)
        got = objective_values(start, path[None], hyp, model, criterion)[0]
        assert got == pytest.approx(_dense(start, path, hyp, model, criterion), rel=1e-9)
    # before flying, the shift is the estimate's: v = ½ |δ|²
    v0 = predicted_nlos_var_m2(start, np.repeat(start[None, None], 2, axis=1), hyp, model)[0]
    np.testing.assert_allclose(v0[0], 0.5 * 5.0**2, rtol=1e-6)
    assert prior_value(hyp, criterion) == pytest.approx(
        _dense(start, np.repeat(start[None], 2, axis=0), hyp, model, criterion), rel=1e-6)


def test_a_user_shadowed_from_low_elevations_is_seen_in_line_of_sight_from_higher_up():
    """With α₃ < 0 (the NLoS ranges were the low ones) the same leg flown higher leaves a smaller
    shift; with a profile by bearing alone (α₃ = 0), altitude does not change it."""
    model = PredictionModel(NOISE, 2.0, 8)
    start = np.array([-80.0, 40.0, 20.0])
    low, high = np.array([[[-80.0, 100.0, 20.0]]]), np.array([[[-80.0, 100.0, 80.0]]])
    start_high = np.array([-80.0, 40.0, 80.0])

    def shift_var(logit, s, path):
        est = _with_nlos(fake_estimate([[0.0, 40.0, 0.0]], np.diag([22.0, 22.0])), [6.0], [0.3], [logit])
        return predicted_nlos_var_m2(s, path, hypotheses_from_estimate(est, sigma_points="none"), model)[0, 0, 0]

    assert shift_var([*WEST_LOGIT, -4.0], start_high, high) < 0.9 * shift_var([*WEST_LOGIT, -4.0], start, low)
    assert shift_var(WEST_LOGIT, start_high, high) == pytest.approx(shift_var(WEST_LOGIT, start, low), rel=1e-9)


def test_ipopt_minimises_the_same_objective_with_an_nlos_shift():
    est = _one_user_west_nlos()
    planner = make_planner("casadi", u_constraints(), NOISE)
    state = PlanningState([0.0, -20.0, 30.0], est)
    hyp = planner.hypotheses(state)
    assert hyp.nlos is not None
    goal = planner.goal(hyp)
    lay = _Layout(Shape(hyp.dim, hyp.bias, planner.criterion, planner.horizon, planner.n_quad), hyp.sample_w.size,
                  planner.max_planes, goal=goal is not None)
    c = planner.constraints
    par = pack_params(lay, state.uav_enu_m, hyp, NOISE, c.delta_m, prior_value(hyp, planner.criterion, goal), 0.002,
                      np.zeros((0, 2)), np.zeros(0), c.home_enu_m, c.return_factor, goal)
    nlp_f = active_mod._solver(lay).get_function("nlp_f")
    rng = np.random.default_rng(2)
    for _ in range(3):
        path = state.uav_enu_m + rng.uniform([-40, -20, -10], [40, 40, 10], size=(planner.horizon, 3)).cumsum(axis=0)
        ipopt_f = float(nlp_f(x=path.ravel(), p=par)["f"])
        assert ipopt_f == pytest.approx(float(planner.evaluate(state, path[None], hyp, 0.002)[0]), rel=1e-9)


def test_a_user_seen_in_nlos_from_the_west_draws_the_vehicle_east():
    """Two legs that see the user alike (mirror images about its north-south line): without the
    shift they are worth the same; with NLoS from the west the eastern one shrinks the bound more,
    and the planner flies east of the user."""
    est = _one_user_west_nlos()
    square = np.array([[-100, -100], [100, -100], [100, 100], [-100, 100]], dtype=float)
    planner = make_planner("casadi", u_constraints(fence_enu_m=square, no_fly_enu_m=()), NOISE)
    east = (np.array([30.0, 20.0, 30.0]), np.array([[30.0, 60.0, 30.0]]))
    west = (np.array([-30.0, 20.0, 30.0]), np.array([[-30.0, 60.0, 30.0]]))

    def value(est_, leg):
        state = PlanningState(leg[0], est_)
        return planner.evaluate(state, leg[1], planner.hypotheses(state), 0.0)[0]

    plain = replace(est, state=None)
    assert value(plain, east) == pytest.approx(value(plain, west), rel=1e-9)
    assert value(est, east) < value(est, west) - 0.02
    # from due south of the user, symmetric but for the NLoS
    r = planner.plan(PlanningState([0.0, 10.0, 30.0], est))
    assert r.waypoint_enu_m[0] > 5.0, r
    # and with the NLoS from the east, west
    from_east = replace(est, state=replace(est.state, nlos_bearing_logit=(WEST_LOGIT * [1, -1, 1])[None]))
    r = make_planner("casadi", planner.constraints, NOISE).plan(PlanningState([0.0, 10.0, 30.0], from_east))
    assert r.waypoint_enu_m[0] < -5.0, r
