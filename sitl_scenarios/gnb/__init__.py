"""The simulated OAI gNB: telnet (`server`), OAI's web server (`rest`), the random-access log
lines (`ra`) and injected faults (`faults`). ``python -m sitl_scenarios.gnb`` serves it."""

from sitl_scenarios.gnb.faults import GnbFaults
from sitl_scenarios.gnb.server import SimulatedGnb
from sitl_scenarios.position import MavlinkPositionSource, static_position

__all__ = ["GnbFaults", "MavlinkPositionSource", "SimulatedGnb", "static_position"]
