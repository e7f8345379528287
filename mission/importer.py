"""Build a mission log (`uavloc-mission/1`) from a flight recorded by other tools: a MAVLink
telemetry log (tlog) for the UAV track and a gNB log for the ranges (`uavloc import`).

**UAV track** (pymavlink): every GLOBAL_POSITION_INT (lat, lon in 1e-7 deg; alt in mm AMSL;
vx, vy, vz in cm/s NED). Radio links reorder and batch messages, so fixes are put in order by the
autopilot's own clock `time_boot_ms`, duplicates dropped, and that clock is placed on UTC with one
offset (docs/design.md §3: the UAV position of a measurement is the track interpolated to its time):

- time base `system` (default when present): SYSTEM_TIME pairs `time_unix_usec` (the autopilot's
  UTC, from GPS) with `time_boot_ms`; offset = median of their difference.
- time base `tlog`: the tlog's own per-message receive stamps (the ground station's UTC) against
  `time_boot_ms`; offset = 10th percentile of the difference (the least-delayed messages).

A tlog without any usable fix, a `time_boot_ms` that restarts (autopilot reboot), or a jump in the
track faster than `max_speed_mps` is an :class:`ImportDataError`.

**gNB log**: text, one record per line. Timestamp convention: a line that carries a measurement
must *start* with its time of measurement in UTC on the gNB host's clock, in one of these forms
(optionally in square brackets), followed by whitespace and the gNB's text:

    1533737170.125 [NR_MAC]   UE 4601: 163.7 Generating RA-Msg2 DCI, ... timing_offset = 3 (estimated ...)
    [2018-08-08T14:06:10.125Z] rnti 4601 ta 12 mu 1 srs_peak 3.2500 fs 46080000 snr_db 28.1

i.e. UNIX seconds with a fraction, or ISO 8601 (a time without a zone is UTC). That is what
`ts '%.s'` or `TZ=UTC ts '%Y-%m-%dT%H:%M:%.SZ'` (moreutils) print when the gNB's output is piped
through them. (The simulated gNB's own Msg2 log runs on simulation time and carries no stamp.)
`--gnb-time-offset` is added to every stamp (to correct a known clock offset). Recognised
payloads, parsed by `mission.gnb.oai` (the same parsers as the live adapter):

- `rtt` reply lines of docs/design.md §8 (`rnti <hex> ta <int> mu <int> srs_peak <float> fs <hz> ...`):
  a complete measurement; `error ...` lines are counted and skipped;
- OAI Msg2 lines (`UE <rnti>: ... timing_offset = N ...`): a coarse TA-only range (needs μ);
- SRS ToA lines (`SRS ToA peak estimator N` in samples, or `SRS ... ToA ...: N ns`), which carry
  no RNTI: each refines the Msg2 line of the same UE just before it (within `srs_pair_window_s`)
  as the SRS part of the RTT (τr = peak / fs, or N ns), as in the paper's RACH + SRS scheme.

**T-tracer recording** (`--t-trace REC.raw`, instead of or beside the gNB log): what OAI's own
`record` tool wrote from the gNB's T tracer (`record -d T_messages.txt -o REC.raw -on
GNB_PHY_UL_TIME_CHANNEL_ESTIMATE -on GNB_MAC_DL_PDU_WITH_DATA -on GNB_MAC_DL_RAR_PDU_WITH_DATA`),
read by the trace mode's own tracker (`mission.gnb.trace_rtt`): each UE's round trip from its RAR
TA, the TA commands it applied and the SRS peak, stamped with the gNB's CLOCK_REALTIME; the newest
of each UE every `interval_s` becomes a measurement, with the live trace mode's thresholds
(`TraceSettings`: `[gnb]`'s defaults). The recording must start before the UEs attach (their RAR
holds the absolute TA); it is decoded with its own T_messages.txt (`--t-messages` only for one
without), and an empty one, one cut inside that preamble, or one whose UEs attached before it
began is an error that says so. A user without any range is a warning naming it and why, an error
when no user has one (:func:`import_flight`).

Lines without a measurement are ignored; a measurement line without a timestamp, or a malformed
one, is an error naming the line. Measurements outside the track's time span (or in a gap of the
track longer than `max_gap_s`) are dropped with a warning; if none overlap, the clocks do not
overlap and that is an error which says by how much.
"""

from __future__ import annotations

import logging
import math
import re
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from estimator.ranging import toa_s_from_raw
from mission.gnb.oai import (
    Msg2Record,
    RttErrorReply,
    SrsToaRecord,
    parse_msg2_line,
    parse_rtt_line,
    parse_srs_toa_line,
    strip_ansi,
)
from mission.gnb.trace_rtt import TraceCounts, TraceRttTracker, TraceSettings
from mission.gnb.ttrace import iter_recording, parse_t_messages, recording_preamble
from mission.log import MissionLogWriter
from uavloc.errors import GnbProtocolError, ImportDataError, RangingError, UavlocError

log = logging.getLogger(__name__)

TIME_BASES = ("auto", "system", "tlog")


# ---------------------------------------------------------------------------------------------
# tlog


@dataclass(frozen=True)
class GpsTrack:
    """The UAV track from a tlog, in time order.

    t_unix_s (T,): UTC of each fix [s]; time_boot_s (T,): the autopilot's clock [s];
    lla (T, 3): lat_deg, lon_deg, alt_m (AMSL); vel_ned_mps (T, 3);
    home_lla (3,) from HOME_POSITION, or None; time_base: "system" or "tlog"; clock_offset_s:
    UTC − time_boot; n_raw: GLOBAL_POSITION_INT messages read; n_dropped: of those, without a fix
    or duplicated.
    """

    t_unix_s: np.ndarray
    time_boot_s: np.ndarray
    lla: np.ndarray
    vel_ned_mps: np.ndarray
    home_lla: np.ndarray | None
    time_base: str
    clock_offset_s: float
    n_raw: int
    n_dropped: int


def _open_tlog(path: Path):
    from pymavlink import mavutil

    if not path.is_file():
        raise ImportDataError(f"tlog {path} does not exist")
    try:
        return mavutil.mavlink_connection(str(path), dialect="common")
    except Exception as exc:  # pymavlink raises bare Exceptions on unreadable files
        raise ImportDataError(f"cannot open tlog {path}: {exc}") from exc


def read_tlog_gps(path: str | Path, time_base: str = "auto", max_speed_mps: float = 60.0,
                  reboot_tolerance_s: float = 10.0) -> GpsTrack:
    """Read the GPS track of a tlog (see the module docstring). `time_base`: "auto" (system when
    the tlog has SYSTEM_TIME with a UTC, else tlog), "system" or "tlog"."""
    if time_base not in TIME_BASES:
        raise ImportDataError(f"time base must be one of {TIME_BASES}, got {time_base!r}")
    path = Path(path)
    mlog = _open_tlog(path)
    rows: list[tuple[float, float, float, float, float, float, float, float]] = []
    sys_pairs: list[tuple[float, float]] = []
    home = None
    running_max_boot = -math.inf
    try:
        while True:
            msg = mlog.recv_match(type=["GLOBAL_POSITION_INT", "SYSTEM_TIME", "HOME_POSITION"])
            if msg is None:
                break
            mtype = msg.get_type()
            if mtype == "GLOBAL_POSITION_INT":
                boot = msg.time_boot_ms / 1000.0
                if boot < running_max_boot - reboot_tolerance_s:
                    raise ImportDataError(
                        f"{path}: time_boot_ms restarts ({running_max_boot:.1f} s -> {boot:.1f} s at tlog time "
                        f"{_utc(msg._timestamp)}): the autopilot rebooted; split the tlog at that point"
                    )
                running_max_boot = max(running_max_boot, boot)
                rows.append((float(msg._timestamp), boot, msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0,
                             msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01))
            elif mtype == "SYSTEM_TIME":
                if msg.time_unix_usec > 0 and msg.time_boot_ms > 0:
                    sys_pairs.append((msg.time_unix_usec * 1e-6, msg.time_boot_ms / 1000.0))
            elif mtype == "HOME_POSITION" and home is None:
                home = np.array([msg.latitude / 1e7, msg.longitude / 1e7, msg.altitude / 1000.0])
    except ImportDataError:
        raise
    except Exception as exc:  # a corrupt tlog makes pymavlink raise various errors
        raise ImportDataError(f"{path}: cannot read MAVLink messages ({type(exc).__name__}: {exc})") from exc
    finally:
        mlog.close()
    n_raw = len(rows)
    if not rows:
        raise ImportDataError(f"{path}: no GLOBAL_POSITION_INT message: this tlog has no GPS track")
    a = np.array(rows)
    # no fix: lat = lon = 0 exactly
    fix = ~((a[:, 2] == 0.0) & (a[:, 3] == 0.0))
    a = a[fix]
    if len(a) < 2:
        raise ImportDataError(f"{path}: {n_raw} GLOBAL_POSITION_INT messages but {len(a)} with a GPS fix: "
                              "need at least 2")
    order = np.argsort(a[:, 1], kind="stable")
    a = a[order]
    keep = np.r_[True, np.diff(a[:, 1]) > 0]  # same time_boot_ms twice: keep the first
    a = a[keep]
    n_dropped = n_raw - len(a)
    if len(a) < 2:
        raise ImportDataError(f"{path}: fewer than 2 distinct GPS fixes")
    if time_base == "auto":
        time_base = "system" if sys_pairs else "tlog"
    if time_base == "system":
        if not sys_pairs:
            raise ImportDataError(f"{path}: no SYSTEM_TIME with a UTC time: use the tlog time base")
        s = np.array(sys_pairs)
        # offset = median(time_unix − time_boot) over SYSTEM_TIME
        offset = float(np.median(s[:, 0] - s[:, 1]))
        spread = float(np.percentile(s[:, 0] - s[:, 1], 90) - np.percentile(s[:, 0] - s[:, 1], 10))
    else:
        diff = a[:, 0] - a[:, 1]
        # offset = 10th percentile of (tlog stamp − time_boot): the least-delayed messages
        offset = float(np.percentile(diff, 10))
        spread = float(np.percentile(diff, 90) - offset)
    if spread > 2.0:
        log.warning("%s: the %s clock and time_boot_ms disagree by up to %.1f s over the flight "
                    "(late telemetry, or an autopilot clock that does not run in real time, e.g. SITL)",
                    path, time_base, spread)
    t = a[:, 1] + offset
    track = GpsTrack(t_unix_s=t, time_boot_s=a[:, 1], lla=a[:, 2:5], vel_ned_mps=a[:, 5:8], home_lla=home,
                     time_base=time_base, clock_offset_s=offset, n_raw=n_raw, n_dropped=n_dropped)
    check_gps_jumps(track, max_speed_mps)
    log.info("%s: %d GPS fixes (%d dropped) over %.1f s, time base %s", path, len(t), n_dropped, t[-1] - t[0],
             time_base)
    return track


def check_gps_jumps(track: GpsTrack, max_speed_mps: float) -> None:
    """Raise ImportDataError where the track moves faster than `max_speed_mps` between two fixes
    (v = ||p_{i+1} − p_i|| / (t_{i+1} − t_i), 3-D, in the ENU frame of the first fix)."""
    o = Origin(*track.lla[0])
    p = o.lla_to_enu(track.lla[:, 0], track.lla[:, 1], track.lla[:, 2])
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    dt = np.diff(track.time_boot_s)
    speed = step / dt
    i = int(np.argmax(speed))
    if speed[i] > max_speed_mps:
        raise ImportDataError(
            f"GPS jump: the track moves {step[i]:.1f} m in {dt[i]:.3f} s ({speed[i]:.0f} m/s > {max_speed_mps:g} m/s) "
            f"at {_utc(track.t_unix_s[i + 1])} (time_boot {track.time_boot_s[i + 1]:.3f} s); a GPS glitch or "
            "a mixed-up log — raise --max-speed if the vehicle really flies that fast"
        )


def _utc(t_unix_s: float) -> str:
    return datetime.fromtimestamp(float(t_unix_s), UTC).isoformat(timespec="milliseconds")


# ---------------------------------------------------------------------------------------------
# gNB log


@dataclass(frozen=True)
class GnbMeasurement:
    """One range measurement from a gNB log line.

    t_unix_s: UTC of the measurement [s] (line stamp + offset); rnti; ta; mu; srs_peak [samples at
    fs_hz] (0 for a coarse Msg2 measurement); fs_hz (None for coarse); snr_db or None;
    toa_s: one-way ToA [s]; source: "rtt", "msg2" or "msg2+srs"; line: 1-based line number.
    """

    t_unix_s: float
    rnti: int
    ta: int
    mu: int
    srs_peak: float
    fs_hz: float | None
    snr_db: float | None
    toa_s: float
    source: str
    line: int


@dataclass
class GnbLogSummary:
    """What parse_gnb_log saw: measurements by source, error replies, lines ignored."""

    counts: Counter = field(default_factory=Counter)
    errors: int = 0
    ignored_lines: int = 0
    unpaired_srs: int = 0


_TS_UNIX = re.compile(r"\[?([0-9]{9,11}(?:\.[0-9]{1,9})?)\]?$")
_TS_ISO = re.compile(r"\[?([0-9]{4}-[0-9]{2}-[0-9]{2}[T ][0-9]{2}:[0-9]{2}:[0-9]{2}(?:\.[0-9]{1,9})?"
                     r"(?:Z|[+-][0-9]{2}:?[0-9]{2})?)\]?$")
_LEAD = re.compile(r"\s*(\[[^\]]{8,40}\]|\S+)(?:\s+(\S.*))?$")
_ISO_FRACTION = re.compile(r"\.([0-9]{1,9})")


def parse_timestamp(token: str) -> float | None:
    """A leading time stamp -> UNIX seconds (UTC); None when the token is not a time stamp.

    Accepts `1533737170.125`, `[1533737170.125]`, `2018-08-08T14:06:10.125Z`, `[2018-08-08 14:06:10]`,
    `2018-08-08T14:06:10+02:00` (a time without a zone is UTC).
    """
    tok = token.strip()
    m = _TS_UNIX.fullmatch(tok)
    if m:
        return float(m.group(1))
    m = _TS_ISO.fullmatch(tok)
    if not m:
        return None
    text = m.group(1).replace(" ", "T").replace("Z", "+00:00")
    # Python's fromisoformat takes 6 fraction digits at most
    text = _ISO_FRACTION.sub(lambda f: "." + (f.group(1) + "000000")[:6], text, count=1)
    try:
        dt = datetime.fromisoformat(text)
    except ValueError:
        return None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return dt.timestamp()


def split_stamp(line: str) -> tuple[float | None, str]:
    """`<stamp> <payload>` -> (UNIX seconds, payload); (None, line) when the line has no stamp.
    An ISO stamp written with a space between date and time counts as one stamp."""
    s = strip_ansi(line).rstrip("\r\n")
    m = re.match(r"\s*\[?([0-9]{4}-[0-9]{2}-[0-9]{2} [0-9]{2}:[0-9]{2}:[0-9]{2}(?:\.[0-9]+)?"
                 r"(?:Z|[+-][0-9]{2}:?[0-9]{2})?)\]?\s+(.*)$", s)
    if m:
        t = parse_timestamp(m.group(1))
        if t is not None:
            return t, m.group(2)
    m = _LEAD.match(s)
    if not m:
        return None, s
    t = parse_timestamp(m.group(1))
    if t is None:
        return None, s
    return t, m.group(2) or ""


def parse_gnb_log(lines: Iterable[str], mu: int | None = None, fs_hz: float | None = None,
                  time_offset_s: float = 0.0, srs_pair_window_s: float = 1.0,
                  where: str = "gNB log") -> tuple[list[GnbMeasurement], GnbLogSummary]:
    """Parse a gNB log (see the module docstring). `mu`: numerology of Msg2 lines (which do not
    print it); `fs_hz`: sampling rate for SRS peak lines. Returns the measurements in time order."""
    out: list[GnbMeasurement] = []
    summary = GnbLogSummary()
    pending_msg2: dict[int, tuple[float, Msg2Record, int]] = {}  # rnti -> last Msg2 awaiting an SRS line
    last_msg2_rnti: int | None = None
    for lineno, raw in enumerate(lines, start=1):
        t, payload = split_stamp(raw)
        try:
            rec: object = None
            if payload.lstrip().startswith(("rnti ", "error")) and not payload.lstrip().startswith("error:"):
                rec = parse_rtt_line(payload)
            else:
                rec = parse_msg2_line(payload)
                if rec is None:
                    rec = parse_srs_toa_line(payload)
        except GnbProtocolError as exc:
            raise ImportDataError(f"{where}:{lineno}: {exc}") from None
        if rec is None:
            summary.ignored_lines += 1
            continue
        if isinstance(rec, RttErrorReply):
            summary.errors += 1
            continue
        if t is None:
            raise ImportDataError(
                f"{where}:{lineno}: a measurement line without a leading time stamp (UNIX seconds or ISO 8601 "
                f"UTC, e.g. `1533737170.125 ...`): {raw.strip()[:120]!r}"
            )
        t += time_offset_s
        try:
            if isinstance(rec, Msg2Record):
                if rec.rnti is None:
                    raise ImportDataError(f"{where}:{lineno}: Msg2 line without `UE <rnti>:`: {raw.strip()[:120]!r}")
                if mu is None:
                    raise ImportDataError(f"{where}:{lineno}: Msg2 lines do not print the numerology: give --mu")
                toa = toa_s_from_raw(rec.timing_offset, mu)
                out.append(GnbMeasurement(t, rec.rnti, rec.timing_offset, mu, 0.0, None, None, toa, "msg2", lineno))
                pending_msg2[rec.rnti] = (t, rec, len(out) - 1)
                last_msg2_rnti = rec.rnti
            elif isinstance(rec, SrsToaRecord):
                if last_msg2_rnti is None or last_msg2_rnti not in pending_msg2 \
                        or t - pending_msg2[last_msg2_rnti][0] > srs_pair_window_s:
                    summary.unpaired_srs += 1
                    continue
                t2, m2, idx = pending_msg2.pop(last_msg2_rnti)
                base = out[idx]
                if rec.peak_samples is not None:
                    if fs_hz is None:
                        raise ImportDataError(
                            f"{where}:{lineno}: an SRS peak in samples needs the sampling rate: give --fs")
                    peak, fs = rec.peak_samples, fs_hz
                else:
                    # a ToA in ns: expressed as a peak at 1 GHz (τr = N ns)
                    peak, fs = rec.toa_ns, 1e9
                toa = toa_s_from_raw(m2.timing_offset, base.mu, peak, fs)
                out[idx] = GnbMeasurement(t2, base.rnti, base.ta, base.mu, float(peak), float(fs), None, toa,
                                          "msg2+srs", base.line)
            else:  # RttReply
                toa = toa_s_from_raw(rec.ta, rec.mu, rec.srs_peak, rec.fs_hz)
                out.append(GnbMeasurement(t, rec.rnti, rec.ta, rec.mu, rec.srs_peak, rec.fs_hz, rec.snr_db, toa,
                                          "rtt", lineno))
        except ImportDataError:
            raise
        except UavlocError as exc:
            raise ImportDataError(f"{where}:{lineno}: {exc}") from None
    for m in out:
        summary.counts[m.source] += 1
    out.sort(key=lambda m: m.t_unix_s)
    return out, summary


def read_gnb_log(path: str | Path, **kwargs) -> tuple[list[GnbMeasurement], GnbLogSummary]:
    """:func:`parse_gnb_log` on a file."""
    path = Path(path)
    try:
        with path.open("r", encoding="utf-8", errors="replace") as fh:
            return parse_gnb_log(fh, where=str(path), **kwargs)
    except OSError as exc:
        raise ImportDataError(f"cannot read gNB log {path}: {exc}") from exc


# ---------------------------------------------------------------------------------------------
# alignment and writing


@dataclass(frozen=True)
class TTraceImport:
    """What :func:`read_t_trace` read: measurements (GnbMeasurement, time order); tracker (the
    TraceRttTracker that followed the recording: its counts, the UEs it knows, why one has no
    range); t_messages: whose T_messages.txt decoded it ("the recording's own" or a path)."""

    measurements: list[GnbMeasurement]
    tracker: TraceRttTracker
    t_messages: str

    @property
    def counts(self) -> TraceCounts:
        return self.tracker.counts

    def why_no_range(self, rnti: int) -> str:
        """Why the recording gives UE `rnti` no range (in the tracker's words)."""
        return self.tracker.why_none(rnti, reattach="record again from before the UEs attach",
                                     where="the recording")

    def why_empty(self) -> str:
        """Why the recording gave no round trip at all: the first of what the counts show."""
        c, tr = self.counts, self.tracker
        if c.events == 0:
            return ("it holds the gNB's T_messages.txt and no event (stopped at once, or recorded without `-on` "
                    "for GNB_PHY_UL_TIME_CHANNEL_ESTIMATE, GNB_MAC_DL_PDU_WITH_DATA, GNB_MAC_DL_RAR_PDU_WITH_DATA)")
        if c.rars == 0 and tr.unknown_rntis:
            ues = ", ".join(f"{r:04x}" for r in sorted(tr.unknown_rntis))
            return (f"UE(s) {ues} sent SRS or TA commands but their random access is not in it: they attached before "
                    "the recording began, and only the RAR carries the absolute TA; start `record` first, then "
                    "attach (or re-attach) the UEs")
        if c.srs == 0:
            return (f"it has no SRS event ({c.rars} random access(es), {c.ta_commands} TA commands): the gNB needs "
                    "do_SRS = 1, and a core network or --do-ra on gNB and UE")
        return "; ".join(self.why_no_range(r) for r in tr.ues()) or (
            f"{c.srs} SRS events but no UE's random access ({c.rars} RARs)")


def read_t_trace(path: str | Path, mu: int = 1, fs_hz: float = 46.08e6, interval_s: float = 0.25,
                 time_offset_s: float = 0.0, t_messages: str | Path | None = None,
                 settings: TraceSettings | None = None) -> TTraceImport:
    """Measurements from a T-tracer recording: per UE, the newest RTT the trace tracker accepted in
    each `interval_s` window of the gNB's clock (plus time_offset_s). settings: the tracker's
    (default: the trace mode's own, TraceSettings of `[gnb]`'s defaults at mu, fs_hz).

    t_messages: the gNB's T_messages.txt, used only for a recording without the server's own (OAI's
    `record` keeps it); given beside a recording that has its own, the recording's wins and a
    different file is warned about. ImportDataError for an empty recording, one cut inside its
    preamble, or one without a preamble and without t_messages."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ImportDataError(f"{path}: cannot read the T-tracer recording ({exc.strerror or exc})") from None
    try:
        own, _ = recording_preamble(data)
    except GnbProtocolError as exc:
        raise ImportDataError(f"{path}: {exc}") from None
    db = None
    source = "the recording's own"
    if t_messages is not None:
        try:
            db = parse_t_messages(Path(t_messages).read_text(errors="replace"))
        except OSError as exc:
            raise ImportDataError(f"{t_messages}: cannot read ({exc.strerror or exc})") from None
        except GnbProtocolError as exc:
            raise ImportDataError(f"--t-messages {t_messages}: {exc}") from None
        if own is None:
            source = str(t_messages)
        elif db != own:
            log.warning("%s carries the T_messages.txt of the gNB that recorded it (%d events); --t-messages %s "
                        "(%d events) differs from it and is ignored", path, len(own.events), t_messages,
                        len(db.events))
        else:
            log.info("%s carries its own T_messages.txt, the same as --t-messages %s", path, t_messages)
    s = settings if settings is not None else TraceSettings(mu=mu, fs_hz=fs_hz)
    tracker = TraceRttTracker(s)
    out: list[GnbMeasurement] = []
    last: dict[int, float] = {}
    try:
        for ev in iter_recording(data, db):
            r = tracker.feed(ev)
            if r is None or r.t_wall_s - last.get(r.rnti, -math.inf) < interval_s:
                continue
            last[r.rnti] = r.t_wall_s
            try:
                toa = toa_s_from_raw(r.ta, s.mu, r.peak, s.fs_hz)
            except RangingError:
                continue
            out.append(GnbMeasurement(r.t_wall_s + time_offset_s, r.rnti, r.ta, s.mu, r.peak, s.fs_hz, None, toa,
                                      "trace", 0))
    except GnbProtocolError as exc:
        hint = " (pass the gNB's T_messages.txt with --t-messages)" if "does not start with" in str(exc) else ""
        raise ImportDataError(f"{path}: {exc}{hint}") from None
    return TTraceImport(out, tracker, source)


@dataclass(frozen=True)
class ImportUser:
    """A user of the imported mission: id, RNTI, ground altitude AMSL [m] (None: the origin's)."""

    id: str
    rnti: int
    ground_alt_m: float | None = None


@dataclass(frozen=True)
class ImportSummary:
    """What `import_flight` wrote."""

    path: Path
    fixes: int
    measurements: int
    per_user: dict[str, int]
    dropped_outside: int
    dropped_unknown_rnti: dict[int, int]
    start_utc: str
    duration_s: float
    time_base: str
    users_without_ranges: dict[str, str] = field(default_factory=dict)


def _why_absent(user: ImportUser, measurements: list[GnbMeasurement], ok: np.ndarray,
                why_absent: Callable[[int], str] | None) -> str:
    """Why `user` gets no range: none of its RNTI at all, or all outside the track."""
    n = sum(1 for m in measurements if m.rnti == user.rnti)
    if n:
        return f"its {n} measurement(s) all fall outside the GPS track (or in its gaps)"
    seen = sorted({m.rnti for m in measurements})
    why = f"RNTI {user.rnti:04x} has no measurement (the ranges are of {', '.join(f'{r:04x}' for r in seen)})"
    return f"{why}: {why_absent(user.rnti)}" if why_absent is not None else why


def interpolate_track(track: GpsTrack, origin: Origin, t_unix_s: np.ndarray,
                      max_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """UAV position at each time, linear in ENU between the fixes around it.

    Returns pos_enu_m (M, 3) and ok (M,): False outside the track or where the fixes around the
    time are more than `max_gap_s` apart.
    """
    t = np.asarray(t_unix_s, float)
    p = origin.lla_to_enu(track.lla[:, 0], track.lla[:, 1], track.lla[:, 2])
    tt = track.t_unix_s
    # p(t) = p_i + (t − t_i)/(t_{i+1} − t_i) · (p_{i+1} − p_i)
    pos = np.stack([np.interp(t, tt, p[:, j]) for j in range(3)], axis=1)
    j = np.clip(np.searchsorted(tt, t, side="right"), 1, len(tt) - 1)
    gap = tt[j] - tt[j - 1]
    ok = (t >= tt[0]) & (t <= tt[-1]) & (gap <= max_gap_s)
    return pos, ok


def import_flight(
    track: GpsTrack,
    measurements: list[GnbMeasurement],
    users: list[ImportUser],
    out_path: str | Path,
    origin: Origin | None = None,
    fs_hz: float | None = None,
    noise: NoiseModel | None = None,
    truth_lla: dict[str, tuple[float, float, float]] | None = None,
    max_gap_s: float = 3.0,
    config: dict | None = None,
    why_absent: Callable[[int], str] | None = None,
    source: str = "gNB log",
) -> ImportSummary:
    """Align the measurements with the track and write a mission log to `out_path` (replaced).

    origin: the mission origin (default: HOME_POSITION of the tlog, else the first fix).
    Mission time t = UTC − UTC of the first fix. Telemetry records: every fix; rtt records: every
    measurement of a known RNTI inside the track, with the interpolated UAV position.

    A user given without any range: an ImportDataError when no user has one, else a warning naming
    it and why (its RNTI is not in the `source`, or its measurements fall outside the track;
    why_absent(rnti) says more, e.g. a T-tracer recording's "attached before the recording
    began"); the summary lists such users (`users_without_ranges`).
    """
    if not users:
        raise ImportDataError("no users given: name them with --users ID:RNTI[:GROUND_ALT_M]")
    by_rnti = {}
    for u in users:
        if u.rnti in by_rnti:
            raise ImportDataError(f"RNTI {u.rnti:04x} given for two users")
        by_rnti[u.rnti] = u
    if len({u.id for u in users}) != len(users):
        raise ImportDataError("user ids must be unique")
    if origin is None:
        o = track.home_lla if track.home_lla is not None else track.lla[0]
        origin = Origin(float(o[0]), float(o[1]), float(o[2]))
    if not measurements:
        raise ImportDataError("the gNB log has no measurement line (rtt reply, Msg2 timing_offset or SRS ToA)")
    t_meas = np.array([m.t_unix_s for m in measurements])
    pos, ok = interpolate_track(track, origin, t_meas, max_gap_s)
    if not ok.any():
        t0, t1 = track.t_unix_s[0], track.t_unix_s[-1]
        g0, g1 = t_meas.min(), t_meas.max()
        shift = (0.5 * (t0 + t1)) - (0.5 * (g0 + g1))
        raise ImportDataError(
            f"the clocks do not overlap: the gNB log spans {_utc(g0)} .. {_utc(g1)}, the GPS track spans "
            f"{_utc(t0)} .. {_utc(t1)} (time base {track.time_base}); the centres differ by {shift:+.1f} s — "
            "check the time zones / clocks, try --time-base, or give --gnb-time-offset"
        )
    dropped_outside = int((~ok).sum())
    if dropped_outside:
        log.warning("%d of %d measurements fall outside the GPS track or in a gap > %g s: dropped",
                    dropped_outside, len(measurements), max_gap_s)
    unknown: Counter = Counter(m.rnti for m, good in zip(measurements, ok, strict=True)
                               if good and m.rnti not in by_rnti)
    if unknown:
        log.warning("measurements of RNTIs not among the users, dropped: %s",
                    ", ".join(f"{r:04x} ({n})" for r, n in sorted(unknown.items())))
    keep = [i for i, m in enumerate(measurements) if ok[i] and m.rnti in by_rnti]
    kept = Counter(measurements[i].rnti for i in keep)
    absent = {u.id: _why_absent(u, measurements, ok, why_absent) for u in users if not kept[u.rnti]}
    if not keep:
        seen = sorted({m.rnti for m in measurements})
        raise ImportDataError(
            f"no measurement of the given users: the {source} has RNTIs {', '.join(f'{r:04x}' for r in seen)}; "
            f"--users gave {', '.join(f'{r:04x}' for r in by_rnti)} ("
            + "; ".join(f"{uid}: {why}" for uid, why in absent.items()) + ")"
        )
    for uid, why in absent.items():
        log.warning("user %s (RNTI %04x) has no range: %s", uid, next(u.rnti for u in users if u.id == uid), why)
    t_start = float(track.t_unix_s[0])
    mus = {measurements[i].mu for i in keep}
    fss = {measurements[i].fs_hz for i in keep if measurements[i].fs_hz is not None}
    radio: dict = {"mu": mus.pop() if len(mus) == 1 else None}
    fs_header = fs_hz if fs_hz is not None else (fss.pop() if len(fss) == 1 else None)
    if fs_header is not None:
        radio["fs_hz"] = float(fs_header)
    radio = {k: v for k, v in radio.items() if v is not None}

    lat, lon, alt = origin.enu_to_lla(pos)
    records: list[tuple[float, int, str, dict]] = []
    for i in range(len(track.t_unix_s)):
        la, lo, al = track.lla[i]
        vn, ve, vd = track.vel_ned_mps[i]
        records.append((float(track.t_unix_s[i]) - t_start, 0, "telemetry",
                        {"lat_deg": float(la), "lon_deg": float(lo), "alt_m": float(al),
                         "vel_ned_mps": [float(vn), float(ve), float(vd)]}))
    per_user: Counter = Counter()
    for i in keep:
        m = measurements[i]
        u = by_rnti[m.rnti]
        per_user[u.id] += 1
        fields: dict = {"user": u.id, "uav": {"lat_deg": float(lat[i]), "lon_deg": float(lon[i]),
                                              "alt_m": float(alt[i])},
                        "toa_s": m.toa_s, "ta": m.ta, "mu": m.mu, "srs_peak": m.srs_peak}
        if m.fs_hz is not None:
            fields["fs_hz"] = m.fs_hz
        if m.snr_db is not None:
            fields["snr_db"] = m.snr_db
        records.append((m.t_unix_s - t_start, 1, "rtt", fields))
    records.sort(key=lambda r: (r[0], r[1]))
    out_path = Path(out_path)
    if out_path.exists():
        out_path.unlink()
    start_utc = _utc(t_start)
    header_users = [{"id": u.id, "rnti": u.rnti,
                     "ground_alt_m": float(u.ground_alt_m if u.ground_alt_m is not None else origin.alt_m)}
                    for u in users]
    with MissionLogWriter(out_path) as w:
        w.write_header(origin, header_users, radio, noise=noise, config=config or {}, start_utc=start_utc)
        if truth_lla:
            ids = {u.id for u in users}
            bad = sorted(set(truth_lla) - ids)
            if bad:
                raise ImportDataError(f"--truth names unknown user(s) {bad}; users: {sorted(ids)}")
            w.write("truth", 0.0, users=[{"id": uid, "lat_deg": v[0], "lon_deg": v[1], "alt_m": v[2]}
                                         for uid, v in truth_lla.items()])
        w.write("event", 0.0, message=f"imported: GPS from tlog (time base {track.time_base}), ranges from gNB log")
        for t, _, rtype, fields in records:
            w.write(rtype, max(t, 0.0), **fields)
    summary = ImportSummary(
        path=out_path, fixes=len(track.t_unix_s), measurements=len(keep), per_user=dict(per_user),
        dropped_outside=dropped_outside, dropped_unknown_rnti=dict(unknown), start_utc=start_utc,
        duration_s=float(track.t_unix_s[-1] - t_start), time_base=track.time_base, users_without_ranges=absent,
    )
    log.info("wrote %s: %d fixes, %d ranges (%s)", out_path, summary.fixes, summary.measurements,
             ", ".join(f"{k}: {v}" for k, v in summary.per_user.items()))
    return summary
