"""Sensors of the built-in vehicle: the GPS/EKF position and velocity errors and the battery (charge
state, drain, electrics). Pure: the random generator is handed in, time is simulated time."""

from __future__ import annotations

import math

import numpy as np

from sitl_scenarios.vehicle.mav import CHARGE_CRITICAL, CHARGE_EMERGENCY, CHARGE_LOW, CHARGE_OK
from sitl_scenarios.vehicle.params import ParamStore

#: PX4's STATUSTEXT when the charge state drops to a level
BATTERY_WARNINGS = {
    CHARGE_LOW: "Low battery level! Return advised",
    CHARGE_CRITICAL: "Critical battery level!",
    CHARGE_EMERGENCY: "Emergency battery level! Landing",
}
#: a pack's capacity in mAh, for BATTERY_STATUS.current_consumed only
CAPACITY_MAH = 5000


class GpsError:
    """Position error of the vehicle's GPS/EKF solution, isotropic in 3-D, σ per axis.

    tau_s = 0: independent per fix (white: the estimator's τ = 0 case, docs/design.md §5). tau_s > 0:
    first-order Gauss-Markov (as the estimator models it), e_k = φ·e_{k-1} + sqrt(1 − φ²)·σ·w,
    φ = exp(−Δt/τ), stationary σ per axis.
    """

    def __init__(self, sigma_m: float, tau_s: float, rng: np.random.Generator) -> None:
        self.sigma_m = float(sigma_m)
        self.tau_s = float(tau_s)
        self._rng = rng
        self._e = rng.normal(0.0, self.sigma_m, 3) if self.sigma_m > 0 else np.zeros(3)
        self._t_s: float | None = None

    def sample(self, t_s: float) -> np.ndarray:
        """Error (3,) [m] ENU at simulated time t_s; the same value for the same t_s."""
        if self._t_s is not None and t_s == self._t_s:
            return self._e
        if self.sigma_m <= 0:
            self._e = np.zeros(3)
        elif self.tau_s <= 0 or self._t_s is None:
            self._e = self._rng.normal(0.0, self.sigma_m, 3)
        else:
            # e_k = φ e_{k-1} + sqrt(1 − φ²) σ w
            phi = math.exp(-max(t_s - self._t_s, 0.0) / self.tau_s)
            self._e = phi * self._e + math.sqrt(1.0 - phi * phi) * self.sigma_m * self._rng.normal(size=3)
        self._t_s = t_s
        return self._e


#: the built-in vehicle's velocity error (EKF output): σ per axis [m/s] and correlation time [s].
#: Below the estimator's default assumption (estimator.noise.DEFAULT_VEL_SIGMA_MPS 0.1 m/s, τ 1 s:
#: a random-walk intensity 2σ²τ four times this one's), as a real autopilot's should be.
VEL_SIGMA_MPS = 0.05
VEL_TAU_S = 1.0


class VelocityError:
    """Error of the vehicle's EKF velocity, isotropic in 3-D: first-order Gauss–Markov with σ per axis
    and a short correlation time, ε_k = φ ε_(k−1) + √(1 − φ²) σ w, φ = exp(−Δt/τ).

    An EKF observes velocity directly (GPS Doppler, IMU), so its error stays small and forgets itself
    within about a second; it does not drift like the position (GpsError), and it is independent of
    the position error here. Its own generator, spawned from the seed of the one handed in (no draw
    is taken from it, so the GPS error sequence is unchanged).
    """

    def __init__(self, rng: np.random.Generator, sigma_mps: float = VEL_SIGMA_MPS, tau_s: float = VEL_TAU_S) -> None:
        self.sigma_mps, self.tau_s = float(sigma_mps), float(tau_s)
        seq = getattr(rng.bit_generator, "seed_seq", None)
        self._rng = np.random.default_rng(seq.spawn(1)[0] if seq is not None else 0)
        self._e = self._rng.normal(0.0, self.sigma_mps, 3) if self.sigma_mps > 0 else np.zeros(3)
        self._t_s: float | None = None

    def sample(self, t_s: float) -> np.ndarray:
        """Error (3,) [m/s] ENU at simulated time t_s; the same value for the same t_s."""
        if self._t_s is not None and t_s == self._t_s:
            return self._e
        if self.sigma_mps <= 0:
            self._e = np.zeros(3)
        elif self._t_s is not None:
            # ε_k = φ ε_(k−1) + √(1 − φ²) σ w
            phi = math.exp(-max(t_s - self._t_s, 0.0) / self.tau_s)
            self._e = phi * self._e + math.sqrt(1.0 - phi * phi) * self.sigma_mps * self._rng.normal(size=3)
        self._t_s = t_s
        return self._e


#: PX4 v1.18 (SIH quadrotor, ../shared/data/px4-v1.18-sih/gpsloss): 4.3 s of its time from
#: GPS_RAW_INT's fix type 0 to the failsafe's descent ("Failsafe: blind land": EKF2_NOAID_TOUT, 5 s,
#: counts from the last GPS fusion, before the fix is reported lost)
DEAD_RECKONING_S = 4.3
#: how the dead-reckoned horizontal position drifts after the fix is lost, d(t) = a τ²/2 + j τ³/6
#: with τ = t − DRIFT_DELAY_S [m], fitted to the same recording: nothing for the first 3 s (the
#: position goes on as flown: 2.1 m at the descent, 4.3 s, all of it the braking the vehicle was
#: in), then 1.6 m more after 6 s, 12 m after 11 s, 30 m after 16 s, 89 m after 26 s, 206 m after
#: 36 s (an acceleration error and a growing tilt error)
DRIFT_DELAY_S = 2.9
DRIFT_ACC_MPS2 = 0.34
DRIFT_JERK_MPS3 = 0.0017


class DeadReckoning:
    """The horizontal error an EKF's position gathers once GPS stops: d(t) = a τ²/2 + j τ³/6, τ =
    max(t − delay, 0) since the loss, along one direction drawn at the loss (seeded), on top of the
    GPS error it had then. Velocity: its derivative, v(t) = a τ + j τ²/2."""

    def __init__(self, rng: np.random.Generator, acc_mps2: float = DRIFT_ACC_MPS2,
                 jerk_mps3: float = DRIFT_JERK_MPS3, delay_s: float = DRIFT_DELAY_S) -> None:
        seq = getattr(rng.bit_generator, "seed_seq", None)
        self._rng = np.random.default_rng(seq.spawn(1)[0] if seq is not None else 1)
        self.acc_mps2, self.jerk_mps3, self.delay_s = float(acc_mps2), float(jerk_mps3), float(delay_s)
        self.since_s: float | None = None
        self._dir = np.zeros(3)

    def start(self, t_s: float) -> None:
        """GPS lost at simulated time t_s: a new direction of drift."""
        heading = self._rng.uniform(0.0, 2.0 * math.pi)
        self._dir = np.array([math.cos(heading), math.sin(heading), 0.0])
        self.since_s = t_s

    def stop(self) -> None:
        self.since_s = None

    def offset_m(self, t_s: float) -> np.ndarray:
        """(3,) ENU [m] at simulated time t_s (zeros while GPS is fine)."""
        if self.since_s is None:
            return np.zeros(3)
        dt = max(t_s - self.since_s - self.delay_s, 0.0)
        return self._dir * (self.acc_mps2 * dt**2 / 2.0 + self.jerk_mps3 * dt**3 / 6.0)

    def velocity_mps(self, t_s: float) -> np.ndarray:
        if self.since_s is None:
            return np.zeros(3)
        dt = max(t_s - self.since_s - self.delay_s, 0.0)
        return self._dir * (self.acc_mps2 * dt + self.jerk_mps3 * dt**2 / 2.0)


def charge_state(battery_pct: float, params: ParamStore) -> int:
    """MAV_BATTERY_CHARGE_STATE of a remaining charge [%] against BAT_LOW/CRIT/EMERGEN_THR."""
    frac = battery_pct / 100.0
    if frac <= params["BAT_EMERGEN_THR"]:
        return CHARGE_EMERGENCY
    if frac <= params["BAT_CRIT_THR"]:
        return CHARGE_CRITICAL
    if frac <= params["BAT_LOW_THR"]:
        return CHARGE_LOW
    return CHARGE_OK


def drained_pct(battery_pct: float, dt_s: float, capacity_s: float, armed: bool, in_air: bool) -> float:
    """The charge [%] after dt_s: an armed vehicle drains 100 % per capacity_s of flight, a tenth
    of that on the ground; disarmed it keeps its charge."""
    if not armed:
        return battery_pct
    rate = 100.0 / capacity_s  # % per second of flight
    return max(battery_pct - rate * dt_s * (1.0 if in_air else 0.1), 0.0)


def battery_electrics(battery_pct: float, cells: int, armed: bool, in_air: bool) -> tuple[int, int]:
    """(voltage [mV], current [cA]) of a LiPo: 3.6 V (empty) .. 4.05 V (full) per cell; 15 A in
    the air, 1.5 A armed on the ground, 0.5 A disarmed."""
    v = cells * (3.6 + 0.45 * battery_pct / 100.0)
    amps = 15.0 if in_air else (1.5 if armed else 0.5)
    return int(v * 1000), int(amps * 100)


def remaining(battery_pct: float, capacity_s: float) -> tuple[int, int]:
    """(charge used [mAh] of a CAPACITY_MAH pack, flight time left [s]) at a remaining charge [%]."""
    used_mah = int((100.0 - battery_pct) / 100.0 * CAPACITY_MAH)
    return used_mah, int(battery_pct / 100.0 * capacity_s)

