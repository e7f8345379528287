"""The built-in vehicle's MAVLink 2 link over UDP: one socket, the targets it sends to before a
ground station talks (like PX4's API link to 127.0.0.1:14540), every peer that talked since, the
pymavlink encoder and a robust parser. No threads: the simulator drives it."""

from __future__ import annotations

import logging
import socket
from collections.abc import Iterator
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)


class _Writer:
    """File-like sink for pymavlink: every packed message goes to each peer."""

    def __init__(self, link: UdpLink) -> None:
        self._link = link

    def write(self, buf: bytes) -> None:
        self._link.send_bytes(buf)


class UdpLink:
    """MAVLink over one UDP socket as system `system_id`, component `component_id`.

    targets: where to send before anyone talks; bind: local (host, port), port 0 picks a free one.
    """

    def __init__(
        self, targets: list[tuple[str, int]], bind: tuple[str, int], system_id: int, component_id: int
    ) -> None:
        self.targets = targets
        self.bind = bind
        self.sock: socket.socket | None = None
        self._peers: dict[tuple[str, int], None] = {}
        self._tx = mavlink.MAVLink(_Writer(self), srcSystem=system_id, srcComponent=component_id)
        self._rx = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._rx.robust_parsing = True
        self.packets_in = 0
        self.packets_out = 0

    def open(self) -> None:
        """Bind the (non-blocking) socket; SimulatorError when the address is taken."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(self.bind)
        except OSError as exc:
            sock.close()
            raise SimulatorError(f"cannot bind the vehicle's UDP socket to {self.bind}: {exc}") from exc
        sock.setblocking(False)
        self.sock = sock

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    @property
    def local_address(self) -> tuple[str, int]:
        if self.sock is None:
            raise SimulatorError("vehicle simulator not started")
        return self.sock.getsockname()

    def send(self, msg: Any) -> None:
        """Encode a pymavlink message and send it to every peer and target."""
        self._tx.send(msg)

    def send_bytes(self, buf: bytes) -> None:
        assert self.sock is not None
        for addr in self.peers():
            try:
                self.sock.sendto(buf, addr)
                self.packets_out += 1
            except OSError as exc:  # e.g. ICMP port unreachable reported on a later send
                log.debug("vehicle: send to %s failed: %s", addr, exc)

    def peers(self) -> list[tuple[str, int]]:
        """Every ground station that talked, then the targets not among them."""
        peers = dict(self._peers)
        for t in self.targets:
            peers.setdefault(t, None)
        return list(peers)

    def datagrams(self) -> Iterator[tuple[bytes, tuple[str, int]]]:
        """The datagrams waiting on the socket, (data, sender), until none is left."""
        assert self.sock is not None
        while True:
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # ICMP errors surface here on some systems
                log.debug("vehicle: receive error: %s", exc)
                return
            yield data, addr

    def accept(self, data: bytes, addr: tuple[str, int]) -> list[Any]:
        """The messages of a datagram taken in (its sender becomes a peer); MAVError when malformed."""
        self.packets_in += 1
        if addr not in self._peers and addr not in self.targets:
            log.info("vehicle: ground station at %s:%d", *addr)
        self._peers[addr] = None
        return self._rx.parse_buffer(data) or []
