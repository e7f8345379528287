"""From gNB numbers to a range (docs/design.md §4, 3GPP TS 38.211 §4.1 and §4.3.1).

    Tc      = 1 / (Δf_max · N_f) = 1 / (480 kHz · 4096)            ≈ 0.5086 ns
    TA step = 16 · 64 · Tc / 2^μ                                   (520.8 ns at μ = 0)
    τc      = TA · TA step                                         coarse round-trip time [s]
    τr      = srs_peak / fs                                        SRS refinement [s]
    RTT     = τc + τr,   τ̂ = RTT / 2,   range = C · τ̂

A RAR (Msg2) timing advance is 12 bits, absolute: 0..3846. A MAC CE timing advance is 6 bits,
relative to the current value: 0..63 with 31 meaning "no change".
"""

from __future__ import annotations

import math

from uavloc.errors import RangingError

#: Speed of light in vacuum [m/s].
C_MPS = 299_792_458.0
#: Basic NR time unit Tc [s] (TS 38.211 §4.1).
TC_S = 1.0 / (480e3 * 4096)
#: Largest absolute timing advance a RAR carries (TS 38.213 §4.2).
TA_RAR_MAX = 3846
#: MAC CE timing advance command range and its "no change" value (TS 38.321 §6.1.3.4).
TA_MAC_CE_MAX = 63
TA_MAC_CE_ZERO = 31
#: Numerologies supported (FR1 and FR2 data numerologies).
MU_VALUES = (0, 1, 2, 3)


def _check_finite(name: str, value: float) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError) as exc:
        raise RangingError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(x):
        raise RangingError(f"{name} must be finite, got {value!r}")
    return x


def _check_mu(mu: int) -> int:
    if isinstance(mu, bool) or not isinstance(mu, int | float) or mu != int(mu) or int(mu) not in MU_VALUES:
        raise RangingError(f"numerology mu must be one of {MU_VALUES}, got {mu!r}")
    return int(mu)


def _check_ta(ta: int, maximum: int, what: str) -> int:
    if isinstance(ta, bool) or not isinstance(ta, int | float) or not math.isfinite(ta) or ta != int(ta):
        raise RangingError(f"{what} must be an integer, got {ta!r}")
    if not 0 <= int(ta) <= maximum:
        raise RangingError(f"{what} must lie in 0..{maximum}, got {ta!r}")
    return int(ta)


def ta_step_s(mu: int) -> float:
    """Round-trip time of one timing-advance step [s]: 16 · 64 · Tc / 2^μ."""
    mu = _check_mu(mu)
    # TA step = 16 · 64 · Tc / 2^μ
    return 16 * 64 * TC_S / 2**mu


def coarse_rtt_s(ta: int, mu: int) -> float:
    """Coarse round-trip time from an absolute timing advance: τc = TA · 16 · 64 · Tc / 2^μ [s]."""
    ta = _check_ta(ta, TA_RAR_MAX, "timing advance")
    return ta * ta_step_s(mu)


def apply_mac_ce(ta_abs: int, ta_ce: int) -> int:
    """New absolute TA after a MAC CE command: TA_new = TA_old + (T_A − 31)."""
    ta_abs = _check_ta(ta_abs, TA_RAR_MAX, "absolute timing advance")
    ta_ce = _check_ta(ta_ce, TA_MAC_CE_MAX, "MAC CE timing advance")
    new = ta_abs + ta_ce - TA_MAC_CE_ZERO
    if not 0 <= new <= TA_RAR_MAX:
        raise RangingError(f"MAC CE {ta_ce} moves TA {ta_abs} out of 0..{TA_RAR_MAX} (to {new})")
    return new


def refine_rtt_s(srs_peak: float, fs_hz: float) -> float:
    """SRS refinement τr = argmax|ĝ| / fs [s]; `srs_peak` in samples (may be fractional, and
    negative: the residual after the TA, which a UE's timing advance can overshoot by up to half a
    TA step inside the TA loop's dead band)."""
    peak = _check_finite("SRS peak", srs_peak)
    fs = _check_finite("sampling rate fs_hz", fs_hz)
    if fs <= 0:
        raise RangingError(f"sampling rate fs_hz must be positive, got {fs_hz!r}")
    # τr = peak / fs
    return peak / fs


def rtt_s(ta: int, mu: int, srs_peak: float = 0.0, fs_hz: float = 1.0) -> float:
    """Round-trip time RTT = τc + τr [s] from a TA and an SRS peak (samples at fs_hz); the sum must
    not be negative."""
    rtt = coarse_rtt_s(ta, mu) + refine_rtt_s(srs_peak, fs_hz)
    if rtt < 0:
        raise RangingError(f"TA {ta} and SRS peak {srs_peak!r} give a negative round trip ({rtt:.3e} s)")
    return rtt


def toa_s_from_raw(ta: int, mu: int, srs_peak: float = 0.0, fs_hz: float = 1.0) -> float:
    """One-way time of arrival τ̂ = RTT / 2 [s]."""
    return 0.5 * rtt_s(ta, mu, srs_peak, fs_hz)


def range_m_from_toa(toa_s: float) -> float:
    """Range = C · τ̂ [m] from a one-way ToA [s]; rejects NaN and negative times."""
    toa = _check_finite("toa_s", toa_s)
    if toa < 0:
        raise RangingError(f"toa_s must be non-negative, got {toa_s!r}")
    return C_MPS * toa


def range_m_from_raw(ta: int, mu: int, srs_peak: float = 0.0, fs_hz: float = 1.0) -> float:
    """Range [m] straight from the gNB's raw numbers."""
    return range_m_from_toa(toa_s_from_raw(ta, mu, srs_peak, fs_hz))


def one_way_m_per_ta_step(mu: int) -> float:
    """One-way distance of one TA step [m]: C · step / 2 (78.07 m at μ = 0)."""
    return C_MPS * ta_step_s(mu) / 2


def one_way_m_per_sample(fs_hz: float) -> float:
    """One-way distance of one SRS sample [m]: C / (2 fs) (3.26 m at 46.08 Msps)."""
    return C_MPS * refine_rtt_s(1.0, fs_hz) / 2
