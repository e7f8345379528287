"""The live view's HTTP server (aiohttp), inside the mission's own event loop.

One page (`/`, with its script and style from this package: no CDN) and a small API:

- `GET /api/info`: {"mode": "live" | "log", "t_end_s", "tiles_url", "title"};
- `GET /api/frame[?t=SECONDS]`: a whole frame (:meth:`mission.view.state.ViewState.frame`), in log
  mode the state at mission time t (the time slider);
- `GET /ws` (live mode): a WebSocket of frames. Each client has its own sender task that waits for
  the state to change, builds one frame with what that client has not seen yet (incremental
  tracks and events) and sends it, at most `max_rate_hz`. The client acknowledges each frame (any
  text message); the next frame goes out only after that, so at most one frame per client is in
  flight and a slow client gets the newest state when it is ready, skipping the frames in between.
  Nothing waits on a browser: the mission only updates the state (O(1) per record) and pulses;
  nothing is queued per client.

Load: every request, on any route, takes a token from one budget of `max_requests_hz` per second
(bursts up to `request_burst`); a request with none left gets 429 with Retry-After, answered only
after `refused_delay_s` (a client polling in a loop waits there, at no cost to the loop, instead
of asking again at once), so that no number of polling clients can take more of the mission's
event loop than that. The live frame of
`/api/frame` is built once per state. Malformed requests get aiohttp's 400 and one debug line in
the log, not a traceback on the mission's console.

Access: on a loopback address nobody else can connect, and requests must name a loopback host
(no DNS rebinding). On any other address an access token is required: the URL printed at start
carries `?token=...`; the page sets it as a cookie; any request without a valid token gets 403.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import hashlib
import hmac
import json
import logging
import re
import secrets
import threading
import time
from collections.abc import Callable
from importlib import resources
from urllib.parse import urlsplit

from aiohttp import WSMsgType, web
from aiohttp.http_exceptions import HttpProcessingError

from mission.view.address import check_tiles_url, is_loopback
from mission.view.state import Cursor, Timeline, ViewState
from uavloc.errors import MissionError

log = logging.getLogger(__name__)

TOKEN_COOKIE = "uavloc_view_token"
STATIC_FILES = {"view.js": "text/javascript", "view3d.js": "text/javascript", "view.css": "text/css",
                "index.html": "text/html"}
#: three.js, vendored from npm (static/vendor/README.md)
VENDOR_FILES = {"three.module.min.js": "text/javascript", "OrbitControls.js": "text/javascript"}
#: the page's import map (an inline script: allowed by its hash in the Content-Security-Policy)
_IMPORT_MAP = re.compile(r'<script type="importmap">(.*?)</script>', re.S)
LOOPBACK_NAMES = {"localhost", "127.0.0.1", "::1", "[::1]"}


def _host_name(host_header: str) -> str:
    """The host of a Host header value (`name`, `name:port`, `[v6]:port`)."""
    if host_header.startswith("["):
        return host_header[1:].split("]", 1)[0]
    return host_header.rsplit(":", 1)[0] if host_header.count(":") == 1 else host_header


class RequestBudget:
    """A token bucket: `rate_hz` requests per second on average, bursts of up to `burst`.

    tokens(t) = min(burst, tokens(t0) + rate_hz · (t − t0)); a request takes one token.
    clock: seconds (monotonic; a test passes its own)."""

    def __init__(self, rate_hz: float, burst: int, clock: Callable[[], float] = time.monotonic):
        if not (rate_hz > 0 and burst >= 1):
            raise MissionError(f"a request budget needs rate_hz > 0 and burst >= 1, got {rate_hz}, {burst}")
        self.rate_hz, self.burst, self.clock = float(rate_hz), int(burst), clock
        self._tokens = float(burst)
        self._t_s = clock()

    def take(self) -> float:
        """0.0 when a token was taken, else the seconds until one is there (nothing taken)."""
        now = self.clock()
        self._tokens = min(float(self.burst), self._tokens + self.rate_hz * max(0.0, now - self._t_s))
        self._t_s = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return 0.0
        return (1.0 - self._tokens) / self.rate_hz


class _RequestLog(logging.LoggerAdapter):
    """aiohttp's request-handler logger: a malformed request (aiohttp's 400 or 413, answered by
    aiohttp) is one debug line, any other failure one error line with the traceback only at debug
    level, so nothing from a browser or a port scanner prints a traceback on the mission's console."""

    def exception(self, msg: object, *args: object, exc_info: object = True, **kw: object) -> None:
        exc = exc_info if isinstance(exc_info, BaseException) else None
        text = (msg % args) if args else str(msg)
        if isinstance(exc, HttpProcessingError):
            self.logger.debug("live view: malformed request (%s): %s", text, str(exc.message).strip())
            return
        what = f"{type(exc).__name__}: {exc}" if exc is not None else "see the debug log"
        self.logger.error("live view: %s: %s", text, what)
        self.logger.debug("live view: %s", text, exc_info=exc_info)


class LiveFeed:
    """The live side: a :class:`ViewState` fed by the mission log writer, and a change pulse.

    :meth:`on_record` is the log writer's listener. It runs on the event loop's thread (where the
    controller writes); from any other thread it is handed over to the loop.
    """

    mode = "live"

    def __init__(self) -> None:
        self.state = ViewState()
        self.ended = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: int | None = None
        self._changed = asyncio.Event()

    def bind_loop(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._thread = threading.get_ident()

    def on_record(self, rec: dict) -> None:
        if self._loop is not None and threading.get_ident() != self._thread:
            self._loop.call_soon_threadsafe(self.on_record, rec)
            return
        self.state.apply(rec)
        self._pulse()

    def end(self) -> None:
        self.ended = True
        self._pulse()

    def _pulse(self) -> None:
        self._changed.set()
        self._changed = asyncio.Event()

    async def wait_change(self, seen_version: int, timeout_s: float) -> None:
        """Return once the state's version differs from `seen_version` (or the feed ended, or timeout)."""
        if self.state.version != seen_version or self.ended:
            return
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                await self._changed.wait()

    @property
    def t_end_s(self) -> float:
        return self.state.t_s

    def frame(self, cursor: Cursor | None = None, t_s: float | None = None) -> tuple[dict, Cursor]:
        doc, cur = self.state.frame(cursor)
        doc["ended"] = self.ended
        return doc, cur


class LogFeed:
    """A recorded mission (`uavloc view LOG`): frames at any time of the slider."""

    mode = "log"

    def __init__(self, records: list[dict]):
        self.timeline = Timeline(records)
        self.ended = True

    @property
    def t_end_s(self) -> float:
        return self.timeline.t_end_s

    def frame(self, cursor: Cursor | None = None, t_s: float | None = None) -> tuple[dict, Cursor]:
        t = self.t_end_s if t_s is None else min(max(0.0, t_s), self.t_end_s)
        doc, cur = self.timeline.state_at(t).frame(None)
        doc["ended"] = True
        doc["t"] = round(t, 3)
        return doc, cur


class ViewServer:
    """An async context manager serving the view of `feed` on host:port.

    token: required on non-loopback hosts (generated when None); tiles_url: background tile URL
    template ({z}/{x}/{y}) or None (metric grid only); max_clients: WebSocket clients at once;
    max_rate_hz: frames per second per client; final_flush_s: on close, how long the senders
    may take to hand the last frame to their clients before the sockets are closed;
    max_requests_hz, request_burst: the request budget of all routes and clients together
    (:class:`RequestBudget`; clock: its clock); refused_delay_s: how long a request over the
    budget waits for its 429.
    """

    def __init__(self, feed: LiveFeed | LogFeed, host: str = "127.0.0.1", port: int = 0, *,
                 token: str | None = None, tiles_url: str | None = None, title: str = "uavloc",
                 max_clients: int = 16, max_rate_hz: float = 5.0, final_flush_s: float = 1.0,
                 max_requests_hz: float = 30.0, request_burst: int = 60, refused_delay_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic):
        if not (max_rate_hz > 0 and max_clients >= 1 and final_flush_s >= 0):
            raise MissionError(f"view server needs max_rate_hz > 0, max_clients >= 1, final_flush_s >= 0; got "
                               f"{max_rate_hz}, {max_clients}, {final_flush_s}")
        self.feed = feed
        self.host = host
        self.port = port
        self.local = is_loopback(host)
        self.token = None if self.local else (token or secrets.token_urlsafe(18))
        self.tiles_url = check_tiles_url(tiles_url)
        self.title = title
        self.max_clients = max_clients
        self.min_interval_s = 1.0 / max_rate_hz
        self.final_flush_s = final_flush_s
        self.budget = RequestBudget(max_requests_hz, request_burst, clock)
        self.refused_delay_s = max(0.0, float(refused_delay_s))
        self.requests_refused = 0  # answered 429: over the request budget
        self._runner: web.AppRunner | None = None
        self._senders: set[asyncio.Task] = set()
        self._sockets: dict[web.WebSocketResponse, asyncio.Event] = {}  # socket -> "frame acknowledged"
        self._closing = asyncio.Event()
        self.frames_sent = 0
        # frames of the current state by client cursor: clients that saw the same send the same text
        self._frame_cache: dict[tuple, tuple[str, int, Cursor]] = {}
        self._frame_cache_state: tuple | None = None

    # -- lifecycle ------------------------------------------------------------------------------

    async def __aenter__(self) -> ViewServer:
        if isinstance(self.feed, LiveFeed):
            self.feed.bind_loop()
        app = web.Application(middlewares=[self._guard])
        app.router.add_get("/", self._index)
        app.router.add_get("/static/{name}", self._static)
        app.router.add_get("/static/vendor/{name}", self._vendor)
        app.router.add_get("/api/info", self._info)
        app.router.add_get("/api/frame", self._frame)
        app.router.add_get("/ws", self._ws)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False,
                                     shutdown_timeout=max(0.5, self.final_flush_s),
                                     logger=_RequestLog(logging.getLogger(f"{__name__}.requests"), {}))
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port, reuse_address=True)
        try:
            await site.start()
        except OSError as exc:
            await self._runner.cleanup()
            raise MissionError(f"live view cannot listen on {self.host}:{self.port}: {exc}") from exc
        self.port = self._runner.addresses[0][1]  # the port the OS chose for port 0
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        """Let each client get the last frame (bounded by final_flush_s), then stop serving."""
        if self._runner is None:
            return
        if isinstance(self.feed, LiveFeed):
            self.feed.end()
        self._closing.set()
        for acked in self._sockets.values():
            acked.set()  # the last frame goes out without waiting for the previous one's ack
        if self._senders:
            await asyncio.wait(set(self._senders), timeout=self.final_flush_s)
        for task in list(self._senders):
            task.cancel()
        async def close_one(ws: web.WebSocketResponse) -> None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(), 0.2)

        await asyncio.gather(*(close_one(ws) for ws in list(self._sockets)))
        runner, self._runner = self._runner, None
        await runner.cleanup()

    @property
    def url(self) -> str:
        host = self.host
        if host in ("0.0.0.0", "::", ""):
            import socket

            host = socket.gethostname()
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.port}/" + (f"?token={self.token}" if self.token else "")

    # -- access ---------------------------------------------------------------------------------

    def _authorized(self, request: web.Request) -> bool:
        if self.token is None:
            # loopback only: refuse requests that name another host (DNS rebinding)
            host = _host_name(request.host)
            return host in LOOPBACK_NAMES or is_loopback(host)
        given = request.query.get("token") or request.cookies.get(TOKEN_COOKIE) or ""
        return hmac.compare_digest(given.encode(), self.token.encode())

    @web.middleware
    async def _guard(self, request: web.Request, handler):
        wait_s = self.budget.take()
        if wait_s > 0.0:
            self.requests_refused += 1
            if self.requests_refused in (1, 10, 100) or self.requests_refused % 1000 == 0:
                log.info("live view: %d request(s) over the budget of %g/s refused (429)", self.requests_refused,
                         self.budget.rate_hz)
            await asyncio.sleep(self.refused_delay_s)
            retry_s = max(1, round(max(wait_s - self.refused_delay_s, 0.0) + 0.5))
            raise web.HTTPTooManyRequests(text="uavloc view: too many requests, try again shortly\n",
                                          headers={"Retry-After": str(retry_s)})
        if not self._authorized(request):
            log.info("live view: refused %s %s from %s (no valid token)", request.method, request.path,
                     request.remote)
            raise web.HTTPForbidden(text="uavloc view: access token required (use the URL printed at start)\n")
        resp = await handler(request)
        if isinstance(resp, web.Response) and not isinstance(resp, web.WebSocketResponse):
            resp.headers.setdefault("Cache-Control", "no-store")
            resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        return resp

    # -- handlers -------------------------------------------------------------------------------

    def _csp(self, html: str) -> str:
        img = "'self' data:"
        if self.tiles_url:
            parts = urlsplit(self.tiles_url)
            img += f" {parts.scheme}://{parts.netloc.replace('{s}', '*')}"
        script = "'self'"
        for m in _IMPORT_MAP.finditer(html):
            digest = base64.b64encode(hashlib.sha256(m.group(1).encode("utf-8")).digest()).decode()
            script += f" 'sha256-{digest}'"
        return (f"default-src 'self'; script-src {script}; style-src 'self'; img-src {img}; "
                "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")

    async def _index(self, request: web.Request) -> web.Response:
        html = resources.files("mission.view").joinpath("static/index.html").read_text(encoding="utf-8")
        resp = web.Response(text=html, content_type="text/html", charset="utf-8")
        resp.headers["Content-Security-Policy"] = self._csp(html)
        if self.token is not None:
            resp.set_cookie(TOKEN_COOKIE, self.token, httponly=True, samesite="Strict")
        return resp

    async def _static(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in STATIC_FILES or name == "index.html":
            raise web.HTTPNotFound()
        body = resources.files("mission.view").joinpath(f"static/{name}").read_bytes()
        return web.Response(body=body, content_type=STATIC_FILES[name], charset="utf-8")

    async def _vendor(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in VENDOR_FILES:
            raise web.HTTPNotFound()
        body = resources.files("mission.view").joinpath(f"static/vendor/{name}").read_bytes()
        resp = web.Response(body=body, content_type=VENDOR_FILES[name], charset="utf-8")
        resp.headers["Cache-Control"] = "max-age=3600"  # unchanged within a version of the package
        return resp

    async def _info(self, request: web.Request) -> web.Response:
        return web.json_response({"mode": self.feed.mode, "t_end_s": self.feed.t_end_s,
                                  "tiles_url": self.tiles_url, "title": self.title,
                                  "max_rate_hz": 1.0 / self.min_interval_s})

    async def _frame(self, request: web.Request) -> web.Response:
        t_s = None
        if "t" in request.query:
            try:
                t_s = float(request.query["t"])
            except ValueError:
                raise web.HTTPBadRequest(text=f"t must be a number of seconds, got {request.query['t']!r}\n") from None
            if t_s != t_s or t_s in (float("inf"), float("-inf")):
                raise web.HTTPBadRequest(text="t must be finite\n")
        if isinstance(self.feed, LiveFeed):
            text = self._frame_text(None)[0]  # built once per state, whoever polls
        else:
            text = json.dumps(self.feed.frame(None, t_s)[0], separators=(",", ":"))
        return web.Response(text=text, content_type="application/json")

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        if not isinstance(self.feed, LiveFeed):
            raise web.HTTPNotFound(text="no live feed: this view shows a recorded mission\n")
        if len(self._sockets) >= self.max_clients or self._closing.is_set():
            raise web.HTTPServiceUnavailable(text=f"at most {self.max_clients} live viewers\n")
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=4096)
        await ws.prepare(request)
        acked = asyncio.Event()
        self._sockets[ws] = acked
        sender = asyncio.create_task(self._send_frames(ws, acked), name="view-sender")
        self._senders.add(sender)
        try:
            async for msg in ws:  # each text message acknowledges the frame in flight
                if msg.type in (WSMsgType.ERROR, WSMsgType.CLOSE):
                    break
                acked.set()
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender
            self._senders.discard(sender)
            self._sockets.pop(ws, None)
        return ws

    def _frame_text(self, cursor: Cursor | None) -> tuple[str, int, Cursor]:
        """(JSON text, state version, new cursor) of the live frame a client with `cursor` needs;
        built once per state and cursor (clients that keep up share it)."""
        feed: LiveFeed = self.feed  # type: ignore[assignment]
        state_key = (feed.state.version, feed.ended)
        if state_key != self._frame_cache_state:
            self._frame_cache.clear()
            self._frame_cache_state = state_key
        key = None if cursor is None else cursor.key()
        hit = self._frame_cache.get(key)
        if hit is None:
            doc, new = feed.frame(cursor)
            hit = (json.dumps(doc, separators=(",", ":")), doc["version"], new)
            self._frame_cache[key] = hit
        return hit

    async def _send_frames(self, ws: web.WebSocketResponse, acked: asyncio.Event) -> None:
        """One client's sender: newest state, what the client lacks, at most max_rate_hz, one
        frame in flight (the next after the client's acknowledgement)."""
        feed: LiveFeed = self.feed  # type: ignore[assignment]
        cursor: Cursor | None = None
        loop = asyncio.get_running_loop()
        try:
            while not ws.closed:
                last_end = feed.ended
                text, seen, cursor = self._frame_text(cursor)
                await ws.send_str(text)
                self.frames_sent += 1
                if last_end:
                    return  # the final frame is out
                t_next = loop.time() + self.min_interval_s
                await acked.wait()
                acked.clear()
                await feed.wait_change(seen, 5.0)
                delay = t_next - loop.time()
                if delay > 0 and not feed.ended:
                    await asyncio.sleep(delay)
        except (ConnectionError, RuntimeError) as exc:  # the client went away mid-send
            log.debug("live view client gone: %s", exc)
