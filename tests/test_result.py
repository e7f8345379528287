"""The one per-user result document and the one horizontal error (mission/result.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from estimator.geodesy import Origin
from estimator.types import Estimate
from mission.result import error_bound_95_m, horizontal_error_m, user_entries, user_entries_of_estimate

ORIGIN = Origin(43.6143, 7.0716, 150.0)


def make_estimate(k: int = 3, seed: int = 0) -> Estimate:
    rng = np.random.default_rng(seed)
    users = rng.uniform(-100, 100, (k, 3))
    users[:, 2] = 0.0
    a = rng.normal(0, 1, (k, 3, 3))
    cov = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(3)
    users[-1] = np.nan  # the last user is not located
    cov[-1] = np.nan
    return Estimate(users_enu_m=users, cov_users_m2=cov, info_users=np.eye(3 * k), bias_m=rng.normal(2, 1, k),
                    uav_enu_m=np.zeros((0, 3)), ambiguous=np.array([False, True, False][:k]),
                    mirror_enu_m=np.full((k, 3), np.nan), n_ranges=np.arange(k) * 10)


@pytest.mark.parametrize(
    ("est", "truth", "err"),
    [
        ((3.0, 4.0, 10.0), (0.0, 0.0, -5.0), 5.0),   # height does not count
        ((1.0, 1.0), (1.0, 1.0), 0.0),
        ((np.nan, 0.0, 0.0), (0.0, 0.0, 0.0), np.nan),
        ((-2.0, 0.0, 0.0), (1.0, 4.0, 0.0), 5.0),
    ],
)
def test_horizontal_error_table(est, truth, err):
    got = horizontal_error_m(np.array(est), np.array(truth))
    assert (np.isnan(got) and np.isnan(err)) or got == pytest.approx(err)


def test_horizontal_error_broadcasts_over_a_history():
    hist = np.arange(24, dtype=float).reshape(4, 2, 3)  # (H, K, 3)
    truth = np.zeros((2, 3))
    np.testing.assert_allclose(horizontal_error_m(hist, truth[None]), np.hypot(hist[..., 0], hist[..., 1]))


def test_error_bound_is_the_estimators():
    est = make_estimate()
    cov = np.array([est.cov_en_m2(k) for k in range(est.n_users)])
    np.testing.assert_array_equal(np.isinf(error_bound_95_m(cov)), np.isinf(est.error_bound_95_m()))
    ok = np.isfinite(est.error_bound_95_m())
    np.testing.assert_allclose(error_bound_95_m(cov)[ok], est.error_bound_95_m()[ok], rtol=1e-12)


def test_entries_of_an_estimate_carry_the_estimators_numbers_and_are_strict_json():
    est = make_estimate()
    truth = np.array([[10.0, 20.0, 0.0], [0.0, 0.0, 0.0], [5.0, 5.0, 0.0]])
    ours = user_entries_of_estimate(est, ORIGIN, ["a", "b", "c"], truth)
    bound = est.error_bound_95_m()
    for k, o in enumerate(ours):
        p = est.users_enu_m[k]
        assert o["ambiguous"] == bool(est.ambiguous[k]) and o["measurements"] == int(est.n_ranges[k])
        if not np.all(np.isfinite(p)):
            assert o["enu_m"] is None and o["lat_deg"] is None
            continue
        lat, lon, alt = (float(x) for x in ORIGIN.enu_to_lla(p))
        assert o["enu_m"] == [float(x) for x in p]
        assert (o["lat_deg"], o["lon_deg"], o["alt_m"]) == pytest.approx((lat, lon, alt), rel=1e-12)
        assert o["cov_en_m2"] == est.cov_en_m2(k).tolist()
        assert o["error_bound_95_m"] == pytest.approx(bound[k], rel=1e-12)
        assert o["error_m"] == pytest.approx(np.hypot(*(p[:2] - truth[k, :2])), rel=1e-12)
    assert ours[0]["truth"]["enu_m"] == [10.0, 20.0, 0.0]
    assert ours[2]["lat_deg"] is None and ours[2]["error_m"] is None and ours[2]["error_bound_95_m"] is None
    assert ours[1]["bias_m"] == pytest.approx(float(est.bias_m[1]))
    json.dumps(ours, allow_nan=False)


def test_entries_without_an_estimate_name_every_user_unlocated():
    doc = user_entries_of_estimate(None, None, ["a", "b"])
    assert [u["id"] for u in doc] == ["a", "b"]
    assert all(u["lat_deg"] is None and u["cov_en_m2"] is None and "error_m" not in u for u in doc)


def test_entries_round_trip_the_position_through_the_origin():
    users = np.array([[30.0, -40.0, 2.0]])
    (u,) = user_entries(["a"], ORIGIN, users, np.eye(2)[None] * 4.0)
    back = ORIGIN.lla_to_enu(u["lat_deg"], u["lon_deg"], u["alt_m"])
    np.testing.assert_allclose(back, users[0], atol=1e-6)
    assert u["sigma_east_m"] == 2.0 and u["sigma_north_m"] == 2.0
    assert "measurements" not in u and "ambiguous" not in u and "truth" not in u
