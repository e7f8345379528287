"""`uavloc` subcommands of the simulation package, found by mission/cli.py through the
`uavloc.commands` entry-point group (pyproject.toml), so mission never imports sitl_scenarios."""
