"""Benchmark: gNB measurement round trip over loopback (adapter <-> simulated OAI gNB), over the
telnet server and over OAI's web server (REST).

    python benchmarks/gnb.py [--n 400] [--triggers 100] [--t-seconds 10]

Targets (issue 3): one UE ≤ 5 ms median round trip; 10 UEs ≤ 50 ms per trigger, over either
transport. A bare TCP echo round trip measured in the same run is the baseline, so the ratios say
what the protocol, the parsing and the radio model cost on this machine; a bare HTTP echo through
aiohttp (client and server, one keep-alive connection) says how much of REST's cost is HTTP itself.

The T stream (trace mode): the events a real gNB with 20 UEs emits (SRS every 8 frames, a TA
command every 100 frames per UE, SIB1), `--t-seconds` of air time made with the simulated T
server's encoder, then (1) parsed offline: decoding plus the RTT tracker against bare framing
(split_frames) in the same run, events per second and the multiple of the real rate; (2) sent
over loopback at the real rate by a separate process to the trace client: its CPU share.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import time
from pathlib import Path

import numpy as np

# this file is benchmarks/gnb.py: put the repository root in place of its folder on sys.path, so that
# `import estimator` finds the package and not benchmarks/estimator.py
_HERE = Path(__file__).resolve().parent
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from mission.gnb import GnbConfig, OaiGnbClient  # noqa: E402 (after the sys.path fix)
from mission.gnb.transport import rest_request  # noqa: E402
from sitl_scenarios.gnb import SimulatedGnb, static_position  # noqa: E402
from sitl_scenarios.scenario import scenario_from_dict, user_tables  # noqa: E402

T_UES = 20

TARGET_ONE_MS = 5.0
TARGET_TEN_MS = 50.0


def ten_user_scenario():
    rng = np.random.default_rng(0)
    users = [{"id": f"u{i}", "rnti": 0x4601 + i, "east_m": float(e), "north_m": float(n)}
             for i, (e, n) in enumerate(rng.uniform(-300, 300, size=(10, 2)))]
    buildings = [{"footprint_enu_m": [[20.0, 20.0], [60.0, 20.0], [60.0, 50.0], [20.0, 50.0]], "height_m": 25.0}]
    return scenario_from_dict({"name": "bench", "seed": 1, **user_tables(users), "buildings": buildings})


async def echo_baseline_ms(n: int) -> list[float]:
    async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while line := await reader.readline():
            writer.write(line)
            await writer.drain()
        writer.close()

    server = await asyncio.start_server(echo, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    r, w = await asyncio.open_connection("127.0.0.1", port)
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        w.write(b"rtt pdcch_order 4601\n")
        await w.drain()
        await r.readline()
        out.append((time.perf_counter() - t0) * 1e3)
    w.close()
    await w.wait_closed()
    server.close()
    await server.wait_closed()
    return out


async def http_echo_baseline_ms(n: int) -> list[float]:
    """POST the REST body of `rtt pdcch_order 4601` to an aiohttp server that answers one display line."""
    import aiohttp
    from aiohttp import web

    async def echo(request: web.Request) -> web.Response:
        await request.read()
        return web.json_response({"display": ["rnti 4601 ta 3 mu 1 srs_peak 1.0 fs 46080000"]})

    app = web.Application()
    app.router.add_post("/oaisoftmodem/{module}/commands", echo)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = runner.addresses[0][1]
    _, body = rest_request("rtt pdcch_order 4601")
    out = []
    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=1)) as s:
        for _ in range(n):
            t0 = time.perf_counter()
            async with s.post(f"http://127.0.0.1:{port}/oaisoftmodem/rtt/commands", json=body) as r:
                await r.read()
            out.append((time.perf_counter() - t0) * 1e3)
    await runner.cleanup()
    return out


async def gnb_ms(n: int, triggers: int, transport: str = "telnet") -> tuple[list[float], list[float], int]:
    sc = ten_user_scenario()
    rest = transport == "rest"
    async with SimulatedGnb(sc, static_position((0.0, 0.0, 40.0)), port=0, rest_port=0 if rest else None) as gnb, \
            OaiGnbClient(GnbConfig(port=gnb.rest_port if rest else gnb.port, transport=transport)) as client:
        rntis = await client.discover()
        one = []
        for i in range(n):
            t0 = time.perf_counter()
            await client.measure(rntis[i % len(rntis)])
            one.append((time.perf_counter() - t0) * 1e3)
        ten = []
        for _ in range(triggers):
            t0 = time.perf_counter()
            got = await client.measure_many(rntis)
            ten.append((time.perf_counter() - t0) * 1e3)
            assert len(got) == len(rntis)
        return one, ten, len(rntis)


def t_stream(air_s: float, ues: int = T_UES) -> tuple[bytes, int]:
    """(the bytes a real gNB's T server sends in air_s seconds with `ues` UEs, event count): the
    preamble, then per 10 ms frame SIB1 every 16 frames, an SRS estimate per UE every 8 and a DL PDU
    with a TA command per UE every 100 (sitl_scenarios.gnb.ttrace's encoders and ids)."""
    from sitl_scenarios.gnb.ttrace import ID, SIM_T_MESSAGES, buffer_bytes, chest_bytes, fields_bytes, frame_bytes

    rng = np.random.default_rng(0)
    out = [frame_bytes(0.0, -1, buffer_bytes(SIM_T_MESSAGES.encode())), frame_bytes(0.0, -2, b"")]
    n = 0
    for k in range(ues):
        rar = bytes([0x40 | k, 0, (2 & 0x1F) << 3, 0, 0, 0, 0x46, k + 1])
        out.append(frame_bytes(0.0, ID["GNB_MAC_DL_RAR_PDU_WITH_DATA"],
                               fields_bytes(0, 0, 0x10F, 0, 10, 0) + buffer_bytes(rar)))
        n += 1
    for f in range(1, round(air_s / 0.01) + 1):
        t = f * 0.01
        if f % 16 == 0:
            out.append(frame_bytes(t, ID["GNB_MAC_DL_PDU_WITH_DATA"], fields_bytes(0, 0, 0xFFFF, f % 1024, 1, 0)
                                   + buffer_bytes(rng.bytes(100))))
            n += 1
        for k in range(ues):
            if f % 8 == 0:
                chest = chest_bytes(float(rng.normal(0, 2)), 8000.0, rng)
                out.append(frame_bytes(t, ID["GNB_PHY_UL_TIME_CHANNEL_ESTIMATE"],
                                       fields_bytes(0, 0x4600 + k + 1, f % 1024, 0, 0) + buffer_bytes(chest)))
                n += 1
            if f % 100 == 0:
                out.append(frame_bytes(t, ID["GNB_MAC_DL_PDU_WITH_DATA"],
                                       fields_bytes(0, 0, 0x4600 + k + 1, f % 1024, 0, 0)
                                       + buffer_bytes(bytes([61, 31, 63]) + bytes(16))))
                n += 1
    return b"".join(out), n


def t_parse(data: bytes) -> tuple[float, float, int]:
    """(framing only [s], decode + tracker [s], RTTs) over the whole stream."""
    from mission.gnb.trace_rtt import TraceRttTracker
    from mission.gnb.ttrace import iter_recording, split_frames

    t0 = time.process_time()
    split_frames(data)
    framing = time.process_time() - t0
    tr = TraceRttTracker()
    t0 = time.process_time()
    for ev in iter_recording(data):
        tr.feed(ev)
    return framing, time.process_time() - t0, tr.counts.rtts


_SENDER = """
import socket, sys, time
data = open(sys.argv[1], "rb").read(); air_s = float(sys.argv[2])
srv = socket.create_server(("127.0.0.1", 0)); print(srv.getsockname()[1], flush=True)
c, _ = srv.accept()
t0, chunk = time.monotonic(), max(1, len(data) // int(air_s * 100))
for i in range(0, len(data), chunk):
    c.sendall(data[i:i + chunk])
    time.sleep(max(0.0, t0 + (i + chunk) / len(data) * air_s - time.monotonic()))
c.close()
"""


async def t_client_cpu(data: bytes, air_s: float) -> tuple[float, int]:
    """(the trace client's CPU share while a separate process sends `data` at the real rate, events)."""
    import subprocess
    import tempfile

    from mission.gnb.tracer import TTracerClient

    with tempfile.NamedTemporaryFile(suffix=".raw") as fh:
        fh.write(data)
        fh.flush()
        proc = subprocess.Popen([sys.executable, "-c", _SENDER, fh.name, str(air_s)], stdout=subprocess.PIPE, text=True)
        try:
            port = int(proc.stdout.readline())
            c0, w0 = time.process_time(), time.perf_counter()
            async with TTracerClient("127.0.0.1", port) as client:
                while proc.poll() is None:
                    await asyncio.sleep(0.05)
                await asyncio.sleep(0.1)
                events = client.tracker.counts.events
            return (time.process_time() - c0) / (time.perf_counter() - w0), events
        finally:
            proc.kill()
            proc.wait()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--n", type=int, default=400, help="single-UE round trips")
    p.add_argument("--triggers", type=int, default=100, help="10-UE triggers")
    p.add_argument("--t-seconds", type=float, default=10.0, help="air seconds of the 20-UE T stream")
    args = p.parse_args(argv)

    base = asyncio.run(echo_baseline_ms(args.n))
    http = asyncio.run(http_echo_baseline_ms(args.n))
    runs = {t: asyncio.run(gnb_ms(args.n, args.triggers, t)) for t in ("telnet", "rest")}

    def q(xs: list[float], pct: float) -> float:
        return float(np.percentile(xs, pct))

    base_med, http_med = statistics.median(base), statistics.median(http)
    print(f"{'what':40s} {'median ms':>10s} {'p95 ms':>8s} {'target':>8s} {'x echo':>8s}")
    print(f"{'bare TCP echo round trip':40s} {base_med:10.3f} {q(base, 95):8.3f} {'':>8s} {1.0:8.1f}")
    print(f"{'bare HTTP echo round trip (aiohttp)':40s} {http_med:10.3f} {q(http, 95):8.3f} {'':>8s} "
          f"{http_med / base_med:8.1f}")
    ok = True
    verdicts = []
    for t, (one, ten, k) in runs.items():
        one_med, ten_med = statistics.median(one), statistics.median(ten)
        print(f"{f'{t}: measure(rnti), 1 UE':40s} {one_med:10.3f} {q(one, 95):8.3f} {TARGET_ONE_MS:8.1f} "
              f"{one_med / base_med:8.1f}")
        print(f"{f'{t}: measure_many, {k} UEs per trigger':40s} {ten_med:10.3f} {q(ten, 95):8.3f} "
              f"{TARGET_TEN_MS:8.1f} {ten_med / base_med:8.1f}")
        ok = ok and one_med <= TARGET_ONE_MS and ten_med <= TARGET_TEN_MS
        verdicts.append(f"{t} 1 UE {one_med:.2f} ms, {k} UEs {ten_med:.2f} ms")
    tel, rst = statistics.median(runs["telnet"][0]), statistics.median(runs["rest"][0])
    print(f"REST / telnet round trip: {rst / tel:.2f}x")
    data, n_ev = t_stream(args.t_seconds)
    framing_s, full_s, rtts = t_parse(data)
    real_rate = n_ev / args.t_seconds
    rate = n_ev / full_s
    print(f"T stream, {T_UES} UEs: {n_ev} events in {args.t_seconds:g} s of air time ({real_rate:.0f} events/s, "
          f"{len(data) / args.t_seconds / 1e6:.2f} MB/s); {rtts} RTTs")
    print(f"  parse + track: {rate:,.0f} events/s = {rate / real_rate:.1f}x the real rate; "
          f"{full_s / framing_s:.1f}x bare framing ({framing_s * 1e3:.1f} ms)")
    cpu, got = asyncio.run(t_client_cpu(data, args.t_seconds))
    print(f"  trace client over loopback at the real rate: {cpu * 100:.1f} % of one core ({got} events)")
    ok = ok and rate >= 5 * real_rate
    verdicts.append(f"T stream parsed at {rate / real_rate:.1f}x a 20-UE gNB (>= 5x)")
    print(f"{'PASS' if ok else 'FAIL'}: {'; '.join(verdicts)} (<= {TARGET_ONE_MS} ms, <= {TARGET_TEN_MS} ms); "
          f"n = {args.n}, triggers = {args.triggers}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
