"""`uavloc sim SCENARIO [--seed N] [--speedup X] [--planner NAME] [--out DIR] [--json] [--connect URL[,URL...]]
[--gnb-transport telnet|rest] [--autopilot px4|ardupilot] [--oai [BUILD]]`:
a whole mission against the built-in vehicle and the simulated gNB (or a running PX4 or ArduPilot SITL;
a fleet scenario's: one URL per vehicle, comma-separated)."""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from mission.commands.argtypes import in_range
from mission.view.live import add_view_arguments

if TYPE_CHECKING:
    from sitl_scenarios.sim_runner import SimulatedMission

log = logging.getLogger(__name__)


def seed_argument(text: str) -> int:
    """`--seed N`: an integer in 0..MAX_SEED (a scenario's `seed` has the same range)."""
    from sitl_scenarios.scenario import MAX_SEED

    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a seed is an integer, got {text!r}") from None
    if not 0 <= seed <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"a seed is in 0..{MAX_SEED}, got {seed}")
    return seed

HELP = ("fly a simulated mission (built-in vehicle or PX4/ArduPilot SITL, simulated gNB) and print where the users "
        "are")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", metavar="SCENARIO",
                   help="scenario file, or the name of a bundled one (paper, three_users_nlos, ...)")
    p.add_argument("--seed", type=seed_argument, metavar="N",
                   help="seed of the simulators and the planner (default: the scenario's)")
    p.add_argument("--speedup", type=in_range(float, 0.0, 1e4, closed=False, what="a number"), default=10.0,
                   help="simulated seconds per wall second of the built-in vehicle (default 10); a built-in "
                        "fleet's vehicles × speed-up is at most 20 (benchmarks/fleet_size.py)")
    p.add_argument("--planner", metavar="NAME",
                   help="casadi, greedy, lawnmower, circle, random, oracle (default: the scenario's, casadi "
                        "when available)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="write the mission log and a report here (default: a new folder under $UAVLOC_RUNS, "
                        "~/uavloc-runs unless set)")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    p.add_argument("--gnb-transport", choices=("telnet", "rest"), default="telnet",
                   help="how the adapter talks to the simulated gNB: its telnet server (default) or OAI's web "
                        "server API (REST)")
    p.add_argument("--gnb-mode", choices=("rtt", "trace", "auto"),
                   help="how the adapter measures: the RTT command (a modified gNB), the T tracer (a stock gNB's "
                        "TA and SRS), or the best the gNB serves (default: the scenario's [gnb] mode, rtt)")
    p.add_argument("--connect", metavar="URL[,URL...]",
                   help="fly a running PX4 or ArduPilot SITL instead (e.g. udpin://0.0.0.0:14540); the simulated "
                        "gNB follows it and scenario positions are offsets from its home. A fleet scenario: one URL "
                        "per [[vehicles]] entry, comma-separated (udpin://127.0.0.1:14541,udpin://127.0.0.1:14542); "
                        "positions are offsets from the first vehicle's home")
    p.add_argument("--autopilot", choices=("px4", "ardupilot"),
                   help="the built-in vehicle's personality (default: the scenario's [vehicle] autopilot, px4)")
    p.add_argument("--oai", nargs="?", const="", metavar="BUILD",
                   help="the world's gNB is a real OAI nr-softmodem and each user a real nr-uesoftmodem (a pair "
                        "per user) over rfsim, from this OAI build folder (bare --oai: $UAVLOC_OAI); ranges from its "
                        "T trace (with --gnb-mode rtt: its PDCCH order, on a build patched with patches/oai-2025.w36), "
                        "the world at rfsim's pace (docs/oai-in-the-loop.md)")
    add_view_arguments(p)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from mission.commands.outdir import LOG_NAME, default_out_dir, mission_log_path
    from mission.status import print_result, write_report
    from mission.view.live import live_view
    from sitl_scenarios.scenario import check_fleet_load, load_scenario, with_autopilot
    from sitl_scenarios.sim_runner import SimulatedMission

    oai = oai_argument(args.oai, args.gnb_mode)  # a bad --oai is said before anything starts
    if args.connect is None:
        from sitl_scenarios.world import start_world_server

        start_world_server()  # the world's imports run while the scenario loads and the planner compiles
    scenario = load_scenario(args.scenario)
    connect = connect_argument(args.connect, scenario)
    if connect is None:
        check_fleet_load(scenario, args.speedup)
    if args.autopilot is not None:
        if args.connect is not None:
            log.warning("--autopilot is ignored with --connect (the autopilot says what it is)")
        else:
            scenario = with_autopilot(scenario, args.autopilot)
    if args.connect is not None and args.speedup != 10.0:
        log.warning("--speedup is ignored with --connect (PX4 SITL sets its own speed)")
    if args.connect is None:
        check_gps_floor(scenario, args.scenario)
    if args.out is None:
        args.out = default_out_dir("sim", scenario.name)
    log_path = mission_log_path(args.out, None, args.out / LOG_NAME)

    from mission.runtime import EXIT_INTERRUPTED, BoundedRun

    runner = BoundedRun()
    held = _Held()

    def finish(result, interrupted: bool) -> int:
        """Print the result, write the report; the command's exit code."""
        print_result(result, args.json)
        if result.pace is not None and result.pace.fell_behind:
            # said again at the very end, where it is read: the figures are a slower flight's
            log.warning("%s", result.pace.message())
        log_failed = held.sim.controller.log_writer.failed
        if log_failed is not None:
            log.error("no report: %s", log_failed)
        elif result.measurements:
            write_report(log_path, args.out)
        return EXIT_INTERRUPTED if interrupted else (0 if result.ok else 1)

    async def main() -> int:
        async with live_view(args, title=f"uavloc sim {scenario.name}") as view:
            async with SimulatedMission(scenario, log_path=log_path, seed=args.seed, speedup=args.speedup,
                                        planner=args.planner, connect=connect,
                                        gnb_transport=args.gnb_transport, gnb_mode=args.gnb_mode, oai=oai,
                                        header_config={"command_line": getattr(args, "command_line", None)}) as sim:
                held.sim = sim
                runner.last_resort = sim.controller.last_resort
                view.follow(sim.controller.log_writer)
                result = await sim.run()
            # the vehicle and the simulators are closed: the page shows the finished mission
            view.mission_over()
            held.exit_code = finish(result, interrupted=False)
            await view.keep_serving(runner, held.exit_code)
            return held.exit_code

    try:
        code = runner.run(main())
    except (asyncio.CancelledError, KeyboardInterrupt):
        if held.exit_code is not None:
            code = held.exit_code  # the mission had ended and its result is printed
        else:
            sim = held.sim
            result = sim.controller.result if sim is not None and sim.controller is not None else None
            if result is None:
                log.error("interrupted before the mission started")
                runner.exit_if_stuck(EXIT_INTERRUPTED)
                return EXIT_INTERRUPTED
            code = finish(result, interrupted=True)
    runner.exit_if_stuck(code)
    return code


def oai_argument(value: str | None, gnb_mode: str | None = None) -> str | None:
    """`--oai [BUILD]`: the build folder (bare: $UAVLOC_OAI); ScenarioError (exit 1) when bare and
    UAVLOC_OAI is unset, or the folder is not an OAI build uavloc can run (with `--gnb-mode rtt`:
    one patched with patches/oai-2025.w36). None: no --oai."""
    import os

    from uavloc.errors import ScenarioError

    if value is None:
        return None
    build = value.strip() or os.environ.get("UAVLOC_OAI", "").strip()
    if not build:
        raise ScenarioError("--oai without a folder takes the OAI build folder from UAVLOC_OAI, which is not set "
                            "(openairinterface5g/cmake_targets/ran_build/build)")
    from sitl_scenarios.oai.conf import build_missing, rtt_missing

    why = build_missing(Path(build).expanduser())
    if why is None and gnb_mode == "rtt":
        why = rtt_missing(Path(build).expanduser())
    if why is not None:
        raise ScenarioError(why)
    return build


def check_gps_floor(scenario, where: str) -> None:
    """A target below the GPS floor of the GPS the built-in vehicle flies with (the world's
    `[vehicle] gps_tau_s` when the mission leaves τ unknown) is refused, as a mission file's is
    (mission.config.gps_floor_problem); ScenarioError (exit 1) naming the file and the key. With
    --connect τ is the autopilot's, unknown until the flight estimates it."""
    from mission.config import gps_floor_problem
    from uavloc.errors import ScenarioError

    problem = gps_floor_problem(scenario.mission_config())
    if problem is not None:
        raise ScenarioError(f"{where}: flight.target_radius_m = "
                            f"{scenario.mission.flight.target_radius_m:g}: {problem} (the built-in vehicle's GPS "
                            f"drifts with [vehicle] gps_tau_s = {scenario.vehicle.gps_tau_s:g} s)")


def connect_argument(text: str | None, scenario) -> str | list[str] | None:
    """`--connect`: one URL for a one-vehicle scenario, a fleet scenario's comma-separated list of one
    URL per `[[vehicles]]` entry; ScenarioError (exit 1), naming --connect, for another count."""
    if text is None:
        return None
    from uavloc.errors import ScenarioError

    urls = [u.strip() for u in text.split(",")]
    n = scenario.mission.fleet_size
    if len(urls) != n or not all(urls):
        what = f"the {n} vehicles of its [[vehicles]]" if n > 1 else "one vehicle"
        raise ScenarioError(f"--connect {text!r}: scenario {scenario.name!r} flies {what}; give "
                            f"{'one URL per vehicle, comma-separated' if n > 1 else 'one URL'} "
                            f"({len([u for u in urls if u])} given)")
    from mission.addresses import first_duplicate, mavlink_endpoint

    dup = first_duplicate([mavlink_endpoint(u) for u in urls])
    if dup is not None:
        i, j = dup
        raise ScenarioError(f"--connect {text!r}: URL {j + 1} ({urls[j]!r}) reaches the same MAVLink endpoint as URL "
                            f"{i + 1} ({urls[i]!r}): each vehicle of scenario {scenario.name!r} has its own autopilot")
    return urls if n > 1 else urls[0]


@dataclass
class _Held:
    """What the command's coroutine leaves for the interrupted path: the simulated mission once
    it started, the exit code once the mission ended and its result was printed."""

    sim: SimulatedMission | None = None
    exit_code: int | None = None
