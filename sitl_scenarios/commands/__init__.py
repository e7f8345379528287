"""`uavloc` subcommands that live with the simulators (each: HELP, add_arguments, run), found by
mission/cli.py through the `uavloc.commands` entry-point group (pyproject.toml), so mission never
imports sitl_scenarios."""
