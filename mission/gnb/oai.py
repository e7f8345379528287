"""Pure parsers for what an OpenAirInterface gNB says (docs/design.md §8): telnet replies and log lines.

No I/O and no clocks: the adapter (`mission/gnb/client.py`) reads bytes and lines and hands them here;
time stamps are supplied by the caller. Every parser raises :class:`GnbProtocolError` (with the
offending text in the message and in `exc.text`) on anything malformed, and nothing else.

Formats, as printed by OAI's own source (common/utils/telnetsrv, openair2/LAYER2/NR_MAC_gNB):

- prompt after every answer: ``softmodem_gnb> `` (a UE prints ``softmodem_5Gue> ``);
- unknown command: ``Error: \\n      <line>\\n is not a softmodem command\\n``;
- ``ci get_single_rnti``: ``single UE RNTI %04x`` or ``different number of UEs``;
- ``ci force_reestab [rnti]``: ``Reset RLC counters of UE RNTI %04x to trigger reestablishment``;
- ``o1 stats``: a JSON document ``{"o1-config": {...}, "O1-Operational": {"num-ues": n, "ues":
  [rnti, ...] (decimal), "ues-thp": [{"rnti": .., "dl": .., "ul": ..}], ...}}`` then ``OK``;
  failures start with ``FAILURE:``;
- Msg2 (RAR) log line: ``UE %04x: <frame>.<slot> Generating RA-Msg2 DCI, RA RNTI 0x%x, state %d,
  preamble_index(RAPID) %d, timing_offset = %d (estimated distance %.1f [m])``;
- SRS ToA log lines of the ranging branches: ``rxAnt %d, SRS ToA peak estimator %d, ...``
  (samples) or ``SRS ... ToA ...: %d ns``;
- the RTT command set of the modified gNB (uavloc's contract): one line per result,
  ``rnti <hex> ta <int> mu <int> srs_peak <float> fs <hz> [snr_db <float>]``, or a line starting
  with ``error``.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from typing import Literal

from estimator.ranging import C_MPS, MU_VALUES, TA_RAR_MAX, toa_s_from_raw
from uavloc.errors import GnbProtocolError, GnbUnknownCommandError, RangingError

PROMPT_GNB = "softmodem_gnb> "
PROMPT_UE = "softmodem_5Gue> "
UNKNOWN_COMMAND_MARK = "is not a softmodem command"
#: Largest reply the parsers accept (characters); OAI replies are a few kB at most.
MAX_REPLY_CHARS = 1 << 20
RNTI_MAX = 0xFFFF
_SHOW = 160  # characters of offending text quoted in a message

_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def protocol_error(what: str, text: str | bytes) -> GnbProtocolError:
    """A GnbProtocolError whose message quotes (a prefix of) the offending text; `exc.text` has it all."""
    shown = text[:_SHOW]
    more = f" ... ({len(text)} chars)" if len(text) > _SHOW else ""
    exc = GnbProtocolError(f"{what}: {shown!r}{more}")
    exc.text = text  # type: ignore[attr-defined]
    return exc


def strip_ansi(text: str) -> str:
    """Remove ANSI colour escapes (OAI colours its log lines on a terminal)."""
    return _ANSI.sub("", text)


# ---------------------------------------------------------------------------------------------
# framing


def decode_reply(data: bytes, prompt: str = PROMPT_GNB) -> str:
    """Bytes received up to and including the prompt -> the answer text before the prompt.

    Raises GnbProtocolError on non-UTF-8 bytes, NUL bytes, a missing prompt or an oversized reply.
    """
    if len(data) > MAX_REPLY_CHARS:
        raise protocol_error(f"reply longer than {MAX_REPLY_CHARS} bytes", data)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise protocol_error("reply is not UTF-8 text", data) from None
    if "\x00" in text:
        raise protocol_error("reply contains NUL bytes", text)
    if not text.endswith(prompt):
        raise protocol_error(f"reply does not end with the prompt {prompt!r}", text)
    return text[: -len(prompt)]


def check_known_command(body: str, request: str = "") -> str:
    """Raise GnbUnknownCommandError when the answer is OAI's unknown-command text; else return body."""
    if UNKNOWN_COMMAND_MARK in body:
        exc = GnbUnknownCommandError(
            f"the gNB does not know the command {request.strip()!r} (is its telnet module loaded, "
            f"e.g. --telnetsrv.shrmod?): {body.strip()[:_SHOW]!r}"
        )
        exc.text = body  # type: ignore[attr-defined]
        raise exc
    return body


def _lines(body: str) -> list[str]:
    return [ln.strip() for ln in strip_ansi(body).replace("\r", "").split("\n") if ln.strip()]


# ---------------------------------------------------------------------------------------------
# numbers


def parse_rnti(token: str, line: str | None = None) -> int:
    """An RNTI token (hex, optional 0x) -> int in 0..0xFFFF; errors quote `line` (default: token)."""
    where = token if line is None else line
    t = token.strip()
    if not re.fullmatch(r"(?:0[xX])?[0-9a-fA-F]{1,4}", t):
        raise protocol_error("bad RNTI (expected 1..4 hex digits)", where)
    return int(t, 16)


_INT = re.compile(r"[+-]?[0-9]{1,12}")
_FLOAT = re.compile(r"[+-]?(?:[0-9]{1,15}(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?")


def _int(token: str, what: str, line: str) -> int:
    if not _INT.fullmatch(token):
        raise protocol_error(f"{what} is not an integer", line)
    return int(token)


def _float(token: str, what: str, line: str) -> float:
    if not _FLOAT.fullmatch(token):
        raise protocol_error(f"{what} is not a number", line)
    v = float(token)
    if not math.isfinite(v):
        raise protocol_error(f"{what} is not finite", line)
    return v


# ---------------------------------------------------------------------------------------------
# RTT command set


@dataclass(frozen=True)
class RttReply:
    """One result line of the RTT command set (raw fields exactly as the gNB printed them).

    ta: absolute timing advance (0..3846); mu: numerology; srs_peak: SRS CIR peak [samples at
    fs_hz, may be fractional]; fs_hz: sampling rate [Hz]; snr_db: SRS SNR [dB] or None.
    """

    rnti: int
    ta: int
    mu: int
    srs_peak: float
    fs_hz: float
    snr_db: float | None = None


@dataclass(frozen=True)
class RttErrorReply:
    """A line starting with `error`: the gNB could not measure (the text says why)."""

    message: str
    rnti: int | None = None


_RTT_KEYS_REQUIRED = ("rnti", "ta", "mu", "srs_peak", "fs")
_RTT_KEYS = (*_RTT_KEYS_REQUIRED, "snr_db")
_ERROR_RNTI = re.compile(r"\brnti\s+(?:0x)?([0-9a-fA-F]{1,4})\b")


def parse_rtt_line(line: str) -> RttReply | RttErrorReply:
    """Parse one RTT result line (`rnti <hex> ta <int> mu <int> srs_peak <float> fs <hz>
    [snr_db <float>]`) or an `error ...` line."""
    s = strip_ansi(line).strip()
    if len(s) > 512:
        raise protocol_error("RTT line too long", line)
    if s[:5].lower() == "error":
        m = _ERROR_RNTI.search(s)
        rnti = int(m.group(1), 16) if m else None
        return RttErrorReply(message=s, rnti=rnti)
    tokens = s.split()
    if len(tokens) % 2 != 0 or not tokens:
        raise protocol_error("RTT line is not `key value` pairs", line)
    fields: dict[str, str] = {}
    for key, value in zip(tokens[::2], tokens[1::2], strict=True):
        if key not in _RTT_KEYS:
            raise protocol_error(f"unknown key {key[:20]!r} in RTT line", line)
        if key in fields:
            raise protocol_error(f"duplicate key {key!r} in RTT line", line)
        fields[key] = value
    missing = [k for k in _RTT_KEYS_REQUIRED if k not in fields]
    if missing:
        raise protocol_error(f"RTT line lacks {', '.join(missing)}", line)
    if tokens[0] != "rnti":
        raise protocol_error("RTT line must start with `rnti`", line)
    rnti = parse_rnti(fields["rnti"], line)
    ta = _int(fields["ta"], "ta", line)
    if not 0 <= ta <= TA_RAR_MAX:
        raise protocol_error(f"ta outside 0..{TA_RAR_MAX}", line)
    mu = _int(fields["mu"], "mu", line)
    if mu not in MU_VALUES:
        raise protocol_error(f"mu not one of {MU_VALUES}", line)
    peak = _float(fields["srs_peak"], "srs_peak", line)
    if peak < 0:
        raise protocol_error("srs_peak is negative", line)
    fs = _float(fields["fs"], "fs", line)
    if not 1e3 <= fs <= 1e10:
        raise protocol_error("fs outside 1 kHz..10 GHz", line)
    snr = _float(fields["snr_db"], "snr_db", line) if "snr_db" in fields else None
    if snr is not None and not -100 <= snr <= 200:
        raise protocol_error("snr_db outside -100..200 dB", line)
    return RttReply(rnti=rnti, ta=ta, mu=mu, srs_peak=peak, fs_hz=fs, snr_db=snr)


def parse_rtt_reply(body: str) -> list[RttReply | RttErrorReply]:
    """Parse the answer of the RTT command (text before the prompt): one result per line, ≥ 1."""
    check_known_command(body)
    if len(body) > MAX_REPLY_CHARS:
        raise protocol_error("RTT reply too long", body)
    lines = _lines(body)
    if not lines:
        raise protocol_error("empty RTT reply", body)
    return [parse_rtt_line(ln) for ln in lines]


# ---------------------------------------------------------------------------------------------
# typed sample


@dataclass(frozen=True)
class RttSample:
    """One range measurement of one UE, as the controller and the mission log use it.

    rnti: the UE (as asked for); ta, mu, srs_peak, fs_hz, snr_db: raw gNB fields (fs_hz None and
    srs_peak 0 for a coarse, Msg2-only sample); toa_s: one-way time of arrival [s] computed with
    estimator.ranging; t_mono_s: monotonic time of the measurement [s] (supplied by the caller);
    source: "rtt" (RTT command set), "trace" (a stock gNB's T tracer: RAR TA plus applied TA
    commands plus SRS peak) or "msg2" (stock modes, coarse TA only); t_wall_s: UNIX time of the
    random access from the gNB log's `wall_clock` stamp (stock modes) or of the SRS occasion from
    the T trace (trace mode); None otherwise. t_unc_s: half-width [s, monotonic] of the interval
    around t_mono_s within which it was measured (a telnet answer: half the time from the request's
    send to the answer's receipt; a gNB stamp: the uncertainty of its clock offset); the placer
    prices it against σ(d) (mission.control.timing).
    """

    rnti: int
    ta: int
    mu: int
    srs_peak: float
    fs_hz: float | None
    snr_db: float | None
    toa_s: float
    t_mono_s: float
    source: Literal["rtt", "msg2", "trace"] = "rtt"
    t_wall_s: float | None = None
    t_unc_s: float = 0.0

    @property
    def range_m(self) -> float:
        """One-way range C · τ̂ [m]."""
        return C_MPS * self.toa_s

    def log_fields(self) -> dict:
        """The raw and derived fields of a mission-log `rtt` record (docs/design.md §10)."""
        out: dict = {"toa_s": self.toa_s, "ta": self.ta, "mu": self.mu, "srs_peak": self.srs_peak}
        if self.fs_hz is not None:
            out["fs_hz"] = self.fs_hz
        if self.snr_db is not None:
            out["snr_db"] = self.snr_db
        return out


def sample_from_rtt(reply: RttReply, t_mono_s: float, t_unc_s: float = 0.0) -> RttSample:
    """RttReply + monotonic time (± t_unc_s) -> RttSample (τ̂ = (TA·step + peak/fs) / 2 via estimator.ranging)."""
    try:
        toa = toa_s_from_raw(reply.ta, reply.mu, reply.srs_peak, reply.fs_hz)
    except RangingError as exc:
        raise protocol_error(f"RTT fields do not give a ToA ({exc})", repr(reply)) from None
    return RttSample(reply.rnti, reply.ta, reply.mu, reply.srs_peak, reply.fs_hz, reply.snr_db, toa,
                     float(t_mono_s), "rtt", t_unc_s=float(t_unc_s))


# ---------------------------------------------------------------------------------------------
# discovery


@dataclass(frozen=True)
class O1Stats:
    """The part of `o1 stats` uavloc uses: the connected UEs' RNTIs, plus the whole document."""

    rntis: list[int]
    document: dict


def parse_o1_stats(body: str) -> O1Stats:
    """Parse `o1 stats`: a JSON document followed by a line `OK`."""
    check_known_command(body)
    if len(body) > MAX_REPLY_CHARS:
        raise protocol_error("o1 stats reply too long", body)
    text = strip_ansi(body).replace("\r", "").rstrip()
    if text.lstrip().startswith("FAILURE"):
        raise protocol_error("o1 stats failed", body)
    if not text.endswith("OK"):
        raise protocol_error("o1 stats reply does not end with OK", body)
    doc_text = text[: -len("OK")]
    try:
        doc = json.loads(doc_text)
    except (ValueError, RecursionError):
        raise protocol_error("o1 stats reply is not a JSON document followed by OK", body) from None
    if not isinstance(doc, dict):
        raise protocol_error("o1 stats JSON is not an object", body)
    op = doc.get("O1-Operational")
    if not isinstance(op, dict):
        raise protocol_error("o1 stats JSON has no object `O1-Operational`", body)
    ues = op.get("ues")
    if not isinstance(ues, list):
        raise protocol_error("o1 stats `O1-Operational.ues` is not a list", body)
    rntis: list[int] = []
    for v in ues:
        if isinstance(v, bool) or not isinstance(v, int) or not 0 < v <= RNTI_MAX:
            raise protocol_error(f"o1 stats UE RNTI {v!r} is not an integer 1..65535", body)
        rntis.append(v)
    n = op.get("num-ues")
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n != len(rntis)):
        raise protocol_error(f"o1 stats num-ues {n!r} does not match {len(rntis)} RNTIs", body)
    if len(set(rntis)) != len(rntis):
        raise protocol_error("o1 stats lists an RNTI twice", body)
    return O1Stats(rntis=rntis, document=doc)


_SINGLE = re.compile(r"single UE RNTI ([0-9a-fA-F]{1,4})")


def parse_single_rnti(body: str) -> int | None:
    """Parse `ci get_single_rnti`: the RNTI, or None when the gNB has not exactly one UE."""
    check_known_command(body)
    lines = _lines(body[:4096]) if len(body) <= 4096 else None
    if lines is None or len(lines) != 1:
        raise protocol_error("get_single_rnti answer is not one line", body)
    (line,) = lines
    if line == "different number of UEs":
        return None
    m = _SINGLE.fullmatch(line)
    if not m:
        raise protocol_error("get_single_rnti answer is not `single UE RNTI <hex>`", body)
    return int(m.group(1), 16)


@dataclass(frozen=True)
class ReestabReply:
    """`ci force_reestab` answer: the RNTI it triggered, or None with OAI's reason (all its lines)."""

    rnti: int | None
    message: str


_REESTAB = re.compile(r"Reset RLC counters of UE RNTI ([0-9a-fA-F]{1,4}) to trigger reestablishment")
#: first lines of OAI's failures (telnetsrv_ci.c: fetch_rnti, then trigger_reestab's ERROR_MSG_RET)
_CI_FAILURES = ("no UE found", "RNTI needs to be", "no MAC/RLC present")
_CI_FAILURE_TAIL = "could not identify UE"


def parse_force_reestab(body: str) -> ReestabReply:
    """Parse `ci force_reestab`: the success line, or OAI's failure text.

    OAI 2025.w36 prints a failure as two lines (`no UE found` or `RNTI needs to be [1,0xfffe]`,
    then `could not identify UE (no UE, no such RNTI, or multiple UEs)`); one-line failures of
    older versions are accepted too.
    """
    check_known_command(body)
    lines = _lines(body[:4096]) if len(body) <= 4096 else None
    if not lines or len(lines) > 2:
        raise protocol_error("force_reestab answer is not one or two lines", body)
    m = _REESTAB.fullmatch(lines[0])
    if m and len(lines) == 1:
        return ReestabReply(rnti=int(m.group(1), 16), message=lines[0])
    if any(lines[0].startswith(f) for f in _CI_FAILURES) and (
            len(lines) == 1 or lines[1].startswith(_CI_FAILURE_TAIL)):
        return ReestabReply(rnti=None, message=" / ".join(lines))
    if len(lines) == 1 and lines[0].startswith(_CI_FAILURE_TAIL):
        return ReestabReply(rnti=None, message=lines[0])
    raise protocol_error("force_reestab answer not understood", body)


# ---------------------------------------------------------------------------------------------
# rfsimulator commands (their output is queued to the rfsim thread and arrives after the prompt)


@dataclass(frozen=True)
class RfsimDistance:
    """`rfsimu setdistance` / `getdistance` output: offset [samples], distance [m] (set only; None
    for getdistance), one-way delay [ms]."""

    offset_samples: int
    distance_m: float | None
    delay_ms: float


_RFSIM_SET = re.compile(r"rfsimu_setdistance_cmd: new_offset (\S+), new \(exact\) distance (\S+) m, "
                        r"new delay (\S+) ms")
_RFSIM_GET = re.compile(r"rfsimu_getdistance_cmd: \S+ offset (\S+) delay (\S+) ms")
#: a line printed by an rfsimu command; it may arrive after the prompt, i.e. before the next answer
ASYNC_LINE = re.compile(r"^\s*rfsimu_\w+_cmd:[^\n]*\n?", re.MULTILINE)


def parse_rfsim_distance(text: str) -> RfsimDistance:
    """The rfsimu distance line in `text` (the answer plus what followed the prompt)."""
    s = strip_ansi(text)
    if len(s) > 4096:
        raise protocol_error("rfsimu answer too long", text)
    m = _RFSIM_SET.search(s)
    if m:
        return RfsimDistance(_int(m.group(1), "new_offset", text), _float(m.group(2), "distance", text),
                             _float(m.group(3), "delay", text))
    m = _RFSIM_GET.search(s)
    if m:
        return RfsimDistance(_int(m.group(1), "offset", text), None, _float(m.group(2), "delay", text))
    raise protocol_error("no rfsimu distance line (the rfsim thread prints it only while a peer is "
                         "connected)", text)


def split_async_lines(body: str) -> tuple[str, list[str]]:
    """Remove late `rfsimu_*_cmd:` lines (output of an earlier rfsimu command) from an answer.

    Returns (the answer without them, the removed lines). OAI queues rfsimu commands to the rfsim
    thread, so their output follows the prompt and lands in front of the next answer.
    """
    found = [m.group(0).strip() for m in ASYNC_LINE.finditer(body)]
    if not found:
        return body, []
    rest = ASYNC_LINE.sub("", body)
    return (rest.lstrip("\n") if rest.strip() else ""), found


# ---------------------------------------------------------------------------------------------
# gNB log lines (stock fallback and research branches)


@dataclass(frozen=True)
class Msg2Record:
    """A Msg2 (RAR) log line: the access's temporary RNTI (None if the line has none), frame.slot,
    the absolute RAR timing advance `timing_offset`, OAI's own distance estimate [m] (None if
    absent), the preamble index (RAPID) and the RA-RNTI (None when the line lacks them).

    The RNTI is the TC-RNTI of this random access, never an existing C-RNTI: which UE made the
    access is known only from later lines (see `mission.gnb.oai_ra`).
    """

    rnti: int | None
    frame: int | None
    slot: int | None
    timing_offset: int
    distance_m: float | None
    preamble: int | None = None
    ra_rnti: int | None = None


_MSG2_MARK = "timing_offset"
_MSG2 = re.compile(r"timing_offset\s*=\s*(\S+)(?:\s*\(estimated distance\s+(\S+)\s*\[m\]\))?")
_MSG2_UE = re.compile(r"\bUE ([0-9a-fA-F]{4}):\s*(?:([0-9]{1,5})\.([0-9]{1,3})\s)?")
_MSG2_RAPID = re.compile(r"preamble_index\(RAPID\)\s*(\S+?),")
_MSG2_RA_RNTI = re.compile(r"RA RNTI 0x([0-9a-fA-F]{1,4})\b")


def parse_msg2_line(line: str) -> Msg2Record | None:
    """A gNB log line -> Msg2Record, None when the line is not a Msg2 line; GnbProtocolError when it
    is one but its numbers are malformed."""
    if _MSG2_MARK not in line or "Msg2" not in line:
        return None
    s = strip_ansi(line)
    if len(s) > 2048:
        raise protocol_error("Msg2 log line too long", line)
    m = _MSG2.search(s)
    if not m:
        raise protocol_error("Msg2 log line without `timing_offset = N`", line)
    ta = _int(m.group(1), "timing_offset", line)
    if not 0 <= ta <= TA_RAR_MAX:
        raise protocol_error(f"timing_offset outside 0..{TA_RAR_MAX}", line)
    dist = None
    if m.group(2) is not None:
        dist = _float(m.group(2), "estimated distance", line)
    ue = _MSG2_UE.search(s)
    rnti = frame = slot = None
    if ue:
        rnti = int(ue.group(1), 16)
        if ue.group(2) is not None:
            frame, slot = int(ue.group(2)), int(ue.group(3))
    preamble = None
    if (mp := _MSG2_RAPID.search(s)) is not None:
        preamble = _int(mp.group(1), "preamble_index", line)
        if not 0 <= preamble <= 63:
            raise protocol_error("preamble_index outside 0..63", line)
    mr = _MSG2_RA_RNTI.search(s)
    ra_rnti = int(mr.group(1), 16) if mr else None
    return Msg2Record(rnti=rnti, frame=frame, slot=slot, timing_offset=ta, distance_m=dist,
                      preamble=preamble, ra_rnti=ra_rnti)


@dataclass(frozen=True)
class SrsToaRecord:
    """An SRS ToA log line of a ranging branch: the peak in samples, or a ToA in ns."""

    antenna: int | None
    peak_samples: float | None
    toa_ns: float | None


_SRS_PEAK = re.compile(r"(?:rxAnt\s+([0-9]{1,3}),\s*)?SRS ToA peak estimator\s+([^\s,]+)")
_SRS_NS = re.compile(r"SRS\b.*?\bToA\b[^:]*:\s*([^\s,]+)\s*ns")


def parse_srs_toa_line(line: str) -> SrsToaRecord | None:
    """A gNB log line -> SrsToaRecord, None when it is not an SRS ToA line."""
    if "SRS" not in line or "ToA" not in line:
        return None
    s = strip_ansi(line)
    if len(s) > 2048:
        raise protocol_error("SRS ToA log line too long", line)
    m = _SRS_PEAK.search(s)
    if m:
        ant = int(m.group(1)) if m.group(1) is not None else None
        return SrsToaRecord(antenna=ant, peak_samples=_float(m.group(2), "SRS ToA peak", line), toa_ns=None)
    m = _SRS_NS.search(s)
    if m:
        return SrsToaRecord(antenna=None, peak_samples=None, toa_ns=_float(m.group(1), "SRS ToA", line))
    return None


def sample_from_msg2(rec: Msg2Record, rnti: int, mu: int, t_mono_s: float,
                     t_wall_s: float | None = None, t_unc_s: float = 0.0) -> RttSample:
    """A coarse RttSample from a Msg2 timing advance (μ of the UL BWP supplied by the caller)."""
    try:
        toa = toa_s_from_raw(rec.timing_offset, mu)
    except RangingError as exc:
        raise protocol_error(f"Msg2 timing_offset does not give a ToA ({exc})", repr(rec)) from None
    return RttSample(rnti, rec.timing_offset, mu, 0.0, None, None, toa, float(t_mono_s), "msg2",
                     None if t_wall_s is None else float(t_wall_s), float(t_unc_s))


# ---------------------------------------------------------------------------------------------
# formatting (used by the simulated gNB; the inverse of the parsers above)


def format_rtt_line(rnti: int, ta: int, mu: int, srs_peak: float, fs_hz: float, snr_db: float | None) -> str:
    """`rnti <hex> ta <int> mu <int> srs_peak <float> fs <hz> [snr_db <float>]` (no newline)."""
    s = f"rnti {rnti:04x} ta {ta} mu {mu} srs_peak {srs_peak:.4f} fs {fs_hz:.0f}"
    return s if snr_db is None else f"{s} snr_db {snr_db:.1f}"


def format_msg2_line(rnti: int, frame: int, slot: int, ra_rnti: int, preamble: int, ta: int, mu: int) -> str:
    """OAI's Msg2 log line (gNB_scheduler_RA.c) with its distance estimate, `[NR_MAC] A` prefix
    (no time stamp)."""
    # OAI: distance = C · (TA · 0.509 ns · 16 · 64 / 2^μ) / 2
    rtt_ns = 0.509 * 16 * 64 / (1 << mu) * ta
    dist = C_MPS * rtt_ns * 1e-9 / 2
    return (f"[NR_MAC] A UE {rnti:04x}: {frame}.{slot} Generating RA-Msg2 DCI, RA RNTI 0x{ra_rnti:x}, "
            f"state 1, preamble_index(RAPID) {preamble}, timing_offset = {ta} (estimated distance "
            f"{dist:.1f} [m])")


def unknown_command_text(line: str) -> str:
    """OAI's answer to an unknown command (telnetsrv.c), before the prompt."""
    return f"Error: \n      {line}\n is not a softmodem command\n"
