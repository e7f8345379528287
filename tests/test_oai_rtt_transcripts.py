"""`rtt pdcch_order` as the patched OAI 2025.w36 gNB answered it (recorded, tests/data/oai-2025.w36-rtt/).

The telnet sessions of a gNB built with patches/oai-2025.w36 (rfsim, `--do-ra`, `do_SRS = 1`) and
its nrUE, the rfsim distance stepped on both sides: every answer goes through the pure parsers,
every range is the distance the rfsimulator said it set, and the sessions are replayed over TCP,
answer by answer as recorded, to the real adapter in `rtt` mode. Never skipped.
"""

from __future__ import annotations

import ast
import asyncio
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

from estimator.ranging import range_m_from_raw
from mission.gnb import GnbConfig, OaiGnbClient
from mission.gnb.oai import PROMPT_GNB, RttErrorReply, RttReply, decode_reply, parse_rtt_reply
from uavloc.errors import GnbNoMeasurementError

DATA = Path(__file__).parent / "data" / "oai-2025.w36-rtt"
_LINE = re.compile(r"^(>>>|<<<) \[\s*([0-9.]+)s\] (b'.*|b\".*)$")
_EXACT = re.compile(r"new \(exact\) distance ([0-9.]+) m")
#: one rfsim sample at 46.08 Msps, one way [m]
SAMPLE_M = 299_792_458.0 / 46.08e6


@dataclass(frozen=True)
class Exchange:
    """One request and what the gNB (or the nrUE) sent back until its prompt (and the rfsimulator's
    line after it)."""

    sent: bytes
    received: bytes
    t_s: float


def session(name: str) -> list[Exchange]:
    out: list[Exchange] = []
    sent: tuple[bytes, float] | None = None
    for line in (DATA / name).read_text().splitlines():
        m = _LINE.match(line)
        if not m:
            continue
        data = ast.literal_eval(m.group(3))
        if m.group(1) == ">>>":
            sent = (data, float(m.group(2)))
        elif sent is not None:
            out.append(Exchange(sent[0], data, sent[1]))
            sent = None
    return out


def orders(name: str) -> list[tuple[float | None, Exchange]]:
    """Each `rtt pdcch_order` exchange with the rfsim distance the gNB side last said it set [m]."""
    distance_m: float | None = 0.0
    out = []
    for ex in session(name):
        if ex.sent.startswith(b"rfsimu setdistance rfsimu_channel_ue0"):
            m = _EXACT.search(ex.received.decode())
            distance_m = float(m.group(1)) if m else None
        elif ex.sent.startswith(b"rtt pdcch_order"):
            out.append((distance_m, ex))
    return out


def body(ex: Exchange) -> str:
    return decode_reply(ex.received, PROMPT_GNB)


def test_the_recordings_are_there_and_hold_orders_at_several_distances():
    got = orders("session.txt")
    distances = {d for d, ex in got if any(isinstance(r, RttReply) for r in parse_rtt_reply(body(ex)))}
    assert len(got) >= 20 and len(distances) >= 3, (len(got), distances)


def test_every_order_answer_parses_and_each_range_is_the_rfsim_distance():
    """A measurement's range is the rfsim distance the rfsimulator reported, to the sample; the
    error lines name the RNTI and why."""
    ranges: dict[float, list[float]] = {}
    errors: list[str] = []
    for distance_m, ex in orders("session.txt"):
        asked = ex.sent.decode().split()[2:]
        results = parse_rtt_reply(body(ex))
        assert len(results) == max(1, len(asked)), ex
        for r in results:
            if isinstance(r, RttErrorReply):
                errors.append(r.message)
                continue
            assert r.mu == 1 and r.fs_hz == 46.08e6 and r.srs_peak == int(r.srs_peak), r
            range_m = range_m_from_raw(r.ta, r.mu, r.srs_peak, r.fs_hz)
            assert distance_m is not None and abs(range_m - distance_m) <= SAMPLE_M / 2, (distance_m, r)
            ranges.setdefault(distance_m, []).append(range_m)
    assert any(e.endswith("not connected") for e in errors), errors
    assert "error bad rnti 'zz'" in errors and any(e.startswith("error missing rnti") for e in errors)
    assert all(re.fullmatch(r"error (rnti [0-9a-f]{4} .+|bad rnti '.*'|missing rnti .+)", e) for e in errors), errors
    assert len(ranges) >= 3


class SequentialReplay:
    """A TCP server answering the recorded `o1 stats` and `rtt pdcch_order` requests with the
    recorded answers, each request's answers in the recorded order."""

    def __init__(self, exchanges: list[Exchange]) -> None:
        self.queue: dict[bytes, list[bytes]] = {}
        for ex in exchanges:
            self.queue.setdefault(ex.sent.rstrip(b"\n"), []).append(ex.received)
        self.port = 0

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while line := await reader.readline():
                answers = self.queue.get(line.rstrip(b"\r\n"), [])
                writer.write(answers.pop(0) if answers else b"Error: \n      x\n is not a softmodem command\n"
                             + PROMPT_GNB.encode())
                await writer.drain()
        finally:
            writer.close()

    async def __aenter__(self) -> SequentialReplay:
        self.server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc) -> None:
        self.server.close()
        await self.server.wait_closed()


def test_the_adapter_measures_the_replayed_patched_gnb_in_rtt_mode():
    """The real adapter, mode rtt, on the replayed gNB: it finds the UE with `o1 stats`, each of the
    UE's single-RNTI orders is a sample at the recorded distance or a GnbNoMeasurementError."""
    exchanges = [ex for ex in session("session.txt") if ex.sent.startswith((b"o1 stats", b"rtt pdcch_order"))]
    single = [(d, ex) for d, ex in orders("session.txt")
              if len(ex.sent.split()) == 3 and re.fullmatch(rb"[0-9a-f]{4}", ex.sent.split()[2])]
    rnti = int(single[0][1].sent.split()[2], 16)
    mine = [(d, ex) for d, ex in single if int(ex.sent.split()[2], 16) == rnti]
    others = [ex for d, ex in single if int(ex.sent.split()[2], 16) != rnti]

    async def run():
        async with SequentialReplay(exchanges) as rep:
            cfg = GnbConfig(port=rep.port, mode="rtt", request_timeout_s=2.0, retries=0)
            async with OaiGnbClient(cfg) as c:
                found = await c.discover()
                got = []
                for _ in mine:
                    try:
                        got.append((await c.measure(rnti)).range_m)
                    except GnbNoMeasurementError as exc:
                        got.append(str(exc))
                for ex in others:
                    with pytest.raises(GnbNoMeasurementError, match="not connected"):
                        await c.measure(int(ex.sent.split()[2], 16))
                return found, got

    found, got = asyncio.run(asyncio.wait_for(run(), 30))
    assert found == [rnti]
    for (distance_m, _), g in zip(mine, got, strict=True):
        assert isinstance(g, str) or abs(g - distance_m) <= SAMPLE_M / 2, (distance_m, g)
    measured = [isinstance(parse_rtt_reply(body(ex))[0], RttReply) for _, ex in mine]
    assert [isinstance(g, float) for g in got] == measured and sum(measured) >= 15, got


def test_the_live_rtt_tests_skip_naming_uavloc_oai_or_the_patch(tmp_path):
    """The sentences tests/test_oai_live_rtt.py skips with: UAVLOC_OAI unset, a stock build, and
    none for a build with the patch's module and gNB code."""
    from tests.test_oai_live import BUILD_FILES
    from tests.test_oai_live_rtt import PATCH_MARK, oai_rtt_build_missing

    assert oai_rtt_build_missing({}).startswith("UAVLOC_OAI is not set")
    for f in BUILD_FILES:
        (tmp_path / f).write_bytes(b"\x7fELF stock")
    why = oai_rtt_build_missing({"UAVLOC_OAI": str(tmp_path)})
    assert why.startswith(f"UAVLOC_OAI={tmp_path} is not patched with patches/oai-2025.w36/") and "README" in why
    (tmp_path / "libtelnetsrv_rtt.so").write_bytes(b"")
    assert "is not patched" in oai_rtt_build_missing({"UAVLOC_OAI": str(tmp_path)})
    (tmp_path / "nr-softmodem").write_bytes(b"\x7fELF ... " + PATCH_MARK + b" %04x")
    assert oai_rtt_build_missing({"UAVLOC_OAI": str(tmp_path)}) is None
