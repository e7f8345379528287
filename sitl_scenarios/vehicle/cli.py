"""`python -m sitl_scenarios.vehicle`: the built-in vehicle on its own, logging its state."""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from typing import Any

from sitl_scenarios.scenario import load_scenario, with_autopilot
from sitl_scenarios.vehicle.simulator import VehicleSimulator
from uavloc.errors import ScenarioError, SimulatorError

log = logging.getLogger(__name__)

DESCRIPTION = "Built-in MAVLink multicopter that MAVSDK takes for PX4 (docs/design.md §9)."


def _parse_targets(parts: list[str]) -> list[tuple[str, int]]:
    """The targets of one --target: `[udp] HOST:PORT [HOST:PORT …]`, `udp://HOST:PORT`, or `none`."""
    words = [w for w in " ".join(parts).split() if w != "udp"]
    out = []
    for word in words:
        text = word
        for prefix in ("udp://", "udpout://"):
            if text.startswith(prefix):
                text = text[len(prefix):]
        if text == "none":
            continue
        host, _, port = text.rpartition(":")
        try:
            port_n = int(port)
        except ValueError:
            port_n = -1
        if not 0 < port_n < 65536:
            raise SimulatorError(f"--target must be [udp] HOST:PORT (port 1-65535), got {word!r} "
                                 f"in {' '.join(parts)!r}")
        out.append((host or "127.0.0.1", port_n))
    return out


def main(argv: list[str] | None = None) -> int:
    """`python -m sitl_scenarios.vehicle --scenario FILE [--speedup X] [--target udp HOST:PORT]`."""
    ap = argparse.ArgumentParser(prog="python -m sitl_scenarios.vehicle", description=DESCRIPTION)
    ap.add_argument("--scenario", default="paper", help="scenario file or bundled name (default: paper)")
    ap.add_argument("--speedup", type=float, default=1.0, help="simulated seconds per wall second")
    ap.add_argument("--target", nargs="+", action="append", default=None,
                    help="where to send before a ground station talks: [udp] HOST:PORT [HOST:PORT …] "
                         "(repeatable; default 127.0.0.1:14540), or none")
    ap.add_argument("--bind", default="0.0.0.0:0", help="local HOST:PORT (port 0: any)")
    ap.add_argument("--seed", type=int, default=None, help="GPS noise seed (default: the scenario's)")
    ap.add_argument("--duration", type=float, default=None, help="stop after this many wall seconds")
    ap.add_argument("--autopilot", choices=("px4", "ardupilot"),
                    help="whose personality the vehicle has (default: the scenario's [vehicle] autopilot)")
    ap.add_argument("--vehicle", type=int, default=0, metavar="I",
                    help="which vehicle of the scenario's fleet ([[vehicles]], from 0): its system id I+1 and its "
                         "home at its launch point (default 0)")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        scenario = load_scenario(args.scenario)
        if args.autopilot is not None:
            scenario = with_autopilot(scenario, args.autopilot)
        bind_host, _, bind_port = args.bind.rpartition(":")
        targets = [t for parts in (args.target or [["127.0.0.1:14540"]]) for t in _parse_targets(parts)]
        kwargs: dict[str, Any] = {"speedup": args.speedup, "target": targets,
                                  "bind": (bind_host or "0.0.0.0", int(bind_port))}
        if args.seed is not None:
            kwargs["seed"] = args.seed
        if not 0 <= args.vehicle < scenario.mission.fleet_size:
            ap.error(f"--vehicle {args.vehicle}: {args.scenario} flies vehicles 0..{scenario.mission.fleet_size - 1}")
        sim = VehicleSimulator.from_scenario(scenario, args.vehicle, **kwargs)
        with sim:
            t_end = None if args.duration is None else time.monotonic() + args.duration
            while t_end is None or time.monotonic() < t_end:
                time.sleep(min(2.0, max(0.0, (t_end or math.inf) - time.monotonic())))
                s = sim.state()
                e, n, u = s.pos_enu_m
                log.info("t=%.1f s %s armed=%s pos_enu=(%.1f, %.1f, %.1f) battery=%.0f%%",
                         s.t_s, s.mode, s.armed, e, n, u, s.battery_pct)
    except KeyboardInterrupt:
        return 0
    except (ScenarioError, SimulatorError, ValueError) as exc:
        log.error("%s", exc)
        return 1
    return 0
