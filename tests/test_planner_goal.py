"""The objective's goal (planner.objective, "Goal"): each row counts through a smooth hinge at the stop
rule's target, so a user already inside it pulls the vehicle nowhere; its derivatives against
central differences, IPOPT's Hessian with it against differences of IPOPT's gradient."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.types import CHI2_2DOF_95
from planner import PlanningState, make_planner
from planner import active as active_mod
from planner.active import _Layout, pack_params
from planner.information import PredictionModel, hypotheses_from_estimate, objective_values, prior_value
from planner.objective import Shape, goal_function, goal_values
from tests.test_planner import fake_estimate, u_constraints
from tests.test_planner_active import NOISE, _estimate_two_users

GOAL = np.array([1.2, 0.12])


@pytest.mark.parametrize("f", [0.3, 1.0, 1.15, 1.2, 1.31, 2.0, 9.0])
def test_hinge_derivatives_equal_central_differences(f):
    g, d1, d2 = (float(v) for v in goal_function()(f, GOAL))
    h = 1e-5
    g_at = lambda x: float(goal_function()(x, GOAL)[0])  # noqa: E731
    assert d1 == pytest.approx((g_at(f + h) - g_at(f - h)) / (2 * h), rel=1e-6, abs=1e-9)
    d1_at = lambda x: float(goal_function()(x, GOAL)[1])  # noqa: E731
    assert d2 == pytest.approx((d1_at(f + h) - d1_at(f - h)) / (2 * h), rel=1e-5, abs=1e-9)
    assert g == pytest.approx(float(goal_values(np.array([f]), GOAL)[0]), rel=1e-12, abs=1e-15)


@pytest.mark.parametrize(("f", "g"), [(9.0, 9.0 - 1.2), (1.2, 0.12 * np.log(2.0)), (0.0, 0.0)])
def test_hinge_is_the_excess_over_the_target_far_from_it(f, g):
    assert float(goal_values(np.array([f]), GOAL)[0]) == pytest.approx(g, abs=1e-4)
    assert np.array_equal(goal_values(np.array([f]), None), [f])


def test_goal_is_the_stop_rules_target_in_criterion_units_and_only_while_a_bound_is_above_it():
    c = u_constraints(target_radius_m=2.5)
    planner = make_planner("casadi", c, NOISE)
    hyp = planner.hypotheses(PlanningState([0.0, -60.0, 30.0], _estimate_two_users(False)))
    f_t = 2.5 / np.sqrt(CHI2_2DOF_95)
    np.testing.assert_allclose(planner.goal(hyp), [f_t, 0.1 * f_t])
    # every bound inside the target (the survey goes on for another reason): no goal
    small = fake_estimate([[-70, 60, 0], [70, 40, 0]], np.eye(2) * 0.2)
    assert planner.goal(planner.hypotheses(PlanningState([0.0, -60.0, 30.0], small))) is None
    # A-optimal (no bound) and goal="none": no goal
    for p in (make_planner("casadi", c, NOISE, criterion="A"), make_planner("casadi", c, NOISE, goal="none")):
        assert p.goal(p.hypotheses(PlanningState([0.0, -60.0, 30.0], _estimate_two_users(False)))) is None


def test_a_user_inside_the_target_pulls_the_vehicle_nowhere():
    """Two users: one well inside the target, one far outside. With the goal, the objective over
    candidate legs moves as that of the outside user alone; without it, the inside user's
    bound shrinking counts too."""
    est = fake_estimate([[-70, 60, 0], [70, 40, 0]], np.array([np.eye(2) * 0.2, np.diag([30.0, 6.0])]))
    c = u_constraints(target_radius_m=2.0)
    planner = make_planner("casadi", c, NOISE)
    state = PlanningState([0.0, -60.0, 30.0], est)
    hyp = planner.hypotheses(state)
    goal = planner.goal(hyp)
    assert goal is not None
    ring = planner.feasible_ring(state)
    model = PredictionModel(NOISE, c.delta_m, planner.n_quad)
    both = objective_values(state.uav_enu_m, ring, hyp, model, "E", goal=goal)
    alone = objective_values(state.uav_enu_m, ring, hypotheses_from_estimate(fake_estimate(
        [[70, 40, 0]], np.diag([30.0, 6.0])), sigma_points="major"), model, "E", goal=goal)
    plain_both = objective_values(state.uav_enu_m, ring, hyp, model, "E")
    plain_alone = objective_values(state.uav_enu_m, ring, hypotheses_from_estimate(fake_estimate(
        [[70, 40, 0]], np.diag([30.0, 6.0])), sigma_points="major"), model, "E")
    # the inside user's part of the objective's spread over the ring: ~1e-5 with the goal, ~1e-3 without
    inside_share = np.ptp(both - alone) / np.ptp(alone)
    plain_share = np.ptp(plain_both - plain_alone) / np.ptp(plain_alone)
    assert inside_share < 1e-4 < plain_share / 5


@pytest.mark.parametrize("bias", [False, True])
def test_ipopts_hessian_with_a_goal_equals_central_differences_of_its_gradient(bias):
    from tests.test_planner_active import _estimate_two_users_bias

    c = u_constraints()
    planner = make_planner("casadi", c, NOISE)
    state = PlanningState([0.0, -60.0, 30.0], _estimate_two_users_bias(False) if bias else _estimate_two_users(False))
    hyp = planner.hypotheses(state)
    goal = planner.goal(hyp)
    lay = _Layout(Shape(hyp.dim, hyp.bias, "E", planner.horizon, planner.n_quad), hyp.sample_w.size,
                  planner.max_planes, goal=True)
    par = pack_params(lay, state.uav_enu_m, hyp, NOISE, c.delta_m, prior_value(hyp, "E", goal), 0.002,
                      np.zeros((0, 2)), np.zeros(0), c.home_enu_m, c.return_factor, goal)
    solver = active_mod._solver(lay)
    grad_f, hess_l = solver.get_function("nlp_grad_f"), solver.get_function("nlp_hess_l")
    n_g = solver.size_in("lbg")[0]
    z = np.array([-30.0, -70.0, 20.0, -70.0, -40.0, 25.0])
    hess = np.asarray(hess_l(z, par, 1.0, np.zeros(n_g)), dtype=float)
    hess = np.triu(hess) + np.triu(hess, 1).T
    grad = lambda x: np.asarray(grad_f(x, par)[1], dtype=float).ravel()  # noqa: E731
    h = 1e-4
    fd = np.column_stack([(grad(z + e) - grad(z - e)) / (2 * h) for e in np.eye(len(z)) * h])
    np.testing.assert_allclose(hess, 0.5 * (fd + fd.T), rtol=1e-4, atol=1e-7)
    with pytest.raises(ValueError, match="goal"):
        pack_params(lay, state.uav_enu_m, hyp, NOISE, c.delta_m, 1.0, 0.0, np.zeros((0, 2)), np.zeros(0),
                    c.home_enu_m, c.return_factor)


def test_the_gps_floor_stays_in_the_prediction_and_out_of_the_prior():
    """With a GPS floor r_floor, the prior information holds Σ − v_f I (v_f = r_floor²/χ²₂(0.95)),
    the rows carry v_f, the objective before flying is still the estimate's own bound, and no leg
    predicts a bound below the floor; a user near its floor gains less from the same leg."""
    from planner.information import floor_var_of, predicted_nlos_var_m2

    est = fake_estimate([[70, 40, 0]], np.diag([3.0, 1.5]))
    floor_m = 2.0
    v_f = floor_m**2 / CHI2_2DOF_95
    assert floor_var_of(est, 0, floor_m) == pytest.approx(v_f)
    hyp = hypotheses_from_estimate(est, sigma_points="none", floor_m=floor_m)
    np.testing.assert_allclose(np.linalg.inv(hyp.prior_info[0, 0]), np.diag([3.0, 1.5]) - v_f * np.eye(2), rtol=1e-5)
    assert hyp.nlos[0, 0, 7] == pytest.approx(v_f)
    # f before flying: sqrt(λ_max(Σ)), the bound over sqrt(χ²₂(0.95)), floor or not
    assert prior_value(hyp, "E") == pytest.approx(np.sqrt(3.0), rel=1e-5)
    model = PredictionModel(NOISE, 2.0, 8)
    start = np.array([0.0, 0.0, 30.0])
    legs = np.array([[[60.0, 20.0, 30.0], [60.0, 70.0, 30.0]]])
    with_floor = objective_values(start, legs, hyp, model, "E")[0]
    plain = objective_values(start, legs, hypotheses_from_estimate(est, sigma_points="none"), model, "E")[0]
    assert np.sqrt(v_f) < with_floor and plain < with_floor < np.sqrt(3.0)
    np.testing.assert_allclose(predicted_nlos_var_m2(start, legs, hyp, model)[0, 0, 0], v_f)
    # an estimate tighter than the floor: at most FLOOR_SHARE_MAX of its smallest variance
    tight = fake_estimate([[70, 40, 0]], np.diag([0.5, 0.2]))
    assert floor_var_of(tight, 0, floor_m) == pytest.approx(0.9 * 0.2)
