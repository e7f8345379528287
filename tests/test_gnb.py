"""Adapter <-> simulated gNB over real TCP on loopback: discovery, K users, both command sets,
every fault ending in a clear error or a retry, never a hang (every test runs under a timeout)."""

from __future__ import annotations

import asyncio
import random
from pathlib import Path

import numpy as np
import pytest

from estimator.ranging import C_MPS, one_way_m_per_ta_step
from mission.gnb import GnbClient, GnbConfig, LogFollower, OaiGnbClient, parse_host_port
from mission.gnb.oai import PROMPT_GNB, format_msg2_line, parse_force_reestab
from sitl_scenarios.gnb import GnbFaults, SimulatedGnb, static_position
from sitl_scenarios.scenario import bundled_scenarios, load_scenario, scenario_from_dict, user_tables
from uavloc.errors import (
    GnbBusyError,
    GnbError,
    GnbNoMeasurementError,
    GnbNoRandomAccessError,
    GnbProtocolError,
    GnbTimeoutError,
    GnbUnknownCommandError,
    MissionConfigError,
    ScenarioError,
    SimulatorError,
)

USERS = [
    {"id": "a", "rnti": "0x4601", "east_m": 60.0, "north_m": 45.0},
    {"id": "b", "rnti": "0xb0b2", "east_m": -80.0, "north_m": 20.0},
    {"id": "c", "rnti": "0x1234", "east_m": 10.0, "north_m": -120.0, "sawtooth_amplitude_m": 4.0},
    {"id": "far", "rnti": "0x0777", "east_m": 5000.0, "north_m": 0.0},  # beyond coverage
]
IN_COVERAGE = [0x1234, 0x4601, 0xB0B2]


def scenario(users=None, faults=None, **radio):
    data = {"name": "gnb-test", "seed": 7, **user_tables(users or USERS),
            "radio": {"coverage_m": 1000.0, "s0_m": 1.0, "ue_sawtooth_amplitude_m": 0.0, **radio}}
    if faults is not None:
        data["faults"] = faults
    return scenario_from_dict(data)


def run(coro, timeout_s: float = 10.0):
    """Run a test coroutine under a hard timeout: a hang is a failure, not a stuck test run."""

    async def guarded():
        async with asyncio.timeout(timeout_s):
            return await coro

    return asyncio.run(guarded())


def client_config(gnb: SimulatedGnb, **kw) -> GnbConfig:
    base = {"port": gnb.port, "request_timeout_s": 0.5, "connect_timeout_s": 0.5, "retries": 2,
            "backoff_initial_s": 0.005, "backoff_max_s": 0.02}
    base.update(kw)
    return GnbConfig(**base)


UAV = np.array([0.0, 0.0, 40.0])


# ---------------------------------------------------------------------------------------------
# discovery and measurement


def test_client_satisfies_protocol():
    assert isinstance(OaiGnbClient(GnbConfig()), GnbClient)


def test_discovery_by_o1_stats_lists_users_in_coverage():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb, discovery="o1")) as c:
            return await c.discover()

    assert run(body()) == IN_COVERAGE


def test_back_to_back_o1_stats_crash_the_simulated_gnb_as_they_crash_oai():
    """OAI 2025.w36 dies with SIGFPE on an `o1 stats` a few ms after the previous one (back to back
    on the real gNB: exit 136); the simulated gNB does too, and the client spaces its `o1 stats`
    (mission.gnb.O1_MIN_INTERVAL_S) across connections and clients, so discovering again and again
    from new clients leaves the gNB alive."""
    from mission.gnb import O1_MIN_INTERVAL_S

    async def raw(gnb):
        reader, writer = await asyncio.open_connection("127.0.0.1", gnb.port)
        writer.write(b"o1 stats\no1 stats\n")  # the second arrives within microseconds
        await writer.drain()
        data = await reader.read()  # the crash closes the connection
        writer.close()
        return data

    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb:
            await raw(gnb)
            back_to_back = gnb.crashed
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb:
            t0 = asyncio.get_running_loop().time()
            for _ in range(3):
                async with OaiGnbClient(client_config(gnb, discovery="o1")) as c:
                    await c.discover()
                    await c.discover()
            return back_to_back, gnb.crashed, asyncio.get_running_loop().time() - t0

    back_to_back, spaced, took_s = run(body())
    assert back_to_back is not None and "SIGFPE" in back_to_back
    assert spaced is None
    assert took_s >= 5 * O1_MIN_INTERVAL_S * 0.9  # six discoveries, five gaps


def test_discovery_single_rnti_and_auto_fallback_when_o1_missing():
    one = [USERS[0]]

    async def body():
        async with SimulatedGnb(scenario(one), static_position(UAV), port=0) as gnb:
            async with OaiGnbClient(client_config(gnb, discovery="single")) as c:
                single = await c.discover()
            # a gNB without the o1 module: `o1 stats` is not a softmodem command
            gnb.process = _without_module(gnb.process, "o1")
            async with OaiGnbClient(client_config(gnb, discovery="auto")) as c:
                auto = await c.discover()
            async with OaiGnbClient(client_config(gnb, discovery="o1")) as c:
                with pytest.raises(GnbUnknownCommandError, match="o1 stats"):
                    await c.discover()
            return single, auto

    assert run(body()) == ([0x4601], [0x4601])


def test_single_rnti_with_several_ues_is_a_clear_error():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb, discovery="single")) as c:
            with pytest.raises(GnbNoMeasurementError, match="not exactly one UE"):
                await c.discover()

    run(body())


def _without_module(process, module):
    from mission.gnb.oai import unknown_command_text

    def patched(line):
        if line.split() and line.split()[0] == module:
            return unknown_command_text(line)
        return process(line)

    return patched


def test_rtt_measurements_of_k_users_match_the_true_geometry():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb)) as c:
            rntis = await c.discover()
            samples = {r: [] for r in rntis}
            for _ in range(20):
                for r, s in (await c.measure_many(rntis)).items():
                    samples[r].append(s)
            return gnb, samples

    gnb, samples = run(body())
    sc = gnb.scenario
    for r, ss in samples.items():
        u = sc.user_by_rnti(r)
        d = float(np.linalg.norm(UAV - [u.east_m, u.north_m, u.up_m]))
        assert len(ss) == 20
        assert all(s.source == "rtt" and s.fs_hz == sc.radio.fs_hz and s.mu == sc.radio.mu for s in ss)
        t = [s.t_mono_s for s in ss]
        assert t == sorted(t)
        # σ = 1 m noise, plus a sawtooth of at most 4 m for user c
        err = np.array([s.range_m for s in ss]) - d
        assert np.all(np.abs(err - (2.0 if r == 0x1234 else 0.0)) < 7.0)
    # the simulator's truth log has one entry per answered measurement
    assert len(gnb.truth) == 60


def test_measure_unknown_or_out_of_coverage_user_is_no_measurement():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb)) as c:
            with pytest.raises(GnbNoMeasurementError, match="out of coverage"):
                await c.measure(0x0777)
            with pytest.raises(GnbNoMeasurementError, match="not connected"):
                await c.measure(0x0999)
            with pytest.raises(GnbError):
                await c.measure(0x10000)
            got = await c.measure_many([0x0777, 0x4601])
            return list(got)

    assert run(body()) == [0x4601]


def test_no_uav_position_yet_is_no_measurement():
    async def body():
        async with SimulatedGnb(scenario(), lambda: None, port=0) as gnb, OaiGnbClient(client_config(gnb)) as c:
            assert await c.discover() == sorted([0x4601, 0xB0B2, 0x1234, 0x0777])
            with pytest.raises(GnbNoMeasurementError, match="no UAV position"):
                await c.measure(0x4601)

    run(body())


def test_configurable_rtt_command_names():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, rtt_module="ranging",
                                rtt_command="trigger") as gnb:
            async with OaiGnbClient(client_config(gnb, rtt_module="ranging", rtt_command="trigger")) as c:
                s = await c.measure(0x4601)
            async with OaiGnbClient(client_config(gnb)) as c:  # default names: not loaded there
                with pytest.raises(GnbUnknownCommandError, match="rtt pdcch_order 4601"):
                    await c.measure(0x4601)
            return s

    assert run(body()).rnti == 0x4601


def test_stock_fallback_force_reestab_and_msg2_log(tmp_path: Path):
    log_path = tmp_path / "gnb.log"
    log_path.write_text("[NR_MAC]   old line, before the mark: timing_offset = 9 Msg2\n")

    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, log_path=log_path,
                                msg2_delay_s=0.02) as gnb, \
                OaiGnbClient(client_config(gnb, mode="stock", stock_mode="active", log_path=log_path,
                                           msg2_timeout_s=1.0)) as c:
            await c.discover()
            return [await c.measure(r) for r in (0x4601, 0xB0B2, 0x4601)]

    samples = run(body())
    step_m = one_way_m_per_ta_step(1)
    u = USERS[0]
    d = float(np.linalg.norm(UAV - [u["east_m"], u["north_m"], 0.0]))
    for s in (samples[0], samples[2]):
        assert s.source == "msg2" and s.fs_hz is None and s.srs_peak == 0.0 and s.rnti == 0x4601
        assert abs(s.range_m - d) <= step_m / 2 + 4 * 1.0  # nearest TA step, σ = 1 m noise
    assert samples[1].rnti == 0xB0B2
    assert log_path.read_text().count("Generating RA-Msg2") == 3


def test_stock_active_without_random_access_is_a_clear_no_measurement(tmp_path: Path):
    log_path = tmp_path / "gnb.log"

    async def body():
        # a UE without traffic: force_reestab is answered, no random access follows (OAI, no core)
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, log_path=log_path,
                                stock_reaction="none") as gnb, \
                OaiGnbClient(client_config(gnb, mode="stock", stock_mode="active", log_path=log_path,
                                           msg2_timeout_s=0.2)) as c:
            with pytest.raises(GnbNoRandomAccessError, match="no random access proven to be UE 4601"):
                await c.measure(0x4601)
            with pytest.raises(GnbNoMeasurementError, match="not sending `ci force_reestab ffff`"):
                await c.measure(0xFFFF)
            return gnb.crashed, c.ci_sent

    crashed, sent = run(body())
    assert crashed is None and sent == ["ci force_reestab 4601"]


def test_log_follower_partial_lines_and_rotation(tmp_path: Path):
    p = tmp_path / "gnb.log"
    f = LogFollower(p, poll_s=0.005)
    f.mark()  # file does not exist yet
    line = format_msg2_line(0x4601, 1, 2, 0x10B, 3, 5, 1)
    p.write_text(line[:30])
    assert f.read_lines() == []
    with p.open("a") as fh:
        fh.write(line[30:] + "\n")
    assert f.read_lines() == [line]
    p.write_text("")  # truncated (rotation)
    assert f.read_lines() == []
    p.write_text("a\nb\n")
    assert f.read_lines() == ["a", "b"]


# ---------------------------------------------------------------------------------------------
# wire behaviour of the simulator, seen with a bare socket


def test_simulator_wire_behaviour_matches_oai():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb:
            r, w = await asyncio.open_connection("127.0.0.1", gnb.port)
            # no prompt on connect
            with pytest.raises(TimeoutError):
                async with asyncio.timeout(0.1):
                    await r.read(1)
            w.write(b"\n")  # empty line: just the prompt
            assert await r.readuntil(PROMPT_GNB.encode()) == PROMPT_GNB.encode()
            w.write(b"foo bar\n")
            ans = (await r.readuntil(PROMPT_GNB.encode())).decode()
            assert ans == "Error: \n      foo bar\n is not a softmodem command\n" + PROMPT_GNB
            w.write(b"ci get_single_rnti extra\n")
            assert (await r.readuntil(PROMPT_GNB.encode())).decode().startswith("no parameter allowed")
            w.write(b"exit\n")
            assert await r.read() == b""  # closed
            w.close()

    run(body())


# ---------------------------------------------------------------------------------------------
# faults: each ends in a clear error or a retry, never a hang


def test_fault_delay_beyond_timeout_is_timeout_then_recovers():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb, request_timeout_s=0.2)) as c:
            await c.measure(0x4601)
            gnb.inject("delay", delay_s=0.6)
            with pytest.raises(GnbTimeoutError, match="within 0.2 s"):
                await c.measure(0x4601)
            assert not c.connected  # a late answer must not be read as the next one
            gnb.inject("delay", delay_s=0.05)  # a short delay is just slow
            return await c.measure(0x4601)

    assert run(body()).rnti == 0x4601


def test_fault_malformed_answers_are_protocol_errors_then_recover():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb)) as c:
            errors = []
            for _ in range(6):  # the simulator cycles through truncated, binary and bad-number answers
                gnb.inject("malformed")
                with pytest.raises(GnbProtocolError) as info:
                    await c.measure(0x4601)
                errors.append(str(info.value))
            gnb.inject("malformed")
            with pytest.raises(GnbProtocolError):
                await c.discover()
            return errors, await c.measure(0x4601)

    errors, sample = run(body())
    assert all(e for e in errors) and sample.rnti == 0x4601


def test_fault_dropped_connection_is_retried_transparently():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb, retries=3)) as c:
            await c.measure(0x4601)
            gnb.inject("drop", count=2)
            s = await c.measure(0x4601)
            return s, c.reconnects, gnb.connections

    s, reconnects, connections = run(body())
    assert s.rnti == 0x4601 and reconnects == 2 and connections == 3


def test_fault_drop_every_time_gives_up_with_clear_error():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb, retries=2)) as c:
            await c.measure(0x4601)  # not fresh any more
            gnb.inject("drop", count=1)
            gnb.inject("refuse", count=2)
            with pytest.raises(GnbError, match="after 3 attempts|one client at a time"):
                await c.measure(0x4601)

    run(body())


def _record_lines(gnb) -> list[str]:
    """Every request line the simulated gNB gets from now on, in order."""
    lines: list[str] = []
    process = gnb.process

    def recording(line: str):
        lines.append(line)
        return process(line)

    gnb.process = recording
    return lines


@pytest.mark.parametrize("first_discovers_again", [False, True])
def test_a_busy_gnb_queues_only_a_bare_line_from_a_new_connection(first_discovers_again):
    """OAI serves one client at a time and runs what a queued client sent when the client before it
    leaves, even after the queued one gave up and left (shared/data/oai-2025.w36/04_two_clients.txt).
    A new connection's first `o1 stats` is preceded by O1_SETTLE_REQUEST, a line OAI never parses
    and answers with the bare prompt: a client that gives up on a busy gNB leaves that queued, not
    an `o1 stats` to run microseconds before the next one (the SIGFPE) or into a closed socket (a
    SIGABRT of the real gNB)."""
    from mission.gnb import O1_SETTLE_REQUEST

    async def body():
        faults = GnbFaults(busy_mode="silent")
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, faults=faults) as gnb:
            lines = _record_lines(gnb)
            first = OaiGnbClient(client_config(gnb, discovery="o1"))
            await first.__aenter__()
            await first.discover()
            async with OaiGnbClient(client_config(gnb, discovery="o1", request_timeout_s=0.5, retries=0)) as second:
                with pytest.raises(GnbBusyError, match="one client at a time"):
                    await second.discover()  # queued behind `first`, abandoned
                if first_discovers_again:
                    await first.discover()
                again = asyncio.create_task(second.discover())  # a new connection, queued too
                await asyncio.sleep(0.1)
                await first.aclose()  # the gNB now runs the abandoned connection's line, then the new one's
                rntis = await again
            return rntis, gnb.crashed, lines

    rntis, crashed, lines = run(body())
    assert crashed is None
    assert rntis == sorted(IN_COVERAGE)
    # the first client (its later discovery on a served connection goes straight), then, once it
    # left, the abandoned connection's bare line and the new connection's
    first = [O1_SETTLE_REQUEST, "o1 stats"] + (["o1 stats"] if first_discovers_again else [])
    assert lines == [*first, "exit", O1_SETTLE_REQUEST, O1_SETTLE_REQUEST, "o1 stats", "exit"]


def test_an_o1_stats_abandoned_while_served_is_settled_before_the_next_one():
    """An `o1 stats` the gNB was slow to answer (here a delayed answer) and the client gave up on may
    still be running; a new connection asks O1_SETTLE_REQUEST first (answered only after it) and
    waits O1_MIN_INTERVAL_S from that answer before its own `o1 stats`."""
    from mission.gnb import O1_MIN_INTERVAL_S, O1_SETTLE_REQUEST

    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb:
            lines = _record_lines(gnb)
            async with OaiGnbClient(client_config(gnb, discovery="o1", request_timeout_s=0.3, retries=0)) as c:
                await c.discover()
                gnb.inject("delay", delay_s=1.0)
                with pytest.raises(GnbTimeoutError):
                    await c.discover()
                t0 = asyncio.get_running_loop().time()
                rntis = await c.discover()  # reconnects
                took_s = asyncio.get_running_loop().time() - t0
            return rntis, lines, took_s, gnb.crashed

    rntis, lines, took_s, crashed = run(body())
    assert crashed is None and rntis == sorted(IN_COVERAGE)
    assert lines == [O1_SETTLE_REQUEST, "o1 stats", "o1 stats", O1_SETTLE_REQUEST, "o1 stats", "exit"]
    assert took_s >= O1_MIN_INTERVAL_S


def test_refused_connections_are_reported_busy():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb:
            gnb.inject("refuse", count=10)
            async with OaiGnbClient(client_config(gnb, retries=2)) as c:
                with pytest.raises(GnbBusyError, match="one client at a time"):
                    await c.discover()

    run(body())


@pytest.mark.parametrize("busy_mode", ["close", "silent"])
def test_second_client_is_busy(busy_mode):
    async def body():
        faults = GnbFaults(busy_mode=busy_mode)
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, faults=faults) as gnb, \
                OaiGnbClient(client_config(gnb)) as first:
            await first.measure(0x4601)
            async with OaiGnbClient(client_config(gnb, request_timeout_s=0.2, retries=1)) as second:
                with pytest.raises(GnbBusyError, match="one client at a time"):
                    await second.measure(0x4601)
            return await first.measure(0x4601)  # the first client is unaffected

    assert run(body()).rnti == 0x4601


def test_server_not_running_is_a_clear_error():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb:
            port = gnb.port
        cfg = GnbConfig(port=port, retries=1, backoff_initial_s=0.001, connect_timeout_s=0.3)
        with pytest.raises(GnbError, match="cannot connect"):
            async with OaiGnbClient(cfg):
                pass

    run(body())


def test_fault_rates_from_the_scenario_faults_table():
    sc = scenario(faults={"gnb": {"malformed_rate": 0.3, "drop_rate": 0.2}, "vehicle": []})
    assert GnbFaults.from_scenario(sc) == GnbFaults(malformed_rate=0.3, drop_rate=0.2)

    async def body():
        async with SimulatedGnb(sc, static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb, retries=4)) as c:
            ok = bad = 0
            for _ in range(60):
                try:
                    await c.measure(0x4601)
                    ok += 1
                except GnbProtocolError:
                    bad += 1
            return ok, bad, c.reconnects

    ok, bad, reconnects = run(body(), timeout_s=20)
    # 30 % malformed, 20 % dropped and retried: both must have happened, nothing else escaped
    assert ok + bad == 60 and 8 <= bad <= 30 and reconnects >= 4


@pytest.mark.parametrize(
    "table",
    [{"delay": 1.0}, {"drop_rate": 1.5}, {"delay_s": -1}, {"busy_mode": "queue"}, {"malformed_rate": True}],
)
def test_fault_table_is_strict(table):
    with pytest.raises(ScenarioError):
        GnbFaults.from_table(table)


def test_inject_rejects_unknown_fault():
    gnb = SimulatedGnb(scenario(), static_position(UAV), port=0)
    with pytest.raises(SimulatorError):
        gnb.inject("explode")  # type: ignore[arg-type]


def test_jittered_backoff_is_seeded_and_bounded():
    async def delays(seed):
        c = OaiGnbClient(GnbConfig(backoff_initial_s=0.001, backoff_max_s=0.004), rng=random.Random(seed))
        out = []
        orig = asyncio.sleep

        async def fake_sleep(d):
            out.append(d)
            await orig(0)

        asyncio.sleep = fake_sleep  # type: ignore[assignment]
        try:
            for k in range(5):
                await c._backoff(k)
        finally:
            asyncio.sleep = orig  # type: ignore[assignment]
        return out

    a, b = run(delays(1)), run(delays(1))
    assert a == b
    caps = [0.001, 0.002, 0.004, 0.004, 0.004]
    assert all(cap / 2 <= d <= cap for d, cap in zip(a, caps, strict=True))


def test_parse_host_port():
    assert parse_host_port("10.0.0.2:9091") == ("10.0.0.2", 9091)
    assert parse_host_port("gnb.local") == ("gnb.local", 9090)
    with pytest.raises(GnbError):
        parse_host_port("host:abc")


def test_config_validation():
    with pytest.raises(GnbError, match="log_path"):
        GnbConfig(mode="stock")
    with pytest.raises(GnbError):
        GnbConfig(rtt_command="pdcch order")


@pytest.mark.parametrize("field, value", [("rtt_command", "pdcch-order"), ("rtt_module", "rtt;ci"),
                                          ("rtt_command", "pdcch order"), ("mode", "stock")])
def test_a_mission_file_and_the_adapter_refuse_the_same_gnb_settings(field, value):
    """One rule (GnbSettings.problems) for a mission file's [gnb] and the adapter's settings: what
    one refuses the other does, naming the same field."""
    import tomllib

    from mission.config import example_mission_path, mission_from_dict

    doc = tomllib.loads(example_mission_path().read_text())
    doc.setdefault("gnb", {})[field] = value
    with pytest.raises(MissionConfigError, match=f"gnb.{field}"):
        mission_from_dict(doc)
    with pytest.raises(GnbError, match=field):
        GnbConfig(**{field: value})


def test_request_refuses_multiline_input():
    with pytest.raises(GnbError):
        run(OaiGnbClient(GnbConfig()).request("o1 stats\nexit"))


def test_range_error_via_tcp_equals_truth_diagnostics():
    """The adapter's range equals the simulator's true range plus its recorded error, to the SRS
    quantization: the whole chain (model -> wire -> parser -> ranging) loses nothing else."""

    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb)) as c:
            out = []
            for _ in range(30):
                s = await c.measure(0xB0B2)
                out.append((s.range_m, gnb.truth[-1]))
            return out

    q = C_MPS / (2 * 46.08e6 * 8)
    for r, truth in run(body()):
        assert abs(r - (truth.true_range_m + truth.error_m)) <= q / 2 + 1e-3


def test_caller_cancellation_mid_request_does_not_desync_the_stream():
    """The controller wraps measure() in its own timeout: a late answer must not be taken as the
    answer to the next request."""

    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb, request_timeout_s=2.0)) as c:
            gnb.inject("delay", delay_s=0.3)
            with pytest.raises(TimeoutError):
                async with asyncio.timeout(0.1):
                    await c.measure(0x4601)
            assert not c.connected
            await asyncio.sleep(0.1)  # the simulator notices the client left (within ~10 ms)
            s = await c.measure(0xB0B2)
            stats = await c.discover()
            return s, stats

    s, stats = run(body())
    assert s.rnti == 0xB0B2 and stats == IN_COVERAGE


def test_stock_active_follows_a_new_rnti_only_through_the_reestablishment_line(tmp_path: Path):
    log_path = tmp_path / "gnb.log"

    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, log_path=log_path,
                                msg2_delay_s=0.01) as gnb, \
                OaiGnbClient(client_config(gnb, mode="stock", stock_mode="active", log_path=log_path,
                                           msg2_timeout_s=2.0)) as c:
            first = await c.measure(0x4601)
            alias1 = dict(c.rnti_alias)
            second = await c.measure(0x4601)  # triggers the UE under its new RNTI
            return first, second, alias1, dict(c.rnti_alias), list(gnb.current_rnti), list(c.ci_sent)

    first, second, alias1, alias2, current, sent = run(body())
    assert first.rnti == second.rnti == 0x4601
    (new1,) = alias1.values()
    assert alias1 == {0x4601: new1} and alias2 == {0x4601: new1, new1: current[0]}
    assert sent == ["ci force_reestab 4601", f"ci force_reestab {new1:04x}"]
    text = log_path.read_text()
    assert f"Reestablishment RNTI {new1:04x} req C-RNTI 4601" in text


def test_stock_active_rejects_the_connected_mode_access_and_an_unproven_new_ue(tmp_path: Path):
    """The recorded OAI case: after the trigger, a C-RNTI RA with timing_offset 0 (a residual), then
    an idle re-attach under a new RNTI that no line ties to the UE: no range, and a message."""
    log_path = tmp_path / "gnb.log"

    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, log_path=log_path,
                                stock_reaction="crnti_then_idle", msg2_delay_s=0.01, reattach_delay_s=0.05) as gnb, \
                OaiGnbClient(client_config(gnb, mode="stock", stock_mode="active", log_path=log_path,
                                           msg2_timeout_s=0.5)) as c:
            with pytest.raises(GnbNoRandomAccessError) as info:
                await c.measure(0x4601)
            kinds = [ra.kind for ra in c.recent_accesses]
            # the stale RNTI is still listed by o1 stats while the gNB keeps the old context; once
            # dropped, a trigger for it is not sent (the recorded gNB segfaulted on exactly this)
            await asyncio.sleep(gnb.linger_s + 0.05)
            with pytest.raises(GnbNoMeasurementError, match="not sending"):
                await c.measure(0x4601)
            return str(info.value), kinds, gnb.crashed, c.ci_sent

    msg, kinds, crashed, sent = run(body())
    assert "connected-mode (C-RNTI) RA of UE 4601" in msg and "initial access of UE" in msg
    assert kinds == ["connected", "initial"] and crashed is None
    assert sent == ["ci force_reestab 4601"]
    assert log_path.read_text().count("Generating RA-Msg2") == 2


def test_stock_passive_takes_each_ues_own_initial_access_with_its_time_stamp(tmp_path: Path):
    log_path = tmp_path / "gnb.log"
    wall0 = 1_796_145_128.0

    async def body():
        t = {"wall": wall0}
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, log_path=log_path,
                                wall=lambda: t["wall"]) as gnb, \
                OaiGnbClient(client_config(gnb, mode="stock", stock_mode="passive", log_path=log_path),
                             wall=lambda: t["wall"] + 2.0) as c:
            with pytest.raises(GnbNoRandomAccessError, match="passive"):
                await c.measure(0x4601)
            gnb.crnti_access(0)           # a residual: never a range
            new_a = gnb.reattach(0)       # user a re-attaches under a new RNTI
            gnb.reattach(1)               # another UE's access in between
            gnb.crnti_access(2)
            sample = await c.measure(new_a)
            with pytest.raises(GnbNoRandomAccessError):
                await c.measure(new_a)    # consumed; nothing new
            with pytest.raises(GnbNoRandomAccessError):
                await c.measure(0x4601)   # nothing ties the old RNTI to the new one
            return sample, new_a, c.ci_sent, [ra.kind for ra in c.recent_accesses]

    sample, new_a, sent, kinds = run(body())
    u = USERS[0]
    d = float(np.linalg.norm(UAV - [u["east_m"], u["north_m"], 0.0]))
    assert sample.rnti == new_a and sample.source == "msg2"
    assert abs(sample.range_m - d) <= one_way_m_per_ta_step(1) / 2 + 4.0
    assert sample.t_wall_s == pytest.approx(wall0, abs=1e-5)
    assert sent == [] and kinds == ["connected", "initial", "initial", "connected"]


def test_ci_commands_that_crash_stock_oai_are_refused_by_the_client():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb, \
                OaiGnbClient(client_config(gnb)) as c:
            for line in ("ci force_reestab 1234", "ci force_ue_release", "ci force_ue_release 4601",
                         "ci force_ul_failure 4601", "ci get_current_bwp 1234"):
                with pytest.raises(GnbError, match="refusing"):
                    await c.request(line)
            with pytest.raises(GnbError, match="refusing"):
                await c.guarded_ci("force_ue_release", 0x4601)
            answer = await c.guarded_ci("get_current_bwp", 0x4601)
            return answer, gnb.crashed, gnb.requests

    answer, crashed, requests = run(body())
    assert answer.startswith("UE 4601 DL BWP") and crashed is None and requests == 3  # bare line, o1 stats, ci


def test_simulated_gnb_crashes_like_oai_on_an_unknown_rnti():
    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb:
            r, w = await asyncio.open_connection("127.0.0.1", gnb.port)
            w.write(b"ci force_reestab\n")  # several UEs: OAI's two-line failure
            two = (await r.readuntil(PROMPT_GNB.encode())).decode()
            w.write(b"ci force_reestab fffe\n")
            bad = (await r.readuntil(PROMPT_GNB.encode())).decode()
            w.write(b"ci force_reestab 2345\n")
            eof = await r.read()
            w.close()
            with pytest.raises(OSError):
                await asyncio.open_connection("127.0.0.1", gnb.port)
            return two, bad, eof, gnb.crashed

    two, bad, eof, crashed = run(body())
    assert two == "no UE found\ncould not identify UE (no UE, no such RNTI, or multiple UEs)\n" + PROMPT_GNB
    assert bad.startswith("RNTI needs to be [1,0xfffe]\ncould not identify UE")
    assert parse_force_reestab(two[: -len(PROMPT_GNB)]).rnti is None
    assert eof == b"" and "force_reestab 2345" in crashed


def test_killed_gnb_is_a_clear_error_and_double_exit_is_harmless():
    async def body():
        gnb = SimulatedGnb(scenario(), static_position(UAV), port=0)
        await gnb.__aenter__()
        async with OaiGnbClient(client_config(gnb, retries=1)) as c:
            await c.measure(0x4601)
            await gnb.__aexit__(None, None, None)  # the gNB dies under the client
            await gnb.__aexit__(None, None, None)
            with pytest.raises(GnbError, match="cannot connect|closed every new connection|after 2 attempts"):
                await c.measure(0x4601)

    run(body())


@pytest.mark.parametrize("path", bundled_scenarios(), ids=lambda p: p.stem)
def test_every_bundled_scenario_serves_its_users(path):
    sc = load_scenario(path)

    async def body():
        async with SimulatedGnb(sc, static_position((0.0, 0.0, sc.mission.flight.altitude_m)), port=0,
                                faults=GnbFaults()) as gnb, OaiGnbClient(client_config(gnb)) as c:
            rntis = await c.discover()
            return rntis, await c.measure_many(rntis)

    rntis, got = run(body())
    assert rntis and set(got) <= set(rntis)
    assert GnbFaults.from_scenario(sc) is not None  # its [faults.gnb] table (if any) is valid


# ---------------------------------------------------------------------------------------------
# preflight probe (mission.gnb.probe), the library behind `uavloc gnb probe`


def test_probe_measures_every_configured_user_and_names_what_is_missing():
    from mission.gnb.probe import probe_gnb

    pos = {"uav": UAV}

    async def body():
        async with SimulatedGnb(scenario(), lambda: pos["uav"], port=0) as gnb, \
                OaiGnbClient(client_config(gnb)) as c:
            good = await probe_gnb(c, rntis=[0x4601, 0xB0B2], count=3)
            every = await probe_gnb(c, count=1)
            pos["uav"] = None  # the gNB lists every UE but measures none
            bad = await probe_gnb(c, rntis=[0x4601, 0x0046], count=1)
            return good, bad, every

    good, bad, every = run(body())
    assert good.ok and [len(u.samples) for u in good.ues] == [3, 3] and good.problems == []
    assert all(abs(s.range_m - 75.0) < 60 for s in good.ues[0].samples)  # sanity: a range, metres
    assert not bad.ok
    msg = bad.message()
    assert "the gNB has 4 UE(s): [0777, 1234, 4601, b0b2]" in msg
    assert "UE 0046 is not among them" in msg
    assert "UE 4601: no measurement (gNB has no RTT for RNTI 4601: error rnti 4601 no UAV position)" in msg
    assert [u.rnti for u in every.ues] == [0x1234, 0x4601, 0xB0B2] and every.ok  # 0777: out of coverage
    doc = bad.to_dict()
    assert doc["gnb_rntis"] == ["0777", "1234", "4601", "b0b2"] and doc["ues"][1]["present"] is False


def test_probe_says_what_is_wrong_with_the_setup(tmp_path: Path):
    from mission.gnb.probe import probe_address, probe_gnb

    async def body():
        out = {}
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, rtt_module="ranging") as gnb:
            out["module"] = await probe_address(client_config(gnb), rntis=[0x4601])
            port = gnb.port
        out["server"] = await probe_address(GnbConfig(port=port, retries=0, connect_timeout_s=0.5))
        far = [USERS[3]]  # its only UE out of coverage: o1 stats lists none
        async with SimulatedGnb(scenario(far), static_position(UAV), port=0) as gnb:
            out["no_ue"] = await probe_address(client_config(gnb))
        log_path = tmp_path / "gnb.log"
        log_path.write_text("12.000001 [NR_MAC] I Frame.Slot 128.0\n")  # `time` stamps: monotonic
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, log_path=log_path,
                                stock_reaction="none") as gnb, \
                OaiGnbClient(client_config(gnb, mode="stock", stock_mode="active", log_path=log_path,
                                           msg2_timeout_s=0.1)) as c:
            out["stock"] = await probe_gnb(c, rntis=[0x4601])
        return out

    out = run(body())
    assert "wrong telnet module" in out["module"].message() and "rtt pdcch_order 4601" in out["module"].message()
    assert "no telnet server" in out["server"].message() and out["server"].gnb_rntis is None
    assert "no UE is connected" in out["no_ue"].message()
    stock = out["stock"].message()
    assert "no wall_clock time stamps (found 'monotonic')" in stock and "no random access seen" in stock
    assert all(not r.ok for r in out.values())


def test_gnb_probe_command_json_and_exit_status(capsys):
    import json

    from mission.cli import main

    async def serve(argv):
        async with SimulatedGnb(scenario(), static_position(UAV), port=0) as gnb:
            return await asyncio.to_thread(main, ["gnb", "probe", "--gnb", f"127.0.0.1:{gnb.port}", *argv])

    assert run(serve(["--rnti", "4601", "--count", "2", "--json"])) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and len(doc["ues"][0]["samples"]) == 2 and doc["ues"][0]["samples"][0]["fs_hz"] == 46.08e6
    assert run(serve(["--rnti", "4601", "--rnti", "46"])) == 1
    out = capsys.readouterr().out
    assert out.startswith("gNB not ready") and "UE 0046 is not among them" in out and "#2: range" in out
    assert main(["gnb", "probe", "--gnb", "127.0.0.1:1", "--mode", "stock"]) == 1  # no --gnb-log: an error


def test_probe_in_passive_mode_lists_each_ues_accesses(tmp_path: Path):
    from mission.gnb.probe import probe_gnb

    log_path = tmp_path / "gnb.log"

    async def body():
        async with SimulatedGnb(scenario(), static_position(UAV), port=0, log_path=log_path) as gnb:
            a = gnb.reattach(0)
            gnb.crnti_access(1)  # a residual only: nothing for b
            gnb.reattach(0)      # a again, under yet another RNTI
            cfg = client_config(gnb, mode="stock", stock_mode="passive", log_path=log_path, log_history=True)
            async with OaiGnbClient(cfg) as c:
                return a, gnb.current_rnti[0], await probe_gnb(c, count=3)

    a, a2, res = run(body())
    by = {u.rnti: u for u in res.ues}
    assert len(by[a].samples) == 1 and len(by[a2].samples) == 1 and not by[0xB0B2].samples
    assert "no random access seen" in by[0xB0B2].errors[0] and not res.ok
    assert res.log_stamps == "wall_clock" and "random access(es) in the log" in "\n".join(res.lines())
