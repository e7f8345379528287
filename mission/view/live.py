"""`--view [HOST:]PORT` for `uavloc sim` and `uavloc fly`: the glue between a command, the mission
log writer and the view server. Importing this module is cheap (aiohttp loads only with --view)."""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import AsyncIterator

from mission.log import MissionLogWriter
from mission.view.address import check_tiles_url, parse_view_address
from uavloc.errors import MissionError


def checked(parse):
    """An argparse type from a parser raising MissionError (a usage error, before anything starts)."""
    def convert(text: str):
        try:
            parse(text)
        except MissionError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return text

    return convert


def add_view_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--view", metavar="[HOST:]PORT", type=checked(parse_view_address),
                   help="serve a live view of the mission in a browser (default host 127.0.0.1; any other "
                        "address requires the access token printed in the URL)")
    p.add_argument("--view-tiles", metavar="URL", type=checked(check_tiles_url),
                   help="background map tiles for the view, e.g. http://tiles.local/{z}/{x}/{y}.png "
                        "(default: a metric grid)")


@contextlib.asynccontextmanager
async def live_view(args: argparse.Namespace, writer: MissionLogWriter, title: str = "uavloc") -> AsyncIterator:
    """Serve the live view of the records `writer` writes while the block runs (nothing without
    `--view`). The URL goes to stderr at start."""
    if getattr(args, "view", None) is None:
        yield None
        return
    from mission.view.server import LiveFeed, ViewServer

    host, port = parse_view_address(args.view)
    feed = LiveFeed()
    writer.subscribe(feed.on_record)
    async with ViewServer(feed, host, port, tiles_url=args.view_tiles, title=title) as server:
        print(f"uavloc: live view at {server.url}", file=sys.stderr, flush=True)
        yield server
