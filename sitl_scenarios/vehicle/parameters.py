"""The parameter protocol of the built-in vehicle: PARAM_REQUEST_LIST / _READ and PARAM_SET
answered with PARAM_VALUE, INT32 values byte-wise encoded as PX4 does."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from sitl_scenarios.vehicle.autopilot import Autopilot
from sitl_scenarios.vehicle.params import decode_param_value, encode_param_value

log = logging.getLogger(__name__)


def param_name(raw: Any) -> str:
    """A PARAM_*.param_id as text (bytes or str, NUL-padded to 16 characters)."""
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", errors="replace")
    return str(raw).split("\x00", 1)[0]


class ParamProtocol:
    """Serves the autopilot's parameter table; send puts a message on the link."""

    def __init__(self, ap: Autopilot, send: Callable[[Any], None]) -> None:
        self.ap = ap
        self._send = send

    def handlers(self) -> dict[str, Callable[[Any], None]]:
        """{MAVLink message type: its handler}."""
        return {
            "PARAM_REQUEST_LIST": self.on_param_request_list,
            "PARAM_REQUEST_READ": self.on_param_request_read,
            "PARAM_SET": self.on_param_set,
        }

    def _send_param(self, index: int) -> None:
        spec, value = self.ap.params.entry(index)
        self._send(mavlink.MAVLink_param_value_message(
            spec.name.encode(), encode_param_value(value, spec.type, self.ap.PARAM_BYTEWISE), spec.type,
            len(self.ap.params), index))

    def on_param_request_list(self, msg: Any) -> None:
        for k in range(len(self.ap.params)):
            self._send_param(k)

    def on_param_request_read(self, msg: Any) -> None:
        name = param_name(msg.param_id)
        k = self.ap.params.index_of(name) if msg.param_index < 0 else msg.param_index
        if k is None or not 0 <= k < len(self.ap.params):
            log.debug("vehicle: unknown parameter %r / index %d requested", name, msg.param_index)
            return  # PX4 does not answer for an unknown parameter
        self._send_param(k)

    def on_param_set(self, msg: Any) -> None:
        name = param_name(msg.param_id)
        k = self.ap.params.index_of(name)
        if k is None:
            log.debug("vehicle: PARAM_SET of unknown parameter %r", name)
            return
        spec, _ = self.ap.params.entry(k)
        value = decode_param_value(msg.param_value, spec.type, self.ap.PARAM_BYTEWISE)
        if math.isfinite(value):
            self.ap.params.set(name, value)
            log.info("vehicle: parameter %s = %g", name, value)
        self._send_param(k)
