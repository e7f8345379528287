"""`uavloc view LOG [--port N] [--host H] [--tiles URL]`: the live view's page for a recorded mission,
with a time slider."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from mission.commands.argtypes import tcp_port
from mission.view.address import check_tiles_url
from mission.view.live import checked

log = logging.getLogger(__name__)

HELP = "show a recorded mission log in a browser, with a time slider"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", type=Path, metavar="LOG", help="mission log (uavloc-mission/1, JSON Lines)")
    p.add_argument("--port", type=tcp_port, default=0, help="TCP port (default 0: any free port, printed at start)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; any other requires the printed access token)")
    p.add_argument("--tiles", metavar="URL", type=checked(check_tiles_url),
                   help="background map tiles, e.g. http://tiles.local/{z}/{x}/{y}.png")


async def serve(log_path: Path, host: str, port: int, tiles_url: str | None, ready=None) -> None:
    """Serve the recorded mission until cancelled; `ready(server)` is called once listening."""
    import asyncio

    from mission.log import iter_log_objects, read_mission_log
    from mission.view.server import LogFeed, ViewServer

    read_mission_log(log_path)  # strict check first: a malformed log is an error with a line number
    with log_path.open(encoding="utf-8") as fh:
        records = [obj for _, obj, _ in iter_log_objects(fh, log_path) if obj is not None]
    async with ViewServer(LogFeed(records), host, port, tiles_url=tiles_url, title=log_path.name) as server:
        if ready is not None:
            ready(server)
        await asyncio.Event().wait()


def run(args: argparse.Namespace) -> int:
    import asyncio
    import contextlib

    def ready(server) -> None:
        print(f"uavloc: view of {args.log} at {server.url}  (Ctrl-C to stop)", file=sys.stderr, flush=True)

    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C is the normal way to stop a viewer
        asyncio.run(serve(args.log, args.host, args.port, args.tiles, ready))
    return 0
