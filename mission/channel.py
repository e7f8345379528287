"""The channel a real gNB's ranges went through, and how far the ranges were from it (docs/oai-in-the-loop.md).

`uavloc sim --oai` logs every rfsim distance its bridge set as a `channel` record (docs/design.md
§10): `user`, `offset` (whole samples of round trip on the nrUE's downlink), `fs_hz`,
`round_trip_m` (offset · c / fs), `range_m` (half of it: the one-way range the gNB should measure),
`true_range_m` (the vehicle-to-user distance the bridge was following), optionally `pace` (rfsim's
simulated seconds per wall second when it was set). This module checks those records and compares
each measured range with the channel in force at its stamp:

    e_i = r̂_i − r_ch(u_i, t_i),   r_ch(u, t) = range_m of u's last channel record with t_ch ≤ t

and counts a range within one sample when |e_i| ≤ c / (2 fs) (one sample of round trip; plus the
records' rounding).
Pure: numpy on records already read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mission.log_checks import LineError

SPEED_OF_LIGHT_MPS = 299_792_458.0
#: a channel record's distances are rounded to 0.1 mm: a range one sample off is within one sample
RECORD_ROUNDING_M = 1e-3


def check_channel_record(obj: dict, user_ix: dict[str, int]) -> dict:
    """A `channel` record's fields checked (LineError naming the bad one); the record itself."""
    if obj.get("user") not in user_ix:
        raise LineError(f"channel record for unknown user {obj.get('user')!r}; header users: {sorted(user_ix)}")
    k = obj.get("offset")
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise LineError(f"channel 'offset' must be a whole number of samples >= 0, got {k!r}")
    for key in ("fs_hz", "range_m", "round_trip_m", "true_range_m"):
        v = obj.get(key)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
            raise LineError(f"channel {key!r} must be a finite number >= 0, got {v!r}")
    if obj["fs_hz"] <= 0:
        raise LineError(f"channel 'fs_hz' must be > 0, got {obj['fs_hz']!r}")
    return obj


@dataclass(frozen=True)
class ChannelResiduals:
    """Measured ranges against the channel in force. residual_m (M,): r̂ − r_ch of the ranges that
    had a channel (ranges before the first setting of their user are left out); sample_range_m:
    one sample of round trip as range [m] (3.253 at 46.08 Msps)."""

    residual_m: np.ndarray
    sample_range_m: float

    @property
    def n(self) -> int:
        return int(self.residual_m.size)

    def to_dict(self) -> dict:
        """{ranges, mean_m, p95_abs_m, within_one_sample, sample_range_m} (None where no range)."""
        e = self.residual_m
        if e.size == 0:
            return {"ranges": 0, "mean_m": None, "p95_abs_m": None, "within_one_sample": None,
                    "sample_range_m": round(self.sample_range_m, 4)}
        return {"ranges": int(e.size), "mean_m": round(float(np.mean(e)), 3),
                "p95_abs_m": round(float(np.percentile(np.abs(e), 95)), 3),
                "within_one_sample": round(float(np.mean(np.abs(e) <= self.sample_range_m + RECORD_ROUNDING_M)), 4),
                "sample_range_m": round(self.sample_range_m, 4)}


def channel_residuals(rtt_t_s: np.ndarray, rtt_user: np.ndarray, rtt_toa_s: np.ndarray, channel: list[dict],
                      user_ix: dict[str, int]) -> ChannelResiduals | None:
    """The residuals of (M,) ranges (stamps [s], user indices, one-way ToA [s]) against the
    `channel` records (file order, times non-decreasing per user); None without channel records."""
    if not channel:
        return None
    fs = float(channel[0]["fs_hz"])
    t_rtt = np.asarray(rtt_t_s, float)
    users = np.asarray(rtt_user, int)
    r_hat = SPEED_OF_LIGHT_MPS * np.asarray(rtt_toa_s, float)
    out = []
    for k in np.unique(users):
        recs = [c for c in channel if user_ix.get(c["user"]) == k]
        if not recs:
            continue
        t_ch = np.array([float(c["t"]) for c in recs])
        r_ch = np.array([float(c["range_m"]) for c in recs])
        order = np.argsort(t_ch, kind="stable")
        t_ch, r_ch = t_ch[order], r_ch[order]
        sel = users == k
        # the last setting at or before each stamp
        j = np.searchsorted(t_ch, t_rtt[sel], side="right") - 1
        ok = j >= 0
        out.append(r_hat[sel][ok] - r_ch[j[ok]])
    e = np.concatenate(out) if out else np.zeros(0)
    return ChannelResiduals(e, SPEED_OF_LIGHT_MPS / (2.0 * fs))
