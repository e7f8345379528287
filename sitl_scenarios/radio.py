"""Radio model of the simulated gNB: from true geometry to the raw numbers a gNB reports.

Pure and seeded (no sockets, no clocks, no files): the simulated gNB and the example-log generator
both call it, with the time and the UAV position supplied by the caller. docs/design.md §4 and §9.

Chain for one measurement of user k from UAV position x at time t (one-way metres first):

    d        = ||x − u_k||                                   true slant range [m]
    n        ~ N(0, σ(d)²),  σ(d) = s0 + a·exp(b·d)          distance-dependent noise [m]
    saw(t)   = A_k · frac(t / P_k + φ_k)                      UE clock sawtooth, 0 → A_k, then reset
                                                              (commercial UEs by default: 12 m, 15 s)
    e_nlos   ~ Exp(mean = nlos_excess_mean_m) if a building cuts the segment x → u_k, else 0
    RTT      = 2 (d + n + saw(t) + e_nlos) / C               [s], clipped at 0
    TA       = floor(RTT / TA step), clipped to 0..3846       TA step = 16·64·Tc / 2^μ
    srs_peak = round((RTT − TA·step) · fs · os) / os          residual in samples at fs (1/os steps)

so that `estimator.ranging.range_m_from_raw(ta, mu, srs_peak, fs)` gives back d + n + saw + e_nlos
up to the SRS quantization (C / (2·fs·os) one-way). Beyond `coverage_m` there is no answer (None).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from estimator.ranging import C_MPS, TA_RAR_MAX, ta_step_s
from mission import geometry
from sitl_scenarios.scenario import BuildingConfig, Scenario, UserConfig
from uavloc.errors import SimulatorError

_EPS = 1e-9


@dataclass(frozen=True)
class RawRtt:
    """One simulated gNB RTT result: the raw fields the gNB prints plus truth diagnostics.

    ta: absolute timing advance (0..3846); mu: numerology; srs_peak: SRS residual [samples at
    fs_hz, multiple of 1/oversampling]; fs_hz: sampling rate [Hz]; snr_db: SRS SNR [dB].
    Truth (never on the wire): true_range_m: slant distance [m]; noise_m: Gaussian part [m];
    sawtooth_m: clock-drift part [m]; nlos: a building blocks the line of sight; nlos_excess_m:
    NLoS excess [m]; error_m: total one-way error before quantization [m].
    """

    rnti: int
    ta: int
    mu: int
    srs_peak: float
    fs_hz: float
    snr_db: float
    true_range_m: float
    noise_m: float
    sawtooth_m: float
    nlos: bool
    nlos_excess_m: float

    @property
    def error_m(self) -> float:
        """One-way range error before quantization [m]: n + saw(t) + e_nlos."""
        return self.noise_m + self.sawtooth_m + self.nlos_excess_m


# ---------------------------------------------------------------------------------------------
# geometry


def point_in_polygon(p_en_m: Sequence[float], polygon_en_m: Sequence[Sequence[float]]) -> bool:
    """Is the 2-D point (east, north) inside the polygon [[e, n], ...] or on its boundary?
    (mission.geometry's one rule: polygons are closed.)"""
    return geometry.contains_point(polygon_en_m, p_en_m)


def segment_blocked_by(uav_enu_m, user_enu_m, building: BuildingConfig) -> bool:
    """Does the 3-D segment UAV → user pass through the building prism (footprint × [0, height))?

    uav_enu_m, user_enu_m: (3,) [m, ENU]. Grazing a wall below the roof blocks; touching the roof
    exactly counts as clear (mission.geometry.segment_blocked_by_prism).
    """
    return geometry.segment_blocked_by_prism(uav_enu_m, user_enu_m, building.footprint_enu_m, building.height_m)


def line_of_sight_blocked(uav_enu_m, user_enu_m, buildings: Sequence[BuildingConfig]) -> bool:
    """True when any building prism cuts the 3-D segment UAV → user (both (3,) ENU [m])."""
    return any(segment_blocked_by(uav_enu_m, user_enu_m, bld) for bld in buildings)


# ---------------------------------------------------------------------------------------------
# the model


class RadioModel:
    """Seeded radio model of a scenario (see the module docstring for the chain).

    scenario: the scenario (users, buildings, radio section); rng: the only source of randomness.
    Each user's sawtooth phase φ_k ∈ [0, 1) is drawn from `rng` at construction, in user order.
    """

    def __init__(self, scenario: Scenario, rng: np.random.Generator) -> None:
        self.scenario = scenario
        self.radio = scenario.radio
        self.rng = rng
        self.noise = scenario.radio_noise_model()
        self.ta_step_s = ta_step_s(self.radio.mu)
        self.users: list[UserConfig] = list(scenario.users)
        self.user_enu_m = np.array([[u.east_m, u.north_m, u.up_m] for u in self.users], float).reshape(-1, 3)
        self.sawtooth_phase = rng.random(len(self.users))
        self._by_rnti = {u.rnti: i for i, u in enumerate(self.users)}

    # -- lookup -------------------------------------------------------------------------------
    def user_index(self, user: int | UserConfig) -> int:
        """Index of a user given as an index or a UserConfig of this scenario."""
        if isinstance(user, UserConfig):
            if user.rnti not in self._by_rnti:
                raise SimulatorError(f"user {user.id!r} (RNTI {user.rnti:#06x}) is not in the scenario")
            return self._by_rnti[user.rnti]
        n = len(self.users)
        if isinstance(user, bool) or not isinstance(user, int | np.integer) or not 0 <= user < n:
            raise SimulatorError(f"user index must be 0..{len(self.users) - 1}, got {user!r}")
        return int(user)

    def index_of_rnti(self, rnti: int) -> int | None:
        """Index of the user with this RNTI, or None."""
        return self._by_rnti.get(rnti)

    # -- deterministic parts ------------------------------------------------------------------
    def sawtooth_params(self, user: int | UserConfig) -> tuple[float, float]:
        """(A [m], P [s]) of a user's clock sawtooth (a commercial UE's is resolved when the scenario
        is read, sitl_scenarios.scenario.scenario_from_dict)."""
        u = self.users[self.user_index(user)]
        return float(u.sawtooth_amplitude_m), float(u.sawtooth_period_s)

    def sawtooth_m(self, user: int | UserConfig, t_s: float) -> float:
        """saw(t) = A · frac(t / P + φ) [m, one-way]; mean A/2 over a period."""
        k = self.user_index(user)
        amp, period = self.sawtooth_params(k)
        if amp == 0.0:
            return 0.0
        # saw(t) = A · frac(t/P + φ)
        phase = t_s / period + self.sawtooth_phase[k]
        return amp * (phase - math.floor(phase))

    def range_sigma_m(self, d_m: float) -> float:
        """σ(d) = s0 + a·exp(b·d) [m]."""
        return float(self.noise.range_sigma_m(d_m))

    def snr_db(self, d_m: float) -> float:
        """Free-space SNR: snr(100 m) − 20·log10(d / 100 m) [dB] (d floored at 1 m)."""
        # snr(d) = snr_100 − 20 log10(d / 100)
        return self.radio.snr_db_at_100m - 20.0 * math.log10(max(d_m, 1.0) / 100.0)

    # -- one measurement ----------------------------------------------------------------------
    def measure(self, user: int | UserConfig, uav_enu_m, t_s: float) -> RawRtt | None:
        """Simulate one RTT measurement of `user` from `uav_enu_m` (3,) [m, ENU] at time `t_s` [s].

        Returns None when the slant range exceeds the coverage range (no answer).
        """
        k = self.user_index(user)
        uav = np.asarray(uav_enu_m, float).reshape(3)
        if not np.all(np.isfinite(uav)):
            raise SimulatorError(f"UAV position must be finite, got {uav!r}")
        user_pos = self.user_enu_m[k]
        # d = ||x − u_k||
        d = float(np.linalg.norm(uav - user_pos))
        if d > self.radio.coverage_m:
            return None
        # n ~ N(0, σ(d)²)
        noise = float(self.rng.normal(0.0, self.range_sigma_m(d)))
        saw = self.sawtooth_m(k, t_s)
        nlos = line_of_sight_blocked(uav, user_pos, self.scenario.buildings)
        # e_nlos ~ Exp(mean) only when blocked
        excess = float(self.rng.exponential(self.radio.nlos_excess_mean_m)) if (
            nlos and self.radio.nlos_excess_mean_m > 0) else 0.0
        # RTT = 2 (d + n + saw + e_nlos) / C
        rtt = max(0.0, 2.0 * (d + noise + saw + excess) / C_MPS)
        # TA = floor(RTT / step), clipped to the RAR range
        ta = min(TA_RAR_MAX, math.floor(rtt / self.ta_step_s))
        # srs_peak = round((RTT − TA·step) · fs · os) / os
        os_ = int(self.radio.oversampling)
        residual_s = rtt - ta * self.ta_step_s
        peak = round(residual_s * self.radio.fs_hz * os_) / os_
        return RawRtt(
            rnti=self.users[k].rnti,
            ta=ta,
            mu=self.radio.mu,
            srs_peak=float(max(peak, 0.0)),
            fs_hz=float(self.radio.fs_hz),
            snr_db=round(self.snr_db(d), 2),
            true_range_m=d,
            noise_m=noise,
            sawtooth_m=saw,
            nlos=nlos,
            nlos_excess_m=excess,
        )

    def measure_rnti(self, rnti: int, uav_enu_m, t_s: float) -> RawRtt | None:
        """:meth:`measure` for the user with this RNTI (SimulatorError if unknown)."""
        k = self.index_of_rnti(rnti)
        if k is None:
            raise SimulatorError(f"no user with RNTI {rnti:#06x} in scenario {self.scenario.name!r}")
        return self.measure(k, uav_enu_m, t_s)


# ---------------------------------------------------------------------------------------------
# cells: which vehicle's gNB serves each UE (a fleet, docs/fleet.md)


#: the carrier of the recorded OAI gNB (its rfsim config, band 78: `-C 3319680000`) [Hz]
CARRIER_HZ = 3.31968e9
#: antenna heights above the ground [m]: a UE held in the hand; a gNB on a vehicle standing on the ground
UE_ANTENNA_M = 1.5
GNB_ANTENNA_M = 0.5


def reach_m(coverage_m: float, gnb_height_m, ue_height_m=UE_ANTENNA_M, carrier_hz: float = CARRIER_HZ):
    """Slant range [m] within which a UE hears a gNB whose antenna is gnb_height_m above the UE's
    ground (arrays broadcast). `coverage_m` is the reach of a gNB in the air, where the path is free
    space; near the ground the wave reflected off it cancels the direct one beyond the two-ray
    breakpoint d_bp = 4 h_gNB h_UE / λ, and the loss grows as d⁴ instead of d². The reach R is where
    the loss equals free space's at coverage_m (R0):

        20 log R0 = 20 log d_bp + 40 log (R / d_bp)   ⇒   R = √(R0 · d_bp)   when d_bp < R0, else R0

    (3.3 GHz: a gNB at 40 m reaches R0 up to d_bp ≈ 2.7 km; one on a landed vehicle, d_bp ≈ 33 m,
    reaches ≈ 120 m of a 450 m cell)."""
    lam_m = C_MPS / carrier_hz
    d_bp = 4.0 * np.maximum(gnb_height_m, GNB_ANTENNA_M) * ue_height_m / lam_m
    return np.where(d_bp < coverage_m, np.sqrt(coverage_m * d_bp), coverage_m)


class CellAttachment:
    """Which of several gNBs serves each UE, as OAI's UEs attach.

    A UE without a cell attaches (a random access, a new RNTI) to the strongest gNB in reach, the
    nearest by slant range (free-space loss grows with distance); it stays on that cell while the
    cell is on the air and within reach, however near another comes (a connected UE does not
    reselect); when its cell moves out of reach or goes off the air, it attaches again where it
    can, or has no cell. The reach is `coverage_m` for a gNB in the air and shorter near the ground
    (:func:`reach_m`): a vehicle that lands takes its cell's far UEs off it.

    user_enu_m: (K, 3) UE positions [m, ENU; up: the ground they stand on]; coverage_m: slant range
    beyond which a gNB in the air is not heard. serving: (K,) the serving gNB's index, −1: none;
    attaches: (K,) random accesses so far.
    """

    def __init__(self, user_enu_m: np.ndarray, coverage_m: float) -> None:
        self.user_enu_m = np.asarray(user_enu_m, dtype=float).reshape(-1, 3)
        if not (math.isfinite(coverage_m) and coverage_m > 0):
            raise SimulatorError(f"coverage_m must be positive, got {coverage_m!r}")
        self.coverage_m = float(coverage_m)
        k = len(self.user_enu_m)
        self.serving = np.full(k, -1, dtype=int)
        self.attaches = np.zeros(k, dtype=int)

    def update(self, gnb_enu_m: np.ndarray, on_air: np.ndarray | None = None) -> np.ndarray:
        """Attach and detach UEs for gNBs at (V, 3) [m, ENU] (on_air (V,) bool: gNBs transmitting;
        None: all); return a copy of `serving`."""
        g = np.asarray(gnb_enu_m, dtype=float).reshape(-1, 3)
        on = np.ones(len(g), dtype=bool) if on_air is None else np.asarray(on_air, dtype=bool)
        d = np.linalg.norm(self.user_enu_m[:, None, :] - g[None, :, :], axis=2)  # (K, V)
        above_m = g[None, :, 2] - self.user_enu_m[:, None, 2] + GNB_ANTENNA_M  # the gNB's antenna over the UE's ground
        heard = (d <= reach_m(self.coverage_m, above_m)) & on[None, :]
        for k in range(len(self.serving)):
            s = self.serving[k]
            if s >= 0 and s < len(g) and heard[k, s]:
                continue
            if heard[k].any():
                self.serving[k] = int(np.argmin(np.where(heard[k], d[k], np.inf)))
                self.attaches[k] += 1
            else:
                self.serving[k] = -1
        return self.serving.copy()
