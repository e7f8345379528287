"""The simulated gNB following a MAVLink vehicle (GLOBAL_POSITION_INT over UDP on loopback), and
the standalone `python -m sitl_scenarios.gnb` entry point."""

from __future__ import annotations

import asyncio
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from estimator.geodesy import Origin
from mission.gnb import GnbConfig, OaiGnbClient
from sitl_scenarios.gnb import MavlinkPositionSource, SimulatedGnb
from sitl_scenarios.scenario import scenario_from_dict, user_tables
from tests.procs import stop_process

HOME = Origin(47.397742, 8.545594, 488.0)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(coro, timeout_s: float = 10.0):
    async def guarded():
        async with asyncio.timeout(timeout_s):
            return await coro

    return asyncio.run(guarded())


def send_position(conn, enu_m, relative_alt_m: float) -> None:
    lat, lon, alt = HOME.enu_to_lla(np.asarray(enu_m, float))
    conn.mav.global_position_int_send(
        1000, round(float(lat) * 1e7), round(float(lon) * 1e7), round(float(alt) * 1e3),
        round(relative_alt_m * 1e3), 0, 0, 0, 0)


async def wait_for(cond, timeout_s: float = 3.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not cond():
            await asyncio.sleep(0.01)


def test_follower_takes_home_from_first_fix_then_tracks_enu():
    port = free_udp_port()

    async def body():
        async with MavlinkPositionSource(f"udpin:127.0.0.1:{port}") as src:
            assert src() is None  # nothing received yet
            tx = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1)
            try:
                send_position(tx, (0.0, 0.0, 0.0), 0.0)  # on the ground at home
                await wait_for(lambda: src.messages >= 1)
                send_position(tx, (30.0, 100.0, 40.0), 40.0)
                await wait_for(lambda: src.messages >= 2)
                return src()
            finally:
                tx.close()

    pos = run(body())
    np.testing.assert_allclose(pos, [30.0, 100.0, 40.0], atol=0.05)


def test_follower_home_position_message_sets_origin():
    src = MavlinkPositionSource("udpin:127.0.0.1:1")  # not entered: handle() is pure
    mav = mavutil.mavlink.MAVLink(None)
    home = mav.home_position_encode(int(HOME.lat_deg * 1e7), int(HOME.lon_deg * 1e7), int(HOME.alt_m * 1e3),
                                    0, 0, 0, [1, 0, 0, 0], 0, 0, 0)
    src.handle(home)
    lat, lon, alt = HOME.enu_to_lla(np.array([-20.0, 50.0, 30.0]))
    gpi = mav.global_position_int_encode(0, round(float(lat) * 1e7), round(float(lon) * 1e7),
                                         round(float(alt) * 1e3), 30000, 0, 0, 0, 0)
    src.handle(gpi)
    np.testing.assert_allclose(src(), [-20.0, 50.0, 30.0], atol=0.05)


def test_gnb_answers_from_the_followed_vehicle_position():
    port = free_udp_port()
    sc = scenario_from_dict({"name": "f", "seed": 2, "radio": {"s0_m": 0.5, "ue_sawtooth_amplitude_m": 0.0},
                             **user_tables([{"id": "a", "rnti": "0x4601", "east_m": 200.0, "north_m": 0.0}])})

    async def body():
        async with MavlinkPositionSource(f"udpin:127.0.0.1:{port}") as src, \
                SimulatedGnb(sc, src, port=0) as gnb, \
                OaiGnbClient(GnbConfig(port=gnb.port, request_timeout_s=1.0)) as c:
            tx = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1)
            try:
                send_position(tx, (0.0, 0.0, 0.0), 0.0)
                await wait_for(lambda: src.messages >= 1)
                near = [(await c.measure(0x4601)).range_m for _ in range(10)]
                send_position(tx, (200.0, -100.0, 50.0), 50.0)
                await wait_for(lambda: src.messages >= 2)
                far = [(await c.measure(0x4601)).range_m for _ in range(10)]
                return near, far
            finally:
                tx.close()

    near, far = run(body())
    assert abs(np.median(near) - 200.0) < 2.0
    assert abs(np.median(far) - float(np.hypot(100.0, 50.0))) < 2.0


@pytest.mark.slow
def test_standalone_entry_point_serves_the_adapter(tmp_path: Path):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "sitl_scenarios.gnb", "--scenario", "paper", "--host", "127.0.0.1", "--port", "0",
         "--static-enu", "0", "0", "40", "--log", str(tmp_path / "gnb.log")],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env)
    try:
        port = None
        assert proc.stderr is not None
        for _ in range(50):  # bounded: the banner comes within the first lines
            line = proc.stderr.readline()
            m = re.search(r"on 127\.0\.0\.1:(\d+)", line)
            if m:
                port = int(m.group(1))
                break
            if not line:
                break
        assert port, "no listening banner from the simulated gNB"

        async def body():
            cfg = GnbConfig(port=port, mode="stock", stock_mode="active", log_path=tmp_path / "gnb.log",
                            msg2_timeout_s=2.0)
            async with OaiGnbClient(cfg) as c:
                rntis = await c.discover()
                s = await c.measure(rntis[0])
            async with OaiGnbClient(GnbConfig(port=port)) as c:
                return rntis, s, await c.measure((await c.discover())[0])  # reestablished: a new RNTI

        rntis, coarse, fine = run(body(), timeout_s=15)
        d = float(np.linalg.norm([60.0, 45.0, -40.0]))  # paper.toml: user at (60, 45, 0)
        assert rntis == [0x4601]
        assert abs(fine.range_m - d) < 15 and abs(coarse.range_m - d) < 40
    finally:
        stop_process(proc, grace_s=5, kill_wait_s=5)
        if proc.stderr is not None:
            proc.stderr.close()
