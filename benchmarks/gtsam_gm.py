"""The Gauss–Markov GPS link as a GTSAM factor, shared by the benchmarks' GTSAM baselines
(honesty.py, replay_process.py). It needs gtsam and numpy only, so that a plain GTSAM script
stays plain (none of the project's imports)."""

from __future__ import annotations

import gtsam
import numpy as np


def gm_link_factor(key_prev, key, gps_prev, gps, phi: float, model) -> gtsam.CustomFactor:
    """CustomFactor e = (x − x̂) − φ (x_prev − x̂_prev) (whitened by `model`); ∂e/∂x_prev = −φ I,
    ∂e/∂x = I. gps_prev, gps: (3,) the two fixes [m, ENU]."""

    def error(this, values, jacobians):
        if jacobians is not None:
            jacobians[0] = -phi * np.eye(3)
            jacobians[1] = np.eye(3)
        return (values.atPoint3(key) - gps) - phi * (values.atPoint3(key_prev) - gps_prev)

    return gtsam.CustomFactor(model, [key_prev, key], error)
