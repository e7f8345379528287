"""OAI gNB adapter: one asyncio client for OpenAirInterface's telnet server or its web server (REST)
(docs/design.md §8; docs/rest-transport.md).

The controller depends on the small :class:`GnbClient` protocol; :class:`OaiGnbClient` implements
it for a real (modified or stock) OAI gNB and for the simulated one (`sitl_scenarios/gnb/server.py`),
over the transport the address names (`mission.gnb.transport`: ``HOST:PORT`` or
``telnet://HOST:PORT`` telnet, ``http://HOST:PORT`` REST). Everything below is written once, above
the transport. The client is an async context manager that owns its connection:

- in trace mode the telnet connection is opened per request and closed after it (OAI's telnet
  server serves one client at a time, and the trace needs it only for discovery); otherwise it is
  held for the client's life;
- a request is one line ``module command [args]``; telnet sends it and reads up to the prompt
  ``softmodem_gnb> ``, REST posts it to ``/oaisoftmodem/<module>/commands`` and reads the
  ``display`` lines; every request has a timeout; late ``rfsimu_*_cmd:`` lines (OAI prints
  them after the prompt) are taken out of the next answer;
- a lost connection is re-opened with jittered exponential backoff (seeded rng) and the request
  re-sent, up to `retries` times; after a timeout the connection is closed (a late answer would
  otherwise be read as the next one) and GnbTimeoutError raised;
- OAI's telnet server serves one client at a time, its web server one command at a time (one
  output buffer): a fresh connection that is closed before its first answer, or stays silent
  (what OAI does), is reported as GnbBusyError; retries follow connection errors only;
- an unknown command (``... is not a softmodem command``) is GnbUnknownCommandError;
- discovery through ``o1 stats`` (RNTI list) or ``ci get_single_rnti``;
- measurement through the RTT command set (default ``rtt pdcch_order <rnti hex>``, names are
  configuration), or one of two stock modes that read Msg2 lines from the gNB log file (followed
  like `tail -f`, every line fed to :class:`mission.gnb.oai_ra.RaTracker`, coarse TA only):
  *active* sends ``ci force_reestab <rnti>`` and waits for a random access the log proves to be
  that UE's; *passive* sends nothing and returns the UE's random accesses that happened anyway.

Stock OAI 2025.w36 crashes (segfault) on ``ci force_reestab``/``force_ue_release``/
``force_ul_failure``/``get_current_bwp`` with an RNTI it does not have. So a ``ci`` command that
names an RNTI is sent only by :meth:`OaiGnbClient.guarded_ci`, right after a fresh discovery on the
same connection that lists the RNTI, and never retried on another connection;
``force_ue_release`` and ``force_ul_failure`` are never sent at all.

All parsing is in the pure `mission.gnb.oai` and `mission.gnb.oai_ra`.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import random
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

from estimator.ranging import toa_s_from_raw
from mission.gnb.clock_offset import OffsetEstimate
from mission.gnb.config import FORBIDDEN_CI, GnbConfig, backoff_delay_s, check_ci_line, parse_host_port
from mission.gnb.log_follower import LogFollower, StockLog
from mission.gnb.oai import (
    RttErrorReply,
    RttSample,
    check_known_command,
    parse_force_reestab,
    parse_o1_stats,
    parse_rtt_reply,
    parse_single_rnti,
    protocol_error,
    sample_from_rtt,
    split_async_lines,
)
from mission.gnb.oai_ra import RandomAccess, RntiChange
from mission.gnb.trace_order import TraceOrder, TraceOrders
from mission.gnb.trace_rtt import TraceRtt
from mission.gnb.tracer import TTracerClient, trace_served_why
from mission.gnb.transport import GnbAddress, GnbTransport, TransportLost, make_transport, parse_gnb_address
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
    RangingError,
)

__all__ = ["FORBIDDEN_CI", "GnbAddress", "GnbClient", "GnbConfig", "LogFollower", "OaiGnbClient", "RttSample",
           "check_ci_line", "parse_gnb_address", "parse_host_port"]

log = logging.getLogger(__name__)

#: at least this long between two `o1 stats` to one gNB from this process [s]: OAI 2025.w36's
#: nr-softmodem dies with SIGFPE (exit 136) on an `o1 stats` that follows another within a few
#: milliseconds (measured on the real gNB: back to back it died on the 2nd pair; 5 ms and 20 ms
#: apart, 20 pairs each, it lived); README, gNB section
O1_MIN_INTERVAL_S = 0.1
#: (host, port) -> monotonic time of the last `o1 stats` sent there, shared by every client
_O1_LAST_SENT: dict[tuple[str, int], float] = {}
#: (host, port) -> when the connection was opened (monotonic [s]) on which this process sent an
#: `o1 stats` whose answer it never read (a timeout, a lost connection, a cancel; the newest such
#: connection). OAI serves one client at a time, in the order they connected, and runs what a
#: queued client sent when it gets to it, even after that client left
#: (shared/data/oai-2025.w36/04_two_clients.txt); so such a request may run at any later moment,
#: and an `o1 stats` queued behind it would run microseconds after it (the SIGFPE above). A
#: connection opened after that one first asks O1_SETTLE_REQUEST: the gNB answers it only after
#: it has run every request queued before it; the spacing then counts from that answer. (An older
#: connection is served before the stale request: its `o1 stats` is safe, and proves nothing.)
_O1_UNANSWERED: dict[tuple[str, int], float] = {}
#: the request sent before an `o1 stats` on a connection not yet served, or after one left
#: unanswered: a line of one character, which OAI never parses and answers with the bare prompt
#: (shared/data/oai-2025.w36/02_noue_probe.txt). What a busy gNB queues, and what runs into a
#: closed socket if we give up waiting, is then nothing at all: a stale `o1 stats` answered into
#: a closed socket aborted the real gNB (EXIT_STATUS 134) once in ~20 runs of test_oai_live.
O1_SETTLE_REQUEST = "e"

#: a request timeout that fired this share of the timeout late or more was the event loop's lag,
#: not the gNB's silence: the answer gets that lag again (at most LOOP_LAG_EXTENSIONS times)
LOOP_LAG_SHARE = 0.1
LOOP_LAG_EXTENSIONS = 3


@runtime_checkable
class GnbClient(Protocol):
    """What the mission controller needs from a gNB.

    discover(): RNTIs of the connected UEs. measure(rnti): one RttSample of that UE, or
    GnbNoMeasurementError when the gNB answered without a measurement; other GnbError subclasses
    for timeouts, a busy or lost gNB, and malformed answers.
    """

    async def discover(self) -> list[int]: ...

    async def measure(self, rnti: int) -> RttSample: ...


class OaiGnbClient:
    """Client of an OAI gNB over telnet or REST (see the module docstring); implements :class:`GnbClient`.

    config: GnbConfig (its `transport` picks the wire, `mission.gnb.transport`); rng: jitter source
    (default random.Random(config.seed)); clock: monotonic clock [s] used to time-stamp samples
    (the midpoint of request and answer for RTT samples; for stock samples the Msg2 line's
    wall_clock stamp mapped through `wall`, or the time it was read when the log has no such
    stamp); wall: UNIX time [s].

    State of the stock modes: `rnti_alias` (requested RNTI -> the RNTI the UE has now, changed only
    by a log line that proves it), `recent_accesses` (every random access the log proved, newest
    last), `late_lines` (rfsimu output that arrived after its prompt).
    """

    def __init__(self, config: GnbConfig | None = None, *, rng: random.Random | None = None,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time) -> None:
        self.config = config if config is not None else GnbConfig()
        self.rng = rng if rng is not None else random.Random(self.config.seed)
        self.clock = clock
        self.wall = wall
        cfg = self.config
        self.address = GnbAddress(cfg.host, int(cfg.port), cfg.transport)
        self.transport: GnbTransport = make_transport(self.address, cfg.prompt, cfg.connect_timeout_s)
        self._lock = asyncio.Lock()
        self._stock_lock = asyncio.Lock()
        #: stock modes: the gNB log and what it proved (None without a log_path)
        self.stock_log = StockLog(self.config.log_path, self.config.log_poll_s, self.config.log_history,
                                  wall=self.wall) if self.config.log_path is not None else None
        self.late_lines: collections.deque[str] = collections.deque(maxlen=64)
        self.known_rntis: list[int] = []
        self.reconnects = 0
        #: answers taken after their request timeout fired late (the event loop lagged)
        self.late_answers = 0
        #: (sent, received) clock instants [s] of the last answered request
        self.last_exchange_s: tuple[float, float] = (math.nan, math.nan)
        self.ci_sent: list[str] = []
        #: the mode measuring now: the configured one, or ("auto") the one chosen on entering
        self.mode: str = cfg.mode
        self.mode_reason = "configured" if cfg.mode != "auto" else ""
        #: trace mode: the T-tracer client (mission.gnb.tracer), entered with this client
        self.tracer: TTracerClient | None = None
        self._trace_last: dict[int, TraceRtt] = {}
        #: trace mode: the PDCCH orders for UEs the trace has no absolute TA of (mission.gnb.trace_order)
        ts = cfg.trace_settings()
        self.trace_orders = TraceOrders(ts.jump_tolerance_m, ts.max_range_rate_mps)

    # -- lifecycle -----------------------------------------------------------------------------
    async def __aenter__(self) -> OaiGnbClient:
        if self.stock_log is not None:
            self.stock_log.start()
        async with self._lock:
            await self._connect_with_retry()
        try:
            if self.mode == "auto":
                await self._choose_mode()
            elif self.mode == "trace":
                await self._start_tracer()
            async with self._lock:
                await self._let_go_locked()
        except BaseException:
            await self.aclose()
            raise
        return self

    @property
    def holds_connection(self) -> bool:
        """Whether the telnet connection is kept between requests: not in trace mode, which needs
        the telnet server only for discovery. OAI's telnet server serves one client at a time, so a
        held connection would keep out a user's concurrent `rfsimu setdistance` (which got an empty
        answer, then timed out, while uavloc held it: issue 50). Over REST there is no such queue."""
        return not (self.mode == "trace" and self.address.transport == "telnet")

    async def _let_go_locked(self) -> None:
        """Under the lock, after a request: close the telnet connection when it is not held
        (holds_connection); the next request opens a new one."""
        if not self.holds_connection and self.transport.connected:
            await self._space_before_leaving()
            await self.transport.goodbye()
            await self._close(spaced=True)

    def _new_tracer(self) -> TTracerClient:
        cfg = self.config
        return TTracerClient(cfg.host, cfg.t_port, cfg.trace_settings(), connect_timeout_s=cfg.connect_timeout_s,
                             backoff_initial_s=cfg.backoff_initial_s, backoff_max_s=cfg.backoff_max_s,
                             rng=random.Random(cfg.seed + 1), wall=self.wall)

    async def _start_tracer(self) -> None:
        """Connect the T-tracer client; GnbTracerError (naming the T port) when it cannot."""
        tracer = self._new_tracer()
        try:
            await tracer.__aenter__()
        except GnbTracerError:
            raise
        except GnbError as exc:  # the T server answered something that is not a T stream
            raise GnbTracerError(str(exc)) from None
        self.tracer = tracer

    async def rtt_command_served(self, rntis: list[int]) -> tuple[bool, str]:
        """Does this gNB have the RTT command? Tried with one measurement of the first of `rntis`:
        (False, why) with no UE to try it on or for an unknown command (a stock gNB), (True, what
        answered) otherwise; other GnbErrors (a lost or silent gNB) propagate."""
        name = f"`{self.config.rtt_module} {self.config.rtt_command}`"
        if not rntis:
            return False, "no UE to try the RTT command on"
        try:
            await self._measure_rtt(rntis[0])
        except GnbUnknownCommandError:
            return False, f"no {name} command (a stock gNB)"
        except GnbNoMeasurementError as exc:
            return True, f"{name} exists ({exc})"
        return True, f"{name} answered"

    async def _choose_mode(self) -> None:
        """mode "auto": the best way this gNB measures, tried in order: the RTT command (a modified
        gNB: one measurement of a discovered UE), the T tracer with SRS events (a stock gNB run with
        --T_stdout 2), the log file (stock, coarse). Sets `mode` and `mode_reason` (logged)."""
        tried: list[str] = []
        rntis: list[int] = []
        try:
            rntis = await self.discover()
            served, why = await self.rtt_command_served(rntis)
        except GnbError as exc:  # a silent or lost gNB: the command was not seen to answer
            served, why = False, f"`{self.config.rtt_module} {self.config.rtt_command}` did not answer ({exc})"
        if served:
            self.mode, self.mode_reason = "rtt", why
        else:
            tried.append(why)
        if self.mode == "auto":
            try:
                await self._start_tracer()
            except GnbError as exc:
                tried.append(str(exc))
            else:
                assert self.tracer is not None
                if self.tracer.status().has_srs:
                    self.mode = "trace"
                    self.mode_reason = trace_served_why(self.tracer.status(), len(rntis))
                else:
                    tried.append(f"the T tracer at {self.tracer.address}: its T_messages.txt has no SRS event")
                    await self.tracer.__aexit__(None, None, None)
                    self.tracer = None
        if self.mode == "auto" and self.stock_log is not None:
            self.mode, self.mode_reason = "stock", f"the gNB log {self.config.log_path} (coarse: one TA step)"
        if self.mode == "auto":
            raise GnbNoModeError(f"gNB at {self.address}: no way to measure ranges: {'; '.join(tried)}; and no gNB log "
                           f"(gnb.log_path) for the stock mode")
        log.info("gNB mode %s: %s%s", self.mode, self.mode_reason, f" (not: {'; '.join(tried)})" if tried else "")

    async def __aexit__(self, *exc_info) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Say goodbye (telnet: `exit`) and close the connection (and the T tracer's)."""
        if self.tracer is not None:
            tracer, self.tracer = self.tracer, None
            await tracer.__aexit__(None, None, None)
        if self.transport.connected:
            await self._space_before_leaving()
            await self.transport.goodbye()
        await self._close(spaced=True)

    async def _space_before_leaving(self) -> None:
        """Telnet: an `o1 stats` this process left queued behind this connection (_O1_UNANSWERED)
        runs as soon as the connection ends: not within O1_MIN_INTERVAL_S of the last one (maybe
        this connection's own, answered just before)."""
        t = self.transport
        if t.connected and t.queued_by_connection and _O1_UNANSWERED.get(self._key, -math.inf) > t.connected_at:
            await self._o1_spacing()

    async def _close(self, spaced: bool = False) -> None:
        if not spaced:
            await self._space_before_leaving()
        await self.transport.close()

    def _drop(self) -> None:
        """Close the connection at once (no awaiting: safe while being cancelled)."""
        self.transport.drop()

    @property
    def connected(self) -> bool:
        return self.transport.connected

    async def _connect(self) -> None:
        await self.transport.connect()

    async def _backoff(self, attempt: int) -> None:
        cfg = self.config
        await asyncio.sleep(backoff_delay_s(attempt, cfg.backoff_initial_s, cfg.backoff_max_s, self.rng))

    async def _connect_with_retry(self) -> None:
        last: GnbError | None = None
        for attempt in range(self.config.retries + 1):
            if attempt:
                await self._backoff(attempt - 1)
            try:
                await self._connect()
                return
            except GnbProtocolError:
                raise  # something else listens there (a telnet port given as http://): say so at once
            except GnbError as exc:
                last = exc
                log.info("gNB connection attempt %d failed: %s", attempt + 1, exc)
        assert last is not None
        raise last

    # -- one request ---------------------------------------------------------------------------
    async def request(self, line: str) -> str:
        """Send one request line and return the answer text (telnet: before the prompt; REST: the
        display lines).

        Retries after a lost connection (jittered backoff); raises GnbTimeoutError, GnbBusyError,
        GnbProtocolError (undecodable answer), GnbUnknownCommandError or GnbError (gNB unreachable,
        or a `ci` line that check_ci_line refuses).
        """
        check_ci_line(line)
        async with self._lock:
            if line == "o1 stats":
                await self._o1_spacing()
            try:
                return await self._request_locked(line, self.config.retries)
            finally:
                await self._let_go_locked()

    async def _request_locked(self, line: str, retries: int, reconnect: bool = True) -> str:
        if "\n" in line or "\r" in line:
            raise GnbError(f"a request is one line, got {line!r}")
        cfg = self.config
        t = self.transport
        refused = 0
        last = ""
        for attempt in range(retries + 1):
            if attempt:
                self.reconnects += 1
                await self._backoff(attempt - 1)
            if not t.connected:
                if not reconnect:
                    raise GnbError(f"not sending {line!r}: the connection was lost since the check before it")
                try:
                    await self._connect()
                except GnbProtocolError:
                    raise
                except GnbError as exc:
                    last = str(exc)
                    log.info("gNB reconnect attempt %d failed: %s", attempt, exc)
                    continue
            fresh = t.fresh
            o1 = line == "o1 stats"
            sent = answered = False
            loop = asyncio.get_running_loop()
            try:
                deadline = loop.time() + cfg.request_timeout_s
                try:
                    async with asyncio.timeout_at(deadline):
                        if o1:
                            await self._settle_o1()
                            fresh = t.fresh
                        sent = True
                        t_sent = self.clock()
                        text = await t.exchange(line)
                except TimeoutError:
                    # the answer may be in already (the loop resumed late) or the loop, not the
                    # gNB, may have spent the time: only then is it taken or waited for
                    late = await self._late_answer(line, deadline) if sent else None
                    if late is None:
                        raise
                    text = late
                answered = True
                self.last_exchange_s = (t_sent, self.clock())
                if o1:  # it ran before its answer: the spacing counts from the later time
                    _O1_LAST_SENT[self._key] = time.monotonic()
            except TimeoutError:
                got = t.unanswered()
                await self._close()
                if got and fresh and cfg.prompt.encode() not in got:
                    # a new connection that never showed the prompt: not an OAI telnet server?
                    raise protocol_error(
                        f"{cfg.host}:{cfg.port} sent {len(got)} byte(s) but no '{cfg.prompt}' prompt within "
                        f"{cfg.request_timeout_s:g} s after {line!r} (is this the gNB's telnet server, "
                        "nr-softmodem --telnetsrv?); it sent", got) from None
                if fresh and not got:
                    raise GnbBusyError(t.busy_message(line, cfg.request_timeout_s)) from None
                partial = f" ({len(got)} byte(s) of it came, without the prompt)" if got else ""
                raise GnbTimeoutError(f"no answer to {line!r} within {cfg.request_timeout_s:g} s{partial}") from None
            except asyncio.CancelledError:
                # cancelled mid-exchange (e.g. the caller's own timeout): the answer may still
                # arrive, so this connection is out of step; drop it without awaiting
                self._drop()
                raise
            except TransportLost as exc:
                await self._close()
                last = str(exc)
                refused += fresh
                log.info("gNB request %r: %s (attempt %d of %d)", line, exc, attempt + 1, retries + 1)
                continue
            finally:
                if o1 and sent and not answered:  # sent, perhaps, and not answered: it may still run
                    _O1_UNANSWERED[self._key] = max(_O1_UNANSWERED.get(self._key, -math.inf), t.connected_at)
            body, late = split_async_lines(text)
            for ln in late:
                log.debug("late rfsimu output before the answer to %r: %s", line, ln)
                self.late_lines.append(ln)
            return body
        if refused == retries + 1:
            raise GnbBusyError(f"the gNB at {self.address} closed every new connection before "
                               f"answering ({refused} attempts): it serves one client at a time; is "
                               f"another client connected?")
        raise GnbError(f"request {line!r} failed after {retries + 1} attempts: {last}")

    async def _late_answer(self, line: str, deadline: float) -> str | None:
        """After the request timeout fired at loop time `deadline` with `line` sent: its answer, if
        the prompt is in the bytes already read (the event loop ran late, the gNB did not), or, when
        the loop itself lagged past the deadline by more than LOOP_LAG_SHARE of the timeout, if it
        comes within that lag again (the time the loop took from the gNB, given back; at most
        LOOP_LAG_EXTENSIONS times): the timeout is the gNB's time to answer, not the machine's.
        None: a timeout."""
        cfg, t = self.config, self.transport
        loop = asyncio.get_running_loop()
        lag_s = loop.time() - deadline
        for extension in range(LOOP_LAG_EXTENSIONS + 1):
            lagged = lag_s > LOOP_LAG_SHARE * cfg.request_timeout_s and extension < LOOP_LAG_EXTENSIONS
            wait_s = lag_s if lagged else 0.0
            start = loop.time()
            text = await t.answer_after_timeout(line, wait_s)
            if text is not None:
                self.late_answers += 1
                log.info("answer to %r taken after its %g s timeout (the event loop ran %.2f s late)", line,
                         cfg.request_timeout_s, lag_s)
                return text
            if not lagged:
                return None
            lag_s = loop.time() - (start + wait_s)
        return None

    async def request_late(self, line: str, wait_s: float = 2.0) -> str:
        """Send a command whose output OAI prints after the prompt (`rfsimu ...`) and return the
        answer plus the lines that followed within wait_s [s] (empty when OAI printed nothing, e.g.
        rfsimu without a connected peer). Over REST the web server waits for that output itself."""
        check_ci_line(line)
        async with self._lock:
            try:
                body = await self._request_locked(line, self.config.retries)
                out = [body] if body.strip() else []
                out += await self.transport.read_late(wait_s)
                return "".join(out)
            finally:
                await self._let_go_locked()

    # -- discovery -----------------------------------------------------------------------------
    async def discover(self) -> list[int]:
        """RNTIs of the connected UEs, by `o1 stats` or `ci get_single_rnti` (config.discovery)."""
        async with self._lock:
            try:
                return await self._discover_locked()
            finally:
                await self._let_go_locked()

    async def _discover_locked(self) -> list[int]:
        mode = self.config.discovery
        rntis: list[int] | None = None
        if mode in ("auto", "o1"):
            await self._o1_spacing()
            try:
                body = self._check_blank_param(await self._request_locked("o1 stats", self.config.retries), "o1 stats")
                rntis = parse_o1_stats(check_known_command(body, "o1 stats")).rntis
            except GnbUnknownCommandError:
                if mode == "o1":
                    raise
                log.info("o1 module not loaded; discovering with `ci get_single_rnti`")
        if rntis is None:
            body = self._check_blank_param(await self._request_locked("ci get_single_rnti", self.config.retries),
                                           "ci get_single_rnti")
            single = parse_single_rnti(check_known_command(body, "ci get_single_rnti"))
            if single is None:
                raise GnbNoMeasurementError(
                    "`ci get_single_rnti` says the gNB has not exactly one UE (0 or several); load the o1 "
                    "telnet module (--telnetsrv.shrmod o1) to discover several UEs")
            rntis = [single]
        self.known_rntis = sorted(rntis)
        log.debug("gNB reports %d UE(s): %s", len(rntis), ", ".join(f"{r:04x}" for r in self.known_rntis))
        return list(self.known_rntis)

    def _check_blank_param(self, body: str, line: str) -> str:
        """REST: OAI's web server hands a command given no parameter the buffer " " (websrv.c), and
        stock OAI's `o1 stats` and `ci get_single_rnti` refuse any buffer (`if (buf)`: "no parameter
        allowed"): say so, and what to do, instead of a parse error."""
        if self.address.transport == "rest" and "no parameter allowed" in body:
            raise GnbError(
                f"`{line}` over OAI's web server at {self.address} answered {body.strip()!r}: the web server "
                f"passes \" \" to a command given no parameter, and stock OAI (2025.w36) refuses any; "
                f"discover over telnet (telnet://{self.address.host}:9090), or run the modified gNB that "
                f"takes a blank buffer for none (docs/rest-transport.md)")
        return body

    @property
    def _key(self) -> tuple[str, int]:
        return (self.config.host, int(self.config.port))

    async def _o1_spacing(self) -> None:
        """Wait until O1_MIN_INTERVAL_S has passed since this process's last `o1 stats` to this gNB
        (by the real monotonic clock: the hazard is in the gNB's time), then note this one."""
        last = _O1_LAST_SENT.get(self._key)
        if last is not None:
            wait_s = O1_MIN_INTERVAL_S - (time.monotonic() - last)
            if wait_s > 0:
                await asyncio.sleep(wait_s)
        _O1_LAST_SENT[self._key] = time.monotonic()

    async def _settle_o1(self) -> None:
        """Before an `o1 stats` (on the current connection, under the lock), ask the transport's
        settle request first (telnet: O1_SETTLE_REQUEST; REST: a read-only command through the web
        server's shared output buffer) when

        - telnet only: the gNB has not answered anything on this connection yet (it may be serving
          another client: the `o1 stats` must not be what waits in its queue); over REST every
          request runs when it arrives, so there is no such queue;
        - an earlier `o1 stats` to this gNB went unanswered (_O1_UNANSWERED) and may still run:
          over telnet only when it was left on a connection opened before this one (OAI serves
          connections in order: an older one's request runs before anything sent here); over REST
          whenever it was (it may still wait for the output buffer).

        The settle answer comes after that stale request has run (telnet: always; REST: when the
        gNB's mutex hands the buffer over in order, which Linux mutexes usually but not surely do;
        docs/rest-transport.md); then wait O1_MIN_INTERVAL_S from it."""
        t = self.transport
        stale_conn_s = _O1_UNANSWERED.get(self._key)
        stale = stale_conn_s is not None and (not t.queued_by_connection or t.connected_at > stale_conn_s)
        if not ((t.fresh and t.settle_when_fresh) or stale):
            return
        if stale:
            log.info("an earlier `o1 stats` to %s went unanswered and may still run: asking %r first",
                     self.address, t.settle_request)
        _, late = split_async_lines(await t.exchange(t.settle_request))
        self.late_lines.extend(late)
        if stale:
            if _O1_UNANSWERED.get(self._key) == stale_conn_s:
                del _O1_UNANSWERED[self._key]
            _O1_LAST_SENT[self._key] = time.monotonic()
            await self._o1_spacing()

    async def guarded_ci(self, command: str, rnti: int) -> str:
        """Send `ci <command> <rnti hex>` only if a discovery taken just before it, on the same
        connection and under the same lock, lists `rnti`; return the answer.

        GnbNoMeasurementError (nothing sent) when the gNB does not have the RNTI; GnbError for a
        forbidden command or when the connection was lost in between (never re-sent elsewhere).
        """
        line = f"ci {command} {rnti:04x}"
        check_ci_line(line, guarded=True)
        async with self._lock:
            rntis = await self._discover_locked()
            if rnti not in rntis:
                raise GnbNoMeasurementError(
                    f"not sending `{line}`: the gNB's UEs are [{', '.join(f'{r:04x}' for r in rntis)}], "
                    f"without {rnti:04x} (stock OAI crashes on an RNTI it does not have)")
            self.ci_sent.append(line)
            try:
                return await self._request_locked(line, 0, reconnect=False)
            finally:
                await self._let_go_locked()

    # -- the gNB log (stock modes) -----------------------------------------------------------------
    @property
    def rnti_alias(self) -> dict[int, int]:
        """Stock modes: an RNTI -> the RNTI that UE has now, as proven by the gNB log."""
        return self.stock_log.rnti_alias if self.stock_log is not None else {}

    @property
    def recent_accesses(self) -> collections.deque[RandomAccess]:
        """Stock modes: every random access the gNB log proved, newest last."""
        return self.stock_log.recent if self.stock_log is not None else collections.deque()

    def current_rnti(self, rnti: int) -> int:
        return self.stock_log.current_rnti(rnti) if self.stock_log is not None else rnti

    def feed_log(self) -> list[RandomAccess | RntiChange]:
        """Read the gNB log's new lines and return what they proved (stock modes)."""
        return self.stock_log.feed() if self.stock_log is not None else []

    # -- measurement ---------------------------------------------------------------------------
    def clock_offset(self) -> OffsetEstimate | None:
        """The gNB host's clock offset as the stamps of the mode measuring now give it (trace: the T
        events; stock: the log's wall-clock lines); None for the RTT command (no stamps) or before
        any stamp."""
        if self.mode == "trace" and self.tracer is not None:
            return self.tracer.offset.estimate(self.wall())
        if self.mode == "stock" and self.stock_log is not None and not self.stock_log.history:
            return self.stock_log.offset.estimate(self.wall())
        return None

    @property
    def clock_refused(self) -> int:
        """Stamped ranges refused so far because the gNB host's clock offset was not bounded."""
        return ((self.tracer.offset.refused if self.tracer is not None else 0)
                + (self.stock_log.offset.refused if self.stock_log is not None else 0))

    def trace_gaps(self) -> list:
        """Trace mode: what each UE's first SRS after a dropped T connection proved, not yet taken
        (mission.gnb.trace_rtt.GapOutcome, oldest first); [] otherwise."""
        return self.tracer.tracker.drain_gaps() if self.tracer is not None else []

    async def measure(self, rnti: int) -> RttSample:
        """One range measurement of the UE `rnti` (see GnbClient)."""
        if isinstance(rnti, bool) or not isinstance(rnti, int) or not 0 < rnti <= 0xFFFF:
            raise GnbError(f"RNTI must be an integer 1..0xffff, got {rnti!r}")
        if self.mode == "stock":
            if self.config.stock_mode == "passive":
                return self._measure_passive(rnti)
            return await self._measure_active(rnti)
        if self.mode == "trace":
            try:
                sample = self._measure_trace(rnti)
            except GnbNoMeasurementError as exc:
                await self._order_for_trace(rnti)
                raise GnbNoMeasurementError(f"{exc}{self.trace_orders.status(rnti)}") from None
            withheld = self.trace_orders.check(rnti, sample.range_m, sample.t_mono_s)
            if withheld is not None:
                raise GnbNoMeasurementError(withheld)
            return sample
        return await self._measure_rtt(rnti)

    def drain_trace_orders(self) -> list[TraceOrder]:
        """Trace mode: what the PDCCH orders did, not yet taken (oldest first)."""
        return self.trace_orders.drain()

    async def _order_for_trace(self, rnti: int) -> None:
        """Trace mode: one `rtt pdcch_order` for a UE the trace has no absolute TA of (or whose TA
        disagreed with an earlier order), when the gNB serves it (mission.gnb.trace_order)."""
        orders, tracer = self.trace_orders, self.tracer
        if tracer is None or not orders.wanted(rnti, tracer.tracker.without_absolute_ta(rnti), self.clock()):
            return
        orders.sending(rnti, self.clock())
        try:
            s = await self._measure_rtt(rnti)
        except GnbUnknownCommandError as exc:
            orders.not_served(str(exc))
            log.info("no PDCCH order on this gNB for UE %04x's absolute TA: %s", rnti, exc)
            return
        except (GnbNoMeasurementError, GnbTimeoutError, GnbBusyError, GnbProtocolError) as exc:
            orders.failed(rnti, str(exc))
            return
        orders.answered(rnti, s.range_m, s.t_mono_s)
        log.info("UE %04x had no absolute TA in the T trace: PDCCH order sent (answered %.2f m)", rnti, s.range_m)

    def _measure_trace(self, rnti: int) -> RttSample:
        """The UE's newest round trip from the T trace (nothing is sent to the gNB): RAR TA plus the
        applied TA commands plus the SRS peak (mission.gnb.trace_rtt), timed by the gNB's trace
        stamp. GnbNoMeasurementError when there is none, it is older than trace_max_age_s, or it is
        the one the last call returned."""
        tracer = self.tracer
        if tracer is None:
            raise GnbError("trace mode without a T tracer connection")
        r = tracer.tracker.latest(rnti)
        if r is None:
            st = tracer.status()
            why = tracer.tracker.why_none(rnti)
            if not st.connected:
                why += f"; {st.problem or 'the T tracer is disconnected'}"
            raise GnbNoMeasurementError(f"no RTT of UE {rnti:04x} in the T trace: {why}")
        est = tracer.offset.estimate(self.wall())
        if est is None or not est.bounded:
            tracer.offset.refused += 1
            raise GnbNoMeasurementError(f"the RTT of UE {rnti:04x} in the T trace cannot be placed in time: the gNB "
                                        f"host's clock offset is not bounded ({tracer.offset.why_unbounded(est)})")
        # the trace stamp in our wall time: s + θ̂ (mission.gnb.clock_offset)
        age_s = self.wall() - (r.t_wall_s + est.offset_s)
        if age_s > self.config.trace_max_age_s:
            raise GnbNoMeasurementError(
                f"the newest RTT of UE {rnti:04x} in the T trace is {age_s:.2f} s old (frame {r.frame}.{r.slot}, "
                f"limit trace_max_age_s {self.config.trace_max_age_s:g} s): {tracer.tracker.why_none(rnti)}")
        if self._trace_last.get(rnti) is r:
            raise GnbNoMeasurementError(f"no new SRS of UE {rnti:04x} since frame {r.frame}.{r.slot}")
        self._trace_last[rnti] = r
        cfg = self.config
        try:
            toa = toa_s_from_raw(r.ta, cfg.mu, r.peak, cfg.fs_hz)
        except RangingError as exc:
            raise GnbNoMeasurementError(f"UE {rnti:04x}: the trace's TA {r.ta} and peak {r.peak:g} give no ToA "
                                        f"({exc})") from None
        return RttSample(rnti, r.ta, cfg.mu, r.peak, cfg.fs_hz, None, toa, self.clock() - max(0.0, age_s), "trace",
                         t_wall_s=r.t_wall_s, t_unc_s=est.spread_s)

    async def measure_many(self, rntis: list[int]) -> dict[int, RttSample]:
        """Measure several UEs one after the other; UEs without a measurement are left out (logged)."""
        out: dict[int, RttSample] = {}
        for r in rntis:
            try:
                out[r] = await self.measure(r)
            except GnbNoMeasurementError as exc:
                log.info("no measurement of %04x: %s", r, exc)
        return out

    async def _measure_rtt(self, rnti: int) -> RttSample:
        line = f"{self.config.rtt_module} {self.config.rtt_command} {rnti:04x}"
        body = await self.request(line)
        # measured between the request's send and the answer's receipt (the gNB gives no stamp)
        t0, t1 = self.last_exchange_s
        results = parse_rtt_reply(check_known_command(body, line))
        for r in results:
            if isinstance(r, RttErrorReply) and r.rnti in (None, rnti):
                raise GnbNoMeasurementError(f"gNB has no RTT for RNTI {rnti:04x}: {r.message}")
        mine = [r for r in results if not isinstance(r, RttErrorReply) and r.rnti == rnti]
        if len(mine) != 1:
            raise protocol_error(f"expected one RTT result for RNTI {rnti:04x}, got {len(mine)}", body)
        return sample_from_rtt(mine[0], 0.5 * (t0 + t1), 0.5 * (t1 - t0))

    def _measure_passive(self, rnti: int) -> RttSample:
        """The newest round-trip random access of the UE since the last call (nothing is sent)."""
        stock = self.stock_log
        assert stock is not None
        stock.feed()
        cur = stock.current_rnti(rnti)
        fresh = stock.take_fresh(cur)
        if not fresh:
            raise GnbNoRandomAccessError(
                f"no new random access of UE {cur:04x} in {self.config.log_path} (passive mode measures "
                f"only the accesses that happen anyway: initial access, re-attach, reestablishment)")
        return stock.sample(fresh[-1], rnti, self.config.mu, self.clock, self.wall, require_wall=True)

    def passive_samples(self, rnti: int) -> list[RttSample]:
        """Stock passive mode: every round-trip random access of the UE the log proved since the
        last call, oldest first (each a coarse sample with its log time stamp); [] when none."""
        stock = self.stock_log
        if stock is None:
            raise GnbError("passive samples need the gNB log (stock mode, log_path)")
        stock.feed()
        return [stock.sample(ra, rnti, self.config.mu, self.clock, self.wall, require_wall=True)
                for ra in stock.take_fresh(stock.current_rnti(rnti))]

    async def _measure_active(self, rnti: int) -> RttSample:
        """Trigger a reestablishment of the UE (guarded `ci force_reestab`), then wait for a random
        access the log proves to be that UE's, with a round-trip TA."""
        stock = self.stock_log
        assert stock is not None
        async with self._stock_lock:
            stock.feed()  # everything before the trigger is history
            wire = stock.current_rnti(rnti)
            line = f"ci force_reestab {wire:04x}"
            body = await self.guarded_ci("force_reestab", wire)
            rep = parse_force_reestab(check_known_command(body, line))
            if rep.rnti is None:
                raise GnbNoMeasurementError(f"`{line}` failed: {rep.message}")
            if rep.rnti != wire:
                raise protocol_error(f"force_reestab answered for RNTI {rep.rnti:04x}, asked {wire:04x}", body)
            seen: list[str] = []
            t_end = self.clock() + self.config.msg2_timeout_s
            while True:
                for ev in stock.feed():
                    if not isinstance(ev, RandomAccess):
                        continue
                    if ev.kind == "reestablishment" and ev.ue_rnti == wire:
                        stock.forget(ev)
                        return stock.sample(ev, rnti, self.config.mu, self.clock, self.wall, require_wall=False)
                    seen.append(ev.describe())
                    if ev.kind == "connected" and ev.ue_rnti == wire:
                        log.info("UE %04x made a connected-mode random access: its TA %d is a residual, "
                                 "not a range; still waiting", wire, ev.timing_offset)
                if self.clock() >= t_end:
                    raise GnbNoRandomAccessError(
                        f"no random access proven to be UE {wire:04x}'s within {self.config.msg2_timeout_s:g} s "
                        f"after `{line}` (seen: {'; '.join(seen) if seen else 'none'}); stock OAI starts a "
                        f"reestablishment only when the UE has traffic, and a connected-mode RA carries no "
                        f"range")
                await asyncio.sleep(self.config.log_poll_s)
