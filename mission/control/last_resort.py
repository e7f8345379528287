"""The mission's end when its event loop does not answer (mission.runtime's signal watchdog).

An ending signal (Ctrl-C, SIGTERM, SIGHUP) normally cancels the mission in its event loop, and the
controller's safe end sends RTL and writes the log's end record. A loop that does not run that
cancellation within seconds (blocked, or too loaded to keep up) cannot do it: :func:`end_from_outside`
does it from the watchdog's thread, without the loop:

- RTL to every vehicle that may be in the air and has not been sent home yet, through the vehicle
  library's blocking call (:meth:`mission.vehicle.mavsdk_vehicle.MavsdkVehicle.return_to_launch_blocking`),
  all vehicles at once, each bounded by `timeout_s` wall seconds;
- the mission log's `interrupted`, `rtl` (or `rtl_failed`) and `end` records, when the log is
  open and has no end record yet. The log is written one whole line per write (mission.log), so
  these lines are whole even beside a record the stalled loop was writing.

Nothing here waits for the event loop or takes a lock the loop's thread may hold.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

from mission.control.config import STATUS_INTERRUPTED

if TYPE_CHECKING:
    from mission.control.crew import VehicleCrew
    from mission.control.journal import MissionJournal

log = logging.getLogger(__name__)


def may_be_airborne(crew: VehicleCrew) -> bool:
    """The vehicle was connected and is not known to be disarmed on the ground."""
    st = crew.vehicle.state
    return crew.connected and not (st.armed is False and st.landed_state in ("ON_GROUND", "UNKNOWN"))


def _rtl(crew: VehicleCrew, outcome: dict[int, str | None]) -> None:
    try:
        crew.vehicle.return_to_launch_blocking()
    except Exception as exc:  # any failure is reported in the log, never raised in a bare thread
        outcome[id(crew)] = f"{type(exc).__name__}: {exc}"
    else:
        outcome[id(crew)] = None


def end_from_outside(crews: Sequence[VehicleCrew], journal: MissionJournal, why: str, timeout_s: float) -> None:
    """RTL to every vehicle that may be airborne and the log's end records (module docstring).
    Called from a thread other than the event loop's; returns within about `timeout_s` wall s."""
    journal.event(f"mission interrupted: {why}; RTL from the watchdog", kind="interrupted")
    todo = [c for c in crews if may_be_airborne(c) and not c.rtl_sent and not c.autopilot_landing]
    outcome: dict[int, str | None] = {}
    threads = [threading.Thread(target=_rtl, args=(c, outcome), name=f"uavloc-rtl-{c.id}", daemon=True)
               for c in todo]
    for th in threads:
        th.start()
    deadline = time.monotonic() + timeout_s
    for th in threads:  # in parallel: one bound for all
        th.join(max(0.0, deadline - time.monotonic()))
    for c in todo:
        error = outcome.get(id(c), f"no answer within the watchdog's {timeout_s:g} s")
        if error is None:
            c.rtl_sent = True
            c.event(f"RTL: {why} (from the watchdog)", kind="rtl", attempts=1)
        else:
            log.error("RTL%s could not be sent: %s; the vehicle is left to its own failsafe", c._of(), error)
            c.event(f"RTL could not be sent ({error}): the vehicle is left to its own failsafe", kind="rtl_failed")
    if journal.is_open and not journal.ended:
        journal.event(f"mission end: {STATUS_INTERRUPTED} ({why})", kind="end", status=STATUS_INTERRUPTED,
                      reason=why)
