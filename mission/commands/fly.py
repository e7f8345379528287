"""`uavloc fly --connect URL --gnb HOST:PORT --scenario FILE [--out DIR]`: fly a real mission."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from mission.view.live import add_view_arguments

log = logging.getLogger(__name__)

HELP = "fly a localization mission with a MAVLink vehicle (PX4) and an OAI gNB"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--connect", required=True, metavar="URL",
                   help="MAVSDK connection URL of the vehicle, e.g. udpin://0.0.0.0:14540 or serial:///dev/ttyACM0:57600")
    p.add_argument("--gnb", required=True, metavar="HOST:PORT", help="the gNB's telnet server (default port 9090)")
    p.add_argument("--scenario", required=True, metavar="FILE",
                   help="mission settings: users (RNTIs), geofence, altitudes, Δ, target "
                   "(positions are offsets from home)")
    p.add_argument("--out", type=Path, metavar="DIR", help="write the mission log and a report here")
    p.add_argument("--log", type=Path, metavar="FILE", help="mission log path (default: DIR/mission.jsonl or "
                   "./uavloc-mission-<UTC>.jsonl)")
    p.add_argument("--planner", metavar="NAME", help="planner (default: the scenario's, casadi when available)")
    p.add_argument("--gnb-mode", choices=("rtt", "stock"), default="rtt",
                   help="rtt: the RTT command set; stock: ci force_reestab + Msg2 lines of --gnb-log")
    p.add_argument("--gnb-log", type=Path, metavar="FILE", help="gNB log file to follow (stock mode)")
    p.add_argument("--json", action="store_true", help="print one JSON document on stdout")
    add_view_arguments(p)


def run(args: argparse.Namespace) -> int:
    import asyncio
    from datetime import UTC, datetime

    from mission.controller import controller_from_scenario
    from mission.gnb import GnbConfig, OaiGnbClient, parse_host_port
    from mission.status import print_result, write_report
    from mission.vehicle import MavsdkVehicle
    from mission.view.live import live_view
    from sitl_scenarios.scenario import load_scenario

    scenario = load_scenario(args.scenario)
    host, port = parse_host_port(args.gnb)
    if args.log is not None:
        log_path = args.log
    elif args.out is not None:
        log_path = args.out / "mission.jsonl"
    else:
        log_path = Path(f"uavloc-mission-{datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')}.jsonl")

    from mission.runtime import EXIT_INTERRUPTED, BoundedRun

    runner = BoundedRun()
    held: dict = {}

    async def main():
        gnb_cfg = GnbConfig(host=host, port=port, mode=args.gnb_mode, log_path=args.gnb_log, mu=scenario.radio.mu)
        async with MavsdkVehicle(args.connect) as vehicle, OaiGnbClient(gnb_cfg) as gnb:
            controller = controller_from_scenario(
                scenario, vehicle, gnb, log_path, planner=args.planner,
                header_config={"command": "fly", "connect": args.connect, "gnb": args.gnb})
            held["controller"] = controller
            async with live_view(args, controller.log_writer, title="uavloc fly"):
                return await controller.run()

    interrupted = False
    try:
        result = runner.run(main())
    except (asyncio.CancelledError, KeyboardInterrupt):
        interrupted = True
        controller = held.get("controller")
        result = controller.result if controller is not None else None
        if result is None:
            log.error("interrupted before the mission started")
            runner.exit_if_stuck(EXIT_INTERRUPTED)
            return EXIT_INTERRUPTED
    print_result(result, args.json)
    if args.out is not None and result.log_path is not None and result.measurements:
        write_report(result.log_path, args.out)
    code = EXIT_INTERRUPTED if interrupted else (0 if result.ok else 1)
    runner.exit_if_stuck(code)
    return code
