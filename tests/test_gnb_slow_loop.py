"""A slow answer is not "not a gNB" (issue 48): an answer whose prompt is in the bytes read is an
answer, even when the client's event loop resumed only after the request timeout; bytes without
the prompt on a connection that has shown it is an OAI telnet server are a timeout; the
"is this the gNB's telnet server?" protocol error stays for a fresh connection that never showed
the prompt. The servers are real TCP servers on loopback, in a thread of their own (a gNB does not
share the controller's event loop) or, for the lag grace, in the client's own loop."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from mission.gnb import GnbConfig, OaiGnbClient
from mission.gnb.oai import PROMPT_GNB
from sitl_scenarios.gnb import SimulatedGnb, static_position
from sitl_scenarios.scenario import scenario_from_dict, user_tables
from uavloc.errors import GnbProtocolError, GnbTimeoutError

RTT_ANSWER = b"rnti 4601 ta 1 mu 1 srs_peak 11.7500 fs 46080000 snr_db 32.5\n"
#: an `o1 stats` answer of the size the issue quotes (1209 bytes)
O1_DOC = {"o1-config": {"pad": "x" * 1080}, "O1-Operational": {"num-ues": 1, "ues": [0x4601],
                                                               "ues-thp": [{"rnti": 0x4601, "dl": 1, "ul": 1}]}}
O1_ANSWER = (json.dumps(O1_DOC) + "\nOK\n").encode()


@contextmanager
def thread_server(answer: Callable[[int, str], bytes], delay_s: float = 0.0) -> Iterator[int]:
    """A TCP server on loopback in its own thread and event loop: each line of a connection gets
    answer(number of the line on that connection, line), delay_s [s] after it came; yields the port."""
    ready = threading.Event()
    box: dict = {}

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        n = 0
        try:
            while line := await reader.readline():
                text = line.decode().strip()
                if text == "exit":
                    break
                if delay_s > 0 and text not in ("e",):
                    await asyncio.sleep(delay_s)
                writer.write(answer(n, text))
                await writer.drain()
                n += 1
        except ConnectionError:
            pass
        finally:
            writer.close()

    async def serve() -> None:
        server = await asyncio.start_server(handle, "127.0.0.1", 0)
        box["port"] = server.sockets[0].getsockname()[1]
        box["stop"] = asyncio.Event()
        box["loop"] = asyncio.get_running_loop()
        ready.set()
        async with server:
            await box["stop"].wait()

    th = threading.Thread(target=asyncio.run, args=(serve(),), daemon=True)
    th.start()
    assert ready.wait(5.0)
    try:
        yield box["port"]
    finally:
        box["loop"].call_soon_threadsafe(box["stop"].set)
        th.join(5.0)


def config(port: int, **kw) -> GnbConfig:
    base = {"port": port, "request_timeout_s": 0.3, "connect_timeout_s": 1.0, "retries": 0,
            "backoff_initial_s": 0.005, "backoff_max_s": 0.02, "discovery": "o1"}
    base.update(kw)
    return GnbConfig(**base)


async def block_loop_after_send(seconds: float) -> None:
    """Let the request go out, then block the event loop (a busy machine, a long callback)."""
    await asyncio.sleep(0.02)
    time.sleep(seconds)


def run(coro, timeout_s: float = 20.0):
    async def guarded():
        async with asyncio.timeout(timeout_s):
            return await coro
    return asyncio.run(guarded())


def oai_answer(n: int, line: str) -> bytes:
    if line == "o1 stats":
        return O1_ANSWER + PROMPT_GNB.encode()
    if line.startswith("rtt "):
        return RTT_ANSWER + PROMPT_GNB.encode()
    return PROMPT_GNB.encode()  # the settle request "e", anything else


@pytest.mark.parametrize("request_line", ["rtt", "o1"])
def test_an_answer_read_while_the_loop_was_blocked_past_the_timeout_is_the_answer(request_line):
    """The issue's abort: the loop resumes after the 0.3 s timeout with the whole answer and its
    prompt in the stream's buffer; the request returns that answer (the 76-byte RTT answer and the
    1209-byte `o1 stats`), never "no prompt"."""
    assert len(O1_ANSWER) + len(PROMPT_GNB) > 1200

    async def body(port):
        async with OaiGnbClient(config(port)) as c:
            blocker = asyncio.create_task(block_loop_after_send(1.0))
            if request_line == "rtt":
                got = await c.measure(0x4601)
            else:
                got = await c.discover()
            await blocker
            return got, c.late_answers, c.connected

    with thread_server(oai_answer, delay_s=0.1) as port:
        got, late, connected = run(body(port))
    if request_line == "rtt":
        assert got.rnti == 0x4601 and got.ta == 1 and got.srs_peak == 11.75
        # the interval it was measured in spans the blocked loop: honest, not a midpoint guess
        assert got.t_unc_s >= 0.45
    else:
        assert got == [0x4601]
    assert late == 1 and connected


def test_a_gnb_in_the_clients_own_lagging_loop_gets_its_time_to_answer():
    """The simulated gNB shares the controller's loop in `uavloc sim`: while the loop is blocked it
    cannot answer at all, and the timeout fires late; the request waits another timeout for the
    answer instead of calling the gNB silent."""
    users = [{"id": "a", "rnti": "0x4601", "east_m": 60.0, "north_m": 45.0}]
    scen = scenario_from_dict({"name": "lag", "seed": 7, **user_tables(users),
                               "radio": {"coverage_m": 1000.0, "s0_m": 1.0, "ue_sawtooth_amplitude_m": 0.0}})

    async def body():
        async with SimulatedGnb(scen, static_position(np.array([0.0, 0.0, 40.0])), port=0) as gnb, \
                OaiGnbClient(config(gnb.port)) as c:
            out = []
            for _ in range(2):
                gnb.inject("delay", delay_s=0.1)  # the answer is due while the loop is blocked
                blocker = asyncio.create_task(block_loop_after_send(0.8))
                out.append(await c.measure(0x4601))
                await blocker
            gnb.inject("delay", delay_s=0.1)
            blocker = asyncio.create_task(block_loop_after_send(0.8))
            out.append(await c.discover())
            await blocker
            return out, c.late_answers

    out, late = run(body())
    assert [s.rnti for s in out[:2]] == [0x4601, 0x4601] and out[2] == [0x4601]
    assert late == 3


def test_bytes_without_the_prompt_on_a_connection_that_showed_it_are_a_timeout():
    """A connection that has answered with the prompt is an OAI telnet server: a later answer cut
    short (no prompt within the timeout) is a GnbTimeoutError, not "is this the gNB?"."""
    def answer(n: int, line: str) -> bytes:
        if line.startswith("rtt ") and n >= 3:  # "e", "o1 stats", one whole answer
            return b"rnti 4601 ta 1 mu"  # half an answer, then silence
        return oai_answer(n, line)

    async def body(port):
        async with OaiGnbClient(config(port)) as c:
            await c.discover()
            await c.measure(0x4601)
            with pytest.raises(GnbTimeoutError, match="within 0.3 s .*without the prompt") as exc:
                await c.measure(0x4601)
            return exc.value, c.connected

    with thread_server(answer) as port:
        exc, connected = run(body(port))
    assert not isinstance(exc, GnbProtocolError) and not connected


def test_a_fresh_connection_that_never_shows_the_prompt_is_still_not_a_gnb():
    """Something else on the port (it answers, never with the prompt): the protocol error stays."""
    async def body(port):
        async with OaiGnbClient(config(port)) as c:
            await c.discover()

    with thread_server(lambda n, line: b"HTTP/1.1 400 Bad Request\r\n") as port, \
            pytest.raises(GnbProtocolError, match="is this the gNB's telnet server"):
        run(body(port))


@pytest.mark.parametrize(("silent", "ok"), [(1, True), (3, True), (4, False)])
def test_the_preflight_probe_asks_again_after_a_timeout(silent, ok):
    """A gNB too busy to answer `o1 stats` once (a loaded machine) does not stop the take-off: the
    probe asks again, TIMEOUT_TRIES times in all; a gNB silent every time fails it."""
    from mission.gnb.probe import TIMEOUT_TRIES, probe_gnb

    assert TIMEOUT_TRIES == 4
    asked = {"o1 stats": 0}

    def answer(n: int, line: str) -> bytes:
        if line == "o1 stats":
            asked[line] += 1
            if asked[line] <= silent:
                return b""  # no answer: the request times out
        return oai_answer(n, line)

    async def probe(port: int):
        client = OaiGnbClient(config(port))
        async with client:
            return await probe_gnb(client, rntis=[0x4601], count=1)

    with thread_server(answer) as port:
        res = run(probe(port), timeout_s=30.0)
    assert res.ok is ok, res.message()
    assert asked["o1 stats"] == (silent + 1 if ok else TIMEOUT_TRIES)
    if not ok:
        assert "discovery failed" in res.message() and "o1 stats" in res.message()
