"""Parsers of OAI gNB replies and log lines: recorded transcripts, tables, and a fuzz.

Transcripts follow OAI's own printf formats (common/utils/telnetsrv/telnetsrv.c, telnetsrv_ci.c,
telnetsrv_o1.c, openair2/LAYER2/NR_MAC_gNB/gNB_scheduler_RA.c); the o1 stats document below is
the shape `o1 stats` prints for a gNB with two UEs.
"""

from __future__ import annotations

import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from estimator.ranging import range_m_from_raw, toa_s_from_raw
from mission.gnb.oai import (
    PROMPT_GNB,
    Msg2Record,
    RttErrorReply,
    RttReply,
    check_known_command,
    decode_reply,
    format_msg2_line,
    format_rtt_line,
    parse_force_reestab,
    parse_msg2_line,
    parse_o1_stats,
    parse_rtt_line,
    parse_rtt_reply,
    parse_single_rnti,
    parse_srs_toa_line,
    sample_from_msg2,
    sample_from_rtt,
    unknown_command_text,
)
from uavloc.errors import GnbProtocolError, GnbUnknownCommandError

O1_STATS_TWO_UES = """{
  "o1-config": {
    "BWP": {
      "dl": [{
        "bwp3gpp:isInitialBwp": true,
        "bwp3gpp:numberOfRBs": 106,
        "bwp3gpp:startRB": 0,
        "bwp3gpp:subCarrierSpacing": 30
      }],
      "ul": [{
        "bwp3gpp:isInitialBwp": true,
        "bwp3gpp:numberOfRBs": 106,
        "bwp3gpp:startRB": 0,
        "bwp3gpp:subCarrierSpacing": 30
      }]
    },
    "NRCELLDU": {
      "nrcelldu3gpp:ssbFrequency": 641280,
      "nrcelldu3gpp:arfcnDL": 640008,
      "nrcelldu3gpp:bSChannelBwDL": 40,
      "nrcelldu3gpp:arfcnUL": 640008,
      "nrcelldu3gpp:bSChannelBwUL": 40,
      "nrcelldu3gpp:nRPCI": 0,
      "nrcelldu3gpp:nRTAC": 1,
      "nrcelldu3gpp:mcc": "001",
      "nrcelldu3gpp:mnc": "01",
      "nrcelldu3gpp:sd": 16777215,
      "nrcelldu3gpp:sst": 1
    },
    "device": {
      "gnbId": 3584,
      "gnbName": "gNB-OAI",
      "vendor": "OpenAirInterface"
    }
  },
  "O1-Operational": {
    "frame-type": "tdd",
    "band-number": 78,
    "num-ues": 2,
    "ues": [17921, 45234],
    "load": 3,
    "ues-thp": [
      {"rnti": 17921, "dl": 12, "ul": 4},
      {"rnti": 45234, "dl": 0, "ul": 0}
    ]
  }
}
OK
"""

O1_STATS_NO_UE = O1_STATS_TWO_UES.replace('"num-ues": 2', '"num-ues": 0').replace(
    '"ues": [17921, 45234]', '"ues": []'
)

# the 2024 OAI Msg2 line, as written to a log file (with and without terminal colours)
MSG2_LINE = ("[NR_MAC]   UE 4601: 158.19 Generating RA-Msg2 DCI, RA RNTI 0x10b, state 1, "
             "preamble_index(RAPID) 52, timing_offset = 3 (estimated distance 117.2 [m])")
MSG2_LINE_COLOUR = "\x1b[32m" + MSG2_LINE + "\x1b[0m"


# ---------------------------------------------------------------------------------------------
# framing


def test_decode_reply_strips_prompt():
    assert decode_reply(b"single UE RNTI 4601\nsoftmodem_gnb> ") == "single UE RNTI 4601\n"


@pytest.mark.parametrize(
    "data",
    [b"single UE RNTI 4601\n", b"\xff\xfe" + PROMPT_GNB.encode(), b"a\x00b" + PROMPT_GNB.encode(),
     b"x" * (1 << 21) + PROMPT_GNB.encode(), b"softmodem_5Gue> "],
)
def test_decode_reply_rejects(data):
    with pytest.raises(GnbProtocolError):
        decode_reply(data)


def test_unknown_command_is_recognised_from_oai_text():
    body = unknown_command_text("rtt pdcch_order 4601")
    with pytest.raises(GnbUnknownCommandError, match="rtt pdcch_order 4601"):
        check_known_command(body, "rtt pdcch_order 4601")
    for parse in (parse_rtt_reply, parse_o1_stats, parse_single_rnti, parse_force_reestab):
        with pytest.raises(GnbUnknownCommandError):
            parse(body)


# ---------------------------------------------------------------------------------------------
# RTT command set


def test_rtt_reply_transcript_with_and_without_snr():
    body = ("rnti 4601 ta 3 mu 1 srs_peak 2.6250 fs 46080000 snr_db 21.4\n"
            "rnti b0b2 ta 0 mu 1 srs_peak 11.125 fs 46080000\n")
    a, b = parse_rtt_reply(body)
    assert a == RttReply(0x4601, 3, 1, 2.625, 46.08e6, 21.4)
    assert b == RttReply(0xB0B2, 0, 1, 11.125, 46.08e6, None)


def test_rtt_error_line_is_a_typed_answer():
    (r,) = parse_rtt_reply("error rnti 4601 out of coverage\n")
    assert r == RttErrorReply("error rnti 4601 out of coverage", 0x4601)
    (r,) = parse_rtt_reply("ERROR: no SRS received\n")
    assert isinstance(r, RttErrorReply) and r.rnti is None


@pytest.mark.parametrize(
    "line",
    [
        "rnti 4601 ta 3 mu 1 srs_peak 2.6 fs",  # truncated
        "rnti 4601 ta 3 mu 1 srs_peak 2.6",  # missing fs
        "rnti 4601 ta 3.5 mu 1 srs_peak 2.6 fs 46080000",  # ta not an integer
        "rnti 4601 ta 3847 mu 1 srs_peak 2.6 fs 46080000",  # ta beyond the RAR range
        "rnti 4601 ta -1 mu 1 srs_peak 2.6 fs 46080000",
        "rnti 4601 ta 3 mu 4 srs_peak 2.6 fs 46080000",  # no such numerology
        "rnti 4601 ta 3 mu 1 srs_peak -2 fs 46080000",
        "rnti 4601 ta 3 mu 1 srs_peak nan fs 46080000",
        "rnti 4601 ta 3 mu 1 srs_peak 1e999 fs 46080000",
        "rnti 4601 ta 3 mu 1 srs_peak 2.6 fs 0",
        "rnti 14601 ta 3 mu 1 srs_peak 2.6 fs 46080000",  # RNTI > 16 bit
        "rnti zz ta 3 mu 1 srs_peak 2.6 fs 46080000",
        "rnti 4601 ta 3 ta 4 mu 1 srs_peak 2.6 fs 46080000",  # duplicate key
        "rnti 4601 ta 3 mu 1 srs_peak 2.6 fs 46080000 bogus 1",
        "ta 3 rnti 4601 mu 1 srs_peak 2.6 fs 46080000",  # must start with rnti
        "rnti 4601 ta 3 mu 1 srs_peak 2.6 fs 46080000 snr_db",
        "",
    ],
)
def test_rtt_malformed_lines_raise_protocol_error_with_text(line):
    with pytest.raises(GnbProtocolError) as info:
        parse_rtt_line(line) if line else parse_rtt_reply(line)
    assert info.value.text == line  # type: ignore[attr-defined]


def test_format_and_parse_rtt_round_trip():
    line = format_rtt_line(0x4601, 17, 1, 3.875, 46.08e6, 12.25)
    r = parse_rtt_line(line)
    assert (r.rnti, r.ta, r.mu, r.srs_peak, r.fs_hz) == (0x4601, 17, 1, 3.875, 46.08e6)


def test_sample_toa_uses_estimator_ranging():
    r = RttReply(0x4601, 3, 1, 2.625, 46.08e6, 20.0)
    s = sample_from_rtt(r, t_mono_s=12.5)
    assert s.toa_s == toa_s_from_raw(3, 1, 2.625, 46.08e6)
    assert s.range_m == pytest.approx(range_m_from_raw(3, 1, 2.625, 46.08e6), rel=1e-12)
    assert s.t_mono_s == 12.5 and s.source == "rtt"
    assert s.log_fields() == {"toa_s": s.toa_s, "ta": 3, "mu": 1, "srs_peak": 2.625, "fs_hz": 46.08e6,
                              "snr_db": 20.0}


# ---------------------------------------------------------------------------------------------
# discovery


def test_o1_stats_transcript():
    stats = parse_o1_stats(O1_STATS_TWO_UES)
    assert stats.rntis == [0x4601, 0xB0B2]
    assert stats.document["o1-config"]["device"]["vendor"] == "OpenAirInterface"
    assert parse_o1_stats(O1_STATS_NO_UE).rntis == []


@pytest.mark.parametrize(
    "body",
    [
        O1_STATS_TWO_UES.replace("OK\n", ""),  # no OK
        O1_STATS_TWO_UES[:200] + "\nOK\n",  # truncated JSON
        O1_STATS_TWO_UES.replace('"num-ues": 2', '"num-ues": 3'),
        O1_STATS_TWO_UES.replace("[17921, 45234]", '["4601", 45234]'),
        O1_STATS_TWO_UES.replace("[17921, 45234]", "[17921, 17921]"),
        O1_STATS_TWO_UES.replace("[17921, 45234]", "[17921, 70000]"),
        O1_STATS_TWO_UES.replace("O1-Operational", "O1-operational"),
        "FAILURE: no parameter allowed\n",
        "[1, 2]\nOK\n",
        "[" * 100000 + "\nOK\n",
    ],
)
def test_o1_stats_malformed(body):
    with pytest.raises(GnbProtocolError):
        parse_o1_stats(body)


@pytest.mark.parametrize(
    ("body", "rnti"),
    [("single UE RNTI 4601\n", 0x4601), ("single UE RNTI 00a3\r\n", 0xA3), ("different number of UEs\n", None)],
)
def test_single_rnti_transcripts(body, rnti):
    assert parse_single_rnti(body) == rnti


@pytest.mark.parametrize("body", ["", "single UE RNTI\n", "single UE RNTI 4601x\n", "single UE RNTI 4601\nmore\n",
                                  "no parameter allowed\n"])
def test_single_rnti_malformed(body):
    with pytest.raises(GnbProtocolError):
        parse_single_rnti(body)


def test_force_reestab_transcripts():
    ok = parse_force_reestab("Reset RLC counters of UE RNTI 4601 to trigger reestablishment\n")
    assert ok.rnti == 0x4601
    bad = parse_force_reestab("RNTI needs to be [1,0xfffe]\n")
    assert bad.rnti is None and "RNTI needs" in bad.message
    with pytest.raises(GnbProtocolError):
        parse_force_reestab("Reset RLC counters of UE RNTI\n")


# ---------------------------------------------------------------------------------------------
# log lines


def test_msg2_line_transcript_plain_and_coloured():
    for line in (MSG2_LINE, MSG2_LINE_COLOUR):
        assert parse_msg2_line(line) == Msg2Record(0x4601, 158, 19, 3, 117.2, preamble=52, ra_rnti=0x10B)


def test_msg2_line_formatter_matches_parser_and_oai_distance():
    line = format_msg2_line(0xB0B2, 10, 3, 0x10B, 7, 12, 1)
    rec = parse_msg2_line(line)
    assert rec is not None and rec.rnti == 0xB0B2 and rec.timing_offset == 12
    # OAI rounds Tc to 0.509 ns: its distance is 0.08 % long
    assert rec.distance_m == pytest.approx(range_m_from_raw(12, 1), rel=1.5e-3)
    s = sample_from_msg2(rec, rnti=0xB0B2, mu=1, t_mono_s=1.0)
    assert s.source == "msg2" and s.fs_hz is None and s.toa_s == toa_s_from_raw(12, 1)


@pytest.mark.parametrize(
    "line",
    ["[NR_MAC]   UE 4601: Generating RA-Msg2 DCI, timing_offset = x3 (estimated distance 1 [m])",
     "[NR_MAC]   UE 4601: Generating RA-Msg2 DCI, timing_offset = 5000",
     "[NR_MAC]   Generating RA-Msg2 DCI timing_offset = 3 (estimated distance abc [m])",
     "[NR_MAC]   Generating RA-Msg2 DCI, timing_offset: 3"],
)
def test_msg2_malformed_raise(line):
    with pytest.raises(GnbProtocolError):
        parse_msg2_line(line)


def test_non_msg2_lines_are_none():
    assert parse_msg2_line("[NR_MAC]   Frame.Slot 128.0") is None
    assert parse_msg2_line("[NR_PHY]   timing_offset in PRACH") is None


def test_srs_toa_lines():
    rec = parse_srs_toa_line("[NR_PHY]   rxAnt 0, SRS ToA peak estimator 7, srs threshold 0.300000")
    assert rec is not None and rec.antenna == 0 and rec.peak_samples == 7.0
    rec = parse_srs_toa_line("[NR_PHY]   SRS ToA for RNTI 4601 ant 0: 391 ns")
    assert rec is not None and rec.toa_ns == 391.0
    assert parse_srs_toa_line("[NR_PHY]   Distance between gNB and UE 0.0") is None
    with pytest.raises(GnbProtocolError):
        parse_srs_toa_line("rxAnt 0, SRS ToA peak estimator inf, srs threshold 0.3")


# ---------------------------------------------------------------------------------------------
# fuzz: ≥ 10 000 generated replies, only GnbProtocolError escapes

_GOOD_RTT = "rnti 4601 ta 3 mu 1 srs_peak 2.6250 fs 46080000 snr_db 21.4\n"
_SEEDS = [_GOOD_RTT, O1_STATS_TWO_UES, "single UE RNTI 4601\n",
          "Reset RLC counters of UE RNTI 4601 to trigger reestablishment\n", MSG2_LINE,
          "rxAnt 0, SRS ToA peak estimator 7, srs threshold 0.3", "error rnti 4601 out of coverage\n"]


def _mutate(draw_data: tuple[int, int, int, str, int]) -> str:
    seed_i, cut, kind, junk, rep = draw_data
    s = _SEEDS[seed_i % len(_SEEDS)]
    if kind == 0:  # truncated
        return s[: cut % (len(s) + 1)]
    if kind == 1:  # junk spliced in
        k = cut % (len(s) + 1)
        return s[:k] + junk + s[k:]
    if kind == 2:  # oversized
        return s * (rep % 20 + 1) + junk * (rep % 7)
    if kind == 3:  # wrong numbers: replace a digit run
        return re.sub(r"[0-9]+", lambda _m: junk or "-", s, count=1 + rep % 3)
    return junk


_text = st.tuples(st.integers(0, 100), st.integers(0, 10_000), st.integers(0, 4),
                  st.text(max_size=40), st.integers(0, 1000)).map(_mutate)
_binary = st.binary(max_size=300)

_PARSERS = (parse_rtt_reply, parse_o1_stats, parse_single_rnti, parse_force_reestab, parse_msg2_line,
            parse_srs_toa_line, parse_rtt_line)


def _only_protocol_errors(text: str) -> None:
    for parse in _PARSERS:
        try:
            result = parse(text)
        except GnbProtocolError:
            continue
        if isinstance(result, list):  # RTT replies: every item is typed and ToA-able
            for r in result:
                if isinstance(r, RttReply):
                    assert sample_from_rtt(r, 0.0).toa_s >= 0


# each example is a batch of replies: 800 × 8 text + 500 × 8 binary = 10 400 generated replies
BATCH = 8


@settings(max_examples=800, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(_text, min_size=BATCH, max_size=BATCH))
def test_fuzz_text_replies_raise_only_protocol_error(texts):
    for text in texts:
        _only_protocol_errors(text)


@settings(max_examples=500, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(_binary, st.booleans()), min_size=BATCH, max_size=BATCH))
def test_fuzz_binary_replies_raise_only_protocol_error(items):
    for data, with_prompt in items:
        raw = data + (PROMPT_GNB.encode() if with_prompt else b"")
        try:
            body = decode_reply(raw)
        except GnbProtocolError:
            continue
        _only_protocol_errors(body)
