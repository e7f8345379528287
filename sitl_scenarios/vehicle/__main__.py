"""`python -m sitl_scenarios.vehicle --scenario FILE [--speedup X] [--target udp HOST:PORT]`."""

import sys

from sitl_scenarios.vehicle.cli import main

sys.exit(main())
