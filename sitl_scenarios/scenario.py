"""Scenario files: strict TOML whose keys are the fields of the dataclasses below (DESIGN.md §9).

Positions (users, buildings, geofence, no-fly zones) are ENU offsets in metres from the origin, so
a scenario flies anywhere: with the built-in vehicle the origin is `[origin]`; with an external
vehicle (PX4 SITL) it is the vehicle's home. Unknown keys, wrong types and out-of-range numbers are a
:class:`ScenarioError` that names the file and the key.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from planner.types import PlanningConstraints
from uavloc.errors import ScenarioError

if typing.TYPE_CHECKING:
    from mission import config as mission_config

SCENARIO_DIR = Path(__file__).resolve().parent


@dataclass(frozen=True)
class OriginConfig:
    """Geodetic origin used by the built-in vehicle (its home)."""

    lat_deg: float = 47.397742
    lon_deg: float = 8.545594
    alt_m: float = 488.0


@dataclass(frozen=True)
class UserConfig:
    """A ground user (UE). `east_m`, `north_m` from the origin; `up_m` its ground height (ENU up).

    sawtooth_amplitude_m / sawtooth_period_s: UE downlink-timing drift as a one-way range error that
    rises linearly from 0 to the amplitude and resets (its mean, amplitude/2, is a range bias).
    Absent from the file: a commercial UE, the radio section's ue_sawtooth_amplitude_m / _period_s,
    resolved once when the scenario is read (:func:`scenario_from_dict`), so a loaded scenario's
    users always carry numbers; 0 amplitude: an ideal UE (e.g. a software UE with a perfect clock).
    """

    id: str
    rnti: int
    east_m: float
    north_m: float
    up_m: float = 0.0
    sawtooth_amplitude_m: float | None = None
    sawtooth_period_s: float | None = None


@dataclass(frozen=True)
class BuildingConfig:
    """A building: footprint polygon [[east_m, north_m], ...] (≥ 3 vertices) and height [m]."""

    footprint_enu_m: list[list[float]]
    height_m: float


@dataclass(frozen=True)
class GeofenceConfig:
    """Inclusion polygon [[east_m, north_m], ...] (may be non-convex; empty: none), a maximum
    horizontal distance from home [m], and exclusion polygons (no-fly zones)."""

    polygon_enu_m: list[list[float]] = field(default_factory=list)
    max_distance_m: float = 500.0
    no_fly_enu_m: list[list[list[float]]] = field(default_factory=list)


@dataclass(frozen=True)
class RadioConfig:
    """The gNB's radio and the range-error model of the simulated gNB.

    mu: numerology (1 → 30 kHz SCS); fs_hz: sampling rate (46.08 Msps with `-E`, 61.44 Msps);
    oversampling: SRS CIR oversampling factor (peak resolution 1/oversampling samples);
    range noise σ(d) = s0_m + a_m·exp(b_per_m·d) (one-way, metres);
    coverage_m: no answer beyond this slant range; nlos_excess_mean_m: mean of the exponential
    excess delay (one-way metres) when a building blocks the line of sight;
    ue_sawtooth_amplitude_m / ue_sawtooth_period_s: the clock sawtooth of a commercial UE (a user
    without its own), 12 m peak as the paper saw with a Quectel module.
    """

    mu: int = 1
    fs_hz: float = 46.08e6
    oversampling: int = 8
    s0_m: float = 3.0
    a_m: float = 0.0
    b_per_m: float = 0.0
    coverage_m: float = 1500.0
    nlos_excess_mean_m: float = 20.0
    snr_db_at_100m: float = 30.0
    ue_sawtooth_amplitude_m: float = 12.0
    ue_sawtooth_period_s: float = 15.0


@dataclass(frozen=True)
class VehicleConfig:
    """Built-in vehicle: speeds [m/s], acceleration [m/s²], GPS noise [m], battery.

    gps_tau_s: correlation time of the GPS error (0: independent per fix; > 0: Gauss-Markov).
    """

    speed_mps: float = 10.0
    climb_mps: float = 3.0
    descent_mps: float = 1.5
    accel_mps2: float = 3.0
    gps_sigma_m: float = 1.0
    # the built-in vehicle's own error; an external autopilot's is not this one (Scenario.noise_model):
    # PX4 SITL's (SIH) EKF output drifts far slower, its increments say tau ~ 120-220 s at sigma 1 m
    gps_tau_s: float = 3.0
    battery_capacity_s: float = 1800.0
    battery_start_pct: float = 100.0


@dataclass(frozen=True)
class MissionConfig:
    """The mission: Δ spacing, altitude above home, limits and stop rule.

    altitude_m: flight height above home [m]; alt_min_m/alt_max_m: allowed band above home;
    target_radius_m: stop when every user's 95 % ellipse is inside this radius;
    budget_m: maximum metres flown in SURVEY; time_limit_s: maximum mission time;
    leg_max_m: maximum leg length the planner may choose; acceptance_m: arrival radius;
    battery_rtl_pct: battery below which the safety monitor returns home;
    sigma_gps_m: σ_gps the estimator assumes; planner: default planner name;
    estimate_bias: estimate a range bias per user (a UE clock sawtooth has a positive mean);
    range_s0_m: the s0 of σ(d) the estimator and planner assume (default: the radio's); raise it
    when the UEs add error the radio's σ(d) leaves out, e.g. a clock sawtooth of amplitude A adds a
    spread of A/√12 around its mean.
    gps_tau_s: correlation time of the GPS error the estimator assumes [s] (0 white; default: the
    vehicle section's, i.e. the built-in vehicle's truth, when the built-in vehicle flies, and
    unknown when an external autopilot does: the log then omits it, and the flight (from the
    take-off's telemetry) and replay (from the whole log's) estimate it from the telemetry
    velocity, else assume estimator.noise.DEFAULT_GPS_TAU_S).
    """

    delta_m: float = 2.0
    altitude_m: float = 30.0
    alt_min_m: float = 10.0
    alt_max_m: float = 120.0
    target_radius_m: float = 2.0
    budget_m: float = 2000.0
    time_limit_s: float = 1200.0
    leg_max_m: float = 80.0
    acceptance_m: float = 2.0
    battery_rtl_pct: float = 25.0
    sigma_gps_m: float = 1.0
    planner: str = "casadi"
    estimate_bias: bool = True
    range_s0_m: float | None = None
    gps_tau_s: float | None = None


@dataclass(frozen=True)
class Scenario:
    """A whole scenario file."""

    name: str
    users: list[UserConfig]
    seed: int = 0
    description: str = ""
    origin: OriginConfig = field(default_factory=OriginConfig)
    buildings: list[BuildingConfig] = field(default_factory=list)
    geofence: GeofenceConfig = field(default_factory=GeofenceConfig)
    radio: RadioConfig = field(default_factory=RadioConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    mission: MissionConfig = field(default_factory=MissionConfig)
    faults: dict[str, Any] = field(default_factory=dict)

    @property
    def origin_geo(self) -> Origin:
        return Origin(self.origin.lat_deg, self.origin.lon_deg, self.origin.alt_m)

    def radio_noise_model(self) -> NoiseModel:
        """The range noise the simulated radio draws from (the truth of a simulation)."""
        r = self.radio
        # σ_gps does not enter the radio; a GPS-noise-free vehicle (gps_sigma_m = 0) still needs a valid model
        return NoiseModel(sigma_gps_m=self.vehicle.gps_sigma_m or 1.0, s0_m=r.s0_m, a_m=r.a_m, b_per_m=r.b_per_m)

    def noise_model(self, external_vehicle: bool = False) -> NoiseModel:
        """The noise model the estimator and planner assume: σ_gps and (when given) s0 from the
        mission section, the rest of σ(d) from the radio section; the GPS correlation time from
        the mission section, else the built-in vehicle's (unknown, None, with external_vehicle:
        PX4's EKF output is not the built-in vehicle's and drifts ~50 times slower)."""
        r, m = self.radio, self.mission
        s0 = r.s0_m if m.range_s0_m is None else m.range_s0_m
        tau = m.gps_tau_s
        if tau is None and not external_vehicle:
            tau = self.vehicle.gps_tau_s
        return NoiseModel(sigma_gps_m=m.sigma_gps_m, s0_m=s0, a_m=r.a_m, b_per_m=r.b_per_m,
                          gps_tau_s=None if tau is None else float(tau))

    def planning_constraints(self, home_enu_m=(0.0, 0.0, 0.0), building_clearance_m: float = 5.0,
                             **overrides: Any) -> PlanningConstraints:
        """The planner's constraints of this scenario's mission and geofence.

        Altitudes in the scenario are above home; here they become ENU `up` (home up + value).
        Buildings: the UAV overflies every building whose height + `building_clearance_m` fits in the
        altitude band (the band's floor is raised to clear the tallest of them); a building too tall
        for the band becomes a no-fly zone. `overrides` replace any field (e.g. margin_m=3.0).
        """
        scenario = self
        m, g = scenario.mission, scenario.geofence
        home = np.asarray(home_enu_m, dtype=float).reshape(3)
        alt_min, alt_max = m.alt_min_m, m.alt_max_m
        no_fly = [np.asarray(p, dtype=float) for p in g.no_fly_enu_m]
        for b in scenario.buildings:
            top = b.height_m + building_clearance_m
            if top <= alt_max:
                alt_min = max(alt_min, top)
            else:
                no_fly.append(np.asarray(b.footprint_enu_m, dtype=float))
        kwargs = dict(
            home_enu_m=home,
            fence_enu_m=np.asarray(g.polygon_enu_m, dtype=float).reshape(-1, 2),
            no_fly_enu_m=tuple(no_fly),
            alt_min_m=home[2] + alt_min,
            alt_max_m=home[2] + alt_max,
            cruise_alt_m=home[2] + min(max(m.altitude_m, alt_min), alt_max),
            leg_max_m=m.leg_max_m,
            max_distance_m=g.max_distance_m,
            budget_m=m.budget_m,
            delta_m=m.delta_m,
            target_radius_m=m.target_radius_m,
            min_leg_m=min(10.0, m.leg_max_m),
        )
        kwargs.update(overrides)
        return PlanningConstraints(**kwargs)

    def mission_config(self, external_vehicle: bool = False) -> mission_config.MissionConfig:
        """The mission part of this scenario as a :class:`mission.config.MissionConfig` (what a real
        flight would be configured with: users without their positions, fence, limits, the noise
        the estimator assumes (noise_model(external_vehicle)), the gNB's numerology). The bridge
        until scenarios are written as a mission plus a world (see mission/config.py)."""
        from mission import config as mc

        m, g, n = self.mission, self.geofence, self.noise_model(external_vehicle)
        out = mc.MissionConfig(
            name=self.name,
            description=self.description,
            users=tuple(mc.MissionUserConfig(u.id, u.rnti, u.up_m) for u in self.users),
            geofence=mc.GeofenceConfig(
                polygon_enu_m=tuple(tuple(p) for p in g.polygon_enu_m),
                no_fly_enu_m=tuple(tuple(tuple(p) for p in z) for z in g.no_fly_enu_m),
                max_distance_m=g.max_distance_m),
            flight=mc.FlightConfig(
                altitude_m=m.altitude_m, alt_min_m=m.alt_min_m, alt_max_m=m.alt_max_m, delta_m=m.delta_m,
                target_radius_m=m.target_radius_m, budget_m=m.budget_m, time_limit_s=m.time_limit_s,
                cruise_speed_mps=self.vehicle.speed_mps, climb_mps=self.vehicle.climb_mps,
                descent_mps=self.vehicle.descent_mps, leg_max_m=m.leg_max_m, acceptance_m=m.acceptance_m,
                planner=m.planner),
            noise=mc.NoiseConfig(sigma_gps_m=n.sigma_gps_m, range_s0_m=n.s0_m, range_a_m=n.a_m,
                                 range_b_per_m=n.b_per_m, gps_tau_s=n.gps_tau_s, estimate_bias=m.estimate_bias),
            gnb=mc.GnbSettings(mu=self.radio.mu, fs_hz=self.radio.fs_hz),
            safety=mc.SafetyConfig(battery_rtl_pct=m.battery_rtl_pct,
                                   battery_takeoff_min_pct=max(mc.SafetyConfig.battery_takeoff_min_pct,
                                                               m.battery_rtl_pct)),
        )
        mc.validate_mission(out, f"scenario {self.name!r}")
        return out

    def user_by_rnti(self, rnti: int) -> UserConfig:
        for u in self.users:
            if u.rnti == rnti:
                return u
        raise ScenarioError(f"scenario {self.name!r} has no user with RNTI {rnti:#06x}")


# ---------------------------------------------------------------------------------------------
# strict conversion of parsed TOML into the dataclasses above


def _convert(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(value, arg, where)
            except ScenarioError as exc:
                errors.append(str(exc))
        raise ScenarioError(errors[0] if errors else f"{where}: unsupported value {value!r}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ScenarioError(f"{where}: expected a table, got {value!r}")
        return _build(tp, value, where)
    if origin is list:
        if not isinstance(value, list):
            raise ScenarioError(f"{where}: expected a list, got {value!r}")
        (item_tp,) = args
        return [_convert(v, item_tp, f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ScenarioError(f"{where}: expected a table, got {value!r}")
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ScenarioError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, str):  # RNTIs are often written in hex: "0x4601"
            try:
                return int(value, 0)
            except ValueError as exc:
                raise ScenarioError(f"{where}: expected an integer, got {value!r}") from exc
        if isinstance(value, bool) or not isinstance(value, int):
            raise ScenarioError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ScenarioError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ScenarioError(f"{where}: must be finite, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ScenarioError(f"{where}: expected a string, got {value!r}")
        return value
    raise ScenarioError(f"{where}: unsupported type {tp!r}")  # pragma: no cover - schema bug


def _build(cls: type, data: dict, where: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ScenarioError(
            f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; allowed: {', '.join(sorted(fields))}"
        )
    kwargs = {}
    for name, f in fields.items():
        if name in data:
            kwargs[name] = _convert(data[name], hints[name], f"{where}.{name}" if where else name)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ScenarioError(f"{where or 'scenario'}: missing required key {name!r}")
    return cls(**kwargs)


def _check(sc: Scenario, where: str) -> None:
    def positive(path: str, v: float) -> None:
        if not v > 0:
            raise ScenarioError(f"{where}: {path} must be positive, got {v!r}")

    if not sc.users:
        raise ScenarioError(f"{where}: a scenario needs at least one user")
    seen_id, seen_rnti = set(), set()
    for u in sc.users:
        if u.id in seen_id:
            raise ScenarioError(f"{where}: duplicate user id {u.id!r}")
        if u.rnti in seen_rnti:
            raise ScenarioError(f"{where}: duplicate RNTI {u.rnti:#06x}")
        if not 0 < u.rnti <= 0xFFEF:
            raise ScenarioError(f"{where}: user {u.id!r} RNTI must be in 0x0001..0xFFEF, got {u.rnti:#x}")
        if u.sawtooth_amplitude_m is not None and not u.sawtooth_amplitude_m >= 0:
            raise ScenarioError(f"{where}: user {u.id!r} sawtooth_amplitude_m must be >= 0")
        if u.sawtooth_period_s is not None:
            positive(f"user {u.id!r} sawtooth_period_s", u.sawtooth_period_s)
        seen_id.add(u.id)
        seen_rnti.add(u.rnti)
    if not -90 <= sc.origin.lat_deg <= 90 or not -180 <= sc.origin.lon_deg <= 180:
        raise ScenarioError(f"{where}: origin lat/lon out of range: {sc.origin}")
    for i, b in enumerate(sc.buildings):
        if len(b.footprint_enu_m) < 3 or any(len(p) != 2 for p in b.footprint_enu_m):
            raise ScenarioError(f"{where}: buildings[{i}].footprint_enu_m needs >= 3 [east, north] points")
        positive(f"buildings[{i}].height_m", b.height_m)
    polys = [("geofence.polygon_enu_m", sc.geofence.polygon_enu_m)] + [
        (f"geofence.no_fly_enu_m[{i}]", p) for i, p in enumerate(sc.geofence.no_fly_enu_m)
    ]
    for path, poly in polys:
        if poly and (len(poly) < 3 or any(len(p) != 2 for p in poly)):
            raise ScenarioError(f"{where}: {path} needs >= 3 [east, north] points")
    positive("geofence.max_distance_m", sc.geofence.max_distance_m)
    r = sc.radio
    if r.mu not in (0, 1, 2, 3):
        raise ScenarioError(f"{where}: radio.mu must be 0..3, got {r.mu}")
    for path in ("fs_hz", "oversampling", "s0_m", "coverage_m", "ue_sawtooth_period_s"):
        positive(f"radio.{path}", getattr(r, path))
    if r.a_m < 0 or r.nlos_excess_mean_m < 0 or not r.ue_sawtooth_amplitude_m >= 0:
        raise ScenarioError(f"{where}: radio.a_m, radio.nlos_excess_mean_m and radio.ue_sawtooth_amplitude_m "
                            "must be >= 0")
    v = sc.vehicle
    for path in ("speed_mps", "climb_mps", "descent_mps", "accel_mps2", "battery_capacity_s"):
        positive(f"vehicle.{path}", getattr(v, path))
    if v.gps_sigma_m < 0 or not 0 < v.battery_start_pct <= 100:
        raise ScenarioError(f"{where}: vehicle.gps_sigma_m must be >= 0 and battery_start_pct in (0, 100]")
    if v.gps_tau_s < 0:
        raise ScenarioError(f"{where}: vehicle.gps_tau_s must be >= 0, got {v.gps_tau_s!r}")
    m = sc.mission
    for path in ("delta_m", "altitude_m", "target_radius_m", "budget_m", "time_limit_s", "leg_max_m",
                 "acceptance_m", "sigma_gps_m"):
        positive(f"mission.{path}", getattr(m, path))
    if not 0 <= m.alt_min_m <= m.altitude_m <= m.alt_max_m:
        raise ScenarioError(
            f"{where}: need 0 <= mission.alt_min_m <= mission.altitude_m <= mission.alt_max_m, got "
            f"{m.alt_min_m}, {m.altitude_m}, {m.alt_max_m}"
        )
    if m.gps_tau_s is not None and not (isinstance(m.gps_tau_s, int | float) and 0 <= m.gps_tau_s < float("inf")):
        raise ScenarioError(f"{where}: mission.gps_tau_s must be a number >= 0, got {m.gps_tau_s!r}")
    if m.range_s0_m is not None and not m.range_s0_m > 0:
        raise ScenarioError(f"{where}: mission.range_s0_m must be positive, got {m.range_s0_m!r}")
    if not 0 <= m.battery_rtl_pct < 100:
        raise ScenarioError(f"{where}: mission.battery_rtl_pct must be in [0, 100), got {m.battery_rtl_pct}")


def scenario_from_dict(data: dict, where: str = "scenario") -> Scenario:
    """Build and validate a :class:`Scenario` from a parsed TOML document."""
    sc = _build(Scenario, data, "")
    _check(sc, where)
    return _resolve_commercial_ues(sc)


def _resolve_commercial_ues(sc: Scenario) -> Scenario:
    """`sc` with every user's absent clock sawtooth set to the radio's commercial-UE one."""
    r = sc.radio
    users = [dataclasses.replace(
        u, sawtooth_amplitude_m=r.ue_sawtooth_amplitude_m if u.sawtooth_amplitude_m is None else u.sawtooth_amplitude_m,
        sawtooth_period_s=r.ue_sawtooth_period_s if u.sawtooth_period_s is None else u.sawtooth_period_s)
        for u in sc.users]
    return dataclasses.replace(sc, users=users)


def resolve_scenario_path(name_or_path: str | Path) -> Path:
    """A path as given, or the name of a bundled scenario (`paper` → sitl_scenarios/paper.toml)."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    bundled = SCENARIO_DIR / (p.name if p.suffix == ".toml" else f"{p.name}.toml")
    if bundled.is_file():
        return bundled
    names = ", ".join(sorted(q.stem for q in SCENARIO_DIR.glob("*.toml")))
    raise ScenarioError(f"no scenario file {str(name_or_path)!r}; bundled scenarios: {names}")


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Read a scenario file (or a bundled scenario by name) strictly."""
    path = resolve_scenario_path(name_or_path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{path}: not valid TOML: {exc}") from exc
    except OSError as exc:
        raise ScenarioError(f"{path}: cannot read: {exc}") from exc
    return scenario_from_dict(data, str(path))


def bundled_scenarios() -> list[Path]:
    """Every scenario file shipped in sitl_scenarios/."""
    return sorted(SCENARIO_DIR.glob("*.toml"))
