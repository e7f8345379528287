"""One module per `uavloc` subcommand: HELP, add_arguments(parser), run(args) -> int."""
