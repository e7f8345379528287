"""argparse types shared by the subcommands: a bad value is a usage error (exit 2, argparse's
message naming the option) before anything starts."""

from __future__ import annotations

import argparse

from mission.view.live import checked


def _gnb_address(text: str) -> None:
    from mission.gnb_config import parse_host_port

    parse_host_port(text)


#: HOST:PORT (or HOST) of a gNB's telnet server, kept as given (the command parses it)
gnb_address = checked(_gnb_address)


def tcp_port(text: str) -> int:
    """A TCP port 0..65535 (0: any free port)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"port must be an integer 0..65535, got {text!r}") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"port must be 0..65535, got {v}")
    return v
