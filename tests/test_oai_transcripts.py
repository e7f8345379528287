"""The parsers and the adapter on what a real OAI 2025.w36 gNB said (recorded fixtures).

`tests/fixtures/oai-2025.w36/` holds telnet sessions and log excerpts of a real gNB and UE (see its
README). Answers are checked with the pure parsers, and replayed over TCP, segment by segment as
they were recorded, to the real adapter; the gNB log excerpts go through the random-access tracker.
"""

from __future__ import annotations

import ast
import asyncio
import contextlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

from estimator.ranging import one_way_m_per_ta_step, range_m_from_raw
from mission.gnb import GnbConfig, OaiGnbClient
from mission.gnb.oai import (
    PROMPT_GNB,
    PROMPT_UE,
    check_known_command,
    decode_reply,
    parse_force_reestab,
    parse_o1_stats,
    parse_rfsim_distance,
    parse_single_rnti,
    split_async_lines,
)
from mission.gnb.oai_ra import RandomAccess, RaTracker, RntiChange, log_time_format, parse_stamp
from uavloc.errors import GnbUnknownCommandError

FIXTURES = Path(__file__).parent / "fixtures" / "oai-2025.w36"
_LINE = re.compile(r"^(>>>|<<<)(.*?) (b'.*|b\".*)$")


def sessions(name: str) -> list[tuple[bytes, bytes, bool]]:
    """A recorded telnet session -> [(bytes sent, bytes received, whether the gNB closed the
    connection after them (an `EOF` answer, or the recorder's send failing on the closed socket))]."""
    out: list[list] = []
    for line in (FIXTURES / name).read_text().splitlines():
        m = _LINE.match(line)
        if out and ((line.startswith("<<<") and "EOF" in line.split("b'", 1)[0])
                    or line.startswith(("BrokenPipeError", "ConnectionResetError"))):
            out[-1][2] = True
        if not m:
            continue
        data = ast.literal_eval(m.group(3))
        if m.group(1) == ">>>":
            out.append([data, [], False])
        elif out and data:
            out[-1][1].append(data)
    return [(sent, b"".join(segs), closed) for sent, segs, closed in out]


def exchanges(name: str) -> list[tuple[bytes, list[bytes]]]:
    """A recorded telnet session -> [(bytes sent, [segments received])]."""
    out: list[tuple[bytes, list[bytes]]] = []
    for line in (FIXTURES / name).read_text().splitlines():
        m = _LINE.match(line)
        if not m:
            continue
        data = ast.literal_eval(m.group(3))
        if m.group(1) == ">>>":
            out.append((data, []))
        elif out and data:
            out[-1][1].append(data)
    return out


def answer(name: str, sent: bytes, prompt: str = PROMPT_GNB) -> str:
    """The first recorded answer to `sent`, up to and including the prompt, decoded."""
    for s, segs in exchanges(name):
        if s == sent:
            data = b"".join(segs)
            return decode_reply(data[: data.index(prompt.encode()) + len(prompt)], prompt)
    raise KeyError(sent)


def test_fixtures_are_the_shared_recordings():
    shared = Path(__file__).resolve().parents[2] / "shared" / "data" / "oai-2025.w36"
    if not shared.is_dir():
        pytest.skip(f"no shared data at {shared} to compare with (the fixtures are used anyway)")
    copied = [f for f in sorted(FIXTURES.glob("*.txt")) if not f.name.startswith("30_")]  # 30: ours
    assert len(copied) == 13
    for f in copied:
        assert f.read_bytes() == (shared / f.name).read_bytes(), f.name
    for name in ("gnb.conf", "ue.conf", "LICENSE.OAI"):
        assert (FIXTURES / "conf" / name).read_bytes() == (shared / "conf" / name).read_bytes(), name


def test_the_oai_tests_skip_naming_uavloc_oai_and_run_the_recorded_conf_on_free_ports(tmp_path):
    """The `oai` fixture's skip sentence, and the recorded conf files with this run's ports."""
    from tests.test_oai_live import BUILD_FILES, _conf_with_ports, oai_build_missing

    assert oai_build_missing({}).startswith("UAVLOC_OAI is not set")
    assert "ran_build/build" in oai_build_missing({"UAVLOC_OAI": ""})
    why = oai_build_missing({"UAVLOC_OAI": str(tmp_path)})
    assert why.startswith(f"UAVLOC_OAI={tmp_path} lacks nr-softmodem, nr-uesoftmodem")
    for f in BUILD_FILES:
        (tmp_path / f).write_bytes(b"")
    assert oai_build_missing({"UAVLOC_OAI": str(tmp_path)}) is None
    gnb = _conf_with_ports((FIXTURES / "conf" / "gnb.conf").read_text(), 20611, 20612)
    ue = _conf_with_ports((FIXTURES / "conf" / "ue.conf").read_text(), 20613, 20612)
    assert re.search(r"telnetsrv = \{\s*listenaddr = \"127.0.0.1\";\s*listenport = 20611;", gnb)
    assert re.search(r"rfsimulator: \{\s*serverport = 20612;\s*serveraddr = \"server\";", gnb)
    assert "listenport = 20613;" in ue and "serverport = 20612;" in ue
    assert "9099" not in gnb and "9091" not in ue


# ---------------------------------------------------------------------------------------------
# every real answer parses


def test_o1_stats_real_answers_without_and_with_a_ue():
    none = parse_o1_stats(answer("01_noue_probe_and_crash.txt", b"o1 stats\n"))
    assert none.rntis == [] and none.document["o1-config"]["device"]["vendor"] == "OpenAirInterface"
    one = parse_o1_stats(answer("05_gnb_probe_with_ue.txt", b"o1 stats\n"))
    assert one.rntis == [0x8D15]  # decimal 36117 in the document


def test_get_single_rnti_real_answers():
    assert parse_single_rnti(answer("01_noue_probe_and_crash.txt", b"ci get_single_rnti\n")) is None
    assert parse_single_rnti(answer("05_gnb_probe_with_ue.txt", b"ci get_single_rnti\n")) == 0x8D15


def test_force_reestab_real_answers_success_and_two_line_failure():
    ok = parse_force_reestab(answer("07_force_reestab_no_effect.txt", b"ci force_reestab 8d15\n"))
    assert ok.rnti == 0x8D15
    fail = parse_force_reestab(answer("01_noue_probe_and_crash.txt", b"ci force_reestab\n"))
    assert fail.rnti is None and fail.message == (
        "no UE found / could not identify UE (no UE, no such RNTI, or multiple UEs)")


def test_unknown_command_real_answers():
    for name, sent in (("01_noue_probe_and_crash.txt", b"foo bar\n"), ("02_noue_probe.txt", b"   \n")):
        with pytest.raises(GnbUnknownCommandError):
            check_known_command(answer(name, sent), sent.decode())


def test_rfsimu_output_after_the_prompt_real_answers():
    rows = []
    for s, segs in exchanges("09_setdistance_transcripts.txt"):
        if s.startswith(b"rfsimu"):
            prompt = PROMPT_GNB if b"ue0" in s else PROMPT_UE
            text = b"".join(segs).decode()
            assert text.startswith(prompt)  # the prompt comes first
            d = parse_rfsim_distance(text[len(prompt):])
            rows.append((d.offset_samples, d.distance_m))
    assert (46, 299.272) in rows and (153, 995.405) in rows and (92, 598.544) in rows and (46, None) in rows
    # arriving in front of the next answer, the late line is taken out of it
    late = "\nrfsimu_setdistance_cmd: new_offset 46, new (exact) distance 299.272 m, new delay 0.000998 ms\n"
    body, lines = split_async_lines(late + "single UE RNTI 8d15\n")
    assert body == "single UE RNTI 8d15\n" and lines == [late.strip()]
    assert parse_single_rnti(body) == 0x8D15


# ---------------------------------------------------------------------------------------------
# replayed over TCP to the adapter, segment by segment


class Replay:
    """A TCP server answering each request line with the recorded segments (nothing on connect)."""

    def __init__(self, name: str, silent: tuple[bytes, ...] = ()) -> None:
        self.answers = {s.rstrip(b"\n"): segs for s, segs in exchanges(name)}
        self.answers.update({key: [] for key in silent})  # requests a gNB that stopped answering leaves unanswered
        self.port = 0
        self.requests: list[bytes] = []

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while line := await reader.readline():
                req = line.rstrip(b"\r\n")
                self.requests.append(req)
                if req.startswith(b"exit"):
                    break
                unknown = [b"Error: \n      x\n is not a softmodem command\nsoftmodem_gnb> "]
                for seg in self.answers.get(req, unknown):
                    writer.write(seg)
                    await writer.drain()
                    await asyncio.sleep(0.002)  # separate TCP segments, as recorded
        finally:
            writer.close()

    async def __aenter__(self) -> Replay:
        self.server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc) -> None:
        self.server.close()
        await self.server.wait_closed()


def run(coro, timeout_s: float = 10.0):
    async def guarded():
        async with asyncio.timeout(timeout_s):
            return await coro

    return asyncio.run(guarded())


def test_adapter_on_the_replayed_gnb_session_with_a_ue():
    async def body():
        async with Replay("05_gnb_probe_with_ue.txt") as rep:
            cfg = GnbConfig(port=rep.port, request_timeout_s=1.0, retries=0)
            async with OaiGnbClient(cfg) as c:
                o1 = await c.discover()
            async with OaiGnbClient(GnbConfig(port=rep.port, discovery="single", retries=0)) as c:
                single = await c.discover()
                late = await c.request_late("rfsimu getdistance rfsimu_channel_ue0", wait_s=1.0)
                # not waited for: the late line lands in front of the next answer and is removed
                await c.request("rfsimu vtime")
                again = await c.discover()
                return o1, single, late, again, list(c.late_lines), rep.requests

    o1, single, late, again, late_lines, requests = run(body())
    assert o1 == single == again == [0x8D15]
    assert parse_rfsim_distance(late).offset_samples == 0
    assert late_lines and late_lines[0].startswith("rfsimu_vtime_cmd: vtime measurement")
    assert not any(r.startswith(b"ci force") for r in requests)


def test_auto_never_recommends_an_rtt_command_that_did_not_answer():
    """The recorded gNB with its UE, silent to `rtt pdcch_order` (a stock gNB that stopped
    answering): not "served", never recommended; auto says it found no way to measure, and the
    telnet server that answered is not called missing."""
    from mission.gnb.probe import probe_address

    async def body():
        free = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0)
        no_t_port = free.sockets[0].getsockname()[1]
        free.close()
        await free.wait_closed()
        async with Replay("05_gnb_probe_with_ue.txt", silent=(b"rtt pdcch_order 8d15",)) as rep:
            cfg = dict(port=rep.port, t_port=no_t_port, request_timeout_s=0.5, connect_timeout_s=0.5, retries=0)
            rtt = await probe_address(GnbConfig(mode="rtt", **cfg), count=1)
            auto = await probe_address(GnbConfig(mode="auto", **cfg), count=1)
            return rtt, auto

    rtt, auto = run(body(), timeout_s=30.0)
    served, why = rtt.modes["rtt"]
    assert not served and why.startswith("`rtt pdcch_order` did not answer (no answer"), why
    assert rtt.recommended is None and "  recommended mode: none" in rtt.lines()
    (problem,) = auto.problems
    assert problem.startswith(f"gNB at telnet://127.0.0.1:{auto.address.split(':')[1]}: no way to measure ranges: "
                              "`rtt pdcch_order` did not answer"), problem
    assert auto.recommended is None and "no telnet server" not in problem


# ---------------------------------------------------------------------------------------------
# random accesses in the real gNB log


def test_real_random_accesses_are_attributed_by_the_lines_that_prove_them():
    lines = (FIXTURES / "20_gnb_log_ra_lines.txt").read_text().splitlines()
    tracker = RaTracker()
    events = tracker.feed_all(lines)
    ras = [(e.kind, e.ue_rnti, e.tc_rnti, e.timing_offset, e.prach_delay, e.preamble)
           for e in events if isinstance(e, RandomAccess)]
    assert ras == [
        ("initial", 0x8D15, 0x8D15, 0, 0, 11),          # attach at 0 m
        ("connected", 0x8D15, 0x2A9E, 0, 0, 44),        # ciUE force_crnti_ra: a residual
        ("initial", 0xBE5C, 0xBE5C, 0, 0, 34),          # re-attach after RLC failure, 0 m
        ("connected", 0xBE5C, 0xBFD1, 0, 0, 49),        # gNB side at 300 m only: C-RNTI RA, TA 0
        ("initial", 0x5E48, 0x5E48, 8, 8, 18),          # force_RRC_IDLE at 299.3 m
        ("initial", 0xF5BF, 0xF5BF, 24, 24, 0),         # 995.4 m: after 8 aliased preambles
        ("initial", 0xF5AA, 0xF5AA, 15, 15, 17),        # 598.5 m
        ("initial", 0x5A08, 0x5A08, 0, 0, 47),          # run 3 attach
        ("connected", 0x5A08, 0x6B5C, 0, 0, 11),        # the Msg2 the old adapter took: 0 m
        ("initial", 0x5B00, 0x5B00, 8, 8, 43),          # the right one, 0.9 s later
    ]
    assert not [e for e in events if isinstance(e, RntiChange)]  # no line proves an RNTI change
    # the aliased accesses at 995 m (RAPID - 1, TA 1) are never reported
    assert tracker.dropped >= 7
    step = one_way_m_per_ta_step(1)
    for set_m, ta in ((299.272, 8), (598.544, 15)):
        assert abs(range_m_from_raw(ta, 1) - set_m) <= step


def test_an_access_is_never_given_to_a_ue_without_its_proof_line():
    lines = (FIXTURES / "20_gnb_log_ra_lines.txt").read_text().splitlines()
    without = [ln for ln in lines if "Create UE context" not in ln and "MAC CE for C-RNTI" not in ln]
    assert [e for e in RaTracker().feed_all(without)] == []


def test_log_time_stamp_kinds():
    assert log_time_format((FIXTURES / "22_gnb_startup_log_head.txt").read_text().splitlines()) == "monotonic"
    run4 = [ln for ln in (FIXTURES / "20_gnb_log_ra_lines.txt").read_text().splitlines()
            if ln.startswith("1796144868")]
    assert log_time_format(run4) == "wall_clock"
    assert parse_stamp(run4[0]) == (pytest.approx(1796144868.784254), "wall_clock")
    assert parse_stamp("2026-12-01 17:30:00.250000 UTC [NR_MAC] A x") == (pytest.approx(1796146200.25), "utc_time")
    assert log_time_format(["[NR_MAC] A UE 4601: 1.2 Generating RA-Msg2 DCI", "[TELNETSRV] Command"]) == "none"


def test_the_connected_mode_access_the_old_adapter_took_for_a_range(tmp_path):
    """Recorded with wall_clock stamps: at 299.3 m the Msg2 after `ci force_reestab 133d` was a C-RNTI
    RA (aa97, timing_offset 0: the old adapter returned 0 m and remembered aa97); the UE re-attached
    as 835c with timing_offset 8. Passive mode over the same log gives each UE its own access."""
    name = "30_gnb_log_wall_clock_crnti_ra.txt"
    lines = (FIXTURES / name).read_text().splitlines()
    assert log_time_format(lines) == "wall_clock"
    ras = [e for e in RaTracker().feed_all(lines) if isinstance(e, RandomAccess)]
    assert [(e.kind, f"{e.ue_rnti:04x}", f"{e.tc_rnti:04x}", e.timing_offset) for e in ras] == [
        ("initial", "133d", "133d", 8), ("connected", "133d", "aa97", 0), ("initial", "835c", "835c", 8),
        ("connected", "835c", "4755", 0), ("initial", "fcb7", "fcb7", 7)]
    log_path = tmp_path / "gnb.log"
    log_path.write_text("\n".join(lines) + "\n")

    async def body():
        c = OaiGnbClient(GnbConfig(mode="stock", stock_mode="passive", log_path=log_path, log_history=True),
                         wall=lambda: 1796147300.0, clock=lambda: 1000.0)
        return {r: c.passive_samples(r) for r in (0x133D, 0xAA97, 0x835C, 0xFCB7)}

    got = run(body())
    assert not got[0xAA97]
    step = one_way_m_per_ta_step(1)
    for r in (0x133D, 0x835C, 0xFCB7):
        (s,) = got[r]
        assert abs(s.range_m - 299.272) <= step and s.t_wall_s is not None
        assert s.t_mono_s == pytest.approx(1000.0 - (1796147300.0 - s.t_wall_s))


@pytest.mark.parametrize("name", [
    "01_noue_probe_and_crash.txt", "02_noue_probe.txt", "03_rfsimu_without_ue_and_exit.txt", "05_gnb_probe_with_ue.txt",
    "06_ue_telnet.txt", "07_force_reestab_no_effect.txt", "08_ue_force_crnti_ra.txt", "09_setdistance_transcripts.txt"])
def test_every_recorded_answer_is_read(name):
    """Each answer that ended with a prompt decodes, and the parser of its command accepts it."""
    if name == "03_rfsimu_without_ue_and_exit.txt":  # recorded with time stamps only, answers are bare prompts
        text = (FIXTURES / name).read_text()
        assert text.count("b'softmodem_gnb> '") == 5 and text.rstrip().endswith("EOF")
        return
    seen = 0
    for sent, segs in exchanges(name):
        data = b"".join(segs)
        prompt = PROMPT_UE if b"softmodem_5Gue> " in data else PROMPT_GNB
        if prompt.encode() not in data:
            assert data == b""  # the gNB died (01) or closed on `exit`
            continue
        cut = data.index(prompt.encode()) + len(prompt)
        body, late = split_async_lines(decode_reply(data[:cut], prompt) + data[cut:].decode())
        cmd = sent.decode().strip()
        if "is not a softmodem command" in body:
            with pytest.raises(GnbUnknownCommandError):
                check_known_command(body, cmd)
        elif cmd == "o1 stats":
            parse_o1_stats(body)
        elif cmd == "ci get_single_rnti":
            parse_single_rnti(body)
        elif cmd.startswith("ci force_reestab"):
            parse_force_reestab(body)
        elif cmd.startswith(("rfsimu setdistance", "rfsimu getdistance")) and late:
            parse_rfsim_distance(late[0])
        elif cmd.startswith("rfsimu vtime") and late:
            assert late[0].startswith("rfsimu_vtime_cmd: vtime measurement")
        seen += 1
    assert seen >= 1


# ---------------------------------------------------------------------------------------------
# the simulated gNB answers each recorded request as the real one did

#: the UE each gNB transcript was recorded with (its RNTI: requests name it), None: no UE
RECORDED_UE = {"01_noue_probe_and_crash.txt": None, "02_noue_probe.txt": None,
               "03_rfsimu_without_ue_and_exit.txt": None, "05_gnb_probe_with_ue.txt": 0x8D15,
               "07_force_reestab_no_effect.txt": 0x8D15, "09_setdistance_transcripts.txt": 0x8D15,
               "10_force_ue_release_crash.txt": 0xF5AA}
#: not compared: `help` (the simulated gNB lists the modules it has, ci, o1, rfsimu and its RTT
#: module; OAI lists seven, telnet, softmodem, loader and measur among them)
NOT_COMPARED = (b"help",)
_RNTI_HEX = re.compile(r"\b[0-9a-f]{4}\b")
_TS = re.compile(r"TS \d+")


def _normalized(data: bytes, closed: bool) -> object:
    """An answer with RNTIs and times aside: the o1 JSON document parsed, its UE list by length;
    a closed connection as such (the recording saw EOF where the simulated gNB may reset)."""
    text = data.decode("utf-8", "replace")
    if text.lstrip().startswith("{"):
        doc_text, _, rest = text.partition("\nOK\n")
        doc = json.loads(doc_text)
        ops = doc.get("O1-Operational", {})
        ops["ues"] = len(ops.get("ues", []))
        return doc, rest, closed
    return _TS.sub("TS <t>", _RNTI_HEX.sub("<rnti>", text)), closed


async def _ask(reader, writer, sent: bytes) -> tuple[bytes, bool]:
    """Send one request; what came back up to the prompt and right after it, and whether the
    connection closed."""
    got = b""
    try:
        writer.write(sent)
        await writer.drain()
        while PROMPT_GNB.encode() not in got:
            chunk = await asyncio.wait_for(reader.read(65536), 2.0)
            if not chunk:
                return got, True
            got += chunk
        with contextlib.suppress(TimeoutError):
            got += await asyncio.wait_for(reader.read(65536), 0.2)  # the rfsimulator's line
    except (ConnectionError, OSError):
        return got, True
    return got, False


@pytest.mark.parametrize("name", sorted(RECORDED_UE))
def test_the_simulated_gnb_answers_each_recorded_request_as_oai_did(name):
    """Each request of a recorded gNB session, sent in order on one connection to the simulated
    gNB with the recorded UE (or none): the same answer, RNTIs and times aside, and the
    connection closed where OAI closed it (`exit`, the crashes of 01 and 10). Requests to the
    UE's telnet server (09) are not the gNB's."""
    from sitl_scenarios.gnb import SimulatedGnb
    from sitl_scenarios.position import static_position
    from sitl_scenarios.scenario import scenario_from_dict, user_tables

    rnti = RECORDED_UE[name]
    users = [{"id": "ue", "rnti": hex(rnti if rnti is not None else 0x0777),
              "east_m": 10.0 if rnti is not None else 9000.0, "north_m": 0.0}]
    sc = scenario_from_dict({"name": "oai-transcript", "seed": 1, **user_tables(users),
                             "radio": {"coverage_m": 1000.0}})
    asked = [(s, d, c) for s, d, c in sessions(name)
             if PROMPT_UE.encode() not in d and not s.strip().startswith(NOT_COMPARED)]
    assert asked, name

    async def body():
        out = []
        async with SimulatedGnb(sc, static_position(np.array([0.0, 0.0, 40.0])), port=0,
                                stock_reaction="none") as gnb:
            reader, writer = await asyncio.open_connection("127.0.0.1", gnb.port)
            closed = False
            for sent, _data, _closed in asked:
                got = (b"", True) if closed else await _ask(reader, writer, sent)
                closed = got[1]
                out.append(got)
            writer.close()
        return out

    got = run(body())
    for (sent, data, closed), (answer_, sim_closed) in zip(asked, got, strict=True):
        assert _normalized(answer_, sim_closed) == _normalized(data, closed), sent
