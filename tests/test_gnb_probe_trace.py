"""`uavloc gnb probe` in trace and auto mode says what it sees (issues 49, 50): it waits, its T
client connected, for UEs to attach; it says how to re-attach a UE that attached before the trace;
it names the side that failed (the T port, not the telnet server); `auto` recommends only a mode it
saw answer, and says the same about the T tracer in both its lines; and in trace mode the client
does not hold the gNB's telnet server (OAI's serves one client at a time) between requests."""

from __future__ import annotations

import asyncio
import contextlib
import time

import numpy as np

from mission.gnb import GnbConfig, OaiGnbClient
from mission.gnb.probe import probe_address, probe_gnb
from mission.gnb.tracer import TraceStatus, trace_served_why
from sitl_scenarios.gnb import SimulatedGnb, static_position
from sitl_scenarios.scenario import scenario_from_dict, user_tables
from uavloc.errors import GnbBusyError

UAV_ENU_M = (30.0, -40.0, 40.0)
#: far beyond every user's coverage (1 500 m): the gNB lists no UE, the T server makes no random access
FAR_ENU_M = (50_000.0, 0.0, 40.0)


def _scenario():
    users = [{"id": f"u{i}", "rnti": 0x4601 + i, "east_m": e, "north_m": n, "sawtooth_amplitude_m": 0.0}
             for i, (e, n) in enumerate([(120.0, 80.0), (-200.0, 150.0)])]
    return scenario_from_dict({"name": "probe", "seed": 3, **user_tables(users), "radio": {"s0_m": 1e-3}})


def run(coro, timeout_s: float = 60.0):
    async def guarded():
        async with asyncio.timeout(timeout_s):
            return await coro

    return asyncio.run(guarded())


def test_the_probe_waits_for_ues_to_attach_while_its_t_client_is_connected():
    """Started before the attach (the gNB lists no UE): the probe waits, says so on its progress
    line, sees each UE's random access when it comes and gives its ranges; exit status 0."""
    sc = _scenario()
    where = {"enu": np.array(FAR_ENU_M)}
    lines: list[str] = []

    async def body():
        async with SimulatedGnb(sc, lambda: where["enu"].copy(), port=0, t_port=0) as gnb:
            cfg = GnbConfig(port=gnb.port, t_port=gnb.t_port, mode="trace", fs_hz=sc.radio.fs_hz)

            async def attach_later():
                await asyncio.sleep(2.5)
                where["enu"] = np.array(UAV_ENU_M)

            task = asyncio.create_task(attach_later())
            t0 = time.monotonic()
            res = await probe_address(cfg, count=2, wait_s=30.0, progress=lines.append)
            await task
            return res, time.monotonic() - t0

    res, took_s = run(body())
    assert res.ok, res.lines()
    assert {u.rnti for u in res.ues} == {0x4601, 0x4602} and all(len(u.samples) == 2 for u in res.ues)
    assert 2.5 <= took_s < 20.0
    assert lines and "the gNB lists no UE yet: attach them now" in lines[0] and "0 random access" in lines[0]
    assert res.trace is not None and res.trace.connected


def test_no_ue_within_the_wait_says_it_waited_and_how_long():
    sc = _scenario()

    async def body():
        async with SimulatedGnb(sc, static_position(FAR_ENU_M), port=0, t_port=0) as gnb:
            cfg = GnbConfig(port=gnb.port, t_port=gnb.t_port, mode="trace")
            return await probe_address(cfg, count=1, wait_s=3.0)

    res = run(body())
    assert not res.ok and res.gnb_rntis == []
    assert any(p.startswith("no UE is connected to the gNB (waited 3 s with the T client connected")
               for p in res.problems), res.problems


def test_a_ue_attached_before_the_trace_began_is_named_with_how_to_reattach_it():
    """The second probe of one stock gNB (no PDCCH order: its RTT command named otherwise): its UEs
    attached while the first one's T client was connected, so the second sees their SRS but not
    their random access."""
    sc = _scenario()
    lines: list[str] = []

    async def body():
        async with SimulatedGnb(sc, static_position(UAV_ENU_M), port=0, t_port=0, rtt_command="stock") as gnb:
            cfg = GnbConfig(port=gnb.port, t_port=gnb.t_port, mode="trace", fs_hz=sc.radio.fs_hz)
            first = await probe_address(cfg, count=1, wait_s=10.0)
            second = await probe_address(cfg, rntis=[0x4601], count=1, wait_s=4.5, progress=lines.append)
            return first, second

    first, second = run(body())
    assert first.ok, first.lines()
    assert not second.ok
    (u,) = second.ues
    assert u.present and not u.samples
    said = u.errors[-1]
    assert "UE 4601 attached before the T trace began" in said and "`ciUE force_RRC_IDLE`" in said
    assert "restart the nrUE" in said and "after waiting" in said
    assert any("attached before the T trace began" in line for line in lines), lines
    assert "UE 4601: no measurement" in second.message()


def test_a_ue_attached_before_the_trace_began_gets_a_pdcch_order_when_the_gnb_serves_it():
    """The same on a gNB that serves `rtt pdcch_order` (patches/oai-2025.w36; here the simulated
    one): the second probe orders the UE once, the ordered access's RAR comes on the T trace, and
    the UE is ranged from the trace, its first range checked against the order's answer."""
    sc = _scenario()

    async def body():
        async with SimulatedGnb(sc, static_position(UAV_ENU_M), port=0, t_port=0) as gnb:
            cfg = GnbConfig(port=gnb.port, t_port=gnb.t_port, mode="trace", fs_hz=sc.radio.fs_hz)
            first = await probe_address(cfg, count=1, wait_s=10.0)
            async with OaiGnbClient(cfg) as client:
                second = await probe_gnb(client, rntis=[0x4601], count=2, wait_s=10.0)
                return first, second, client.drain_trace_orders(), client.tracer.tracker.counts.rars

    first, second, orders, rars = run(body())
    assert first.ok and second.ok, second.lines()
    assert [o.what for o in orders] == ["ordered", "agree"] and rars == 1, orders
    assert "attached before the T trace began" in orders[0].message and "PDCCH order" in orders[0].message
    (u,) = second.ues
    true_m = float(np.linalg.norm(np.array(UAV_ENU_M) - np.array([120.0, 80.0, 0.0])))
    assert all(abs(s.range_m - true_m) < 10.0 for s in u.samples) and all(s.source == "trace" for s in u.samples)


def test_a_t_tracer_failure_is_not_called_no_telnet_server():
    """The telnet server is up and the T port is not: the problem names the T tracer and says the
    telnet server answered."""
    sc = _scenario()

    async def body():
        async with SimulatedGnb(sc, static_position(UAV_ENU_M), port=0) as gnb:
            cfg = GnbConfig(port=gnb.port, t_port=1, mode="trace", connect_timeout_s=0.5, retries=0)
            return gnb.port, await probe_address(cfg, count=1)

    port, res = run(body())
    (problem,) = res.problems
    assert problem.startswith(f"T tracer failed (the telnet server at 127.0.0.1:{port} answered): no T tracer at "
                              "127.0.0.1:1"), problem
    assert "no telnet server" not in problem


def test_no_telnet_server_is_still_called_so():
    async def body():
        server = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        server.close()
        await server.wait_closed()
        return await probe_address(GnbConfig(port=port, mode="trace", connect_timeout_s=0.5, retries=0), count=1)

    res = run(body())
    assert res.problems[0].startswith("no telnet server:"), res.problems


def test_auto_with_no_ue_says_the_same_of_the_t_tracer_in_both_lines():
    """No UE attached: no RTT command to try, the T tracer answers with the SRS event in its
    T_messages.txt and no SRS yet; the mode line and the served line agree."""
    sc = _scenario()

    async def body():
        async with SimulatedGnb(sc, static_position(FAR_ENU_M), port=0, t_port=0) as gnb:
            return await probe_address(GnbConfig(port=gnb.port, t_port=gnb.t_port, mode="auto"), count=1)

    res = run(body())
    assert res.mode == "trace" and res.modes["rtt"] == (False, "no UE to try the RTT command on")
    served, why = res.modes["trace"]
    assert served and "no SRS event yet" in why and "no SRS event yet" in res.mode_reason
    text = "\n".join(res.lines())
    assert "not served (no SRS" not in text and "with SRS events" not in text
    assert res.recommended == "trace"


def test_the_trace_reason_with_ues_listed_does_not_say_none_comes_before_an_attach():
    """Measured on OAI 2025.w36: `--mode auto` chose trace the moment its T client connected, a UE
    already attached, and said "none comes before a UE attaches with SRS"; with UEs listed it says
    the client has just connected."""
    st = TraceStatus("127.0.0.1:2021", True, 0, (), True, 3, 0, 0, 0.1, "")
    assert "none comes before a UE attaches" in trace_served_why(st)
    with_ue = trace_served_why(st, ues=1)
    assert "just connected" in with_ue and "1 UE(s)" in with_ue and "none comes before" not in with_ue
    assert "12 SRS events so far" in trace_served_why(TraceStatus("a", True, 0, (), True, 12, 12, 0, 0.1, ""), 1)


def test_trace_mode_does_not_hold_the_telnet_server_between_requests():
    """OAI's telnet server serves one client at a time: a user's own telnet session (here one
    request on a fresh connection, with no retry) gets through while the trace-mode client runs,
    and is kept out while an rtt-mode client holds the connection."""
    sc = _scenario()

    async def body():
        async with SimulatedGnb(sc, static_position(UAV_ENU_M), port=0, t_port=0) as gnb:
            user = GnbConfig(port=gnb.port, retries=0, request_timeout_s=1.0)
            cfg = GnbConfig(port=gnb.port, t_port=gnb.t_port, mode="trace")
            async with OaiGnbClient(cfg) as trace_client:
                assert not trace_client.connected and not trace_client.holds_connection
                rntis = await trace_client.discover()
                assert not trace_client.connected
                async with OaiGnbClient(user) as other:
                    got = await other.discover()
            held = None
            async with OaiGnbClient(GnbConfig(port=gnb.port, mode="rtt")) as rtt_client:
                await rtt_client.discover()
                assert rtt_client.connected and rtt_client.holds_connection
                with contextlib.suppress(GnbBusyError):
                    async with OaiGnbClient(user) as other:
                        held = await other.discover()
            return rntis, got, held

    rntis, got, held = run(body())
    assert rntis == got == [0x4601, 0x4602]
    assert held is None


def test_the_waiting_trace_probe_asks_again_while_a_user_holds_the_telnet_server():
    """A user's telnet session holds the gNB's one telnet client slot for 3 s while the trace probe
    starts (its requests time out after 1 s): the probe's discoveries meet a busy server, it asks
    again, and gives its ranges once the user leaves (a concurrent `rfsimu setdistance` on a real
    gNB must not end the probe)."""
    sc = _scenario()

    async def body():
        async with SimulatedGnb(sc, static_position(UAV_ENU_M), port=0, t_port=0) as gnb:
            cfg = GnbConfig(port=gnb.port, t_port=gnb.t_port, mode="trace", fs_hz=sc.radio.fs_hz,
                            request_timeout_s=1.0, retries=0)
            async with OaiGnbClient(GnbConfig(port=gnb.port, mode="rtt")) as user:
                await user.discover()
                assert user.holds_connection
                probe = asyncio.create_task(probe_address(cfg, count=2, wait_s=20.0))
                await asyncio.sleep(3.0)
                assert not probe.done()
            return await probe

    res = run(body())
    assert res.ok, res.lines()
    assert [u.rnti for u in res.ues] == [0x4601, 0x4602] and all(len(u.samples) == 2 for u in res.ues)


def test_uavloc_gnb_probe_says_on_stderr_what_it_waits_for():
    """`uavloc gnb probe --mode trace` against `python -m sitl_scenarios.gnb --t-port 0` (a stock
    gNB: no `rtt pdcch_order`): the first probe sees the UEs attach (exit 0); the second, started
    after, prints its waiting line on stderr and exits 1 naming the UE that attached before the T
    trace began and how to re-attach it."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    from tests.procs import standalone_trace_gnb

    with standalone_trace_gnb("paper", repo, "--rtt-command", "stock") as (port, t_port):
        probe = [sys.executable, "-m", "mission", "gnb", "probe", "--gnb", f"127.0.0.1:{port}", "--mode", "trace",
                 "--t-port", t_port, "--count", "1", "--json"]
        first = subprocess.run([*probe, "--wait", "20"], cwd=repo, capture_output=True, text=True, timeout=60)
        second = subprocess.run([*probe, "--wait", "4.5"], cwd=repo, capture_output=True, text=True, timeout=60)
    assert first.returncode == 0, first.stdout + first.stderr
    assert second.returncode == 1, second.stdout + second.stderr
    assert "gnb probe: waiting for UEs" in second.stderr and "attached before the T trace began" in second.stderr
    doc = json.loads(second.stdout)
    assert "attached before the T trace began" in doc["message"] and "ciUE force_RRC_IDLE" in doc["message"]
    assert doc["trace"]["connected"] and doc["trace"]["srs"] > 0 and doc["trace"]["rtts"] == 0
