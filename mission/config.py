"""The mission file a real flight is flown with (`uavloc fly --mission FILE`): strict TOML.

What an operator knows before take-off and nothing else: the users by id and RNTI (with the
height of the ground they stand on), the geofence and no-fly zones, the altitude band, Δ, the
target accuracy, budget and time limit, the cruise speed, the noise model the estimator assumes,
how to talk to the gNB, and how long to wait before giving up on a lost link or gNB. A mission
file never holds a user's true position: that is what the flight is for.

The TOML keys ARE the field names of the frozen dataclasses below (`[flight] budget_m = 1200`),
read by the one strict loader of every uavloc file (mission.schema): an unknown key, a key in the
wrong unit (`budget_km`), a wrong type, a NaN, a number outside its field's bounds (what a
multicopter mission can mean: `MAX_HEIGHT_M`, `MAX_SPEED_MPS`, ... beside each field) or a
file that is not UTF-8 is a :class:`MissionConfigError` naming the file, the key and the value.
:func:`validate_mission` checks what spans fields (distinct users and RNTIs, the altitude band,
home inside the fence and outside every no-fly zone, a fleet's ids and bands, ...). Units are in
the names (`_m`, `_s`, `_mps`, `_pct`, `_deg`, `_hz`); positions are ENU offsets in metres from
home (`*_enu_m`, as in docs/design.md §9) or geodetic (`*_lat_lon_deg`, [[lat_deg, lon_deg],
...]), one or the other per polygon kind; :meth:`GeofenceConfig.polygons_enu_m` turns both into
home-ENU once home is known.

A simulation scenario (sitl_scenarios/scenario.py) is a mission file plus world sections (true
users, buildings, radio, vehicle model, faults): its mission half is a :class:`MissionConfig`
read and checked exactly as here, so a simulated mission is flown with the settings a real one
would be. `sitl_scenarios` imports `mission` and never the other way; nothing here takes a
scenario.

Example: `mission/examples/flight.toml` (shipped as package data; :func:`example_mission_path`).
"""

from __future__ import annotations

import dataclasses
import re
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from estimator.geodesy import Origin
from estimator.gps import gps_floor_bound_95_m, gps_tau_for_floor_s
from estimator.noise import DEFAULT_GPS_TAU_S, NoiseModel
from mission import schema
from mission.schema import bounded, positive
from uavloc.errors import MissionConfigError, UavlocError

if typing.TYPE_CHECKING:
    from planner.types import PlanningConstraints

EXAMPLES_DIR = Path(__file__).resolve().parent / "examples"

Polygon = tuple[tuple[float, float], ...]

# What a multicopter mission can mean: the upper bounds of the numbers of a mission file (each
# field's bounds are beside it, mission.schema.bounded; a value outside is refused with its key).
#: heights above home and ground heights [m] (the legal ceiling is 120 m in most countries)
MAX_HEIGHT_M = 500.0
#: distances from home and leg lengths [m]
MAX_DISTANCE_M = 20_000.0
#: survey metres [m] (a multicopter's range on one battery is a few km)
MAX_BUDGET_M = 100_000.0
#: mission time [s] (a multicopter's endurance is well under an hour)
MAX_MISSION_S = 7200.0
#: horizontal speed [m/s]; vertical speeds [m/s]
MAX_SPEED_MPS = 30.0
MAX_VERTICAL_MPS = 10.0
#: the largest C-RNTI (0xFFF0.. are reserved)
MAX_RNTI = 0xFFEF

#: keys that would place a user: a mission file never holds them.
TRUE_POSITION_KEYS = frozenset({
    "east_m", "north_m", "up_m", "x_m", "y_m", "z_m", "lat_deg", "lon_deg", "alt_m", "position",
    "position_enu_m", "pos_enu_m", "enu_m", "latitude", "longitude", "true_position",
})
#: top-level sections of a simulation scenario that describe the world, not the mission.
WORLD_SECTIONS = frozenset({"buildings", "radio", "vehicle", "faults", "truth", "origin", "seed", "world"})


@dataclass(frozen=True)
class MissionUserConfig:
    """A user (UE) to locate. rnti: its C-RNTI (1..0xFFEF; "0x4601" or 17921);
    ground_height_m: height of the ground it stands on above home [m] (ENU up; 0 = level with home)."""

    id: str
    rnti: int = bounded(dataclasses.MISSING, 1, MAX_RNTI, what="an RNTI is in 0x0001..0xFFEF")
    ground_height_m: float = bounded(0.0, -MAX_HEIGHT_M, MAX_HEIGHT_M)


@dataclass(frozen=True)
class GeofenceConfig:
    """Where the vehicle may fly. Inclusion polygon and no-fly (exclusion) polygons, each given
    either as ENU offsets from home [m] ([[east_m, north_m], ...]) or geodetic ([[lat_deg, lon_deg],
    ...]); open rings (the closing edge is implied), ≥ 3 vertices, possibly non-convex; empty:
    none. max_distance_m: largest horizontal distance from home [m]."""

    polygon_enu_m: Polygon = ()
    polygon_lat_lon_deg: Polygon = ()
    no_fly_enu_m: tuple[Polygon, ...] = ()
    no_fly_lat_lon_deg: tuple[Polygon, ...] = ()
    max_distance_m: float = positive(500.0, MAX_DISTANCE_M)

    def polygons_enu_m(self, home: Origin) -> tuple[np.ndarray | None, tuple[np.ndarray, ...]]:
        """(fence (P, 2) or None, no-fly zones ((Q, 2), ...)) in the home ENU frame [m]."""

        def enu(poly_deg: Polygon) -> np.ndarray:
            lat, lon = np.asarray(poly_deg, float).T
            return home.lla_to_enu(lat, lon, np.full_like(lat, home.alt_m))[:, :2]

        fence = (np.asarray(self.polygon_enu_m, float) if self.polygon_enu_m
                 else enu(self.polygon_lat_lon_deg) if self.polygon_lat_lon_deg else None)
        zones = tuple(np.asarray(z, float) for z in self.no_fly_enu_m)
        zones += tuple(enu(z) for z in self.no_fly_lat_lon_deg)
        return fence, zones


@dataclass(frozen=True)
class FlightConfig:
    """How to fly. altitude_m: survey height above home; alt_min_m ≤ altitude_m ≤ alt_max_m: the
    allowed band above home [m]; delta_m: keyframe spacing Δ [m]; target_radius_m: stop when every
    user's 95 % error ellipse fits in this radius [m]; budget_m: survey metres; time_limit_s:
    mission time; cruise_speed_mps, climb_mps, descent_mps: speeds asked of the vehicle (and its
    leg / landing timeouts) [m/s]; leg_max_m: longest leg the planner may choose; acceptance_m:
    arrival radius [m]; planner: "casadi", "greedy", "lawnmower", "circle" or "random" (not
    "oracle": it needs the true positions a flight does not have)."""

    altitude_m: float = positive(30.0, MAX_HEIGHT_M)
    alt_min_m: float = bounded(10.0, 0.0, MAX_HEIGHT_M)
    alt_max_m: float = positive(120.0, MAX_HEIGHT_M)
    delta_m: float = positive(2.0, 100.0)
    target_radius_m: float = positive(2.0, 1000.0)
    budget_m: float = positive(2000.0, MAX_BUDGET_M)
    time_limit_s: float = positive(1200.0, MAX_MISSION_S)
    cruise_speed_mps: float = positive(10.0, MAX_SPEED_MPS)
    climb_mps: float = positive(3.0, MAX_VERTICAL_MPS)
    descent_mps: float = positive(1.5, MAX_VERTICAL_MPS)
    leg_max_m: float = positive(80.0, MAX_DISTANCE_M)
    acceptance_m: float = positive(2.0, 50.0)
    planner: Literal["casadi", "greedy", "lawnmower", "circle", "random"] = "casadi"


@dataclass(frozen=True)
class NoiseConfig:
    """The noise the estimator and planner assume (docs/design.md §4, §5).

    sigma_gps_m: per-axis GPS error [m]; gps_tau_s: its correlation time [s] (absent: unknown);
    σ(d) = range_s0_m + range_a_m·exp(range_b_per_m·d) one-way range spread [m];
    estimate_bias: estimate a range bias per user (a UE clock sawtooth has a positive mean), with a
    zero-mean prior of bias_prior_sigma_m [m]; bias_held: what a bias too small to show is held at
    (estimator.types.SolverParams.bias_held): "zero" (ideal UEs, or offsets calibrated out) or
    "sawtooth" (commercial UEs: the mean of a clock sawtooth too small to track, and its spread).
    """

    # the defaults are NoiseModel's (estimator.noise), not typed again here
    sigma_gps_m: float = positive(NoiseModel.sigma_gps_m, 100.0)
    gps_tau_s: float | None = bounded(None, 0.0, 1e5)
    range_s0_m: float = positive(NoiseModel.range_s0_m, 1000.0)
    range_a_m: float = bounded(NoiseModel.range_a_m, 0.0, 1000.0)
    range_b_per_m: float = bounded(NoiseModel.range_b_per_m, -1.0, 1.0)
    estimate_bias: bool = False
    bias_prior_sigma_m: float = positive(10.0, 1000.0)
    bias_held: Literal["zero", "sawtooth"] = "zero"

    def noise_model(self) -> NoiseModel:
        """The estimator's :class:`NoiseModel`."""
        return NoiseModel(sigma_gps_m=self.sigma_gps_m, range_s0_m=self.range_s0_m, range_a_m=self.range_a_m,
                          range_b_per_m=self.range_b_per_m, gps_tau_s=self.gps_tau_s)

    def header_noise(self) -> dict:
        """The mission log header's `noise` section (docs/design.md §10), with `gps_tau_s` when known."""
        return self.noise_model().to_log_dict()


@dataclass(frozen=True)
class GnbSettings:
    """How to measure with the gNB (docs/design.md §8; the address is given on the command line).

    transport: "telnet" or "rest" (OAI's web server), for a `--gnb` address without a scheme
    (`telnet://` and `http://` say it themselves); mode: "rtt" (the RTT telnet module), "trace"
    (a stock gNB's T tracer: RAR TA, TA commands and the SRS peak, docs/oai.md), "stock" (the Msg2
    lines of log_path) or "auto" (the best the gNB serves, found before take-off); t_port: the
    gNB's T tracer port (`--T_port`, default 2021); trace_max_age_s: trace mode, the oldest RTT a
    keyframe takes [s]; trace_max_range_rate_mps: trace mode, the fastest a range may change
    (cruise speed plus the users' speed) [m/s]: a faster jump is held until it is physical;
    trace_jump_tolerance_m: what range noise may add to that jump (about 3 σ of one SRS) [m];
    trace_clock_step_m: the largest drop of a range taken at once, a commercial UE's clock
    correction (its sawtooth's amplitude) [m];
    srs_min_peak_to_mean_db: trace mode, an SRS estimate whose peak stands less above its mean
    tap power is stale [dB]; stock_mode:
    "active" (trigger a random access with `ci force_reestab`, then wait for its Msg2) or "passive"
    (only the random accesses that happen anyway); rtt_module, rtt_command: the RTT command's
    names; discovery: "auto", "o1" or "single"; mu, fs_hz: numerology and sampling rate of the gNB
    (the log header's `radio`); log_path: the gNB log followed in stock mode; request_timeout_s,
    connect_timeout_s: per request / connection attempt [s]; msg2_timeout_s: active stock mode, how
    long to wait for the UE's random access after the trigger [s] (real OAI: about 5 s of log time,
    and the rfsimulator may run at 0.4x real time, hence 15 s); retries: reconnect attempts after a
    lost connection; coverage_m: the cell's reach, the slant range beyond which the gNB hears no UE
    [m] (the planner counts no ranges from beyond it). :meth:`measure_timeout_s` is what the
    controller allows one measurement;
    the adapter's settings are these and its own (:meth:`mission.gnb.config.GnbConfig.of`).
    """

    transport: Literal["telnet", "rest"] = "telnet"
    mode: Literal["rtt", "trace", "stock", "auto"] = "rtt"
    t_port: int = bounded(2021, 1, 65535)
    trace_max_age_s: float = positive(0.5, 60.0)
    trace_max_range_rate_mps: float = positive(12.0, 200.0)
    trace_jump_tolerance_m: float = positive(5.0, 1000.0)
    trace_clock_step_m: float = bounded(15.0, 0.0, 1000.0)
    srs_min_peak_to_mean_db: float = bounded(18.0, 0.0, 60.0)
    stock_mode: Literal["active", "passive"] = "passive"
    rtt_module: str = "rtt"
    rtt_command: str = "pdcch_order"
    discovery: Literal["auto", "o1", "single"] = "auto"
    mu: int = bounded(1, 0, 3, what="the numerology is 0..3")
    fs_hz: float = positive(46.08e6, 1e10)
    coverage_m: float = positive(1500.0, 1e5)
    log_path: str | None = None
    request_timeout_s: float = positive(2.0, 120.0)
    connect_timeout_s: float = positive(2.0, 120.0)
    msg2_timeout_s: float = positive(15.0, 600.0)
    retries: int = bounded(3, 0, 100)

    def problems(self) -> list[tuple[str, Any, str]]:
        """(field, value, why) of each setting that cannot work with the others or with OAI: the
        one check of a mission file's [gnb] (validate_mission) and of the adapter's settings
        (mission.gnb.config.GnbConfig)."""
        out: list[tuple[str, Any, str]] = []
        if self.mode == "stock" and not self.log_path:
            out.append(("mode", self.mode, "stock mode reads the TA from the gNB log: set gnb.log_path"))
        for key in ("rtt_module", "rtt_command"):
            if not re.fullmatch(r"[A-Za-z0-9_]+", getattr(self, key)):
                out.append((key, getattr(self, key), "a telnet module/command name is one word of [A-Za-z0-9_]"))
        return out

    def measure_timeout_s(self) -> float:
        """The controller's bound on one measurement [s]: the adapter's own request timeout and one
        reconnect, plus (active stock mode) the wait for the Msg2, so that the adapter, not the
        controller, is the one to say what went wrong.

            T = 2 · (connect_timeout_s + request_timeout_s) + 0.5 [+ msg2_timeout_s]
        """
        t = 2.0 * (self.connect_timeout_s + self.request_timeout_s) + 0.5
        if self.mode == "stock" and self.stock_mode == "active":
            t += self.msg2_timeout_s
        return t


@dataclass(frozen=True)
class SafetyConfig:
    """When to give up. link_timeout_s: no vehicle data this long is a lost link [s];
    link_lost_wait_s: wait this long for it before returning home [s]; gnb_lost_wait_s: fly on
    without measurements this long before returning home [s]; battery_takeoff_min_pct: do not take
    off below this charge [%]; battery_rtl_pct: return home below this charge [%]; max_refusals:
    consecutive refused waypoints before returning home; breach_confirm_fixes: consecutive fixes
    outside a position limit that confirm a breach; alt_margin_m: tolerance of the altitude-band
    check while surveying [m]. A fleet (`[[vehicles]]`): separation_m: the least horizontal
    distance between two vehicles at every moment of their legs [m]; separation_vertical_m: two
    vehicles this far apart in altitude are separated whatever their horizontal distance (altitude
    layers) [m]; 0: no layers, every pair keeps separation_m."""

    link_timeout_s: float = positive(3.0, 60.0)
    link_lost_wait_s: float = positive(10.0, 600.0)
    gnb_lost_wait_s: float = positive(20.0, MAX_MISSION_S)
    battery_takeoff_min_pct: float = bounded(50.0, 0.0, 99.0)
    battery_rtl_pct: float = bounded(25.0, 0.0, 99.0)
    max_refusals: int = bounded(3, 1, 1000)
    breach_confirm_fixes: int = bounded(3, 1, 100)
    alt_margin_m: float = bounded(5.0, 0.0, 50.0)
    separation_m: float = bounded(15.0, 1.0, 500.0)
    separation_vertical_m: float = bounded(10.0, 0.0, 200.0)


#: a vehicle id of `[[vehicles]]`: letters, digits, '_' and '-', 1 to 32 of them
VEHICLE_ID = re.compile(r"[A-Za-z0-9_-]{1,32}")
#: the thinnest altitude band a vehicle of a fleet may be given [m]
MIN_VEHICLE_BAND_M = 5.0


@dataclass(frozen=True)
class VehicleEntryConfig:
    """One vehicle of a fleet (a `[[vehicles]]` entry; issue 41: each UAV carries its own gNB).
    id: its name, unique in the file (letters, digits, `_` and `-`, 1..32 of them); connect: the
    MAVLink address `uavloc fly` connects it with (e.g. "udpin://0.0.0.0:14541"; absent: the command
    line's --connect, for a one-vehicle fleet only; an empty string is an error, not "absent");
    gnb: its gNB's address as `--gnb` takes it (absent: the command line's --gnb, for a one-vehicle
    fleet only); gnb_mode: its gNB's `[gnb]
    mode` (empty: the mission's); alt_min_m, alt_max_m: its altitude band above home [m], inside
    the mission's `[flight]` band and at least MIN_VEHICLE_BAND_M thick (a side left out is the
    mission's); it cruises at the mission's `altitude_m` clipped into its band
    (:meth:`MissionConfig.vehicle_cruise_alt_m`). A simulation gives each vehicle its addresses
    itself, and a scenario's entries hold neither (sitl_scenarios.scenario);
    :func:`mission.addresses.fleet_address_problem` says what a flight lacks."""

    id: str
    connect: str | None = None
    gnb: str | None = None
    gnb_mode: str = ""
    alt_min_m: float | None = bounded(None, 0.0, MAX_HEIGHT_M)
    alt_max_m: float | None = positive(None, MAX_HEIGHT_M)


@dataclass(frozen=True)
class MissionConfig:
    """A whole mission file. vehicles: the fleet (`[[vehicles]]`); empty: one vehicle, addressed
    by the command line's --connect and --gnb."""

    name: str
    users: tuple[MissionUserConfig, ...]
    description: str = ""
    geofence: GeofenceConfig = field(default_factory=GeofenceConfig)
    flight: FlightConfig = field(default_factory=FlightConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    gnb: GnbSettings = field(default_factory=GnbSettings)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    vehicles: tuple[VehicleEntryConfig, ...] = ()

    def noise_model(self) -> NoiseModel:
        return self.noise.noise_model()

    @property
    def fleet_size(self) -> int:
        """How many vehicles fly the mission: one without `[[vehicles]]`."""
        return max(1, len(self.vehicles))

    def vehicle_band_m(self, i: int) -> tuple[float, float]:
        """(alt_min_m, alt_max_m) above home of vehicle i (0..fleet_size-1) [m]: its own, a side it
        leaves out the mission's `[flight]` one (all of it without `[[vehicles]]`)."""
        if not 0 <= i < self.fleet_size:
            raise IndexError(f"vehicle {i} of a fleet of {self.fleet_size}")
        f = self.flight
        if not self.vehicles:
            return f.alt_min_m, f.alt_max_m
        v = self.vehicles[i]
        return (f.alt_min_m if v.alt_min_m is None else v.alt_min_m,
                f.alt_max_m if v.alt_max_m is None else v.alt_max_m)

    def vehicle_cruise_alt_m(self, i: int) -> float:
        """Vehicle i's cruise altitude above home [m]: the mission's `altitude_m` clipped into its band."""
        lo, hi = self.vehicle_band_m(i)
        return min(max(self.flight.altitude_m, lo), hi)

    def vehicle_constraints(self, c, vehicle: int):
        """Vehicle `vehicle`'s planning constraints from the mission's `c` (planner.types.
        PlanningConstraints, perhaps with more than this file says: a scenario's buildings): in its
        own altitude band and at its cruise altitude when the mission names its vehicles
        (`[[vehicles]]`); `c` itself otherwise."""
        if self.fleet_size == 1 or vehicle >= len(self.vehicles):
            return c
        lo, hi = self.vehicle_band_m(vehicle)
        lo = max(c.alt_min_m, lo)
        return dataclasses.replace(c, alt_min_m=lo, alt_max_m=hi, cruise_alt_m=float(np.clip(c.cruise_alt_m, lo, hi)))

    def header_fields(self, home: Origin) -> dict:
        """The mission log header's optional shape fields (docs/design.md §10): `geofence` and
        `no_fly_zones` as open [[lat_deg, lon_deg], ...] rings, `altitude_band_m` {min_m, max_m}
        above home, and for a fleet (`[[vehicles]]`) `vehicles` [{id, alt_min_m, alt_max_m}] (each
        one's band above home, :meth:`vehicle_band_m`). Fields without a value are left out."""

        def lat_lon(ring_enu_m: np.ndarray) -> list[list[float]]:
            lat, lon, _ = home.enu_to_lla(np.column_stack([ring_enu_m, np.zeros(len(ring_enu_m))]))
            return [[float(a), float(o)] for a, o in zip(np.atleast_1d(lat), np.atleast_1d(lon), strict=True)]

        fence, zones = self.geofence.polygons_enu_m(home)
        out: dict = {}
        if fence is not None:
            out["geofence"] = lat_lon(fence)
        if zones:
            out["no_fly_zones"] = [lat_lon(z) for z in zones]
        out["altitude_band_m"] = {"min_m": self.flight.alt_min_m, "max_m": self.flight.alt_max_m}
        if self.vehicles:
            bands = [self.vehicle_band_m(i) for i in range(len(self.vehicles))]
            out["vehicles"] = [{"id": v.id, "alt_min_m": lo, "alt_max_m": hi}
                               for v, (lo, hi) in zip(self.vehicles, bands, strict=True)]
        return out

    def planning_constraints(self, home: Origin, *, vehicle: int | None = None,
                             **overrides: Any) -> PlanningConstraints:
        """The planner's constraints in the home ENU frame (home at (0, 0, 0); altitudes above
        home become ENU up). vehicle: the band and cruise altitude are this vehicle's
        (:meth:`vehicle_band_m`, :meth:`vehicle_cruise_alt_m`); None: the mission's.
        `overrides` replace any field (e.g. margin_m=3.0)."""
        from planner.types import PlanningConstraints

        fence, zones = self.geofence.polygons_enu_m(home)
        f = self.flight
        alt_min_m, alt_max_m, cruise_alt_m = f.alt_min_m, f.alt_max_m, f.altitude_m
        if vehicle is not None:
            alt_min_m, alt_max_m = self.vehicle_band_m(vehicle)
            cruise_alt_m = self.vehicle_cruise_alt_m(vehicle)
        kwargs = dict(
            home_enu_m=np.zeros(3),
            fence_enu_m=np.zeros((0, 2)) if fence is None else fence,
            no_fly_enu_m=zones,
            alt_min_m=alt_min_m,
            alt_max_m=alt_max_m,
            cruise_alt_m=cruise_alt_m,
            leg_max_m=f.leg_max_m,
            max_distance_m=self.geofence.max_distance_m,
            budget_m=f.budget_m,
            delta_m=f.delta_m,
            target_radius_m=f.target_radius_m,
            floor_m=gps_floor_m(self),
            min_leg_m=min(10.0, f.leg_max_m),
            coverage_m=self.gnb.coverage_m,
        )
        kwargs.update(overrides)
        return PlanningConstraints(**kwargs)

    def user_by_rnti(self, rnti: int) -> MissionUserConfig | None:
        return next((u for u in self.users if u.rnti == rnti), None)


# ---------------------------------------------------------------------------------------------
# strict conversion of parsed TOML into the dataclasses above (mission.schema) and the checks
# across fields


def _explain_unknown(cls: type, name: str) -> str | None:
    """Why a key a mission file never holds is wrong (true positions, world sections)."""
    if name in TRUE_POSITION_KEYS and cls is not VehicleEntryConfig:  # a vehicle is not a user
        return ("a mission file never holds true positions (they are what the flight measures); true user "
                "positions belong to a simulation world in sitl_scenarios")
    if cls is MissionConfig and name in WORLD_SECTIONS:
        fields = sorted(f.name for f in dataclasses.fields(MissionConfig))
        return f"describes the simulated world, not the mission; a mission file holds only {', '.join(fields)}"
    return None


def build_dataclass(cls: type, data: dict, where: str, prefix: str = "") -> Any:
    """An instance of the frozen dataclass `cls` from a parsed TOML table of a mission file,
    strictly (:func:`mission.schema.build`). where: the file (for messages); prefix: the key path."""
    return schema.build(cls, data, where, prefix, error=MissionConfigError, explain=_explain_unknown)


def validate_mission(mc: MissionConfig, where: str) -> None:
    """Raise :class:`MissionConfigError` unless the values of `mc` are consistent and in range."""
    def bad(key: str, value: Any, problem: str) -> MissionConfigError:
        return schema.fail(where, key, value, problem, MissionConfigError)

    schema.check_bounds(mc, where, error=MissionConfigError)
    if not mc.users:
        raise bad("users", [], "a mission needs at least one user")
    ids, rntis = set(), set()
    for i, u in enumerate(mc.users):
        if u.id in ids:
            raise bad(f"users[{i}].id", u.id, "duplicate user id")
        if u.rnti in rntis:
            raise bad(f"users[{i}].rnti", u.rnti, "duplicate RNTI")
        ids.add(u.id)
        rntis.add(u.rnti)
    g = mc.geofence
    if g.polygon_enu_m and g.polygon_lat_lon_deg:
        raise bad("geofence.polygon_lat_lon_deg", g.polygon_lat_lon_deg,
                  "give the fence once: polygon_enu_m or polygon_lat_lon_deg")
    polys = [("geofence.polygon_enu_m", g.polygon_enu_m), ("geofence.polygon_lat_lon_deg", g.polygon_lat_lon_deg)]
    polys += [(f"geofence.no_fly_enu_m[{i}]", p) for i, p in enumerate(g.no_fly_enu_m)]
    polys += [(f"geofence.no_fly_lat_lon_deg[{i}]", p) for i, p in enumerate(g.no_fly_lat_lon_deg)]
    for key, poly in polys:
        if poly and len(poly) < 3:
            raise bad(key, [list(p) for p in poly], "a polygon needs >= 3 vertices")
        if "lat_lon" in key and any(not (-90 <= la <= 90 and -180 <= lo <= 180) for la, lo in poly):
            raise bad(key, [list(p) for p in poly], "latitude must be in [-90, 90], longitude in [-180, 180] degrees")
    if not (g.polygon_lat_lon_deg or g.no_fly_lat_lon_deg):
        # ENU polygons are offsets from home: home must be a place the vehicle may be (geodetic
        # polygons are checked when home is known, before take-off, MissionController)
        from mission.safety import home_violations
        from uavloc.errors import SafetyError

        try:
            problems = home_violations(mc.geofence.polygons_enu_m(Origin(0.0, 0.0, 0.0)))
        except SafetyError as exc:
            raise bad("geofence", "", str(exc)) from None
        if problems:
            raise bad("geofence", "home (0, 0)", f"{'; '.join(problems)} (the vehicle takes off and lands at home)")
    f = mc.flight
    if not 0 <= f.alt_min_m <= f.altitude_m <= f.alt_max_m:
        raise bad("flight.altitude_m", f.altitude_m,
                  f"need 0 <= alt_min_m ({f.alt_min_m:g}) <= altitude_m <= alt_max_m ({f.alt_max_m:g})")
    for key, value, why in mc.gnb.problems():
        raise bad(f"gnb.{key}", value, why)
    _validate_vehicles(mc, bad)
    if mc.noise.gps_tau_s is not None:  # unknown τ (an external autopilot's): judged when known
        floor = gps_floor_problem(mc)
        if floor is not None:
            raise bad("flight.target_radius_m", f.target_radius_m, floor)
    s = mc.safety
    if s.battery_takeoff_min_pct < s.battery_rtl_pct:
        raise bad("safety.battery_takeoff_min_pct", s.battery_takeoff_min_pct,
                  f"must be >= battery_rtl_pct ({s.battery_rtl_pct:g})")


def _validate_vehicles(mc: MissionConfig, bad: Callable[[str, Any, str], UavlocError]) -> None:
    """The checks of `[[vehicles]]` (validate_mission): ids, gNB modes, altitude bands. The
    addresses are not checked here (a simulation gives them itself):
    :func:`mission.addresses.fleet_address_problem`."""
    f = mc.flight
    modes = typing.get_args(typing.get_type_hints(GnbSettings)["mode"])
    ids: dict[str, int] = {}
    for i, v in enumerate(mc.vehicles):
        key = f"vehicles[{i}]"
        if not VEHICLE_ID.fullmatch(v.id):
            raise bad(f"{key}.id", v.id, "a vehicle id is 1 to 32 letters, digits, '_' or '-'")
        if v.id in ids:
            raise bad(f"{key}.id", v.id, f"duplicate vehicle id (vehicles[{ids[v.id]}] has it)")
        ids[v.id] = i
        for name in ("connect", "gnb"):
            value = getattr(v, name)
            if value is not None and not value.strip():
                raise bad(f"{key}.{name}", value, f"empty: leave the key out for the command line's --{name} (one "
                          "vehicle only), or give the address")
        if v.gnb_mode:
            if v.gnb_mode not in modes:
                raise bad(f"{key}.gnb_mode", v.gnb_mode,
                          f"must be one of {', '.join(map(repr, modes))}, or \"\" for the mission's gnb.mode")
            for name, _, why in dataclasses.replace(mc.gnb, mode=v.gnb_mode).problems():
                if name == "mode":
                    raise bad(f"{key}.gnb_mode", v.gnb_mode, why)
        lo, hi = mc.vehicle_band_m(i)
        if v.alt_min_m is not None and lo < f.alt_min_m:
            raise bad(f"{key}.alt_min_m", v.alt_min_m,
                      f"below the mission's flight.alt_min_m ({f.alt_min_m:g}): a vehicle's band lies inside the "
                      "mission's")
        if v.alt_max_m is not None and hi > f.alt_max_m:
            raise bad(f"{key}.alt_max_m", v.alt_max_m,
                      f"above the mission's flight.alt_max_m ({f.alt_max_m:g}): a vehicle's band lies inside the "
                      "mission's")
        if hi - lo < MIN_VEHICLE_BAND_M:
            side = ("alt_max_m" if v.alt_max_m is not None else "alt_min_m" if v.alt_min_m is not None else None)
            why = "empty: need alt_min_m < alt_max_m" if hi <= lo else f"{hi - lo:g} m thick"
            raise bad(f"{key}.{side}" if side else key, getattr(v, side) if side else [lo, hi],
                      f"the vehicle's band [{lo:g}, {hi:g}] m (a side left out is the mission's flight.alt_min_m / "
                      f"alt_max_m) is {why}; a vehicle's band is at least {MIN_VEHICLE_BAND_M:g} m thick")


def survey_s(flight: FlightConfig) -> float:
    """The longest a survey can last [s]: its budget at the cruise speed, within the time limit."""
    return min(flight.budget_m / flight.cruise_speed_mps, flight.time_limit_s)


def gps_floor_m(mc: MissionConfig) -> float:
    """The 95 % bound [m] the GPS error leaves common to every user of this mission however it flies
    (estimator.gps.gps_floor_bound_95_m over its longest survey, τ unknown taken as DEFAULT_GPS_TAU_S)."""
    return gps_floor_bound_95_m(mc.noise.sigma_gps_m, _floor_tau_s(mc), survey_s(mc.flight))


def _floor_tau_s(mc: MissionConfig) -> float:
    return DEFAULT_GPS_TAU_S if mc.noise.gps_tau_s is None else mc.noise.gps_tau_s


def gps_floor_problem(mc: MissionConfig) -> str | None:
    """Why the target cannot be reached for the GPS (both numbers, and what would allow it), or None."""
    f, n = mc.flight, mc.noise
    floor = gps_floor_m(mc)
    if f.target_radius_m >= floor:
        return None
    t = survey_s(f)
    # r95 ∝ σ_gps: the σ that brings the floor to the target
    sigma_ok = n.sigma_gps_m * f.target_radius_m / floor
    tau_ok = gps_tau_for_floor_s(n.sigma_gps_m, t, f.target_radius_m)
    return (f"below the GPS floor of {floor:.2f} m: a GPS error of σ {n.sigma_gps_m:g} m drifting with τ "
            f"{_floor_tau_s(mc):g} s "
            f"leaves that 95 % bound common to track and users over the longest survey ({t:.0f} s: budget_m at "
            f"cruise_speed_mps, within time_limit_s), which no flight removes; a target of {f.target_radius_m:g} m "
            f"needs noise.sigma_gps_m <= {sigma_ok:.2f} m (RTK) or noise.gps_tau_s <= {tau_ok:.0f} s, or a target "
            f">= {floor:.2f} m")


#: the tables of a mission file whose keys are plain settings (not users or polygons)
SETTING_TABLES = ("flight", "noise", "gnb", "safety")


def setting_tables(flat: dict, where: str, error: type[UavlocError] = MissionConfigError) -> dict:
    """{table: {key: value}} of settings given by their key alone ({"budget_m": 1500} →
    {"flight": {"budget_m": 1500}}): every key of flight, noise, gnb and safety is unique, so its
    name says its table (campaign families take their mission settings this way)."""
    table_of = {f.name: t for t in SETTING_TABLES
                for f in dataclasses.fields(typing.get_type_hints(MissionConfig)[t])}
    out: dict = {}
    for key, value in flat.items():
        if key not in table_of:
            raise schema.fail(where, key, value, "not a setting of a mission file's "
                              f"{', '.join(f'[{t}]' for t in SETTING_TABLES)}", error)
        out.setdefault(table_of[key], {})[key] = value
    return out


def with_settings(mc: MissionConfig, flat: dict, where: str = "settings") -> MissionConfig:
    """`mc` with the settings of `flat` given by their key alone (:func:`setting_tables`:
    {"time_limit_s": 600} replaces flight.time_limit_s), checked again as a mission file is."""
    tables = setting_tables(flat, where)
    out = dataclasses.replace(mc, **{t: dataclasses.replace(getattr(mc, t), **kv) for t, kv in tables.items()})
    validate_mission(out, where)
    return out


def mission_from_dict(data: dict, where: str = "mission") -> MissionConfig:
    """Build and validate a :class:`MissionConfig` from a parsed TOML document; `where` names the
    source in every message."""
    mc = build_dataclass(MissionConfig, data, where)
    validate_mission(mc, where)
    return mc


def load_mission(path: str | Path) -> MissionConfig:
    """Read a mission file strictly (see the module docstring)."""
    return mission_from_dict(schema.read_toml(path, "mission file", MissionConfigError), str(path))


def example_mission_path(name: str = "flight") -> Path:
    """A mission file shipped with the package (`mission/examples/<name>.toml`)."""
    return EXAMPLES_DIR / f"{name}.toml"
