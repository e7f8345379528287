"""Scenario files: strict TOML whose keys are the fields of the dataclasses below (DESIGN.md §9).

Positions (users, buildings, geofence, no-fly zones) are ENU offsets in metres from the origin, so
a scenario flies anywhere: with the built-in vehicle the origin is `[origin]`; with an external
vehicle (PX4 SITL) it is the vehicle's home. Unknown keys, wrong types and out-of-range numbers are a
:class:`ScenarioError` that names the file and the key.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from mission import config as mc
from mission import schema
from mission.config import MAX_DISTANCE_M, MAX_HEIGHT_M
from mission.schema import bounded, like, positive
from planner.types import PlanningConstraints
from uavloc.errors import MissionConfigError, ScenarioError

SCENARIO_DIR = Path(__file__).resolve().parent

#: the largest seed (numpy's SeedSequence takes non-negative integers; 32 bits is plenty)
MAX_SEED = 2**32 - 1
#: the tables of `[faults]`: the simulated gNB's (sitl_scenarios.gnb_faults) and the vehicle's
FAULT_TABLES = ("gnb", "vehicle")


@dataclass(frozen=True)
class OriginConfig:
    """Geodetic origin used by the built-in vehicle (its home)."""

    lat_deg: float = bounded(47.397742, -90.0, 90.0)
    lon_deg: float = bounded(8.545594, -180.0, 180.0)
    alt_m: float = bounded(488.0, -500.0, 9000.0)


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
    rnti: int = like(mc.MissionUserConfig, "rnti")
    east_m: float = bounded(dataclasses.MISSING, -MAX_DISTANCE_M, MAX_DISTANCE_M)
    north_m: float = bounded(dataclasses.MISSING, -MAX_DISTANCE_M, MAX_DISTANCE_M)
    up_m: float = bounded(0.0, -MAX_HEIGHT_M, MAX_HEIGHT_M)
    sawtooth_amplitude_m: float | None = bounded(None, 0.0, 200.0)
    sawtooth_period_s: float | None = positive(None, 1e5)


@dataclass(frozen=True)
class BuildingConfig:
    """A building: footprint polygon [[east_m, north_m], ...] (≥ 3 vertices) and height [m]."""

    footprint_enu_m: list[tuple[float, float]]
    height_m: float = positive(dataclasses.MISSING, 1000.0)


@dataclass(frozen=True)
class GeofenceConfig:
    """Inclusion polygon [[east_m, north_m], ...] (may be non-convex; empty: none), a maximum
    horizontal distance from home [m], and exclusion polygons (no-fly zones)."""

    polygon_enu_m: list[tuple[float, float]] = field(default_factory=list)
    max_distance_m: float = positive(500.0, MAX_DISTANCE_M)
    no_fly_enu_m: list[list[tuple[float, float]]] = field(default_factory=list)


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

    mu: int = like(mc.GnbSettings, "mu")
    fs_hz: float = like(mc.GnbSettings, "fs_hz")
    oversampling: int = bounded(8, 1, 1024)
    s0_m: float = like(mc.NoiseConfig, "range_s0_m")
    a_m: float = like(mc.NoiseConfig, "range_a_m")
    b_per_m: float = like(mc.NoiseConfig, "range_b_per_m")
    coverage_m: float = positive(1500.0, 1e5)
    nlos_excess_mean_m: float = bounded(20.0, 0.0, 500.0)
    snr_db_at_100m: float = bounded(30.0, -50.0, 100.0)
    ue_sawtooth_amplitude_m: float = bounded(12.0, 0.0, 200.0)
    ue_sawtooth_period_s: float = positive(15.0, 1e5)


@dataclass(frozen=True)
class VehicleConfig:
    """Built-in vehicle: speeds [m/s], acceleration [m/s²], GPS noise [m], battery.

    gps_tau_s: correlation time of the GPS error (0: independent per fix; > 0: Gauss-Markov).
    """

    speed_mps: float = like(mc.FlightConfig, "cruise_speed_mps")
    climb_mps: float = like(mc.FlightConfig, "climb_mps")
    descent_mps: float = like(mc.FlightConfig, "descent_mps")
    accel_mps2: float = positive(3.0, 50.0)
    gps_sigma_m: float = bounded(1.0, 0.0, 100.0)
    # the built-in vehicle's own error; an external autopilot's is not this one (Scenario.noise_model):
    # PX4 SITL's (SIH) EKF output drifts far slower, its increments say tau ~ 120-220 s at sigma 1 m
    gps_tau_s: float = bounded(3.0, 0.0, 1e5)
    battery_capacity_s: float = positive(1800.0, 1e5)
    battery_start_pct: float = positive(100.0, 100.0)


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

    delta_m: float = like(mc.FlightConfig, "delta_m")
    altitude_m: float = like(mc.FlightConfig, "altitude_m")
    alt_min_m: float = like(mc.FlightConfig, "alt_min_m")
    alt_max_m: float = like(mc.FlightConfig, "alt_max_m")
    target_radius_m: float = like(mc.FlightConfig, "target_radius_m")
    budget_m: float = like(mc.FlightConfig, "budget_m")
    time_limit_s: float = like(mc.FlightConfig, "time_limit_s")
    leg_max_m: float = like(mc.FlightConfig, "leg_max_m")
    acceptance_m: float = like(mc.FlightConfig, "acceptance_m")
    battery_rtl_pct: float = like(mc.SafetyConfig, "battery_rtl_pct")
    sigma_gps_m: float = like(mc.NoiseConfig, "sigma_gps_m")
    planner: str = "casadi"
    estimate_bias: bool = True
    range_s0_m: float | None = positive(None, 1000.0)
    gps_tau_s: float | None = like(mc.NoiseConfig, "gps_tau_s")


@dataclass(frozen=True)
class Scenario:
    """A whole scenario file."""

    name: str
    users: list[UserConfig]
    seed: int = bounded(0, 0, MAX_SEED)
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

    def mission_config(self, external_vehicle: bool = False, where: str | None = None) -> mc.MissionConfig:
        """The mission part of this scenario as a :class:`mission.config.MissionConfig` (what a real
        flight would be configured with: users without their positions, fence, limits, the noise
        the estimator assumes (noise_model(external_vehicle)), the gNB's numerology). The bridge
        until scenarios are written as a mission plus a world (see mission/config.py). Checked by
        mission.config.validate_mission (where: the file, for messages)."""
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
        mc.validate_mission(out, where or f"scenario {self.name!r}")
        return out

    def user_by_rnti(self, rnti: int) -> UserConfig:
        for u in self.users:
            if u.rnti == rnti:
                return u
        raise ScenarioError(f"scenario {self.name!r} has no user with RNTI {rnti:#06x}")


# ---------------------------------------------------------------------------------------------
# strict conversion of parsed TOML into the dataclasses above: mission.schema, as for mission files


def _check(sc: Scenario, where: str) -> None:
    """The checks across fields (each number's own range is checked by mission.schema.build)."""
    for i, u in enumerate(sc.users):
        if not (u.id and u.id.strip()):
            raise schema.fail(where, f"users[{i}].id", u.id, "a user needs an id", ScenarioError)
    for i, b in enumerate(sc.buildings):
        if len(b.footprint_enu_m) < 3:
            raise schema.fail(where, f"buildings[{i}].footprint_enu_m", b.footprint_enu_m,
                              "needs >= 3 [east, north] points", ScenarioError)
    for i, poly in enumerate([sc.geofence.polygon_enu_m, *sc.geofence.no_fly_enu_m]):
        if poly and len(poly) < 3:
            key = "geofence.polygon_enu_m" if i == 0 else f"geofence.no_fly_enu_m[{i - 1}]"
            raise schema.fail(where, key, poly, "needs >= 3 [east, north] points", ScenarioError)
    unknown = sorted(set(sc.faults) - set(FAULT_TABLES))
    if unknown:
        raise schema.fail(where, f"faults.{unknown[0]}", sc.faults[unknown[0]],
                          f"unknown key; allowed here: {', '.join(FAULT_TABLES)}", ScenarioError)
    # the simulators' own strict readers of their tables, so a bad fault is refused at load
    from sitl_scenarios.gnb_faults import GnbFaults
    from sitl_scenarios.vehicle.fault_events import faults_from_scenario

    try:
        GnbFaults.from_table(sc.faults.get("gnb", {}))
        faults_from_scenario(sc.faults)
    except ScenarioError as exc:
        raise ScenarioError(f"{where}: {exc}") from None
    # the mission part is checked as a mission file is (users, RNTIs, fence, home, band, ...)
    try:
        sc.mission_config(where=where)
    except MissionConfigError as exc:
        raise ScenarioError(str(exc)) from None


def scenario_from_dict(data: dict, where: str = "scenario") -> Scenario:
    """Build and validate a :class:`Scenario` from a parsed TOML document; `where` (the file)
    names the source in every message."""
    sc = schema.build(Scenario, data, where, error=ScenarioError)
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


def bundled_scenario_names() -> list[str]:
    """The names of the scenario files shipped in sitl_scenarios/ (`paper`, ...)."""
    return sorted(q.stem for q in SCENARIO_DIR.glob("*.toml"))


def resolve_scenario_path(name_or_path: str | Path, base_dir: Path | None = None) -> Path:
    """The file of a scenario: a bare name without a folder or suffix (`paper`) is a bundled
    scenario (sitl_scenarios/paper.toml); anything else (`nodir/paper.toml`, `paper.toml`) is a
    path, relative to base_dir when given, and must exist: never the bundled file of the same name."""
    text = str(name_or_path)
    p = Path(text)
    bare = p.parent == Path(".") and not p.suffix and "/" not in text and "\\" not in text
    names = ", ".join(bundled_scenario_names())
    if bare:
        bundled = SCENARIO_DIR / f"{p.name}.toml"
        if bundled.is_file():
            return bundled
        raise ScenarioError(f"no bundled scenario {text!r} (a file is given by its path, e.g. {text}.toml "
                            f"or ./{text}); bundled scenarios: {names}")
    path = p if base_dir is None or p.is_absolute() else base_dir / p
    if not path.is_file():
        raise ScenarioError(f"{path}: no such scenario file (a bundled scenario is given by its bare name; "
                            f"bundled scenarios: {names})")
    return path


def load_scenario(name_or_path: str | Path, base_dir: Path | None = None) -> Scenario:
    """Read a scenario file (or a bundled scenario by name, :func:`resolve_scenario_path`) strictly."""
    path = resolve_scenario_path(name_or_path, base_dir)
    return scenario_from_dict(schema.read_toml(path, "scenario file", ScenarioError), str(path))


def controller_from_scenario(scenario: Scenario, vehicle: Any, gnb: Any, log_path: str | Path, *,
                             seed: int | None = None, external_vehicle: bool = False, **kwargs: Any) -> Any:
    """A :class:`mission.controller.MissionController` for a simulation scenario: its mission
    (`scenario.mission_config(external_vehicle)`: an external autopilot's GPS error is not the
    built-in vehicle's) flown by `mission.controller.controller_from_mission`, with the planning
    constraints that also keep clear of the scenario's buildings. seed: default the scenario's;
    kwargs: controller_from_mission's (planner, time_scale, truth, header_config, params,
    buildings, ControllerConfig overrides)."""
    from mission.controller import controller_from_mission

    header = {"scenario": scenario.name, **(kwargs.pop("header_config", None) or {})}
    return controller_from_mission(
        scenario.mission_config(external_vehicle), vehicle, gnb, log_path,
        seed=scenario.seed if seed is None else seed, header_config=header,
        constraints=lambda home: scenario.planning_constraints(), **kwargs)


def flight_mission(name_or_path: str | Path) -> mc.MissionConfig:
    """The mission part of a scenario as a real autopilot flies it (`uavloc fly --scenario`, found
    through the `uavloc.scenarios` entry point's module): no true positions, and the GPS error
    model left to the flight (an external autopilot's is not the built-in vehicle's)."""
    return load_scenario(name_or_path).mission_config(external_vehicle=True)


def bundled_scenarios() -> list[Path]:
    """Every scenario file shipped in sitl_scenarios/."""
    return sorted(SCENARIO_DIR.glob("*.toml"))
