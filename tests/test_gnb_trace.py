"""The trace mode end to end against the simulated gNB's T server: the client, the probe, `uavloc
gnb probe --mode trace`, and a whole mission (the real gNB's recordings: tests/test_ttrace.py)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from estimator.ranging import C_MPS
from mission.gnb import GnbConfig, OaiGnbClient
from mission.gnb.probe import probe_address
from mission.gnb.tracer import TTracerClient
from mission.gnb.ttrace import parse_t_messages
from sitl_scenarios.gnb import SimulatedGnb, static_position
from sitl_scenarios.gnb.ttrace import SIM_T_MESSAGES
from sitl_scenarios.scenario import scenario_from_dict, user_tables
from uavloc.errors import GnbError, GnbNoMeasurementError

REPO = Path(__file__).resolve().parents[1]
UAV_ENU_M = (30.0, -40.0, 40.0)


def _scenario(noise_m: float = 1e-3, sawtooth_m: float = 0.0):
    users = [{"id": f"u{i}", "rnti": 0x4601 + i, "east_m": e, "north_m": n, "sawtooth_amplitude_m": sawtooth_m}
             for i, (e, n) in enumerate([(120.0, 80.0), (-200.0, 150.0), (10.0, 300.0)])]
    return scenario_from_dict({"name": "trace", "seed": 3, **user_tables(users), "radio": {"s0_m": noise_m}})


def _true_range_m(sc, k: int) -> float:
    u = sc.users[k]
    return float(np.linalg.norm(np.array(UAV_ENU_M) - np.array([u.east_m, u.north_m, u.up_m])))


def test_the_simulated_t_server_has_its_own_ids():
    """Ids come from the server's T_messages.txt: the simulated gNB's differ from OAI 2025.w36's."""
    db = parse_t_messages(SIM_T_MESSAGES)
    assert db.id_of("GNB_PHY_UL_TIME_CHANNEL_ESTIMATE") != 34 and db.id_of("GNB_MAC_DL_PDU_WITH_DATA") != 48


def test_trace_mode_measures_every_ue_to_the_sample():
    """No noise, no sawtooth: every UE's range to the SRS quantization (3.26 m at 46.08 Msps)."""
    sc = _scenario()

    async def main():
        async with SimulatedGnb(sc, static_position(UAV_ENU_M), port=0, t_port=0) as gnb:
            cfg = GnbConfig(port=gnb.port, t_port=gnb.t_port, mode="trace", fs_hz=sc.radio.fs_hz)
            async with OaiGnbClient(cfg) as client:
                assert client.tracer is not None and client.mode == "trace"
                out = {}
                for _ in range(100):
                    await client.tracer.wait_for_events(0.2)
                    for r in await client.discover():
                        with contextlib.suppress(GnbNoMeasurementError):
                            out[r] = await client.measure(r)
                    if len(out) == 3:
                        break
                # the same SRS occasion is never handed out twice
                with pytest.raises(GnbNoMeasurementError, match="no new SRS"):
                    await client.measure(0x4601)
                return out, client.tracer.status()

    out, st = asyncio.run(main())
    assert len(out) == 3 and st.connected and st.srs > 0 and not st.missing_events
    one_sample_m = C_MPS / (2 * sc.radio.fs_hz)
    for k in range(3):
        s = out[0x4601 + k]
        assert s.source == "trace" and s.t_wall_s is not None
        assert abs(s.range_m - _true_range_m(sc, k)) <= one_sample_m, (k, s)


def test_a_dropped_t_connection_is_reopened():
    sc = _scenario()

    async def main():
        async with SimulatedGnb(sc, static_position(UAV_ENU_M), port=0, t_port=0) as gnb, \
                TTracerClient("127.0.0.1", gnb.t_port, backoff_initial_s=0.01) as client:
            assert await client.wait_for_events(2.0)
            for w in list(gnb.t_server._writers):
                w.close()
            for _ in range(100):
                await asyncio.sleep(0.05)
                if client.reconnects:
                    break
            assert await client.wait_for_events(2.0)
            return client.reconnects, client.status()

    reconnects, st = asyncio.run(main())
    assert reconnects >= 1 and st.connected


def test_no_t_server_is_a_clear_error():
    sc = _scenario()

    async def main():
        async with SimulatedGnb(sc, static_position(UAV_ENU_M), port=0) as gnb:
            cfg = GnbConfig(port=gnb.port, t_port=1, mode="trace", connect_timeout_s=0.5, retries=0)
            with pytest.raises(GnbError, match=r"no T tracer at 127.0.0.1:1 .*--T_stdout 2 --T_nowait"):
                async with OaiGnbClient(cfg):
                    pass
            # auto: the RTT command answers first, and the probe says what else the gNB serves
            res = await probe_address(GnbConfig(port=gnb.port, t_port=1, mode="auto", connect_timeout_s=0.5), count=1)
            return res

    res = asyncio.run(main())
    assert res.ok and res.mode == "rtt" and res.recommended == "rtt"
    assert res.modes["trace"][0] is False and "no T tracer" in res.modes["trace"][1]


def test_uavloc_gnb_probe_mode_trace_exits_0(tmp_path):
    """`uavloc gnb probe --mode trace` against `python -m sitl_scenarios.gnb --t-port`."""
    from tests.procs import standalone_trace_gnb

    with standalone_trace_gnb("three_users_nlos", REPO) as (port, t_port):
        proc = subprocess.run([sys.executable, "-m", "mission", "gnb", "probe", "--gnb", f"127.0.0.1:{port}",
                               "--mode", "trace", "--t-port", t_port, "--count", "2", "--json"],
                              cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["ok"] and doc["mode"] == "trace" and doc["trace"]["srs"] > 0
    assert doc["modes"]["trace"]["served"] and doc["recommended"] == "rtt"
    assert {u["rnti"] for u in doc["ues"]} == {"4601", "4602", "4603"}
    assert all(len(u["samples"]) == 2 and all(math.isfinite(s["range_m"]) for s in u["samples"]) for u in doc["ues"])


@pytest.mark.sim
def test_a_mission_flown_in_trace_mode_reaches_its_target(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "mission", "-q", "sim", "paper", "--gnb-mode", "trace", "--seed", "2",
                           "--speedup", "20", "--json", "--out", str(tmp_path / "out")],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    doc = json.loads(proc.stdout)
    assert doc["status"] == "target_reached"
    for u in doc["users"]:
        # a 95 % bound: beyond it in about one run in twenty (this run's timing is the wall clock's)
        assert u["error_m"] <= 1.5 * u["error_bound_95_m"], u
    header = json.loads((tmp_path / "out" / "mission.jsonl").read_text().splitlines()[0])
    assert header["config"]["gnb_mode"] == "trace"


def test_a_campaign_spec_names_the_gnb_mode_of_its_full_runs():
    from sitl_scenarios.campaign.spec import spec_from_dict
    from uavloc.errors import CampaignError

    def spec(**campaign):
        return spec_from_dict({"campaign": {"name": "t", "planners": ["lawnmower"], **campaign},
                               "scenarios": [{"file": "paper"}]})

    rtt, trace = spec(mode="full"), spec(mode="full", gnb_mode="trace")
    assert [r.gnb_mode for r in rtt.runs + trace.runs] == ["rtt", "trace"]
    assert rtt.runs[0].key != trace.runs[0].key
    with pytest.raises(CampaignError, match="only full mode"):
        spec(mode="fast", gnb_mode="trace")
    with pytest.raises(CampaignError, match="'rtt' or 'trace'"):
        spec(mode="full", gnb_mode="stock")

