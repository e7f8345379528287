"""`--view [HOST:]PORT` for `uavloc sim` and `uavloc fly`: the glue between a command, the mission
log writer and the view server. Importing this module is cheap (aiohttp loads only with --view)."""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING

from mission.log import MissionLogWriter
from mission.runtime import BoundedRun, signal_label
from mission.view.address import check_tiles_url, parse_view_address
from uavloc.errors import MissionError

if TYPE_CHECKING:
    from mission.view.server import LiveFeed, ViewServer

log = logging.getLogger(__name__)


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


class LiveView:
    """The live view of one mission (`--view`), or nothing without `--view` (every method is then
    a no-op): :meth:`follow` the mission log writer, :meth:`mission_over` once the mission has
    ended, then :meth:`keep_serving` until an ending signal (issue 39)."""

    def __init__(self, server: ViewServer | None = None, feed: LiveFeed | None = None):
        self.server = server
        self.feed = feed

    @property
    def url(self) -> str | None:
        return None if self.server is None else self.server.url

    def follow(self, writer: MissionLogWriter) -> None:
        """Show the records `writer` writes from now on."""
        if self.feed is not None:
            writer.subscribe(self.feed.on_record)

    def mission_over(self) -> None:
        """The mission has ended (its last record is written): pages get the final frame, marked ended."""
        if self.feed is not None:
            self.feed.end()

    async def keep_serving(self, runner: BoundedRun, exit_code: int) -> None:
        """Serve the finished mission until SIGINT, SIGTERM or SIGHUP (not at all without `--view`).
        exit_code: the mission's own, the process's exit code whatever ends the wait."""
        if self.server is None:
            return
        self.mission_over()
        print(f"uavloc: the mission is over; the live view stays at {self.server.url} until Ctrl-C",
              file=sys.stderr, flush=True)
        signum = await runner.wait_for_ending_signal(exit_code)
        log.info("%s: live view closed (exit code %d, the mission's)", signal_label(signum), exit_code)


@contextlib.asynccontextmanager
async def live_view(args: argparse.Namespace, title: str = "uavloc") -> AsyncIterator[LiveView]:
    """Serve the live view while the block runs (a :class:`LiveView` doing nothing without
    `--view`). The URL goes to stderr at start; the block attaches the mission log writer with
    :meth:`LiveView.follow`."""
    if getattr(args, "view", None) is None:
        yield LiveView()
        return
    from mission.view.server import LiveFeed, ViewServer

    host, port = parse_view_address(args.view)
    feed = LiveFeed()
    async with ViewServer(feed, host, port, tiles_url=args.view_tiles, title=title) as server:
        print(f"uavloc: live view at {server.url}", file=sys.stderr, flush=True)
        yield LiveView(server, feed)
