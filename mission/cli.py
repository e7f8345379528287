"""`uavloc` command line: a thin dispatcher (docs/design.md §11).

Each subcommand is a module with `HELP`, `add_arguments(parser)` and `run(args) -> int`; heavy
imports happen inside `run`. The mission's own live in `mission/commands/<name>.py`; other
packages add theirs through the `uavloc.commands` entry-point group (pyproject.toml: `sim` is
`sitl_scenarios.commands.sim`), read at run time, so mission never imports the simulators. This is the one place where a
:class:`UavlocError` becomes a message on stderr and an exit code, and the one place that
configures logging.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import shlex
import sys

from uavloc import __version__
from uavloc.errors import UavlocError

# The estimator's matrices are small (3×3 blocks, K×K user blocks): a multithreaded BLAS only adds
# overhead and fights the event loop for the cores. Must be set before numpy is first imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

log = logging.getLogger("uavloc")

#: the mission's own subcommands -> module implementing each
COMMANDS = {
    "fly": "mission.commands.fly",
    "replay": "mission.commands.replay",
    "calibrate": "mission.commands.calibrate",
    "import": "mission.commands.importer",
    "gnb": "mission.commands.gnb",
    "view": "mission.commands.view",
}

#: the entry-point group other packages add subcommands through
ENTRY_POINT_GROUP = "uavloc.commands"

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uavloc",
        description="UAV-aided 5G NR user localization: fly, simulate and replay RTT ranging missions.",
    )
    parser.add_argument("--version", action="version", version=f"uavloc {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors on stderr")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, modname in all_commands().items():
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            if exc.name != modname:
                raise
            continue  # command not built yet
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def all_commands() -> dict[str, str]:
    """{subcommand: module}: the entry points of the `uavloc.commands` group first (in name order),
    then the mission's own. An installed uavloc without the group (an old editable install)
    prints how to fix it."""
    from importlib.metadata import entry_points

    found = {ep.name: ep.value for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name)}
    if not found:
        log.debug("no %r entry points: reinstall uavloc (pip install -e .) for `uavloc sim`", ENTRY_POINT_GROUP)
    return {**found, **COMMANDS}


class _StderrHandler(logging.StreamHandler):
    """A handler writing to whatever `sys.stderr` is when a record comes, not to the stream it was
    when main() ran: main() may run in a process (a test, a notebook) that swaps and closes stderr."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:
        pass


def configure_logging(verbose: int, quiet: bool) -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose >= 2 else logging.INFO)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s" if verbose else "%(message)s"))
    root = logging.getLogger()
    # replace only the handler a previous call installed (main() may run several times in one process)
    for old in [h for h in root.handlers if getattr(h, "_uavloc", False)]:
        root.removeHandler(old)
    handler._uavloc = True  # type: ignore[attr-defined]
    root.addHandler(handler)
    root.setLevel(level)
    if verbose < 2:
        for noisy in ("matplotlib", "PIL", "asyncio"):
            logging.getLogger(noisy).setLevel(logging.WARNING)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # the command as typed, for the mission log's header (the report names it)
    args.command_line = shlex.join(["uavloc", *(sys.argv[1:] if argv is None else argv)])
    configure_logging(args.verbose, args.quiet)
    try:
        return int(args._run(args) or 0)
    except UavlocError as exc:
        log.error("uavloc %s: %s", args.command, exc)
        return EXIT_ERROR
    except KeyboardInterrupt:
        log.error("uavloc %s: interrupted", args.command)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # the reader of stdout went away (`uavloc replay LOG --json | head`): nothing more can be
        # said there, and the interpreter's own flush at exit must not fail again
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        log.error("uavloc %s: its output was closed before it ended", args.command)
        return EXIT_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
