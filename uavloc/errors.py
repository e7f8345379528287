"""The one exception hierarchy of the project.

Every error the project raises on purpose derives from :class:`UavlocError`, with a subclass per
package (and a few finer ones where a caller needs to tell them apart). Only the CLI turns them into
messages and exit codes. Messages say what was wrong and with which value.
"""

from __future__ import annotations


class UavlocError(Exception):
    """Base of every error uavloc raises on purpose."""


# --- estimator/ -------------------------------------------------------------------------------
class EstimatorError(UavlocError):
    """Bad input to, or failure of, the estimator."""


class RangingError(EstimatorError):
    """A gNB number (TA, SRS peak, sampling rate, numerology) that cannot be turned into a range."""


# --- planner/ ---------------------------------------------------------------------------------
class PlannerError(UavlocError):
    """The planner got bad input or could not produce a feasible waypoint."""


# --- mission/ ---------------------------------------------------------------------------------
class MissionError(UavlocError):
    """The mission controller or one of its adapters failed."""


class MissionConfigError(MissionError):
    """A mission file (`uavloc fly --mission`) that does not follow the schema; names file, key, value."""


class MissionLogError(MissionError):
    """A mission log that does not follow `uavloc-mission/1`."""


class GnbError(MissionError):
    """Talking to the gNB failed."""


class GnbProtocolError(GnbError):
    """The gNB answered something that does not parse; carries the offending text."""


class GnbTimeoutError(GnbError):
    """The gNB did not answer in time."""


class GnbBusyError(GnbError):
    """The gNB's telnet server serves another client (OAI serves one at a time)."""


class GnbUnknownCommandError(GnbProtocolError):
    """The gNB answered `... is not a softmodem command` (telnet module not loaded or misnamed)."""


class GnbTracerError(GnbError):
    """The gNB's T tracer (its T port, not its telnet server) cannot be reached or read."""


class GnbNoModeError(GnbError):
    """Mode "auto": the gNB answered, but serves no way to measure ranges (each way tried said why)."""


class GnbPreflightError(GnbError):
    """Before take-off, a configured user is not among the gNB's UEs or did not answer a measurement."""


class GnbNoMeasurementError(GnbError):
    """The gNB answered, but without a measurement (an `error ...` line, UE unknown or out of coverage)."""


class GnbNoRandomAccessError(GnbNoMeasurementError):
    """Stock OAI modes: no random access proven to be the UE's was seen in the gNB log in time."""


class VehicleError(MissionError):
    """The vehicle refused a command, timed out or was lost."""


class SafetyError(MissionError):
    """A command the safety gate refused."""


class ImportDataError(MissionError):
    """Input for `uavloc import` (tlog, gNB log) that cannot be used."""


# --- sitl_scenarios/ --------------------------------------------------------------------------
class ScenarioError(UavlocError):
    """A scenario file that does not follow the schema (unknown key, wrong type, bad value)."""


class SimulatorError(UavlocError):
    """The built-in vehicle or gNB simulator failed."""


class CampaignError(UavlocError):
    """A campaign spec that does not follow the schema (unknown key, bad value), or results that cannot be used."""
