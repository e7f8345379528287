"""A TCP relay between uavloc's T client and an OAI gNB's T server that a test can cut
(`uavloc sim --oai`'s fault injection, docs/oai-in-the-loop.md).

:class:`TRelay` listens on a free loopback port; each client connection gets its own connection to
the gNB's T port and bytes are copied both ways. :meth:`TRelay.cut` closes every open pair (the T
client sees its connection drop; OAI's T server — the forked `local_tracer` — sees its client
leave, turns every trace off and listens again: the gNB keeps running) and, for `hold_s` seconds,
closes any new client at once (the T client's reconnects fail and back off).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

log = logging.getLogger(__name__)


class TRelay:
    """See the module docstring. target_port: the gNB's T port (loopback)."""

    def __init__(self, target_port: int, host: str = "127.0.0.1") -> None:
        self.host, self.target_port = host, int(target_port)
        self.port = 0
        self.cuts = 0
        #: pairs relayed so far (one per client connection that reached the gNB)
        self.connections = 0
        self._server: asyncio.AbstractServer | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._closed_until = 0.0

    async def __aenter__(self) -> TRelay:
        self._server = await asyncio.start_server(self._client, self.host, 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._server is not None:
            self._server.close()
        self._close_all()
        if self._server is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None

    def cut(self, hold_s: float = 0.0) -> None:
        """Close every relayed connection; refuse new ones for hold_s wall seconds."""
        self.cuts += 1
        self._closed_until = time.monotonic() + max(0.0, hold_s)
        n = len(self._writers) // 2
        self._close_all()
        log.warning("T relay :%d cut %d connection(s) to the gNB's T port %d (new ones refused for %.1f s)",
                    self.port, n, self.target_port, hold_s)

    def _close_all(self) -> None:
        for w in list(self._writers):
            w.close()
        self._writers.clear()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if time.monotonic() < self._closed_until:
            writer.close()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection(self.host, self.target_port)
        except OSError as exc:
            log.warning("T relay: the gNB's T port %d: %s", self.target_port, exc)
            writer.close()
            return
        self.connections += 1
        self._writers.update((writer, up_writer))
        await asyncio.gather(self._pipe(reader, up_writer), self._pipe(up_reader, writer))

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(1 << 16):
                writer.write(data)
                await writer.drain()
        except (OSError, ConnectionError):
            pass
        finally:
            self._writers.discard(writer)
            writer.close()


__all__ = ["TRelay"]
