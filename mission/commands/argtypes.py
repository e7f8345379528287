"""argparse types shared by the subcommands: a bad value is a usage error (exit 2, argparse's
message naming the option) before anything starts."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from mission.view.live import checked


def _gnb_address(text: str) -> None:
    from mission.gnb.transport import parse_gnb_address

    parse_gnb_address(text)


#: a gNB's address (HOST[:PORT], telnet://HOST[:PORT], http://HOST[:PORT]), kept as given: the
#: command parses it with the transport its mission file names for an address without a scheme
gnb_address = checked(_gnb_address)


def in_range(convert: Callable[[str], float], lo: float, hi: float, *, closed: bool, what: str):
    """An argparse type: `convert(text)` within [lo, hi] (closed) or (lo, hi) (open); `what` names
    the expected value in the message."""
    brackets = ("[", "]") if closed else ("(", ")")
    span = f"{brackets[0]}{lo:g}, {hi:g}{brackets[1]}"

    def parse(text: str):
        try:
            v = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if not (lo <= v <= hi if closed else lo < v < hi):
            raise argparse.ArgumentTypeError(f"must be in {span}, got {text}")
        return v

    return parse


#: a TCP port (0: any free port)
tcp_port = in_range(int, 0, 65535, closed=True, what="a port number 0..65535")
