"""Preflight check of a gNB: discover its UEs, measure each, and say exactly what is wrong.

`uavloc gnb probe` prints a :class:`ProbeResult`; a mission controller calls :func:`probe_gnb` with
its configured RNTIs before take-off and refuses to take off unless ``result.ok``, showing
``result.message()`` (which RNTIs the gNB has, and what it answered for each configured one).

    result = await probe_gnb(gnb, rntis=[0x4601, 0xB0B2], count=1)
    if not result.ok:
        raise MissionError(f"not taking off: {result.message()}")

In trace mode the probe waits (``wait_s``, a progress line every PROGRESS_EVERY_S) for UEs to attach
while its T client is connected, since only a random access seen in the trace gives a UE's absolute
TA; a UE that attached before is named with how to re-attach it.

A probe never raises for what the gNB says or fails to say: every failure becomes a `problem`
(setup: no telnet server, no T tracer, wrong module, no UE, a log without `wall_clock` time stamps) or an
error of one UE (no measurement, no random access seen), in the gNB's own words.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

from mission.gnb.client import GnbClient, GnbConfig, OaiGnbClient
from mission.gnb.oai import RttSample
from mission.gnb.oai_ra import log_time_format
from mission.gnb.tracer import TraceStatus, TTracerClient, trace_served_why
from uavloc.errors import (
    GnbBusyError,
    GnbError,
    GnbNoMeasurementError,
    GnbNoModeError,
    GnbNoRandomAccessError,
    GnbProtocolError,
    GnbTimeoutError,
    GnbTracerError,
    GnbUnknownCommandError,
)

log = logging.getLogger(__name__)
T = TypeVar("T")

#: how much of the end of a gNB log the time-stamp check reads [bytes]
LOG_TAIL_BYTES = 1 << 20
#: tries of one request that timed out (a slow answer on a busy machine is a timeout, asked again;
#: a gNB that stays silent fails the probe after these), with a pause before each new try [s]: a
#: starved gNB is starved for seconds at a time (benchmarks/load.py beside four busy loops: three
#: back-to-back 1 s timeouts aborted 4 of the first 8 loaded missions before take-off)
TIMEOUT_TRIES = 4
RETRY_PAUSES_S = (0.5, 1.0, 2.0)


@dataclass
class UeProbe:
    """What one UE gave: rnti; expected (a configured user); present (among the gNB's UEs);
    samples (RttSample); took_s (request-to-answer time of each sample [s]); errors (the reason
    of each failed attempt, in the gNB's own words)."""

    rnti: int
    expected: bool
    present: bool
    samples: list[RttSample] = field(default_factory=list)
    took_s: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.present and bool(self.samples)

    def to_dict(self) -> dict:
        return {
            "rnti": f"{self.rnti:04x}", "expected": self.expected, "present": self.present, "ok": self.ok,
            "samples": [_sample_dict(s, t) for s, t in zip(self.samples, self.took_s, strict=True)],
            "errors": list(self.errors),
        }


def _sample_dict(s: RttSample, took_s: float) -> dict:
    out = {"range_m": round(s.range_m, 3), "toa_s": s.toa_s, "ta": s.ta, "mu": s.mu, "source": s.source,
           "srs_peak": s.srs_peak, "fs_hz": s.fs_hz, "snr_db": s.snr_db, "took_s": round(took_s, 4)}
    if s.t_wall_s is not None:
        out["t_utc"] = _utc(s.t_wall_s)
    return out


def _utc(t_s: float) -> str:
    return datetime.fromtimestamp(t_s, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


@dataclass
class ProbeResult:
    """The outcome of a probe.

    address: "host:port" (telnet) or "http://host:port" (REST); mode: "rtt", "stock/active" or
    "stock/passive"; gnb_rntis: the UEs the gNB listed (None when discovery failed); ues: one
    UeProbe per UE probed (configured ones first); problems: what is wrong with the setup, one
    sentence each; log_stamps: time-stamp kind of the gNB log (stock modes, else None); count:
    measurements asked per UE.
    """

    address: str
    mode: str
    count: int
    gnb_rntis: list[int] | None = None
    ues: list[UeProbe] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    log_stamps: str | None = None
    duration_s: float = 0.0
    #: trace mode: what the T tracer client saw (mission.gnb.tracer.TraceStatus)
    trace: TraceStatus | None = None
    #: why the client measures in `mode` ("configured", or what mode "auto" found)
    mode_reason: str = ""
    #: each way to measure -> whether this gNB serves it, and why ("rtt", "trace", "stock")
    modes: dict[str, tuple[bool, str]] = field(default_factory=dict)

    @property
    def recommended(self) -> str | None:
        """The best mode this gNB serves: rtt (a modified gNB), then trace, then stock (coarse)."""
        return next((m for m in ("rtt", "trace", "stock") if self.modes.get(m, (False, ""))[0]), None)

    @property
    def ok(self) -> bool:
        """No setup problem, at least one UE, and every probed UE present with a measurement."""
        return not self.problems and bool(self.ues) and all(u.ok for u in self.ues)

    def message(self) -> str:
        """One paragraph: which RNTIs the gNB has and, for every UE that failed, what it answered."""
        if self.gnb_rntis is None:
            has = "the gNB's UEs are unknown"
        else:
            has = f"the gNB has {len(self.gnb_rntis)} UE(s): [{', '.join(f'{r:04x}' for r in self.gnb_rntis)}]"
        parts = [has]
        parts += self.problems
        for u in self.ues:
            if u.ok:
                continue
            if not u.present:
                parts.append(f"UE {u.rnti:04x} is not among them")
            else:
                said = u.errors[-1] if u.errors else "no answer"
                if any(said in p for p in self.problems) or said.startswith("not measured"):
                    said = "see above"
                parts.append(f"UE {u.rnti:04x}: no measurement ({said})")
        head = "gNB ready" if self.ok else "gNB not ready"
        return f"{head} at {self.address} ({self.mode}): " + "; ".join(parts)

    def to_dict(self) -> dict:
        return {"ok": self.ok, "address": self.address, "mode": self.mode, "count": self.count,
                "gnb_rntis": None if self.gnb_rntis is None else [f"{r:04x}" for r in self.gnb_rntis],
                "log_stamps": self.log_stamps, "problems": list(self.problems),
                "ues": [u.to_dict() for u in self.ues], "duration_s": round(self.duration_s, 3),
                "mode_reason": self.mode_reason,
                "trace": None if self.trace is None else asdict(self.trace),
                "modes": {m: {"served": ok, "why": why} for m, (ok, why) in self.modes.items()},
                "recommended": self.recommended, "message": self.message()}

    def lines(self) -> list[str]:
        """Human-readable report, one string per line."""
        out = [self.message()]
        if self.mode_reason and self.mode_reason != "configured":
            out.append(f"  mode {self.mode}: {self.mode_reason}")
        if self.trace is not None:
            t = self.trace
            age = "never" if t.last_event_age_s is None else f"{t.last_event_age_s:.2f} s ago"
            out.append(f"  T tracer {t.address}: {'connected' if t.connected else 'disconnected'}, {t.events} events "
                       f"({t.srs} SRS, {t.rtts} RTTs), last {age}"
                       + (f", missing events: {', '.join(t.missing_events)}" if t.missing_events else "")
                       + (f"; {t.problem}" if t.problem else ""))
        for m, (ok, why) in self.modes.items():
            out.append(f"  mode {m}: {'served' if ok else 'not served'} ({why})")
        if self.modes:
            out.append(f"  recommended mode: {self.recommended or 'none'}")
        for u in self.ues:
            tag = "configured" if u.expected else "found"
            what = (f"{len(u.samples)} random access(es) in the log" if self.mode.endswith("passive")
                    else f"{len(u.samples)}/{self.count} measurement(s)")
            out.append(f"  UE {u.rnti:04x} ({tag}{'' if u.present else ', absent'}): {what}")
            for k, (s, took) in enumerate(zip(u.samples, u.took_s, strict=True), 1):
                snr = "-" if s.snr_db is None else f"{s.snr_db:.1f} dB"
                peak = "" if s.fs_hz is None else f"  SRS peak {s.srs_peak:+.2f} @ {s.fs_hz / 1e6:g} Msps"
                src = "gNB trace" if s.source == "trace" else "gNB log"
                when = "" if s.t_wall_s is None else f"  at {_utc(s.t_wall_s)} ({src})"
                out.append(f"    #{k}: range {s.range_m:8.2f} m  TA {s.ta} (mu {s.mu}){peak}  SNR {snr}  "
                           f"took {took:.3f} s{when}")
            for e in u.errors:
                out.append(f"    error: {e}")
        return out


def check_log_stamps(path: Path) -> tuple[str | None, str | None]:
    """(time-stamp kind of the gNB log's tail, a problem sentence or None)."""
    try:
        with Path(path).open("rb") as fh:
            fh.seek(0, 2)
            size = fh.tell()
            fh.seek(max(0, size - LOG_TAIL_BYTES))
            text = fh.read().decode("utf-8", errors="replace")
    except OSError as exc:
        return None, f"cannot read the gNB log {path}: {exc}"
    kind = log_time_format(text.splitlines())
    if kind in ("wall_clock", "utc_time"):
        return kind, None
    return kind, (f"the gNB log {path} has no wall_clock time stamps (found {kind!r}): run nr-softmodem with "
                  f"--log_config.global_log_options level,nocolor,wall_clock so random accesses line up with "
                  f"telemetry")


async def probe_gnb(client: GnbClient, *, rntis: list[int] | None = None, count: int = 1,
                    log_path: Path | None = None, address: str = "", mode: str = "",
                    clock: Callable[[], float] = time.monotonic, wait_s: float = 0.0,
                    progress: Callable[[str], None] | None = None) -> ProbeResult:
    """Discover the gNB's UEs and take `count` measurements of each UE of `rntis` (default: every UE
    the gNB lists). log_path: a gNB log whose time stamps are checked (stock modes). Trace mode:
    wait up to `wait_s` [s] (at least TRACE_WAIT_S) for UEs to attach and give their round trips
    while the T client is connected, saying what it waits for through `progress` (one line every
    PROGRESS_EVERY_S). Never raises a GnbError: see ProbeResult."""
    if count < 1:
        raise GnbError(f"a probe takes at least one measurement per UE, got count={count}")
    cfg: GnbConfig | None = client.config if isinstance(client, OaiGnbClient) else None
    if cfg is not None:
        address = address or _address(cfg)
        mode = mode or mode_name(client.mode, cfg.stock_mode)
        log_path = log_path if log_path is not None else cfg.log_path
    res = ProbeResult(address=address or "gNB", mode=mode or "?", count=count)
    t0 = clock()
    if log_path is not None:
        res.log_stamps, problem = check_log_stamps(log_path)
        if problem:
            res.problems.append(problem)
    tracer = client.tracer if isinstance(client, OaiGnbClient) and client.mode == "trace" else None
    if tracer is not None:
        fatal = await _probe_trace(client, tracer, res, rntis, count, wait_s, progress, clock)
    else:
        fatal = await _probe_requests(client, res, rntis, count, cfg, clock)
    present = [u for u in res.ues if u.present]
    if present and not any(u.ok for u in present) and mode.startswith("stock") and not fatal:
        res.problems.append("no random access seen for any UE")
    if isinstance(client, OaiGnbClient):
        res.mode_reason = client.mode_reason
        if client.tracer is not None:
            res.trace = client.tracer.status()
    res.duration_s = clock() - t0
    return res


async def _probe_requests(client: GnbClient, res: ProbeResult, rntis: list[int] | None, count: int,
                          cfg: GnbConfig | None, clock: Callable[[], float]) -> str | None:
    """rtt and stock modes: one discovery, then `count` measurements of each UE (requests, or the
    log in passive stock mode); fills `res`, returns what stopped it (None when nothing did)."""
    try:
        res.gnb_rntis = await _asked_again(client.discover)
    except GnbUnknownCommandError as exc:
        res.problems.append(f"discovery failed, telnet module missing: {exc}")
    except GnbError as exc:
        res.problems.append(f"discovery failed: {exc}")
    if res.gnb_rntis is not None and not res.gnb_rntis:
        res.problems.append("no UE is connected to the gNB")
    have = set(res.gnb_rntis or [])
    targets = list(rntis) if rntis is not None else sorted(have)
    for r in targets:
        u = UeProbe(rnti=r, expected=rntis is not None, present=r in have)
        res.ues.append(u)
        if res.gnb_rntis is not None and not u.present:
            u.errors.append("not among the gNB's UEs")
    fatal: str | None = "discovery failed" if res.gnb_rntis is None else None
    passive = isinstance(client, OaiGnbClient) and cfg is not None and client.mode == "stock" and (
        cfg.stock_mode == "passive")
    for u in res.ues:
        if not u.present:
            continue
        if fatal:
            u.errors.append(f"not measured: {fatal}")
            continue
        if passive:
            assert isinstance(client, OaiGnbClient)
            try:
                got = client.passive_samples(u.rnti)[-count:]
            except GnbError as exc:
                u.errors.append(str(exc))
                continue
            u.samples.extend(got)
            u.took_s.extend([0.0] * len(got))
            if not got:
                u.errors.append(f"no random access seen in {cfg.log_path if cfg else 'the gNB log'} (passive: "
                                f"initial accesses, re-attaches and reestablishments only)")
            continue
        for _ in range(count):
            t1 = clock()
            try:
                s = await _asked_again(lambda r=u.rnti: client.measure(r))
            except GnbUnknownCommandError as exc:
                u.errors.append(str(exc))
                res.problems.append(f"wrong telnet module: {exc}")
                fatal = "the gNB lacks the measurement command"
                break
            except GnbNoRandomAccessError as exc:
                u.errors.append(f"no random access seen: {exc}")
                continue
            except (GnbNoMeasurementError, GnbProtocolError) as exc:
                u.errors.append(str(exc))
                continue
            except GnbError as exc:
                u.errors.append(str(exc))
                res.problems.append(f"the gNB stopped answering: {exc}")
                fatal = "the gNB stopped answering"
                break
            if not math.isfinite(s.range_m):
                u.errors.append(f"non-finite range from TA {s.ta}")
                continue
            u.samples.append(s)
            u.took_s.append(clock() - t1)
    return fatal


async def _asked_again(request: Callable[[], Awaitable[T]]) -> T:
    """request(), asked again after a timeout, TIMEOUT_TRIES times in all (the last timeout raised)."""
    for attempt in range(TIMEOUT_TRIES):
        try:
            return await request()
        except (GnbTimeoutError, GnbBusyError) as exc:  # busy: a new connection's request timed out
            if attempt + 1 == TIMEOUT_TRIES:
                raise
            log.info("gNB request timed out (try %d of %d), asking again: %s", attempt + 1, TIMEOUT_TRIES, exc)
            await asyncio.sleep(RETRY_PAUSES_S[attempt])
    raise AssertionError("unreachable")


#: trace mode: the least the probe waits for the UEs' round trips [s] (SRS every 80 ms, a first
#: RTT after three agreeing occasions; an rfsimulator may run at 0.4x real time)
TRACE_WAIT_S = 3.0
#: trace mode: how often the waiting probe asks the gNB for its UEs [s] (a telnet connection each)
TRACE_DISCOVER_EVERY_S = 1.0
#: how often the waiting probe says what it waits for [s]
PROGRESS_EVERY_S = 2.0


async def _probe_trace(client: OaiGnbClient, tracer: TTracerClient, res: ProbeResult, rntis: list[int] | None,
                       count: int, wait_s: float, progress: Callable[[str], None] | None,
                       clock: Callable[[], float]) -> str | None:
    """Trace mode: take `count` round trips of each UE (of `rntis`, else every UE the gNB lists)
    from the T trace, waiting up to max(wait_s, TRACE_WAIT_S) for UEs to attach while the T client
    is connected (their random access carries the absolute TA) and for their round trips. The gNB
    is asked for its UEs every TRACE_DISCOVER_EVERY_S (a timeout or busy server, e.g. the user's
    own telnet session, is asked again; the last UEs stand); `progress` gets a line every
    PROGRESS_EVERY_S. Fills `res`; returns what stopped it (None when nothing did)."""
    t_start = clock()
    wait_s = max(wait_s, TRACE_WAIT_S)
    deadline = t_start + wait_s
    ues: dict[int, UeProbe] = {r: UeProbe(rnti=r, expected=True, present=False) for r in rntis or []}
    why: dict[int, str] = {}
    last_discovery = -math.inf
    last_progress = t_start - PROGRESS_EVERY_S + 1.0  # the first line after 1 s: none when all goes at once
    fatal: str | None = None
    busy = ""  # the last discovery's timeout while the gNB's telnet served someone else
    while True:
        now = clock()
        if now - last_discovery >= TRACE_DISCOVER_EVERY_S:
            last_discovery = now
            try:
                res.gnb_rntis = await client.discover()
                busy = ""
            except GnbUnknownCommandError as exc:
                fatal = f"discovery failed, telnet module missing: {exc}"
            except (GnbTimeoutError, GnbBusyError) as exc:  # another client on the gNB's telnet: asked again
                busy = f"discovery failed: {exc}"
                log.info("trace probe: %s; asking again in %g s", busy, TRACE_DISCOVER_EVERY_S)
            except GnbError as exc:
                fatal = f"discovery failed: {exc}"
            if fatal:
                res.problems.append(fatal)
                break
            for r in res.gnb_rntis or []:
                if rntis is None:
                    ues.setdefault(r, UeProbe(rnti=r, expected=False, present=True))
            for r, u in ues.items():
                u.present = r in (res.gnb_rntis or [])
        for u in ues.values():
            while u.present and len(u.samples) < count:
                t1 = clock()
                try:
                    sample = await client.measure(u.rnti)
                except GnbError as exc:
                    why[u.rnti] = str(exc)
                    break
                if not math.isfinite(sample.range_m):
                    why[u.rnti] = f"non-finite range from TA {sample.ta}"
                    break
                u.samples.append(sample)
                u.took_s.append(clock() - t1)
        if (ues and all(len(u.samples) >= count for u in ues.values())) or clock() >= deadline:
            break
        if progress is not None and clock() - last_progress >= PROGRESS_EVERY_S:
            last_progress = clock()
            progress(_waiting_line(clock() - t_start, wait_s, ues, why, count, tracer))
        await tracer.wait_for_events(min(0.25, max(0.0, deadline - clock())))
    if busy and res.gnb_rntis is None:
        res.problems.append(busy)
    res.ues = sorted(ues.values(), key=lambda u: (not u.expected, u.rnti))
    for u in res.ues:
        if len(u.samples) >= count:
            continue
        if not u.present:
            if res.gnb_rntis is not None:
                u.errors.append("not among the gNB's UEs")
        elif fatal:
            u.errors.append(f"not measured: {fatal}")
        else:
            u.errors.append(why.get(u.rnti, "no round trip in the T trace")
                            + f" (after waiting {clock() - t_start:.0f} s with the T client connected)")
    if res.gnb_rntis is not None and not res.gnb_rntis:
        res.problems.append(f"no UE is connected to the gNB (waited {clock() - t_start:.0f} s with the T client "
                            f"connected: attach the UEs while the probe waits, --wait S)")
    return fatal


def _waiting_line(elapsed_s: float, wait_s: float, ues: dict[int, UeProbe], why: dict[int, str], count: int,
                  tracer: TTracerClient) -> str:
    """One progress line of the waiting trace probe."""
    c = tracer.tracker.counts
    if not ues:
        what = "the gNB lists no UE yet: attach them now"
    else:
        what = "; ".join(f"UE {u.rnti:04x} {len(u.samples)}/{count}"
                         + ("" if len(u.samples) >= count or not u.present else f" ({why.get(u.rnti, 'waiting')})")
                         + ("" if u.present else " (not listed by the gNB)") for u in ues.values())
    return (f"gnb probe: waiting for UEs {elapsed_s:.0f}/{wait_s:.0f} s: {what}; T trace: {c.rars} random "
            f"access(es), {c.srs} SRS")


async def served_modes(client: OaiGnbClient, rntis: list[int]) -> dict[str, tuple[bool, str]]:
    """Which ways to measure the gNB behind `client` serves: its RTT command (tried on one UE), a
    T tracer with SRS events (at config.t_port), a gNB log with wall-clock stamps (config.log_path)."""
    cfg = client.config
    out: dict[str, tuple[bool, str]] = {}
    try:
        out["rtt"] = await client.rtt_command_served(rntis)
    except GnbError as exc:  # a timeout, a lost connection: the command was not seen to answer
        out["rtt"] = (False, f"`{cfg.rtt_module} {cfg.rtt_command}` did not answer ({exc})")
    tracer = client.tracer
    try:
        if tracer is None:
            async with client._new_tracer() as t:
                await t.wait_for_events(1.0)
                st = t.status()
        else:
            st = tracer.status()
        if not st.has_srs:
            out["trace"] = (False, f"the T tracer at {st.address}: its T_messages.txt has no SRS event")
        elif st.srs == 0 and rntis:
            out["trace"] = (False, f"the T tracer at {st.address} answered, but no SRS event came while the gNB has "
                                   f"{len(rntis)} UE(s): the gNB needs do_SRS = 1, and without a core --do-ra on gNB "
                                   f"and UE")
        else:
            out["trace"] = (True, trace_served_why(st))
    except GnbError as exc:
        out["trace"] = (False, str(exc))
    if cfg.log_path is None:
        out["stock"] = (False, "no gNB log given (gnb.log_path / --gnb-log)")
    else:
        kind, problem = check_log_stamps(Path(cfg.log_path))
        out["stock"] = (problem is None, problem or f"the gNB log {cfg.log_path} ({kind} stamps)")
    return out


async def probe_address(config: GnbConfig, *, rntis: list[int] | None = None, count: int = 1, wait_s: float = 0.0,
                        progress: Callable[[str], None] | None = None) -> ProbeResult:
    """probe_gnb on a fresh connection to config's gNB; a gNB that cannot be reached is a problem
    naming the side that failed (its telnet or web server, or its T tracer)."""
    if count < 1:
        raise GnbError(f"a probe takes at least one measurement per UE, got count={count}")
    address = _address(config)
    mode = mode_name(config.mode, config.stock_mode)
    try:
        async with OaiGnbClient(config) as client:
            res = await probe_gnb(client, rntis=rntis, count=count, wait_s=wait_s, progress=progress)
            res.modes = await served_modes(client, res.gnb_rntis or [])
            return res
    except GnbNoModeError as exc:  # auto: the gNB answered, and serves no way to measure
        res = ProbeResult(address=address, mode=mode, count=count)
        res.problems.append(str(exc))
        return res
    except GnbTracerError as exc:  # the telnet (or web) server answered: the T port failed
        res = ProbeResult(address=address, mode=mode, count=count)
        server = "web server" if config.transport == "rest" else "telnet server"
        res.problems.append(f"T tracer failed (the {server} at {address} answered): {exc}")
        return res
    except GnbError as exc:
        res = ProbeResult(address=address, mode=mode, count=count)
        what = "no web server" if config.transport == "rest" else "no telnet server"
        res.problems.append(f"{what}: {exc}")
        return res


def mode_name(mode: str, stock_mode: str) -> str:
    """"rtt", "trace", "auto" or "stock/<active|passive>"."""
    return f"stock/{stock_mode}" if mode == "stock" else mode


def _address(cfg: GnbConfig) -> str:
    """"host:port" over telnet (as before), "http://host:port" over REST."""
    return f"http://{cfg.host}:{cfg.port}" if cfg.transport == "rest" else f"{cfg.host}:{cfg.port}"
