"""Generated scenario families: seeded random worlds drawn from parameter ranges.

Scenario j of a family is drawn from `numpy.random.default_rng(seed + j)` (its structure: fence,
no-fly zones, buildings, users) and `default_rng([seed + j, 1])` (its conditions: GPS drift, UE
clocks, NLoS excess), so adding a condition never changes the geometry of a family, and the
geometry draws are those of the planner benchmark's scenarios (seed 1000, the defaults below).

World (ENU metres from home, home at the origin):
- fence: a rectangle [−W, +E] × [−S, +N], each half-width drawn from `fence_half_m`; with
  probability `notch_prob` a notch (40–80 m wide, 40–70 % deep) cut into the north or south side, a
  non-convex fence;
- `no_fly`: that many squares of 20–40 m (dropped when within 25 m + side of home);
- `buildings`: that many squares of 10–20 m, heights from `building_height_m` (the planners fly
  above them; one that blocks the line of sight to a user adds an NLoS excess with mean
  `nlos_excess_mean_m`, 0: none);
- `users`: that many users inside the fence, at least 5 m from its edges;
- range noise σ(d) = s0 + a·exp(b·d): s0 = `range_s0_m`; a = 0.3 m, b = 0.01 /m in a share
  `distance_noise_share` of the scenarios, a = 0 elsewhere;
- vehicle GPS error: σ `gps_sigma_m` per axis, Gauss–Markov with correlation time `gps_tau_s`
  (0: independent per fix); the mission's `sigma_gps_m` is that σ (when > 0) unless `[families.mission]` sets it;
- the gNB's reach `coverage_m`: a UE farther (slant range) hears no cell;
- UE clocks: a sawtooth of amplitude `sawtooth_amplitude_m` and period `sawtooth_period_s`,
  drawn per user.

A parameter given as a number is fixed; as [lo, hi] it is drawn uniformly per scenario (per user
for the clock parameters; integers for counts, both ends included).
"""

from __future__ import annotations

import math
import typing
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mission import geometry, schema
from mission.config import MissionConfig, setting_tables
from sitl_scenarios.scenario import Scenario, scenario_from_dict, user_tables
from uavloc.errors import ScenarioError

#: the mission every family member flies unless `[families.mission]` says otherwise: settings of a
#: mission file's [flight], [noise], [gnb] and [safety] by their key alone (mission.config.setting_tables)
DEFAULT_MISSION = {"delta_m": 2.0, "altitude_m": 30.0, "alt_min_m": 15.0, "alt_max_m": 80.0, "leg_max_m": 60.0,
                   "budget_m": 3000.0, "target_radius_m": 0.6, "sigma_gps_m": 1.0}


@dataclass(frozen=True)
class FamilySpec:
    """One `[[families]]` table (see the module docstring for what each parameter draws)."""

    name: str
    count: int = 10
    seed: int = 1000
    users: int | list[int] = field(default_factory=lambda: [1, 5])
    fence_half_m: float | list[float] = field(default_factory=lambda: [100.0, 160.0])
    notch_prob: float = 0.6
    no_fly: int | list[int] = field(default_factory=lambda: [0, 2])
    buildings: int | list[int] = field(default_factory=lambda: [0, 3])
    building_height_m: float | list[float] = field(default_factory=lambda: [8.0, 25.0])
    max_distance_m: float = 250.0
    range_s0_m: float = 3.0
    distance_noise_share: float = 0.0
    nlos_excess_mean_m: float | list[float] = 0.0
    gps_sigma_m: float | list[float] = 1.0
    gps_tau_s: float | list[float] = 0.0
    sawtooth_amplitude_m: float | list[float] = 0.0
    sawtooth_period_s: float | list[float] = 20.0
    speed_mps: float = 10.0
    coverage_m: float = 1500.0
    mission: dict[str, Any] = field(default_factory=dict)


#: parameter → (smallest allowed, largest allowed)
_BOUNDS = {
    "users": (1, 50), "fence_half_m": (50.0, 5000.0), "no_fly": (0, 20), "buildings": (0, 50),
    "building_height_m": (1.0, 500.0), "nlos_excess_mean_m": (0.0, 500.0), "gps_sigma_m": (0.0, 50.0),
    "gps_tau_s": (0.0, 1e5), "sawtooth_amplitude_m": (0.0, 200.0), "sawtooth_period_s": (0.1, 1e5),
}


def _range(value: Any, key: str) -> tuple[Any, Any]:
    """A number → (v, v); [lo, hi] → (lo, hi), checked against the parameter's bounds."""
    lo, hi = (value, value) if not isinstance(value, list) else (tuple(value) if len(value) == 2 else (None, None))
    if lo is None:
        raise ScenarioError(f"{key}: a range is [lo, hi], got {value!r}")
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise ScenarioError(f"{key}: need finite lo <= hi, got {value!r}")
    a, b = _BOUNDS[key.rsplit(".", 1)[-1]]
    if lo < a or hi > b:
        raise ScenarioError(f"{key}: must lie in [{a}, {b}], got {value!r}")
    return lo, hi


def validate_family(fam: FamilySpec, where: str) -> None:
    """Raise ScenarioError naming the key of the first bad parameter."""
    if not schema.SAFE_NAME.fullmatch(fam.name):
        raise ScenarioError(f"{where}.name {fam.name!r}: one word of letters, digits, '_', '-' and '.' "
                            "(it names the family's scenarios and its condition)")
    if not 1 <= fam.count <= 100_000:
        raise ScenarioError(f"{where}.count must be in 1..100000, got {fam.count}")
    if fam.seed < 0:
        raise ScenarioError(f"{where}.seed must be >= 0, got {fam.seed}")
    for key in _BOUNDS:
        _range(getattr(fam, key), f"{where}.{key}")
    for key in ("notch_prob", "distance_noise_share"):
        v = getattr(fam, key)
        if not 0.0 <= v <= 1.0:
            raise ScenarioError(f"{where}.{key} must be in [0, 1], got {v!r}")
    for key in ("max_distance_m", "range_s0_m", "speed_mps", "coverage_m"):
        if not getattr(fam, key) > 0:
            raise ScenarioError(f"{where}.{key} must be positive, got {getattr(fam, key)!r}")
    # each setting strictly, named by the key the spec gives it (families[i].mission.budget_m)
    tables = setting_tables({**DEFAULT_MISSION, **fam.mission}, f"{where}.mission", ScenarioError)
    for table, values in tables.items():
        schema.build(typing.get_type_hints(MissionConfig)[table], values, where, f"{where}.mission",
                     error=ScenarioError)


def generate_scenario(fam: FamilySpec, j: int, where: str = "") -> Scenario:
    """Scenario j of the family (seeded by fam.seed + j; named `<family><j>`); `where` prefixes errors."""
    rng = np.random.default_rng(fam.seed + j)

    def uniform(key: str) -> float:
        lo, hi = _range(getattr(fam, key), key)
        return float(rng.uniform(lo, hi))

    def count(key: str) -> int:
        lo, hi = _range(getattr(fam, key), key)
        return int(rng.integers(int(lo), int(hi) + 1))

    x0, x1 = -uniform("fence_half_m"), uniform("fence_half_m")
    y0, y1 = -uniform("fence_half_m"), uniform("fence_half_m")
    fence = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    kind = "rectangle"
    if rng.random() < fam.notch_prob and x1 - x0 > 140:  # a notch cut into the north or south side
        kind = "notched"
        w = rng.uniform(40, 80)
        a = rng.uniform(x0 + 30, x1 - 30 - w)
        if rng.random() < 0.5:
            depth = rng.uniform(0.4, 0.7) * y1
            fence = [[x0, y0], [x1, y0], [x1, y1], [a + w, y1], [a + w, y1 - depth], [a, y1 - depth], [a, y1],
                     [x0, y1]]
        else:
            depth = rng.uniform(0.4, 0.7) * -y0
            fence = [[x0, y0], [a, y0], [a, y0 + depth], [a + w, y0 + depth], [a + w, y0], [x1, y0], [x1, y1],
                     [x0, y1]]
    poly = np.array(fence)
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) / 2

    def random_inside(clear: float) -> np.ndarray:
        for _ in range(100_000):
            p = rng.uniform([x0 + clear, y0 + clear], [x1 - clear, y1 - clear])
            if geometry.contains_point(poly, p) and all(
                geometry.contains_point(poly, p + d) for d in clear * np.array([[1, 0], [-1, 0], [0, 1], [0, -1]])
            ):
                return p
        raise ScenarioError(f"family {fam.name!r}: no room for a {clear} m clearance in scenario {j}")

    no_fly = []
    for _ in range(count("no_fly")):
        side = rng.uniform(20, 40)
        c = random_inside(side)
        if np.linalg.norm(c) < side + 25:
            continue
        no_fly.append((c + side * square).tolist())
    buildings = []
    for _ in range(count("buildings")):
        c, side = random_inside(15), rng.uniform(10, 20)
        buildings.append({"footprint_enu_m": (c + side * square).tolist(), "height_m": uniform("building_height_m")})
    n_users = count("users")
    positions = [random_inside(5) for _ in range(n_users)]
    distance_noise = bool(rng.random() < fam.distance_noise_share)

    # conditions from their own stream, so that they never move the geometry
    crng = np.random.default_rng([fam.seed + j, 1])

    def cond(key: str) -> float:
        lo, hi = _range(getattr(fam, key), key)
        return float(crng.uniform(lo, hi)) if hi > lo else float(lo)

    gps_sigma_m, gps_tau_s, nlos_mean_m = cond("gps_sigma_m"), cond("gps_tau_s"), cond("nlos_excess_mean_m")
    users = []
    for k, p in enumerate(positions):
        users.append({"id": f"ue{k}", "rnti": 0x4601 + k, "east_m": float(p[0]), "north_m": float(p[1]),
                      "sawtooth_amplitude_m": cond("sawtooth_amplitude_m"),
                      "sawtooth_period_s": cond("sawtooth_period_s")})
    where_j = f"{where} scenario {fam.name}{j:02d}" if where else f"{fam.name}{j:02d}"
    name = f"{fam.name}{j:02d}"
    data = {
        "name": name,
        "description": f"family {fam.name!r} #{j}: {kind} fence",
        "seed": fam.seed + j,
        **user_tables(users),
        "buildings": buildings,
        "geofence": {"polygon_enu_m": poly.tolist(), "max_distance_m": fam.max_distance_m, "no_fly_enu_m": no_fly},
        "radio": {"s0_m": fam.range_s0_m, "a_m": 0.3 if distance_noise else 0.0,
                  "b_per_m": 0.01 if distance_noise else 0.0, "nlos_excess_mean_m": nlos_mean_m,
                  "coverage_m": fam.coverage_m},
        "vehicle": {"speed_mps": fam.speed_mps, "gps_sigma_m": gps_sigma_m, "gps_tau_s": gps_tau_s},
        # the mission assumes the GPS σ it flies with (a perfect GPS: the default) unless
        # [families.mission] says otherwise
        **setting_tables({**DEFAULT_MISSION, **({"sigma_gps_m": gps_sigma_m} if gps_sigma_m > 0 else {}),
                          **fam.mission}, where_j, ScenarioError),
    }
    return scenario_from_dict(data, where_j)
