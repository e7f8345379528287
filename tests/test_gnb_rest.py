"""The gNB client over both transports (telnet, OAI's web server) against the simulated gNB, on the
same cases: discovery, measurements, unknown command, unknown RNTI, busy gNB, malformed answers,
HTTP errors, a body over 1 KB, a slow server; OAI's REST formats and caveats as the simulated web
server serves them; fuzzed replies; a whole `uavloc sim` mission over REST."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import aiohttp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from mission.gnb import O1_MIN_INTERVAL_S, GnbAddress, GnbConfig, OaiGnbClient, parse_gnb_address
from mission.gnb.transport import REST_MAX_BODY_BYTES, parse_rest_display, parse_rest_modules, rest_request
from sitl_scenarios.gnb import GnbFaults, SimulatedGnb, static_position
from sitl_scenarios.gnb.rest import display_lines, websrv_buffer
from sitl_scenarios.scenario import scenario_from_dict, user_tables
from uavloc.errors import (
    GnbBusyError,
    GnbError,
    GnbNoMeasurementError,
    GnbProtocolError,
    GnbTimeoutError,
    GnbUnknownCommandError,
)

USERS = [
    {"id": "a", "rnti": "0x4601", "east_m": 60.0, "north_m": 45.0},
    {"id": "b", "rnti": "0xb0b2", "east_m": -80.0, "north_m": 20.0},
    {"id": "c", "rnti": "0x1234", "east_m": 10.0, "north_m": -120.0},
    {"id": "far", "rnti": "0x0777", "east_m": 5000.0, "north_m": 0.0},  # beyond coverage
]
IN_COVERAGE = [0x1234, 0x4601, 0xB0B2]
UAV = (0.0, 0.0, 40.0)
TRANSPORTS = ["telnet", "rest"]


def scenario():
    return scenario_from_dict({"name": "gnb-rest-test", "seed": 7, **user_tables(USERS),
                               "radio": {"coverage_m": 1000.0, "s0_m": 1.0, "ue_sawtooth_amplitude_m": 0.0}})


def run(coro, timeout_s: float = 15.0):
    async def guarded():
        async with asyncio.timeout(timeout_s):
            return await coro

    return asyncio.run(guarded())


def sim(**kw) -> SimulatedGnb:
    return SimulatedGnb(scenario(), static_position(UAV), port=0, rest_port=0, **kw)


def cfg(gnb: SimulatedGnb, transport: str, **kw) -> GnbConfig:
    base = {"port": gnb.rest_port if transport == "rest" else gnb.port, "transport": transport,
            "request_timeout_s": 0.5, "connect_timeout_s": 0.5, "retries": 2, "backoff_initial_s": 0.005,
            "backoff_max_s": 0.02}
    base.update(kw)
    return GnbConfig(**base)


# ---------------------------------------------------------------------------------------------
# the same cases over both transports


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_discovery_lists_the_users_in_coverage(transport):
    async def body():
        async with sim() as gnb, OaiGnbClient(cfg(gnb, transport, discovery="o1")) as c:
            return await c.discover()

    assert run(body()) == IN_COVERAGE


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_measurements_match_the_true_geometry(transport):
    async def body():
        async with sim() as gnb, OaiGnbClient(cfg(gnb, transport)) as c:
            samples = await c.measure_many(await c.discover())
            return samples, list(gnb.truth)

    samples, truth = run(body())
    assert sorted(samples) == IN_COVERAGE
    by_rnti = {t.rnti: t for t in truth}
    for r, s in samples.items():
        assert s.ta == by_rnti[r].ta and s.srs_peak == pytest.approx(by_rnti[r].srs_peak, abs=1e-4)
        assert abs(s.range_m - by_rnti[r].true_range_m) < 30.0


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_stock_active_mode_triggers_only_a_listed_ue_and_reads_its_msg2(transport, tmp_path):
    log_path = tmp_path / "gnb.log"

    async def body():
        async with sim(log_path=log_path, msg2_delay_s=0.02) as gnb, OaiGnbClient(cfg(
                gnb, transport, mode="stock", stock_mode="active", log_path=log_path, msg2_timeout_s=1.0)) as c:
            got = [await c.measure(r) for r in (0x4601, 0xB0B2)]
            with pytest.raises(GnbNoMeasurementError, match="not sending `ci force_reestab 0777`"):
                await c.measure(0x0777)  # out of coverage: never sent
            return got, c.ci_sent, gnb.crashed

    got, sent, crashed = run(body())
    assert [s.rnti for s in got] == [0x4601, 0xB0B2] and all(s.source == "msg2" for s in got)
    assert sent == ["ci force_reestab 4601", "ci force_reestab b0b2"] and crashed is None


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_stock_passive_mode_sends_nothing_and_reads_the_log(transport, tmp_path):
    log_path = tmp_path / "gnb.log"

    async def body():
        async with sim(log_path=log_path) as gnb, OaiGnbClient(cfg(
                gnb, transport, mode="stock", stock_mode="passive", log_path=log_path)) as c:
            await c.discover()
            new_a = gnb.reattach(0)
            sample = await c.measure(new_a)
            return sample, new_a, c.ci_sent

    sample, new_a, sent = run(body())
    assert sample.rnti == new_a and sample.source == "msg2" and sent == []


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_unknown_command_is_the_same_error(transport):
    async def body():
        async with sim(rtt_command="other") as gnb:
            async with OaiGnbClient(cfg(gnb, transport)) as c:
                with pytest.raises(GnbUnknownCommandError, match="pdcch_order"):
                    await c.measure(0x4601)
            async with OaiGnbClient(cfg(gnb, transport, rtt_module="nomodule")) as d:
                with pytest.raises(GnbUnknownCommandError, match="nomodule"):
                    await d.measure(0x4601)

    run(body())


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_unknown_rnti_is_no_measurement_and_no_ci_is_sent(transport):
    async def body():
        async with sim() as gnb, OaiGnbClient(cfg(gnb, transport)) as c:
            with pytest.raises(GnbNoMeasurementError, match="0777"):
                await c.measure(0x0777)  # out of coverage
            with pytest.raises(GnbNoMeasurementError, match="not sending"):
                await c.guarded_ci("force_reestab", 0x0999)
            return c.ci_sent, gnb.crashed

    ci_sent, crashed = run(body())
    assert ci_sent == [] and crashed is None


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_busy_gnb_is_gnb_busy_error(transport):
    """Telnet: OAI serves one client at a time and leaves the next one unanswered. REST: another
    client's slow command holds the web server's one output buffer."""

    async def body():
        async with sim(faults=GnbFaults(busy_mode="silent")) as gnb, OaiGnbClient(
                cfg(gnb, transport, request_timeout_s=2.0)) as first:
            await first.discover()
            gnb.inject("delay", delay_s=1.0)
            slow = asyncio.create_task(first.measure(0x4601))
            await asyncio.sleep(0.1)
            async with OaiGnbClient(cfg(gnb, transport, request_timeout_s=0.3, retries=0)) as second:
                with pytest.raises(GnbBusyError, match="another client"):
                    await second.discover()
            return await slow, gnb.crashed

    sample, crashed = run(body())
    assert sample.rnti == 0x4601 and crashed is None


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_malformed_answers_are_protocol_errors_then_recover(transport):
    async def body():
        async with sim() as gnb, OaiGnbClient(cfg(gnb, transport)) as c:
            await c.discover()
            errors = 0
            for _ in range(6):
                gnb.inject("malformed")
                try:
                    await c.measure(0x4601)
                except GnbProtocolError:
                    errors += 1
                await asyncio.sleep(0)
            return errors, await c.measure(0x4601)

    errors, good = run(body())
    assert errors >= 4  # a malformed answer may still parse when the mangling missed every number
    assert good.rnti == 0x4601


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_slow_server_times_out_then_recovers(transport):
    async def body():
        async with sim() as gnb, OaiGnbClient(cfg(gnb, transport, request_timeout_s=0.3)) as c:
            await c.discover()
            gnb.inject("delay", delay_s=0.8)
            with pytest.raises(GnbTimeoutError, match="0.3 s"):
                await c.measure(0x4601)
            await asyncio.sleep(0.6)  # the slow answer's buffer is freed
            return await c.measure(0x4601)

    assert run(body()).rnti == 0x4601


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_a_lost_connection_is_retried_transparently(transport):
    async def body():
        async with sim() as gnb, OaiGnbClient(cfg(gnb, transport)) as c:
            await c.discover()
            gnb.inject("drop")
            s = await c.measure(0x4601)
            return s, c.reconnects

    s, reconnects = run(body())
    assert s.rnti == 0x4601 and reconnects == 1


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_an_abandoned_o1_stats_is_settled_and_spaced_before_the_next(transport):
    """A slow `o1 stats` given up on may still run (telnet: queued; REST: waiting for, or holding,
    the output buffer): the next one is preceded by the transport's settle request, answered
    after it, and spaced O1_MIN_INTERVAL_S from that answer; the gNB does not crash."""

    async def body():
        async with sim() as gnb, OaiGnbClient(cfg(gnb, transport, discovery="o1", request_timeout_s=0.4,
                                                  retries=0)) as c:
            await c.discover()
            gnb.inject("delay", delay_s=0.6)
            with pytest.raises(GnbTimeoutError):
                await c.discover()
            t0 = asyncio.get_running_loop().time()
            rntis = await c.discover()
            posted = list(gnb.rest.posted)
            return rntis, asyncio.get_running_loop().time() - t0, gnb.crashed, c.transport.settle_request, posted

    rntis, took_s, crashed, settle, posted = run(body())
    assert crashed is None and rntis == IN_COVERAGE
    assert took_s >= O1_MIN_INTERVAL_S
    if transport == "rest":
        names = [(m, b["name"]) for m, b in posted if b]
        assert names == [("o1", "stats"), ("o1", "stats"), ("ci", "get_single_rnti"), ("o1", "stats")]
        assert settle == "ci get_single_rnti"


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_the_gnb_not_listening_is_a_clear_error(transport):
    async def body():
        async with sim() as gnb:
            config = cfg(gnb, transport, retries=1)
        with pytest.raises(GnbError, match="cannot connect"):
            async with OaiGnbClient(config):
                pass

    run(body())


# ---------------------------------------------------------------------------------------------
# REST only: OAI's web server formats and caveats


def test_http_error_is_a_gnb_error_and_not_retried():
    async def body():
        async with sim() as gnb, OaiGnbClient(cfg(gnb, "rest")) as c:
            await c.discover()
            before = gnb.rest.requests
            gnb.inject("http_error")
            with pytest.raises(GnbError, match="HTTP 500"):
                await c.measure(0x4601)
            return gnb.rest.requests - before, c.reconnects

    sent, reconnects = run(body())
    assert sent == 1 and reconnects == 0


def test_a_request_over_1kb_is_refused_by_client_and_server():
    async def body():
        async with sim() as gnb:
            async with OaiGnbClient(cfg(gnb, "rest")) as c:
                with pytest.raises(GnbError, match="refuses more than 1024"):
                    await c.request("rtt pdcch_order " + "4" * 1100)
                with pytest.raises(GnbError, match="at most 2 parameters"):
                    await c.request("rtt pdcch_order 4601 4602 1234")
            url = f"http://127.0.0.1:{gnb.rest_port}/oaisoftmodem/rtt/commands"
            big = json.dumps({"name": "pdcch_order", "param": [{"name": "P0", "value": "4" * 1100, "type": "string",
                                                                 "modifiable": False}]})
            async with aiohttp.ClientSession() as s, s.post(url, data=big,
                                                            headers={"Content-Type": "application/json"}) as r:
                return r.status

    assert run(body()) == 413


@pytest.mark.parametrize(("body", "content_type", "status", "text"), [
    (b"{not json", "application/json", 400, "Unproperly formatted request body"),
    (b'{"name": "stats"}', "text/plain", 400, "Unproperly formatted request body"),
    (b'{"param": []}', "application/json", 400, "No command name in request body"),
    (b'{"name": "nosuch"}', "application/json", 501, "Unknown command in request body"),
    (b'{"name": "stats", "param": []}', "application/json", 500, "Unknown command in request body"),
    (b'{"name": "stats", "param": [{"name": "P0", "value": "1"}]}', "application/json", 500, "Unknown command"),
    (json.dumps({"name": "stats", "param": [{"name": f"P{k}", "value": "1", "type": "string", "modifiable": False}
                                            for k in range(3)]}).encode(), "application/json", 500, "Unknown"),
])
def test_malformed_requests_get_oais_status_codes(body, content_type, status, text):
    async def go():
        async with sim() as gnb, aiohttp.ClientSession() as s:
            url = f"http://127.0.0.1:{gnb.rest_port}/oaisoftmodem/o1/commands"
            async with s.post(url, data=body, headers={"Content-Type": content_type}) as r:
                return r.status, await r.text(), gnb.crashed

    got_status, got_text, crashed = run(go())
    assert (got_status, crashed) == (status, None)
    assert text in got_text


def test_module_and_command_listings_have_oais_shape():
    async def go():
        async with sim() as gnb, aiohttp.ClientSession() as s:
            base = f"http://127.0.0.1:{gnb.rest_port}/oaisoftmodem"
            async with s.get(f"{base}/commands") as r:
                modules = parse_rest_modules(await r.read())
            async with s.get(f"{base}/ci/commands") as r:
                ci = await r.json()
            async with s.get(f"{base}/nosuch/commands") as r:
                missing = r.status
            return modules, ci, missing

    modules, ci, missing = run(go())
    assert modules == ["ci", "o1", "rtt"] and missing == 404
    assert {"name": "get_single_rnti"} in ci and "confirm" in ci[-1]
    assert ci[1]["question"][0]["pname"] == "P0"


def test_a_command_without_parameter_gets_a_blank_and_stock_oai_refuses_it():
    """websrv.c hands a command given no parameter " "; stock OAI's `o1 stats` and `ci
    get_single_rnti` refuse any buffer, and `ci force_reestab` reads " " as RNTI 0 (refused, not a
    crash). The client says what that means instead of a parse error."""

    async def body():
        async with sim(stock_websrv=True) as gnb:
            async with OaiGnbClient(cfg(gnb, "rest")) as c:
                with pytest.raises(GnbError, match="passes \" \" to a command given no parameter"):
                    await c.discover()
            async with aiohttp.ClientSession() as s, s.post(
                    f"http://127.0.0.1:{gnb.rest_port}/oaisoftmodem/ci/commands",
                    json={"name": "force_reestab"}) as r:
                reestab = (await r.json())["display"]
            return reestab, gnb.crashed

    reestab, crashed = run(body())
    assert crashed is None
    assert reestab == ["RNTI needs to be [1,0xfffe]", "could not identify UE (no UE, no such RNTI, or multiple UEs)"]


def test_a_ci_command_with_an_unknown_rnti_crashes_the_gnb_over_rest_too():
    """The hazard is the gNB's, not the transport's: the simulated web server dies with the gNB."""

    async def body():
        async with sim() as gnb, aiohttp.ClientSession() as s:
            url = f"http://127.0.0.1:{gnb.rest_port}/oaisoftmodem/ci/commands"
            with pytest.raises(aiohttp.ClientError):
                async with s.post(url, json={"name": "force_reestab", "param": [
                        {"name": "P0", "value": "0999", "type": "string", "modifiable": False}]}) as r:
                    await r.read()
            return gnb.crashed

    assert "segfault" in run(body())


def test_a_telnet_port_given_as_http_is_a_clear_error_at_once():
    async def body():
        async with sim() as gnb:
            config = GnbConfig(port=gnb.port, transport="rest", connect_timeout_s=1.0, retries=3)
            client = OaiGnbClient(config)
            with pytest.raises(GnbProtocolError, match="does not speak HTTP.*telnet://"):
                await client.__aenter__()
            return gnb.connections

    assert run(body()) == 1  # not retried


def test_rest_request_bodies_have_the_four_keys_and_no_empty_param():
    assert rest_request("o1 stats") == ("o1", {"name": "stats"})
    mod, body = rest_request("rtt pdcch_order 4601")
    assert mod == "rtt" and body["param"] == [{"name": "P0", "value": "4601", "type": "string", "modifiable": False}]
    assert len(json.dumps(body)) < REST_MAX_BODY_BYTES
    assert [websrv_buffer(v) for v in ([], ["4601"], ["a", "b"])] == [" ", "4601 ", "a b"]
    assert display_lines("a\n\nb\n") == ["a", "b"]


@pytest.mark.parametrize(("text", "expected"), [
    ("127.0.0.1:9090", GnbAddress("127.0.0.1", 9090, "telnet")),
    ("gnb.local", GnbAddress("gnb.local", 9090, "telnet")),
    ("telnet://10.0.0.2:9091", GnbAddress("10.0.0.2", 9091, "telnet")),
    ("http://127.0.0.1:8090", GnbAddress("127.0.0.1", 8090, "rest")),
    ("http://10.0.0.2/", GnbAddress("10.0.0.2", 8090, "rest")),
    ("HTTP://[::1]:8091", GnbAddress("::1", 8091, "rest")),
])
def test_parse_gnb_address(text, expected):
    assert parse_gnb_address(text) == expected


@pytest.mark.parametrize(("text", "match"), [
    ("https://h:1", "scheme 'https'"), ("ftp://h:1", "scheme"), ("http://h:1/oaisoftmodem", "path"),
    ("http://h:x", "not a number"), ("http://", "no host"),
])
def test_parse_gnb_address_errors(text, match):
    with pytest.raises(GnbError, match=match):
        parse_gnb_address(text)


def test_a_scheme_less_address_takes_the_default_transport_and_its_port():
    assert parse_gnb_address("h", default="rest") == GnbAddress("h", 8090, "rest")
    assert parse_gnb_address("telnet://h", default="rest") == GnbAddress("h", 9090, "telnet")
    with pytest.raises(GnbError, match="transport"):
        parse_gnb_address("h", default="grpc")


# ---------------------------------------------------------------------------------------------
# fuzzed replies


@seed(20500)
@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.one_of(st.binary(max_size=300),
                 st.builds(lambda d: json.dumps(d).encode(), st.recursive(
                     st.none() | st.booleans() | st.integers() | st.text(max_size=20),
                     lambda c: st.lists(c, max_size=4) | st.dictionaries(st.sampled_from(["display", "x"]), c,
                                                                          max_size=2), max_leaves=10))))
def test_fuzzed_rest_bodies_parse_or_raise_protocol_error(raw):
    try:
        text = parse_rest_display(raw)
    except GnbProtocolError:
        return
    assert isinstance(text, str)


@seed(20501)
@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(st.text(alphabet=st.characters(blacklist_characters="\n\x00", blacklist_categories=("Cs",)),
                        min_size=1, max_size=40), max_size=8))
def test_display_lines_round_trip(lines):
    assert parse_rest_display(json.dumps({"display": lines}).encode()) == "".join(f"{x}\n" for x in lines)


@seed(20502)
@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(st.binary(max_size=200), st.builds(lambda ls: json.dumps({"display": ls}).encode(),
                                                     st.lists(st.text(max_size=60), max_size=5))),
       st.sampled_from([200, 200, 200, 400, 404, 500, 501, 503]))
def test_fuzzed_http_replies_end_in_a_gnb_error_or_a_sample(raw, status):
    """A web server answering anything: the client measures, or raises a GnbError subclass."""
    from aiohttp import web

    async def body():
        async def commands(request):
            return web.json_response([{"name": "ci"}, {"name": "o1"}, {"name": "rtt"}])

        async def execute(request):
            await request.read()
            return web.Response(status=status, body=raw, content_type="application/json")

        app = web.Application()
        app.router.add_get("/oaisoftmodem/commands", commands)
        app.router.add_post("/oaisoftmodem/{module}/commands", execute)
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        port = runner.addresses[0][1]
        try:
            async with OaiGnbClient(GnbConfig(port=port, transport="rest", request_timeout_s=1.0,
                                              retries=0)) as c:
                try:
                    return await c.measure(0x4601)
                except GnbError as exc:
                    return exc
        finally:
            await runner.cleanup()

    got = run(body())
    assert isinstance(got, GnbError) or got.rnti == 0x4601


# ---------------------------------------------------------------------------------------------
# a whole mission over REST


def test_a_whole_sim_mission_over_rest_locates_every_user(tmp_path):
    from sitl_scenarios.scenario import load_scenario
    from sitl_scenarios.sim_runner import SimulatedMission

    # the scenario the telnet mission test holds to its target radius (test_mission_e2e): with
    # three_users_nlos a user ended beyond it in 3 of 14 runs here, whatever the transport
    # (the estimator's honesty there is issue 22's, not the transport's)
    sc = load_scenario("paper")

    async def body():
        async with SimulatedMission(sc, log_path=tmp_path / "m.jsonl", speedup=40.0, gnb_transport="rest") as m:
            result = await m.run()
            return result, m.gnb_client.config.transport, m.gnb_sim.rest_requests

    result, transport, rest_requests = run(body(), timeout_s=240.0)
    assert transport == "rest" and rest_requests > 10
    assert result.ok, result.reason  # every user located, none ambiguous
    assert result.not_located() == [] and len(result.result.user_ids) == len(sc.users)
    err = result.error_m()
    # the target is a 95 % bound: the error lies beyond it in about one run in twenty, so "located"
    # is within half as much again (the transport carries the ranges; the estimator's honesty is
    # held by its own tests)
    assert err is not None and np.all(err <= 1.5 * sc.mission.flight.target_radius_m), err


# ---------------------------------------------------------------------------------------------
# the command line


def test_gnb_probe_over_rest_and_a_telnet_port_given_as_http(capsys):
    from mission.cli import main

    async def serve(address_of):
        async with sim() as gnb:
            return await asyncio.to_thread(main, ["gnb", "probe", "--gnb", address_of(gnb), "--count", "2", "--json"])

    assert run(serve(lambda g: f"http://127.0.0.1:{g.rest_port}")) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and doc["address"].startswith("http://") and doc["gnb_rntis"] == ["1234", "4601", "b0b2"]
    assert all(len(u["samples"]) == 2 and u["samples"][0]["range_m"] > 0 for u in doc["ues"])
    assert run(serve(lambda g: f"telnet://127.0.0.1:{g.port}")) == 0
    capsys.readouterr()
    assert run(serve(lambda g: f"http://127.0.0.1:{g.port}")) == 1
    doc = json.loads(capsys.readouterr().out)
    assert not doc["ok"] and "does not speak HTTP" in doc["message"] and "telnet://" in doc["message"]


def test_a_campaign_spec_names_the_gnb_transport_of_its_full_runs():
    from sitl_scenarios.campaign.spec import spec_from_dict
    from uavloc.errors import CampaignError

    def spec(**campaign):
        return spec_from_dict({"campaign": {"name": "t", "planners": ["lawnmower"], **campaign},
                               "scenarios": [{"file": "paper"}]})

    telnet, rest = spec(mode="full"), spec(mode="full", gnb_transport="rest")
    assert [r.gnb_transport for r in telnet.runs + rest.runs] == ["telnet", "rest"]
    assert telnet.runs[0].key != rest.runs[0].key
    with pytest.raises(CampaignError, match="only full mode"):
        spec(mode="fast", gnb_transport="rest")
    with pytest.raises(CampaignError, match="'telnet' or 'rest'"):
        spec(mode="full", gnb_transport="http")


def test_a_mission_files_transport_applies_to_an_address_without_scheme(tmp_path):
    from mission.config import load_mission

    text = (Path(__file__).parent.parent / "mission/examples/flight.toml").read_text()
    path = tmp_path / "m.toml"
    path.write_text(text.replace("[gnb]\n", '[gnb]\ntransport = "rest"\n', 1))
    gnb = load_mission(path).gnb
    address = parse_gnb_address("10.0.0.2", default=gnb.transport)
    config = GnbConfig.of(gnb, address.host, address.port)
    assert (config.transport, config.port) == ("rest", 8090)
