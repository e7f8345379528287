"""The simulated gNB's web server: OAI's REST interface to the telnet modules (docs/rest-transport.md).

Served next to the telnet port by :class:`sitl_scenarios.gnb.SimulatedGnb` (``rest_port``), over
the same command functions, with OAI 2025.w36's formats and caveats (common/utils/websrv/websrv.c,
websrv_utils.c):

- ``GET /oaisoftmodem/commands``: ``[{"name": "ci"}, {"name": "o1"}, ...]`` (the loaded modules);
  ``GET /oaisoftmodem/<module>/commands``: the module's commands, those with a parameter with a
  ``question``, then a ``confirm`` entry; ``GET /oaisoftmodem/info``, ``GET|POST
  /oaisoftmodem/<module>/variables``: small documents of the same shape;
- ``POST /oaisoftmodem/<module>/commands`` ``{"name": "<command>", "param": [{"name", "value",
  "type", "modifiable"}, ...]}``: HTTP 200 ``{"display": [lines]}`` with the lines the command
  printed (empty lines dropped, as OAI's strtok does), whatever the command's own status: a
  failure is text among the lines; a body that is not JSON (or not sent as application/json) is
  HTTP 400 ``Unproperly formatted request body``, no name 400 ``No command name in request body``,
  an unknown command 501 ``Unknown command in request body``, a `param` entry without all four
  keys, an empty list or more than two entries 500 (with that same text, as OAI's code does); an
  unknown module 404;
- the command receives ``"p0 p1"``, ``"p0 "`` or ``" "`` for no parameter (never nothing);
  `SimulatedGnb.stock_websrv` says whether its commands take that blank for an argument (stock:
  `o1 stats` and `ci get_single_rnti` then answer ``no parameter allowed``) or for none (the
  modified gNB uavloc's RTT mode assumes);
- a request body over 1024 bytes is refused (HTTP 413);
- one output buffer, behind one lock, for every request: commands run one at a time.

Faults (SimulatedGnb.inject / the scenario's ``[faults.gnb]``): ``delay`` (the answer comes late,
the buffer held meanwhile: a slow or busy server), ``malformed`` (the body is not the JSON
document), ``drop`` (the connection closes instead of the answer), ``refuse`` (a request's
connection closes before it runs), ``http_error`` (HTTP 500).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from typing import Protocol

from aiohttp import web

from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

PREFIX = "/oaisoftmodem"
#: OAI's web server refuses a longer request body [bytes]
MAX_BODY_BYTES = 1024
#: the output buffer OAI allocates per command (websrv_printf_start(response, 16384, ...)) [bytes]
OUTPUT_BUFFER_BYTES = 16384
_UNKNOWN = "Unknown command in request body"


def websrv_buffer(values: list[str]) -> str:
    """What OAI's web server hands a command: ``"%s %s"`` of the first two values ("" when absent)."""
    return f"{values[0] if values else ''} {values[1] if len(values) > 1 else ''}"


def display_lines(text: str) -> list[str]:
    """The command's output -> OAI's display lines (split on newlines, empty ones dropped)."""
    return [ln for ln in text[: OUTPUT_BUFFER_BYTES - 1].split("\n") if ln]


def _param_values(param: object) -> list[str] | None:
    """The values of a `param` list as OAI unpacks it (1 or 2 entries, each with string name, value
    and type and a boolean modifiable), or None when OAI would refuse it."""
    if not isinstance(param, list) or not 1 <= len(param) <= 2:
        return None
    out = []
    for p in param:
        if not isinstance(p, dict) or not all(isinstance(p.get(k), str) for k in ("name", "value", "type")):
            return None
        if not isinstance(p.get("modifiable"), bool):
            return None
        out.append(p["value"])
    return out


class RestBackend(Protocol):
    """What the web server needs from the simulated gNB (`sitl_scenarios.gnb.SimulatedGnb`)."""

    stock_websrv: bool
    crashed: str | None

    def modules(self) -> list[str]: ...

    def module_commands(self, module: str) -> list[tuple[str, str]] | None: ...

    def run_command(self, module: str, cmd: str, args: str) -> str | None: ...

    def crash_now(self) -> None: ...

    def take_fault(self, kind: str) -> bool: ...

    def take_delay(self) -> float: ...

    def malform_bytes(self, answer: str) -> bytes: ...


class GnbRestServer:
    """aiohttp server of one simulated gNB's REST API on host:port (port 0: ephemeral, read `.port`)."""

    def __init__(self, gnb: RestBackend, host: str, port: int) -> None:
        self.gnb = gnb
        self.host = host
        self.port = port
        self.requests = 0
        #: the JSON bodies of the command requests, in order (for tests)
        self.posted: list[tuple[str, dict | None]] = []
        self._buffer = asyncio.Lock()  # OAI's websrv_printf_buff.mutex
        self._runner: web.AppRunner | None = None
        self._server: asyncio.Server | None = None

    def _app(self) -> web.Application:
        app = web.Application(client_max_size=MAX_BODY_BYTES)
        app.router.add_get(f"{PREFIX}/commands", self._modules)
        app.router.add_get(f"{PREFIX}/info", self._info)
        app.router.add_get(f"{PREFIX}/{{module}}/commands", self._commands)
        app.router.add_post(f"{PREFIX}/{{module}}/commands", self._execute)
        app.router.add_route("*", f"{PREFIX}/{{module}}/variables", self._variables)
        return app

    async def __aenter__(self) -> GnbRestServer:
        self._runner = web.AppRunner(self._app(), access_log=None, handle_signals=False)
        await self._runner.setup()
        try:
            self._server = await asyncio.get_running_loop().create_server(self._runner.server, self.host, self.port)
        except OSError as exc:
            await self._runner.cleanup()
            raise SimulatorError(f"simulated gNB web server cannot listen on {self.host}:{self.port}: {exc}") from exc
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("simulated gNB web server on http://%s:%d%s", self.host, self.port, PREFIX)
        return self

    async def __aexit__(self, *exc_info) -> None:
        server, runner, self._server, self._runner = self._server, self._runner, None, None
        if server is not None:
            server.close()
        if runner is not None:
            await runner.shutdown()
            self.crash()
            await runner.cleanup()
        if server is not None:
            with contextlib.suppress(Exception):
                await server.wait_closed()

    def crash(self) -> None:
        """Stop listening and drop every connection (the gNB died)."""
        if self._server is not None:
            self._server.close()
        if self._runner is not None and self._runner.server is not None:
            for handler in list(self._runner.server.connections):
                handler.force_close()
                if handler.transport is not None:
                    handler.transport.close()

    # -- endpoints -----------------------------------------------------------------------------
    async def _modules(self, request: web.Request) -> web.Response:
        return web.json_response([{"name": m} for m in self.gnb.modules()])

    async def _info(self, request: web.Request) -> web.Response:
        return web.json_response({"display": ["simulated nr-softmodem (uavloc)", "version OAI 2025.w36 formats"]})

    async def _commands(self, request: web.Request) -> web.Response:
        module = request.match_info["module"]
        cmds = self.gnb.module_commands(module)
        if cmds is None:
            return web.Response(status=404, text="Request for an unknown module")
        out: list[dict] = []
        for name, question in cmds:
            entry: dict = {"name": name}
            if question:
                entry["question"] = [{"display": question, "pname": "P0", "type": "string"}]
            out.append(entry)
        out.append({"confirm": f"execute {module} command?"})
        return web.json_response(out)

    async def _variables(self, request: web.Request) -> web.Response:
        if self.gnb.module_commands(request.match_info["module"]) is None:
            return web.Response(status=404, text="Request for an unknown module")
        return web.json_response([])

    async def _execute(self, request: web.Request) -> web.StreamResponse:
        gnb = self.gnb
        self.requests += 1
        module = request.match_info["module"]
        if gnb.module_commands(module) is None:
            return web.Response(status=404, text="Request for an unknown module")
        if gnb.take_fault("refuse"):
            log.info("fault: closing a REST connection before its command")
            return self._abort(request)
        raw = await request.read()  # over MAX_BODY_BYTES: aiohttp answers 413
        try:
            body = json.loads(raw) if request.content_type == "application/json" else None
        except ValueError:
            body = None
        self.posted.append((module, body if isinstance(body, dict) else None))
        if not isinstance(body, dict):
            return web.Response(status=400, text="Unproperly formatted request body")
        name = body.get("name")
        if not isinstance(name, str):
            return web.Response(status=400, text="No command name in request body")
        if name not in {c for c, _ in gnb.module_commands(module) or []}:
            return web.Response(status=501, text=_UNKNOWN)
        values: list[str] = []
        if "param" in body:
            got = _param_values(body["param"])
            if got is None:
                return web.Response(status=500, text=_UNKNOWN)
            values = got
        buf = websrv_buffer(values)
        async with self._buffer:
            answer = gnb.run_command(module, name, buf if gnb.stock_websrv or buf.strip() else "")
            if gnb.crashed is not None:
                gnb.crash_now()
                return self._abort(request)
            if gnb.take_fault("drop"):
                log.info("fault: dropping the REST connection instead of answering %s %s", module, name)
                return self._abort(request)
            delay_s = gnb.take_delay()
            if delay_s > 0:
                await asyncio.sleep(delay_s)
            if gnb.take_fault("http_error"):
                return web.Response(status=500, text="Internal server error")
            doc = json.dumps({"display": display_lines(answer or "")})
            if gnb.take_fault("malformed"):
                log.info("fault: malformed REST answer to %s %s", module, name)
                return web.Response(status=200, body=gnb.malform_bytes(doc), content_type="application/json")
            return web.Response(status=200, text=doc, content_type="application/json")

    @staticmethod
    def _abort(request: web.Request) -> web.StreamResponse:
        if request.transport is not None:
            request.transport.close()
        return web.Response(status=500)  # never reaches the closed socket
