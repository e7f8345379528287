"""Keyframe selection at Δ metres: known tables, online == batch, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.keyframes import KeyframeSelector, select_keyframes
from uavloc.errors import EstimatorError


@pytest.mark.parametrize(
    "east,delta,expected",
    [
        ([0.0, 1.0, 1.9, 2.0, 3.0, 4.1, 4.2], 2.0, [0, 3, 5]),
        ([0.0, 0.5, 1.0], 2.0, [0]),
        ([0.0, 3.0, 6.0], 2.0, [0, 1, 2]),
        ([0.0, 0.0, 0.0], 0.0, [0, 1, 2]),
        ([], 2.0, []),
    ],
)
def test_keeps_first_then_each_delta_from_last_kept(east, delta, expected):
    pos = np.column_stack([east, np.zeros(len(east)), np.full(len(east), 30.0)]) if east else np.zeros((0, 3))
    np.testing.assert_array_equal(select_keyframes(pos, delta), expected)


def test_distance_is_three_dimensional():
    pos = np.array([[0.0, 0.0, 30.0], [0.0, 0.0, 32.0], [1.0, 1.0, 32.0]])
    np.testing.assert_array_equal(select_keyframes(pos, 2.0), [0, 1])


def test_online_selector_equals_batch_selection():
    rng = np.random.default_rng(1)
    pos = np.cumsum(rng.normal(scale=0.7, size=(500, 3)), axis=0)
    sel = KeyframeSelector(2.0)
    online = [i for i, p in enumerate(pos) if sel.accept(p)]
    np.testing.assert_array_equal(online, select_keyframes(pos, 2.0))
    np.testing.assert_array_equal(sel.last_kept_enu_m, pos[online[-1]])


@pytest.mark.parametrize(
    "pos,delta,match",
    [
        (np.zeros((3, 2)), 2.0, r"\(N, 3\)"),
        (np.array([[0.0, np.nan, 0.0]]), 2.0, "row 0"),
        (np.zeros((3, 3)), -1.0, "-1.0"),
        (np.zeros((3, 3)), float("nan"), "nan"),
    ],
)
def test_bad_input_rejected(pos, delta, match):
    with pytest.raises(EstimatorError, match=match):
        select_keyframes(pos, delta)


def test_selector_rejects_bad_position():
    with pytest.raises(EstimatorError, match="finite"):
        KeyframeSelector(2.0).accept(np.array([0.0, np.inf, 1.0]))
