"""`uavloc` subcommands that live with the simulators (each: HELP, add_arguments, run)."""
