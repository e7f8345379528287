"""The simulated world in its own process (sitl_scenarios/world.py): never outlives the mission
(closed, after an exception, when its parent is killed), speaks through the parent's logging, and
its gNB computes each range from the vehicle's true position at the instant it stamps it."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission, free_udp_port
from sitl_scenarios.world import WorldProcess, WorldSpec
from tests.test_mission_e2e import _run

pytestmark = pytest.mark.sim

REPO = Path(__file__).resolve().parents[1]


def _alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie nobody reaped yet has ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _gone_within(pid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while _alive(pid):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_the_world_is_gone_after_an_exception_in_the_controller_and_its_warnings_are_logged(tmp_path, caplog):
    sc = load_scenario("paper")

    async def broken_run():
        raise RuntimeError("the controller failed")

    async def body():
        async with SimulatedMission(sc, tmp_path / "m.jsonl", speedup=10.0) as sim:
            pid = sim.world.info.pid
            assert pid != 0 and _alive(pid) and sim.world.process.is_alive()
            assert sim.vehicle_sim.state().t_s >= 0.0  # the control channel answers
            await sim.kill_gnb()  # the world's warning comes back through this process's logging
            sim.controller.run = broken_run
            try:
                await sim.run()
            except RuntimeError:
                return pid, sim
        raise AssertionError("the controller's exception did not come through")

    with caplog.at_level(logging.WARNING):
        pid, sim = _run(body(), 60.0)
    assert not _alive(pid) and sim.world.process.exitcode == 0  # stopped gracefully, not killed
    assert any(r.name == "sitl_scenarios.world" and "gNB 0 killed" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("how", ["SIGKILL", "SIGTERM"])
def test_the_world_ends_when_its_parent_dies(tmp_path, how):
    """A parent killed without a chance to close the world (SIGKILL; SIGTERM at its default action):
    the world sees its pipe close and ends."""
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent("""\
        import time

        from sitl_scenarios.scenario import load_scenario
        from sitl_scenarios.sim_runner import free_udp_port
        from sitl_scenarios.world import WorldProcess, WorldSpec

        if __name__ == "__main__":
            world = WorldProcess(WorldSpec(load_scenario("paper"), 1, 10.0, (free_udp_port(),)))
            world.start()
            print(world.info.pid, flush=True)
            time.sleep(120)
        """))
    proc = subprocess.Popen([sys.executable, str(script)], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
                            stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.strip().isdigit(), line
        pid = int(line)
        assert _alive(pid)
        proc.send_signal(getattr(signal, how))
        proc.wait(10)
        assert _gone_within(pid, 10.0), f"the world {pid} outlived its parent"
    finally:
        proc.kill()
        proc.wait()


def test_closing_a_world_that_does_not_stop_kills_it(tmp_path, monkeypatch):
    """A world that ignores the stop request (SIGSTOPped: it answers nothing) is terminated, then
    killed: close() returns within its timeouts and nothing is left."""
    from sitl_scenarios import world as world_mod
    monkeypatch.setattr(world_mod, "STOP_TIMEOUT_S", 1.0)
    world = WorldProcess(WorldSpec(load_scenario("paper"), 1, 10.0, (free_udp_port(),)))
    world.start()
    pid = world.info.pid
    os.kill(pid, signal.SIGSTOP)
    t0 = time.monotonic()
    world.close()
    assert time.monotonic() - t0 < 1.0 + 1.0 + 2 * world_mod.KILL_TIMEOUT_S + 1.0
    assert not _alive(pid) and world.process.exitcode == -signal.SIGKILL


@pytest.mark.slow
def test_each_range_is_computed_from_the_true_position_at_its_stamp(tmp_path):
    """A whole mission: every range the world's gNB computed carries its stamp (the vehicle's
    simulated time) and the UAV position it used, and that pair is one snapshot of the vehicle's
    true state (the same t_s never with another position), and the true range is the distance from
    that position; the vehicle moved meanwhile, so a position of another instant would show."""
    sc = load_scenario("paper")
    user = np.array([[u.east_m, u.north_m, u.up_m] for u in sc.users], float)
    rntis = [u.rnti for u in sc.users]

    async def fly():
        async with SimulatedMission(sc, tmp_path / "m.jsonl", speedup=20.0, planner="lawnmower") as sim:
            result = await sim.run()
            return result, sim.gnb_sim.stamps(), sim.world.track(0), sim.world.info.pid

    result, stamps, track, pid = _run(fly(), 180.0)
    assert result.measurements >= 20 and len(stamps) >= result.measurements
    uav = np.array([s[1] for s in stamps])
    assert np.ptp(uav[:, 0]) + np.ptp(uav[:, 1]) > 50.0  # it flew while measuring
    for t_s, pos, rnti, true_range_m in stamps:
        assert t_s in track, t_s
        np.testing.assert_allclose(pos, track[t_s], atol=1e-9)
        k = rntis.index(rnti)
        assert true_range_m == pytest.approx(float(np.linalg.norm(pos - user[k])), abs=1e-9)
    # the vehicle's snapshots of distinct instants differ while it flies: t_s names one position
    ts = np.array(sorted(track))
    assert len(ts) > 100 and np.all(np.diff(ts) > 0)
    assert not _alive(pid)


def _start_and_close_a_world(conn) -> None:
    """In a daemonic process: start a world, report its pid, close it."""
    world = WorldProcess(WorldSpec(load_scenario("paper"), 1, 10.0, (free_udp_port(),)))
    world.start()
    try:
        conn.send((world.info.pid, world.call("vehicle", 0, "state", ()).t_s))
    finally:
        world.close()
    conn.send(world.process.exitcode)


def test_a_daemonic_process_such_as_a_dask_worker_can_start_the_world():
    """A full-mode campaign run flies in a Dask worker, a daemonic process, which multiprocessing
    refuses children: the world starts there too, and ends with it."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    here, there = ctx.Pipe()
    proc = ctx.Process(target=_start_and_close_a_world, args=(there,), daemon=True)
    proc.start()
    try:
        assert here.poll(120), "no answer from the daemonic process"
        pid, t_s = here.recv()
        assert t_s >= 0.0
        assert here.poll(30) and here.recv() == 0
        proc.join(10)
        assert proc.exitcode == 0 and not _alive(pid)
    finally:
        proc.kill()
        proc.join()


def test_a_gnbs_stamp_and_uav_position_are_one_snapshot_of_the_vehicle():
    """Within one step of the world's event loop every read of vehicle 0 (the gNB's clock, its UAV
    position, the fleet's cells) is one snapshot, however far the vehicle's thread has gone on
    meanwhile; the next step reads afresh."""
    from sitl_scenarios.vehicle import VehicleSimulator
    from sitl_scenarios.world import _Truth

    sc = load_scenario("paper")

    async def body():
        async with VehicleSimulator.from_scenario(sc, speedup=50.0, target=None, bind=("127.0.0.1", 0)) as sim:
            truth = _Truth([sim], sc.origin_geo)
            await asyncio.sleep(0.05)
            t_stamp = truth.clock(0)
            time.sleep(0.1)  # the vehicle's thread simulates 5 s meanwhile
            assert sim.state().t_s > t_stamp + 1.0
            assert truth.clock(0) == t_stamp
            np.testing.assert_array_equal(truth.position(0), truth.track[0][t_stamp])
            await asyncio.sleep(0)
            return t_stamp, truth.clock(0)

    t_stamp, t_next = asyncio.run(body())
    assert t_next > t_stamp + 1.0


def test_a_vehicle_port_is_held_until_its_adapter_binds_it():
    """The MAVSDK adapter's port is named to the world before the adapter binds it; while the world
    starts, its own sockets bind ports the OS picks, and one was once given that port (paper ×10
    under load: "cannot open MAVLink connection … BIND_ERROR", 1 of 80 load-benchmark runs). A
    reserved port can be bound by no other socket until it is released, and by the adapter then."""
    import errno
    import socket

    from sitl_scenarios.sim_runner import reserve_udp_port

    held = reserve_udp_port()
    port = held.getsockname()[1]
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other, pytest.raises(OSError) as err:
            other.bind(("127.0.0.1", port))
        assert err.value.errno == errno.EADDRINUSE
    finally:
        held.close()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as adapter:
        adapter.bind(("127.0.0.1", port))
