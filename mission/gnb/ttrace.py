"""OAI's T tracer: the wire format and the events that carry a UE's round trip (pure functions).

A stock OAI gNB started with ``--T_stdout 2 --T_nowait`` serves its T tracer on TCP port 2021
(``--T_port``). The protocol, as OAI 2025.w36 (`common/utils/T/tracer/record.c`, `utils.c`,
`local_tracer.c`) has it:

- the client sends one byte ``1`` (T_ENABLE), an int32 N and N int32 flags (1 = on), one per
  event in the order of the server's ``T_messages.txt``;
- the server sends frames: int32 length (of what follows), ``struct timespec`` (int64 s, int64
  ns, CLOCK_REALTIME), int32 event id, then the fields in the order of that event's ``FORMAT``
  line: ``int`` int32, ``ulong`` uint64, ``float`` float32, ``string`` NUL-terminated, ``buffer``
  int32 length + bytes; all little-endian;
- on connect the server first sends its own ``T_messages.txt`` as event −1 (a buffer: the file's
  bytes, in one or more chunks) and then event −2 (no fields). Event ids are the 0-based
  positions of the file's ``ID =`` lines; they shift between OAI versions, so they are always
  taken from that file, never hard-coded.

The events read here (`../shared/data/oai-2025.w36-ttrace/README.md`):

- ``GNB_MAC_DL_RAR_PDU_WITH_DATA``: the RAR, whose MAC RAR holds the 12-bit absolute TA and the
  temporary C-RNTI (TS 38.321 §6.2.3);
- ``GNB_MAC_DL_PDU_WITH_DATA``: a UE's DL MAC PDU; a Timing Advance Command MAC CE (LCID 61, one
  octet TAG(2) | TA(6), TS 38.321 §6.1.3.4; 31 = no change) rides on one every 100 frames;
- ``GNB_PHY_UL_TIME_CHANNEL_ESTIMATE``: the SRS channel impulse response, int16 I/Q, FFT-shifted
  so that zero delay is at index N/2;
- ``GNB_PHY_UL_SRS_TOA_NS`` (newer OAI branches only): the SRS ToA in ns, 8× oversampled;
- ``ENB_PHY_INITIATE_RA_PROCEDURE``: the PRACH detection (its ``delay`` is the PRACH TA).

Every parser raises :class:`uavloc.errors.GnbProtocolError` naming what was malformed.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from uavloc.errors import GnbProtocolError

#: the frame header after the length: timespec (int64 s, int64 ns) + int32 id
_HEAD = struct.Struct("<qqi")
_INT32 = struct.Struct("<i")
#: special ids the server sends first: its T_messages.txt (buffer chunks), then the end of it
ID_MESSAGES_TXT = -1
ID_MESSAGES_END = -2
#: the one byte that starts a client's event mask (T_ENABLE in `common/utils/T/T_defs.h`)
T_ENABLE = 1
#: frames longer than this are refused as a corrupt stream [bytes] (an SRS estimate of 273 PRB
#: with 4096-point FFT is 16 KiB; a T_messages.txt chunk is at most the whole file)
MAX_FRAME_BYTES = 8 << 20

EV_RAR = "GNB_MAC_DL_RAR_PDU_WITH_DATA"
EV_DL_PDU = "GNB_MAC_DL_PDU_WITH_DATA"
EV_DL_RETX = "GNB_MAC_RETRANSMISSION_DL_PDU_WITH_DATA"
EV_SRS_CHEST = "GNB_PHY_UL_TIME_CHANNEL_ESTIMATE"
EV_SRS_TOA_NS = "GNB_PHY_UL_SRS_TOA_NS"
EV_PRACH = "ENB_PHY_INITIATE_RA_PROCEDURE"
#: the events the trace mode asks for (those absent from a gNB's T_messages.txt are skipped)
RANGING_EVENTS = (EV_RAR, EV_DL_PDU, EV_DL_RETX, EV_SRS_CHEST, EV_SRS_TOA_NS, EV_PRACH)

_FIELD_TYPES = ("int", "ulong", "float", "string", "buffer")


def _error(what: str, data: bytes | str = b"") -> GnbProtocolError:
    shown = data[:64] if data else data
    return GnbProtocolError(f"T tracer: {what}" + (f" (got {shown!r})" if shown else ""))


# ---------------------------------------------------------------------------------------------
# the event database (T_messages.txt)


@dataclass(frozen=True)
class EventDef:
    """One event of T_messages.txt: id (its 0-based position), name, fields [(type, name), ...]."""

    id: int
    name: str
    fields: tuple[tuple[str, str], ...]


@dataclass(frozen=True)
class TMessages:
    """The event database of one OAI build: events in id order."""

    events: tuple[EventDef, ...]

    def id_of(self, name: str) -> int | None:
        """The id of event `name`, None when this build has no such event."""
        for ev in self.events:
            if ev.name == name:
                return ev.id
        return None

    def by_id(self, event_id: int) -> EventDef:
        if not 0 <= event_id < len(self.events):
            raise _error(f"event id {event_id} is not in this T_messages.txt ({len(self.events)} events): "
                         "is it the gNB's own?")
        return self.events[event_id]

    def mask(self, names: tuple[str, ...] | list[str]) -> bytes:
        """What a client sends to turn on the events `names` (present ones) and off every other:
        byte T_ENABLE, int32 N, N int32 flags."""
        on = {self.id_of(n) for n in names} - {None}
        flags = [1 if ev.id in on else 0 for ev in self.events]
        return bytes([T_ENABLE]) + struct.pack(f"<i{len(flags)}i", len(flags), *flags)


_ID_RE = re.compile(r"^\s*ID\s*=\s*(\S+)\s*$")
_FORMAT_RE = re.compile(r"^\s*FORMAT\s*=\s*(.*?)\s*$")


def parse_t_messages(text: str) -> TMessages:
    """T_messages.txt (OAI's `common/utils/T/T_messages.txt`) -> TMessages.

    Ids are the positions of the ``ID =`` lines; each event's ``FORMAT = type,name : type,name``
    line gives its fields (an event without one has none). GnbProtocolError on a file without
    events, a field type T does not know, or a FORMAT line outside an event.
    """
    names: list[str] = []
    formats: dict[int, tuple[tuple[str, str], ...]] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("#"):
            continue
        m = _ID_RE.match(line)
        if m:
            names.append(m.group(1))
            continue
        m = _FORMAT_RE.match(line)
        if m:
            if not names:
                raise _error(f"T_messages.txt line {lineno}: FORMAT before any ID", line)
            fields = []
            for part in m.group(1).split(":"):
                part = part.strip()
                if not part:
                    continue
                typ, sep, name = part.partition(",")
                typ, name = typ.strip(), name.strip()
                if not sep or typ not in _FIELD_TYPES or not name:
                    raise _error(f"T_messages.txt line {lineno}: field {part!r} is not 'type,name' with a type "
                                 f"of {', '.join(_FIELD_TYPES)}", line)
                fields.append((typ, name))
            formats[len(names) - 1] = tuple(fields)
    if not names:
        raise _error("T_messages.txt holds no event (no 'ID =' line)", text[:64])
    return TMessages(tuple(EventDef(i, n, formats.get(i, ())) for i, n in enumerate(names)))


# ---------------------------------------------------------------------------------------------
# frames and events


@dataclass(frozen=True)
class TEvent:
    """One decoded event: id, name, t_wall_s (the gNB's CLOCK_REALTIME when it was traced [s]),
    values (field name -> int, float, str or bytes, in FORMAT order)."""

    id: int
    name: str
    t_wall_s: float
    values: dict[str, int | float | str | bytes]


def split_frames(data: bytes | bytearray) -> tuple[list[bytes], int]:
    """Cut a byte stream into frames: ([frame body, ...], bytes consumed). A frame is an int32
    length then that many bytes; an incomplete last frame is left for the next call."""
    frames: list[bytes] = []
    off, n = 0, len(data)
    while n - off >= 4:
        (length,) = _INT32.unpack_from(data, off)
        if not _HEAD.size <= length <= MAX_FRAME_BYTES:
            raise _error(f"frame length {length} at byte {off} is not a T frame (the stream is out of step, or "
                         "this is not a T tracer)", bytes(data[off:off + 16]))
        if n - off - 4 < length:
            break
        frames.append(bytes(data[off + 4:off + 4 + length]))
        off += 4 + length
    return frames, off


def frame_head(body: bytes) -> tuple[float, int]:
    """A frame body's (t_wall_s, event id)."""
    if len(body) < _HEAD.size:
        raise _error(f"frame of {len(body)} bytes is shorter than its header", body)
    s, ns, event_id = _HEAD.unpack_from(body, 0)
    return s + ns * 1e-9, event_id


def decode_event(body: bytes, db: TMessages) -> TEvent:
    """One frame body -> TEvent, its fields decoded by the event's FORMAT in `db`."""
    t_wall_s, event_id = frame_head(body)
    if event_id == ID_MESSAGES_TXT:
        return TEvent(event_id, "T_MESSAGES_TXT", t_wall_s, {"data": _buffer(body, _HEAD.size, "T_messages.txt")[0]})
    if event_id == ID_MESSAGES_END:
        return TEvent(event_id, "T_MESSAGES_END", t_wall_s, {})
    ev = db.by_id(event_id)
    off = _HEAD.size
    values: dict[str, int | float | str | bytes] = {}
    for typ, name in ev.fields:
        try:
            if typ == "int":
                (values[name],) = _INT32.unpack_from(body, off)
                off += 4
            elif typ == "ulong":
                (values[name],) = struct.unpack_from("<Q", body, off)
                off += 8
            elif typ == "float":
                (values[name],) = struct.unpack_from("<f", body, off)
                off += 4
            elif typ == "string":
                end = body.index(b"\0", off)
                values[name] = body[off:end].decode("utf-8", "replace")
                off = end + 1
            else:
                values[name], off = _buffer(body, off, f"{ev.name}.{name}")
        except (struct.error, ValueError):
            raise _error(f"{ev.name} ends before its field {name!r} ({len(body)} bytes)", body) from None
    if off != len(body):
        raise _error(f"{ev.name} has {len(body) - off} byte(s) after its last field: is this T_messages.txt "
                     "the gNB's own?", body[off:])
    return TEvent(event_id, ev.name, t_wall_s, values)


def _buffer(body: bytes, off: int, what: str) -> tuple[bytes, int]:
    (n,) = _INT32.unpack_from(body, off)
    if n < 0 or off + 4 + n > len(body):
        raise _error(f"{what}: buffer length {n} exceeds the frame", body[off:off + 8])
    return body[off + 4:off + 4 + n], off + 4 + n


class TMessagesAssembler:
    """Collects the server's own T_messages.txt (events −1, then −2) from the first frames of a
    connection; `db` is set once event −2 arrived."""

    def __init__(self) -> None:
        self._chunks: list[bytes] = []
        self.db: TMessages | None = None

    def feed(self, body: bytes) -> bool:
        """Take one frame; True when it belonged to the T_messages.txt preamble."""
        _, event_id = frame_head(body)
        if event_id == ID_MESSAGES_TXT:
            self._chunks.append(_buffer(body, _HEAD.size, "T_messages.txt")[0])
            return True
        if event_id == ID_MESSAGES_END:
            self.db = parse_t_messages(b"".join(self._chunks).decode("utf-8", "replace"))
            self._chunks = []
            return True
        return False


def recording_preamble(data: bytes | bytearray) -> tuple[TMessages | None, int]:
    """A recording's own T_messages.txt (the server's events −1, then −2, at its start) and how many
    frames it spans: (db, frames), or (None, 0) for a recording that does not start with one.

    GnbProtocolError naming what is wrong: an empty recording; one that ends inside the preamble
    (cut at byte N: the recording was stopped, or the file truncated, before the server had sent
    its T_messages.txt); bytes that are not T frames."""
    n = len(data)
    if n == 0:
        raise _error("the recording is empty (0 bytes): nothing was recorded (was `record` stopped at once, "
                     "or the file overwritten?)")
    frames, used = split_frames(data)
    asm = TMessagesAssembler()
    for i, body in enumerate(frames):
        if not asm.feed(body):
            if i:
                raise _error(f"the recording's T_messages.txt preamble ends at byte {used} without its end marker "
                             "(event -2): the recording is damaged")
            return None, 0
        if asm.db is not None:
            return asm.db, i + 1
    # every whole frame was preamble (or there was none): the recording ends inside it, or in its
    # first frame
    if frames or (n - used >= 4 + _HEAD.size and frame_head(bytes(data[used + 4:used + 4 + _HEAD.size]))[1]
                  in (ID_MESSAGES_TXT, ID_MESSAGES_END)):
        where = (f"its frame at byte {used} needs {4 + _INT32.unpack_from(data, used)[0]} bytes" if n - used >= 4
                 else "before its end marker, event -2")
        raise _error(f"the recording is cut inside the gNB's T_messages.txt preamble at byte {n} ({where}): it was "
                     "stopped, or the file truncated, before the T server had sent its event database; record "
                     "again (OAI's `record` keeps the whole preamble)")
    raise _error(f"the recording is cut at byte {n}, inside its first frame (of {4 + _INT32.unpack_from(data, 0)[0]} "
                 "bytes)" if n >= 4 else f"the recording is {n} byte(s) long: not even one frame header")


def iter_recording(data: bytes, db: TMessages | None = None) -> Iterator[TEvent]:
    """Every event of a recording made with OAI's `record` (or read off the socket), in order.

    The recording's own T_messages.txt preamble (events −1, −2: the gNB's that recorded it) is
    always used when it has one; `db` (the gNB's T_messages.txt) only for a recording without one.
    A truncated last frame is dropped (a recording stopped mid-write). GnbProtocolError for an
    empty recording, one cut inside its preamble (:func:`recording_preamble`), or one without a
    preamble and without `db`."""
    own, skip = recording_preamble(data)
    if own is not None:
        db = own
    elif db is None:
        raise _error("the recording does not start with the gNB's T_messages.txt (events -1, -2): pass the "
                     "gNB's T_messages.txt")
    frames, _ = split_frames(data)
    for body in frames[skip:]:
        yield decode_event(body, db)


# ---------------------------------------------------------------------------------------------
# MAC PDUs (TS 38.321 §6.1.2, §6.1.5, §6.2.3)

#: DL-SCH LCIDs of fixed-size MAC CEs and their sizes [bytes] (TS 38.321 Table 6.2.1-1)
_DL_FIXED_CE_BYTES = {47: 2, 48: 2, 49: 3, 51: 2, 52: 2, 56: 1, 57: 4, 58: 1, 59: 0, 60: 0, 61: 1, 62: 6}
LCID_TA_COMMAND = 61
LCID_PADDING = 63
#: TA command value meaning "no change" (6 bits, 0..63, relative; TS 38.213 §4.2)
TA_CMD_NO_CHANGE = 31


def ta_commands(pdu: bytes) -> list[int]:
    """The Timing Advance Commands (6-bit values, 0..63) of a DL MAC PDU, in order.

    Walks the subPDUs: R/LCID for fixed-size MAC CEs, R/F/LCID/L(8 or 16 bits) for SDUs and
    variable-size CEs, padding (LCID 63) ends the PDU. GnbProtocolError on a PDU that ends inside a
    subPDU."""
    out: list[int] = []
    off, n = 0, len(pdu)
    while off < n:
        head = pdu[off]
        lcid = head & 0x3F
        if lcid == LCID_PADDING:
            break
        if lcid in _DL_FIXED_CE_BYTES:
            size = _DL_FIXED_CE_BYTES[lcid]
            off += 1
        else:
            long_l = bool(head & 0x40)
            if off + (3 if long_l else 2) > n:
                raise _error(f"DL MAC PDU ends in the subheader of LCID {lcid}", pdu)
            size = (pdu[off + 1] << 8 | pdu[off + 2]) if long_l else pdu[off + 1]
            off += 3 if long_l else 2
        if off + size > n:
            raise _error(f"DL MAC PDU: LCID {lcid} wants {size} byte(s), {n - off} left", pdu)
        if lcid == LCID_TA_COMMAND:
            out.append(pdu[off] & 0x3F)
        off += size
    return out


@dataclass(frozen=True)
class RarGrant:
    """One MAC RAR of a RAR PDU: rapid (the preamble), ta (12-bit absolute TA), tc_rnti."""

    rapid: int
    ta: int
    tc_rnti: int


def rar_grants(pdu: bytes) -> list[RarGrant]:
    """The MAC RARs of a RAR PDU (TS 38.321 §6.1.5: subheaders E/T/R/R/BI or E/T/RAPID, each
    RAPID one followed by a 7-octet MAC RAR: R | TA(12) | UL grant(27) | TC-RNTI(16))."""
    out: list[RarGrant] = []
    off, n = 0, len(pdu)
    while off < n:
        head = pdu[off]
        more, is_rapid = bool(head & 0x80), bool(head & 0x40)
        off += 1
        if is_rapid:
            if off + 7 > n:
                raise _error(f"RAR PDU ends inside a MAC RAR ({n - off} of 7 bytes)", pdu)
            rar = pdu[off:off + 7]
            ta = ((rar[0] & 0x7F) << 5) | (rar[1] >> 3)
            out.append(RarGrant(head & 0x3F, ta, rar[5] << 8 | rar[6]))
            off += 7
        if not more:
            break
    return out


# ---------------------------------------------------------------------------------------------
# the SRS channel impulse response


@dataclass(frozen=True)
class SrsPeak:
    """The strongest tap of one SRS impulse response.

    peak: its delay relative to zero delay [samples] (index − N/2, refined by a parabola through the
    power of the three taps around it; fractional); peak_to_mean_db: its power over the mean tap
    power [dB] (a real SRS stands ~31 dB above, the stale buffer OAI traces when none was received
    ~9 dB); n: taps."""

    peak: float
    peak_to_mean_db: float
    n: int


def srs_peak(chest_t: bytes) -> SrsPeak:
    """Decode OAI's ``chest_t`` (int16 I, int16 Q per tap, zero delay at N/2) and find its peak.

    p[i] = I² + Q²;  i* = argmax p;  the run [l, r] of taps around i* with p ≥ p[i*]/2 (−3 dB):
    a band-limited channel (an rfsim channel model) spreads one delay over a plateau several taps
    wide whose highest tap wanders, so its centre is taken:
        peak = Σ_{l..r} k·p[k] / Σ_{l..r} p[k] − N/2                                   (r > l)
    and a single tap is refined by a parabola through the power of its neighbours:
        peak = i* + ½ (p[i*−1] − p[i*+1]) / (p[i*−1] − 2 p[i*] + p[i*+1]) − N/2,  |δ| ≤ ½  (r = l)
    ratio = 10·log10(p[i*] / mean p).
    """
    if len(chest_t) < 16 or len(chest_t) % 4:
        raise _error(f"SRS impulse response of {len(chest_t)} bytes is not int16 I/Q taps", chest_t)
    iq = np.frombuffer(chest_t, dtype="<i2").astype(np.float64).reshape(-1, 2)
    p = iq[:, 0] ** 2 + iq[:, 1] ** 2
    n = len(p)
    i = int(np.argmax(p))
    mean = float(p.mean())
    if p[i] <= 0.0:
        return SrsPeak(0.0, -math.inf, n)
    half = 0.5 * p[i]
    lo = i
    while lo > 0 and p[lo - 1] >= half:
        lo -= 1
    hi = i
    while hi < n - 1 and p[hi + 1] >= half:
        hi += 1
    if hi > lo:
        k = np.arange(lo, hi + 1)
        centre = float(np.dot(k, p[lo:hi + 1]) / p[lo:hi + 1].sum())
        return SrsPeak(centre - n / 2, 10.0 * math.log10(p[i] / mean), n)
    delta = 0.0
    if 0 < i < n - 1:
        den = p[i - 1] - 2.0 * p[i] + p[i + 1]
        if den < 0.0:
            delta = float(np.clip(0.5 * (p[i - 1] - p[i + 1]) / den, -0.5, 0.5))
    return SrsPeak(i + delta - n / 2, 10.0 * math.log10(p[i] / mean), n)
