"""The three-user mission flown by uavloc against real PX4 SITL (SIH quadrotor), started from
../shared/px4-sitl by the `px4` fixture (tests/conftest.py): end to end, and Ctrl-C mid-survey.

A second MAVLink client on PX4's GCS link (tests.px4.GcsClient) watches what PX4 does, so the
vehicle's side is checked from PX4's own reports, not from uavloc's.
"""

from __future__ import annotations

import asyncio
import json
import signal
import sys
from pathlib import Path

import numpy as np
import pytest

from mission.control.config import STATUS_TARGET
from mission.log import read_mission_log
from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission
from tests.px4 import GcsClient, wait_until
from tests.test_mission_e2e import assert_log_replays_to_the_result

pytestmark = pytest.mark.px4

SCENARIO = "three_users_nlos"
#: wall seconds a whole mission may take at speed factor 4 before the test fails (about 45 s
#: on an idle 2-core machine)
MISSION_TIMEOUT_S = 400.0
#: metres from home PX4 may land after RTL (its landing accuracy plus EKF2's position error)
LANDING_RADIUS_M = 5.0


def _events(path: Path) -> list[dict]:
    out = []
    for line in path.read_text().splitlines():
        obj = json.loads(line)
        if obj.get("type") == "event":
            out.append(obj)
    return out


def test_three_user_mission_on_px4_reaches_the_target_and_replays(px4, tmp_path):
    sc = load_scenario(SCENARIO)
    log_path = tmp_path / "mission.jsonl"

    async def fly():
        async with GcsClient(px4.gcs_url) as gcs:
            async with SimulatedMission(sc, log_path, connect=px4.api_url) as sim:
                result = await asyncio.wait_for(sim.run(), MISSION_TIMEOUT_S)
            await gcs.wait_for(lambda s: s.landed_disarmed(), 60, "PX4 landed and disarmed")
            return result, gcs.seen

    result, seen = asyncio.run(fly())
    assert result.status == STATUS_TARGET, (result.reason, result.events[-10:])
    err = result.error_m()
    assert err is not None and np.all(err <= sc.mission.flight.target_radius_m), err
    # the stop rule judged a batch refresh (estimator.refresh); the final answer is the cold batch
    # solve over every keyframe (the last few included), whose 95 % bound may come out a few per
    # cent either side (seen: 4.0016 m for 4 m)
    assert np.all(result.estimate.error_bound_95_m() <= 1.1 * sc.mission.flight.target_radius_m)
    assert result.rtl_sent and result.landed
    # PX4's side: it flew RTL home and landed there
    assert "RETURN_TO_LAUNCH" in seen.modes, seen.modes
    assert seen.text_with("RTL: start return"), seen.texts
    assert seen.home_offset_m() < LANDING_RADIUS_M
    # PX4's GPS error is not the built-in vehicle's: its correlation time is left to replay to
    # estimate from the telemetry (tens to hundreds of seconds, not the built-in vehicle's 3 s)
    assert "gps_tau_s" not in read_mission_log(log_path).header.noise.to_log_dict()
    # ... and the flight estimates it from the take-off's telemetry for its own estimator (PX4's
    # EKF output is smooth at the telemetry rate: seconds at least, not white)
    (tau,) = [e for e in _events(log_path) if e.get("kind") == "gps_tau"]
    assert tau.get("gps_tau_s", 0.0) > 10.0, tau
    kinds = [e.get("kind") for e in _events(log_path)]
    for kind in ("home", "arm", "takeoff", "speed", "stop", "rtl", "landed", "end"):
        assert kind in kinds, kind

    # the log replays to the same estimates (`uavloc replay`)
    assert_log_replays_to_the_result(log_path, result)


def test_ctrl_c_mid_survey_sends_px4_home_and_closes_the_log(px4, tmp_path):
    """SIGINT to `uavloc sim --connect` while surveying: exit code 130, RTL accepted by PX4, the
    vehicle lands at home, the log is complete."""
    out_dir = tmp_path / "out"
    log_path = out_dir / "mission.jsonl"

    def rtt_records() -> int:
        if not log_path.exists():
            return 0
        return log_path.read_text().count('"type":"rtt"')

    async def run():
        async with GcsClient(px4.gcs_url) as gcs:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "mission", "-q", "sim", SCENARIO, "--connect", px4.api_url,
                "--out", str(out_dir), "--json", stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
            try:
                await wait_until(lambda: rtt_records() >= 30 or proc.returncode is not None, MISSION_TIMEOUT_S,
                                 "30 measurements logged", gcs.describe)
                assert proc.returncode is None, "uavloc ended before Ctrl-C"
                assert gcs.seen.flight_mode == "HOLD" and gcs.seen.in_air_seen, gcs.describe()
                proc.send_signal(signal.SIGINT)
                stdout, stderr = await asyncio.wait_for(proc.communicate(), 120)
            finally:
                if proc.returncode is None:
                    proc.kill()
                    await proc.wait()
            # PX4 carries on with the RTL after uavloc exited
            await gcs.wait_for(lambda s: s.landed_disarmed(), 180, "PX4 landed and disarmed")
            return proc.returncode, stdout.decode(), stderr.decode(), gcs.seen

    code, stdout, stderr, seen = asyncio.run(run())
    assert code == 130, stderr[-2000:]
    doc = json.loads(stdout)
    assert doc["status"] == "interrupted"
    assert "RETURN_TO_LAUNCH" in seen.modes, seen.modes
    assert seen.text_with("RTL: start return"), seen.texts
    assert seen.home_offset_m() < LANDING_RADIUS_M
    # the log is complete: every line parses, the RTL PX4 accepted and the end are in it
    mlog = read_mission_log(log_path)
    assert len(mlog.rtt_t_s) >= 30 and mlog.skipped_torn_line is None
    events = _events(log_path)
    kinds = [e.get("kind") for e in events]
    assert "interrupted" in kinds and "rtl" in kinds, kinds
    assert events[-1]["kind"] == "end" and events[-1]["status"] == "interrupted"
