"""The three-user mission flown by uavloc against the user's own ArduCopter SITL (`UAVLOC_ARDUPILOT`,
sitl_scenarios.ardupilot_sitl): end to end, and Ctrl-C mid-survey. Skipped with a sentence naming
UAVLOC_ARDUPILOT when it is unset.

uavloc flies ArduCopter over SERIAL0; a pymavlink client on SERIAL1 (:class:`Watcher`) sees what
ArduCopter itself reports (its modes, arming, position, texts), so the vehicle's side is checked
from ArduPilot's reports, not from uavloc's.
"""

from __future__ import annotations

import asyncio
import json
import math
import signal
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from estimator.geodesy import Origin
from mission.control.config import STATUS_TARGET
from mission.log import read_mission_log
from sitl_scenarios.ardupilot_sitl import ArduCopterSitl, binary_from_env, missing_requirement
from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission

pytestmark = pytest.mark.ardupilot

SCENARIO = "three_users_nlos"
SPEEDUP = 4.0
#: wall seconds a whole mission may take at speed-up 4 before the test fails
MISSION_TIMEOUT_S = 500.0
#: metres from home ArduCopter may land after RTL
LANDING_RADIUS_M = 5.0
RTL, LAND = 6, 9


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Watcher:
    """pymavlink on ArduCopter's SERIAL1 (udpin), in a thread: modes, arming, position, texts."""

    def __init__(self, port: int):
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="ardupilotmega",
                                               source_system=250)
        self.modes: list[int] = []
        self.armed: bool | None = None
        self.armed_seen = False
        self.texts: list[str] = []
        self.lla: tuple[float, float, float] | None = None
        self.home: Origin | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> Watcher:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.conn.close()

    def _run(self) -> None:
        asked = False
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.2)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "HEARTBEAT" and msg.autopilot == mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
                if not asked:  # ArduPilot streams nothing else until asked
                    self.conn.mav.request_data_stream_send(msg.get_srcSystem(), 1, mavutil.mavlink.MAV_DATA_STREAM_ALL,
                                                           4, 1)
                    asked = True
                if not self.modes or self.modes[-1] != msg.custom_mode:
                    self.modes.append(msg.custom_mode)
                self.armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self.armed_seen = self.armed_seen or self.armed
            elif kind == "STATUSTEXT":
                self.texts.append(msg.text)
            elif kind == "GLOBAL_POSITION_INT" and (msg.lat, msg.lon) != (0, 0):
                self.lla = (msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
            elif kind == "HOME_POSITION":
                self.home = Origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)

    def home_offset_m(self) -> float:
        if self.home is None or self.lla is None:
            return math.inf
        e, n, _ = self.home.lla_to_enu(*self.lla)
        return float(math.hypot(e, n))

    def landed_disarmed(self) -> bool:
        return self.armed_seen and self.armed is False

    def describe(self) -> str:
        return (f"modes {self.modes}, armed {self.armed}, {self.home_offset_m():.1f} m from home; ArduPilot said: "
                f"{self.texts[-10:]}")


@pytest.fixture
def ardupilot(tmp_path):
    """A fresh ArduCopter SITL of the user's binary for one test: SERIAL0 for uavloc (its
    `udpin://` URL in .url), SERIAL1 for a Watcher (.watch_port); stopped after the test."""
    binary = binary_from_env()
    reason = missing_requirement(binary)
    if reason:
        pytest.skip(reason)
    uavloc_port, watch_port = _free_udp_port(), _free_udp_port()
    instance = uavloc_port % 50  # its own TCP ports for the unused SERIAL2.. (5760 + 10 i)
    sitl = ArduCopterSitl(binary, instance, SPEEDUP, tmp_path / "ardupilot-work", [uavloc_port, watch_port],
                          tmp_path / "ardupilot.log")
    sitl.url, sitl.watch_port = f"udpin://127.0.0.1:{uavloc_port}", watch_port
    with sitl:
        yield sitl


def _wait(cond, timeout_s: float, what: str, describe=None) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"not seen within {timeout_s:g} s: {what}" + (f" ({describe()})" if describe else ""))
        time.sleep(0.1)


def test_three_user_mission_on_ardupilot_reaches_the_target(ardupilot, tmp_path):
    sc = load_scenario(SCENARIO)
    log_path = tmp_path / "mission.jsonl"

    async def fly():
        async with SimulatedMission(sc, log_path, connect=ardupilot.url) as sim:
            return await asyncio.wait_for(sim.run(), MISSION_TIMEOUT_S)

    with Watcher(ardupilot.watch_port) as watch:
        result = asyncio.run(fly())
        _wait(watch.landed_disarmed, 120, "ArduCopter landed and disarmed", watch.describe)
    assert result.status == STATUS_TARGET, (result.reason, result.events[-10:])
    err = result.error_m()
    # the target is a 95 % bound: the error lies beyond it in about one run in twenty
    assert err is not None and np.all(err <= 1.5 * sc.mission.flight.target_radius_m), err
    assert result.rtl_sent and result.landed
    assert RTL in watch.modes and 4 in watch.modes, watch.describe()  # GUIDED, then RTL by mode
    assert watch.home_offset_m() < LANDING_RADIUS_M, watch.describe()
    kinds = [e.get("kind") for e in read_mission_log(log_path).events]
    for kind in ("home", "arm", "takeoff", "speed", "stop", "rtl", "landed", "end"):
        assert kind in kinds, kind


def test_ctrl_c_mid_survey_sends_ardupilot_home(ardupilot, tmp_path):
    """SIGINT to `uavloc sim --connect` while surveying: exit code 130, ArduCopter in RTL, landed at
    home after uavloc exited, the log complete."""
    import subprocess

    out_dir = tmp_path / "out"
    log_path = out_dir / "mission.jsonl"

    def rtt_records() -> int:
        return log_path.read_text().count('"type":"rtt"') if log_path.exists() else 0

    with Watcher(ardupilot.watch_port) as watch:
        proc = subprocess.Popen([sys.executable, "-m", "mission", "-q", "sim", SCENARIO, "--connect", ardupilot.url,
                                 "--out", str(out_dir), "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                cwd=Path(__file__).resolve().parents[1], text=True)
        try:
            _wait(lambda: rtt_records() >= 30 or proc.poll() is not None, MISSION_TIMEOUT_S, "30 measurements logged",
                  watch.describe)
            assert proc.poll() is None, "uavloc ended before Ctrl-C"
            proc.send_signal(signal.SIGINT)
            stdout, stderr = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        _wait(watch.landed_disarmed, 240, "ArduCopter landed and disarmed", watch.describe)
    assert proc.returncode == 130, stderr[-2000:]
    assert json.loads(stdout)["status"] == "interrupted"
    assert watch.modes[-1] == RTL, watch.describe()
    assert watch.home_offset_m() < LANDING_RADIUS_M, watch.describe()
    mlog = read_mission_log(log_path)
    assert len(mlog.rtt_t_s) >= 30 and mlog.skipped_torn_line is None
    kinds = [e.get("kind") for e in mlog.events]
    assert kinds[-3:] == ["interrupted", "rtl", "end"], kinds[-5:]
