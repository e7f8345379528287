"""Scenario files: a mission file plus the world it is flown in (docs/design.md §9).

    Scenario  =  mission: mission.config.MissionConfig   what is flown: `name`, `description`,
                                                          [[users]] (id, rnti, ground_height_m),
                                                          [geofence], [flight], [noise], [gnb], [safety],
                                                          [[vehicles]] (a fleet)
              +  world: World                             what is true: `seed`, [origin],
                                                          [truth.<user id>], [[buildings]], [radio],
                                                          [vehicle], [faults]

Both halves are read by the one strict loader (mission.schema: unknown keys, types, units, NaN,
ranges, RNTIs) and the mission half is checked exactly as `uavloc fly --mission` checks a mission
file (mission.config.validate_mission), so a simulated mission is flown with the settings a real
one would be. Where the file leaves them out, the mission's vehicle speeds, assumed range noise and
gNB numerology come from its world (:data:`MISSION_DEFAULTS_FROM_WORLD`).

Positions (users, buildings, geofence, no-fly zones) are ENU offsets in metres from the origin, so
a scenario flies anywhere: with the built-in vehicle the origin is `[origin]`; with an external
vehicle (PX4 SITL) it is the vehicle's home. Every error is a :class:`ScenarioError` that names
the file and the key.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from mission import config as mc
from mission import schema
from mission.config import MAX_DISTANCE_M
from mission.schema import bounded, like, positive
from planner.fleet import Separation
from planner.types import PlanningConstraints
from sitl_scenarios.gnb.faults import GnbFaults
from sitl_scenarios.vehicle_faults import FaultEvent, check_fault_event
from uavloc.errors import MissionConfigError, ScenarioError

SCENARIO_DIR = Path(__file__).resolve().parent

#: the largest seed (numpy's SeedSequence takes non-negative integers; 32 bits is plenty)
MAX_SEED = 2**32 - 1

#: the largest built-in fleet × speed-up `uavloc sim` flies, and the largest built-in fleet at any
#: speed-up (benchmarks/fleet_size.py on 2 cores, docs/fleet.md): each built-in vehicle is a
#: simulator thread, a MAVSDK server and a simulated gNB, whose work grows with the speed-up;
#: beyond them the loop lags by seconds and the gNBs go unanswered (8 vehicles at ×5: lag p99 9.5 s,
#: no range), then the fleet does not end (16 at ×5); 4 at ×5 held, as two_uavs does at ×10
MAX_VEHICLE_SPEEDUP = 20.0
MAX_BUILTIN_VEHICLES = 8


@dataclass(frozen=True)
class OriginConfig:
    """Geodetic origin used by the built-in vehicle (its home)."""

    lat_deg: float = bounded(47.397742, -90.0, 90.0)
    lon_deg: float = bounded(8.545594, -180.0, 180.0)
    alt_m: float = bounded(488.0, -500.0, 9000.0)


@dataclass(frozen=True)
class TrueUserConfig:
    """Where a user really is and how its clock behaves (`[truth.<id>]`, matched to the mission's
    user of that id). east_m, north_m from the origin [m]; its height is the mission's
    ground_height_m (the ground it stands on is known before take-off).

    sawtooth_amplitude_m / sawtooth_period_s: UE downlink-timing drift as a one-way range error that
    rises linearly from 0 to the amplitude and resets (its mean, amplitude/2, is a range bias).
    Absent from the file: a commercial UE, the radio section's ue_sawtooth_amplitude_m / _period_s,
    resolved once when the scenario is read (:func:`scenario_from_dict`), so a loaded scenario's
    users always carry numbers; 0 amplitude: an ideal UE (e.g. a software UE with a perfect clock).
    """

    east_m: float = bounded(dataclasses.MISSING, -MAX_DISTANCE_M, MAX_DISTANCE_M)
    north_m: float = bounded(dataclasses.MISSING, -MAX_DISTANCE_M, MAX_DISTANCE_M)
    sawtooth_amplitude_m: float | None = bounded(None, 0.0, 200.0)
    sawtooth_period_s: float | None = positive(None, 1e5)


@dataclass(frozen=True)
class UserConfig:
    """A simulated user, the mission's user joined with its truth (:attr:`Scenario.users`): id,
    RNTI, true east_m, north_m and up_m (its ground height) from the origin [m], clock sawtooth."""

    id: str
    rnti: int
    east_m: float
    north_m: float
    up_m: float
    sawtooth_amplitude_m: float
    sawtooth_period_s: float


@dataclass(frozen=True)
class BuildingConfig:
    """A building: footprint polygon [[east_m, north_m], ...] (≥ 3 vertices) and height [m]."""

    footprint_enu_m: list[tuple[float, float]]
    height_m: float = positive(dataclasses.MISSING, 1000.0)


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
    coverage_m: float = like(mc.GnbSettings, "coverage_m")
    nlos_excess_mean_m: float = bounded(20.0, 0.0, 500.0)
    snr_db_at_100m: float = bounded(30.0, -50.0, 100.0)
    ue_sawtooth_amplitude_m: float = bounded(12.0, 0.0, 200.0)
    ue_sawtooth_period_s: float = positive(15.0, 1e5)


@dataclass(frozen=True)
class VehicleConfig:
    """Built-in vehicle: speeds [m/s], acceleration [m/s²], GPS noise [m], battery.

    gps_tau_s: correlation time of the GPS error (0: independent per fix; > 0: Gauss-Markov).
    autopilot: whose personality the built-in vehicle has on the wire and in flight, PX4's or
    ArduCopter's (sitl_scenarios.vehicle.ardupilot; docs/ardupilot.md).
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
    autopilot: Literal["px4", "ardupilot"] = "px4"


@dataclass(frozen=True)
class FaultsConfig:
    """The simulators' fault injection: `[faults.gnb]` (the simulated gNB's, GnbFaults) and
    `[[faults.vehicle]]` (the built-in vehicle's scheduled faults, FaultEvent)."""

    gnb: GnbFaults = field(default_factory=GnbFaults)
    vehicle: list[FaultEvent] = field(default_factory=list)


@dataclass(frozen=True)
class World:
    """What is true in a simulation (the world sections of a scenario file): the noise seed, the
    built-in vehicle's home, where the users are, the buildings, the radio, the vehicle model and
    the simulators' faults (`[faults.gnb]`, sitl_scenarios.gnb.faults; `[[faults.vehicle]]`,
    sitl_scenarios.vehicle_faults)."""

    truth: dict[str, TrueUserConfig]
    seed: int = bounded(0, 0, MAX_SEED)
    origin: OriginConfig = field(default_factory=OriginConfig)
    buildings: list[BuildingConfig] = field(default_factory=list)
    radio: RadioConfig = field(default_factory=RadioConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    faults: FaultsConfig = field(default_factory=FaultsConfig)


@dataclass(frozen=True)
class Scenario:
    """A whole scenario file: a mission file's mission plus the world it is flown in."""

    mission: mc.MissionConfig
    world: World

    # -- the world's and the mission's parts under their usual names
    name = property(lambda self: self.mission.name)
    description = property(lambda self: self.mission.description)
    geofence = property(lambda self: self.mission.geofence)
    seed = property(lambda self: self.world.seed)
    origin = property(lambda self: self.world.origin)
    buildings = property(lambda self: self.world.buildings)
    radio = property(lambda self: self.world.radio)
    vehicle = property(lambda self: self.world.vehicle)
    faults = property(lambda self: self.world.faults)

    @property
    def users(self) -> list[UserConfig]:
        """The users in the mission's order, each with its truth."""
        t = self.world.truth
        return [UserConfig(u.id, u.rnti, t[u.id].east_m, t[u.id].north_m, u.ground_height_m,
                           t[u.id].sawtooth_amplitude_m, t[u.id].sawtooth_period_s) for u in self.mission.users]

    @property
    def origin_geo(self) -> Origin:
        return Origin(self.origin.lat_deg, self.origin.lon_deg, self.origin.alt_m)

    def radio_noise_model(self) -> NoiseModel:
        """The range noise the simulated radio draws from (the truth of a simulation)."""
        r = self.radio
        # σ_gps does not enter the radio; a GPS-noise-free vehicle (gps_sigma_m = 0) still needs a valid model
        return NoiseModel(sigma_gps_m=self.vehicle.gps_sigma_m or 1.0, range_s0_m=r.s0_m, range_a_m=r.a_m,
                          range_b_per_m=r.b_per_m)

    def mission_config(self, external_vehicle: bool = False) -> mc.MissionConfig:
        """The mission as flown: the file's, with the GPS error's correlation time, when the file
        leaves it unknown, the built-in vehicle's (that is what it flies with); with an external
        autopilot it stays unknown (PX4's EKF output is not the built-in vehicle's and drifts ~50
        times slower: the flight and replay estimate it from the telemetry)."""
        m = self.mission
        if m.noise.gps_tau_s is not None or external_vehicle:
            return m
        return dataclasses.replace(m, noise=dataclasses.replace(m.noise, gps_tau_s=self.vehicle.gps_tau_s))

    def noise_model(self, external_vehicle: bool = False) -> NoiseModel:
        """The noise model the estimator and planner assume (:meth:`mission_config`'s)."""
        return self.mission_config(external_vehicle).noise_model()

    def planning_constraints(self, home_enu_m=(0.0, 0.0, 0.0), building_clearance_m: float = 5.0,
                             external_vehicle: bool = False, **overrides: Any) -> PlanningConstraints:
        """The planner's constraints of the mission (MissionConfig.planning_constraints) that also
        keep clear of the buildings, with home at home_enu_m.

        Altitudes in the mission are above home; here they become ENU `up` (home up + value).
        Buildings: the UAV overflies every building whose height + `building_clearance_m` fits in the
        altitude band (the band's floor is raised to clear the tallest of them); a building too tall
        for the band becomes a no-fly zone. The mission is :meth:`mission_config`'s (its GPS floor is
        the flown GPS error's). `overrides` replace any field (e.g. margin_m=3.0).
        """
        base = self.mission_config(external_vehicle).planning_constraints(self.origin_geo)
        home = np.asarray(home_enu_m, dtype=float).reshape(3)
        f = self.mission.flight
        alt_min, no_fly = f.alt_min_m, list(base.no_fly_enu_m)
        for b in self.buildings:
            top = b.height_m + building_clearance_m
            if top <= f.alt_max_m:
                alt_min = max(alt_min, top)
            else:
                no_fly.append(np.asarray(b.footprint_enu_m, dtype=float))
        kwargs = dict(home_enu_m=home, no_fly_enu_m=tuple(no_fly), alt_min_m=home[2] + alt_min,
                      alt_max_m=home[2] + f.alt_max_m,
                      cruise_alt_m=home[2] + min(max(f.altitude_m, alt_min), f.alt_max_m))
        kwargs.update(overrides)
        return dataclasses.replace(base, **kwargs)

    def user_by_rnti(self, rnti: int) -> UserConfig:
        for u in self.users:
            if u.rnti == rnti:
                return u
        raise ScenarioError(f"scenario {self.name!r} has no user with RNTI {rnti:#06x}")


# ---------------------------------------------------------------------------------------------
# strict conversion of parsed TOML into the dataclasses above: mission.schema, as for mission files


#: the top-level keys of a scenario file that are the world's (the rest are a mission file's)
WORLD_KEYS = tuple(f.name for f in dataclasses.fields(World))

#: the tables of a scenario's mission whose defaults come from its world, when the file leaves them
#: out: (mission table, key) ← (world table, key). The speeds the mission asks of the vehicle are
#: the built-in vehicle's; the range noise the estimator assumes is the radio's; the gNB is the
#: simulated one.
MISSION_DEFAULTS_FROM_WORLD = (
    (("flight", "cruise_speed_mps"), ("vehicle", "speed_mps")),
    (("flight", "climb_mps"), ("vehicle", "climb_mps")),
    (("flight", "descent_mps"), ("vehicle", "descent_mps")),
    (("noise", "range_s0_m"), ("radio", "s0_m")),
    (("noise", "range_a_m"), ("radio", "a_m")),
    (("noise", "range_b_per_m"), ("radio", "b_per_m")),
    (("gnb", "mu"), ("radio", "mu")),
    (("gnb", "fs_hz"), ("radio", "fs_hz")),
    (("gnb", "coverage_m"), ("radio", "coverage_m")),
)
#: a scenario's mission defaults that differ from a mission file's: its UEs are commercial ones
#: by default (a clock sawtooth, whose mean is a range bias), so the estimator keeps a range bias
SCENARIO_MISSION_DEFAULTS = (("noise", "estimate_bias", True),)

_OLD_MISSION_TABLE = ("a scenario file is a mission file plus world sections: the keys of the former [mission] "
                      "table are in [flight] (delta_m, altitude_m, budget_m, planner, ...), [noise] (sigma_gps_m, "
                      "range_s0_m, gps_tau_s, estimate_bias) and [safety] (battery_rtl_pct); user positions are "
                      "in [truth.<id>]")


def _commercial_ues(world: World) -> bool:
    """Whether any user of the world is a commercial UE (a clock sawtooth of positive amplitude,
    its own or the radio's default)."""
    return any(_with_radio_sawtooth(t, world.radio).sawtooth_amplitude_m > 0 for t in world.truth.values())


def _mission_table(data: dict, world: World) -> dict:
    """The mission file part of a scenario document, with the defaults its world gives."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items() if k not in WORLD_KEYS}
    for (table, key), (wtable, wkey) in MISSION_DEFAULTS_FROM_WORLD:
        if isinstance(out.setdefault(table, {}), dict):
            out[table].setdefault(key, getattr(getattr(world, wtable), wkey))
    for table, key, value in SCENARIO_MISSION_DEFAULTS:
        if isinstance(out.setdefault(table, {}), dict):
            out[table].setdefault(key, value)
    if isinstance(out["noise"], dict):
        # the operator knows the kind of UEs: commercial ones (a clock sawtooth) hold an
        # insignificant bias at an untracked sawtooth's mean, ideal ones at 0
        out["noise"].setdefault("bias_held", "sawtooth" if _commercial_ues(world) else "zero")
    safety = out.setdefault("safety", {})
    if isinstance(safety, dict) and "battery_rtl_pct" in safety:
        # a low-battery return threshold above the take-off floor raises the floor with it
        safety.setdefault("battery_takeoff_min_pct", max(mc.SafetyConfig.battery_takeoff_min_pct,
                                                         safety["battery_rtl_pct"]))
    return out


def _explain_unknown(cls: type, name: str) -> str | None:
    if cls is mc.MissionConfig:
        keys = sorted({f.name for f in dataclasses.fields(mc.MissionConfig)} | set(WORLD_KEYS))
        return f"unknown key {name!r}; allowed here: {', '.join(keys)}"
    if cls is mc.MissionUserConfig and name in ("east_m", "north_m", "up_m", "sawtooth_amplitude_m",
                                                "sawtooth_period_s"):
        return f"a user's truth is in [truth.<id>] (up_m is the user's ground_height_m); {_OLD_MISSION_TABLE}"
    return None


def _check(sc: Scenario, where: str) -> None:
    """The checks across fields and sections (each number's own range is checked by
    mission.schema.build, the mission's consistency by mission.config.validate_mission)."""
    ids = [u.id for u in sc.mission.users]
    for uid in ids:
        if uid not in sc.world.truth:
            raise schema.fail(where, "truth", sorted(sc.world.truth), f"user {uid!r} has no [truth.{uid}]",
                              ScenarioError)
    extra = sorted(set(sc.world.truth) - set(ids))
    if extra:
        raise schema.fail(where, f"truth.{extra[0]}", sc.world.truth[extra[0]], "no [[users]] entry has this id",
                          ScenarioError)
    for i, b in enumerate(sc.buildings):
        if len(b.footprint_enu_m) < 3:
            raise schema.fail(where, f"buildings[{i}].footprint_enu_m", b.footprint_enu_m,
                              "needs >= 3 [east, north] points", ScenarioError)
    for i, v in enumerate(sc.mission.vehicles):
        for key in ("connect", "gnb"):
            if getattr(v, key) is not None:
                raise schema.fail(where, f"vehicles[{i}].{key}", getattr(v, key),
                                  "a scenario's vehicles are the simulator's: `uavloc sim` gives each its own "
                                  "addresses (built-in vehicles and simulated gNBs; external autopilots by "
                                  "`--connect URL,URL`), so the key would be ignored; leave it out", ScenarioError)
    _check_launch_points(sc, where)
    vehicle_ids = [v.id for v in sc.mission.vehicles]
    for i, ev in enumerate(sc.faults.vehicle):
        check_fault_event(ev, where, f"faults.vehicle[{i}]")
        if ev.vehicle and ev.vehicle not in vehicle_ids:
            raise schema.fail(where, f"faults.vehicle[{i}].vehicle", ev.vehicle,
                              f"no [[vehicles]] entry has this id (ids: {vehicle_ids})", ScenarioError)


def launch_points_enu_m(home_enu_m: np.ndarray, n_vehicles: int, separation: Separation) -> np.ndarray:
    """(V, 3) where a simulated fleet's vehicles take off: on a ring around home, vehicle v at bearing
    θ_v = 2πv/V from east, neighbours 5 m more than the horizontal separation
    apart (one vehicle: at home). A UE attaches to the nearest cell at take-off, so a ring gives each
    vehicle the users of its own sector; on a line, the middle vehicle of three took off with none."""
    home = np.asarray(home_enu_m, float)
    if n_vehicles == 1:
        return home[None, :].copy()
    # neighbours on the ring a chord 2 r sin(π/V) = separation + 5 m apart
    r = (separation.horizontal_m + 5.0) / (2.0 * np.sin(np.pi / n_vehicles))
    theta = 2.0 * np.pi * np.arange(n_vehicles) / n_vehicles
    return home[None, :] + np.column_stack([r * np.cos(theta), r * np.sin(theta), np.zeros(n_vehicles)])


def _check_launch_points(sc: Scenario, where: str) -> None:
    """A built-in fleet takes off from its launch points (sitl_scenarios.fleet: a ring whose size
    grows with `[safety] separation_m`): each must be a place one vehicle's home may be, inside the
    fence, outside every no-fly zone, within max_distance_m of the origin, as a flight checks a
    vehicle's home before take-off (mission.safety.SafetyGate.home_violations)."""
    if sc.mission.fleet_size < 2:
        return
    from mission.safety import SafetyGate, SafetyLimits

    fence, zones = sc.geofence.polygons_enu_m(sc.origin_geo)
    gate = SafetyGate(SafetyLimits(fence_enu_m=fence, no_fly_enu_m=zones, max_distance_m=sc.geofence.max_distance_m))
    safety = sc.mission.safety
    points = launch_points_enu_m(np.zeros(3), sc.mission.fleet_size,
                                 Separation(safety.separation_m, safety.separation_vertical_m))
    bad = [(v, p, gate.home_violations(p)) for v, p in zip(sc.mission.vehicles, points, strict=True)]
    bad = [b for b in bad if b[2]]
    if bad:
        radius_m = float(np.hypot(*points[0, :2]))
        raise schema.fail(where, "safety.separation_m", sc.mission.safety.separation_m,
                          f"the {sc.mission.fleet_size} vehicles take off on a ring of {radius_m:.1f} m around the "
                          f"origin (neighbours separation_m + 5 m apart), and "
                          + "; ".join(f"{v.id}'s {'; '.join(why)}" for v, _, why in bad)
                          + ": no vehicle takes off from there (a smaller separation_m or fleet, or a wider "
                            "[geofence])", ScenarioError)


def scenario_from_dict(data: dict, where: str = "scenario") -> Scenario:
    """Build and validate a :class:`Scenario` from a parsed TOML document: its world sections
    (:data:`WORLD_KEYS`) and a mission file (mission.config, checked as `uavloc fly --mission`
    checks one, with the defaults :data:`MISSION_DEFAULTS_FROM_WORLD` gives); `where` (the file)
    names the source in every message."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{where}: a scenario is a TOML document")
    if "mission" in data:
        raise schema.fail(where, "mission", data["mission"], _OLD_MISSION_TABLE, ScenarioError)
    # a key neither part knows is named before a part misses one (often it is that one, misspelt)
    mission_keys = {f.name for f in dataclasses.fields(mc.MissionConfig)}
    for name, value in data.items():
        if name not in WORLD_KEYS and name not in mission_keys:
            raise schema.fail(where, name, value, _explain_unknown(mc.MissionConfig, name), ScenarioError)
    world = schema.build(World, {k: v for k, v in data.items() if k in WORLD_KEYS}, where, error=ScenarioError)
    mission = schema.build(mc.MissionConfig, _mission_table(data, world), where, error=ScenarioError,
                           explain=_explain_unknown)
    try:
        mc.validate_mission(mission, where)
    except MissionConfigError as exc:
        raise ScenarioError(str(exc)) from None
    sc = Scenario(mission, world)
    _check(sc, where)
    return _resolve_commercial_ues(sc)


def _resolve_commercial_ues(sc: Scenario) -> Scenario:
    """`sc` with every user's absent clock sawtooth set to the radio's commercial-UE one."""
    truth = {uid: _with_radio_sawtooth(t, sc.radio) for uid, t in sc.world.truth.items()}
    return dataclasses.replace(sc, world=dataclasses.replace(sc.world, truth=truth))


def _with_radio_sawtooth(t: TrueUserConfig, r: RadioConfig) -> TrueUserConfig:
    """A user's truth with an absent clock sawtooth set to the radio's commercial-UE one."""
    return dataclasses.replace(
        t, sawtooth_amplitude_m=r.ue_sawtooth_amplitude_m if t.sawtooth_amplitude_m is None else t.sawtooth_amplitude_m,
        sawtooth_period_s=r.ue_sawtooth_period_s if t.sawtooth_period_s is None else t.sawtooth_period_s)


def user_tables(users: list[dict]) -> dict:
    """The `[[users]]` (mission) and `[truth.<id>]` (world) tables of a scenario document for
    simulated users given one table each: id, rnti, east_m, north_m, up_m (its ground height, 0
    when absent), sawtooth_amplitude_m, sawtooth_period_s (optional). For code that writes worlds
    (campaign families, tests, benchmarks); the keys are checked when the document is read."""
    truth_keys = ("east_m", "north_m", "sawtooth_amplitude_m", "sawtooth_period_s")
    mission = [{"id": u["id"], "rnti": u["rnti"], **({"ground_height_m": u["up_m"]} if "up_m" in u else {}),
                **{k: v for k, v in u.items() if k not in (*truth_keys, "id", "rnti", "up_m")}} for u in users]
    truth = {u["id"]: {k: u[k] for k in truth_keys if k in u} for u in users}
    return {"users": mission, "truth": truth}


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


def check_fleet_load(scenario: Scenario, speedup: float) -> None:
    """MissionError unless this machine carries the scenario's built-in fleet at `speedup`:
    at most MAX_BUILTIN_VEHICLES vehicles and vehicles × speed-up at most MAX_VEHICLE_SPEEDUP (a
    fleet of two or more: one vehicle is not bounded)."""
    from uavloc.errors import MissionError

    n = scenario.mission.fleet_size
    load = n * speedup
    # one vehicle flies at any speed-up the simulation offers (x200: tests/test_mission_e2e.py); a
    # fleet's vehicles share the controller's loop, which is what the limit bounds
    if n == 1 or (n <= MAX_BUILTIN_VEHICLES and load <= MAX_VEHICLE_SPEEDUP):
        return
    why = (f"{n} vehicles, more than the {MAX_BUILTIN_VEHICLES} built-in vehicles it can carry"
           if n > MAX_BUILTIN_VEHICLES else
           f"{n} vehicles × speed-up {speedup:g} = {load:g}, above the {MAX_VEHICLE_SPEEDUP:g} it can carry")
    hint = (f"--speedup {MAX_VEHICLE_SPEEDUP / n:g} or less" if n <= MAX_BUILTIN_VEHICLES
            else f"at most {MAX_BUILTIN_VEHICLES} [[vehicles]]")
    raise MissionError(f"scenario {scenario.name!r} flies {n} built-in vehicles at ×{speedup:g}: {why} "
                       f"(vehicles × speed-up <= {MAX_VEHICLE_SPEEDUP:g}, at most {MAX_BUILTIN_VEHICLES} "
                       f"vehicles: benchmarks/fleet_size.py on 2 cores; beyond, the loop lags by seconds, the gNBs "
                       f"go unanswered and the fleet stalls); give {hint}")


def with_autopilot(scenario: Scenario, autopilot: str) -> Scenario:
    """The scenario with the built-in vehicle's personality `autopilot` ("px4", "ardupilot")."""
    vehicle = dataclasses.replace(scenario.vehicle, autopilot=autopilot)
    return dataclasses.replace(scenario, world=dataclasses.replace(scenario.world, vehicle=vehicle))


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
    if scenario.mission.fleet_size > 1 and not external_vehicle:
        # the built-in fleet takes off on a ring around the scenario's origin (sitl_scenarios.fleet):
        # the mission's ENU frame, where its fence and buildings are, is that origin's
        kwargs.setdefault("origin", lambda homes: scenario.origin_geo)
    return controller_from_mission(
        scenario.mission_config(external_vehicle), vehicle, gnb, log_path,
        seed=scenario.seed if seed is None else seed, header_config=header,
        constraints=lambda home: scenario.planning_constraints(external_vehicle=external_vehicle), **kwargs)


def flight_mission(name_or_path: str | Path) -> mc.MissionConfig:
    """The mission part of a scenario as a real autopilot flies it (`uavloc fly --scenario`, found
    through the `uavloc.scenarios` entry point's module): no true positions, and the GPS error
    model left to the flight (an external autopilot's is not the built-in vehicle's)."""
    return load_scenario(name_or_path).mission_config(external_vehicle=True)


def bundled_scenarios() -> list[Path]:
    """Every scenario file shipped in sitl_scenarios/."""
    return sorted(SCENARIO_DIR.glob("*.toml"))
