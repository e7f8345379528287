"""The delete-a-block jackknife of each user's estimate (estimator.jackknife)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from estimator.batch import solve_batch
from estimator.jackknife import jackknife_cov, jackknife_inflate
from estimator.linearize import linearize
from estimator.noise import NoiseModel
from estimator.problem import check_params, pack_keyframes
from estimator.simulate import simulate
from estimator.types import SolverParams
from uavloc.errors import EstimatorError


def _solved_problem(seed: int, params: SolverParams):
    """A simulated problem (3 users, a circle, some NLoS) and its batch solution's x, θ."""
    sc = simulate(np.random.default_rng(seed), n_users=3, n_keyframes=160, noise=NoiseModel(), p_nlos=0.1,
                  nlos_mean_m=10.0, bias_m=np.array([0.0, 3.0, 0.0]))
    est = solve_batch(sc.keyframes, 3, sc.user_up_m, NoiseModel(), params)
    prob = pack_keyframes(sc.keyframes, 3, sc.user_up_m, NoiseModel(), params)
    prob.nlos_prob_k = est.state.nlos_prob_k
    prob.noise_scale_k = est.state.noise_scale
    theta = np.column_stack([est.users_enu_m[:, :2], est.bias_m])
    return prob, est.uav_enu_m, theta


@pytest.mark.parametrize("blocks", [2, 4, 8])
def test_jackknife_is_the_one_step_solve_without_each_block(blocks):
    """Against the slow, obvious reference: for each block, user k's normal equations (track held)
    from linearize on the problem with that block's ranges deleted, one Gauss–Newton step from θ̂."""
    params = SolverParams(bias_select=False)
    prob, x, theta = _solved_problem(3, params)
    active = np.ones(3, dtype=bool)
    v_j = jackknife_cov(prob, x, theta, active, blocks)
    n, p = x.shape[0], prob.p
    for k in range(3):
        rows = np.flatnonzero(prob.mask[:n, k])
        deltas = []
        for blk in np.array_split(rows, blocks):
            mask = prob.mask.copy()
            mask[blk, k] = False
            sub = replace(prob, mask=mask, range_m=np.where(mask, prob.range_m, np.nan))
            lin = linearize(sub, x, theta, active)
            h = lin.huu.reshape(3, p, 3, p)[k, :, k, :]
            g = lin.gu.reshape(3, p)[k]
            full = linearize(prob, x, theta, active).gu.reshape(3, p)[k]
            # the full problem's gradient at θ̂ is its convergence residual: take it out
            deltas.append(np.linalg.solve(h, g - full))
        d = np.array(deltas) - np.mean(deltas, axis=0)
        ref = (blocks - 1) / blocks * d.T @ d
        np.testing.assert_allclose(v_j[k], ref, rtol=1e-7, atol=1e-10 * np.abs(ref).max())


def test_jackknife_skips_users_without_enough_ranges():
    prob, x, theta = _solved_problem(4, SolverParams())
    v_j = jackknife_cov(prob, x, theta, np.array([True, False, True]), 40)
    assert np.all(np.isnan(v_j[1]))
    assert np.all(np.isnan(v_j)) or np.all(np.isfinite(v_j[0]))  # 160 ranges < 40 blocks · 3 · 4


def test_inflate_is_the_larger_covariance_in_every_direction():
    rng = np.random.default_rng(0)
    for _ in range(50):
        a, b = rng.normal(size=(2, 3, 3))
        cov, v_j = a @ a.T + 0.1 * np.eye(3), b @ b.T
        out = jackknife_inflate(cov, v_j)
        assert np.linalg.eigvalsh(out - cov)[0] >= -1e-9 * np.abs(out).max()
        assert np.linalg.eigvalsh(out - v_j)[0] >= -1e-9 * np.abs(out).max()
        # the smallest such: in cov's whitened frame the eigenvalues are max(λ, 1)
        li = np.linalg.inv(np.linalg.cholesky(cov))
        lam = np.linalg.eigvalsh(li @ v_j @ li.T)
        np.testing.assert_allclose(np.linalg.eigvalsh(li @ out @ li.T), np.maximum(lam, 1.0), rtol=1e-9)
    cov = np.diag([4.0, 1.0])
    assert jackknife_inflate(cov, 0.5 * cov) is cov
    assert jackknife_inflate(cov, np.full((2, 2), np.nan)) is cov


@pytest.mark.slow
def test_a_one_sided_nlos_block_widens_the_users_covariance_and_the_others_little():
    """A third of one user's ranges, one stretch of the circle, carry an NLoS excess (Exp 10 m):
    the solve shifts that user with white residuals and S⁻¹ does not say so; the jackknife over 4
    blocks brings more of them inside, at a cost to users without the block (20 problems)."""
    nees = {0: [], 4: []}
    width = {0: [], 4: []}
    for seed in range(20):
        sc = simulate(np.random.default_rng(seed), n_users=3, n_keyframes=240, noise=NoiseModel())
        n = len(sc.keyframes)
        rng = np.random.default_rng(100 + seed)
        start = int(rng.integers(0, n - n // 3))
        kfs = []
        for i, kf in enumerate(sc.keyframes):
            r = kf.range_m.copy()
            if start <= i < start + n // 3:
                r[kf.user_idx == 0] += rng.exponential(10.0)
            kfs.append(replace(kf, range_m=r))
        for g in nees:
            est = solve_batch(kfs, 3, sc.user_up_m, NoiseModel(), SolverParams(jackknife_blocks=g))
            for k in range(3):
                e = est.users_enu_m[k, :2] - sc.users_enu_m[k, :2]
                nees[g].append((k, float(e @ np.linalg.solve(est.cov_en_m2(k), e))))
                width[g].append(float(np.trace(est.cov_en_m2(k))))
    plain, jack = np.array(nees[0]), np.array(nees[4])
    block = plain[:, 0] == 0
    assert np.mean(plain[block, 1] <= 5.99) <= 0.2
    assert np.mean(jack[block, 1] <= 5.99) >= np.mean(plain[block, 1] <= 5.99) + 0.2
    # the users without a block stay honest, and their ellipses grow by less than a third on
    # average (a 4-block jackknife has 3 degrees of freedom: its chance highs widen some)
    assert np.mean(jack[~block, 1] <= 5.99) >= 0.9
    assert np.mean(np.sqrt(np.array(width[4])[~block] / np.array(width[0])[~block])) <= 4 / 3


@pytest.mark.parametrize("value", [1, 101, -2, 4.0, True, float("nan")])
def test_a_bad_number_of_blocks_is_an_estimator_error_naming_it(value):
    with pytest.raises(EstimatorError, match="jackknife_blocks"):
        check_params(SolverParams(jackknife_blocks=value))
