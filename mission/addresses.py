"""When two addresses of a fleet are one (issue 49): MAVLink connection URLs and gNB addresses
compared as the endpoints they reach, not as text.

- A host is resolved: an IP literal is itself; a name is what the resolver gives (`localhost` →
  127.0.0.1, ::1), or the name itself when it does not resolve. The loopback and wildcard
  addresses (`127.0.0.1`, `::1`, `0.0.0.0`, `::`, `localhost`, an empty host) are all this
  machine: a client that connects to 0.0.0.0 reaches the local host, and a socket listening on
  0.0.0.0 takes the port on every address.
- MAVLink (MAVSDK URLs): `udpin://H:P` and the older `udp://H:P` (`udp://:P`) listen on UDP port P,
  `udpout://H:P` sends to it; `tcpin://` listens, `tcpout://` and the older `tcp://` connect;
  `serial://DEV:BAUD` and `serialflowcontrol://DEV:BAUD` open a device (the baud rate does not
  make it another). Two listeners on one port of this machine are one endpoint whatever their
  host; two senders are one when host and port are.
- A gNB (`HOST[:PORT]`, `telnet://HOST[:PORT]`, `http://HOST[:PORT]`, mission.gnb.transport):
  one TCP endpoint, host and port (the default port is the transport's), whatever the scheme.

Pure apart from the resolver; :func:`fleet_address_problem` is `uavloc fly`'s check of a fleet's
addresses, :func:`first_duplicate` that of `uavloc sim --connect`.
"""

from __future__ import annotations

import ipaddress
import os
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mission.config import MissionConfig

#: what every local (loopback or wildcard) host resolves to
LOCAL = "this machine"


@lru_cache(maxsize=256)
def resolve_host(host: str) -> frozenset[str]:
    """The addresses `host` stands for: {LOCAL} for a loopback or wildcard one, its IP literal,
    the resolver's addresses of a name, or the lower-case name when it does not resolve."""
    h = host.strip().strip("[]").lower()
    if h in ("", "localhost", "*"):
        return frozenset({LOCAL})
    try:
        ips = {ipaddress.ip_address(h)}
    except ValueError:
        try:
            ips = {ipaddress.ip_address(info[4][0].split("%")[0]) for info in socket.getaddrinfo(h, None)}
        except (OSError, UnicodeError, ValueError):
            return frozenset({h})
    return frozenset(LOCAL if ip.is_loopback or ip.is_unspecified else str(ip) for ip in ips)


@dataclass(frozen=True)
class Endpoint:
    """What an address reaches: kind ("udp", "tcp", "serial", or the unparsed text's scheme),
    listen (a local socket bound to the port), hosts (:func:`resolve_host`), port (0: none),
    path (a serial device's, resolved)."""

    kind: str
    listen: bool = False
    hosts: frozenset[str] = frozenset()
    port: int = 0
    path: str = ""

    def same(self, other: Endpoint) -> bool:
        """Whether the two are one endpoint (the module docstring)."""
        if self.kind != other.kind or self.listen != other.listen:
            return False
        if self.kind == "serial" or self.path or other.path:
            return self.path == other.path
        if self.port != other.port:
            return False
        if self.listen:
            # one port of this machine: every local listener shares it
            return bool(self.hosts & other.hosts) or LOCAL in self.hosts or LOCAL in other.hosts
        return bool(self.hosts & other.hosts)


def _host_port(rest: str) -> tuple[str, int]:
    host, sep, port = rest.rpartition(":")
    if not sep:
        return rest, 0
    try:
        return host, int(port)
    except ValueError:
        return rest, 0


#: MAVSDK schemes: (kind, listen)
_MAVLINK_SCHEMES = {"udpin": ("udp", True), "udp": ("udp", True), "udpout": ("udp", False),
                    "tcpin": ("tcp", True), "tcpout": ("tcp", False), "tcp": ("tcp", False)}


def mavlink_endpoint(url: str) -> Endpoint:
    """The endpoint of a MAVSDK connection URL (the module docstring); an unknown form is its own
    lower-case text."""
    text = url.strip()
    scheme, sep, rest = text.partition("://")
    scheme = scheme.lower()
    if sep and scheme in ("serial", "serialflowcontrol"):
        device, _, _baud = rest.rpartition(":") if rest.count(":") else (rest, "", "")
        return Endpoint("serial", path=os.path.realpath(device or rest))
    if sep and scheme in _MAVLINK_SCHEMES:
        kind, listen = _MAVLINK_SCHEMES[scheme]
        host, port = _host_port(rest)
        return Endpoint(kind, listen, resolve_host(host), port)
    return Endpoint(text.lower(), path=text.lower())


def gnb_endpoint(address: str, default_transport: str = "telnet") -> Endpoint:
    """The TCP endpoint of a gNB address as `--gnb` takes it (mission.gnb.transport.parse_gnb_address;
    GnbError when it is malformed)."""
    from mission.gnb.transport import parse_gnb_address

    a = parse_gnb_address(address, default=default_transport)
    return Endpoint("tcp", False, resolve_host(a.host), a.port)


def first_duplicate(ends: Sequence[Endpoint]) -> tuple[int, int] | None:
    """(i, j), i < j, of the first two endpoints that are one (:meth:`Endpoint.same`), or None."""
    for j in range(len(ends)):
        for i in range(j):
            if ends[i].same(ends[j]):
                return i, j
    return None


def fleet_address_problem(mc: MissionConfig) -> str | None:
    """What `uavloc fly` lacks to reach the vehicles and gNBs of `mc` (a mission.config.MissionConfig),
    or None. A fleet of two or more vehicles needs every vehicle's own `connect` and `gnb` (the
    command line's --connect and --gnb address one vehicle), well formed, no two on one endpoint
    however spelt; a mission without `[[vehicles]]` or with one vehicle takes what it leaves out
    from the command line. Not a check of mission.config.validate_mission: a simulation gives every
    vehicle its addresses itself."""
    from uavloc.errors import UavlocError

    n = len(mc.vehicles)
    if n < 2:
        return None
    missing = [f"vehicles[{i}].{key} ({v.id})" for i, v in enumerate(mc.vehicles)
               for key in ("connect", "gnb") if not getattr(v, key)]
    if missing:
        return (f"a fleet of {n} vehicles is flown with each vehicle's own connect and gnb addresses (the command "
                f"line's --connect and --gnb address one vehicle); not given: {', '.join(missing)}")
    gnbs = []
    for i, v in enumerate(mc.vehicles):
        try:
            gnbs.append(gnb_endpoint(v.gnb, mc.gnb.transport))
        except UavlocError as exc:
            return f"vehicles[{i}].gnb = {v.gnb!r}: {exc}"
    checks = (("connect", [v.connect for v in mc.vehicles], [mavlink_endpoint(v.connect) for v in mc.vehicles],
               "MAVLink address"), ("gnb", [v.gnb for v in mc.vehicles], gnbs, "gNB"))
    for key, texts, ends, what in checks:
        dup = first_duplicate(ends)
        if dup is not None:
            i, j = dup
            same = "" if texts[i] == texts[j] else f" (as {texts[i]!r})"
            return (f"vehicles[{j}].{key} = {texts[j]!r} reaches the same endpoint as vehicles[{i}].{key}{same}: "
                    f"each vehicle of a fleet has its own {what}")
    return None
