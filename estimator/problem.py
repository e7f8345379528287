"""Input checking and the array form of a SLAM problem (docs/design.md §5).

Keyframes arrive as a list of :class:`estimator.types.Keyframe`; the solver works on dense arrays:

    gps_enu_m   (N, 3)  GPS fix per keyframe [m, ENU]
    range_m     (N, K)  measured range keyframe n -> user k [m], NaN where none
    mask        (N, K)  True where a range exists
    odom_enu_m  (N, 3)  displacement from keyframe n−1 to n [m, ENU] (row 0 unused)
    odom_mask   (N,)    True where a relative-motion factor links n−1 and n
    odom_sigma_m (N,)   its per-axis σ [m] (NaN where none; None: params.motion_sigma_m)
    chain_start (N,)    True where keyframe n starts a vehicle's chain: no GPS link or motion factor
                        to keyframe n−1, another vehicle's (None: keyframe 0 alone)
    vehicle     (N,)    the vehicle (Keyframe.vehicle) that took keyframe n (None: one vehicle)

A fleet's keyframes (Keyframe.vehicle) are solved sorted by vehicle, each vehicle's in the order
they came (estimator.batch.solve_batch): every chain link is then between rows n−1 and n, and the
keyframe block of the normal matrix stays block-tridiagonal, with no link across a chain start.

User parameters are packed per user as θ_k = [east, north, (up if 3-D), (bias if estimated)], an
array Θ of shape (K, p) with p = d + (1 if bias). In 2-D mode `up` is the known ground height.
"""

from __future__ import annotations

import operator
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import repeat

import numpy as np

from estimator.gps import gps_phi
from estimator.noise import NoiseModel
from estimator.robust import check_loss
from estimator.types import Keyframe, SolverParams
from uavloc.errors import EstimatorError


def check_params(params: SolverParams) -> None:
    """Raise EstimatorError naming the first invalid solver setting."""
    if not isinstance(params, SolverParams):
        raise EstimatorError(f"params must be SolverParams, got {type(params).__name__}")
    check_loss(params.loss, params.loss_scale)
    if not (0.0 < params.nlos_prob < 1.0):
        raise EstimatorError(f"nlos_prob must be in (0, 1), got {params.nlos_prob!r}")
    if not (np.isfinite(params.nlos_mean_m) and params.nlos_mean_m > 0):
        raise EstimatorError(f"nlos_mean_m must be positive, got {params.nlos_mean_m!r}")
    if params.user_dim not in (2, 3):
        raise EstimatorError(f"user_dim must be 2 or 3, got {params.user_dim!r}")
    if not (np.isfinite(params.bias_prior_sigma_m) and params.bias_prior_sigma_m > 0):
        raise EstimatorError(f"bias_prior_sigma_m must be positive, got {params.bias_prior_sigma_m!r}")
    jb = params.jackknife_blocks
    if isinstance(jb, bool) or not isinstance(jb, int | np.integer) or not (jb == 0 or 2 <= jb <= 100):
        raise EstimatorError(f"jackknife_blocks must be 0 or an integer in 2..100, got {params.jackknife_blocks!r}")
    if not isinstance(params.nlos_shift, bool | np.bool_):
        raise EstimatorError(f"nlos_shift must be true or false, got {params.nlos_shift!r}")
    if params.bias_held not in ("zero", "sawtooth"):
        raise EstimatorError(f"bias_held must be 'zero' or 'sawtooth', got {params.bias_held!r}")
    cov = params.coverage_m
    if isinstance(cov, bool) or not isinstance(cov, int | float | np.integer | np.floating) or not cov > 0:
        raise EstimatorError(f"coverage_m must be positive (inf: unlimited), got {cov!r}")
    if params.motion_sigma_m is not None and not (
        np.isfinite(params.motion_sigma_m) and params.motion_sigma_m > 0
    ):
        raise EstimatorError(f"motion_sigma_m must be positive or None, got {params.motion_sigma_m!r}")
    if not (np.isfinite(params.delta_m) and params.delta_m >= 0):
        raise EstimatorError(f"delta_m must be a non-negative number, got {params.delta_m!r}")
    if int(params.max_iterations) < 1:
        raise EstimatorError(f"max_iterations must be >= 1, got {params.max_iterations!r}")
    if not (np.isfinite(params.step_tol_m) and params.step_tol_m > 0):
        raise EstimatorError(f"step_tol_m must be positive, got {params.step_tol_m!r}")
    if not (np.isfinite(params.step_tol_sigma) and params.step_tol_sigma >= 0):
        raise EstimatorError(f"step_tol_sigma must be >= 0, got {params.step_tol_sigma!r}")
    if int(params.online_resolve_every) < 1:
        raise EstimatorError(f"online_resolve_every must be >= 1, got {params.online_resolve_every!r}")
    if not (np.isfinite(params.online_max_step_m) and params.online_max_step_m > 0):
        raise EstimatorError(f"online_max_step_m must be positive, got {params.online_max_step_m!r}")
    if not (np.isfinite(params.step_tol_uav_m) and params.step_tol_uav_m > 0):
        raise EstimatorError(f"step_tol_uav_m must be positive, got {params.step_tol_uav_m!r}")
    if int(params.window) < 2:
        raise EstimatorError(f"window must be >= 2 keyframes, got {params.window!r}")


def check_users(n_users: int, user_up_m: np.ndarray) -> np.ndarray:
    """Validate the user count and (K,) ground heights; return them as a float array."""
    if isinstance(n_users, bool) or not isinstance(n_users, int | np.integer) or n_users < 1:
        raise EstimatorError(f"n_users must be a positive integer, got {n_users!r}")
    up = np.asarray(user_up_m, dtype=float)
    if up.shape != (n_users,):
        raise EstimatorError(f"user_up_m must have shape ({n_users},), got {up.shape}")
    if not np.all(np.isfinite(up)):
        raise EstimatorError(f"user_up_m must be finite, got {up.tolist()}")
    return up


def check_keyframe(kf: Keyframe, n_users: int, index: int | None = None) -> tuple[np.ndarray, ...]:
    """Validate one keyframe; return (gps (3,), user_idx (m,) int, range_m (m,), odom (3,) or None)."""
    where = "keyframe" if index is None else f"keyframe {index}"
    if not isinstance(kf, Keyframe):
        raise EstimatorError(f"{where} must be a Keyframe, got {type(kf).__name__}")
    gps = np.asarray(kf.gps_enu_m, dtype=float)
    if gps.shape != (3,):
        raise EstimatorError(f"{where}: gps_enu_m must have shape (3,), got {gps.shape}")
    if not np.isfinite(gps).all():
        raise EstimatorError(f"{where}: gps_enu_m must be finite, got {gps.tolist()}")
    idx = np.asarray(kf.user_idx)
    rng = np.asarray(kf.range_m, dtype=float)
    if idx.ndim != 1 or rng.ndim != 1 or idx.shape != rng.shape:
        raise EstimatorError(
            f"{where}: user_idx and range_m must be 1-D of equal length, got {idx.shape} and {rng.shape}"
        )
    if idx.size:
        if idx.dtype.kind not in "iu":
            raise EstimatorError(f"{where}: user_idx must be integers, got {idx.tolist()}")
        if idx.min() < 0 or idx.max() >= n_users:
            bad = idx[(idx < 0) | (idx >= n_users)]
            raise EstimatorError(f"{where}: user index {int(bad[0])} outside [0, {n_users})")
        if idx.size > 1:
            lst = idx.tolist()
            if len(set(lst)) != len(lst):
                raise EstimatorError(f"{where}: a user appears twice in user_idx {lst}")
        if not rng.min() >= 0 or not np.isfinite(rng.max()):
            bad = ~np.isfinite(rng) | (rng < 0)
            raise EstimatorError(
                f"{where}: range_m must be finite and >= 0, got {float(rng[bad][0])!r} for user {int(idx[bad][0])}"
            )
        idx = idx.astype(np.intp, copy=False)
    else:
        idx = idx.astype(np.intp)
    if isinstance(kf.t_s, bool) or not isinstance(kf.t_s, int | float | np.floating | np.integer) or not (
            np.isfinite(kf.t_s)):
        raise EstimatorError(f"{where}: t_s must be a finite number, got {kf.t_s!r}")
    odom = None
    if kf.odom_enu_m is not None:
        odom = np.asarray(kf.odom_enu_m, dtype=float)
        if odom.shape != (3,) or not np.isfinite(odom).all():
            raise EstimatorError(f"{where}: odom_enu_m must be 3 finite numbers, got {np.ravel(odom).tolist()}")
    v = kf.vehicle
    if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 0:
        raise EstimatorError(f"{where}: vehicle must be an integer >= 0, got {v!r}")
    sm = kf.odom_sigma_m
    if sm is not None and (isinstance(sm, bool) or not isinstance(sm, int | float | np.floating | np.integer)
                           or not (np.isfinite(sm) and sm > 0)):
        raise EstimatorError(f"{where}: odom_sigma_m must be a positive number or None, got {sm!r}")
    return gps, idx, rng, odom


@dataclass
class Problem:
    """Array form of a SLAM problem; see the module docstring for shapes and units."""

    gps_enu_m: np.ndarray
    range_m: np.ndarray
    mask: np.ndarray
    odom_enu_m: np.ndarray
    odom_mask: np.ndarray
    user_up_m: np.ndarray
    noise: NoiseModel
    params: SolverParams
    #: (K,) per-user NLoS probability π_k of the "nlos" loss (None: params.nlos_prob for all)
    nlos_prob_k: np.ndarray | None = None
    #: (N,) keyframe times [s] for the Gauss–Markov GPS links (None: GPS treated as white)
    t_s: np.ndarray | None = None
    #: keyframe 0 carries its own GPS prior (False in an online window whose keyframe 0 is linked
    #: to a keyframe already folded into the marginalization prior)
    gps_first: bool = True
    #: (K,) per-user scale s_k of the range noise, σ_k(d) = s_k σ(d) (None: 1 for all)
    noise_scale_k: np.ndarray | None = None
    #: (K,) per-user σ of the bias prior (None: params.bias_prior_sigma_m for all; estimator.solve
    #: sets the held σ of params.bias_held where the bias selection held a bias)
    bias_sigma_k: np.ndarray | None = None
    #: (K,) per-user mean of the bias prior [m] (None: 0 for all; estimator.solve sets the held
    #: mean of params.bias_held where the bias selection held a bias)
    bias_mean_k: np.ndarray | None = None
    #: (K,) users whose bias the selection keeps whatever the test says (a tracked clock sawtooth:
    #: its fitted offset is uncertain, and the free bias carries that into the covariance)
    bias_force_k: np.ndarray | None = None
    #: (N, K) gain g_nk of user k's bias in range n, r̂ = d + b_k g_nk (None: 1 everywhere); a
    #: tracked clock sawtooth (estimator.clock) makes b_k its amplitude and g its shape
    bias_gain: np.ndarray | None = None
    #: (N,) per-axis σ of each keyframe's motion factor [m] where odom_mask (None: params.motion_sigma_m)
    odom_sigma_m: np.ndarray | None = None
    #: (N,) True where a keyframe starts a vehicle's chain (module docstring); None: keyframe 0 alone
    chain_start: np.ndarray | None = None
    #: (N,) int vehicle of each keyframe (Keyframe.vehicle; estimator.silence: whose cell was silent);
    #: None: one vehicle
    vehicle: np.ndarray | None = None

    def odom_weight(self) -> np.ndarray:
        """(N,) weight 1/σ_m,n² of the motion factor linking keyframe n−1 to n; 0 where none."""
        if self.odom_sigma_m is None:
            sm = self.params.motion_sigma_m
            return self.odom_mask / (sm * sm) if sm is not None else np.zeros(self.n_keyframes)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.odom_mask, 1.0 / np.square(self.odom_sigma_m), 0.0)

    def gps_phi(self) -> np.ndarray:
        """(N,) Gauss–Markov links φ_n of the GPS factors (estimator.gps.gps_phi); 0 when white."""
        n = self.n_keyframes
        if self.t_s is None:
            return np.zeros(n)
        tau = self.noise.gps_tau_used_s
        phi = gps_phi(self.t_s[:n], tau)
        if self.chain_start is not None:
            # a vehicle's first keyframe: its own prior, no link to another vehicle's fix
            phi[self.chain_start[:n]] = 0.0
        return phi

    @property
    def gps_linked(self) -> bool:
        """True when GPS factors link consecutive keyframes (τ > 0 and times known)."""
        return self.t_s is not None and self.noise.gps_tau_used_s > 0.0 and self.n_keyframes > 1

    @property
    def n_keyframes(self) -> int:
        return int(self.gps_enu_m.shape[0])

    @property
    def n_users(self) -> int:
        return int(self.range_m.shape[1])

    @property
    def user_dim(self) -> int:
        return int(self.params.user_dim)

    @property
    def n_bias(self) -> int:
        return 1 if self.params.estimate_bias else 0

    @property
    def p(self) -> int:
        """Parameters per user: d (+1 with a bias)."""
        return self.user_dim + self.n_bias

    @property
    def use_motion(self) -> bool:
        """Motion factors link some keyframes (odom_mask is only set where a σ is known)."""
        return (self.params.motion_sigma_m is not None or self.odom_sigma_m is not None) and bool(
            np.any(self.odom_mask))

    def min_ranges(self) -> int:
        """Ranges a user needs before it is estimated: one more than its unknowns."""
        return self.p + 1


#: the Keyframe fields pack_keyframes reads, in one C-level call per keyframe
_KEYFRAME_FIELDS = operator.attrgetter("gps_enu_m", "user_idx", "range_m", "odom_enu_m", "t_s", "odom_sigma_m",
                                       "vehicle")


def pack_keyframes(
    keyframes: Sequence[Keyframe], n_users: int, user_up_m: np.ndarray, noise: NoiseModel,
    params: SolverParams,
) -> Problem:
    """Validate keyframes and build the dense :class:`Problem` arrays."""
    if not isinstance(noise, NoiseModel):
        raise EstimatorError(f"noise must be a NoiseModel, got {type(noise).__name__}")
    check_params(params)
    up = check_users(n_users, user_up_m)
    n = len(keyframes)
    if n < 1:
        raise EstimatorError("need at least one keyframe, got 0")
    # vectorised checks of the whole batch; on any failure the per-keyframe check names the culprit
    try:
        # (map over C-level callables: a Python loop per keyframe cost a tenth of a small solve)
        if not all(map(isinstance, keyframes, repeat(Keyframe))):
            raise ValueError
        # the fields of all keyframes in one pass
        gps_l, ui, rr, odoms, ts, osig, vv = zip(*map(_KEYFRAME_FIELDS, keyframes), strict=True)
        t_s = np.array(ts, dtype=float)
        vehicle = np.array(vv)
        gps = np.array(gps_l, dtype=float)
        # len() raises TypeError on a 0-d value; concatenate raises ValueError on mixed ndim
        lengths_l = list(map(len, ui))
        if lengths_l != list(map(len, rr)):
            raise ValueError
        lengths = np.array(lengths_l)
        idx = np.concatenate(ui)
        r = np.concatenate(rr).astype(float)
        kf_of = np.repeat(np.arange(n), lengths)
        ok = (
            gps.shape == (n, 3) and np.isfinite(gps).all()
            and idx.ndim == 1 and r.ndim == 1 and idx.shape == kf_of.shape
            and (idx.size == 0 or (idx.dtype.kind in "iu" and idx.min() >= 0 and idx.max() < n_users))
            and np.isfinite(r).all() and (r.size == 0 or r.min() >= 0)
            and t_s.shape == (n,) and np.isfinite(t_s).all()
            and vehicle.shape == (n,) and vehicle.dtype.kind in "iu" and vehicle.min() >= 0
            and not any(map(isinstance, vv, repeat((bool, np.bool_))))
        )
        if ok and idx.size:
            # a user twice in one keyframe: some (keyframe, user) cell counted more than once
            ok = int(np.bincount(kf_of * n_users + idx, minlength=n * n_users).max()) <= 1
        has_odom = any(map(operator.is_not, odoms, repeat(None)))
        if ok and has_odom:
            for o, sm in zip(odoms, osig, strict=True):
                if o is not None and (np.shape(o) != (3,) or not np.isfinite(np.asarray(o, float)).all()):
                    ok = False
                    break
                if sm is not None and (isinstance(sm, bool) or not isinstance(sm, int | float | np.number)
                                       or not (np.isfinite(sm) and sm > 0)):
                    ok = False
                    break
    except (ValueError, TypeError):
        ok = False
    if not ok:
        for i, kf in enumerate(keyframes):
            check_keyframe(kf, n_users, i)
        raise EstimatorError("keyframes are malformed")  # pragma: no cover (the loop raises)
    rng = np.full((n, n_users), np.nan, order="F")
    rng[kf_of, idx.astype(np.intp)] = r
    # a keyframe whose vehicle differs from the one before starts that vehicle's chain
    starts = np.r_[True, vehicle[1:] != vehicle[:-1]]
    chain_start = starts if starts[1:].any() else None
    odom = np.zeros((n, 3))
    odom_mask = np.zeros(n, dtype=bool)
    odom_sigma = None
    if has_odom:
        # σ_m,n: the keyframe's own, else params.motion_sigma_m; no factor where neither is known
        default = np.nan if params.motion_sigma_m is None else float(params.motion_sigma_m)
        odom_sigma = np.full(n, np.nan)
        for i, (o, sm) in enumerate(zip(odoms, osig, strict=True)):
            if o is not None and i > 0 and (chain_start is None or not chain_start[i]):
                odom[i] = o
                odom_sigma[i] = default if sm is None else float(sm)
        odom_mask = ~np.isnan(odom_sigma)
    return Problem(gps, rng, ~np.isnan(rng), odom, odom_mask, up, noise, params, t_s=t_s, odom_sigma_m=odom_sigma,
                   chain_start=chain_start,
                   vehicle=None if np.all(vehicle == vehicle[0]) else vehicle.astype(np.intp))


def users_from_theta(theta: np.ndarray, user_up_m: np.ndarray, user_dim: int) -> np.ndarray:
    """(K, p) packed user parameters -> (K, 3) ENU positions [m] (up = ground height in 2-D)."""
    users = np.empty((theta.shape[0], 3))
    users[:, :2] = theta[:, :2]
    users[:, 2] = theta[:, 2] if user_dim == 3 else user_up_m
    return users
