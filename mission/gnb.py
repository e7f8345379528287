"""OAI gNB adapter: an asyncio telnet client for OpenAirInterface's telnet server (DESIGN.md §8).

The controller depends on the small :class:`GnbClient` protocol; :class:`OaiGnbClient` implements
it over TCP for a real (modified or stock) OAI gNB and for the simulated one
(`sitl_scenarios/gnb.py`). The client is an async context manager that owns its connection:

- a request is one line ``module command [args]\n``; the answer is everything up to the prompt
  ``softmodem_gnb> ``; every request has a timeout; late ``rfsimu_*_cmd:`` lines (OAI prints
  them after the prompt) are taken out of the next answer;
- a lost connection is re-opened with jittered exponential backoff (seeded rng) and the request
  re-sent, up to `retries` times; after a timeout the connection is closed (a late answer would
  otherwise be read as the next one) and GnbTimeoutError raised;
- OAI serves one client at a time: a fresh connection that is closed before its first answer, or
  stays silent (what OAI does), is reported as GnbBusyError;
- an unknown command (``... is not a softmodem command``) is GnbUnknownCommandError;
- discovery through ``o1 stats`` (RNTI list) or ``ci get_single_rnti``;
- measurement through the RTT command set (default ``rtt pdcch_order <rnti hex>``, names are
  configuration), or one of two stock modes that read Msg2 lines from the gNB log file (followed
  like `tail -f`, every line fed to :class:`mission.oai_ra.RaTracker`, coarse TA only):
  *active* sends ``ci force_reestab <rnti>`` and waits for a random access the log proves to be
  that UE's; *passive* sends nothing and returns the UE's random accesses that happened anyway.

Stock OAI 2025.w36 crashes (segfault) on ``ci force_reestab``/``force_ue_release``/
``force_ul_failure``/``get_current_bwp`` with an RNTI it does not have. So a ``ci`` command that
names an RNTI is sent only by :meth:`OaiGnbClient.guarded_ci`, right after a fresh discovery on the
same connection that lists the RNTI, and never retried on another connection;
``force_ue_release`` and ``force_ul_failure`` are never sent at all.

All parsing is in the pure `mission.oai` and `mission.oai_ra`.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
import random
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

from mission.gnb_config import FORBIDDEN_CI, GnbConfig, check_ci_line, parse_host_port
from mission.gnb_log import LogFollower, StockLog
from mission.oai import (
    MAX_REPLY_CHARS,
    RttErrorReply,
    RttSample,
    check_known_command,
    decode_reply,
    parse_force_reestab,
    parse_o1_stats,
    parse_rtt_reply,
    parse_single_rnti,
    protocol_error,
    sample_from_rtt,
    split_async_lines,
)
from mission.oai_ra import RandomAccess, RntiChange
from uavloc.errors import (
    GnbBusyError,
    GnbError,
    GnbNoMeasurementError,
    GnbNoRandomAccessError,
    GnbTimeoutError,
    GnbUnknownCommandError,
)

__all__ = ["FORBIDDEN_CI", "GnbClient", "GnbConfig", "LogFollower", "OaiGnbClient", "RttSample", "check_ci_line",
           "parse_host_port"]

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

@runtime_checkable
class GnbClient(Protocol):
    """What the mission controller needs from a gNB.

    discover(): RNTIs of the connected UEs. measure(rnti): one RttSample of that UE, or
    GnbNoMeasurementError when the gNB answered without a measurement; other GnbError subclasses
    for timeouts, a busy or lost gNB, and malformed answers.
    """

    async def discover(self) -> list[int]: ...

    async def measure(self, rnti: int) -> RttSample: ...


class _ConnectionLost(Exception):
    pass


def _unanswered_bytes(reader: asyncio.StreamReader | None) -> bytes:
    """What the server sent that no prompt ended yet (the stream's buffer after a timed-out
    read; empty when nothing came)."""
    buf = getattr(reader, "_buffer", None)  # CPython's StreamReader keeps unread bytes there
    return bytes(buf) if buf else b""


class OaiGnbClient:
    """Telnet client of an OAI gNB (see the module docstring); implements :class:`GnbClient`.

    config: GnbConfig; rng: jitter source (default random.Random(config.seed)); clock: monotonic
    clock [s] used to time-stamp samples (the midpoint of request and answer for RTT samples; for
    stock samples the Msg2 line's wall_clock stamp mapped through `wall`, or the time it was read
    when the log has no such stamp); wall: UNIX time [s].

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
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._fresh = True  # no answer received yet on the current connection
        self._connected_at = -math.inf  # when the current connection was opened (monotonic [s])
        self._lock = asyncio.Lock()
        self._stock_lock = asyncio.Lock()
        self._prompt = self.config.prompt.encode()
        #: stock modes: the gNB log and what it proved (None without a log_path)
        self.stock_log = StockLog(self.config.log_path, self.config.log_poll_s, self.config.log_history) if (
            self.config.log_path is not None) else None
        self.late_lines: collections.deque[str] = collections.deque(maxlen=64)
        self.known_rntis: list[int] = []
        self.reconnects = 0
        self.ci_sent: list[str] = []

    # -- lifecycle -----------------------------------------------------------------------------
    async def __aenter__(self) -> OaiGnbClient:
        if self.stock_log is not None:
            self.stock_log.start()
        async with self._lock:
            await self._connect_with_retry()
        return self

    async def __aexit__(self, *exc_info) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Say `exit` (OAI closes on input starting with `ex`) and close the connection."""
        if self._writer is not None:
            await self._space_before_leaving()
            with contextlib.suppress(ConnectionError, OSError):
                self._writer.write(b"exit\n")
        await self._close(spaced=True)

    async def _space_before_leaving(self) -> None:
        """An `o1 stats` this process left queued behind this connection (_O1_UNANSWERED) runs as
        soon as the connection ends: not within O1_MIN_INTERVAL_S of the last one (maybe this
        connection's own, answered just before)."""
        if self._writer is not None and _O1_UNANSWERED.get(self._key, -math.inf) > self._connected_at:
            await self._o1_spacing()

    async def _close(self, spaced: bool = False) -> None:
        if not spaced:
            await self._space_before_leaving()
        w, self._writer, self._reader = self._writer, None, None
        if w is not None:
            w.close()
            with contextlib.suppress(ConnectionError, OSError, TimeoutError):
                async with asyncio.timeout(1.0):
                    await w.wait_closed()

    def _drop(self) -> None:
        """Close the connection at once (no awaiting: safe while being cancelled)."""
        w, self._writer, self._reader = self._writer, None, None
        if w is not None:
            w.close()

    @property
    def connected(self) -> bool:
        return self._writer is not None

    async def _connect(self) -> None:
        cfg = self.config
        try:
            async with asyncio.timeout(cfg.connect_timeout_s):
                self._reader, self._writer = await asyncio.open_connection(
                    cfg.host, cfg.port, limit=MAX_REPLY_CHARS + len(self._prompt))
        except TimeoutError:
            raise GnbTimeoutError(f"connecting to the gNB at {cfg.host}:{cfg.port} timed out after "
                                  f"{cfg.connect_timeout_s:g} s") from None
        except OSError as exc:
            raise GnbError(f"cannot connect to the gNB telnet server at {cfg.host}:{cfg.port}: {exc} "
                           f"(is nr-softmodem running with --telnetsrv?)") from exc
        self._fresh = True
        self._connected_at = time.monotonic()
        log.debug("connected to gNB %s:%d", cfg.host, cfg.port)

    async def _backoff(self, attempt: int) -> None:
        cfg = self.config
        # delay = min(max, initial · 2^attempt) · U(0.5, 1)   (equal jitter)
        delay = min(cfg.backoff_max_s, cfg.backoff_initial_s * 2**attempt) * (0.5 + 0.5 * self.rng.random())
        await asyncio.sleep(delay)

    async def _connect_with_retry(self) -> None:
        last: GnbError | None = None
        for attempt in range(self.config.retries + 1):
            if attempt:
                await self._backoff(attempt - 1)
            try:
                await self._connect()
                return
            except GnbError as exc:
                last = exc
                log.info("gNB connection attempt %d failed: %s", attempt + 1, exc)
        assert last is not None
        raise last

    # -- one request ---------------------------------------------------------------------------
    async def _exchange(self, line: str) -> bytes:
        assert self._reader is not None and self._writer is not None
        try:
            self._writer.write(line.encode() + b"\n")
            await self._writer.drain()
            return await self._reader.readuntil(self._prompt)
        except asyncio.IncompleteReadError as exc:
            raise _ConnectionLost(f"the gNB closed the connection ({len(exc.partial)} bytes of answer)") from None
        except asyncio.LimitOverrunError:
            await self._close()
            raise protocol_error(f"answer to {line!r} longer than {MAX_REPLY_CHARS} bytes without a prompt",
                                 "") from None
        except (ConnectionError, OSError) as exc:
            raise _ConnectionLost(f"connection to the gNB failed: {exc}") from None

    async def request(self, line: str) -> str:
        """Send one request line and return the answer text before the prompt.

        Retries after a lost connection (jittered backoff); raises GnbTimeoutError, GnbBusyError,
        GnbProtocolError (undecodable answer) or GnbError (gNB unreachable, or a `ci` line that
        check_ci_line refuses).
        """
        check_ci_line(line)
        async with self._lock:
            return await self._request_locked(line, self.config.retries)

    async def _request_locked(self, line: str, retries: int, reconnect: bool = True) -> str:
        if "\n" in line or "\r" in line:
            raise GnbError(f"a request is one line, got {line!r}")
        cfg = self.config
        refused = 0
        last = ""
        for attempt in range(retries + 1):
            if attempt:
                self.reconnects += 1
                await self._backoff(attempt - 1)
            if self._writer is None:
                if not reconnect:
                    raise GnbError(f"not sending {line!r}: the connection was lost since the check before it")
                try:
                    await self._connect()
                except GnbError as exc:
                    last = str(exc)
                    log.info("gNB reconnect attempt %d failed: %s", attempt, exc)
                    continue
            fresh = self._fresh
            o1 = line == "o1 stats"
            sent = answered = False
            try:
                async with asyncio.timeout(cfg.request_timeout_s):
                    if o1:
                        await self._settle_o1()
                        fresh = self._fresh
                    sent = True
                    data = await self._exchange(line)
                    answered = True
                    if o1:  # it ran before its answer: the spacing counts from the later time
                        _O1_LAST_SENT[self._key] = time.monotonic()
            except TimeoutError:
                got = _unanswered_bytes(self._reader)
                await self._close()
                if got:
                    # something answered, but not an OAI telnet server: say what, not "no answer"
                    raise protocol_error(
                        f"{cfg.host}:{cfg.port} sent {len(got)} byte(s) but no '{cfg.prompt}' prompt within "
                        f"{cfg.request_timeout_s:g} s after {line!r} (is this the gNB's telnet server, "
                        "nr-softmodem --telnetsrv?); it sent", got) from None
                if fresh:
                    raise GnbBusyError(
                        f"no answer to {line!r} within {cfg.request_timeout_s:g} s on a new connection to "
                        f"{cfg.host}:{cfg.port}: the OAI telnet server serves one client at a time; is "
                        f"another client connected (or is the gNB hung)?") from None
                raise GnbTimeoutError(f"no answer to {line!r} within {cfg.request_timeout_s:g} s") from None
            except asyncio.CancelledError:
                # cancelled mid-exchange (e.g. the caller's own timeout): the answer may still
                # arrive, so this connection is out of step; drop it without awaiting
                self._drop()
                raise
            except _ConnectionLost as exc:
                await self._close()
                last = str(exc)
                refused += fresh
                log.info("gNB request %r: %s (attempt %d of %d)", line, exc, attempt + 1, retries + 1)
                continue
            finally:
                if o1 and sent and not answered:  # sent, perhaps, and not answered: it may still run
                    _O1_UNANSWERED[self._key] = max(_O1_UNANSWERED.get(self._key, -math.inf), self._connected_at)
            self._fresh = False
            body, late = split_async_lines(decode_reply(data, cfg.prompt))
            for ln in late:
                log.debug("late rfsimu output before the answer to %r: %s", line, ln)
                self.late_lines.append(ln)
            return body
        if refused == retries + 1:
            raise GnbBusyError(f"the gNB at {cfg.host}:{cfg.port} closed every new connection before "
                               f"answering ({refused} attempts): it serves one client at a time; is "
                               f"another client connected?")
        raise GnbError(f"request {line!r} failed after {retries + 1} attempts: {last}")

    async def request_late(self, line: str, wait_s: float = 2.0) -> str:
        """Send a command whose output OAI prints after the prompt (`rfsimu ...`) and return the
        answer plus the lines that followed within wait_s [s] (empty when OAI printed nothing, e.g.
        rfsimu without a connected peer)."""
        check_ci_line(line)
        async with self._lock:
            body = await self._request_locked(line, self.config.retries)
            out = [body] if body.strip() else []
            reader = self._reader
            assert reader is not None
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(wait_s):
                    while True:
                        raw = await reader.readuntil(b"\n")
                        text = raw.decode("utf-8", errors="replace")
                        if text.strip():
                            out.append(text)
                            if text.lstrip().startswith("rfsimu_"):
                                break
            return "".join(out)

    # -- discovery -----------------------------------------------------------------------------
    async def discover(self) -> list[int]:
        """RNTIs of the connected UEs, by `o1 stats` or `ci get_single_rnti` (config.discovery)."""
        async with self._lock:
            return await self._discover_locked()

    async def _discover_locked(self) -> list[int]:
        mode = self.config.discovery
        rntis: list[int] | None = None
        if mode in ("auto", "o1"):
            await self._o1_spacing()
            body = await self._request_locked("o1 stats", self.config.retries)
            try:
                rntis = parse_o1_stats(check_known_command(body, "o1 stats")).rntis
            except GnbUnknownCommandError:
                if mode == "o1":
                    raise
                log.info("o1 module not loaded; discovering with `ci get_single_rnti`")
        if rntis is None:
            body = await self._request_locked("ci get_single_rnti", self.config.retries)
            single = parse_single_rnti(check_known_command(body, "ci get_single_rnti"))
            if single is None:
                raise GnbNoMeasurementError(
                    "`ci get_single_rnti` says the gNB has not exactly one UE (0 or several); load the o1 "
                    "telnet module (--telnetsrv.shrmod o1) to discover several UEs")
            rntis = [single]
        self.known_rntis = sorted(rntis)
        log.debug("gNB reports %d UE(s): %s", len(rntis), ", ".join(f"{r:04x}" for r in self.known_rntis))
        return list(self.known_rntis)

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
        """Before an `o1 stats` (on the current connection, under the lock), ask O1_SETTLE_REQUEST
        first when the gNB has not answered anything on this connection yet (it may be serving
        another client: the `o1 stats` must not be what waits in its queue), or when an earlier
        `o1 stats` to this gNB went unanswered on a connection opened before this one
        (_O1_UNANSWERED): the answer comes after that stale request has run; then wait
        O1_MIN_INTERVAL_S from it."""
        stale_conn_s = _O1_UNANSWERED.get(self._key)
        stale = stale_conn_s is not None and self._connected_at > stale_conn_s
        if not (self._fresh or stale):
            return
        if stale:
            log.info("an earlier `o1 stats` to %s:%d went unanswered and may still run: asking %r first",
                     *self._key, O1_SETTLE_REQUEST)
        _, late = split_async_lines(decode_reply(await self._exchange(O1_SETTLE_REQUEST), self.config.prompt))
        self.late_lines.extend(late)
        self._fresh = False
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
            return await self._request_locked(line, 0, reconnect=False)

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
    async def measure(self, rnti: int) -> RttSample:
        """One range measurement of the UE `rnti` (see GnbClient)."""
        if isinstance(rnti, bool) or not isinstance(rnti, int) or not 0 < rnti <= 0xFFFF:
            raise GnbError(f"RNTI must be an integer 1..0xffff, got {rnti!r}")
        if self.config.mode == "stock":
            if self.config.stock_mode == "passive":
                return self._measure_passive(rnti)
            return await self._measure_active(rnti)
        return await self._measure_rtt(rnti)

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
        t0 = self.clock()
        body = await self.request(line)
        t1 = self.clock()
        results = parse_rtt_reply(check_known_command(body, line))
        for r in results:
            if isinstance(r, RttErrorReply) and r.rnti in (None, rnti):
                raise GnbNoMeasurementError(f"gNB has no RTT for RNTI {rnti:04x}: {r.message}")
        mine = [r for r in results if not isinstance(r, RttErrorReply) and r.rnti == rnti]
        if len(mine) != 1:
            raise protocol_error(f"expected one RTT result for RNTI {rnti:04x}, got {len(mine)}", body)
        return sample_from_rtt(mine[0], 0.5 * (t0 + t1))

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
