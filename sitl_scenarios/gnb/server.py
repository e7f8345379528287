"""Simulated OAI gNB: a TCP server that speaks the OAI telnet protocol (docs/design.md §8, §9).

Wire behaviour as OAI's `common/utils/telnetsrv/telnetsrv.c`: a request is one line; the answer
is the command's output followed by the prompt ``softmodem_gnb> `` (no prompt on connect); lines
of ≤ 2 characters get just the prompt; input starting with ``ex`` closes the connection; an
unknown command answers ``Error: ... is not a softmodem command``; one client at a time (a
second client is accepted and left waiting unanswered until the first leaves, as OAI does;
``busy_mode = "close"`` closes it instead). Commands, with OAI 2025.w36's texts
(`../shared/data/oai-2025.w36/`):

- ``o1 stats``: OAI's JSON document (UEs in coverage under ``O1-Operational.ues``) then ``OK``;
- ``ci get_single_rnti``: ``single UE RNTI %04x`` / ``different number of UEs``;
- ``ci get_reestab_count``: ``UE RNTI %04x reestab N reconfig 0`` / ``no single UE in RRC present``;
- ``rfsimu setdistance|getdistance rfsimu_channel_ue0 [m]``, ``rfsimu vtime``: the bare prompt, then
  the rfsimulator's line (offset in samples at 46.08 MHz; nothing without a UE or for another
  channel), as the recorded gNB printed it;
- ``ci force_reestab [rnti]``: OAI's answer (failures in two lines), then the random-access lines
  of the UE's reaction (`stock_reaction`) in the gNB log; ``ci force_reestab``,
  ``force_ue_release``, ``force_ul_failure`` and ``get_current_bwp`` with an RNTI in 1..0xfffd the
  gNB does not have **crash the simulated gNB** as they crash OAI (every connection closed, the
  port no longer listening, `crashed` says why); so does an ``o1 stats`` within O1_CRASH_WINDOW_S
  of the previous one (SIGFPE, as OAI 2025.w36 did back to back);
- ``rtt pdcch_order <rnti> [<rnti> ...]`` (module and command names configurable): one line per
  RNTI, ``rnti <hex> ta .. mu .. srs_peak .. fs .. snr_db ..`` or ``error rnti <hex> <reason>``.

The gNB log (`log_path`) gets OAI's random-access lines with `wall_clock` stamps: the L1
``Initiating RA procedure with preamble N ... delay D``, the MAC ``TC-RNTI`` line, the Msg2 line
(fresh temporary RNTI, ``preamble_index(RAPID) N``, ``timing_offset``), then the line that tells
who it was: ``Received a MAC CE for C-RNTI with <old>`` (a connected-mode RA, TA 0),
``Reestablishment RNTI <tc> req C-RNTI <old>``, or ``Create UE context`` (initial access of a new
UE). :meth:`SimulatedGnb.reattach` makes a UE go idle and attach again with a new RNTI (as
``ciUE force_RRC_IDLE`` does), :meth:`SimulatedGnb.crnti_access` makes it do a C-RNTI RA.

A fleet's gNBs (one per vehicle) share one cell attachment: with ``cell``
(:class:`sitl_scenarios.gnb.cells.GnbCell`) the gNB serves only the UEs attached to its cell
(``o1 stats``, ``ci``, the RTT command, the T tracer, the REST API alike); any other UE is to it an
RNTI it does not have, answered as such (``error rnti .. not connected``, a crash on ``ci
force_reestab <rnti>``). A UE that attaches to its cell, other than those attached when the fleet
came on the air, makes an initial access there (the RA lines in the log, a RAR in the T tracer),
keeping its RNTI (a simplification: OAI would give it a new one; `sitl_scenarios.gnb.cells`). A gNB
that stops or crashes leaves the air and its UEs attach elsewhere.

Answers come from the true geometry through :class:`sitl_scenarios.radio.RadioModel`. The UAV
position comes from a callable (the built-in vehicle, in-process) or from a MAVLink stream
(:class:`MavlinkPositionSource`, GLOBAL_POSITION_INT). Faults (delay, malformed answer, dropped
connection, refused connection, HTTP error) come from the scenario's ``[faults.gnb]`` table and
from :meth:`SimulatedGnb.inject` for tests. With ``rest_port`` the same gNB also serves OAI's web
server API (`sitl_scenarios/gnb/rest.py`) over the same commands, state and crash hazards.

Standalone::

    python -m sitl_scenarios.gnb --scenario FILE --port 9090 --rest-port 8090 --follow udpin:0.0.0.0:14550
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import dataclasses
import json
import logging
import random
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np

from estimator.ranging import C_MPS
from mission.gnb.oai import PROMPT_GNB, format_rtt_line, unknown_command_text
from sitl_scenarios.gnb.cells import GnbCell
from sitl_scenarios.gnb.faults import GnbFaults
from sitl_scenarios.gnb.ra import OaiRaLog
from sitl_scenarios.gnb.rest import GnbRestServer
from sitl_scenarios.gnb.ttrace import SimulatedTServer
from sitl_scenarios.position import MavlinkPositionSource, PositionSource, static_position
from sitl_scenarios.radio import RadioModel, RawRtt
from sitl_scenarios.scenario import Scenario, load_scenario
from uavloc.errors import ScenarioError, SimulatorError

log = logging.getLogger(__name__)

FaultKind = Literal["delay", "malformed", "drop", "refuse", "http_error"]
#: what a UE does after `ci force_reestab`: a reestablishment (a UE with traffic, OAI with a core),
#: a connected-mode RA then an idle re-attach (what the recorded OAI did), or nothing (no traffic)
StockReaction = Literal["reestablish", "crnti_then_idle", "none"]
_STOCK_REACTIONS = ("reestablish", "crnti_then_idle", "none")
#: `ci` commands that dereference the UE of a given RNTI without checking it (telnetsrv_ci.c)
_CRASHING_CI = ("force_reestab", "force_ue_release", "force_ul_failure", "get_current_bwp")
_CI_UNKNOWN = "could not identify UE (no UE, no such RNTI, or multiple UEs)\n"
_FAULT_KINDS = ("delay", "malformed", "drop", "refuse", "http_error")
_MAX_LINE = 2048  # OAI's TELNET_MAX_MSGLENGTH
#: the rfsimulator's sample rate at 106 PRB, 30 kHz (rfsimu vtime of the recorded gNB) [Hz]
RFSIM_SAMPLE_RATE_HZ = 46_080_000.0
#: the UE's channel model in the recorded configuration (gnb.conf / ue.conf `modellist_rfsimu_1`)
RFSIM_CHANNEL = "rfsimu_channel_ue0"
#: an `o1 stats` this soon after the previous one crashes the gNB [s] (0 ms crashed OAI, 5 ms did not)
O1_CRASH_WINDOW_S = 0.002


class SimulatedGnb:
    """The simulated gNB server; an async context manager owning its listening socket and tasks.

    scenario: users, buildings, radio; position: PositionSource of the true UAV position (ENU);
    host/port: where to listen (port 0: an ephemeral port, read it from `.port` after entering);
    log_path: gNB log file for Msg2 lines (None: none written); clock: simulation time [s] for the
    UE clock sawtooth (default: monotonic seconds since the server started); faults: GnbFaults
    (default: the scenario's); seed: seeds the radio model and the fault draws (default: the
    scenario's seed); rtt_module / rtt_command: names of the RTT command; msg2_delay_s: time from
    `ci force_reestab` to the Msg2 log line [s]; reestab_new_rnti: a UE comes back from
    reestablishment with a new C-RNTI (as a real UE may), shown in its Msg2 line; cell: this gNB's
    cell of a fleet's shared attachment (None: one gNB, every UE in coverage is its own); its
    `position` should be the one the shared cells' `positions` give for it. clock_offset_s: the gNB
    host's clock runs this far [s] ahead of `wall` (its log and T trace stamps; issue 48).
    """

    def __init__(
        self,
        scenario: Scenario,
        position: PositionSource,
        *,
        host: str = "127.0.0.1",
        port: int = 9090,
        log_path: str | Path | None = None,
        clock: Callable[[], float] | None = None,
        faults: GnbFaults | None = None,
        seed: int | None = None,
        rtt_module: str = "rtt",
        rtt_command: str = "pdcch_order",
        msg2_delay_s: float = 0.03,
        stock_reaction: StockReaction = "reestablish",
        reattach_delay_s: float = 0.05,
        linger_s: float = 0.5,
        wall: Callable[[], float] = time.time,
        rest_port: int | None = None,
        stock_websrv: bool = False,
        t_port: int | None = None,
        cell: GnbCell | None = None,
        clock_offset_s: float = 0.0,
    ) -> None:
        if cell is not None and len(cell.shared.current_rnti) != len(scenario.users):
            raise SimulatorError(f"the shared cells have {len(cell.shared.current_rnti)} UEs, the scenario "
                                 f"{len(scenario.users)}")
        if stock_reaction not in _STOCK_REACTIONS:
            raise SimulatorError(f"stock_reaction must be one of {_STOCK_REACTIONS}, got {stock_reaction!r}")
        self.scenario = scenario
        self.position = position
        self.host = host
        self.port = port
        self.log_path = Path(log_path) if log_path is not None else None
        self.faults = faults if faults is not None else GnbFaults.from_scenario(scenario)
        seq = np.random.SeedSequence(scenario.seed if seed is None else seed)
        radio_seed, fault_seed = seq.spawn(2)
        self.radio = RadioModel(scenario, np.random.default_rng(radio_seed))
        self._fault_rng = random.Random(int(fault_seed.generate_state(1)[0]))
        self._t0 = time.monotonic()
        self.clock = clock if clock is not None else (lambda: time.monotonic() - self._t0)
        self.rtt_module = rtt_module
        self.rtt_command = rtt_command
        self.msg2_delay_s = msg2_delay_s
        self.stock_reaction = stock_reaction
        self.reattach_delay_s = reattach_delay_s
        self.linger_s = linger_s
        self.wall = (lambda: wall() + clock_offset_s) if clock_offset_s else wall
        #: the web server's port (None: no REST API; 0: an ephemeral port, read it after entering)
        self.rest_port = rest_port
        #: REST: the commands take the web server's blank buffer " " for an argument, as stock OAI
        #: 2025.w36 does (`o1 stats`, `ci get_single_rnti`: "no parameter allowed"); False: for none,
        #: as the modified gNB of the RTT mode does (sitl_scenarios/gnb/rest.py)
        self.stock_websrv = stock_websrv
        self.rest: GnbRestServer | None = None
        #: the T tracer's port (None: none; 0: an ephemeral port, read it after entering)
        self.t_port = t_port
        self.t_server: SimulatedTServer | None = None
        #: this gNB's cell of a fleet's shared attachment (None: a single gNB)
        self.cell = cell
        #: {user: attach number} of the UEs attached to this cell, as this gNB last saw them
        self._cell_attach: dict[int, int] = {}
        #: current C-RNTI of each user (a new one after a reestablishment or a re-attach); a fleet's
        #: gNBs share one list (a UE keeps its RNTI across cells)
        self.current_rnti: list[int] = (cell.shared.current_rnti if cell is not None
                                        else [u.rnti for u in scenario.users])
        #: old contexts of UEs that went idle: RNTI -> monotonic time the gNB drops it
        self.lingering: dict[int, float] = {}
        #: why the simulated gNB crashed (as OAI does on a `ci` command with an unknown RNTI)
        self.crashed: str | None = None
        self._last_o1_s: float | None = None  # monotonic time of the last `o1 stats`
        #: writes OAI's random-access lines to log_path
        self.ra_log = OaiRaLog(self.log_path, self.wall, random.Random(int(seq.spawn(1)[0].generate_state(1)[0])))
        self._t_seed = int(seq.spawn(1)[0].generate_state(1)[0])
        #: recent RTT results with their truth, newest last (for tests and diagnostics)
        self.truth: collections.deque[RawRtt] = collections.deque(maxlen=100_000)
        self.requests = 0
        #: reestablishments per current RNTI (`ci get_reestab_count`)
        self.reestab_count: dict[int, int] = {}
        #: the rfsimulator's channel offset [samples] (`rfsimu setdistance|getdistance`)
        self.rfsim_offset = 0
        #: text the rfsimulator prints after the prompt of the request that asked for it
        self._after_prompt = ""
        self.connections = 0
        self._once: collections.Counter[str] = collections.Counter()
        self._once_delay_s = 0.0
        self._slot = asyncio.Lock()
        self._server: asyncio.Server | None = None
        self._tg: asyncio.TaskGroup | None = None
        self._handlers: set[asyncio.Task] = set()
        self._writers: set[asyncio.StreamWriter] = set()

    # -- fault API ---------------------------------------------------------------------------
    def inject(self, kind: FaultKind, count: int = 1, delay_s: float | None = None) -> None:
        """Make the next `count` answers (connections, for "refuse") faulty, deterministically."""
        if kind not in _FAULT_KINDS:
            raise SimulatorError(f"unknown fault {kind!r}; known: {', '.join(_FAULT_KINDS)}")
        self._once[kind] += count
        if kind == "delay":
            if delay_s is None or delay_s < 0:
                raise SimulatorError(f"a delay fault needs delay_s >= 0, got {delay_s!r}")
            self._once_delay_s = float(delay_s)

    def _fault(self, kind: FaultKind, rate: float) -> bool:
        if self._once[kind] > 0:
            self._once[kind] -= 1
            return True
        return rate > 0 and self._fault_rng.random() < rate

    # -- lifecycle -----------------------------------------------------------------------------
    async def __aenter__(self) -> SimulatedGnb:
        self._tg = asyncio.TaskGroup()
        await self._tg.__aenter__()
        try:
            self._server = await asyncio.start_server(self._on_connect, self.host, self.port,
                                                      limit=4 * _MAX_LINE)
        except OSError as exc:
            await self._tg.__aexit__(None, None, None)
            raise SimulatorError(f"simulated gNB cannot listen on {self.host}:{self.port}: {exc}") from exc
        self.port = self._server.sockets[0].getsockname()[1]
        if self.rest_port is not None:
            try:
                self.rest = await GnbRestServer(self, self.host, self.rest_port).__aenter__()
            except BaseException:
                self._server.close()
                await self._tg.__aexit__(None, None, None)
                raise
            self.rest_port = self.rest.port
        if self.t_port is not None:
            try:
                self.t_server = await SimulatedTServer(self, self.host, self.t_port, self._t_seed).__aenter__()
            except BaseException:
                self._server.close()
                await self._tg.__aexit__(None, None, None)
                raise
            self.t_port = self.t_server.port
        log.info("simulated gNB listening on %s:%d (%d users)", self.host, self.port, len(self.scenario.users))
        return self

    async def __aexit__(self, *exc_info) -> None:
        """Stop listening, close the connections and wait for the tasks; a second call is a no-op."""
        if self._server is None or self._tg is None:
            return
        server, tg, self._server, self._tg = self._server, self._tg, None, None
        if self.cell is not None:
            self.cell.leave_air()
        server.close()
        rest, self.rest = self.rest, None
        if rest is not None:
            await rest.__aexit__(None, None, None)
        t_server, self.t_server = self.t_server, None
        if t_server is not None:
            await t_server.__aexit__(None, None, None)
        for w in list(self._writers):
            w.close()  # handlers see EOF and return; waiting (silent busy) ones too once served
        if self._handlers:
            _done, pending = await asyncio.wait(list(self._handlers), timeout=2.0)
            for t in pending:
                t.cancel()
            if pending:
                await asyncio.wait(pending)
        await server.wait_closed()
        await tg.__aexit__(*exc_info)

    async def serve_forever(self) -> None:
        """Serve until cancelled (standalone use)."""
        assert self._server is not None
        await self._server.serve_forever()

    # -- connections ---------------------------------------------------------------------------
    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        self._writers.add(writer)
        self.connections += 1
        try:
            if self.take_fault("refuse"):
                log.info("fault: refusing a connection")
                return
            if self._slot.locked() and self.faults.busy_mode == "close":
                log.info("refusing a second client: OAI serves one client at a time")
                return
            async with self._slot:
                await self._serve(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError):
            log.debug("client went away")
        except asyncio.CancelledError:
            # the root of this connection's task: end quietly (asyncio's stream callback in 3.11
            # logs an error for a cancelled client_connected_cb task)
            log.debug("connection handler cancelled at shutdown")
        finally:
            self._writers.discard(writer)
            writer.close()
            with contextlib.suppress(ConnectionError, OSError):
                await writer.wait_closed()
            self._handlers.discard(task)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while True:
            try:
                raw = await reader.readuntil(b"\n")
            except asyncio.LimitOverrunError:
                log.warning("request line longer than %d bytes: closing", 4 * _MAX_LINE)
                return
            except asyncio.IncompleteReadError:
                return  # client disconnected
            line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
            self.requests += 1
            answer = self.process(line)
            if self.crashed is not None:
                self.crash_now()
                return
            if answer is None:
                log.debug("client sent %r: closing", line)
                return
            if self.take_fault("drop"):
                log.info("fault: dropping the connection instead of answering %r", line)
                return
            delay = self.take_delay()
            if delay > 0 and not await self._sleep_unless_gone(reader, delay):
                log.debug("client left while its answer was delayed")
                return
            data = answer.encode()
            if self.take_fault("malformed"):
                data = self.malform_bytes(answer)
                log.info("fault: malformed answer to %r", line)
            after, self._after_prompt = self._after_prompt, ""
            writer.write(data + PROMPT_GNB.encode())
            await writer.drain()
            if after:  # the rfsimulator prints from its own thread, after the prompt
                writer.write(after.encode())
                await writer.drain()

    @staticmethod
    async def _sleep_unless_gone(reader: asyncio.StreamReader, delay_s: float) -> bool:
        """Sleep delay_s in short steps; False as soon as the client has closed its side."""
        end = time.monotonic() + delay_s
        while (left := end - time.monotonic()) > 0:
            if reader.at_eof():
                return False
            await asyncio.sleep(min(0.01, left))
        return not reader.at_eof()

    def take_fault(self, kind: FaultKind) -> bool:
        """Whether this answer (connection, for "refuse") gets the fault `kind` (injected or drawn)."""
        rates = {"malformed": self.faults.malformed_rate, "drop": self.faults.drop_rate,
                 "refuse": self.faults.refuse_rate, "http_error": 0.0}
        return self._fault(kind, rates[kind])

    def take_delay(self) -> float:
        """The extra delay of this answer [s] (0: none)."""
        if self._once["delay"] > 0:
            self._once["delay"] -= 1
            return self._once_delay_s
        if self.faults.delay_rate > 0 and self._fault_rng.random() < self.faults.delay_rate:
            return self.faults.delay_s
        return 0.0

    def malform_bytes(self, answer: str) -> bytes:
        kind = self._fault_rng.randrange(3)
        if kind == 0 and len(answer) > 2:  # truncated
            return answer[: len(answer) // 2].encode()
        if kind == 1:  # binary garbage
            return bytes(self._fault_rng.randrange(128, 256) for _ in range(16))
        return (answer.replace(" ta ", " ta x").replace("\"ues\": [", "\"ues\": [\"") or "?").encode()

    # -- commands ------------------------------------------------------------------------------
    def process(self, line: str) -> str | None:
        """One request line -> answer text (without the prompt), or None to close (OAI rules)."""
        buf = line.strip("\r\n")
        if len(buf) <= 2:
            return ""
        if buf[:2].lower() == "ex":
            return None
        parts = buf.split(None, 2)
        if not parts:  # only blanks: OAI echoes them in its unknown-command text
            return unknown_command_text(buf)
        module = parts[0].lower()
        cmd = parts[1].lower() if len(parts) > 1 else ""
        args = parts[2] if len(parts) > 2 else ""
        if module == "help":
            return ("   module 0 = ci:\n      ci get_single_rnti \n      ci force_reestab [rnti(hex,opt)]\n"
                    "   module 1 = o1:\n      o1 stats \n"
                    f"   module 2 = {self.rtt_module}:\n      {self.rtt_module} {self.rtt_command} <rnti(hex)>\n")
        answer = self.run_command(module, cmd, args)
        return unknown_command_text(buf) if answer is None else answer

    def modules(self) -> list[str]:
        """The loaded telnet modules (what the web server lists)."""
        return ["ci", "o1"] + ([] if self.rtt_module_lost() else [self.rtt_module.lower()])

    def module_commands(self, module: str) -> list[tuple[str, str]] | None:
        """(command, question or "") of a loaded module, None when it is not loaded."""
        if module not in self.modules():
            return None
        if module == "ci":
            return [("get_single_rnti", ""), ("force_reestab", "RNTI (hex, optional)"),
                    ("force_ue_release", "RNTI (hex, optional)"), ("force_ul_failure", "RNTI (hex, optional)"),
                    ("get_current_bwp", "RNTI (hex, optional)")]
        if module == "o1":
            return [("stats", "")]
        return [(self.rtt_command.lower(), "RNTI (hex)")]

    def run_command(self, module: str, cmd: str, args: str) -> str | None:
        """One telnet module command with its argument buffer ("" for none) -> its output, or None
        when the gNB has no such command. Shared by the telnet and the REST server."""
        if module == "ci" and cmd == "get_single_rnti":
            return self._get_single_rnti(args)
        if module == "ci" and cmd == "get_reestab_count":
            return self._get_reestab_count()
        if module == "rfsimu":
            self._after_prompt = self._rfsimu(cmd, args)
            return ""
        if module == "ci" and cmd in _CRASHING_CI:
            return self._ci_with_rnti(cmd, args)
        if module == "o1" and cmd == "stats":
            return self._o1_stats(args)
        if module == self.rtt_module.lower() and cmd == self.rtt_command.lower() and not self.rtt_module_lost():
            return self._rtt(args)
        return None

    def rtt_module_lost(self) -> bool:
        """The fault `rtt_module_lost_at_s`: the RTT module is gone from this simulation time on."""
        t = self.faults.rtt_module_lost_at_s
        return t is not None and self.clock() >= t

    def _uav(self) -> np.ndarray | None:
        pos = self.position()
        if pos is None:
            return None
        p = np.asarray(pos, float).reshape(3)
        return p if np.all(np.isfinite(p)) else None

    def served_users(self) -> dict[int, int]:
        """{user index: attach number} of the UEs this gNB serves: every user (number 0) without a
        shared cell; with one, the UEs attached to its cell now. Each attach this gNB has not seen
        yet, other than one the fleet started with, is an initial access in its log."""
        if self.cell is None:
            return dict.fromkeys(range(len(self.radio.users)), 0)
        now = self.cell.served()
        for k in [k for k, n in self._cell_attach.items() if now.get(k) != n]:
            del self._cell_attach[k]  # attached elsewhere, or to no cell
        for k, n in now.items():
            if k not in self._cell_attach:
                self._cell_attach[k] = n
                if not self.cell.attached_at_start(k):
                    self._attach_access(k)
        return now

    def _attach_access(self, k: int) -> None:
        """User k attaches to this cell: an initial access with its RNTI as the TC-RNTI (it keeps
        its RNTI across cells: sitl_scenarios.gnb.cells) and the full round-trip TA."""
        got = self._round_trip_ta(k)
        if got is not None:
            self.ra_log.initial(self._frame(), self.current_rnti[k], *got)
            # whose cell: the fleet's gNB index (vehicle index) and its telnet port
            log.info("UE %04x attached to the cell of gNB %d (vehicle %d, port %d)", self.current_rnti[k],
                     self.cell.index, self.cell.index, self.port)

    def _connected_rntis(self) -> list[int]:
        """UEs in coverage of the UAV (all of them while the UAV position is unknown), or with a
        shared cell the UEs attached to it, and the old contexts of UEs that went idle until the
        gNB drops them."""
        out = []
        if self.cell is not None:
            served = self.served_users()
            out = [self.current_rnti[k] for k in range(len(self.radio.users)) if k in served]
        else:
            uav = self._uav()
            for k in range(len(self.radio.users)):
                if uav is None or np.linalg.norm(uav - self.radio.user_enu_m[k]) <= self.scenario.radio.coverage_m:
                    out.append(self.current_rnti[k])
        now = time.monotonic()
        for r, until in list(self.lingering.items()):
            if until <= now:
                del self.lingering[r]
            elif r not in out:
                out.append(r)
        return out

    def _user_of(self, rnti: int) -> int | None:
        return self.current_rnti.index(rnti) if rnti in self.current_rnti else None

    def _get_single_rnti(self, args: str) -> str:
        if args:
            return "no parameter allowed\n"
        rntis = self._connected_rntis()
        if len(rntis) != 1:
            return "different number of UEs\n"
        return f"single UE RNTI {rntis[0]:04x}\n"

    def _get_reestab_count(self) -> str:
        """`ci get_reestab_count` (telnetsrv_ci.c): the one UE's reestablishments and RRC
        reconfigurations (none here)."""
        rntis = self._connected_rntis()
        if len(rntis) != 1:
            return "no single UE in RRC present\n"
        return f"UE RNTI {rntis[0]:04x} reestab {self.reestab_count.get(rntis[0], 0)} reconfig 0\n"

    def _rfsimu(self, cmd: str, args: str) -> str:
        """OAI's rfsimulator commands, answered after the prompt (rfsimulator/simulator.c), on the
        channel `rfsimu_channel_ue0` that exists while a UE is connected; unknown channels and
        commands print nothing. The offset is kept and reported; the simulated ranges come from the
        true geometry, not from it. Samples at RFSIM_SAMPLE_RATE_HZ: offset = ⌊d·fs/c⌋."""
        words = args.split()
        channel = words[0] if words else ""
        if cmd == "vtime":
            if not self._connected_rntis():
                return ""
            ts = int(self.clock() * RFSIM_SAMPLE_RATE_HZ)
            return f"rfsimu_vtime_cmd: vtime measurement: TS {ts} sample_rate {RFSIM_SAMPLE_RATE_HZ:.3f}\n"
        if channel != RFSIM_CHANNEL or not self._connected_rntis():
            return ""
        if cmd == "getdistance":
            return (f"rfsimu_getdistance_cmd: <default> offset {self.rfsim_offset} "
                    f"delay {self.rfsim_offset / RFSIM_SAMPLE_RATE_HZ * 1e3:.6f} ms\n")
        if cmd == "setdistance" and len(words) == 2:
            try:
                distance_m = float(words[1])
            except ValueError:
                return ""
            self.rfsim_offset = int(distance_m * RFSIM_SAMPLE_RATE_HZ / C_MPS)
            exact_m = self.rfsim_offset * C_MPS / RFSIM_SAMPLE_RATE_HZ
            return (f"\nrfsimu_setdistance_cmd: new_offset {self.rfsim_offset}, new (exact) distance {exact_m:.3f} m, "
                    f"new delay {self.rfsim_offset / RFSIM_SAMPLE_RATE_HZ * 1e3:.6f} ms\n")
        return ""

    def _o1_stats(self, args: str) -> str:
        # OAI 2025.w36 dies with SIGFPE on an `o1 stats` within a few ms of the previous one (the
        # real gNB, back to back: exit 136 on the 2nd pair; 5 ms apart: 20 pairs lived)
        now = time.monotonic()
        last, self._last_o1_s = self._last_o1_s, now
        if last is not None and now - last < O1_CRASH_WINDOW_S:
            self.crashed = f"SIGFPE: `o1 stats` {1e3 * (now - last):.1f} ms after the previous one"
            log.warning("simulated gNB crashes: %s", self.crashed)
            return ""
        if args:
            return "FAILURE: no parameter allowed\n"
        r = self.scenario.radio
        scs_khz = 15 * (1 << r.mu)
        rntis = self._connected_rntis()
        bwp = {"bwp3gpp:isInitialBwp": True, "bwp3gpp:numberOfRBs": 106, "bwp3gpp:startRB": 0,
               "bwp3gpp:subCarrierSpacing": scs_khz}
        doc = {
            "o1-config": {
                "BWP": {"dl": [bwp], "ul": [bwp]},
                # the cell of the recorded configuration (../shared/data/oai-2025.w36/conf/gnb.conf)
                "NRCELLDU": {"nrcelldu3gpp:ssbFrequency": 621312, "nrcelldu3gpp:arfcnDL": 620040,
                             "nrcelldu3gpp:bSChannelBwDL": 40, "nrcelldu3gpp:arfcnUL": 620040,
                             "nrcelldu3gpp:bSChannelBwUL": 40, "nrcelldu3gpp:nRPCI": 0, "nrcelldu3gpp:nRTAC": 1,
                             "nrcelldu3gpp:mcc": "208", "nrcelldu3gpp:mnc": "99", "nrcelldu3gpp:sd": 16777215,
                             "nrcelldu3gpp:sst": 1},
                "device": {"gnbId": 3584, "gnbName": "gnb-rfsim", "vendor": "OpenAirInterface"},
            },
            "O1-Operational": {
                "frame-type": "tdd", "band-number": 78, "num-ues": len(rntis), "ues": rntis, "load": 0,
                "ues-thp": [{"rnti": x, "dl": 0, "ul": 0} for x in rntis],
            },
        }
        return json.dumps(doc, indent=2) + "\nOK\n"

    def _measure(self, rnti: int) -> RawRtt | str:
        """A RawRtt, or the reason there is none (a UE of another cell is not connected here)."""
        k = self._user_of(rnti)
        if k is None or (self.cell is not None and k not in self.served_users()):
            return "not connected"
        return self._measure_user(k)

    def _measure_user(self, k: int) -> RawRtt | str:
        """User k's RawRtt from this gNB's UAV position now, or the reason there is none."""
        uav = self._uav()
        if uav is None:
            return "no UAV position"
        raw = self.radio.measure(k, uav, float(self.clock()))
        if raw is None:
            return "out of coverage"
        self.truth.append(raw)
        return raw

    def _rtt(self, args: str) -> str:
        tokens = args.split()
        if not tokens:
            return "error missing rnti (usage: <rnti hex> [<rnti hex> ...])\n"
        out = []
        for tok in tokens:
            try:
                rnti = int(tok, 16)
            except ValueError:
                out.append(f"error bad rnti {tok[:16]!r}")
                continue
            res = self._measure(rnti)
            if isinstance(res, str):
                out.append(f"error rnti {rnti:04x} {res}")
            else:
                out.append(format_rtt_line(rnti, res.ta, res.mu, res.srs_peak, res.fs_hz, res.snr_db))
                if self.t_server is not None:  # the order's random access, on the T trace too
                    self.t_server.ordered(self._user_of(rnti))
        return "\n".join(out) + "\n"

    def _ci_with_rnti(self, cmd: str, args: str) -> str:
        """`ci force_reestab|force_ue_release|force_ul_failure|get_current_bwp [rnti]` as OAI 2025.w36
        (telnetsrv_ci.c: fetch_rnti, then the command): failures in two lines; an RNTI in
        1..0xfffd that the gNB does not have crashes it."""
        connected = self._connected_rntis()
        if args:  # OAI: any buffer, even websrv's " " (strtol gives 0)
            try:
                rnti = int(args.split()[0], 16) if args.split() else 0  # OAI: strtol(buf, NULL, 16)
            except ValueError:
                rnti = 0
            if not 1 <= rnti < 0xFFFE:
                return "RNTI needs to be [1,0xfffe]\n" + _CI_UNKNOWN
        else:
            if len(connected) != 1:
                return ("no UE found\n" + _CI_UNKNOWN) * (2 if cmd == "force_ue_release" else 1)
            rnti = connected[0]
        if rnti not in connected:
            self.crashed = f"segfault: `ci {cmd} {rnti:04x}` with an RNTI the gNB does not have"
            log.warning("simulated gNB crashes: %s", self.crashed)
            return ""
        if cmd == "force_reestab":
            k = self._user_of(rnti)
            if k is not None and self.stock_reaction != "none" and self._tg is not None:
                self._tg.create_task(self._react_later(k))
            return f"Reset RLC counters of UE RNTI {rnti:04x} to trigger reestablishment\n"
        if cmd == "get_current_bwp":
            return f"UE {rnti:04x} DL BWP ID 0 (initial) UL BWP ID 0 (initial)\n"
        # force_ue_release / force_ul_failure: the UE is dropped and attaches again
        k = self._user_of(rnti)
        if k is not None:
            self.reattach(k)
        return ""

    def crash_now(self) -> None:
        """Die like nr-softmodem on a segfault: stop listening and drop every connection."""
        if self.log_path is not None:
            with self.log_path.open("a", encoding="utf-8") as fh:
                fh.write(f"{self.crashed}\n")
        if self.cell is not None:
            self.cell.leave_air()
        if self._server is not None:
            self._server.close()
        for w in list(self._writers):
            w.close()
        if self.rest is not None:
            self.rest.crash()

    # -- random accesses ------------------------------------------------------------------------
    def _frame(self) -> int:
        return int(float(self.clock()) / 0.01) % 1023

    def _new_rnti(self) -> int:
        return self.ra_log.new_tc_rnti(set(self.current_rnti) | set(self.lingering))

    def _round_trip_ta(self, k: int) -> tuple[int, int] | None:
        """(PRACH timing estimate: the TA rounded to the nearest step, μ) of user k, or None."""
        res = self._measure_user(k)
        if isinstance(res, str):
            log.info("no random access of user %d: %s", k, res)
            return None
        step_s = self.radio.ta_step_s
        ta = res.ta + (1 if res.srs_peak / res.fs_hz >= step_s / 2 else 0)
        return min(ta, 3846), res.mu

    def crnti_access(self, k: int) -> None:
        """User k, connected, does a C-RNTI random access: TA 0 (a residual), RNTI unchanged."""
        self.ra_log.connected(self._frame(), self.current_rnti[k], self._new_rnti(), self.scenario.radio.mu)

    def reattach(self, k: int) -> int | None:
        """User k goes idle and attaches again (initial access, new RNTI, full TA), as after
        `ciUE force_RRC_IDLE`; the gNB keeps its old context for linger_s. Returns the new RNTI
        (None when the user has no coverage)."""
        got = self._round_trip_ta(k)
        if got is None:
            return None
        old, tc = self.current_rnti[k], self._new_rnti()
        self.lingering[old] = time.monotonic() + self.linger_s
        self.current_rnti[k] = tc
        self.ra_log.initial(self._frame(), tc, *got)
        return tc

    def reestablish(self, k: int) -> int | None:
        """User k reestablishes: a random access with a full TA and a new RNTI, which OAI's
        `Reestablishment RNTI <new> req C-RNTI <old>` line ties to the old one. Returns the new RNTI."""
        got = self._round_trip_ta(k)
        if got is None:
            return None
        old, tc = self.current_rnti[k], self._new_rnti()
        self.current_rnti[k] = tc
        self.reestab_count[tc] = self.reestab_count.pop(old, 0) + 1
        self.ra_log.reestablishment(self._frame(), old, tc, *got)
        return tc

    async def _react_later(self, k: int) -> None:
        await asyncio.sleep(self.msg2_delay_s)
        if self.stock_reaction == "reestablish":
            self.reestablish(k)
        elif self.stock_reaction == "crnti_then_idle":
            self.crnti_access(k)
            await asyncio.sleep(self.reattach_delay_s)
            self.reattach(k)


# ---------------------------------------------------------------------------------------------
# standalone


async def _run(args: argparse.Namespace) -> None:
    scenario = load_scenario(args.scenario)
    async with contextlib.AsyncExitStack() as stack:
        if args.follow:
            origin = scenario.origin_geo if args.origin == "scenario" else None
            position: PositionSource = await stack.enter_async_context(MavlinkPositionSource(args.follow, origin))
        else:
            position = static_position(args.static_enu or (0.0, 0.0, scenario.mission.flight.altitude_m))
        gnb = await stack.enter_async_context(SimulatedGnb(
            scenario, position, host=args.host, port=args.port, log_path=args.log, seed=args.seed,
            rtt_module=args.rtt_module, rtt_command=args.rtt_command, stock_reaction=args.stock_reaction,
            rest_port=args.rest_port, stock_websrv=args.stock_websrv, t_port=args.t_port,
            clock_offset_s=args.clock_offset, faults=None if args.rtt_module_lost_after is None else
            dataclasses.replace(GnbFaults.from_scenario(scenario), rtt_module_lost_at_s=args.rtt_module_lost_after)))
        rest = "" if gnb.rest_port is None else f", REST on http://{args.host}:{gnb.rest_port}"
        rest += "" if gnb.t_port is None else f", T tracer on {args.host}:{gnb.t_port}"
        print(f"simulated gNB for scenario {scenario.name!r} on {args.host}:{gnb.port}{rest}", file=sys.stderr)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError):
                loop.add_signal_handler(sig, stop.set)
        await stop.wait()
        log.info("simulated gNB stopping (%d connections, %d requests)", gnb.connections, gnb.requests)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m sitl_scenarios.gnb", description=__doc__.split("\n")[0])
    p.add_argument("--scenario", required=True, help="scenario TOML file or bundled name")
    p.add_argument("--host", default="0.0.0.0")
    p.add_argument("--port", type=int, default=9090, help="telnet port (default 9090)")
    p.add_argument("--rest-port", type=int, metavar="PORT",
                   help="also serve OAI's web server (REST) API on this port (OAI's default is 8090)")
    p.add_argument("--t-port", type=int, metavar="PORT",
                   help="also serve OAI's T tracer on this port (OAI's default is 2021; 0: a free port): the RAR, "
                        "TA commands and SRS impulse responses of the trace mode")
    p.add_argument("--stock-websrv", action="store_true",
                   help="REST: commands take the web server's blank parameter for an argument, as stock OAI "
                        "2025.w36 does (o1 stats and ci get_single_rnti then refuse it)")
    p.add_argument("--follow", help="MAVLink URL to follow the vehicle, e.g. udpin:0.0.0.0:14550")
    p.add_argument("--origin", choices=("home", "scenario"), default="home",
                   help="ENU origin when following MAVLink: the vehicle's home or the scenario origin")
    p.add_argument("--static-enu", type=float, nargs=3, metavar=("E", "N", "U"),
                   help="fixed UAV position [m ENU] without --follow (default: above the origin)")
    p.add_argument("--log", type=Path, help="gNB log file for Msg2 lines (stock fallback)")
    p.add_argument("--seed", type=int, help="override the scenario seed")
    p.add_argument("--rtt-module", default="rtt")
    p.add_argument("--rtt-command", default="pdcch_order")
    p.add_argument("--stock-reaction", choices=("reestablish", "crnti_then_idle", "none"), default="reestablish",
                   help="what a UE does after `ci force_reestab`: reestablish (a UE with traffic), a C-RNTI "
                        "random access then an idle re-attach (the recorded OAI), or nothing (no traffic)")
    p.add_argument("--rtt-module-lost-after", type=float, metavar="S",
                   help="fault: the RTT module is gone S seconds after the server started")
    p.add_argument("--clock-offset", type=float, default=0.0, metavar="S", help="the gNB host's clock runs S s ahead")
    p.add_argument("-v", "--verbose", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        asyncio.run(_run(args))
    except KeyboardInterrupt:
        return 0
    except (ScenarioError, SimulatorError) as exc:
        log.error("%s", exc)
        return 1
    return 0

