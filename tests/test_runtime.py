"""mission.runtime.BoundedRun: the event loop of `uavloc sim`/`fly` ends even when a blocking call
of the vehicle library never returns (the MAVSDK 4.1 wedge), and reports it."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import threading
import time

import numpy as np
import pytest

from mission.runtime import EXIT_INTERRUPTED, BoundedRun
from uavloc.errors import VehicleError


def test_a_call_stuck_in_the_executor_does_not_hold_the_loop_and_is_reported() -> None:
    release = threading.Event()

    async def mission() -> str:
        loop = asyncio.get_running_loop()
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(0.2):
                await loop.run_in_executor(None, release.wait)  # a MAVSDK call that never returns
        return "result"

    runner = BoundedRun(shutdown_timeout_s=0.5)
    try:
        assert runner.run(mission()) == "result"
        assert runner.stuck
    finally:
        release.set()


def test_a_clean_run_is_not_stuck_and_errors_propagate() -> None:
    async def ok() -> int:
        await asyncio.to_thread(lambda: None)
        return 3

    runner = BoundedRun(shutdown_timeout_s=2.0)
    assert runner.run(ok()) == 3 and not runner.stuck

    async def fails() -> None:
        raise VehicleError("refused")

    with pytest.raises(VehicleError, match="refused"):
        BoundedRun().run(fails())


@pytest.mark.sim
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_sigterm_or_sighup_during_the_survey_sends_the_vehicle_home(tmp_path, signum) -> None:
    """Issue 21 #1: a `kill` or a dropped terminal during `uavloc fly`'s survey ends the mission as
    Ctrl-C does: RTL (the vehicle seen returning home), the log closed with its end record, exit 130."""
    from mission.log import read_mission_log
    from tests.fly_rig import REPO, external_fly_rig, rtt_lines, wait_for

    out = tmp_path / "out"
    log_path = out / "mission.jsonl"
    with external_fly_rig(tmp_path, speedup=20.0) as rig:
        proc = subprocess.Popen(rig.fly_args("--out", str(out)), cwd=REPO, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            wait_for(lambda: rtt_lines(log_path) >= 5, 90, "5 measurements", proc)
            home = np.asarray(rig.vehicle.state().home_enu_m)
            proc.send_signal(signum)
            _out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        state = rig.vehicle.state()
        d0_m = float(np.linalg.norm((state.pos_enu_m - home)[:2]))
        time.sleep(1.0)
        d1_m = float(np.linalg.norm((rig.vehicle.state().pos_enu_m - home)[:2]))
    assert proc.returncode == EXIT_INTERRUPTED, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    # returning home, or (when uavloc took longer to exit than the 20x-speed return: a loaded
    # machine) already landed there; a vehicle left alone would hover in Hold where it was
    landed_home = not state.in_air and d0_m < 5.0
    assert state.mode == "return_to_launch" or landed_home, (state.mode, state.in_air, d0_m)
    # closing in on home, or over it already (descending: the true position then wanders by the GPS
    # error around the home the vehicle's estimate holds)
    assert d1_m < d0_m or not state.in_air or d0_m < 5.0, (d0_m, d1_m)
    kinds = [e.get("kind", "") for e in read_mission_log(log_path).events]
    assert kinds[-3:] == ["interrupted", "rtl", "end"], kinds[-5:]
    last = log_path.read_bytes().rstrip(b"\n").rsplit(b"\n", 1)[-1]
    assert b'"kind":"end"' in last, last


# -- ending signals under a loaded or blocked loop (issue 49) -----------------------------------

#: a process running a BoundedRun whose loop argv[1] describes: "blocked" (a coroutine that blocks
#: the loop with time.sleep: nothing the loop schedules ever runs) or "flooded" (threads filling the
#: loop's self-pipe with call_soon_threadsafe while the coroutine keeps the loop busy in 50 ms
#: chunks: the state of a loop with 50 vehicles' telemetry callbacks). It prints READY, then what
#: became of the run: RESORT (the runner's last resort, called from its watchdog) or CANCELLED.
_RUNNER = """
import asyncio, sys, threading, time
from mission.runtime import BoundedRun

mode = sys.argv[1]
runner = BoundedRun(answer_timeout_s=1.0, signal_grace_s=4.0, last_resort_timeout_s=2.0)
runner.last_resort = lambda why: print("RESORT", why, flush=True)

async def mission():
    loop = asyncio.get_running_loop()
    if mode == "flooded":
        def flood():
            while True:
                loop.call_soon_threadsafe(lambda: None)
        for _ in range(4):
            threading.Thread(target=flood, daemon=True).start()
    print("READY", flush=True)
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end:
        time.sleep(60 if mode == "blocked" else 0.05)
        await asyncio.sleep(0)

try:
    runner.run(mission())
except asyncio.CancelledError:
    print("CANCELLED", flush=True)
    sys.exit(130)
"""


def _signal_runner(mode: str, signum: int) -> tuple[int, str, str, float]:
    """(exit code, stdout, stderr, wall seconds from the signal to the exit) of _RUNNER."""
    import sys

    from tests.test_mission_e2e import REPO

    proc = subprocess.Popen([sys.executable, "-c", _RUNNER, mode], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "READY"
        time.sleep(0.5)
        t0 = time.monotonic()
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=30)
        return proc.returncode, out, err, time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP], ids=["TERM", "INT", "HUP"])
def test_a_signal_ends_a_run_whose_loop_is_blocked(signum) -> None:
    """The loop never runs the cancellation: the watchdog calls the last resort after
    answer_timeout_s (1 s) and exits 130."""
    code, out, err, wall_s = _signal_runner("blocked", signum)
    assert code == EXIT_INTERRUPTED, err
    assert "RESORT the event loop did not answer the signal within 1 s" in out, (out, err)
    assert wall_s < 6.0, wall_s


def test_a_signal_ends_a_run_whose_loop_is_flooded() -> None:
    """Threads keep the loop's self-pipe full (asyncio's own signal handling lost every signal
    there: "Exception ignored when trying to write to the signal wakeup fd: BlockingIOError"):
    the signal still cancels the mission, in the loop, within seconds."""
    code, out, err, wall_s = _signal_runner("flooded", signal.SIGTERM)
    assert code == EXIT_INTERRUPTED, err
    assert "CANCELLED" in out and "RESORT" not in out, (out, err[-2000:])
    assert "BlockingIOError" not in err and "ending the mission" in err, err[-2000:]
    assert wall_s < 6.0, wall_s


#: vehicles of the loaded fleet below: the most `uavloc sim` flies (sitl_scenarios.scenario
#: MAX_BUILTIN_VEHICLES), at the highest speed-up it allows them, beside busy loops on every core
#: (its loop falls seconds behind: "Callback took more than 1 second", "fell N s behind")
LOADED_FLEET = 8


@pytest.mark.sim
@pytest.mark.slow
def test_sigterm_ends_a_loaded_fleet_mission_within_seconds(tmp_path) -> None:
    """Issue 49: `uavloc sim` of the largest fleet it flies, on a machine whose every core is busy
    (10 vehicles at x20 stayed in PREFLIGHT for 10 minutes), SIGTERM once every vehicle is connected: exit
    130 within the watchdog's bound (answer 5 s + grace 15 s + last resort 5 s), the log whole and
    ending in its end record (written by the controller, or by the watchdog's last resort when
    the loop did not answer)."""
    import json
    import os
    import sys

    from tests.test_mission_e2e import REPO

    text = (REPO / "sitl_scenarios" / "two_uavs.toml").read_text()
    more = "".join(f'\n[[vehicles]]\nid = "uav{i}"\n' for i in range(3, LOADED_FLEET + 1))
    scenario = tmp_path / "loaded.toml"
    scenario.write_text(text.replace('[[vehicles]]\nid = "uav2"\n', '[[vehicles]]\nid = "uav2"\n' + more, 1))
    log_path = tmp_path / "out" / "mission.jsonl"
    from sitl_scenarios.scenario import MAX_BUILTIN_VEHICLES, MAX_VEHICLE_SPEEDUP

    assert LOADED_FLEET == MAX_BUILTIN_VEHICLES
    speedup = MAX_VEHICLE_SPEEDUP / LOADED_FLEET
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2 * (os.cpu_count() or 2))]
    proc = subprocess.Popen([sys.executable, "-m", "mission", "sim", str(scenario), "--speedup", f"{speedup:g}",
                             "--out", str(tmp_path / "out")], cwd=REPO, env=dict(os.environ, PYTHONUNBUFFERED="1"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        # every vehicle connected and its home known (its loop already lagging seconds behind)
        while (log_path.read_text() if log_path.exists() else "").count('"kind":"home"') < LOADED_FLEET:
            assert proc.poll() is None and time.monotonic() < deadline, "the vehicles' homes never came"
            time.sleep(0.2)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=60)
        wall_s = time.monotonic() - t0
    finally:
        for b in busy:
            b.kill()
            b.wait()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == EXIT_INTERRUPTED, err[-3000:]
    assert wall_s < 30.0, wall_s
    assert "BlockingIOError" not in err and "Traceback" not in err, err[-3000:]
    records = [json.loads(line) for line in log_path.read_text().splitlines()]  # every line whole
    end = records[-1]
    assert end["type"] == "event" and end["kind"] == "end" and end["status"] == "interrupted", end
    assert [r.get("kind") for r in records].count("end") == 1


@pytest.mark.sim
@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_the_last_resort_rtl_needs_no_event_loop(autopilot) -> None:
    """The watchdog's RTL (MavsdkVehicle.return_to_launch_blocking), called from a thread of its
    own, sends a vehicle in the air home: MAVSDK's blocking call on PX4, DO_SET_MODE RTL on
    ArduPilot."""
    from estimator.geodesy import Origin
    from mission.vehicle import MavsdkVehicle
    from sitl_scenarios.scenario import VehicleConfig
    from sitl_scenarios.vehicle import VehicleSimulator
    from tests.test_ardupilot_mission import _free_udp_port

    home = Origin(43.6143, 7.0716, 150.0)

    async def fly() -> str:
        port = _free_udp_port()
        async with VehicleSimulator(home, VehicleConfig(autopilot=autopilot), speedup=20.0,
                                    target=("127.0.0.1", port), bind=("127.0.0.1", 0)) as sim, \
                MavsdkVehicle(f"udpin://127.0.0.1:{port}") as v:
            await v.connect(20.0)
            telemetry = asyncio.create_task(v.run_telemetry(lambda fix: None))
            await v.wait_ready(60.0)
            await v.arm()
            await v.takeoff(10.0)
            await sim.wait_for(lambda s: s.pos_enu_m[2] > 9.0, 30.0)
            done = threading.Event()

            def last_resort() -> None:
                v.return_to_launch_blocking()
                done.set()

            threading.Thread(target=last_resort, daemon=True).start()
            await sim.wait_for(lambda s: s.mode == "return_to_launch", 20.0)
            assert await asyncio.to_thread(done.wait, 10.0)  # returned, without raising
            telemetry.cancel()
            return sim.state().mode

    assert asyncio.run(asyncio.wait_for(fly(), 120.0)) == "return_to_launch"
