"""`uavloc gnb probe --gnb ADDRESS [--mode rtt|trace|stock|auto] [--t-port P] [--gnb-log FILE] [--count N]
[--wait S] [--json]`.

The preflight check an operator runs before take-off: discover the gNB's UEs, take N
measurements of each, print ranges, TA, SRS peak and timing, or say exactly what is wrong; and
which ways to measure the gNB serves (its RTT command, a T tracer with SRS events, a log file)
and which is best. In trace mode it waits up to --wait seconds, its T client connected, for UEs to
attach and give their round trips. Exit status 0 when every UE answered, 1 otherwise. The logic is
`mission.gnb.probe.probe_address`.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from mission.commands.argtypes import gnb_address, in_range

log = logging.getLogger(__name__)

HELP = "check a gNB before flight: discover its UEs and measure each (gnb probe)"


def _rnti(text: str) -> int:
    try:
        v = int(text, 16)
    except ValueError:
        raise argparse.ArgumentTypeError(f"RNTI must be hex (e.g. 4601), got {text!r}") from None
    if not 0 < v <= 0xFFFF:
        raise argparse.ArgumentTypeError(f"RNTI must be 1..ffff, got {text!r}")
    return v


#: measurements per UE
_count = in_range(int, 1, 1000, closed=True, what="an integer count")
#: seconds of a wait or timeout
_seconds = in_range(float, 0.0, 3600.0, closed=False, what="seconds")


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="gnb_command", metavar="SUBCOMMAND", required=True)
    q = sub.add_parser("probe", help="discover the UEs and measure each", description=__doc__.split("\n\n")[1])
    q.add_argument("--gnb", required=True, metavar="ADDRESS", type=gnb_address,
                   help="the gNB: HOST:PORT or telnet://HOST:PORT (telnet server, default port 9090), "
                        "http://HOST:PORT (OAI's web server, default port 8090)")
    q.add_argument("--mode", choices=("rtt", "trace", "stock", "auto"), default="rtt",
                   help="rtt: the RTT command set of a modified gNB; trace: a stock gNB's T tracer (RAR TA, TA "
                        "commands, SRS peak; nr-softmodem --T_stdout 2 --T_nowait); stock: Msg2 lines of "
                        "--gnb-log; auto: the best the gNB serves")
    q.add_argument("--t-port", type=in_range(int, 1, 65535, closed=True, what="a port"), default=2021,
                   metavar="PORT", help="trace mode: the gNB's T tracer port (--T_port; default 2021)")
    q.add_argument("--stock", choices=("active", "passive"), default="passive",
                   help="stock mode: passive only reads the random accesses that happen anyway (default); "
                        "active triggers `ci force_reestab` and waits for the UE's random access (it killed "
                        "OAI 2025.w36 with SIGFPE when a discovery followed a few seconds later: README)")
    q.add_argument("--gnb-log", type=Path, metavar="FILE", help="the gNB's log file (stock mode)")
    q.add_argument("--count", type=_count, default=3, metavar="N", help="measurements per UE (default 3)")
    q.add_argument("--rnti", type=_rnti, action="append", metavar="HEX",
                   help="a configured UE that must be present and answer (repeatable; default: every UE found)")
    q.add_argument("--wait", type=_seconds, default=15.0, metavar="S",
                   help="trace: how long to wait, with the T client connected, for UEs to attach and give their "
                        "N round trips (a line on stderr says what it waits for; it ends as soon as every UE has "
                        "them); stock active: how long to wait for the UE's random access (default 15)")
    q.add_argument("--timeout", type=_seconds, default=2.0, metavar="S", help="per request (default 2)")
    q.add_argument("--rtt-module", default="rtt", help="RTT command set: module name (default rtt)")
    q.add_argument("--rtt-command", default="pdcch_order", help="RTT command set: command (default pdcch_order)")
    q.add_argument("--mu", type=int, default=1, help="numerology of the UL BWP (stock TA unit; default 1)")
    q.add_argument("--json", action="store_true", help="print one JSON document on stdout")


def run(args: argparse.Namespace) -> int:
    import asyncio

    from mission.gnb import GnbConfig, parse_gnb_address
    from mission.gnb.probe import probe_address
    from uavloc.errors import GnbError

    address = parse_gnb_address(args.gnb)
    if args.mode == "stock" and args.gnb_log is None:
        raise GnbError("--mode stock reads the random accesses from the gNB log: give --gnb-log FILE")
    if args.gnb_log is not None and not args.gnb_log.is_file():
        raise GnbError(f"--gnb-log {args.gnb_log}: no such file")
    cfg = GnbConfig(host=address.host, port=address.port, transport=address.transport, mode=args.mode,
                    stock_mode=args.stock, t_port=args.t_port,
                    log_path=args.gnb_log if args.mode in ("stock", "auto") else None, rtt_module=args.rtt_module,
                    rtt_command=args.rtt_command, request_timeout_s=args.timeout, connect_timeout_s=args.timeout,
                    retries=1, msg2_timeout_s=args.wait, mu=args.mu,
                    log_history=args.mode == "stock" and args.stock == "passive")
    result = asyncio.run(probe_address(cfg, rntis=args.rnti, count=args.count, wait_s=args.wait,
                                       progress=lambda line: print(line, file=sys.stderr, flush=True)))
    if args.json:
        json.dump(result.to_dict(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print("\n".join(result.lines()))
    return 0 if result.ok else 1
