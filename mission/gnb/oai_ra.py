"""Random accesses in an OAI gNB log: which Msg2 belongs to which UE, and what its TA means (pure).

Stock OAI measures a UE's round trip only at a random access (RA): the Msg2 line's
``timing_offset`` is the TA the gNB estimated from the preamble. Three facts of OAI 2025.w36
(`../shared/data/oai-2025.w36/`, and OAI's source) decide which Msg2 lines are ranges:

- the Msg2 line names the access's fresh **temporary** RNTI (TC-RNTI), never the UE's C-RNTI;
- a connected UE's RA (C-RNTI RA: ``ciUE force_crnti_ra``, a beam or sync recovery) reuses the TA
  the UE already applies, so its ``timing_offset`` is a residual (about 0), not the round trip.
  OAI then logs ``Received a MAC CE for C-RNTI with <old>`` (gNB_scheduler_ulsch.c);
- which UE made an access is known only from later lines: ``Create UE context: ... (rnti: <tc>``
  (rrc_gNB_UE_context.c: an initial access, a new UE whose RNTI is the TC-RNTI), or
  ``Reestablishment RNTI <tc> req C-RNTI <old>`` (rrc_gNB.c: the UE <old> is back, now as <tc>).

:class:`RaTracker` reads log lines in order and reports a :class:`RandomAccess` only when a line
*proves* its owner, and an :class:`RntiChange` only when a line proves that a UE's RNTI changed.
The L1 line ``[RAPROC] F.S Initiating RA procedure with preamble N, ... delay D`` is paired with the
Msg2 through the MAC line ``F.S UE RA-RNTI .. TC-RNTI <tc>: initiating RA procedure`` (same
frame.slot) and the Msg2's ``preamble_index(RAPID) N``.

Log time stamps (OAI ``--log_config.global_log_options``): ``wall_clock`` prints UNIX seconds
(``1796145128.105249``), ``utc_time`` a UTC date, ``time`` the monotonic clock (seconds since
boot: cannot be lined up with telemetry).
"""

from __future__ import annotations

import calendar
import collections
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

from mission.gnb.oai import Msg2Record, parse_msg2_line, protocol_error, strip_ansi

StampKind = Literal["wall_clock", "utc_time", "monotonic", "none"]
RaKind = Literal["initial", "reestablishment", "connected"]

#: 2001-09-09 in UNIX seconds: a CLOCK_REALTIME stamp is larger, a CLOCK_MONOTONIC one (uptime) smaller
WALL_CLOCK_MIN_S = 1e9

_STAMP_NUM = re.compile(r"^\s*([0-9]{1,12})\.([0-9]{6}) ")
_STAMP_UTC = re.compile(r"^\s*([0-9]{4})-([0-9]{2})-([0-9]{2}) ([0-9]{2}):([0-9]{2}):([0-9]{2})\.([0-9]{6}) UTC ")


def parse_stamp(line: str) -> tuple[float | None, StampKind]:
    """The time stamp OAI's logger put in front of a line: (seconds, kind).

    wall_clock and utc_time give UNIX seconds [s]; `time` gives monotonic seconds (kind
    "monotonic"); a line without a stamp (e.g. the telnet server's own prints) gives (None, "none").
    """
    m = _STAMP_NUM.match(line)
    if m:
        t = int(m.group(1)) + int(m.group(2)) * 1e-6
        return t, ("wall_clock" if t >= WALL_CLOCK_MIN_S else "monotonic")
    m = _STAMP_UTC.match(line)
    if m:
        y, mo, d, h, mi, s, us = (int(g) for g in m.groups())
        if not (1 <= mo <= 12 and 1 <= d <= 31 and h < 24 and mi < 60 and s < 61):
            return None, "none"
        return calendar.timegm((y, mo, d, h, mi, s, 0, 0, 0)) + us * 1e-6, "utc_time"
    return None, "none"


def log_time_format(lines: Iterable[str]) -> StampKind:
    """The time-stamp kind of a gNB log: that of most stamped `[MODULE]` lines, "none" if no such
    line carries a stamp (logged without `time`, `wall_clock` or `utc_time`)."""
    counts: collections.Counter[str] = collections.Counter()
    for line in lines:
        if "[" not in line:
            continue
        _t, kind = parse_stamp(line)
        counts[kind] += 1
    stamped = {k: n for k, n in counts.items() if k != "none"}
    if not stamped:
        return "none"
    return max(stamped, key=lambda k: stamped[k])  # type: ignore[return-value]


# ---------------------------------------------------------------------------------------------
# the lines of a random access


@dataclass(frozen=True)
class PrachRecord:
    """L1 ``[RAPROC] F.S Initiating RA procedure with preamble N, energy E dB (...), delay D``."""

    frame: int
    slot: int
    preamble: int
    delay: int
    energy_db: float


@dataclass(frozen=True)
class RaInitRecord:
    """MAC ``F.S UE RA-RNTI <ra> TC-RNTI <tc>: initiating RA procedure`` (same F.S as the L1 line)."""

    frame: int
    slot: int
    ra_rnti: int
    tc_rnti: int


_PRACH = re.compile(r"\[RAPROC\] ([0-9]{1,4})\.([0-9]{1,3}) Initiating RA procedure with preamble ([0-9]{1,2}), "
                    r"energy (-?[0-9]{1,3}(?:\.[0-9]+)?) dB.*?, delay ([0-9]{1,5})\b")
_RA_INIT = re.compile(r"\b([0-9]{1,4})\.([0-9]{1,3}) UE RA-RNTI ([0-9a-fA-F]{1,4}) TC-RNTI ([0-9a-fA-F]{1,4}): "
                      r"initiating RA procedure")
_CRNTI_CE = re.compile(r"Received a MAC CE for C-RNTI with ([0-9a-fA-F]{1,4})\b")
_REESTAB = re.compile(r"Reestablishment RNTI ([0-9a-fA-F]{1,4}) req C-RNTI ([0-9a-fA-F]{1,4})\b")
_CREATE = re.compile(r"Create UE context: .*\(rnti: ([0-9a-fA-F]{1,4}),")


def parse_prach_line(line: str) -> PrachRecord | None:
    """The L1 PRACH detection line, None for any other line; GnbProtocolError for a malformed one."""
    if "Initiating RA procedure with preamble" not in line:
        return None
    s = strip_ansi(line)
    m = _PRACH.search(s)
    if not m:
        raise protocol_error("PRACH line without `F.S ... preamble N, energy E dB ..., delay D`", line)
    preamble = int(m.group(3))
    if preamble > 63:
        raise protocol_error("PRACH preamble outside 0..63", line)
    return PrachRecord(int(m.group(1)), int(m.group(2)), preamble, int(m.group(5)), float(m.group(4)))


def parse_ra_init_line(line: str) -> RaInitRecord | None:
    """The MAC `initiating RA procedure` line with the TC-RNTI, None for any other line."""
    if "TC-RNTI" not in line or "initiating RA procedure" not in line:
        return None
    m = _RA_INIT.search(strip_ansi(line))
    if not m:
        raise protocol_error("RA initiation line without `F.S UE RA-RNTI x TC-RNTI y`", line)
    return RaInitRecord(int(m.group(1)), int(m.group(2)), int(m.group(3), 16), int(m.group(4), 16))


# ---------------------------------------------------------------------------------------------
# what the tracker reports


@dataclass(frozen=True)
class RandomAccess:
    """A random access whose owner a log line proved.

    kind: "initial" (a new UE: ue_rnti = tc_rnti), "reestablishment" (the UE ue_rnti is back as
    tc_rnti) or "connected" (a C-RNTI RA of the connected UE ue_rnti: timing_offset is a residual,
    not a round trip); timing_offset: Msg2 TA; prach_delay: the L1 line's delay (None when the L1
    line was not found); preamble: RAPID; frame, slot: of the Msg2; t_s, stamp: the Msg2 line's
    time stamp and its kind; line: the Msg2 line; proof: the line that proved the owner.
    """

    kind: RaKind
    ue_rnti: int
    tc_rnti: int
    timing_offset: int
    prach_delay: int | None
    preamble: int | None
    frame: int | None
    slot: int | None
    t_s: float | None
    stamp: StampKind
    line: str
    proof: str

    @property
    def round_trip(self) -> bool:
        """True when timing_offset is the UE's round trip (not a connected UE's residual)."""
        return self.kind != "connected"

    def describe(self) -> str:
        what = {"initial": f"initial access of UE {self.ue_rnti:04x}",
                "reestablishment": f"reestablishment of UE {self.ue_rnti:04x} (now {self.tc_rnti:04x})",
                "connected": f"connected-mode (C-RNTI) RA of UE {self.ue_rnti:04x}, TA residual"}[self.kind]
        return f"{what}: TC-RNTI {self.tc_rnti:04x}, preamble {self.preamble}, timing_offset {self.timing_offset}"


@dataclass(frozen=True)
class RntiChange:
    """A log line proved that the UE `old` now has the RNTI `new` (reestablishment)."""

    old: int
    new: int
    t_s: float | None
    proof: str


@dataclass
class _Pending:
    msg2: Msg2Record
    prach: PrachRecord | None
    t_s: float | None
    stamp: StampKind
    line: str


class RaTracker:
    """Follows the random accesses of a gNB log, line by line (no I/O, no clocks).

    feed(line) returns what that line proved: RandomAccess and RntiChange objects, in order. An
    access nobody proves (a failed RAR, an aliased preamble, a C-RNTI RA whose MAC CE cannot be
    told apart from another pending access) is never reported; `dropped` counts those forgotten.
    max_pending bounds the memory of unresolved accesses and of L1 lines; pending_max_s [s of log
    time] forgets an access not proven that long after its Msg2 (a proof follows within tens of
    milliseconds; the rfsimulator may run at 0.4x real time).
    """

    def __init__(self, max_pending: int = 64, pending_max_s: float = 2.0) -> None:
        self.max_pending = max_pending
        self.pending_max_s = pending_max_s
        self._prach: collections.OrderedDict[tuple[int, int, int], PrachRecord] = collections.OrderedDict()
        self._init_slot: collections.OrderedDict[int, tuple[int, int]] = collections.OrderedDict()
        self._pending: collections.OrderedDict[int, _Pending] = collections.OrderedDict()
        self.dropped = 0
        self.ambiguous_ce = 0
        self.lines = 0
        self.stamps: collections.Counter[str] = collections.Counter()

    @staticmethod
    def _bounded_put(d: collections.OrderedDict, key, value, limit: int) -> int:
        d.pop(key, None)
        d[key] = value
        n = 0
        while len(d) > limit:
            d.popitem(last=False)
            n += 1
        return n

    def _expire(self, now_s: float) -> None:
        old = [tc for tc, p in self._pending.items() if p.t_s is not None and p.t_s < now_s - self.pending_max_s]
        for tc in old:
            del self._pending[tc]
        self.dropped += len(old)

    def _find_prach(self, msg2: Msg2Record) -> PrachRecord | None:
        if msg2.preamble is None:
            return None
        slot = self._init_slot.get(msg2.rnti) if msg2.rnti is not None else None
        if slot is not None:
            return self._prach.get((*slot, msg2.preamble))
        for (_f, _s, p), rec in reversed(self._prach.items()):  # newest detection of that preamble
            if p == msg2.preamble:
                return rec
        return None

    def _resolve(self, tc: int, kind: RaKind, ue: int, proof: str) -> RandomAccess | None:
        p = self._pending.pop(tc, None)
        if p is None:
            return None
        return RandomAccess(kind=kind, ue_rnti=ue, tc_rnti=tc, timing_offset=p.msg2.timing_offset,
                            prach_delay=p.prach.delay if p.prach else None, preamble=p.msg2.preamble,
                            frame=p.msg2.frame, slot=p.msg2.slot, t_s=p.t_s, stamp=p.stamp,
                            line=p.line.strip(), proof=proof.strip())

    def feed(self, line: str) -> list[RandomAccess | RntiChange]:
        """One log line -> what it proved (usually nothing). Malformed RA lines raise GnbProtocolError."""
        self.lines += 1
        t_s, stamp = parse_stamp(line)
        if t_s is not None:
            self.stamps[stamp] += 1
            self._expire(t_s)
        if "RA" not in line and "RNTI" not in line:
            return []
        if (pr := parse_prach_line(line)) is not None:
            self._bounded_put(self._prach, (pr.frame, pr.slot, pr.preamble), pr, self.max_pending)
            return []
        if (ri := parse_ra_init_line(line)) is not None:
            self._bounded_put(self._init_slot, ri.tc_rnti, (ri.frame, ri.slot), self.max_pending)
            return []
        if (m2 := parse_msg2_line(line)) is not None:
            if m2.rnti is None:
                return []
            pending = _Pending(m2, self._find_prach(m2), t_s, stamp, line)
            self.dropped += self._bounded_put(self._pending, m2.rnti, pending, self.max_pending)
            return []
        s = strip_ansi(line)
        if (m := _CRNTI_CE.search(s)) is not None:
            # the CE does not name the TC-RNTI: it settles an access only when one is pending
            if len(self._pending) == 1:
                tc = next(iter(self._pending))
                ra = self._resolve(tc, "connected", int(m.group(1), 16), line)
                return [ra] if ra is not None else []
            self.ambiguous_ce += 1
            return []
        if (m := _REESTAB.search(s)) is not None:
            tc, old = int(m.group(1), 16), int(m.group(2), 16)
            out: list[RandomAccess | RntiChange] = []
            ra = self._resolve(tc, "reestablishment", old, line)
            if ra is not None:
                out.append(ra)
            if old != tc:
                out.append(RntiChange(old=old, new=tc, t_s=t_s, proof=line.strip()))
            return out
        if (m := _CREATE.search(s)) is not None:
            tc = int(m.group(1), 16)
            ra = self._resolve(tc, "initial", tc, line)
            return [ra] if ra is not None else []
        return []

    def feed_all(self, lines: Iterable[str]) -> list[RandomAccess | RntiChange]:
        out: list[RandomAccess | RntiChange] = []
        for line in lines:
            out.extend(self.feed(line))
        return out
