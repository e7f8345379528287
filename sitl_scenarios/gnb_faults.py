"""Fault injection of the simulated gNB: the scenario's ``[faults.gnb]`` table (re-exported by
`sitl_scenarios.gnb`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from uavloc.errors import ScenarioError


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

    delay_s: float = 0.0
    delay_rate: float = 0.0
    malformed_rate: float = 0.0
    drop_rate: float = 0.0
    refuse_rate: float = 0.0
    busy_mode: str = "silent"
    rtt_module_lost_at_s: float | None = None

    @classmethod
    def from_table(cls, table: dict[str, Any], where: str = "faults.gnb") -> GnbFaults:
        """Strict conversion: unknown keys, wrong types and out-of-range rates are ScenarioError."""
        if not isinstance(table, dict):
            raise ScenarioError(f"{where}: expected a table, got {table!r}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(table) - set(fields))
        if unknown:
            raise ScenarioError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(fields)}")
        kwargs: dict[str, Any] = {}
        for k, v in table.items():
            if k == "busy_mode":
                if v not in ("close", "silent"):
                    raise ScenarioError(f"{where}.busy_mode must be 'close' or 'silent', got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ScenarioError(f"{where}.{k} must be a non-negative number, got {v!r}")
            elif k.endswith("_rate") and v > 1:
                raise ScenarioError(f"{where}.{k} is a probability, got {v!r}")
            kwargs[k] = v if k == "busy_mode" else float(v)
        return cls(**kwargs)

    @classmethod
    def from_scenario(cls, scenario: Any) -> GnbFaults:
        """The `[faults.gnb]` table of a sitl_scenarios.scenario.Scenario (which checked it at load)."""
        return cls.from_table(scenario.faults.get("gnb", {}))
