"""An asyncio client of OAI's T tracer that follows every UE's round trip (the gNB's trace mode).

:class:`TTracerClient` is an async context manager: entering connects to the gNB's T server,
reads the server's own T_messages.txt (events −1, −2: the ids of this build), turns on the ranging
events (:data:`mission.gnb.ttrace.RANGING_EVENTS`) and starts its reader task; every event goes to
a :class:`mission.gnb.trace_rtt.TraceRttTracker`. A lost connection is re-opened with jittered
exponential backoff (seeded rng) and the tracker goes on: it is told of the gap
(:meth:`mission.gnb.trace_rtt.TraceRttTracker.connection_gap`), since the TA commands the gNB sent
meanwhile were missed, and checks each UE's TA at its next SRS (its air-time gap rule restarts the
rate gates). Leaving cancels the reader and closes the socket. Nothing is ever sent but the event mask:
the trace is passive and cannot disturb the gNB.

Parsing is in the pure :mod:`mission.gnb.ttrace` and :mod:`mission.gnb.trace_rtt`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import time
from collections.abc import Callable
from dataclasses import dataclass

from mission.gnb.clock_offset import ClockOffset
from mission.gnb.config import backoff_delay_s
from mission.gnb.trace_rtt import TraceRttTracker, TraceSettings
from mission.gnb.ttrace import (
    EV_RAR,
    EV_SRS_CHEST,
    EV_SRS_TOA_NS,
    RANGING_EVENTS,
    TMessages,
    TMessagesAssembler,
    decode_event,
    split_frames,
)
from uavloc.errors import GnbError, GnbProtocolError, GnbTracerError

log = logging.getLogger(__name__)

#: what a user must start the gNB with for this client (docs/oai.md, trace mode)
T_OPTIONS_HINT = "nr-softmodem ... --T_stdout 2 --T_nowait [--T_port PORT]"


@dataclass(frozen=True)
class TraceStatus:
    """What the T client knows now: address; connected; reconnects; missing_events: ranging events
    the gNB's T_messages.txt lacks; has_srs: it has an SRS event; events, srs, rtts: counts since
    start; last_event_age_s: wall seconds since the last event (None before any); problem: the last
    error (empty when none)."""

    address: str
    connected: bool
    reconnects: int
    missing_events: tuple[str, ...]
    has_srs: bool
    events: int
    srs: int
    rtts: int
    last_event_age_s: float | None
    problem: str


def trace_served_why(st: TraceStatus, ues: int = 0) -> str:
    """Why the trace mode is served by the T tracer of status `st` (one wording for the mode
    choice and the probe): it answered with a T_messages.txt that has an SRS event, and whether
    SRS events came yet (none before a UE is attached with SRS configured). ues: how many UEs the
    gNB lists (with some, no SRS yet is the moment just after the T client connected)."""
    if st.srs:
        got = f"{st.srs} SRS events so far"
    elif ues:
        got = f"no SRS event yet: the T client has just connected, the gNB lists {ues} UE(s)"
    else:
        got = "no SRS event yet: none comes before a UE attaches with SRS"
    return f"the T tracer at {st.address} answered, its T_messages.txt has the SRS event ({got})"


class TTracerClient:
    """Client of a gNB's T tracer (see the module docstring).

    host, port: the T server (`--T_port`, default 2021); settings: the tracker's; connect_timeout_s:
    per connection attempt [s]; preamble_timeout_s: how long to wait for the server's T_messages.txt
    [s]; t_messages: the gNB's T_messages.txt for a server that sends none (None: required from
    the server); rng: backoff jitter; wall: UNIX time [s].
    """

    def __init__(self, host: str, port: int, settings: TraceSettings | None = None, *,
                 connect_timeout_s: float = 2.0, preamble_timeout_s: float = 5.0, t_messages: TMessages | None = None,
                 backoff_initial_s: float = 0.05, backoff_max_s: float = 2.0, rng: random.Random | None = None,
                 wall: Callable[[], float] = time.time) -> None:
        self.host, self.port = host, int(port)
        self.tracker = TraceRttTracker(settings)
        #: the gNB host's clock against ours, from every event's arrival − stamp (mission.gnb.clock_offset)
        self.offset = ClockOffset()
        self.connect_timeout_s = connect_timeout_s
        self.preamble_timeout_s = preamble_timeout_s
        self.db: TMessages | None = t_messages
        self._own_db = t_messages
        self.backoff_initial_s, self.backoff_max_s = backoff_initial_s, backoff_max_s
        self.rng = rng if rng is not None else random.Random(0)
        self.wall = wall
        self.reconnects = 0
        self.problem = ""
        self.last_event_wall_s: float | None = None
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._buf = bytearray()
        self._early: list[bytes] = []  # frames read with the preamble, not yet decoded
        self._tg: asyncio.TaskGroup | None = None
        self._task: asyncio.Task | None = None
        #: set whenever events were fed (the probe waits on it)
        self.fed = asyncio.Event()

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    # -- lifecycle -----------------------------------------------------------------------------
    async def __aenter__(self) -> TTracerClient:
        await self._connect()
        self._tg = asyncio.TaskGroup()
        await self._tg.__aenter__()
        self._task = self._tg.create_task(self._run(), name=f"t-tracer {self.address}")
        return self

    async def __aexit__(self, *exc_info) -> None:
        if self._task is not None:
            self._task.cancel()
        if self._tg is not None:
            tg, self._tg = self._tg, None
            with contextlib.suppress(asyncio.CancelledError):
                await tg.__aexit__(None, None, None)
        self._close()

    @property
    def connected(self) -> bool:
        return self._writer is not None and not self._writer.is_closing()

    def _close(self) -> None:
        w, self._writer, self._reader = self._writer, None, None
        if w is not None:
            w.close()

    async def _connect(self, gap: bool = False) -> None:
        """Open the connection, read the server's T_messages.txt, send the event mask; gap: a
        connection dropped before this one (the tracker is told before the new events)."""
        try:
            async with asyncio.timeout(self.connect_timeout_s):
                self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        except (OSError, TimeoutError) as exc:
            raise GnbTracerError(f"no T tracer at {self.address} ({exc or 'timed out'}): start the gNB with "
                           f"{T_OPTIONS_HINT}") from None
        self._buf.clear()
        self._early = []
        try:
            db = await self._read_preamble()
        except OSError as exc:
            self._close()
            raise GnbTracerError(f"the T tracer at {self.address} dropped the connection: {exc}") from None
        except BaseException:
            self._close()
            raise
        self.db = db
        missing = [e for e in RANGING_EVENTS if db.id_of(e) is None]
        if missing:
            log.debug("the gNB's T_messages.txt has no %s", ", ".join(missing))
        assert self._writer is not None
        self._writer.write(db.mask(RANGING_EVENTS))
        await self._writer.drain()
        self.problem = ""
        if gap:
            self.tracker.connection_gap()
        self._drain_buffer()  # what came with the preamble

    async def _read_preamble(self) -> TMessages:
        asm = TMessagesAssembler()
        assert self._reader is not None
        try:
            async with asyncio.timeout(self.preamble_timeout_s):
                while asm.db is None:
                    data = await self._reader.read(1 << 16)
                    if not data:
                        raise GnbTracerError(f"the T tracer at {self.address} closed the connection before sending its "
                                       "T_messages.txt (another tracer connected? OAI's T server takes one)")
                    self._buf += data
                    frames, used = split_frames(self._buf)
                    del self._buf[:used]
                    for i, body in enumerate(frames):
                        if not asm.feed(body):  # a server that sends no T_messages.txt
                            self._early = frames[i:]
                            return self._fallback_db()
                        if asm.db is not None:
                            self._early = frames[i + 1:]
                            break
        except TimeoutError:
            return self._fallback_db()
        return asm.db

    def _fallback_db(self) -> TMessages:
        if self._own_db is None:
            raise GnbProtocolError(
                f"the T tracer at {self.address} sent no T_messages.txt within {self.preamble_timeout_s:g} s: "
                "an OAI older than the T_messages.txt handshake (pass the gNB's own T_messages.txt), or not a "
                "T tracer")
        return self._own_db

    async def _backoff(self, attempt: int) -> None:
        await asyncio.sleep(backoff_delay_s(attempt, self.backoff_initial_s, self.backoff_max_s, self.rng))

    async def _run(self) -> None:
        attempt = 0
        while True:
            if not self.connected:
                try:
                    await self._connect(gap=True)
                    self.reconnects += 1
                    attempt = 0
                    log.info("T tracer at %s reconnected", self.address)
                except GnbError as exc:
                    self.problem = str(exc)
                    await self._backoff(attempt)
                    attempt += 1
                    continue
            try:
                assert self._reader is not None
                data = await self._reader.read(1 << 16)
                if not data:
                    raise ConnectionResetError("the T server closed the connection")
                self._buf += data
                self._drain_buffer()
            except (OSError, GnbProtocolError) as exc:
                self.problem = f"T tracer at {self.address}: {exc}"
                log.warning("%s; reconnecting", self.problem)
                self._close()

    def _drain_buffer(self) -> None:
        frames, self._early = self._early, []
        if self._buf:
            more, used = split_frames(self._buf)
            del self._buf[:used]
            frames += more
        if not frames:
            return
        assert self.db is not None
        arrival = self.wall()
        for body in frames:
            try:
                ev = decode_event(body, self.db)
            except GnbProtocolError as exc:
                self.tracker.counts.malformed += 1
                self.tracker.counts.last_malformed = str(exc)
                continue
            self.offset.add(arrival, ev.t_wall_s)
            self.tracker.feed(ev)
        self.last_event_wall_s = self.wall()
        self.fed.set()

    # -- queries -------------------------------------------------------------------------------
    def status(self) -> TraceStatus:
        db = self.db
        missing = tuple(e for e in (EV_RAR, EV_SRS_CHEST) if db is None or db.id_of(e) is None)
        has_srs = db is not None and (db.id_of(EV_SRS_CHEST) is not None or db.id_of(EV_SRS_TOA_NS) is not None)
        c = self.tracker.counts
        age = None if self.last_event_wall_s is None else max(0.0, self.wall() - self.last_event_wall_s)
        return TraceStatus(self.address, self.connected, self.reconnects, missing, has_srs, c.events, c.srs, c.rtts,
                           age, self.problem)

    async def wait_for_events(self, timeout_s: float) -> bool:
        """Wait until events arrive (True) or timeout_s passes (False)."""
        self.fed.clear()
        try:
            async with asyncio.timeout(timeout_s):
                await self.fed.wait()
            return True
        except TimeoutError:
            return False


__all__ = ["T_OPTIONS_HINT", "TTracerClient", "TraceStatus", "trace_served_why"]
