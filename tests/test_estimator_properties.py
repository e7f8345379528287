"""The estimator never raises on data (issue 21): property tests over degenerate inputs.

Each property draws a problem from a seeded family that reaches the ends of every range the
missions and campaigns meet — a clock sawtooth whose period is near the log's span, users seen
from one side (a straight line), every range NLoS, σ_gps and τ at their ends, 1 or 20 users,
keyframes without ranges, motion factors of tiny or huge σ, distance-dependent noise far out — and
asserts that the clock fit, the online filter step, the window marginalization, the batch solve and
the refreshed estimator return an answer whose numbers are finite where a user is estimated and
whose uncertainty is honest where not (NaN position, infinite covariance), never an exception.

hypothesis runs derandomized (the examples are a function of the test: the suite is
deterministic) and with a bounded number of examples, so the file runs in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from estimator.batch import solve_batch
from estimator.clock import SawtoothFit, fit_sawtooth, refine_sawtooth
from estimator.noise import NoiseModel
from estimator.online import OnlineEstimator
from estimator.refresh import RefreshedEstimator
from estimator.simulate import simulate
from estimator.types import Estimate, Keyframe, SolverParams

PROPS = settings(derandomize=True, deadline=None, database=None, print_blob=True,
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def props(max_examples: int) -> settings:
    """PROPS with this many examples."""
    return settings(PROPS, max_examples=max_examples)


@dataclass(frozen=True)
class World:
    """One drawn problem: keyframes, K users' ground heights, the noise model, the solver params."""

    keyframes: list
    n_users: int
    user_up_m: np.ndarray
    noise: NoiseModel
    params: SolverParams
    users_enu_m: np.ndarray


@st.composite
def worlds(draw, max_keyframes: int = 120, max_users: int = 20) -> World:
    """A simulated problem at the ends of its ranges (module docstring)."""
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    n_users = draw(st.sampled_from([1, 2, 5, max_users]))
    n = draw(st.integers(8, max_keyframes))
    pattern = draw(st.sampled_from(["circle", "line", "lawnmower"]))
    far = draw(st.sampled_from([1.0, 3.0]))  # users up to 330 m away with far = 3
    distance_noise = draw(st.booleans())
    noise = NoiseModel(
        sigma_gps_m=draw(st.sampled_from([0.3, 1.0, 3.0])),
        range_s0_m=draw(st.sampled_from([0.05, 3.0, 10.0])),
        range_a_m=0.3 if distance_noise else 0.0, range_b_per_m=0.01 if distance_noise else 0.0,
        gps_tau_s=draw(st.sampled_from([0.0, 60.0, 600.0])),
    )
    ang = rng.uniform(0, 2 * np.pi, n_users)
    rad = rng.uniform(40.0, 110.0, n_users) * far
    users = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), np.zeros(n_users)])
    if pattern == "line":  # seen from one side only
        users[:, 1] = np.abs(users[:, 1]) + 20.0
    sc = simulate(rng, n_keyframes=n, pattern=pattern, noise=noise, users_enu_m=users,
                  p_nlos=draw(st.sampled_from([0.0, 0.3, 1.0])), nlos_mean_m=draw(st.sampled_from([5.0, 40.0])),
                  p_visible=draw(st.sampled_from([1.0, 0.5, 0.1])), gps_tau_s=noise.gps_tau_s,
                  dt_s=draw(st.sampled_from([0.4, 1.0])),
                  odom_sigma_m=draw(st.sampled_from([None, 1e-4, 0.05, 1e3])))
    t = np.array([kf.t_s for kf in sc.keyframes])
    span = max(float(t[-1] - t[0]), 1.0)
    # a sawtooth per user: none, or of period from a fifth of the span to past it
    amp = draw(st.sampled_from([0.0, 8.0, 20.0]))
    period = span * rng.choice([0.2, 0.5, 0.9, 1.0, 1.1], n_users)
    phase = rng.uniform(0, 1, n_users)
    saw = amp * np.mod(t[:, None] / period[None, :] - phase[None, :], 1.0)
    empty = rng.random(n) < draw(st.sampled_from([0.0, 0.3]))  # keyframes without ranges
    kfs = []
    for i, kf in enumerate(sc.keyframes):
        idx = kf.user_idx[:0] if empty[i] else kf.user_idx
        kfs.append(replace(kf, user_idx=idx, range_m=kf.range_m[: idx.size] + saw[i, idx]))
    params = SolverParams(
        window=draw(st.sampled_from([12, 100])),
        loss=draw(st.sampled_from(["nlos", "huber", "none"])),
        motion_sigma_m=draw(st.sampled_from([None, 1e-3, 10.0])),
        bias_prior_sigma_m=draw(st.sampled_from([1e-3, 10.0, 1e4])),
    )
    return World(kfs, n_users, sc.user_up_m, noise, params, users)


def _assert_honest(est: Estimate, n_users: int) -> None:
    """Finite position and symmetric positive semi-definite covariance for every estimated user,
    NaN position and infinite covariance for the others."""
    assert est.users_enu_m.shape == (n_users, 3)
    for k in range(n_users):
        cov = np.asarray(est.cov_users_m2[k], dtype=float)
        if np.all(np.isfinite(est.users_enu_m[k])):
            assert np.all(np.isfinite(cov)) or np.all(np.isinf(np.diag(cov))), (k, cov)
            if np.all(np.isfinite(cov)):
                np.testing.assert_allclose(cov, cov.T, rtol=1e-6, atol=1e-9 * (1.0 + np.abs(cov).max()))
                assert np.linalg.eigvalsh(0.5 * (cov + cov.T))[0] >= -1e-6 * (1.0 + np.abs(cov).max()), (k, cov)
        else:
            assert np.all(np.isnan(est.users_enu_m[k, :2])), (k, est.users_enu_m[k])
            assert not np.all(np.isfinite(cov)), (k, cov)
    assert np.all(np.isfinite(est.error_bound_95_m()) | np.isinf(est.error_bound_95_m()))


# --- the clock fit ------------------------------------------------------------------------------


@st.composite
def clock_series(draw):
    """(t (n,), residuals (n,), nuisance (n, 2) or None): a sawtooth of any period against the
    samples' span, with noise from none to huge, duplicated times and a few non-finite values."""
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    n = draw(st.sampled_from([0, 1, 15, 16, 40, 300]))
    span = draw(st.sampled_from([0.0, 1e-3, 30.0, 600.0]))
    t = np.sort(rng.uniform(0.0, span, n)) + draw(st.sampled_from([0.0, 1e6]))
    if draw(st.booleans()):
        t = np.round(t, 0)  # many equal times
    period = max(span, 1e-3) * draw(st.sampled_from([0.05, 0.5, 0.9, 1.0, 1.5]))
    amp = draw(st.sampled_from([0.0, 1e-9, 12.0, 1e6]))
    r = amp * np.mod(t / period + 0.3, 1.0) + rng.normal(size=n) * draw(st.sampled_from([0.0, 1.0, 1e4]))
    if n and draw(st.booleans()):
        r[rng.integers(0, n)] = np.nan
    z = rng.normal(size=(n, 2)) if draw(st.booleans()) else None
    return t, r, z, period


def _finite_fit(fit: SawtoothFit) -> bool:
    return bool(np.all(np.isfinite([fit.period_s, fit.phase, fit.amplitude_m, fit.offset_m]))
                and fit.period_s > 0 and np.isfinite(fit.explained))


@props(60)
@given(clock_series())
def test_clock_fit_and_refinement_return_a_finite_sawtooth_or_none(series):
    t, r, z, period = series
    fit = fit_sawtooth(t, r, z)
    assert fit is None or _finite_fit(fit)
    prev = fit if fit is not None else SawtoothFit(period, 0.3, 12.0, 0.0, 0.5)
    new = refine_sawtooth(t, r, prev, z)
    assert new is prev or _finite_fit(new)


# --- the online estimator: filter steps and marginalization --------------------------------------


@props(12)
@given(worlds(max_keyframes=90))
def test_online_filter_steps_and_marginalization_never_raise(world):
    """Every keyframe, through filter steps (online_resolve_every = 5) and, with window 12, the
    marginalization of the oldest keyframes."""
    on = OnlineEstimator(world.n_users, world.user_up_m, world.noise, world.params)
    for kf in world.keyframes:
        est = on.add_keyframe(kf)
    _assert_honest(est, world.n_users)


# --- the batch solve and the refreshed estimator -------------------------------------------------


@props(10)
@given(worlds(max_keyframes=80))
def test_batch_solve_never_raises_and_reports_honest_uncertainty(world):
    est = solve_batch(world.keyframes, world.n_users, world.user_up_m, world.noise, world.params)
    _assert_honest(est, world.n_users)
    # a user with fewer ranges than unknowns is not estimated
    counts = np.zeros(world.n_users, dtype=int)
    for kf in world.keyframes:
        counts[kf.user_idx] += 1
    assert np.all(np.isnan(est.users_enu_m[counts < 3, 0]))


@props(6)
@given(worlds(max_keyframes=80, max_users=5))
def test_refreshed_estimator_never_raises(world):
    """The mission's estimator: online steps, warm and cold batch refreshes (clock refinement)."""
    ref = RefreshedEstimator(world.n_users, world.user_up_m, world.noise, world.params)
    for kf in world.keyframes:
        est = ref.add_keyframe(kf)
    assert ref.online_failure is None
    _assert_honest(est, world.n_users)
    _assert_honest(ref.refresh(), world.n_users)


@pytest.mark.parametrize("n_ranges", [0, 1, 2, 3])
def test_a_user_with_too_few_ranges_is_reported_not_estimated(n_ranges):
    """A user ranged 0..3 times among 40 keyframes: NaN and an infinite covariance until it has
    the p + 1 ranges its p unknowns need (never an exception from the solve)."""
    sc = simulate(np.random.default_rng(3), n_users=2, n_keyframes=40)
    kfs = [Keyframe(kf.gps_enu_m, kf.user_idx[:1] if i >= n_ranges else kf.user_idx,
                    kf.range_m[:1] if i >= n_ranges else kf.range_m, t_s=kf.t_s)
           for i, kf in enumerate(sc.keyframes)]
    est = solve_batch(kfs, 2, sc.user_up_m, NoiseModel())
    _assert_honest(est, 2)
    assert np.all(np.isfinite(est.users_enu_m[0]))
    assert np.isnan(est.users_enu_m[1, 0]) == (n_ranges < 4)
