"""A fleet in the estimator: vehicles as a dimension of one problem (docs/fleet.md).

Each vehicle's keyframes are a chain of their own: its drifting GPS error and its displacement link
a keyframe to that vehicle's previous one. The reference is the one-vehicle solver, whose chain link
vanishes across a long enough pause (φ = exp(−Δt/τ) → 0): vehicle B's keyframes flown after A's,
a day later, with no displacement across the pause, are the same problem as the fleet's.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.batch import solve_batch
from estimator.noise import NoiseModel
from estimator.problem import pack_keyframes
from estimator.refresh import RefreshedEstimator
from estimator.types import Keyframe, SolverParams
from uavloc.errors import EstimatorError

USERS = np.array([[60.0, 40.0, 0.0], [-50.0, 70.0, 0.0], [20.0, -80.0, 0.0]])
NOISE = NoiseModel(range_s0_m=1.0, range_a_m=0.0, range_b_per_m=0.0, sigma_gps_m=1.0, gps_tau_s=60.0)
PARAMS = SolverParams(track_clock=False, motion_sigma_m=0.2)


def _fleet(seed: int = 3, n: int = 40) -> list[Keyframe]:
    """Two vehicles flying circles at once, interleaved in time; each with its own drifting GPS
    offset (Gauss–Markov, τ = 60 s) and its own displacement between its keyframes."""
    rng = np.random.default_rng(seed)
    out = []
    for v, (cx, r) in enumerate(((-30.0, 40.0), (40.0, 30.0))):
        beta = rng.normal(0.0, 1.0, 3)
        prev = None
        for i in range(n):
            t = 2.0 * i + 0.7 * v
            a = 0.15 * i + v
            pos = np.array([cx + r * np.cos(a), r * np.sin(a), 30.0 + 5 * v])
            beta = np.exp(-2.0 / 60.0) * beta + rng.normal(0.0, np.sqrt(1 - np.exp(-4.0 / 60.0)), 3)
            d = np.linalg.norm(USERS - pos, axis=1)
            odom = None if prev is None else pos - prev + rng.normal(0.0, 0.2, 3)
            out.append(Keyframe(pos + beta, np.arange(3), d + rng.normal(0.0, 1.0, 3), odom_enu_m=odom, t_s=t,
                                odom_sigma_m=None if odom is None else 0.2, vehicle=v))
            prev = pos
    return sorted(out, key=lambda kf: kf.t_s)


def test_a_fleet_is_its_vehicles_chains_apart():
    kfs = _fleet()
    est = solve_batch(kfs, 3, USERS[:, 2], NOISE, PARAMS)
    # the reference: one vehicle flying A's chain, then B's a day later (no link across the pause)
    a = [kf for kf in kfs if kf.vehicle == 0]
    b = [kf for kf in kfs if kf.vehicle == 1]
    b_later = [dataclasses.replace(kf, vehicle=0, t_s=kf.t_s + 86400.0,
                                   odom_enu_m=None if i == 0 else kf.odom_enu_m,
                                   odom_sigma_m=None if i == 0 else kf.odom_sigma_m) for i, kf in enumerate(b)]
    ref = solve_batch(a + b_later, 3, USERS[:, 2], NOISE, PARAMS)
    np.testing.assert_allclose(est.users_enu_m, ref.users_enu_m, atol=1e-6)
    np.testing.assert_allclose(est.cov_users_m2, ref.cov_users_m2, rtol=1e-6, atol=1e-9)
    # the track comes back in the order the keyframes were given
    order = [i for i, kf in enumerate(kfs) if kf.vehicle == 0] + [i for i, kf in enumerate(kfs) if kf.vehicle == 1]
    np.testing.assert_allclose(est.uav_enu_m[order], ref.uav_enu_m, atol=1e-6)
    assert np.all(est.error_bound_95_m() < 3.0)


def test_no_chain_link_crosses_vehicles():
    kfs = sorted(_fleet(n=5), key=lambda kf: kf.vehicle)
    prob = pack_keyframes(kfs, 3, USERS[:, 2], NOISE, PARAMS)
    assert prob.chain_start.tolist() == [True] + [False] * 4 + [True] + [False] * 4
    assert prob.gps_phi()[5] == 0.0 and np.all(prob.gps_phi()[[1, 2, 3, 4, 6, 7, 8, 9]] > 0.9)
    assert not prob.odom_mask[5] and prob.odom_mask[6]


def test_refreshed_estimator_takes_a_fleet_and_ends_on_the_batch_answer():
    kfs = _fleet(n=25)
    est = RefreshedEstimator(3, USERS[:, 2], NOISE, PARAMS)
    for kf in kfs:
        last = est.add_keyframe(kf)
    assert est.online_estimate is None and est.online_failure is None
    final = solve_batch(kfs, 3, USERS[:, 2], NOISE, PARAMS)
    assert last.source == "batch"
    assert np.max(np.abs(last.users_enu_m - final.users_enu_m)) < 0.5


def test_a_warm_refresh_of_a_fleet_starts_from_its_track_in_order():
    # the warm answer's track is in the given order; the solve's rows are sorted by vehicle: a
    # track started from the wrong rows would end metres off
    kfs = _fleet(n=30)
    first = solve_batch(kfs[:40], 3, USERS[:, 2], NOISE, PARAMS)
    warm = solve_batch(kfs, 3, USERS[:, 2], NOISE, PARAMS, warm=first)
    cold = solve_batch(kfs, 3, USERS[:, 2], NOISE, PARAMS)
    assert warm.state.warm_started
    # (a warm solve keeps the earlier answer's model choices: centimetres from the cold one)
    np.testing.assert_allclose(warm.users_enu_m, cold.users_enu_m, atol=0.05)
    np.testing.assert_allclose(warm.uav_enu_m, cold.uav_enu_m, atol=0.05)


@pytest.mark.parametrize("bad", [-1, 1.5, True, "a"])
def test_a_bad_vehicle_index_is_named(bad):
    kfs = _fleet(n=3)
    kfs[2] = dataclasses.replace(kfs[2], vehicle=bad)
    with pytest.raises(EstimatorError, match="keyframe 2: vehicle must be an integer"):
        solve_batch(kfs, 3, USERS[:, 2], NOISE, PARAMS)


def test_the_online_window_goes_on_when_a_user_leaves_it():
    """A UAV that flies out of a user's reach: the user's ranges all leave the online window (it
    stays estimated from the marginalized prior). The window's mirror check used to restart it from
    the window's ranges, of which there are none, and the online estimator raised."""
    from estimator.online import OnlineEstimator

    params = SolverParams(track_clock=False, window=20, online_resolve_every=2, online_check_every=2)
    online = OnlineEstimator(3, USERS[:, 2], NOISE, params)
    rng = np.random.default_rng(2)
    for i in range(80):
        pos = np.array([60.0 * np.cos(0.1 * i), 60.0 * np.sin(0.1 * i), 30.0]) if i < 40 else \
            np.array([60.0 + 8.0 * (i - 40), 0.0, 30.0])
        heard = np.arange(3) if i < 40 else np.array([0])  # users 1 and 2 out of reach after keyframe 40
        d = np.linalg.norm(USERS[heard] - pos, axis=1)
        est = online.add_keyframe(Keyframe(pos + rng.normal(0, 0.5, 3), heard, d + rng.normal(0, 1.0, len(heard)),
                                           t_s=float(i)))
    assert np.all(np.isfinite(est.users_enu_m[:, :2]))
    assert np.linalg.norm(est.users_enu_m[1, :2] - USERS[1, :2]) < 5.0
