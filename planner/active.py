"""The active planner: the next waypoint from the information objective, by CasADi + IPOPT (docs/design.md §6).

Defaults: criterion "E" (f = the error-ellipse semi-major axis per user, what the stop rule and
the benchmark measure; "A" for 3-D users), horizon 2 (two waypoints planned, the first flown).

Objective (planner.information; normalised by its value before the leg, J₀, so IPOPT sees O(1);
shown for one leg, a horizon sums the information of its legs and their lengths):

    min_p  Σ_k w_k Σ_s c_ks g(f(I_ks(p))) / J₀  +  λ · ℓ(p),     ℓ(p) = |p − x_c|,
           λ = cost_rel · (1 − min_ring J/J₀) / leg_max  (a full leg must buy back cost_rel of the
           best ring leg's gain, so the trade-off does not fade as the uncertainty shrinks)

    s.t.   min_leg² ≤ |p − x_c|² ≤ cap²,  cap = min(leg_max, budget left)       (leg length)
           alt_min ≤ p_up ≤ alt_max                                             (altitude band)
           |p_en − home_en|² ≤ R_max²                                           (distance from home)
           ℓ(p) + return_factor · |p − home| ≤ energy                            (return home)
           A p_en ≤ c                                                            (convex free cell)

g is the goal's hinge at the stop rule's target (planner.objective, "Goal"; `ActivePlanner.goal`):
the survey ends when every user's bound is within the target, so only the part of a bound above
it is left to remove; a user already inside it weighs (almost) nothing, and the legs go to the
users that keep the survey going. g(f) = f with goal="none", for criteria "A" and "D", and while
no bound is above the target.

The fence may be non-convex and no-fly zones cut holes, so each IPOPT start gets its own convex
cell around its seed leg (planner.geometry.convex_cell): any p in the cell has a straight leg from
x_c inside the free space. Starts: the best few feasible candidates of a coarse ring (24 headings
× 3 lengths × 3 altitudes, evaluated in numpy) with distinct headings, plus the previous plan's
heading (warm start). The answer is the best, by the numpy objective, of the IPOPT solutions that
pass the exact check and the best ring candidate — so it is never worse than the ring, and it is
never infeasible (the base class re-checks it).

Range biases: when the estimate carries a bias per user (`Estimate.bias_m` not None), f is applied
to the position information of the joint (position, bias) information (its Schur complement over
the bias; planner.information), so legs that separate the bias from the position — ranges at
diverse distances and elevations, e.g. over the user and far away — score better. Without biases
the objective is unchanged.

Users the estimator has not initialised: while none can be planned for, or all planned-for users
already meet the target, the planner explores (planner.information.explore_waypoint).

Transit. With a cell of limited reach, the users still above the target may all be beyond the
reach of every leg of the horizon (farther, horizontally, than √(R² − h²) plus H full legs): no
leg can range them, and the objective only holds what is left of the users already inside the
target (the goal's hinge is smooth) or nothing at all, so the planner polished those, or hopped
10 m in place, while a user 750 m away waited. The planner then flies the feasible ring leg that
brings it nearest the nearest such user (either of its hypotheses while it is ambiguous).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import casadi as ca
import numpy as np

from estimator.noise import NoiseModel
from estimator.types import CHI2_2DOF_95
from planner.base import BasePlanner
from planner.geometry import convex_cell, legs_feasible
from planner.information import (
    Hypotheses,
    PredictionModel,
    explore_waypoint,
    hypotheses_from_estimate,
    hypotheses_from_truth,
    hypothesis_rows,
    noise_parameters,
    objective_values,
    prior_row_values,
    prior_value,
    users_initialised,
)
from planner.objective import N_GOAL, N_NLOS, N_NOISE_PAR, SQRT_EPS_M2, Shape, goal_function, kernel, mapped
from planner.stop import reported_bound_95_m
from planner.types import PlanningConstraints, PlanningState
from uavloc.errors import PlannerError

log = logging.getLogger(__name__)

_IPOPT_OPTS = {
    "ipopt.print_level": 0,
    "ipopt.sb": "yes",
    "print_time": False,
    "ipopt.max_iter": 60,
    "ipopt.tol": 1e-4,
    "ipopt.acceptable_tol": 1e-3,
    "ipopt.acceptable_iter": 5,
    # the starts are feasible and near an optimum: a small barrier start saves most iterations
    "ipopt.mu_init": 1e-4,
    "ipopt.bound_push": 1e-6,
    "ipopt.bound_frac": 1e-6,
    "error_on_fail": False,
}
#: users (and mirrors) estimated farther than this from home are treated as not initialised [m].
MAX_USER_RANGE_M = 5000.0


@dataclass(frozen=True)
class _Layout:
    """What fixes one IPOPT problem (one cached solver each): the row kernel's shape, the number of
    rows (users × samples), the convex cell's half-planes, whether the kernels are compiled and
    whether the rows count through a goal's hinge (planner.objective, "Goal")."""

    shape: Shape
    n_rows: int
    n_planes: int
    compiled: bool = True
    max_iter: int = 60
    goal: bool = False


def _layout(planner: ActivePlanner, hyp: Hypotheses) -> _Layout:
    shape = Shape(hyp.dim, hyp.bias, planner.criterion, planner.horizon, planner.n_quad)
    return _Layout(shape, int(hyp.sample_w.size), planner.max_planes, planner.compiled, planner.max_iter,
                   planner.goal(hyp) is not None)


_SOLVERS: dict[_Layout, ca.Function] = {}


def _solver(lay: _Layout) -> ca.Function:
    """IPOPT on the objective of planner.objective, built once per layout and process.

    Parameters p = [x_c (3); U (3R); P (p²R); s (R); wts (R); NLoS (N_NLOS R); noise (4); Δ; λ;
    A (2 n_pl); c (n_pl); home (3); return factor; goal [f_T, w] (only with lay.goal)], matrices
    column-major with one column per row (pack_params).
    Variables z = [w_1; …; w_H] (3H); constraints, in order: |w_1 − x_c|² (leg), |w_h − w_(h−1)|²
    for h ≥ 2, |w_h,en − home_en|² for every h, the energy of the first leg, A w_h,en − c ≤ 0 for
    every h (rows of h consecutive). IPOPT gets the value, gradient and Hessian of the rows from
    the row kernels (mapped over the R rows), so no derivative is taken through them here; with a
    goal the rows count through its hinge g (planner.objective, "Goal"):

        J = Σ_r w_r g(f_r),  ∇J = Σ_r w_r g'(f_r) ∇f_r,  ∇²J = Σ_r w_r (g'(f_r) ∇²f_r + g''(f_r) ∇f_r ∇f_rᵀ)
    """
    if lay in _SOLVERS:
        return _SOLVERS[lay]
    sh, R, n_pl = lay.shape, lay.n_rows, lay.n_planes
    n_h, pp = sh.horizon, sh.n_par**2
    vgh, value = kernel("vgh", sh, lay.compiled), kernel("value", sh, lay.compiled)
    sizes = [3, 3 * R, pp * R, R, R, N_NLOS * R, N_NOISE_PAR, 1, 1, 2 * n_pl, n_pl, 3, 1]
    sizes += [N_GOAL] if lay.goal else []
    par = ca.MX.sym("p", sum(sizes))
    x_c, U, P, s, wts, nl, noise_par, delta, lam, A, c, home, ret, *goal = ca.vertsplit(
        par, list(np.cumsum([0, *sizes])))
    U, P, s, wts = ca.reshape(U, 3, R), ca.reshape(P, pp, R), ca.reshape(s, 1, R), ca.reshape(wts, R, 1)
    nl = ca.reshape(nl, N_NLOS, R)
    A = ca.reshape(A, n_pl, 2)
    z = ca.MX.sym("z", 3 * n_h)
    f_rows, g_rows, h_rows = mapped(vgh, R)(z, x_c, U, P, s, noise_par, delta, nl)
    f_value = mapped(value, R)(z, x_c, U, P, s, noise_par, delta, nl)
    outer = None
    if lay.goal:
        # g(f_r), g'(f_r), g''(f_r) of every row (1 × R each)
        g_value = mapped(goal_function(), R)(f_value, goal[0])[0]
        f_rows, d1, d2 = mapped(goal_function(), R)(f_rows, goal[0])
        f_value = g_value
        # Σ_r w_r g''(f_r) ∇f_r ∇f_rᵀ
        outer = (g_rows * ca.repmat(d2 * wts.T, 3 * n_h, 1)) @ g_rows.T
        wts_grad = d1.T * wts
    else:
        wts_grad = wts
    unc = f_value @ wts
    wps = [z[3 * h:3 * h + 3] for h in range(n_h)]
    prev, lengths = x_c, []
    for wp in wps:
        lengths.append(ca.sqrt(ca.sumsqr(wp - prev) + SQRT_EPS_M2))
        prev = wp
    cost = lam * sum(lengths)
    g = ca.vertcat(
        ca.sumsqr(wps[0] - x_c),  # first leg length²
        *[ca.sumsqr(wps[h] - wps[h - 1]) for h in range(1, n_h)],  # later legs²
        *[ca.sumsqr((wp - home)[:2]) for wp in wps],  # horizontal distance from home²
        lengths[0] + ret * ca.sqrt(ca.sumsqr(wps[0] - home) + SQRT_EPS_M2),  # energy of the first leg
        *[A @ wp[:2] - c for wp in wps],  # convex cell
    )
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", g.shape[0])
    grad = g_rows @ wts_grad + ca.gradient(cost, z)
    hess_rows = h_rows @ ca.kron(wts_grad, ca.DM.eye(3 * n_h))
    if outer is not None:
        hess_rows = hess_rows + outer
    hess = lam_f * hess_rows + ca.hessian(lam_f * cost + ca.dot(lam_g, g), z)[0]
    opts = dict(_IPOPT_OPTS)
    opts["ipopt.max_iter"] = lay.max_iter
    opts["grad_f"] = ca.Function("grad_f", [z, par], [f_rows @ wts + cost, grad])
    opts["hess_lag"] = ca.Function("hess_lag", [z, par, lam_f, lam_g], [ca.triu(hess)])
    solver = ca.nlpsol("leg", "ipopt", {"x": z, "p": par, "f": unc + cost, "g": g}, opts)
    _SOLVERS[lay] = solver
    log.debug("built the IPOPT problem for %s", lay)
    return solver


def objective_function(lay: _Layout) -> ca.Function:
    """(z, p) → (f, ∇f) of a layout's problem: exactly what its IPOPT minimises (for the tests)."""
    sol = _solver(lay)
    return sol.get_function("nlp_grad_f")


def pack_params(
    lay: _Layout,
    x_c: np.ndarray,
    hyp: Hypotheses,
    noise: NoiseModel,
    delta_m: float,
    norm: float,
    lam: float,
    A: np.ndarray,
    c: np.ndarray,
    home: np.ndarray,
    return_factor: float,
    goal: np.ndarray | None = None,
    coverage_m: float = float("inf"),
) -> np.ndarray:
    """The parameter vector of :func:`_solver`'s problem (weights divided by `norm`; goal [f_T, w]
    when the layout has one, planner.objective's "Goal")."""
    if hyp.n_par != lay.shape.n_par or hyp.sample_w.size != lay.n_rows:
        raise ValueError(f"layout {lay} does not fit hypotheses of {hyp.n_par} parameters, {hyp.sample_w.size} rows")
    if lay.goal != (goal is not None):
        raise ValueError(f"layout {lay} {'needs' if lay.goal else 'takes no'} goal, got {goal!r}")
    rows = hypothesis_rows(hyp)
    A_pad = np.zeros((lay.n_planes, 2))
    c_pad = np.ones(lay.n_planes)  # 0·p ≤ 1: inactive rows
    A_pad[: len(A)], c_pad[: len(c)] = A, c
    return np.concatenate([
        x_c, rows.users_enu_m.ravel(), rows.prior_info.reshape(lay.n_rows, -1).ravel(), rows.scale,
        rows.weights / norm, rows.nlos.ravel(), noise_parameters(noise, coverage_m), [delta_m, lam],
        A_pad.ravel(order="F"), c_pad, home, [return_factor],
        *([] if goal is None else [np.asarray(goal, dtype=float).reshape(N_GOAL)]),
    ])


class ActivePlanner(BasePlanner):
    """CasADi/IPOPT next-waypoint planner ("casadi").

    criterion: "A" (trace), "D" (log-det) or "E" (sqrt of the covariance's largest eigenvalue: the
    error-ellipse semi-major axis, 2-D users); cost_rel: the cost of a full-length leg as a fraction
    of the best ring leg's predicted gain (see `cost_per_m`); n_starts: IPOPT starts from the ring
    (the warm start adds one); n_quad: quadrature points per leg; sigma_points: "major", "all" or
    "none" (planner.information.hypotheses_from_estimate; the mirror is always included while
    ambiguous); user_weights: (K,) w_k; max_planes: cap on the convex cell's half-planes;
    weighting: "sqrt" multiplies w_k by 1/sqrt(tr Σ_k); horizon: waypoints planned ahead (only the
    first is flown; all lie in the first leg's convex cell; `last_horizon_enu_m` holds them);
    compiled: the objective's kernels compiled to machine code (planner.objective); ipopt_seeds:
    IPOPT runs only from this many of the best seeds by the objective (0: from every seed);
    max_iter: IPOPT's iteration cap; precompile: compile the kernels when the planner is made
    (see `precompile`) instead of at the first plan that needs them; goal: "target" counts each
    row through the hinge at the stop rule's target (see `goal`), "none" counts f itself;
    goal_width: the hinge's width w as a fraction of f_T.
    """

    name = "casadi"

    def __init__(
        self,
        constraints: PlanningConstraints,
        noise: NoiseModel,
        rng_seed: int = 0,
        criterion: str = "E",
        cost_rel: float = 0.2,
        n_starts: int = 1,
        n_quad: int = 8,
        sigma_points: str = "major",
        user_weights: np.ndarray | None = None,
        max_planes: int = 24,
        weighting: str = "none",
        horizon: int = 2,
        compiled: bool = True,
        ipopt_seeds: int = 1,
        max_iter: int = 30,
        precompile: bool = False,
        goal: str = "target",
        goal_width: float = 0.1,
    ) -> None:
        super().__init__(constraints, noise, rng_seed)
        self.compiled = bool(compiled)
        if ipopt_seeds < 0 or max_iter < 1:
            raise PlannerError(f"need ipopt_seeds >= 0 and max_iter >= 1; got {ipopt_seeds}, {max_iter}")
        self.ipopt_seeds = int(ipopt_seeds)
        self.max_iter = int(max_iter)
        if weighting not in ("none", "sqrt"):
            raise PlannerError(f"weighting must be 'none' or 'sqrt', got {weighting!r}")
        self.weighting = weighting
        if criterion not in ("A", "D", "E"):
            raise PlannerError(f"criterion must be 'A', 'D' or 'E', got {criterion!r}")
        if n_starts < 1 or n_quad < 2 or cost_rel < 0:
            raise PlannerError(f"need n_starts >= 1, n_quad >= 2, cost_rel >= 0; got {n_starts}, {n_quad}, {cost_rel}")
        self.criterion = criterion
        if goal not in ("target", "none") or not goal_width > 0:
            raise PlannerError(f"goal must be 'target' or 'none' and goal_width > 0; got {goal!r}, {goal_width!r}")
        self.goal_mode = goal
        self.goal_width = float(goal_width)
        self._goal: tuple | None = None
        self.cost_rel = float(cost_rel)
        self.n_starts = int(n_starts)
        self.n_quad = int(n_quad)
        self.sigma_points = sigma_points
        self.user_weights = None if user_weights is None else np.asarray(user_weights, dtype=float)
        self.max_planes = int(max_planes)
        self.horizon = int(horizon)
        if self.horizon < 1:
            raise PlannerError(f"horizon must be >= 1, got {horizon}")
        self._visited: list[np.ndarray] = []
        self._prev_dir = np.zeros(3)
        self._prev_path: np.ndarray | None = None
        self.last_horizon_enu_m: np.ndarray | None = None
        self._norm: tuple | None = None
        if precompile and self.compiled:
            self.precompile()

    def prepare(self) -> None:
        """Before take-off: the kernels the first plans need (precompile)."""
        self.precompile()

    def precompile(self) -> None:
        """Build (compile) now the kernels plans with 2-D users will need, with and without range
        biases, so the first plan with an estimate does not pay the compiler (once per process)."""
        for bias in (False, True):
            shape = Shape(2, bias, self.criterion, self.horizon, self.n_quad)
            kernel("vgh", shape, self.compiled)
            kernel("value", shape, self.compiled)
            kernel("value", Shape(2, bias, self.criterion, 1, self.n_quad), self.compiled)

    # -- hypotheses ------------------------------------------------------------------------------
    def hypotheses(self, state: PlanningState) -> Hypotheses | None:
        """Posterior samples to plan for, or None to explore (see the module docstring)."""
        est = state.estimate
        if est is None:
            return None
        ok = users_initialised(est)
        if state.users is not None:  # a fleet's vehicle plans for the users its cell serves
            ok &= state.users
        home = self.constraints.home_enu_m
        # a user estimated absurdly far away is a diverged solve, not something to fly toward
        ok &= np.linalg.norm(np.nan_to_num(est.users_enu_m[:, :2] - home[:2], nan=np.inf), axis=1) <= MAX_USER_RANGE_M
        if not ok.any():
            return None
        if not ok.all():
            bound = reported_bound_95_m(est)
            if np.all(bound[ok] <= self.constraints.target_radius_m):
                return None
        return hypotheses_from_estimate(est, self.weights(est), sigma_points=self.sigma_points, users=ok,
                                        home_enu_m=home, max_range_m=MAX_USER_RANGE_M,
                                        floor_m=self.constraints.floor_m)

    def weights(self, est) -> np.ndarray:
        """(K,) w_k: `user_weights` (default 1), times 1/sqrt(tr Σ_k) with weighting="sqrt".

        Σ_k sqrt(tr Σ_k) is (up to a constant) the mean error bound over users; its gradient is
        Σ_k ∇tr Σ_k / (2 sqrt(tr Σ_k)), so A-optimal with these weights is its first-order version.
        """
        w = np.ones(est.n_users) if self.user_weights is None else self.user_weights.copy()
        if self.weighting == "sqrt":
            tr = np.trace(np.asarray(est.cov_users_m2, dtype=float), axis1=1, axis2=2)
            with np.errstate(invalid="ignore", divide="ignore"):
                w = w / np.sqrt(np.where(np.isfinite(tr) & (tr > 0), tr, 1.0))
        return w

    def goal(self, hyp: Hypotheses) -> np.ndarray | None:
        """[f_T, w] of the hinge the rows count through (planner.objective, "Goal"), or None (g(f) = f).

        The stop rule ends the survey when every user's bound r95 = sqrt(χ²₂(0.95)) · f ("E") is
        within the target T, so f_T = T / sqrt(χ²₂(0.95)) and w = goal_width · f_T. None with
        goal="none", for criteria other than "E" (whose f is no bound), and when no row with weight
        is above f_T before flying (the survey goes on for another reason, an ambiguous mirror or
        an unlocated user: then every bound counts)."""
        if self._goal is not None and self._goal[0] is hyp and self._goal[1] == self.criterion:
            return self._goal[2]
        goal = None
        if self.goal_mode == "target" and self.criterion == "E":
            f_t = self.constraints.target_radius_m / np.sqrt(CHI2_2DOF_95)
            rows = hypothesis_rows(hyp)
            if np.any(prior_row_values(hyp, self.criterion)[rows.weights > 0] > f_t):
                goal = np.array([f_t, self.goal_width * f_t])
        self._goal = (hyp, self.criterion, goal)
        return goal

    def uncertainty(self, state: PlanningState, paths_enu_m: np.ndarray, hyp: Hypotheses) -> np.ndarray:
        """(C,) predicted Σ_k w_k Σ_s c_ks g(f(I_ks)) / J₀ after flying candidate leg ends (C, 3) or
        horizons (C, H, 3) from the UAV (no cost term; g the goal's hinge, `goal`)."""
        norm = self._prior_value(hyp)
        return objective_values(state.uav_enu_m, paths_enu_m, hyp, self.prediction, self.criterion,
                                compiled=self.compiled, goal=self.goal(hyp)) / norm

    @property
    def prediction(self) -> PredictionModel:
        """The objective's prediction of a horizon: the planner's noise, the constraints' Δ, n_quad."""
        return PredictionModel(self.noise, self.constraints.delta_m, self.n_quad, self.constraints.coverage_m)

    def _prior_value(self, hyp: Hypotheses) -> float:
        """J₀ = prior_value(hyp) with the goal (computed once for the hypotheses of a plan)."""
        if self._norm is None or self._norm[0] is not hyp or self._norm[1] != self.criterion:
            self._norm = (hyp, self.criterion, prior_value(hyp, self.criterion, self.goal(hyp)))
        return self._norm[2]

    def cost_per_m(self, ring_uncertainty: np.ndarray) -> float:
        """λ (normalised units per metre) = cost_rel · (best gain of a ring leg) / leg_max:
        a full-length leg must buy back at least cost_rel of what the best ring leg gains."""
        finite = ring_uncertainty[np.isfinite(ring_uncertainty)]
        gain = max(1.0 - float(np.min(finite)), 0.0) if len(finite) else 0.0
        return self.cost_rel * gain / self.constraints.leg_max_m

    def evaluate(self, state: PlanningState, paths_enu_m: np.ndarray, hyp: Hypotheses, lam: float) -> np.ndarray:
        """(C,) the normalised objective J/J₀ + λ·Σℓ of leg ends (C, 3) or horizons (C, H, 3) —
        what IPOPT minimises."""
        W = np.asarray(paths_enu_m, dtype=float)
        W3 = W[:, None, :] if W.ndim == 2 else W
        prev = np.concatenate([np.broadcast_to(state.uav_enu_m, (len(W3), 1, 3)), W3[:, :-1]], axis=1)
        total = np.linalg.norm(W3 - prev, axis=2).sum(axis=1)
        return self.uncertainty(state, W, hyp) + lam * total

    # -- planning --------------------------------------------------------------------------------
    def _seed_ends(self, state: PlanningState, ring: np.ndarray, values: np.ndarray) -> list[np.ndarray]:
        """Up to n_starts first-leg ends: best ring candidates with headings ≥ 40° apart."""
        x = state.uav_enu_m
        heading = np.arctan2(ring[:, 1] - x[1], ring[:, 0] - x[0])
        chosen: list[int] = []
        for i in np.argsort(values):
            if not np.isfinite(values[i]):
                break
            if all(abs(np.angle(np.exp(1j * (heading[i] - heading[j])))) >= np.radians(40) for j in chosen):
                chosen.append(int(i))
            if len(chosen) >= self.n_starts:
                break
        return [ring[i] for i in chosen]

    def _extend(self, state: PlanningState, first: np.ndarray, hyp: Hypotheses, lam: float) -> np.ndarray:
        """(H, 3) horizon from a first waypoint: each further waypoint the best of 24 full-length
        feasible legs at the same altitude (greedy on the H-leg objective; a repeated waypoint when
        no leg is feasible)."""
        c = self.constraints
        path = np.repeat(first[None], self.horizon, axis=0)
        for h in range(1, self.horizon):
            prev = path[h - 1]
            theta = 2 * np.pi * np.arange(24) / 24
            ends = np.column_stack([prev[0] + c.leg_max_m * np.cos(theta), prev[1] + c.leg_max_m * np.sin(theta),
                                    np.full(24, prev[2])])
            ends = ends[legs_feasible(c, prev, ends, c.leg_max_m)]
            if len(ends) == 0:
                break
            cand = np.repeat(path[None], len(ends), axis=0)
            cand[:, h:] = ends[:, None, :]
            vals = self.evaluate(state, cand, hyp, lam)
            if np.isfinite(vals).any():
                path = cand[int(np.nanargmin(np.where(np.isfinite(vals), vals, np.nan)))]
        return path

    def _path_feasible(self, state: PlanningState, path: np.ndarray, leg_cap_m: float) -> bool:
        """Exact check of every leg of a horizon (the first with the budget and energy)."""
        c, x = self.constraints, state.uav_enu_m
        if not legs_feasible(c, x, path[:1], leg_cap_m, state.energy_remaining_m)[0]:
            return False
        if np.linalg.norm(path[0] - x) < min(c.min_leg_m, leg_cap_m) - 1e-6:
            return False
        return all(
            np.linalg.norm(path[h] - path[h - 1]) < 1e-6 or legs_feasible(c, path[h - 1], path[h:h + 1], c.leg_max_m)[0]
            for h in range(1, len(path))
        )

    def _ipopt(
        self, state: PlanningState, hyp: Hypotheses, seed: np.ndarray, norm: float, lam: float
    ) -> tuple[np.ndarray, str]:
        """IPOPT from a seed horizon (H, 3) (or first waypoint (3,) when H = 1) → ((H, 3), status)."""
        c, x = self.constraints, state.uav_enu_m
        n_h = self.horizon
        seed = np.asarray(seed, dtype=float).reshape(n_h, 3)
        lay = _layout(self, hyp)
        solver = _solver(lay)
        # the cell around the first seed leg holds every waypoint, so every leg (convex) stays free
        A, off = convex_cell(c, x[:2], seed[0, :2], self.max_planes)
        par = pack_params(lay, x, hyp, self.noise, c.delta_m, norm, lam, A, off, c.home_enu_m,
                          c.return_factor, self.goal(hyp), c.coverage_m)
        cap = self.leg_cap_m(state)
        energy = state.energy_remaining_m if np.isfinite(state.energy_remaining_m) else 1e12
        lbg, ubg = [min(c.min_leg_m, cap) ** 2], [cap**2]
        lbg += [0.0] * (n_h - 1)
        ubg += [c.leg_max_m**2] * (n_h - 1)
        lbg += [-np.inf] * n_h
        ubg += [c.max_distance_m**2] * n_h
        lbg += [-np.inf]
        ubg += [energy]
        lbg += [-np.inf] * (self.max_planes * n_h)
        ubg += [0.0] * (self.max_planes * n_h)
        lbx = np.tile([-np.inf, -np.inf, c.alt_min_m], n_h)
        ubx = np.tile([np.inf, np.inf, c.alt_max_m], n_h)
        sol = solver(x0=seed.ravel(), p=par, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        status = solver.stats().get("return_status", "?")
        return np.asarray(sol["x"]).ravel().reshape(n_h, 3), status

    def _propose(self, state: PlanningState, leg_cap_m: float) -> tuple[np.ndarray, str, float]:
        x = state.uav_enu_m
        self._visited.append(x.copy())
        self.last_horizon_enu_m = None
        hyp = self.hypotheses(state)
        if hyp is None:
            wp = explore_waypoint(self, state, np.array(self._visited))
            self._remember(x, wp[None])
            return wp, "explore", float("nan")
        if self.criterion == "E" and hyp.dim != 2:
            log.warning("criterion 'E' is for 2-D users; planning A-optimal for %d-D users", hyp.dim)
            self.criterion = "A"
        ring = self.feasible_ring(state)
        if len(ring) == 0:
            return x.copy(), "no ring", float("nan")
        if np.isfinite(self.constraints.coverage_m):
            wp = self._transit(state, ring)
            if wp is not None:
                self._remember(x, wp[None])
                return wp, "transit", float("nan")
        unc = self.uncertainty(state, ring, hyp)
        lam = self.cost_per_m(unc)
        values = unc + lam * np.linalg.norm(ring - x, axis=1)
        values = np.where(np.isfinite(values), values, np.inf)
        if not np.isfinite(values).any():
            log.warning("objective not finite on any ring candidate; exploring instead")
            wp = explore_waypoint(self, state, np.array(self._visited))
            self._remember(x, wp[None])
            return wp, "explore", float("nan")
        # seeds: the best ring ends (extended greedily to the horizon) and the previous plan's tail
        seeds = [self._extend(state, end, hyp, lam) for end in self._seed_ends(state, ring, values)]
        if self.horizon == 1:
            best_i = int(np.argmin(values))
            best, best_val = ring[best_i][None], float(values[best_i])
        else:
            seed_vals = self.evaluate(state, np.array(seeds), hyp, lam)
            best_i = int(np.argmin(seed_vals))
            best, best_val = seeds[best_i], float(seed_vals[best_i])
        best_status = "ring"
        warm = self._warm_start(state)
        if warm is not None:
            seeds.append(warm)
        if self.ipopt_seeds and len(seeds) > self.ipopt_seeds:
            # IPOPT only from the best seeds by the objective (each solve costs more than the ring)
            order = np.argsort(self.evaluate(state, np.array(seeds).reshape(len(seeds), self.horizon, 3), hyp, lam))
            seeds = [seeds[i] for i in order[:self.ipopt_seeds]]
        norm = self._prior_value(hyp)
        for seed in seeds:
            try:
                path, status = self._ipopt(state, hyp, seed, norm, lam)
            except RuntimeError as exc:  # CasADi evaluation errors: keep the ring answer
                log.warning("IPOPT failed from %s: %s", seed, exc)
                continue
            if not np.all(np.isfinite(path)) or not self._path_feasible(state, path, leg_cap_m):
                log.debug("IPOPT answer %s (%s) fails the exact check", path, status)
                continue
            val = float(self.evaluate(state, path[None], hyp, lam)[0])
            if val < best_val:
                ok = status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
                best, best_val, best_status = path, val, "ipopt" if ok else f"ipopt:{status}"
        self._remember(x, best)
        return best[0].copy(), best_status, best_val

    def _transit(self, state: PlanningState, ring: np.ndarray) -> np.ndarray | None:
        """When every user above the target that this vehicle plans for (its estimate, or its mirror
        while ambiguous) is beyond the reach of the whole horizon, the ring leg ending nearest the
        nearest of them; else None (module docstring, "Transit")."""
        c = self.constraints
        est = state.estimate
        if est is None:  # (the oracle plans for the true users before the first range)
            return None
        bound = reported_bound_95_m(est)
        left = users_initialised(est) & ~(bound <= self.constraints.target_radius_m)
        if state.users is not None:
            left &= state.users
        spots = [est.users_enu_m[left, :2]]
        amb = left & np.asarray(est.ambiguous, dtype=bool) & np.all(np.isfinite(est.mirror_enu_m), axis=1)
        spots.append(est.mirror_enu_m[amb, :2])
        spots = np.concatenate(spots)
        if len(spots) == 0:
            return None
        x = state.uav_enu_m[:2]
        dist = np.linalg.norm(spots - x, axis=1)
        if np.min(dist) <= c.reach_m + self.horizon * c.leg_max_m:
            return None
        goal = spots[int(np.argmin(dist))]
        return ring[int(np.argmin(np.linalg.norm(ring[:, :2] - goal, axis=1)))].copy()

    def _warm_start(self, state: PlanningState) -> np.ndarray | None:
        """The previous plan shifted by one leg (its heading continued when H = 1), if its first leg
        is feasible from here."""
        if self._prev_path is None:
            return None
        c, x = self.constraints, state.uav_enu_m
        cap = self.leg_cap_m(state)
        if self.horizon > 1 and len(self._prev_path) > 1:
            warm = np.concatenate([self._prev_path[1:], self._prev_path[-1:]])
        else:
            warm = (x + self._prev_dir * cap)[None]
            warm[0, 2] = np.clip(warm[0, 2], c.alt_min_m, c.alt_max_m)
            warm = np.repeat(warm, self.horizon, axis=0)
        if np.linalg.norm(warm[0] - x) < 1e-3:
            return None
        if not legs_feasible(c, x, warm[:1], cap, state.energy_remaining_m)[0]:
            return None
        return warm

    def _remember(self, x: np.ndarray, path: np.ndarray) -> None:
        self.last_horizon_enu_m = np.asarray(path, dtype=float).copy()
        self._prev_path = self.last_horizon_enu_m
        step = path[0] - x
        n = float(np.linalg.norm(step))
        self._prev_dir = step / n if n > 0 else np.zeros(3)


class ReferenceActivePlanner(ActivePlanner):
    """The active planner as it was before its speed-ups ("casadi_reference"): the same objective
    and decisions up to IPOPT's stopping point, with interpreted (not compiled) kernels, IPOPT from
    every seed and up to 60 iterations — the slow baseline the planner benchmark times it against."""

    name = "casadi_reference"

    def __init__(self, constraints, noise, rng_seed=0, **opts) -> None:
        opts.setdefault("compiled", False)
        opts.setdefault("ipopt_seeds", 0)
        opts.setdefault("max_iter", 60)
        super().__init__(constraints, noise, rng_seed, **opts)


class OraclePlanner(ActivePlanner):
    """The active planner given the true user positions (`true_users_enu_m`, (K, 3)): it plans with
    the estimator's information but at the truth, with no posterior samples and no exploration."""

    name = "oracle"

    def __init__(self, constraints, noise, rng_seed=0, true_users_enu_m=None, **opts) -> None:
        if true_users_enu_m is None:
            raise PlannerError("the oracle planner needs true_users_enu_m=(K, 3)")
        super().__init__(constraints, noise, rng_seed, **opts)
        self.true_users_enu_m = np.asarray(true_users_enu_m, dtype=float).reshape(-1, 3)

    def hypotheses(self, state: PlanningState) -> Hypotheses | None:
        est = state.estimate
        dim = int(est.cov_users_m2.shape[1]) if est is not None else 2
        return hypotheses_from_truth(self.true_users_enu_m, est, dim, self.user_weights, self.constraints.floor_m)


class GreedyPlanner(ActivePlanner):
    """Greedy heading search: the best of 24 full-length legs at the cruise altitude on the
    A-optimal objective at the estimate (and its mirror while ambiguous; no sigma points, no IPOPT)."""

    name = "greedy"

    def __init__(self, constraints, noise, rng_seed=0, **opts) -> None:
        opts.setdefault("sigma_points", "none")
        opts.setdefault("criterion", "A")
        super().__init__(constraints, noise, rng_seed, **opts)

    def _propose(self, state: PlanningState, leg_cap_m: float) -> tuple[np.ndarray, str, float]:
        x = state.uav_enu_m
        self._visited.append(x.copy())
        hyp = self.hypotheses(state)
        if hyp is None:
            return explore_waypoint(self, state, np.array(self._visited)), "explore", float("nan")
        from planner.base import ring_candidates

        ring = ring_candidates(x, leg_cap_m, np.array([self.constraints.cruise_alt_m]), 24, (1.0,))
        ring = ring[legs_feasible(self.constraints, x, ring, leg_cap_m, state.energy_remaining_m)]
        if len(ring) == 0:
            ring = self.feasible_ring(state)
        if len(ring) == 0:
            return x.copy(), "no ring", float("nan")
        values = self.uncertainty(state, ring, hyp)
        i = int(np.argmin(values))
        return ring[i].copy(), self.name, float(values[i])
