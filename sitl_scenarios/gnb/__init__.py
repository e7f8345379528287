"""The simulated OAI gNB: telnet (`server`), OAI's web server (`rest`), its T tracer (`ttrace`),
the random-access log lines (`ra`), injected faults (`faults`) and a fleet's gNBs sharing one cell
attachment (`cells`). ``python -m sitl_scenarios.gnb``
serves it.

The names below are loaded on first use: `sitl_scenarios.scenario` imports `faults` while the
server module imports the scenario.
"""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {"GnbFaults": "sitl_scenarios.gnb.faults", "SimulatedGnb": "sitl_scenarios.gnb.server",
          "GnbCell": "sitl_scenarios.gnb.cells", "SharedCells": "sitl_scenarios.gnb.cells",
          "MavlinkPositionSource": "sitl_scenarios.position", "static_position": "sitl_scenarios.position"}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_WHERE[name]), name)
