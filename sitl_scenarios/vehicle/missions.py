"""The mission protocol of the built-in vehicle (MAVLink mission microservice, as PX4 serves it):
upload (MISSION_COUNT -> MISSION_REQUEST_INT ... -> MISSION_ACK, with re-requests on silence),
download, clear and set-current, for the mission, fence and rally plans."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from sitl_scenarios.vehicle.autopilot import Autopilot
from sitl_scenarios.vehicle.mav import (
    FRAME_GLOBAL,
    FRAME_GLOBAL_RELATIVE_ALT,
    FRAME_GLOBAL_TERRAIN_ALT,
    FRAME_MISSION,
    GLOBAL_FRAMES,
    MISSION_TYPE_MISSION,
)
from sitl_scenarios.vehicle.navigator import MissionItem, mission_command_supported

log = logging.getLogger(__name__)

#: the longest plan accepted (items)
MAX_ITEMS = 1000
#: an upload re-requests the item it waits for after this silence [wall s], at most RETRIES times
RETRY_WALL_S = 0.25
RETRIES = 8
#: MISSION_ITEM frames whose x, y are float degrees (MISSION_ITEM_INT carries degE7)
_FLOAT_DEG_FRAMES = (FRAME_GLOBAL, FRAME_GLOBAL_RELATIVE_ALT, FRAME_GLOBAL_TERRAIN_ALT)
#: frames a mission item may have (global ones, and MAV_FRAME_MISSION for items without a position)
_MISSION_FRAMES = GLOBAL_FRAMES | {FRAME_MISSION}


@dataclass
class _Upload:
    mission_type: int
    count: int
    items: list[MissionItem]
    sysid: int
    compid: int
    last_wall_s: float
    retries: int = 0



class MissionProtocol:
    """Uploads and downloads the autopilot's plans. send puts a message on the link; send_stream
    sends a stream message now (MISSION_CURRENT); wall_s: the wall clock of the last tick."""

    def __init__(
        self,
        ap: Autopilot,
        send: Callable[[Any], None],
        send_stream: Callable[[int], None],
        wall_s: Callable[[], float],
    ) -> None:
        self.ap = ap
        self._send = send
        self._send_stream = send_stream
        self._wall_s = wall_s
        self._upload: _Upload | None = None

    def handlers(self) -> dict[str, Callable[[Any], None]]:
        """{MAVLink message type: its handler}."""
        return {
            "MISSION_COUNT": self.on_mission_count,
            "MISSION_ITEM_INT": self.on_mission_item_int,
            "MISSION_ITEM": self.on_mission_item,
            "MISSION_REQUEST_LIST": self.on_mission_request_list,
            "MISSION_REQUEST_INT": self.on_mission_request_int,
            "MISSION_REQUEST": self.on_mission_request,
            "MISSION_ACK": self.on_mission_ack,
            "MISSION_CLEAR_ALL": self.on_mission_clear_all,
            "MISSION_SET_CURRENT": self.on_mission_set_current,
        }

    def _ack(self, msg: Any, mission_type: int, result: int) -> None:
        self._send(mavlink.MAVLink_mission_ack_message(
            msg.get_srcSystem(), msg.get_srcComponent(), result, mission_type))

    def on_mission_count(self, msg: Any) -> None:
        mtype = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        if msg.count == 0:
            self.ap.set_mission(mtype, [])
            self._upload = None
            self._ack(msg, mtype, mavlink.MAV_MISSION_ACCEPTED)
            return
        if msg.count > MAX_ITEMS:
            self._ack(msg, mtype, mavlink.MAV_MISSION_NO_SPACE)
            return
        self._upload = _Upload(mtype, msg.count, [], msg.get_srcSystem(), msg.get_srcComponent(),
                               self._wall_s())
        self._request_next()

    def _request_next(self) -> None:
        up = self._upload
        assert up is not None
        self._send(mavlink.MAVLink_mission_request_int_message(
            up.sysid, up.compid, len(up.items), up.mission_type))

    def upload_timeouts(self, now: float) -> None:
        up = self._upload
        if up is None or now - up.last_wall_s < RETRY_WALL_S:
            return
        up.retries += 1
        up.last_wall_s = now
        if up.retries > RETRIES:
            log.info("vehicle: mission upload timed out at item %d of %d", len(up.items), up.count)
            self._upload = None
            return
        self._request_next()

    def on_mission_item_int(self, msg: Any) -> None:
        self._mission_item(msg, msg.x, msg.y)

    def on_mission_item(self, msg: Any) -> None:
        glob = msg.frame in _FLOAT_DEG_FRAMES
        x = round(msg.x * 1e7) if glob else int(msg.x)
        y = round(msg.y * 1e7) if glob else int(msg.y)
        self._mission_item(msg, x, y)

    def _mission_item(self, msg: Any, x: int, y: int) -> None:
        up = self._upload
        mtype = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        if up is None or mtype != up.mission_type:
            return
        if msg.seq != len(up.items):
            self._request_next()  # out of order or repeated: ask again for the one we need
            return
        if mtype == MISSION_TYPE_MISSION and not mission_command_supported(msg.command):
            self._upload = None
            self._ack(msg, mtype, mavlink.MAV_MISSION_UNSUPPORTED)
            return
        if mtype == MISSION_TYPE_MISSION and msg.frame not in _MISSION_FRAMES:
            self._upload = None
            self._ack(msg, mtype, mavlink.MAV_MISSION_UNSUPPORTED_FRAME)
            return
        up.items.append(MissionItem(msg.seq, msg.frame, msg.command, msg.current, msg.autocontinue,
                                    msg.param1, msg.param2, msg.param3, msg.param4, x, y, msg.z, mtype))
        up.last_wall_s, up.retries = self._wall_s(), 0
        if len(up.items) < up.count:
            self._request_next()
            return
        self.ap.set_mission(mtype, up.items)
        self._upload = None
        log.info("vehicle: mission type %d uploaded, %d items", mtype, len(up.items))
        self._ack(msg, mtype, mavlink.MAV_MISSION_ACCEPTED)
        if mtype == MISSION_TYPE_MISSION:
            self._send_stream(mavlink.MAVLINK_MSG_ID_MISSION_CURRENT)

    def on_mission_request_list(self, msg: Any) -> None:
        mtype = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        self._send(mavlink.MAVLink_mission_count_message(
            msg.get_srcSystem(), msg.get_srcComponent(), len(self.ap.mission_items(mtype)), mtype))

    def on_mission_request_int(self, msg: Any) -> None:
        self._send_item(msg, as_int=True)

    def on_mission_request(self, msg: Any) -> None:
        self._send_item(msg, as_int=False)

    def _send_item(self, msg: Any, as_int: bool) -> None:
        mtype = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        items = self.ap.mission_items(mtype)
        if not 0 <= msg.seq < len(items):
            self._ack(msg, mtype, mavlink.MAV_MISSION_INVALID_SEQUENCE)
            return
        it = items[msg.seq]
        current = int(mtype == MISSION_TYPE_MISSION and msg.seq == self.ap.mission.current)
        if as_int:
            out = mavlink.MAVLink_mission_item_int_message(
                msg.get_srcSystem(), msg.get_srcComponent(), it.seq, it.frame, it.command, current,
                it.autocontinue, it.param1, it.param2, it.param3, it.param4, it.x, it.y, it.z, mtype)
        else:
            scale = 1e-7 if it.frame in GLOBAL_FRAMES else 1.0
            out = mavlink.MAVLink_mission_item_message(
                msg.get_srcSystem(), msg.get_srcComponent(), it.seq, it.frame, it.command, current,
                it.autocontinue, it.param1, it.param2, it.param3, it.param4, it.x * scale, it.y * scale,
                it.z, mtype)
        self._send(out)

    def on_mission_ack(self, msg: Any) -> None:
        log.debug("vehicle: mission ack %d from ground station", msg.type)

    def on_mission_clear_all(self, msg: Any) -> None:
        mtype = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        self.ap.set_mission(mtype, [])
        self._ack(msg, mtype, mavlink.MAV_MISSION_ACCEPTED)

    def on_mission_set_current(self, msg: Any) -> None:
        if self.ap.set_mission_current(msg.seq):
            self._send_stream(mavlink.MAVLINK_MSG_ID_MISSION_CURRENT)
        else:
            self._ack(msg, MISSION_TYPE_MISSION, mavlink.MAV_MISSION_INVALID_SEQUENCE)
