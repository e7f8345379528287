"""The wire under the one gNB client (`mission.gnb.OaiGnbClient`): OAI's telnet server or its web
server (REST), chosen by the address (docs/rest-transport.md).

A transport carries one request line (``module command [p0 [p1]]``) and returns the text the
telnet command printed; it knows nothing of UEs, discovery, measurement modes or the crash guards,
which the client above writes once for both. What differs, and how each transport says it:

- ``TelnetTransport``: one TCP connection; the answer ends with the prompt; OAI serves one client
  at a time and queues the lines of the others (``fresh``: nothing answered yet on this connection,
  so a timeout may mean a busy gNB); a request that runs into a closed socket is still run later.
- ``RestTransport``: HTTP/JSON through aiohttp (``POST /oaisoftmodem/<module>/commands``); the
  answer's ``display`` lines joined with newlines; every HTTP request is run when it arrives
  (no queue of connections), but all of them share one output buffer behind one mutex in the
  gNB (websrv_utils.c ``websrv_printf_start``), so they are serialised there, in no guaranteed
  order.

Both raise `TransportLost` for a connection that failed before an answer (the client retries
those, and only those), GnbTimeoutError/GnbError for connecting, GnbProtocolError for an answer
that is not the transport's format; a command the gNB does not have comes back as the telnet
server's own text (``... is not a softmodem command``), which the client checks once for both.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from dataclasses import dataclass
from typing import Literal, Protocol

from mission.gnb.oai import MAX_REPLY_CHARS, decode_reply, protocol_error, unknown_command_text
from uavloc.errors import GnbError, GnbProtocolError, GnbTimeoutError

log = logging.getLogger(__name__)

Transport = Literal["telnet", "rest"]
TRANSPORTS: tuple[Transport, ...] = ("telnet", "rest")
#: default ports: OAI's --telnetsrv.listenport and --websrv.listenport
DEFAULT_PORTS: dict[Transport, int] = {"telnet": 9090, "rest": 8090}
_SCHEMES: dict[str, Transport] = {"telnet": "telnet", "http": "rest"}

#: OAI's web server refuses a request body longer than this [bytes] (websrv.c, ulfius max_post_body_size)
REST_MAX_BODY_BYTES = 1024
#: at most this many `param` entries per command (websrv.c websrv_processwebfunc: 1 or 2)
REST_MAX_PARAMS = 2
#: OAI's path prefix of the telnet modules' endpoints
REST_PREFIX = "/oaisoftmodem"


class TransportLost(Exception):
    """The connection failed before the answer arrived; the client may re-send on a new one."""


@dataclass(frozen=True)
class GnbAddress:
    """Where the gNB listens and how to talk to it: `HOST:PORT` or `telnet://HOST:PORT` (telnet),
    `http://HOST:PORT` (OAI's web server)."""

    host: str
    port: int
    transport: Transport = "telnet"

    def __str__(self) -> str:
        scheme = "http" if self.transport == "rest" else "telnet"
        return f"{scheme}://{self.host}:{self.port}"


def parse_gnb_address(text: str, default: Transport = "telnet") -> GnbAddress:
    """"HOST[:PORT]", "telnet://HOST[:PORT]" or "http://HOST[:PORT][/]" -> GnbAddress.

    default: the transport of an address without a scheme (a mission file's `gnb.transport`); a
    scheme says it itself. The default port is the transport's OAI default (9090, 8090).
    """
    if default not in TRANSPORTS:
        raise GnbError(f"gNB transport must be one of {', '.join(TRANSPORTS)}, got {default!r}")
    from mission.gnb.config import parse_host_port

    s = text.strip()
    scheme, sep, rest = s.partition("://")
    if sep:
        kind = _SCHEMES.get(scheme.lower())
        if kind is None:
            raise GnbError(f"bad gNB address {text!r}: scheme {scheme!r} is not telnet:// or http:// "
                           f"(https is not served by OAI's web server)")
        if rest.endswith("/"):
            rest = rest[:-1]
        if "/" in rest:
            raise GnbError(f"bad gNB address {text!r}: a path is not allowed (OAI serves {REST_PREFIX}/...)")
    else:
        kind, rest = default, s
    if not rest:
        raise GnbError(f"bad gNB address {text!r}: no host")
    host, port = parse_host_port(rest, DEFAULT_PORTS[kind])
    return GnbAddress(host, port, kind)


class GnbTransport(Protocol):
    """One way of carrying request lines to the gNB (see the module docstring).

    address; fresh: nothing answered yet on the current connection; connected_at: when the current
    connection was opened (monotonic [s]); queued_by_connection: the gNB serves connections one
    after the other, so a request left on an older connection runs before anything on a newer one
    (telnet); settle_request: a harmless request whose answer proves that everything the gNB had
    queued before it has run; settle_when_fresh: ask it before the first `o1 stats` of a connection.
    """

    address: GnbAddress
    fresh: bool
    connected_at: float
    queued_by_connection: bool
    settle_request: str
    settle_when_fresh: bool

    @property
    def connected(self) -> bool: ...

    async def connect(self) -> None: ...

    async def exchange(self, line: str) -> str: ...

    async def read_late(self, wait_s: float) -> list[str]: ...

    async def answer_after_timeout(self, line: str, wait_s: float) -> str | None: ...

    async def goodbye(self) -> None: ...

    async def close(self) -> None: ...

    def drop(self) -> None: ...

    def busy_message(self, line: str, timeout_s: float) -> str: ...

    def unanswered(self) -> bytes:
        """What the server sent that no complete answer ended yet (after a timed-out exchange)."""
        ...


# ---------------------------------------------------------------------------------------------
# telnet


class TelnetTransport:
    """OAI's telnet server: a line out, everything up to the prompt back."""

    queued_by_connection = True
    #: a line of one character, which OAI never parses and answers with the bare prompt
    #: (shared/data/oai-2025.w36/02_noue_probe.txt)
    settle_request = "e"
    settle_when_fresh = True

    def __init__(self, address: GnbAddress, prompt: str, connect_timeout_s: float) -> None:
        self.address = address
        self.prompt = prompt
        self.connect_timeout_s = connect_timeout_s
        self._prompt = prompt.encode()
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self.fresh = True
        self.connected_at = -math.inf

    @property
    def connected(self) -> bool:
        return self._writer is not None

    async def connect(self) -> None:
        a = self.address
        try:
            async with asyncio.timeout(self.connect_timeout_s):
                self._reader, self._writer = await asyncio.open_connection(
                    a.host, a.port, limit=MAX_REPLY_CHARS + len(self._prompt))
        except TimeoutError:
            raise GnbTimeoutError(f"connecting to the gNB at {a} timed out after "
                                  f"{self.connect_timeout_s:g} s") from None
        except OSError as exc:
            raise GnbError(f"cannot connect to the gNB telnet server at {a.host}:{a.port}: {exc} "
                           f"(is nr-softmodem running with --telnetsrv?)") from exc
        self.fresh = True
        self.connected_at = time.monotonic()
        log.debug("connected to gNB %s", a)

    async def exchange(self, line: str) -> str:
        assert self._reader is not None and self._writer is not None
        try:
            self._writer.write(line.encode() + b"\n")
            await self._writer.drain()
        except (ConnectionError, OSError) as exc:
            raise TransportLost(f"connection to the gNB failed: {exc}") from None
        return await self._read_answer(line)

    async def answer_after_timeout(self, line: str, wait_s: float) -> str | None:
        """The answer of the exchange a timeout interrupted, if it came after all: taken from the
        stream's buffer at once when the prompt is there (the event loop resumed after the deadline
        with the answer already read), else read for at most wait_s [s] more (0: not at all);
        None when no prompt came. Raises as `exchange` does for a lost or malformed stream."""
        if self._reader is None:
            return None
        if self._prompt not in self.unanswered() and wait_s <= 0:
            return None
        try:
            # with the prompt in the buffer readuntil returns without waiting
            async with asyncio.timeout(max(wait_s, 0.0) if self._prompt not in self.unanswered() else None):
                return await self._read_answer(line)
        except TimeoutError:
            return None

    async def _read_answer(self, line: str) -> str:
        assert self._reader is not None
        try:
            data = await self._reader.readuntil(self._prompt)
        except asyncio.IncompleteReadError as exc:
            raise TransportLost(f"the gNB closed the connection ({len(exc.partial)} bytes of answer)") from None
        except asyncio.LimitOverrunError:
            self.drop()
            raise protocol_error(f"answer to {line!r} longer than {MAX_REPLY_CHARS} bytes without a prompt",
                                 "") from None
        except (ConnectionError, OSError) as exc:
            raise TransportLost(f"connection to the gNB failed: {exc}") from None
        self.fresh = False
        return decode_reply(data, self.prompt)

    async def read_late(self, wait_s: float) -> list[str]:
        """Lines that follow the prompt within wait_s [s], up to the first `rfsimu_` one."""
        out: list[str] = []
        reader = self._reader
        if reader is None:
            return out
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(wait_s):
                while True:
                    text = (await reader.readuntil(b"\n")).decode("utf-8", errors="replace")
                    if text.strip():
                        out.append(text)
                        if text.lstrip().startswith("rfsimu_"):
                            break
        return out

    async def goodbye(self) -> None:
        """Say `exit` (OAI closes on input starting with `ex`)."""
        if self._writer is not None:
            with contextlib.suppress(ConnectionError, OSError):
                self._writer.write(b"exit\n")

    async def close(self) -> None:
        w, self._writer, self._reader = self._writer, None, None
        if w is not None:
            w.close()
            with contextlib.suppress(ConnectionError, OSError, TimeoutError):
                async with asyncio.timeout(1.0):
                    await w.wait_closed()

    def drop(self) -> None:
        w, self._writer, self._reader = self._writer, None, None
        if w is not None:
            w.close()

    def unanswered(self) -> bytes:
        """The bytes after the last prompt that no prompt ended yet (the stream's buffer after a
        timed-out read; empty when nothing came)."""
        buf = getattr(self._reader, "_buffer", None)  # CPython's StreamReader keeps unread bytes there
        return bytes(buf) if buf else b""

    def busy_message(self, line: str, timeout_s: float) -> str:
        return (f"no answer to {line!r} within {timeout_s:g} s on a new connection to {self.address.host}:"
                f"{self.address.port}: the OAI telnet server serves one client at a time; is another client "
                f"connected (or is the gNB hung)?")


# ---------------------------------------------------------------------------------------------
# REST (OAI's web server)


def rest_request(line: str) -> tuple[str, dict]:
    """A request line -> (module, the JSON body of `POST /oaisoftmodem/<module>/commands`).

    ``module command [p0 [p1]]``: OAI's web server takes at most two parameters, each with all four
    keys (name, value, type, modifiable; websrv.c unpacks ``{s:s,s:s,s:s,s:b}``), and a command
    without parameters must carry no `param` at all (an empty list is refused with HTTP 500). It
    hands the command ``"p0 p1"``, ``"p0 "`` or ``" "`` (never nothing).
    """
    parts = line.split()
    if len(parts) < 2:
        raise GnbError(f"a REST request names a module and a command, got {line!r}")
    module, command, params = parts[0], parts[1], parts[2:]
    if len(params) > REST_MAX_PARAMS:
        raise GnbError(f"OAI's web server takes at most {REST_MAX_PARAMS} parameters, {line!r} has {len(params)}")
    body: dict = {"name": command}
    if params:
        body["param"] = [{"name": f"P{k}", "value": v, "type": "string", "modifiable": False}
                         for k, v in enumerate(params)]
    return module, body


def parse_rest_display(raw: bytes) -> str:
    """The body of an HTTP 200 answer, ``{"display": ["line", ...]}`` -> the text the command printed
    (its lines joined, each ended by a newline: what the telnet server would have sent before the
    prompt, less the empty lines, which OAI's strtok drops). GnbProtocolError on anything else."""
    if len(raw) > MAX_REPLY_CHARS:
        raise protocol_error(f"REST answer longer than {MAX_REPLY_CHARS} bytes", raw)
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise protocol_error("REST answer is not a UTF-8 JSON document", raw) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("display"), list):
        raise protocol_error('REST answer is not an object with a list "display"', raw)
    lines = doc["display"]
    if not all(isinstance(x, str) for x in lines):
        raise protocol_error('REST "display" holds something else than strings', raw)
    text = "".join(f"{x}\n" for x in lines)
    if "\x00" in text:
        raise protocol_error("REST answer contains NUL characters", text)
    return text


def parse_rest_modules(raw: bytes) -> list[str]:
    """`GET /oaisoftmodem/commands` -> the loaded telnet modules' names; GnbProtocolError otherwise."""
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise protocol_error("the module list is not a UTF-8 JSON document", raw) from None
    if not isinstance(doc, list) or not all(isinstance(d, dict) and isinstance(d.get("name"), str) for d in doc):
        raise protocol_error('the module list is not a list of {"name": ...}', raw)
    return [d["name"] for d in doc]


class RestTransport:
    """OAI's web server (`--websrv`, port `--websrv.listenport`, default 8090) through aiohttp.

    One keep-alive connection (aiohttp's connector with limit 1); `connect` reads the module list
    (`GET /oaisoftmodem/commands`), which also tells an OAI web server from anything else on that
    port; `exchange` posts the command and returns its display lines.
    """

    queued_by_connection = False
    #: read-only in every OAI version (stock refuses any buffer, websrv always passes one); it goes
    #: through the shared output buffer, so its answer comes after a command waiting there
    settle_request = "ci get_single_rnti"
    settle_when_fresh = False

    def __init__(self, address: GnbAddress, connect_timeout_s: float) -> None:
        self.address = address
        self.connect_timeout_s = connect_timeout_s
        self.base = f"http://{address.host}:{address.port}{REST_PREFIX}"
        self._session = None  # aiohttp.ClientSession
        self.modules: list[str] = []
        self.fresh = True
        self.connected_at = -math.inf

    @property
    def connected(self) -> bool:
        return self._session is not None

    async def connect(self) -> None:
        import aiohttp

        a = self.address
        session = aiohttp.ClientSession(
            connector=aiohttp.TCPConnector(limit=1, force_close=False),
            timeout=aiohttp.ClientTimeout(total=None, sock_connect=self.connect_timeout_s),
            raise_for_status=False)
        try:
            async with asyncio.timeout(self.connect_timeout_s):
                async with session.get(f"{self.base}/commands") as resp:
                    status, raw = resp.status, await resp.read()
        except TimeoutError:
            await session.close()
            raise GnbTimeoutError(f"no HTTP answer from the gNB at {a} within {self.connect_timeout_s:g} s "
                                  f"(is this OAI's web server port, --websrv.listenport, default 8090? a telnet "
                                  f"port says nothing to an HTTP request)") from None
        except aiohttp.ClientConnectorError as exc:
            await session.close()
            raise GnbError(f"cannot connect to the gNB web server at {a}: {exc.os_error} (is nr-softmodem "
                           f"running with --websrv and --telnetsrv?)") from exc
        except aiohttp.ClientError as exc:
            await session.close()
            said = str(exc)
            if "softmodem" in said and "not a softmodem command" in said:
                why = "it answered each header line as OAI's telnet server does (`... is not a softmodem command`)"
            else:
                why = f"{type(exc).__name__}: {' '.join(said.split())[:120]}"
            raise GnbProtocolError(f"the server at {a} does not speak HTTP: {why}; a telnet port is given as "
                                   f"telnet://{a.host}:{a.port} or {a.host}:{a.port}") from exc
        except BaseException:
            await session.close()
            raise
        try:
            if status != 200:
                raise protocol_error(f"{a} is not OAI's web server: GET {REST_PREFIX}/commands answered HTTP "
                                     f"{status}", raw)
            self.modules = parse_rest_modules(raw)
        except GnbError:
            await session.close()
            raise
        self._session = session
        self.fresh = True
        self.connected_at = time.monotonic()
        log.debug("connected to gNB web server %s, modules %s", a, ", ".join(self.modules))

    async def exchange(self, line: str) -> str:
        import aiohttp

        assert self._session is not None
        module, body = rest_request(line)
        data = json.dumps(body, separators=(",", ":")).encode()
        if len(data) > REST_MAX_BODY_BYTES:
            raise GnbError(f"request {line!r} is {len(data)} bytes as JSON, OAI's web server refuses more than "
                           f"{REST_MAX_BODY_BYTES}")
        if self.modules and module not in self.modules:
            log.debug("%r: module %r not among the web server's modules %s", line, module, self.modules)
            return unknown_command_text(line)
        try:
            async with self._session.post(f"{self.base}/{module}/commands", data=data,
                                          headers={"Content-Type": "application/json"}) as resp:
                status = resp.status
                raw = await resp.content.read(MAX_REPLY_CHARS + 1)
        except (aiohttp.ClientConnectionError, aiohttp.ClientPayloadError) as exc:
            raise TransportLost(f"connection to the gNB web server failed: {type(exc).__name__}: {exc}") from None
        except aiohttp.ClientResponseError as exc:  # not HTTP at all
            raise protocol_error(f"answer to {line!r} is not HTTP ({exc.message})", "") from None
        self.fresh = False
        if status == 200:
            return parse_rest_display(raw)
        text = raw[:200].decode("utf-8", errors="replace")
        if status == 501 or status == 404:  # unknown command (websrv.c), or no such module endpoint:
            # the telnet server's text, so that the one check above the transport says it
            log.debug("%r: HTTP %d %r", line, status, text)
            return unknown_command_text(line)
        if status == 413:
            raise GnbError(f"the gNB web server refused {line!r} as too large (HTTP 413)")
        raise GnbError(f"the gNB web server answered HTTP {status} to {line!r}: {text!r}")

    async def read_late(self, wait_s: float) -> list[str]:
        return []  # the web server waits for a queued command's output and puts it in display

    async def goodbye(self) -> None:
        return None

    async def close(self) -> None:
        s, self._session = self._session, None
        if s is not None:
            with contextlib.suppress(Exception):
                await s.close()

    def drop(self) -> None:
        s, self._session = self._session, None
        if s is not None and s.connector is not None:
            s.connector.close()  # synchronous: the sockets close now, and the session counts as closed

    def unanswered(self) -> bytes:
        return b""  # an HTTP answer comes whole or not at all

    async def answer_after_timeout(self, line: str, wait_s: float) -> str | None:
        return None  # an interrupted HTTP request is gone with its connection

    def busy_message(self, line: str, timeout_s: float) -> str:
        return (f"no answer to {line!r} within {timeout_s:g} s from the gNB web server at {self.address}: it runs "
                f"one command at a time through a single output buffer; is another client's command running "
                f"(or is the gNB hung)?")


def make_transport(address: GnbAddress, prompt: str, connect_timeout_s: float) -> TelnetTransport | RestTransport:
    if address.transport == "rest":
        return RestTransport(address, connect_timeout_s)
    return TelnetTransport(address, prompt, connect_timeout_s)
