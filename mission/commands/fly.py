"""`uavloc fly --mission FILE --connect URL --gnb HOST:PORT [--out DIR]`: fly a real mission.

The mission file (mission/config.py; example: mission/examples/flight.toml) holds everything the
flight needs and no true position. `--scenario FILE` is a deprecated alias that flies the mission
part of a simulation scenario (its true positions are ignored)."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from mission.commands.argtypes import gnb_address
from mission.view.live import add_view_arguments

if TYPE_CHECKING:
    from mission.controller import MissionController

log = logging.getLogger(__name__)

HELP = "fly a localization mission with a MAVLink vehicle (PX4) and an OAI gNB"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", metavar="URL",
                   help="MAVSDK connection URL of the vehicle, e.g. udpin://0.0.0.0:14540 or "
                        "serial:///dev/ttyACM0:57600 (required for one vehicle; a fleet's vehicles are addressed "
                        "in the mission file's [[vehicles]])")
    p.add_argument("--gnb", metavar="ADDRESS", type=gnb_address,
                   help="the gNB: HOST:PORT or telnet://HOST:PORT (telnet server, default port 9090), "
                        "http://HOST:PORT (OAI's web server, default port 8090) (required for one vehicle)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--mission", metavar="FILE",
                     help="mission file: users (id, RNTI), geofence, altitudes, Δ, target, noise, gNB and "
                     "safety settings (example: mission/examples/flight.toml)")
    src.add_argument("--scenario", metavar="FILE",
                     help="deprecated: fly the mission part of a simulation scenario (use --mission)")
    p.add_argument("--out", type=Path, metavar="DIR", help="write the mission log and a report here")
    p.add_argument("--log", type=Path, metavar="FILE", help="mission log path (default: DIR/mission.jsonl or "
                   "$UAVLOC_RUNS/<UTC>-fly-<mission>/mission.jsonl, $UAVLOC_RUNS default ~/uavloc-runs)")
    p.add_argument("--planner", metavar="NAME", help="planner (default: the mission's, casadi when available)")
    p.add_argument("--gnb-mode", choices=("rtt", "trace", "stock", "auto"), help="override the mission's gnb.mode")
    p.add_argument("--t-port", type=int, metavar="PORT",
                   help="override the mission's gnb.t_port (trace mode: the gNB's T tracer, --T_port)")
    p.add_argument("--gnb-log", type=Path, metavar="FILE", help="override the mission's gnb.log_path (stock mode)")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    add_view_arguments(p)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from mission.addresses import fleet_address_problem
    from mission.commands.outdir import LOG_NAME, default_out_dir, mission_log_path
    from mission.config import load_mission, with_settings
    from mission.controller import controller_from_mission, resolve_planner_name
    from mission.gnb import GnbConfig, OaiGnbClient, parse_gnb_address
    from mission.status import print_result, write_report
    from mission.vehicle import MavsdkVehicle
    from mission.view.live import live_view
    from uavloc.errors import MissionConfigError

    if args.mission is not None:
        mission = load_mission(args.mission)
    else:
        log.warning("--scenario is deprecated for fly: write a mission file (--mission; see "
                    "mission/examples/flight.toml); the scenario's true positions are ignored")
        mission = _scenario_mission(args.scenario)
    source = args.mission or args.scenario
    # an address the command would not use is an error, never dropped: a fleet's are its file's,
    # and a vehicle entry's own wins over the command line's
    ignored = [f"--{key} (the file gives {what})" for key, given in (("connect", args.connect), ("gnb", args.gnb))
               for what in [f"each of its {mission.fleet_size} vehicles' {key}" if mission.fleet_size > 1
                            else f"vehicles[0].{key}" if mission.vehicles and getattr(mission.vehicles[0], key)
                            else None] if given is not None and what is not None]
    if ignored:
        print(f"uavloc fly: error: {' and '.join(ignored)} would be ignored: {source} names "
              f"{'a fleet of ' + str(mission.fleet_size) + ' vehicles' if mission.fleet_size > 1 else 'the address'}"
              "; leave the option out or the key", file=sys.stderr)
        return 2
    problem = fleet_address_problem(mission)
    if problem is not None:
        raise MissionConfigError(f"{source}: {problem}")
    gnb_over = {}
    if args.gnb_mode is not None:
        gnb_over["mode"] = args.gnb_mode
    if args.gnb_log is not None:
        gnb_over["log_path"] = str(args.gnb_log)
    if args.t_port is not None:
        gnb_over["t_port"] = args.t_port
    if gnb_over:
        mission = with_settings(mission, gnb_over, "command line")
    # a flight knows no true positions: the oracle planner is refused before anything connects
    resolve_planner_name(args.planner or mission.flight.planner, truth_known=False)
    # each vehicle's MAVLink and gNB address: a fleet's from its `[[vehicles]]`, one vehicle's from
    # the command line (what its one entry leaves out)
    entries = mission.vehicles if mission.fleet_size > 1 else [None]
    connects = [e.connect if e is not None else args.connect for e in entries]  # (fleet_address_problem: given)
    if mission.fleet_size == 1 and mission.vehicles:
        connects = [mission.vehicles[0].connect or args.connect]
    gnb_args = [e.gnb if e is not None else args.gnb for e in entries]
    if mission.fleet_size == 1 and mission.vehicles:
        gnb_args = [mission.vehicles[0].gnb or args.gnb]
    lacking = [flag for flag, given in (("--connect", connects[0]), ("--gnb", gnb_args[0])) if not given]
    if lacking:
        print(f"uavloc fly: error: {' and '.join(lacking)} required: {args.mission or args.scenario} flies one vehicle "
              "(a fleet names each vehicle's addresses in [[vehicles]])", file=sys.stderr)
        return 2
    addresses = [parse_gnb_address(g, default=mission.gnb.transport) for g in gnb_args]
    if args.out is None and args.log is None:
        args.out = default_out_dir("fly", Path(args.mission).stem if args.mission is not None else "mission")
    log_path = mission_log_path(args.out, args.log, args.out / LOG_NAME if args.out is not None else args.log)

    from mission.runtime import EXIT_INTERRUPTED, BoundedRun

    runner = BoundedRun()
    held = _Held()

    def finish(result, interrupted: bool) -> int:
        """Print the result, write the report; the command's exit code."""
        print_result(result, args.json)
        log_failed = held.controller.log_writer.failed
        if log_failed is not None:
            log.error("no report: %s", log_failed)
        elif args.out is not None and result.log_path is not None and result.measurements:
            write_report(result.log_path, args.out)
        return EXIT_INTERRUPTED if interrupted else (0 if result.ok else 1)

    def gnb_config(i: int):
        gcfg = mission.gnb
        mode = mission.vehicles[i].gnb_mode if i < len(mission.vehicles) else ""
        if mode and args.gnb_mode is None:  # the command line's --gnb-mode is every vehicle's
            gcfg = dataclasses.replace(gcfg, mode=mode)
        a = addresses[i]
        return GnbConfig.of(gcfg, a.host, a.port, transport=a.transport)

    async def main() -> int:
        async with live_view(args, title="uavloc fly") as view:
            async with contextlib.AsyncExitStack() as stack:
                vehicles = [await stack.enter_async_context(MavsdkVehicle(url)) for url in connects]
                gnbs = [await stack.enter_async_context(OaiGnbClient(gnb_config(i))) for i in range(len(connects))]
                fleet = len(vehicles) > 1
                controller = controller_from_mission(
                    mission, vehicles if fleet else vehicles[0], gnbs if fleet else gnbs[0], log_path,
                    planner=args.planner,
                    header_config={"command": "fly", "connect": connects if fleet else connects[0],
                                   "gnb": gnb_args if fleet else gnb_args[0],
                                   "command_line": getattr(args, "command_line", None),
                                   "mission_file": None if args.mission is None else str(args.mission)})
                held.controller = controller
                runner.last_resort = controller.last_resort
                view.follow(controller.log_writer)
                result = await controller.run()
            # the vehicle link and the gNB are closed: the page shows the finished mission
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
            controller = held.controller
            result = controller.result if controller is not None else None
            if result is None:
                log.error("interrupted before the mission started")
                runner.exit_if_stuck(EXIT_INTERRUPTED)
                return EXIT_INTERRUPTED
            code = finish(result, interrupted=True)
    runner.exit_if_stuck(code)
    return code


@dataclass
class _Held:
    """What the command's coroutine leaves for the interrupted path: the controller once the
    mission started, the exit code once the mission ended and its result was printed."""

    controller: MissionController | None = None
    exit_code: int | None = None


def _scenario_mission(name: str):
    """The mission part of a simulation scenario (the deprecated `--scenario`): the
    `flight_mission(name)` of the module the `uavloc.scenarios` entry point names, so mission
    never imports sitl_scenarios nor sees a scenario."""
    import importlib
    from importlib.metadata import entry_points

    from uavloc.errors import MissionConfigError

    eps = [ep for ep in entry_points(group="uavloc.scenarios") if ep.name == "load"]
    if not eps:
        raise MissionConfigError("--scenario needs the simulation package (sitl_scenarios) installed; "
                                 "use --mission FILE")
    return importlib.import_module(eps[0].module).flight_mission(name)
