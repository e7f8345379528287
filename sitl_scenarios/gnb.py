"""Simulated OAI gNB: a TCP server that speaks the OAI telnet protocol (DESIGN.md §8, §9).

Wire behaviour as OAI's `common/utils/telnetsrv/telnetsrv.c`: a request is one line; the answer
is the command's output followed by the prompt ``softmodem_gnb> `` (no prompt on connect); lines
of ≤ 2 characters get just the prompt; input starting with ``ex`` closes the connection; an
unknown command answers ``Error: ... is not a softmodem command``; one client at a time (a
second client is closed at once, or with ``busy_mode = "silent"`` left waiting unanswered like
OAI's listen backlog). Commands:

- ``o1 stats``: OAI's JSON document (UEs in coverage under ``O1-Operational.ues``) then ``OK``;
- ``ci get_single_rnti``: ``single UE RNTI %04x`` / ``different number of UEs``;
- ``ci force_reestab [rnti]``: OAI's answer, then (after `msg2_delay_s`) an OAI Msg2 line with
  ``timing_offset`` (TA rounded to the nearest step) appended to the gNB log file;
- ``rtt pdcch_order <rnti> [<rnti> ...]`` (module and command names configurable): one line per
  RNTI, ``rnti <hex> ta .. mu .. srs_peak .. fs .. snr_db ..`` or ``error rnti <hex> <reason>``.

Answers come from the true geometry through :class:`sitl_scenarios.radio.RadioModel`. The UAV
position comes from a callable (the built-in vehicle, in-process) or from a MAVLink stream
(:class:`MavlinkPositionSource`, GLOBAL_POSITION_INT). Faults (delay, malformed answer, dropped
connection, refused connection) come from the scenario's ``[faults.gnb]`` table and from
:meth:`SimulatedGnb.inject` for tests.

Standalone::

    python -m sitl_scenarios.gnb --scenario FILE --port 9090 --follow udpin:0.0.0.0:14550
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import dataclasses
import json
import logging
import math
import random
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from estimator.geodesy import Origin
from mission.oai import PROMPT_GNB, format_msg2_line, format_rtt_line, unknown_command_text
from sitl_scenarios.radio import RadioModel, RawRtt
from sitl_scenarios.scenario import Scenario, load_scenario
from uavloc.errors import ScenarioError, SimulatorError

log = logging.getLogger(__name__)

#: A UAV position source: returns the true UAV position (3,) [m, ENU] now, or None if unknown.
PositionSource = Callable[[], "np.ndarray | None"]
FaultKind = Literal["delay", "malformed", "drop", "refuse"]
_FAULT_KINDS = ("delay", "malformed", "drop", "refuse")
_MAX_LINE = 2048  # OAI's TELNET_MAX_MSGLENGTH


@dataclass
class GnbFaults:
    """Fault injection of the simulated gNB (the scenario's ``[faults.gnb]`` table).

    delay_s: extra delay of an answer [s], applied with probability delay_rate;
    malformed_rate: probability an answer is replaced by a malformed one (truncated, binary, bad
    numbers), still followed by the prompt; drop_rate: probability the connection is closed
    instead of answering; refuse_rate: probability a new connection is closed at once;
    busy_mode: how a second concurrent client is treated, "close" or "silent" (accepted, unanswered
    until the first one leaves, as OAI's backlog does).
    """

    delay_s: float = 0.0
    delay_rate: float = 0.0
    malformed_rate: float = 0.0
    drop_rate: float = 0.0
    refuse_rate: float = 0.0
    busy_mode: str = "close"

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
    def from_scenario(cls, scenario: Scenario) -> GnbFaults:
        return cls.from_table(scenario.faults.get("gnb", {}))


class SimulatedGnb:
    """The simulated gNB server; an async context manager owning its listening socket and tasks.

    scenario: users, buildings, radio; position: PositionSource of the true UAV position (ENU);
    host/port: where to listen (port 0: an ephemeral port, read it from `.port` after entering);
    log_path: gNB log file for Msg2 lines (None: none written); clock: simulation time [s] for the
    UE clock sawtooth (default: monotonic seconds since the server started); faults: GnbFaults
    (default: the scenario's); seed: seeds the radio model and the fault draws (default: the
    scenario's seed); rtt_module / rtt_command: names of the RTT command; msg2_delay_s: time from
    `ci force_reestab` to the Msg2 log line [s]; reestab_new_rnti: a UE comes back from
    reestablishment with a new C-RNTI (as a real UE may), shown in its Msg2 line.
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
        reestab_new_rnti: bool = False,
    ) -> None:
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
        self.reestab_new_rnti = reestab_new_rnti
        #: current C-RNTI of each user (changes on reestablishment when reestab_new_rnti)
        self.current_rnti: list[int] = [u.rnti for u in scenario.users]
        #: recent RTT results with their truth, newest last (for tests and diagnostics)
        self.truth: collections.deque[RawRtt] = collections.deque(maxlen=100_000)
        self.requests = 0
        self.connections = 0
        self._once: collections.Counter[str] = collections.Counter()
        self._once_delay_s = 0.0
        self._slot = asyncio.Lock()
        self._server: asyncio.Server | None = None
        self._tg: asyncio.TaskGroup | None = None
        self._handlers: set[asyncio.Task] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self._frame_ra = 0

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
        log.info("simulated gNB listening on %s:%d (%d users)", self.host, self.port, len(self.scenario.users))
        return self

    async def __aexit__(self, *exc_info) -> None:
        """Stop listening, close the connections and wait for the tasks; a second call is a no-op."""
        if self._server is None or self._tg is None:
            return
        server, tg, self._server, self._tg = self._server, self._tg, None, None
        server.close()
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
            if self._fault("refuse", self.faults.refuse_rate):
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
            if answer is None:
                log.debug("client sent %r: closing", line)
                return
            if self._fault("drop", self.faults.drop_rate):
                log.info("fault: dropping the connection instead of answering %r", line)
                return
            delay = 0.0
            if self._once["delay"] > 0:
                self._once["delay"] -= 1
                delay = self._once_delay_s
            elif self.faults.delay_rate > 0 and self._fault_rng.random() < self.faults.delay_rate:
                delay = self.faults.delay_s
            if delay > 0 and not await self._sleep_unless_gone(reader, delay):
                log.debug("client left while its answer was delayed")
                return
            data = answer.encode()
            if self._fault("malformed", self.faults.malformed_rate):
                data = self._malform(answer)
                log.info("fault: malformed answer to %r", line)
            writer.write(data + PROMPT_GNB.encode())
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

    def _malform(self, answer: str) -> bytes:
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
        module = parts[0].lower()
        cmd = parts[1].lower() if len(parts) > 1 else ""
        args = parts[2] if len(parts) > 2 else ""
        if module == "help":
            return ("   module 0 = ci:\n      ci get_single_rnti \n      ci force_reestab [rnti(hex,opt)]\n"
                    "   module 1 = o1:\n      o1 stats \n"
                    f"   module 2 = {self.rtt_module}:\n      {self.rtt_module} {self.rtt_command} <rnti(hex)>\n")
        if module == "ci" and cmd == "get_single_rnti":
            return self._get_single_rnti(args)
        if module == "ci" and cmd == "force_reestab":
            return self._force_reestab(args)
        if module == "o1" and cmd == "stats":
            return self._o1_stats(args)
        if module == self.rtt_module.lower() and cmd == self.rtt_command.lower():
            return self._rtt(args)
        return unknown_command_text(buf)

    def _uav(self) -> np.ndarray | None:
        pos = self.position()
        if pos is None:
            return None
        p = np.asarray(pos, float).reshape(3)
        return p if np.all(np.isfinite(p)) else None

    def _connected_rntis(self) -> list[int]:
        """UEs in coverage of the UAV (all of them while the UAV position is unknown)."""
        uav = self._uav()
        out = []
        for k in range(len(self.radio.users)):
            if uav is None or np.linalg.norm(uav - self.radio.user_enu_m[k]) <= self.scenario.radio.coverage_m:
                out.append(self.current_rnti[k])
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

    def _o1_stats(self, args: str) -> str:
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
                "NRCELLDU": {"nrcelldu3gpp:ssbFrequency": 641280, "nrcelldu3gpp:arfcnDL": 640008,
                             "nrcelldu3gpp:bSChannelBwDL": 40, "nrcelldu3gpp:arfcnUL": 640008,
                             "nrcelldu3gpp:bSChannelBwUL": 40, "nrcelldu3gpp:nRPCI": 0, "nrcelldu3gpp:nRTAC": 1,
                             "nrcelldu3gpp:mcc": "001", "nrcelldu3gpp:mnc": "01", "nrcelldu3gpp:sd": 16777215,
                             "nrcelldu3gpp:sst": 1},
                "device": {"gnbId": 3584, "gnbName": "gNB-uavloc-sim", "vendor": "OpenAirInterface"},
            },
            "O1-Operational": {
                "frame-type": "tdd", "band-number": 78, "num-ues": len(rntis), "ues": rntis, "load": 0,
                "ues-thp": [{"rnti": x, "dl": 0, "ul": 0} for x in rntis],
            },
        }
        return json.dumps(doc, indent=2) + "\nOK\n"

    def _measure(self, rnti: int) -> RawRtt | str:
        """A RawRtt, or the reason there is none."""
        k = self._user_of(rnti)
        if k is None:
            return "not connected"
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
        return "\n".join(out) + "\n"

    def _force_reestab(self, args: str) -> str:
        if args.strip():
            try:
                rnti = int(args.split()[0], 16)  # OAI: strtol(buf, NULL, 16)
            except ValueError:
                rnti = 0
            if not 1 <= rnti < 0xFFFE:
                return "RNTI needs to be [1,0xfffe]\n"
        else:
            rntis = self._connected_rntis()
            if len(rntis) != 1:
                return "no UE found\n"
            rnti = rntis[0]
        if self.log_path is not None and self._tg is not None:
            self._tg.create_task(self._msg2_later(rnti))
        return f"Reset RLC counters of UE RNTI {rnti:04x} to trigger reestablishment\n"

    async def _msg2_later(self, rnti: int) -> None:
        await asyncio.sleep(self.msg2_delay_s)
        res = self._measure(rnti)
        if isinstance(res, str):
            log.info("no Msg2 for RNTI %04x: %s", rnti, res)
            return
        # PRACH timing estimate: TA rounded to the nearest step (the RadioModel's TA is a floor)
        step_s = self.radio.ta_step_s
        ta = res.ta + (1 if res.srs_peak / res.fs_hz >= step_s / 2 else 0)
        ta = min(ta, 3846)
        k = self._user_of(rnti)
        if self.reestab_new_rnti and k is not None:
            new = rnti
            while new in self.current_rnti:  # next free C-RNTI
                new = new % 0xFFEF + 1
            self.current_rnti[k] = new
            rnti = new
        t = float(self.clock())
        frame = int(t / 0.01) % 1024
        slot = int((t % 0.01) / (0.001 / (1 << res.mu)))
        self._frame_ra += 1
        line = format_msg2_line(rnti, frame, slot, 0x10B, self._frame_ra % 64, ta, res.mu)
        assert self.log_path is not None
        with self.log_path.open("a", encoding="utf-8") as fh:
            fh.write(f"[NR_MAC]   UE {rnti:04x}: {frame}.{slot} RA procedure triggered (reestablishment)\n")
            fh.write(line + "\n")


# ---------------------------------------------------------------------------------------------
# UAV position from a MAVLink stream


class MavlinkPositionSource:
    """The UAV's position from a MAVLink stream (GLOBAL_POSITION_INT), as a PositionSource.

    url: pymavlink connection string (e.g. "udpin:0.0.0.0:14550"); origin: the ENU origin (None:
    the vehicle's home, from HOME_POSITION or, until that arrives, from the first
    GLOBAL_POSITION_INT as lat/lon and alt − relative_alt). An async context manager owning the
    connection and its polling task. Calling it returns (3,) ENU [m] or None before the first fix.
    """

    def __init__(self, url: str, origin: Origin | None = None, poll_s: float = 0.01) -> None:
        self.url = url
        self.origin = origin
        self._home_from_vehicle = origin is None
        self.poll_s = poll_s
        self._lla: tuple[float, float, float] | None = None
        self._conn: Any = None
        self._tg: asyncio.TaskGroup | None = None
        self._stop = asyncio.Event()
        self.messages = 0

    def __call__(self) -> np.ndarray | None:
        if self._lla is None or self.origin is None:
            return None
        return self.origin.lla_to_enu(*self._lla)

    async def __aenter__(self) -> MavlinkPositionSource:
        from pymavlink import mavutil

        try:
            self._conn = mavutil.mavlink_connection(self.url, source_system=245, source_component=191)
        except OSError as exc:
            raise SimulatorError(f"cannot open MAVLink stream {self.url!r}: {exc}") from exc
        self._tg = asyncio.TaskGroup()
        await self._tg.__aenter__()
        self._tg.create_task(self._poll())
        return self

    async def __aexit__(self, *exc_info) -> None:
        self._stop.set()
        assert self._tg is not None
        await self._tg.__aexit__(*exc_info)
        self._conn.close()

    def handle(self, msg: Any) -> None:
        """Apply one MAVLink message (GLOBAL_POSITION_INT or HOME_POSITION)."""
        mtype = msg.get_type()
        if mtype == "GLOBAL_POSITION_INT":
            lat, lon, alt = msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3
            if self._home_from_vehicle and self.origin is None:
                self.origin = Origin(lat, lon, alt - msg.relative_alt * 1e-3)
                log.info("ENU origin from the first fix: %s", self.origin)
            self._lla = (lat, lon, alt)
            self.messages += 1
        elif mtype == "HOME_POSITION" and self._home_from_vehicle:
            home = Origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            if home != self.origin:
                log.info("ENU origin from HOME_POSITION: %s", home)
            self.origin = home

    async def _poll(self) -> None:
        while not self._stop.is_set():
            for _ in range(1000):  # bounded burst, then yield to the loop
                msg = self._conn.recv_match(type=["GLOBAL_POSITION_INT", "HOME_POSITION"], blocking=False)
                if msg is None:
                    break
                self.handle(msg)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.poll_s):
                    await self._stop.wait()


def static_position(pos_enu_m) -> PositionSource:
    """A PositionSource that always returns the same ENU position (3,) [m]."""
    p = np.asarray(pos_enu_m, float).reshape(3)
    return lambda: p.copy()


# ---------------------------------------------------------------------------------------------
# standalone


async def _run(args: argparse.Namespace) -> None:
    scenario = load_scenario(args.scenario)
    async with contextlib.AsyncExitStack() as stack:
        if args.follow:
            origin = scenario.origin_geo if args.origin == "scenario" else None
            position: PositionSource = await stack.enter_async_context(MavlinkPositionSource(args.follow, origin))
        else:
            position = static_position(args.static_enu or (0.0, 0.0, scenario.mission.altitude_m))
        gnb = await stack.enter_async_context(SimulatedGnb(
            scenario, position, host=args.host, port=args.port, log_path=args.log, seed=args.seed,
            rtt_module=args.rtt_module, rtt_command=args.rtt_command))
        print(f"simulated gNB for scenario {scenario.name!r} on {args.host}:{gnb.port}", file=sys.stderr)
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
    p.add_argument("--port", type=int, default=9090)
    p.add_argument("--follow", help="MAVLink URL to follow the vehicle, e.g. udpin:0.0.0.0:14550")
    p.add_argument("--origin", choices=("home", "scenario"), default="home",
                   help="ENU origin when following MAVLink: the vehicle's home or the scenario origin")
    p.add_argument("--static-enu", type=float, nargs=3, metavar=("E", "N", "U"),
                   help="fixed UAV position [m ENU] without --follow (default: above the origin)")
    p.add_argument("--log", type=Path, help="gNB log file for Msg2 lines (stock fallback)")
    p.add_argument("--seed", type=int, help="override the scenario seed")
    p.add_argument("--rtt-module", default="rtt")
    p.add_argument("--rtt-command", default="pdcch_order")
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


if __name__ == "__main__":
    raise SystemExit(main())
