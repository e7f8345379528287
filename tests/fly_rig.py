"""`uavloc fly` against a vehicle and a gNB it did not start: the built-in vehicle (its own threads)
and the simulated gNB (its own event loop in a thread) stand in for the Pixhawk and the OAI gNB, so
a test can watch the vehicle (`VehicleSimulator.state()`) while the command flies it."""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


@dataclass
class FlyRig:
    """What `external_fly_rig` yields: the vehicle being flown and the command line's arguments."""

    vehicle: object  # sitl_scenarios.vehicle.VehicleSimulator
    connect: str
    gnb: str
    mission: Path

    def fly_args(self, *extra: str, pre: tuple[str, ...] = ()) -> list[str]:
        """`python -m mission [pre] fly ...` for this rig, the lawnmower planner, `extra` appended."""
        return [sys.executable, "-m", "mission", *pre, "fly", "--connect", self.connect, "--gnb", self.gnb,
                "--mission", str(self.mission), "--planner", "lawnmower", *extra]


def one_user_mission(folder: Path) -> Path:
    """The shipped example mission file with the paper scenario's one user (0x4601) only."""
    from mission.config import example_mission_path

    text = example_mission_path().read_text(encoding="utf-8")
    start = text.index('[[users]]\nid = "ue2"')
    path = folder / "flight.toml"
    path.write_text(text[:start] + text[text.index("\n#", start) + 1:], encoding="utf-8")
    return path


@contextlib.contextmanager
def external_fly_rig(folder: Path, speedup: float) -> Iterator[FlyRig]:
    """The paper scenario's vehicle and gNB, running until the block ends."""
    from sitl_scenarios.gnb import SimulatedGnb
    from sitl_scenarios.scenario import load_scenario
    from sitl_scenarios.sim_runner import free_udp_port
    from sitl_scenarios.vehicle import VehicleSimulator

    sc = load_scenario("paper")
    port = free_udp_port()
    mission = one_user_mission(folder)
    with VehicleSimulator.from_scenario(sc, speedup=speedup, target=("127.0.0.1", port), bind=("127.0.0.1", 0),
                                        max_stream_wall_hz=100.0) as veh:
        started = threading.Event()
        stop: dict = {}
        gnb_port: dict = {}

        def serve_gnb() -> None:
            async def main():
                stop["event"] = asyncio.Event()
                stop["loop"] = asyncio.get_running_loop()
                async with SimulatedGnb(sc, lambda: np.asarray(veh.state().pos_enu_m), port=0,
                                        clock=lambda: veh.state().t_s) as gnb:
                    gnb_port["port"] = gnb.port
                    started.set()
                    await stop["event"].wait()

            asyncio.run(main())

        thread = threading.Thread(target=serve_gnb, daemon=True)
        thread.start()
        assert started.wait(10)
        try:
            yield FlyRig(veh, f"udpin://127.0.0.1:{port}", f"127.0.0.1:{gnb_port['port']}", mission)
        finally:
            stop["loop"].call_soon_threadsafe(stop["event"].set)
            thread.join(10)


def wait_for(predicate, timeout_s: float, what: str, proc: subprocess.Popen | None = None) -> None:
    """Poll `predicate` every 50 ms; fail after timeout_s [s] or when `proc` ended first."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if proc is not None and proc.poll() is not None:
            _out, err = proc.communicate()
            raise AssertionError(f"the command ended (exit {proc.returncode}) before {what}:\n{err[-3000:]}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def rtt_lines(log_path: Path) -> int:
    """Measurement records written so far."""
    try:
        return log_path.read_bytes().count(b'"type":"rtt"')
    except FileNotFoundError:
        return 0


@dataclass
class TinyDisk:
    """A folder whose files cannot grow past `size_b` bytes: a real tmpfs of that size (root),
    else a file-size limit for the subprocesses started with `preexec` (EFBIG instead of ENOSPC;
    the same refused write)."""

    path: Path
    size_b: int
    mounted: bool

    def preexec(self) -> None:
        if not self.mounted:
            import resource
            import signal

            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a refused write, not a killed process
            resource.setrlimit(resource.RLIMIT_FSIZE, (self.size_b, self.size_b))


@contextlib.contextmanager
def tiny_disk(folder: Path, size_b: int = 80_000) -> Iterator[TinyDisk]:
    import os

    path = folder / "disk"
    path.mkdir()
    mounted = False
    if os.geteuid() == 0:
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_b}", "tmpfs", str(path)],
                                 capture_output=True).returncode == 0
    try:
        yield TinyDisk(path, size_b, mounted)
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(path)], capture_output=True)
