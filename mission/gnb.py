"""OAI gNB adapter: an asyncio telnet client for OpenAirInterface's telnet server (DESIGN.md §8).

The controller depends on the small :class:`GnbClient` protocol; :class:`OaiGnbClient` implements
it over TCP for a real (modified or stock) OAI gNB and for the simulated one
(`sitl_scenarios/gnb.py`). The client is an async context manager that owns its connection:

- a request is one line ``module command [args]\\n``; the answer is everything up to the prompt
  ``softmodem_gnb> ``; every request has a timeout;
- a lost connection is re-opened with jittered exponential backoff (seeded rng) and the request
  re-sent, up to `retries` times; after a timeout the connection is closed (a late answer would
  otherwise be read as the next one) and GnbTimeoutError raised;
- OAI serves one client at a time: a fresh connection that is closed before its first answer, or
  stays silent, is reported as GnbBusyError;
- an unknown command (``... is not a softmodem command``) is GnbUnknownCommandError;
- discovery through ``o1 stats`` (RNTI list) or ``ci get_single_rnti``;
- measurement through the RTT command set (default ``rtt pdcch_order <rnti hex>``, names are
  configuration), or the stock fallback: ``ci force_reestab <rnti>`` then the Msg2 line
  ``timing_offset = N`` from the gNB log file, followed like `tail -f` (coarse TA only).

All parsing is in the pure `mission.oai`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol, runtime_checkable

from estimator.ranging import MU_VALUES
from mission.oai import (
    MAX_REPLY_CHARS,
    PROMPT_GNB,
    Msg2Record,
    RttErrorReply,
    RttSample,
    check_known_command,
    decode_reply,
    parse_force_reestab,
    parse_msg2_line,
    parse_o1_stats,
    parse_rtt_reply,
    parse_single_rnti,
    protocol_error,
    sample_from_msg2,
    sample_from_rtt,
)
from uavloc.errors import (
    GnbBusyError,
    GnbError,
    GnbNoMeasurementError,
    GnbTimeoutError,
    GnbUnknownCommandError,
)

__all__ = ["GnbClient", "GnbConfig", "LogFollower", "OaiGnbClient", "RttSample", "parse_host_port"]

log = logging.getLogger(__name__)


@runtime_checkable
class GnbClient(Protocol):
    """What the mission controller needs from a gNB.

    discover(): RNTIs of the connected UEs. measure(rnti): one RttSample of that UE, or
    GnbNoMeasurementError when the gNB answered without a measurement; other GnbError subclasses
    for timeouts, a busy or lost gNB, and malformed answers.
    """

    async def discover(self) -> list[int]: ...

    async def measure(self, rnti: int) -> RttSample: ...


@dataclass(frozen=True)
class GnbConfig:
    """Settings of :class:`OaiGnbClient`.

    host, port: the gNB telnet server (`--telnetsrv.listenport`, default 9090); prompt: what ends
    an answer; mode: "rtt" (RTT command set) or "stock" (force_reestab + Msg2 log line);
    rtt_module, rtt_command: the RTT command's names; discovery: "o1", "single" or "auto" (o1
    stats, falling back to ci get_single_rnti when the o1 module is not loaded);
    request_timeout_s, connect_timeout_s: per request / connection attempt [s]; retries: reconnect
    attempts after a lost connection; backoff_initial_s, backoff_max_s: jittered exponential
    backoff; seed: seeds the jitter; log_path: gNB log file followed in stock mode; msg2_timeout_s:
    how long to wait for the Msg2 line [s]; log_poll_s: log polling period [s]; mu: numerology of
    the UL BWP, the unit of the Msg2 TA (stock mode).
    """

    host: str = "127.0.0.1"
    port: int = 9090
    prompt: str = PROMPT_GNB
    mode: Literal["rtt", "stock"] = "rtt"
    rtt_module: str = "rtt"
    rtt_command: str = "pdcch_order"
    discovery: Literal["auto", "o1", "single"] = "auto"
    request_timeout_s: float = 2.0
    connect_timeout_s: float = 2.0
    retries: int = 3
    backoff_initial_s: float = 0.05
    backoff_max_s: float = 2.0
    seed: int = 0
    log_path: Path | None = None
    msg2_timeout_s: float = 3.0
    log_poll_s: float = 0.01
    mu: int = 1

    def __post_init__(self) -> None:
        if self.mode not in ("rtt", "stock"):
            raise GnbError(f"gNB mode must be 'rtt' or 'stock', got {self.mode!r}")
        if self.discovery not in ("auto", "o1", "single"):
            raise GnbError(f"gNB discovery must be 'auto', 'o1' or 'single', got {self.discovery!r}")
        if self.mode == "stock" and self.log_path is None:
            raise GnbError("stock mode reads the TA from the gNB log: set log_path")
        if self.mu not in MU_VALUES:
            raise GnbError(f"mu must be one of {MU_VALUES}, got {self.mu!r}")
        for name in ("request_timeout_s", "connect_timeout_s", "msg2_timeout_s", "log_poll_s"):
            if not getattr(self, name) > 0:
                raise GnbError(f"{name} must be positive, got {getattr(self, name)!r}")
        if self.retries < 0 or self.backoff_initial_s < 0 or self.backoff_max_s < 0:
            raise GnbError("retries and backoff times must be non-negative")
        for name in ("rtt_module", "rtt_command"):
            v = getattr(self, name)
            if not v or any(c.isspace() for c in v):
                raise GnbError(f"{name} must be one word, got {v!r}")


def parse_host_port(text: str, default_port: int = 9090) -> tuple[str, int]:
    """"HOST:PORT" (or "HOST") -> (host, port); GnbError when the port is not a number."""
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    try:
        p = int(port)
    except ValueError:
        raise GnbError(f"bad gNB address {text!r}: port {port!r} is not a number") from None
    if not 0 < p < 65536:
        raise GnbError(f"bad gNB address {text!r}: port out of range")
    return host.strip("[]") or "127.0.0.1", p


class _ConnectionLost(Exception):
    pass


class LogFollower:
    """Follow a growing log file like `tail -f`, from a mark, for Msg2 lines (polling, no threads).

    Handles a file that does not exist yet, and truncation/rotation (restarts from the beginning).
    """

    def __init__(self, path: Path, poll_s: float = 0.01) -> None:
        self.path = Path(path)
        self.poll_s = poll_s
        self.position = 0
        self._partial = b""

    def _size(self) -> int:
        try:
            return self.path.stat().st_size
        except FileNotFoundError:
            return 0

    def mark(self) -> None:
        """Forget everything written so far: later reads start at the current end of the file."""
        self.position = self._size()
        self._partial = b""

    def read_lines(self) -> list[str]:
        """Complete lines appended since the last read (a partial last line is kept for later)."""
        size = self._size()
        if size < self.position:  # truncated or rotated
            log.info("gNB log %s shrank (%d < %d): reading from the start", self.path, size, self.position)
            self.position, self._partial = 0, b""
        if size == self.position:
            return []
        try:
            with self.path.open("rb") as fh:
                fh.seek(self.position)
                data = fh.read(min(size - self.position, 1 << 22))
        except OSError as exc:
            raise GnbError(f"cannot read the gNB log {self.path}: {exc}") from exc
        self.position += len(data)
        data = self._partial + data
        *complete, self._partial = data.split(b"\n")
        return [ln.decode("utf-8", errors="replace") for ln in complete]

    async def wait_msg2(self, accept: Callable[[Msg2Record], bool], timeout_s: float) -> Msg2Record:
        """The first Msg2 record after the mark that `accept`s; GnbTimeoutError after timeout_s.

        A malformed Msg2 line raises GnbProtocolError (clearer than waiting for the timeout).
        """
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    for line in self.read_lines():
                        rec = parse_msg2_line(line)
                        if rec is not None and accept(rec):
                            return rec
                        if rec is not None:
                            log.debug("ignoring Msg2 of another UE: %s", line.strip())
                    await asyncio.sleep(self.poll_s)
        except TimeoutError:
            raise GnbTimeoutError(f"no matching Msg2 `timing_offset` line in {self.path} within "
                                  f"{timeout_s:g} s") from None


class OaiGnbClient:
    """Telnet client of an OAI gNB (see the module docstring); implements :class:`GnbClient`.

    config: GnbConfig; rng: jitter source (default random.Random(config.seed)); clock: monotonic
    clock [s] used to time-stamp samples (the midpoint of request and answer for RTT samples, the
    time the Msg2 line was read for stock samples).
    """

    def __init__(self, config: GnbConfig | None = None, *, rng: random.Random | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config if config is not None else GnbConfig()
        self.rng = rng if rng is not None else random.Random(self.config.seed)
        self.clock = clock
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._fresh = True  # no answer received yet on the current connection
        self._lock = asyncio.Lock()
        self._stock_lock = asyncio.Lock()
        self._prompt = self.config.prompt.encode()
        self._follower = LogFollower(self.config.log_path, self.config.log_poll_s) if (
            self.config.log_path is not None) else None
        self.known_rntis: list[int] = []
        #: stock mode: requested RNTI -> the RNTI the UE got after its reestablishment
        self.rnti_alias: dict[int, int] = {}
        self.reconnects = 0

    # -- lifecycle -----------------------------------------------------------------------------
    async def __aenter__(self) -> OaiGnbClient:
        async with self._lock:
            await self._connect_with_retry()
        return self

    async def __aexit__(self, *exc_info) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        """Say `exit` (OAI closes on input starting with `ex`) and close the connection."""
        if self._writer is not None:
            with contextlib.suppress(ConnectionError, OSError):
                self._writer.write(b"exit\n")
        await self._close()

    async def _close(self) -> None:
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
        GnbProtocolError (undecodable answer) or GnbError (gNB unreachable).
        """
        if "\n" in line or "\r" in line:
            raise GnbError(f"a request is one line, got {line!r}")
        cfg = self.config
        async with self._lock:
            refused = 0
            last = ""
            for attempt in range(cfg.retries + 1):
                if attempt:
                    self.reconnects += 1
                    await self._backoff(attempt - 1)
                if self._writer is None:
                    try:
                        await self._connect()
                    except GnbError as exc:
                        last = str(exc)
                        log.info("gNB reconnect attempt %d failed: %s", attempt, exc)
                        continue
                fresh = self._fresh
                try:
                    async with asyncio.timeout(cfg.request_timeout_s):
                        data = await self._exchange(line)
                except TimeoutError:
                    await self._close()
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
                    log.info("gNB request %r: %s (attempt %d of %d)", line, exc, attempt + 1, cfg.retries + 1)
                    continue
                self._fresh = False
                return decode_reply(data, cfg.prompt)
            if refused == cfg.retries + 1:
                raise GnbBusyError(f"the gNB at {cfg.host}:{cfg.port} closed every new connection before "
                                   f"answering ({refused} attempts): it serves one client at a time; is "
                                   f"another client connected?")
            raise GnbError(f"request {line!r} failed after {cfg.retries + 1} attempts: {last}")

    # -- discovery -----------------------------------------------------------------------------
    async def discover(self) -> list[int]:
        """RNTIs of the connected UEs, by `o1 stats` or `ci get_single_rnti` (config.discovery)."""
        mode = self.config.discovery
        rntis: list[int] | None = None
        if mode in ("auto", "o1"):
            body = await self.request("o1 stats")
            try:
                rntis = parse_o1_stats(check_known_command(body, "o1 stats")).rntis
            except GnbUnknownCommandError:
                if mode == "o1":
                    raise
                log.info("o1 module not loaded; discovering with `ci get_single_rnti`")
        if rntis is None:
            body = await self.request("ci get_single_rnti")
            single = parse_single_rnti(check_known_command(body, "ci get_single_rnti"))
            if single is None:
                raise GnbNoMeasurementError(
                    "`ci get_single_rnti` says the gNB has not exactly one UE (0 or several); load the o1 "
                    "telnet module (--telnetsrv.shrmod o1) to discover several UEs")
            rntis = [single]
        self.known_rntis = sorted(rntis)
        log.info("gNB reports %d UE(s): %s", len(rntis), ", ".join(f"{r:04x}" for r in self.known_rntis))
        return list(self.known_rntis)

    # -- measurement ---------------------------------------------------------------------------
    async def measure(self, rnti: int) -> RttSample:
        """One range measurement of the UE `rnti` (see GnbClient)."""
        if isinstance(rnti, bool) or not isinstance(rnti, int) or not 0 < rnti <= 0xFFFF:
            raise GnbError(f"RNTI must be an integer 1..0xffff, got {rnti!r}")
        if self.config.mode == "stock":
            return await self._measure_stock(rnti)
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

    async def _measure_stock(self, rnti: int) -> RttSample:
        assert self._follower is not None
        async with self._stock_lock:
            wire = self.rnti_alias.get(rnti, rnti)
            self._follower.mark()
            line = f"ci force_reestab {wire:04x}"
            body = await self.request(line)
            rep = parse_force_reestab(check_known_command(body, line))
            if rep.rnti is None:
                raise GnbNoMeasurementError(f"`{line}` failed: {rep.message}")
            if rep.rnti != wire:
                raise protocol_error(f"force_reestab answered for RNTI {rep.rnti:04x}, asked {wire:04x}", body)
            known = set(self.known_rntis) | set(self.rnti_alias.values())

            def accept(rec: Msg2Record) -> bool:
                # the UE may come back with a new C-RNTI after reestablishment
                return rec.rnti is None or rec.rnti == wire or rec.rnti not in known

            rec = await self._follower.wait_msg2(accept, self.config.msg2_timeout_s)
            if rec.rnti is not None and rec.rnti != wire:
                log.info("UE %04x came back from reestablishment as %04x", wire, rec.rnti)
                self.rnti_alias[rnti] = rec.rnti
            return sample_from_msg2(rec, rnti, self.config.mu, self.clock())


