"""Campaign specs: strict TOML naming scenarios × planners × estimators × fleet sizes × seeds, and the runs
they expand to.

A spec (every table and key below; anything else is a :class:`CampaignError` naming the key)::

    [campaign]
    name = "planners"                 # required
    mode = "fast"                     # "fast" (kinematic vehicle and channel) or "full" (MAVLink + gNB)
    seeds = [0, 1, 2]                 # noise seeds: every scenario is flown once per seed
    planners = ["lawnmower", "casadi"]
    targets_m = [1.0, 0.6]            # accuracy targets: metres flown until the mean 95 % bound ≤ T
    fleet = [1, 2, 3]                 # fleet sizes: vehicles per run, each with its own gNB (1..8; fast
                                      # mode only above 1; default [1])
    speedup = 20.0                    # full mode: simulated seconds per wall second
    gnb_transport = "telnet"          # full mode: the gNB adapter over "telnet" or "rest" (OAI's web server)
    gnb_mode = "rtt"                  # full mode: measure with the RTT command ("rtt") or the T tracer ("trace")

    [estimators.default]              # named estimator variants: SolverParams fields (default: one, "default")
    window = 40

    [planner_options.casadi]          # keyword options of a planner's constructor (fast mode)
    horizon = 2

    [[scenarios]]                     # scenario files: a path (relative to the spec) or a bundled name
    file = "three_users_nlos"
    condition = "nlos"                # the condition the summary groups it under (default: its name)

    [[families]]                      # generated scenarios (sitl_scenarios.campaign.families)
    name = "drift"                    # also the condition
    count = 20
    gps_tau_s = [60.0, 300.0]         # a number is fixed; [lo, hi] is drawn uniformly per scenario
    [families.mission]                # MissionConfig fields over the family's defaults
    budget_m = 1500.0

The runs are the product scenarios × planners × estimators × fleet sizes × seeds; each :class:`RunSpec`
carries everything a worker needs (the scenario itself, not a path) and a key that changes whenever the
run's definition does, so a resumed campaign skips exactly the runs it already has (a one-vehicle run
keeps the key it had before fleets existed).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from estimator.types import SolverParams
from mission import schema
from mission.estimation import mission_solver_params
from sitl_scenarios.campaign.families import FamilySpec, generate_scenario, validate_family
from sitl_scenarios.scenario import Scenario, load_scenario
from uavloc.errors import CampaignError, ScenarioError, UavlocError

MODES = ("fast", "full")
#: the largest fleet a run may fly (`campaign.fleet`)
FLEET_MAX = 8


@dataclass(frozen=True)
class CampaignSection:
    """The `[campaign]` table (see the module docstring)."""

    name: str
    mode: str = "fast"
    seeds: list[int] = field(default_factory=lambda: [0])
    planners: list[str] = field(default_factory=lambda: ["casadi"])
    targets_m: list[float] = field(default_factory=lambda: [1.0])
    fleet: list[int] = field(default_factory=lambda: [1])
    speedup: float = 20.0
    gnb_transport: str = "telnet"
    gnb_mode: str = "rtt"
    description: str = ""


@dataclass(frozen=True)
class ScenarioFileSpec:
    """One `[[scenarios]]` entry: a scenario file and the condition it belongs to."""

    file: str
    condition: str = ""


@dataclass(frozen=True)
class SpecDocument:
    """A whole spec file (see the module docstring): the `[campaign]` table, named estimator
    variants and planner options (tables checked by :func:`spec_from_dict`), scenario files and
    families."""

    campaign: CampaignSection
    estimators: dict[str, dict[str, Any]] = field(default_factory=lambda: {"default": {}})
    planner_options: dict[str, dict[str, Any]] = field(default_factory=dict)
    scenarios: list[ScenarioFileSpec] = field(default_factory=list)
    families: list[FamilySpec] = field(default_factory=list)


@dataclass(frozen=True)
class RunSpec:
    """One run: a scenario flown by one planner with one estimator variant, a fleet size and one noise seed.

    key: unique and stable (changes with any part of the definition); condition: the group the
    summary puts it in (family name or scenario condition); scenario_params: flat description of the
    scenario for the results table; targets_m: accuracy targets [m], descending; n_vehicles: the
    fleet size (vehicles flown together, each with its own gNB; above 1 fast mode only).
    """

    key: str
    condition: str
    scenario: Scenario
    scenario_params: dict
    planner: str
    planner_opts: dict
    estimator: str
    params: SolverParams
    seed: int
    mode: str
    targets_m: tuple[float, ...]
    speedup: float = 20.0
    gnb_transport: str = "telnet"
    gnb_mode: str = "rtt"
    n_vehicles: int = 1


@dataclass(frozen=True)
class Campaign:
    """A loaded spec: its settings and the runs it expands to, in a stable order."""

    name: str
    path: Path | None
    section: CampaignSection
    runs: list[RunSpec]

    @property
    def targets_m(self) -> tuple[float, ...]:
        return tuple(sorted(self.section.targets_m, reverse=True))


# ---------------------------------------------------------------------------------------------


def _err(where: str, msg: str) -> CampaignError:
    return CampaignError(f"{where}: {msg}")


def _solver_params(opts: Any, base: dict, key: str, where: str) -> SolverParams:
    """SolverParams from a spec table over `base`: every key a field, every value of the field's type."""
    from estimator.problem import check_params

    if not isinstance(opts, dict):
        raise _err(where, f"{key}: expected a table, got {opts!r}")
    params = dataclasses.replace(schema.build(SolverParams, opts, where, key, error=CampaignError), **{
        k: v for k, v in base.items() if k not in opts})
    try:
        check_params(params)
    except UavlocError as exc:
        raise _err(where, f"{key}: {exc}") from exc
    return params


def _check_section(c: CampaignSection, where: str) -> None:
    from planner import planner_names

    if not c.name.strip():
        raise _err(where, "campaign.name must not be empty")
    if not schema.SAFE_NAME.fullmatch(c.name):
        # the name makes the default output folder and the results' file names
        raise _err(where, f"campaign.name {c.name!r}: one word of letters, digits, '_', '-' and '.' "
                   "(not '.' or '..'), so it names no folder outside --out")
    if c.mode not in MODES:
        raise _err(where, f"campaign.mode must be one of {', '.join(MODES)}, got {c.mode!r}")
    if not c.seeds:
        raise _err(where, "campaign.seeds must name at least one seed")
    if len(set(c.seeds)) != len(c.seeds) or any(s < 0 for s in c.seeds):
        raise _err(where, f"campaign.seeds must be distinct non-negative integers, got {c.seeds}")
    known = planner_names()
    if not c.planners:
        raise _err(where, "campaign.planners must name at least one planner")
    for p in c.planners:
        if p not in known:
            raise _err(where, f"campaign.planners: unknown planner {p!r}; choose from {', '.join(known)}")
    if c.mode == "full" and "oracle" in c.planners:
        raise _err(where, "campaign.planners: 'oracle' needs the true users, which full mode's controller never has")
    if len(set(c.planners)) != len(c.planners):
        raise _err(where, f"campaign.planners has duplicates: {c.planners}")
    if not c.targets_m or any(not (math.isfinite(t) and t > 0) for t in c.targets_m):
        raise _err(where, f"campaign.targets_m must be positive numbers, got {c.targets_m}")
    if len(set(c.targets_m)) != len(c.targets_m):
        raise _err(where, f"campaign.targets_m has duplicates: {c.targets_m}")
    if not c.fleet or len(set(c.fleet)) != len(c.fleet) or any(not 1 <= n <= FLEET_MAX for n in c.fleet):
        raise _err(where, f"campaign.fleet must be distinct fleet sizes from 1 to {FLEET_MAX} (vehicles per run), "
                   f"got {c.fleet}")
    if c.mode == "full" and any(n != 1 for n in c.fleet):
        raise _err(where, f"campaign.fleet {c.fleet}: full mode flies one vehicle; fleet sizes > 1 need "
                   'mode = "fast"')
    if not (math.isfinite(c.speedup) and 0 < c.speedup <= 1000):
        raise _err(where, f"campaign.speedup must be in (0, 1000], got {c.speedup}")
    if c.gnb_transport not in ("telnet", "rest"):
        raise _err(where, f"campaign.gnb_transport must be 'telnet' or 'rest', got {c.gnb_transport!r}")
    if c.gnb_transport != "telnet" and c.mode != "full":
        raise _err(where, "campaign.gnb_transport: only full mode talks to a gNB (fast mode has no adapter)")
    if c.gnb_mode not in ("rtt", "trace"):
        raise _err(where, f"campaign.gnb_mode must be 'rtt' or 'trace', got {c.gnb_mode!r}")
    if c.gnb_mode != "rtt" and c.mode != "full":
        raise _err(where, "campaign.gnb_mode: only full mode talks to a gNB (fast mode has no adapter)")


def _scenario_params(sc: Scenario, kind: str) -> dict:
    """Flat description of a scenario for the results table (the columns of results.SCENARIO_COLUMNS)."""
    return {
        "users": len(sc.users),
        "buildings": len(sc.buildings),
        "no_fly": len(sc.geofence.no_fly_enu_m),
        "fence_vertices": len(sc.geofence.polygon_enu_m),
        "gps_sigma_m": sc.vehicle.gps_sigma_m,
        "gps_tau_s": sc.vehicle.gps_tau_s,
        "sawtooth_max_m": max((u.sawtooth_amplitude_m for u in sc.users), default=0.0),
        "nlos_excess_mean_m": sc.radio.nlos_excess_mean_m,
        "range_s0_m": sc.radio.s0_m,
        "range_a_m": sc.radio.a_m,
        "source": kind,
    }


def _run_key(condition: str, sc: Scenario, planner: str, opts: dict, estimator: str, params: SolverParams,
             seed: int, mode: str, targets: tuple[float, ...], speedup: float, gnb_transport: str = "telnet",
             gnb_mode: str = "rtt", n_vehicles: int = 1) -> str:
    definition = {
        "scenario": dataclasses.asdict(sc), "planner": planner, "planner_opts": opts,
        "params": dataclasses.asdict(params), "seed": seed, "mode": mode, "targets_m": list(targets),
        "speedup": speedup if mode == "full" else None,
    }
    if gnb_transport != "telnet":  # absent over telnet: the keys of existing campaigns stay as they were
        definition["gnb_transport"] = gnb_transport
    if gnb_mode != "rtt":
        definition["gnb_mode"] = gnb_mode
    fleet = ""
    if n_vehicles != 1:  # likewise: a one-vehicle run keeps the key it had before fleets
        definition["n_vehicles"] = n_vehicles
        fleet = f"x{n_vehicles}/"
    digest = hashlib.sha1(json.dumps(definition, sort_keys=True, default=repr).encode()).hexdigest()[:12]
    return f"{condition}/{sc.name}/{planner}/{estimator}/{fleet}s{seed}#{digest}"


def spec_from_dict(data: dict, where: str = "spec", base_dir: Path | None = None,
                   path: Path | None = None) -> Campaign:
    """Validate a parsed spec and expand it to its runs (CampaignError naming the key on anything bad)."""
    doc: SpecDocument = schema.build(SpecDocument, data, where, error=CampaignError)
    section = doc.campaign
    _check_section(section, where)
    targets = tuple(sorted(section.targets_m, reverse=True))

    # estimator variants: name → options over each scenario's mission's settings (mission_solver_params)
    est_tables = doc.estimators
    if not est_tables:
        raise _err(where, "estimators: expected at least one [estimators.NAME] table")
    for name, opts in est_tables.items():
        _solver_params(opts, {}, f"estimators.{name}", where)  # fail early, before any scenario

    planner_opts = doc.planner_options
    for name, opts in planner_opts.items():
        if name not in section.planners:
            raise _err(where, f"planner_options.{name}: {name!r} is not in campaign.planners {section.planners}")
        if not isinstance(opts, dict):
            raise _err(where, f"planner_options.{name}: expected a table, got {opts!r}")
        if section.mode == "full" and opts:
            raise _err(where, f"planner_options.{name}: full mode flies each planner with its defaults")

    # scenarios: (condition, scenario, params), the files' and the families' alike
    scenarios: list[tuple[str, Scenario, dict]] = []
    for i, fs in enumerate(doc.scenarios):
        try:
            sc = load_scenario(fs.file, base_dir)
        except ScenarioError as exc:
            raise _err(where, f"scenarios[{i}].file: {exc}") from exc
        scenarios.append((fs.condition or sc.name, sc, _scenario_params(sc, f"file:{fs.file}")))
    for i, fam in enumerate(doc.families):
        try:
            validate_family(fam, f"families[{i}]")
            scenarios += [(fam.name, sc, _scenario_params(sc, f"family:{fam.name}"))
                          for sc in (generate_scenario(fam, j, f"families[{i}]") for j in range(fam.count))]
        except ScenarioError as exc:
            raise _err(where, str(exc)) from exc
    if not scenarios:
        raise _err(where, "a campaign needs [[scenarios]] or [[families]]")
    names = [(c, sc.name) for c, sc, _ in scenarios]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise _err(where, f"scenario names repeat within a condition: {dup}")

    runs: list[RunSpec] = []
    for condition, sc, sp in scenarios:
        # the estimator settings the scenario's mission flies with (mission.estimation), under the spec's
        base = dataclasses.asdict(mission_solver_params(sc.mission))
        for planner in section.planners:
            opts = dict(planner_opts.get(planner, {}))
            for est_name, est_opts in est_tables.items():
                params = _solver_params(est_opts, base, f"estimators.{est_name}", where)
                for n_vehicles in section.fleet:
                    for seed in section.seeds:
                        key = _run_key(condition, sc, planner, opts, est_name, params, seed, section.mode, targets,
                                       section.speedup, section.gnb_transport, section.gnb_mode, n_vehicles)
                        runs.append(RunSpec(key=key, condition=condition, scenario=sc, scenario_params=sp,
                                            planner=planner, planner_opts=opts, estimator=est_name, params=params,
                                            seed=seed, mode=section.mode, targets_m=targets,
                                            speedup=section.speedup, gnb_transport=section.gnb_transport,
                                            gnb_mode=section.gnb_mode, n_vehicles=n_vehicles))
    _check_planner_options(section, planner_opts, scenarios[0][1], where)
    return Campaign(section.name, path, section, runs)


def _check_planner_options(section: CampaignSection, planner_opts: dict, sc: Scenario, where: str) -> None:
    """Build each planner once with its options, so a bad option is an error before any run starts
    (`precompile = true` compiles its kernels here too: into the kernel cache, as the runs do, not
    the user's working folder)."""
    from mission.kernel_cache import use_kernel_cache
    from planner import make_planner

    use_kernel_cache()
    c = sc.planning_constraints()
    truth = [[u.east_m, u.north_m, u.up_m] for u in sc.users]
    for name in section.planners:
        opts = dict(planner_opts.get(name, {}))
        if name == "oracle":
            opts.setdefault("true_users_enu_m", truth)
        try:
            make_planner(name, c, sc.noise_model(), rng_seed=0, **opts)
        except UavlocError as exc:
            raise _err(where, f"planner_options.{name}: {exc}") from exc
        except (TypeError, ValueError) as exc:
            raise _err(where, f"planner_options.{name}: {exc}") from exc


def load_spec(path: str | Path) -> Campaign:
    """Read a campaign spec file strictly and expand it to its runs."""
    p = Path(path)
    data = schema.read_toml(p, "campaign spec", CampaignError)
    return spec_from_dict(data, str(p), base_dir=p.resolve().parent, path=p)
