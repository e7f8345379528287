"""Built-in vehicle benchmarks: its clock and stream rates on the wire, a MAVSDK flight, and how soon
MAVSDK notices a paused link, all on the wall clock (the tests check the same properties by the
order and count of events, without timing them).

    python benchmarks/vehicle.py [--speedup 8] [--skip-flight] [--skip-link]

1. Clock and streams: a raw UDP ground station listens for 2 wall seconds at `--speedup`. The
   vehicle time the stamps cover divided by the wall time measured in the same run must be the
   speedup (ratio 1.00 ± 0.15); heartbeats at 1 Hz vehicle time, i.e. `speedup` Hz on the wire (at
   least 1 Hz); ATTITUDE at 10 Hz vehicle time capped at 25 Hz on the wire.
2. Flight: MAVSDK health → arm → takeoff 20 m → goto 100 m north → RTL → landed at 25x (the flight
   of tests/test_vehicle_mavsdk.py); the wall time against the vehicle time of the same flight.
   Target: landed within 30 wall seconds.
3. Link pause of 6 wall seconds: when MAVSDK declares the link lost (target 2..6 s: its timeout is
   about 3 s) and back (target 5.5..9 s, i.e. soon after the pause).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import sys
import time
from pathlib import Path

# benchmarks/ holds scripts named like packages: the repository root replaces this folder on sys.path
_HERE = Path(__file__).resolve().parent
REPO = _HERE.parent
sys.path[:] = [str(REPO)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from estimator.geodesy import Origin  # noqa: E402
from sitl_scenarios.vehicle import VehicleSimulator  # noqa: E402

ORIGIN = Origin(43.6143, 7.0716, 150.0)


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def clock_and_streams(speedup: float, wall_s: float = 2.0) -> bool:
    """Stamps' vehicle time per wall second, heartbeat and ATTITUDE rates on the wire."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        gcs.settimeout(0.2)
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        stamps: list[tuple[float, int]] = []
        heartbeats = 0
        with VehicleSimulator(ORIGIN, speedup=speedup, target=gcs.getsockname(), bind=("127.0.0.1", 0)):
            t_end = time.monotonic() + wall_s
            while time.monotonic() < t_end:
                try:
                    data, _ = gcs.recvfrom(65535)
                except TimeoutError:
                    continue
                for m in parser.parse_buffer(data) or []:
                    if m.get_type() == "ATTITUDE":
                        stamps.append((time.monotonic(), m.time_boot_ms))
                    elif m.get_type() == "HEARTBEAT":
                        heartbeats += 1
    if len(stamps) < 2:
        print("  FAILED: fewer than two ATTITUDE messages received")
        return False
    (w0, b0), (w1, b1) = stamps[0], stamps[-1]
    clock_ratio = (b1 - b0) / 1000.0 / (w1 - w0) / speedup
    hb_hz, hb_target = heartbeats / wall_s, max(min(speedup, 25.0), 1.0)
    att_hz, att_target = len(stamps) / wall_s, min(10.0 * speedup, 25.0)
    ok = abs(clock_ratio - 1.0) <= 0.15 and 0.75 <= hb_hz / hb_target <= 1.25 and att_hz / att_target <= 1.08
    print(f"clock and streams at speedup {speedup:g}, {wall_s:g} wall seconds (load {_load()}):")
    print(f"  vehicle time / wall time / speedup:  {clock_ratio:.3f}   (target 1.00 ± 0.15)")
    print(f"  heartbeats on the wire:  {hb_hz:5.1f} Hz = {hb_hz / hb_target:.2f} x {hb_target:g} Hz expected")
    print(f"  ATTITUDE on the wire:    {att_hz:5.1f} Hz = {att_hz / att_target:.2f} x {att_target:g} Hz expected"
          " (10 Hz vehicle time, 25 Hz cap)")
    print(f"  targets {'met' if ok else 'NOT met'}")
    return ok


def flight() -> bool:
    """The MAVSDK takeoff / goto / RTL flight of the tests, timed."""
    from tests.test_vehicle_mavsdk import fly_goto_rtl, vehicle_link

    async def run() -> tuple[dict, float]:
        async with vehicle_link("builtin") as link:
            timings = await fly_goto_rtl(link)
            return timings, link.sim.state().t_s

    t0 = time.monotonic()
    timings, vehicle_s = asyncio.run(run())
    wall = time.monotonic() - t0
    ok = timings["landed_s"] < 30.0
    print(f"\nMAVSDK flight takeoff 20 m / goto 100 m / RTL at 25x (load {_load()}):")
    print("  " + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items()) + "  (wall, from the first health check)")
    print(f"  vehicle time {vehicle_s:.1f} s in {wall:.1f} wall s: {vehicle_s / wall:.1f}x effective speedup")
    print(f"  target landed < 30 wall s: {'met' if ok else 'NOT met'}")
    return ok


def link_pause(speedup: float = 4.0) -> bool:
    """Seconds until MAVSDK declares a paused link lost, and back."""
    from tests.test_vehicle_mavsdk import first, vehicle_link

    async def run() -> tuple[float, float]:
        async with vehicle_link("builtin", speedup=speedup) as link:
            states = link.system.is_connected_state()
            await link.system.is_connected()
            t0 = time.monotonic()
            link.sim.pause_link(6.0 * speedup)
            await first(states, lambda c: c is False, 30.0)
            lost = time.monotonic() - t0
            await first(states, lambda c: c is True, 30.0)
            return lost, time.monotonic() - t0

    lost, back = asyncio.run(run())
    ok = 2.0 < lost < 6.0 and 5.5 < back < 9.0
    print(f"\nlink paused for 6 wall seconds (load {_load()}):")
    print(f"  MAVSDK: lost after {lost:.2f} s (target 2..6), back after {back:.2f} s (target 5.5..9)")
    print(f"  targets {'met' if ok else 'NOT met'}")
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speedup", type=float, default=8.0, help="speedup of the clock and stream test")
    ap.add_argument("--skip-flight", action="store_true")
    ap.add_argument("--skip-link", action="store_true")
    args = ap.parse_args()
    ok = clock_and_streams(args.speedup)
    if not args.skip_flight:
        ok = flight() and ok
    if not args.skip_link:
        ok = link_pause() and ok
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
