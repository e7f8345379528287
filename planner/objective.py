"""The planner's objective, defined once in CasADi: IPOPT minimises it and numpy evaluates it (docs/design.md §6).

One row is one hypothesis of one user (a posterior sample u with its prior information P, noise
scale s and weight). After flying the horizon x_c → w_1 → … → w_H with a range every Δ metres, the
row's predicted information is (midpoint rule, Q points per leg at t_q = (q − ½)/Q, each standing
for ℓ/(ΔQ) ranges):

    J(u) = P + Σ_legs (ℓ/(ΔQ)) Σ_q h_q h_qᵀ / σ_eff²(d_q),   d_q = sqrt(|m_q − u|² + ε)
    σ_eff² = (s · σ(d))² + σ_gps²,   σ(d) = s0 + a·e^{b d}                          (noise scale s)
    h_q = g_q = (m_q − u)[:d] / d_q                    (positions only, p = d)
    h_q = [g_q; −1]                                    (with a range bias last, p = d + 1)

The sign of the bias entry does not matter (h hᵀ); it is the estimator's range factor's Jacobian
on (u, b) up to the factor −1/σ_eff (estimator.factors.range_jacobian; planner.information's
`predicted_information` computes the same from that factor and the tests check the two agree).
With a bias the position information is the Schur complement I = A − c cᵀ/s of J = [[A, c],
[cᵀ, s]]. A tracked clock sawtooth is a bias whose gain follows the sawtooth's shape; a constant
gain leaves the Schur complement unchanged, so it is modelled as this bias. A GPS error along the
line of sight shifts the range one-for-one: σ_gps² is folded into the range variance.

NLoS shift (estimator.nlos_shift). A user whose NLoS excess comes from one side carries the shift
½ |δ|² I₂ (horizontal) in the covariance the stop rule judges, |δ| = κ π, π the share of its ranges
that are NLoS and κ = 2μ/c. The horizon's ranges change π: from the n ranges so far, of which π₀ n
NLoS, and the profile p(β, ε) = σ(α₀ + α₁ cos β + α₂ sin β + α₃ sin ε) of the NLoS probability
by the UAV's bearing β and elevation ε seen from the user (estimator.nlos_shift.nlos_bearing_logit;
sin ε = (m − u)_up / d),

    π̂ = (π₀ n + Σ_legs (ℓ/(ΔQ)) Σ_q p(β_q, ε_q)) / (n + Σ_legs ℓ/Δ),    v = ½ (κ π̂)²

so legs that see the user from its line-of-sight side, or from above its blockers, shrink v. A
row without a shift has κ = 0.

Coverage. A UE farther than the gNB's reach R (slant range) is not heard: a quadrature point's
ranges count with the smooth cut c(d) = 1 / (1 + exp((d − R)/COVERAGE_EDGE_M)) (1 well inside the
cell, 0 beyond it; R = NO_COVERAGE_LIMIT_M when the reach is unknown), so that legs that carry the
UAV out of a user's reach buy it nothing (before, a UAV at the far side of a 900 m world saw the
users 600 m away through a 400 m cell and hovered up and down where it was).

GPS floor. A drifting GPS error (correlation time τ of tens to hundreds of seconds) moves the
track and the users together: the part of it the survey's duration does not average away stays in
every user's bound, whatever the legs (estimator.gps.gps_floor_bound_95_m; PlanningConstraints.
floor_m = r_floor, its 95 % bound). The row carries it as v_f = r_floor² / χ²₂(0.95) per
horizontal axis (planner.information.floor_var_of), left out of the prior information P as the
shift is, and added to v: v ← ½ (κ π̂)² + v_f. More ranges then shrink only the part of the bound
above the floor, as they do in the estimate, so a user near its floor no longer looks like one
whose bound a few legs halve.

The row's value is the criterion of Σ = I⁻¹ + v P_h (P_h the horizontal projector; what the stop
rule and the benchmark measure for "E"):

    f = tr(I⁻¹) + 2v ("A"),  −log det I + log(1 + v tr I_h + v² det I_h) ("D"),
        sqrt(1/λ_min(I) + v) ("E", d = 2, λ_min = (tr − sqrt((I₀₀ − I₁₁)² + 4 I₀₁² + ε_E tr²)) / 2,
        smooth at isotropy)

(I_h the horizontal block of I; det(I⁻¹ + v P_h) = det(I⁻¹) · det(I + v I P_h).)

Goal. The stop rule asks every user's bound to be within the target T, so what is left to do is
the part of each bound above T: a user already inside it gains the survey nothing, however much
its bound still shrinks. With a goal [f_T, w] (f_T = T / sqrt(χ²₂(0.95)) for "E", whose f is the
bound over sqrt(χ²₂(0.95)); planner.active) a row counts the smooth hinge of its value

    g(f) = w · softplus((f − f_T) / w),   g' = σ((f − f_T)/w),   g'' = σ (1 − σ) / w

(≈ f − f_T above the target, ≈ 0 below it, w the width of the bend), and the objective sums
w_r g(f_r) instead of w_r f_r; its gradient and Hessian in the waypoints are Σ w_r g' ∇f_r and
Σ w_r (g' ∇²f_r + g'' ∇f_r ∇f_rᵀ), from the same row kernels. Without a goal g(f) = f.

The objective sums the rows with their weights (planner.active adds the leg-length cost and the
normalisation). Kernels (:func:`kernel`, one per :class:`Shape`, whatever the number of users and samples): the
row's value, and its value, gradient and upper-triangular Hessian in the waypoints z (what IPOPT
needs, so no derivative is taken through the mapped rows at solve time). Built once per process;
compiled to machine code by the injectable :data:`compile_hook` (default: CasADi's JIT through the
system C compiler, whose temporary files CasADi removes; the SX virtual machine when that fails or
when `compiled=False`, the slow reference configuration).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

log = logging.getLogger(__name__)

#: ε added under square roots [m²].
SQRT_EPS_M2 = 1e-9
#: relative ε under the eigenvalue-gap square root of the "E" criterion (smooth at isotropy).
E_GAP_EPS = 1e-6
#: entries of the kernels' noise parameters [s0, a, b, σ_gps², R]
N_NOISE_PAR = 5
#: width of the coverage edge's smooth cut [m] (module docstring, "Coverage")
COVERAGE_EDGE_M = 10.0
#: the reach R given when a cell's reach is not limited [m]
NO_COVERAGE_LIMIT_M = 1e6
#: C compiler flags of the kernels: -O1 evaluates about as fast as -O2 and compiles in a few seconds.
JIT_FLAGS = ("-O1",)


@dataclass(frozen=True)
class Shape:
    """What fixes a row kernel: position dimension d, a bias per user, criterion, horizon H, Q."""

    dim: int
    bias: bool
    criterion: str
    horizon: int
    n_quad: int

    @property
    def n_par(self) -> int:
        """p: parameters per user (d, or d + 1 with the bias last)."""
        return self.dim + int(self.bias)


def criterion_expr(info: dict, d: int, criterion: str, v=0.0):
    """f of the position information given as {(i, j): I_ij, i ≤ j} (SX expressions), d = 2 or 3,
    with the NLoS shift's variance v [m²] on each horizontal axis (module docstring)."""
    # log det(I + v I P_h) = log(1 + v tr I_h + v² det I_h)
    det_h = info[0, 0] * info[1, 1] - info[0, 1] ** 2
    shift_logdet = ca.log(1.0 + v * (info[0, 0] + info[1, 1]) + v * v * det_h)
    if criterion == "E":
        if d != 2:
            raise ValueError("criterion 'E' is implemented for 2-D users only")
        tr = info[0, 0] + info[1, 1]
        gap = ca.sqrt((info[0, 0] - info[1, 1]) ** 2 + 4 * info[0, 1] ** 2 + E_GAP_EPS * tr**2)
        # sqrt(λ_max(I⁻¹ + v I₂)) = sqrt(1/λ_min(I) + v)
        return ca.sqrt(1.0 / (0.5 * (tr - gap)) + v)
    if d == 2:
        # tr(I⁻¹) = (I₀₀ + I₁₁) / det I
        return (info[0, 0] + info[1, 1]) / det_h + 2.0 * v if criterion == "A" else -ca.log(det_h) + shift_logdet
    i00, i01, i02, i11, i12, i22 = (info[0, 0], info[0, 1], info[0, 2], info[1, 1], info[1, 2], info[2, 2])
    c00, c11, c22 = i11 * i22 - i12**2, i00 * i22 - i02**2, i00 * i11 - i01**2
    det = i00 * c00 - i01 * (i01 * i22 - i12 * i02) + i02 * (i01 * i12 - i11 * i02)
    # tr(I⁻¹) = tr(adj I) / det I
    return (c00 + c11 + c22) / det + 2.0 * v if criterion == "A" else -ca.log(det) + shift_logdet


#: length of a row's goal vector: [f_T, w] (:func:`goal_expr`)
N_GOAL = 2


def goal_expr(f, goal):
    """(g, g', g'') of a row's value f [criterion units] and goal [f_T, w] (SX or MX; module
    docstring, "Goal"): the smooth hinge g = w · softplus((f − f_T)/w) and its first two
    derivatives in f."""
    f_t, width = goal[0], goal[1]
    x = (f - f_t) / width
    # softplus(x) = log(1 + eˣ) = max(x, 0) + log(1 + e^−|x|)   (no overflow for large |x|)
    g = width * (ca.fmax(x, 0.0) + ca.log1p(ca.exp(-ca.fabs(x))))
    # g' = σ(x),  g'' = σ(x) (1 − σ(x)) / w
    sig = 1.0 / (1.0 + ca.exp(-x))
    return g, sig, sig * (1.0 - sig) / width


def goal_values(f: np.ndarray, goal: np.ndarray | None) -> np.ndarray:
    """g(f) of row values f (any shape) for goal [f_T, w] (:func:`goal_expr` in numpy); f itself
    when goal is None."""
    if goal is None:
        return np.asarray(f, dtype=float)
    f_t, width = float(goal[0]), float(goal[1])
    # g = w · softplus((f − f_T)/w),  softplus(x) = log(1 + eˣ) = logaddexp(0, x)
    return width * np.logaddexp(0.0, (np.asarray(f, dtype=float) - f_t) / width)


#: length of a row's NLoS vector: [π₀ n, n, α₀, α₁, α₂, κ, α₃, v_f] (module docstring)
N_NLOS = 8


def coverage_cut(dist_m, reach_m):
    """c(d) = 1 / (1 + exp((d − R)/COVERAGE_EDGE_M)) of distances (any shape) [m], numpy (module
    docstring, "Coverage"; the kernels compute the same in CasADi)."""
    z = np.clip((np.asarray(dist_m, dtype=float) - reach_m) / COVERAGE_EDGE_M, -700.0, 700.0)
    return 1.0 / (1.0 + np.exp(z))


def shift_var_expr(nl_count, n_count, kappa):
    """v = ½ (κ π̂)², π̂ = nl_count / n_count (module docstring)."""
    pi_hat = nl_count / (n_count + 1e-9)
    return 0.5 * (kappa * pi_hat) ** 2


def _position_part(J: dict, d: int, bias: bool) -> dict:
    """{(i, j)} of the position information: J itself, or its Schur complement A − c cᵀ/s (bias last)."""
    if not bias:
        return {(i, j): J[i, j] for i in range(d) for j in range(i, d)}
    s = J[d, d]
    return {(i, j): J[i, j] - J[i, d] * J[j, d] / s for i in range(d) for j in range(i, d)}


def row_expr(z, x_c, u, P, scale, noise_par, delta, nlos, shape: Shape):
    """SX f of one row (module docstring). z: 3H waypoints stacked; x_c, u: 3; P: p·p row-major;
    scale: s; noise_par: [s0, a, b, σ_gps², R] (R the cell's reach [m]); delta: Δ;
    nlos: [π₀ n, n, α₀, α₁, α₂, κ, α₃, v_f].
    Returns (f, [ℓ_1 … ℓ_H])."""
    d, p, n_q = shape.dim, shape.n_par, shape.n_quad
    t = (np.arange(n_q) + 0.5) / n_q
    acc = {(i, j): P[i * p + j] for i in range(p) for j in range(i, p)}
    s0, a, b, sgps2, reach = noise_par[0], noise_par[1], noise_par[2], noise_par[3], noise_par[4]
    nl_count, n_count = nlos[0], nlos[1]
    prev, lengths = x_c, []
    for h in range(shape.horizon):
        wp = z[3 * h:3 * h + 3]
        step = wp - prev
        length = ca.sqrt(ca.sumsqr(step) + SQRT_EPS_M2)
        lengths.append(length)
        per_point = length / (delta * n_q)  # ranges each quadrature point stands for
        for q in range(n_q):
            rel = prev + t[q] * step - u
            dist = ca.sqrt(ca.sumsqr(rel) + SQRT_EPS_M2)
            # n / σ_eff², σ_eff² = (s σ(d))² + σ_gps²
            w = per_point / ((scale * (s0 + a * ca.exp(b * dist))) ** 2 + sgps2)
            # c(d): no ranges beyond the cell's reach (module docstring, "Coverage")
            w = w / (1.0 + ca.exp((dist - reach) / COVERAGE_EDGE_M))
            hv = [rel[i] / dist for i in range(d)] + ([-1.0] if shape.bias else [])
            # the NLoS probability at this point's bearing and elevation from the user,
            # p(β, ε) = σ(α·(1, cos β, sin β, sin ε))
            rho = ca.sqrt(rel[0] ** 2 + rel[1] ** 2 + SQRT_EPS_M2)
            p_nlos = 1.0 / (1.0 + ca.exp(-(nlos[2] + nlos[3] * rel[0] / rho + nlos[4] * rel[1] / rho
                                           + nlos[6] * rel[2] / dist)))
            nl_count = nl_count + per_point * p_nlos
            n_count = n_count + per_point
            for i in range(p):
                for j in range(i, p):
                    acc[i, j] = acc[i, j] + w * hv[i] * hv[j]
        prev = wp
    v = shift_var_expr(nl_count, n_count, nlos[5]) + nlos[7]
    return criterion_expr(_position_part(acc, d, shape.bias), d, shape.criterion, v), lengths


def jit_function(name: str, inputs: list, outputs: list, directory: str | None = None) -> ca.Function:
    """The default :data:`compile_hook`: a CasADi Function compiled by the system C compiler.

    directory: where the compiler's C source lives while the Function does (ending in a path
    separator; None: CasADi's default, the current directory)."""
    jit_options: dict = {"flags": list(JIT_FLAGS), "verbose": False}
    if directory is not None:
        jit_options["directory"] = directory
    opts = {"jit": True, "compiler": "shell", "jit_cleanup": True, "jit_options": jit_options}
    return ca.Function(name, inputs, outputs, opts)


#: how kernels are compiled: (name, SX inputs, SX outputs) → Function. Replace it (e.g. with one
#: that loads a compiled library from a cache folder) to keep the compiler's I/O elsewhere; None:
#: never compile (the SX virtual machine).
compile_hook: Callable[[str, list, list], ca.Function] | None = jit_function


_KERNELS: dict[tuple[str, Shape, bool], ca.Function] = {}


def _build(name: str, inputs: list, outputs: list, compiled: bool) -> ca.Function:
    if compiled and compile_hook is not None:
        try:
            return compile_hook(name, inputs, outputs)
        except RuntimeError as exc:  # no C compiler: the same function, interpreted
            log.warning("could not compile the planner kernel %s (%s); interpreting it", name, exc)
    return ca.Function(name, inputs, outputs)


def kernel(kind: str, shape: Shape, compiled: bool = True) -> ca.Function:
    """A row kernel, built (and compiled) once per process:

    "value": (z, x_c, u, P, s, noise, Δ, nlos) → f;  "vgh": the same → (f, ∇_z f, triu ∇²_z f);
    "prior": (P, nlos) → f(P), the criterion of the prior information and the present NLoS shift
    alone (never compiled).
    """
    key = (kind, shape, bool(compiled and kind != "prior"))
    if key in _KERNELS:
        return _KERNELS[key]
    p = shape.n_par
    P = ca.SX.sym("P", p * p)
    nlos = ca.SX.sym("nlos", N_NLOS)
    tag = f"{shape.criterion}{shape.dim}{'b' if shape.bias else ''}h{shape.horizon}q{shape.n_quad}"
    if kind == "prior":
        prior = {(i, j): P[i * p + j] for i in range(p) for j in range(i, p)}
        v = shift_var_expr(nlos[0], nlos[1], nlos[5]) + nlos[7]
        f = criterion_expr(_position_part(prior, shape.dim, shape.bias), shape.dim, shape.criterion, v)
        fun = ca.Function(f"prior_{tag}", [P, nlos], [f])
    elif kind in ("value", "vgh"):
        z = ca.SX.sym("z", 3 * shape.horizon)
        x_c, u, scale = ca.SX.sym("x_c", 3), ca.SX.sym("u", 3), ca.SX.sym("s")
        noise_par, delta = ca.SX.sym("noise", N_NOISE_PAR), ca.SX.sym("delta")
        f, _ = row_expr(z, x_c, u, P, scale, noise_par, delta, nlos, shape)
        ins = [z, x_c, u, P, scale, noise_par, delta, nlos]
        if kind == "value":
            fun = _build(f"row_{tag}", ins, [f], compiled)
        else:
            hess, grad = ca.hessian(f, z)
            fun = _build(f"row_vgh_{tag}", ins, [f, grad, ca.triu(hess)], compiled)
    else:
        raise ValueError(f"kernel kind must be 'value', 'vgh' or 'prior', got {kind!r}")
    _KERNELS[key] = fun
    log.debug("built the planner's %s kernel for %s (compiled=%s)", kind, shape, key[2])
    return fun


_GOAL_FUNCTION: list[ca.Function] = []


def goal_function() -> ca.Function:
    """(f, goal) → (g, g', g'') of :func:`goal_expr` for one row (built once per process, interpreted:
    three scalars)."""
    if not _GOAL_FUNCTION:
        f, goal = ca.SX.sym("f"), ca.SX.sym("goal", N_GOAL)
        _GOAL_FUNCTION.append(ca.Function("goal", [f, goal], list(goal_expr(f, goal))))
    return _GOAL_FUNCTION[0]


_MAPS: dict[tuple[int, int], ca.Function] = {}


def mapped(fun: ca.Function, n: int) -> ca.Function:
    """`fun` over n columns (serial map; a few per process, so cached by size)."""
    key = (id(fun), n)
    if key not in _MAPS:
        if len(_MAPS) > 256:
            _MAPS.clear()
        _MAPS[key] = fun.map(n, "serial")
    return _MAPS[key]


def row_values(shape: Shape, start_enu_m: np.ndarray, paths: np.ndarray, users_enu_m: np.ndarray,
               prior_info: np.ndarray, scale: np.ndarray, noise_par: np.ndarray, delta_m: float,
               nlos: np.ndarray, compiled: bool = True) -> np.ndarray:
    """f of every (candidate, row): paths (C, H, 3); users_enu_m (R, 3); prior_info (R, p, p);
    scale (R,); nlos (R, N_NLOS) → (C, R), the value kernel evaluated (what IPOPT minimises, term
    by term)."""
    C, R = len(paths), len(users_enu_m)
    n = C * R
    z = np.repeat(np.asarray(paths, dtype=float).reshape(C, -1), R, axis=0).T  # (3H, C·R)
    u = np.tile(np.asarray(users_enu_m, dtype=float), (C, 1)).T
    P = np.tile(np.asarray(prior_info, dtype=float).reshape(R, -1), (C, 1)).T
    s = np.tile(np.asarray(scale, dtype=float), C)[None]
    nl = np.tile(np.asarray(nlos, dtype=float).reshape(R, N_NLOS), (C, 1)).T
    x_c = np.asarray(start_enu_m, dtype=float)
    f = mapped(kernel("value", shape, compiled), n)(z, x_c, u, P, s, noise_par, delta_m, nl)
    return np.asarray(f, dtype=float).reshape(C, R)


def prior_values(shape: Shape, prior_info: np.ndarray, nlos: np.ndarray) -> np.ndarray:
    """f(P) of every row: prior_info (R, p, p), nlos (R, N_NLOS) → (R,) (the prior kernel evaluated)."""
    R = len(prior_info)
    out = mapped(kernel("prior", shape), R)(np.asarray(prior_info, dtype=float).reshape(R, -1).T,
                                            np.asarray(nlos, dtype=float).reshape(R, N_NLOS).T)
    return np.asarray(out, dtype=float).reshape(R)
