"""Where the view listens and where its map tiles come from: pure parsing, no I/O (cheap to import
for the command-line options)."""

from __future__ import annotations

import ipaddress
from urllib.parse import urlsplit

from uavloc.errors import MissionError

__all__ = ["check_tiles_url", "is_loopback", "parse_view_address"]


def is_loopback(host: str) -> bool:
    """True for loopback addresses (127.0.0.0/8, ::1) and `localhost`."""
    h = host.strip("[]")
    if h == "localhost":
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False


def parse_view_address(text: str) -> tuple[str, int]:
    """`[HOST:]PORT` → (host, port); host defaults to 127.0.0.1, `[::1]:PORT` for IPv6."""
    s = str(text).strip()
    host, sep, port_s = s.rpartition(":")
    if not sep:
        host, port_s = "127.0.0.1", s
    host = host.strip("[]") or "127.0.0.1"
    try:
        port = int(port_s)
    except ValueError:
        raise MissionError(f"--view wants [HOST:]PORT, got {text!r}") from None
    if not 0 <= port <= 65535:
        raise MissionError(f"--view port must be 0..65535, got {port}")
    return host, port


def check_tiles_url(url: str | None) -> str | None:
    """A tile URL template with {z}, {x}, {y} over http(s), or None."""
    if url is None:
        return None
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise MissionError(f"tile URL must be http(s)://host/...{{z}}/{{x}}/{{y}}..., got {url!r}")
    missing = [k for k in ("{z}", "{x}", "{y}") if k not in url]
    if missing:
        raise MissionError(f"tile URL {url!r} lacks {', '.join(missing)}")
    return url
