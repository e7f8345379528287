"""Fault injection of the simulated gNB: the scenario's ``[faults.gnb]`` table (re-exported by
`sitl_scenarios.gnb`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

from mission import schema
from mission.schema import bounded
from uavloc.errors import ScenarioError

#: the longest extra delay of an answer [s] and the latest simulation time of a fault [s]
MAX_DELAY_S = 600.0
MAX_FAULT_TIME_S = 1e6


@dataclass
class GnbFaults:
    """Fault injection of the simulated gNB (the scenario's ``[faults.gnb]`` table).

    delay_s: extra delay of an answer [s], applied with probability delay_rate;
    malformed_rate: probability an answer is replaced by a malformed one (truncated, binary, bad
    numbers), still followed by the prompt; drop_rate: probability the connection is closed
    instead of answering; refuse_rate: probability a new connection is closed at once;
    busy_mode: how a second concurrent client is treated, "silent" (accepted, unanswered until the
    first one leaves, as OAI does) or "close"; rtt_module_lost_at_s: from this simulation time
    [s] on the RTT telnet module is gone (its command answers `... is not a softmodem command`, as
    a gNB restarted without it would); absent: never.
    """

    delay_s: float = bounded(0.0, 0.0, MAX_DELAY_S)
    delay_rate: float = bounded(0.0, 0.0, 1.0, what="is a probability in [0, 1]")
    malformed_rate: float = bounded(0.0, 0.0, 1.0, what="is a probability in [0, 1]")
    drop_rate: float = bounded(0.0, 0.0, 1.0, what="is a probability in [0, 1]")
    refuse_rate: float = bounded(0.0, 0.0, 1.0, what="is a probability in [0, 1]")
    busy_mode: Literal["silent", "close"] = "silent"
    rtt_module_lost_at_s: float | None = bounded(None, 0.0, MAX_FAULT_TIME_S)

    @classmethod
    def from_table(cls, table: dict[str, Any], where: str = "faults.gnb") -> GnbFaults:
        """Strictly (mission.schema): unknown keys, wrong types and out-of-range numbers are a
        ScenarioError naming `where` and the key."""
        return schema.build(cls, table, where, error=ScenarioError)

    @classmethod
    def from_scenario(cls, scenario: Any) -> GnbFaults:
        """A copy (the simulated gNB may change its own) of a scenario's `[faults.gnb]`."""
        return dataclasses.replace(scenario.faults.gnb)
