"""Settings of the OAI gNB adapter, its address, and the `ci` commands it refuses to send
(re-exported by `mission.gnb`)."""

from __future__ import annotations

import dataclasses
import random
from dataclasses import dataclass
from typing import Any

from estimator.ranging import MU_VALUES
from mission.config import GnbSettings
from mission.gnb.oai import PROMPT_GNB
from mission.gnb.trace_rtt import TraceSettings
from uavloc.errors import GnbError

#: `ci` commands never sent: they release the UE, and crash stock OAI with an RNTI it no longer has
FORBIDDEN_CI = ("force_ue_release", "force_ul_failure")
#: `ci` commands that act on one UE: sent only with an RNTI a fresh discovery listed
UE_CI = ("force_reestab", "get_current_bwp")
#: the ways to measure: the modified gNB's RTT command, a stock gNB's T tracer, its log, the best found
GNB_MODES = ("rtt", "trace", "stock", "auto")


@dataclass(frozen=True)
class GnbConfig(GnbSettings):
    """Settings of :class:`OaiGnbClient`: a mission file's gNB settings
    (:class:`mission.config.GnbSettings`: transport, mode, stock_mode, rtt_module, rtt_command,
    discovery, mu, log_path (a str or Path), timeouts, retries; :meth:`of` makes one from them)
    and what only the adapter has.

    host, port: the gNB telnet server (`--telnetsrv.listenport`, default 9090) or web server
    (`--websrv.listenport`, default 8090); prompt: what ends a telnet answer; backoff_initial_s,
    backoff_max_s: jittered exponential backoff after a lost connection [s]; seed: seeds the
    jitter; log_poll_s: gNB log polling period [s]; log_history: read the gNB log from its start
    (else from its end when connecting). Stock mode "passive" is the default because on OAI
    2025.w36 a discovery a few seconds after `ci force_reestab` killed the gNB with SIGFPE in our
    runs: "active" is an explicit choice.
    """

    host: str = "127.0.0.1"
    port: int = 9090
    prompt: str = PROMPT_GNB
    backoff_initial_s: float = 0.05
    backoff_max_s: float = 2.0
    seed: int = 0
    log_poll_s: float = 0.01
    log_history: bool = False

    @classmethod
    def of(cls, settings: GnbSettings, host: str, port: int, **overrides: Any) -> GnbConfig:
        """The adapter's settings for the gNB at host:port: a mission file's `settings`, and
        overrides of any field."""
        mine = {f.name: getattr(settings, f.name) for f in dataclasses.fields(GnbSettings)}
        return cls(**{**mine, "host": host, "port": port, **overrides})

    def trace_settings(self) -> TraceSettings:
        """How the trace mode reads the T stream (mission.gnb.trace_rtt): TraceSettings.of(self)."""
        return TraceSettings.of(self)

    def __post_init__(self) -> None:
        if self.transport not in ("telnet", "rest"):
            raise GnbError(f"gNB transport must be 'telnet' or 'rest', got {self.transport!r}")
        if self.mode not in GNB_MODES:
            raise GnbError(f"gNB mode must be one of {', '.join(GNB_MODES)}, got {self.mode!r}")
        if self.stock_mode not in ("active", "passive"):
            raise GnbError(f"stock mode must be 'active' or 'passive', got {self.stock_mode!r}")
        if self.discovery not in ("auto", "o1", "single"):
            raise GnbError(f"gNB discovery must be 'auto', 'o1' or 'single', got {self.discovery!r}")
        if self.mu not in MU_VALUES:
            raise GnbError(f"mu must be one of {MU_VALUES}, got {self.mu!r}")
        for name in ("request_timeout_s", "connect_timeout_s", "msg2_timeout_s", "log_poll_s"):
            if not getattr(self, name) > 0:
                raise GnbError(f"{name} must be positive, got {getattr(self, name)!r}")
        if self.retries < 0 or self.backoff_initial_s < 0 or self.backoff_max_s < 0:
            raise GnbError("retries and backoff times must be non-negative")
        for key, value, why in self.problems():
            raise GnbError(f"{key} {value!r}: {why}")


def backoff_delay_s(attempt: int, initial_s: float, max_s: float, rng: random.Random) -> float:
    """The wait before reconnect `attempt` (0-based) [s], jittered exponential ("equal jitter"):

        delay = min(max, initial · 2^attempt) · U(0.5, 1)
    """
    return min(max_s, initial_s * 2**attempt) * (0.5 + 0.5 * rng.random())


def parse_host_port(text: str, default_port: int = 9090) -> tuple[str, int]:
    """"HOST:PORT" (or "HOST") -> (host, port); GnbError when the port is not a number."""
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    try:
        p = int(port)
    except ValueError:
        raise GnbError(f"bad gNB address {text!r}: port {port!r} is not a number") from None
    if not 0 < p < 65536:
        raise GnbError(f"bad gNB address {text!r}: port out of range")
    return host.strip("[]") or "127.0.0.1", p


def check_ci_line(line: str, guarded: bool = False) -> None:
    """Refuse a `ci` request that could crash or release a UE on stock OAI (GnbError).

    Never `force_ue_release` / `force_ul_failure`; a `ci` command acting on a UE never without its
    RNTI (UE_CI); a `ci` command with an argument (an RNTI) only when `guarded` (sent by
    OaiGnbClient.guarded_ci right after a fresh discovery).
    """
    parts = line.split()
    if not parts or parts[0].lower() != "ci":
        return
    cmd = parts[1].lower() if len(parts) > 1 else ""
    if cmd in FORBIDDEN_CI:
        raise GnbError(f"refusing to send {line!r}: `ci {cmd}` releases the UE, and with an RNTI the gNB "
                       f"no longer has it crashes stock OAI (2025.w36)")
    if cmd in UE_CI and len(parts) < 3:
        raise GnbError(f"refusing to send {line!r}: without an RNTI stock OAI picks a UE itself, which is "
                       f"unchecked (the gNB may hold a stale context after a re-attach, and the real gNB died "
                       f"under this command in our tests); name an RNTI that a fresh `o1 stats` lists")
    if len(parts) > 2 and not guarded:
        raise GnbError(f"refusing to send {line!r}: a `ci` command naming an RNTI is sent only right after "
                       f"a fresh `o1 stats` lists it (OaiGnbClient.guarded_ci); stock OAI crashes on an "
                       f"RNTI it does not have")
