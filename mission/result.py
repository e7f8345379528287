"""The one per-user result document, the one horizontal error and the one status of every tool.

`uavloc sim`, `uavloc fly`, `uavloc replay` and the report all describe a located user the same
way (docs/design.md §11): :func:`user_entries` builds that list from plain arrays, and
:func:`user_entries_of_estimate` from an :class:`estimator.types.Estimate`. Each entry::

    id, lat_deg, lon_deg, alt_m, enu_m            where (None when the user is not located)
    cov_en_m2, sigma_east_m, sigma_north_m         east-north covariance [m²] and its √diagonal [m]
    error_bound_95_m                               semi-major axis of the 95 % ellipse [m]
    measurements, ambiguous                        when known
    bias_m                                         when range biases were estimated (mean range
                                                   bias [m]; where a user's bias was selected off, the
                                                   value it is held at: 0, or with bias_held
                                                   "sawtooth" an untracked sawtooth's mean)
    clock_sawtooth                                 {period_s, amplitude_m} where a UE clock sawtooth
                                                   was tracked (then bias_m is its mean, A/2)
    noise_scale                                    when estimated: how much noisier than the assumed
                                                   σ(d) this user's ranges were
    nlos_shift_m                                   when estimated: the shift [m] an NLoS excess from
                                                   one side can make unseen, in cov_en_m2 (0: no NLoS)
    error_m, truth                                 when the truth is known (simulation)

Floats are finite or None (JSON has no NaN). Pure: numpy and the origin's pymap3d conversion.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from estimator.types import error_bound_95_m


def horizontal_error_m(users_enu_m: np.ndarray, truth_enu_m: np.ndarray) -> np.ndarray:
    """(...,) east-north distance ||(e, n)_estimate − (e, n)_truth|| [m]; NaN where either is
    unknown. users_enu_m, truth_enu_m: (..., 3) or (..., 2), broadcast against each other."""
    u = np.asarray(users_enu_m, dtype=float)
    t = np.asarray(truth_enu_m, dtype=float)
    # e_k = sqrt((ê_k − e_k)² + (n̂_k − n_k)²)
    return np.linalg.norm(u[..., :2] - t[..., :2], axis=-1)


def result_status(estimate: Any) -> str:
    """"ok" when every user of the estimate (users_enu_m (K, 3), ambiguous (K,)) is located without
    ambiguity; "ambiguous" or "incomplete" otherwise (replay's document and the report)."""
    if not np.all(np.isfinite(estimate.users_enu_m)):
        return "incomplete"
    if np.any(estimate.ambiguous):
        return "ambiguous"
    return "ok"


def finite_or_none(x: Any) -> float | None:
    """A finite float, or None (JSON has no NaN or infinity)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def user_entries(
    user_ids: Sequence[str],
    origin: Origin | None,
    users_enu_m: np.ndarray | None,
    cov_en_m2: np.ndarray | None,
    *,
    measurements: Sequence[int] | np.ndarray | None = None,
    ambiguous: Sequence[bool] | np.ndarray | None = None,
    bias_m: np.ndarray | None = None,
    clock_sawtooth: Sequence[dict | None] | None = None,
    noise_scale: np.ndarray | None = None,
    nlos_shift_m: np.ndarray | None = None,
    truth_enu_m: np.ndarray | None = None,
) -> list[dict]:
    """The per-user entries (module docstring) of K users.

    users_enu_m: (K, 3) ENU about `origin` [m] (NaN rows: not located), or None when nothing is
    estimated (then `origin` may be None too); cov_en_m2: (K, 2, 2) [m²] or None; measurements (K,),
    ambiguous (K,), bias_m (K,), clock_sawtooth (K,) of dicts or None, noise_scale (K,),
    nlos_shift_m (K,), truth_enu_m (K, 3): optional, their keys appear when given (bias, noise
    scale and shift None where the user is not located).
    """
    k_users = len(user_ids)
    users = (np.full((k_users, 3), np.nan) if users_enu_m is None or origin is None
             else np.asarray(users_enu_m, dtype=float).reshape(k_users, 3))
    cov = (np.full((k_users, 2, 2), np.nan) if cov_en_m2 is None
           else np.asarray(cov_en_m2, dtype=float).reshape(k_users, 2, 2))
    located = np.all(np.isfinite(users), axis=1)
    if origin is not None and np.any(located):
        lat, lon, alt = (np.atleast_1d(a) for a in origin.enu_to_lla(np.where(located[:, None], users, 0.0)))
    else:
        lat = lon = alt = np.full(k_users, np.nan)
    bound = error_bound_95_m(cov)
    err = None if truth_enu_m is None else horizontal_error_m(users, truth_enu_m)
    out = []
    for k, uid in enumerate(user_ids):
        c = cov[k]
        c_ok = bool(np.all(np.isfinite(c)))
        entry: dict[str, Any] = {
            "id": uid,
            "lat_deg": float(lat[k]) if located[k] else None,
            "lon_deg": float(lon[k]) if located[k] else None,
            "alt_m": float(alt[k]) if located[k] else None,
            "enu_m": [float(x) for x in users[k]] if located[k] else None,
            "cov_en_m2": c.tolist() if c_ok else None,
            "sigma_east_m": math.sqrt(c[0, 0]) if c_ok and c[0, 0] >= 0 else None,
            "sigma_north_m": math.sqrt(c[1, 1]) if c_ok and c[1, 1] >= 0 else None,
            "error_bound_95_m": finite_or_none(bound[k]),
        }
        if measurements is not None:
            entry["measurements"] = int(measurements[k])
        if ambiguous is not None:
            entry["ambiguous"] = bool(ambiguous[k])
        if noise_scale is not None:
            entry["noise_scale"] = finite_or_none(noise_scale[k]) if located[k] else None
        if nlos_shift_m is not None:
            entry["nlos_shift_m"] = finite_or_none(nlos_shift_m[k]) if located[k] else None
        if bias_m is not None:
            entry["bias_m"] = finite_or_none(bias_m[k]) if located[k] else None
        if clock_sawtooth is not None and clock_sawtooth[k] is not None and located[k]:
            entry["clock_sawtooth"] = dict(clock_sawtooth[k])
        if err is not None and truth_enu_m is not None:
            entry["error_m"] = finite_or_none(err[k])
            t = np.asarray(truth_enu_m, dtype=float)[k]
            if origin is not None and np.all(np.isfinite(t)):
                tl = origin.enu_to_lla(t)
                entry["truth"] = {"lat_deg": float(tl[0]), "lon_deg": float(tl[1]), "alt_m": float(tl[2]),
                                  "enu_m": [float(x) for x in t]}
        out.append(entry)
    return out


def user_entries_of_estimate(estimate: Any, origin: Origin | None, user_ids: Sequence[str],
                             truth_enu_m: np.ndarray | None = None) -> list[dict]:
    """:func:`user_entries` of an `estimator.types.Estimate` (None: no user located)."""
    if estimate is None:
        return user_entries(user_ids, origin, None, None, truth_enu_m=truth_enu_m)
    k = len(user_ids)
    bias = None
    clock_doc: list[dict | None] | None = None
    if estimate.bias_m is not None:
        bias = np.array(estimate.bias_m, dtype=float)
        st = estimate.state
        on = None if st is None else st.bias_on
        clocks = (None if st is None else st.clock) or [None] * k
        clock_doc = [None] * k
        for j in range(k):
            if clocks[j] is not None and np.isfinite(bias[j]):
                # a tracked clock sawtooth: its amplitude is the estimated b; its mean A/2 the bias
                clock_doc[j] = {"period_s": float(clocks[j].period_s), "amplitude_m": float(bias[j])}
                bias[j] *= 0.5
            elif on is not None and not on[j]:
                # selected off: the value it is held at
                bias[j] = 0.0 if st.bias_held_m is None else float(st.bias_held_m[j])
    scale = None if estimate.state is None else estimate.state.noise_scale
    shift = None if estimate.state is None else estimate.state.nlos_shift_m
    return user_entries(
        user_ids, origin, estimate.users_enu_m,
        np.array([estimate.cov_en_m2(j) for j in range(k)]).reshape(k, 2, 2),
        measurements=estimate.n_ranges, ambiguous=estimate.ambiguous, bias_m=bias,
        clock_sawtooth=clock_doc, noise_scale=None if scale is None else np.asarray(scale, dtype=float),
        nlos_shift_m=None if shift is None else np.asarray(shift, dtype=float), truth_enu_m=truth_enu_m,
    )
