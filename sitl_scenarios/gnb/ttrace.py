"""The simulated gNB's T tracer: OAI's T protocol over TCP, with the events and habits of OAI 2025.w36
(`../shared/data/oai-2025.w36-ttrace/README.md`), so the trace mode flies against it unchanged.

Wire (as `common/utils/T/local_tracer.c`): one client at a time; on connect the server sends its
own T_messages.txt as event −1 (a buffer) then event −2, reads the client's mask (byte 1, int32 N,
N int32 flags) and from then on sends the events turned on, each as int32 length, timespec
(CLOCK_REALTIME), int32 id, fields. Its T_messages.txt is :data:`SIM_T_MESSAGES`: the events it
emits, in an order of its own (ids differ from OAI's, as between OAI versions).

Habits, in the gNB's air time (the simulation clock: frames of 10 ms):

- a UE's random access when it first comes into coverage (a fleet's gNB: each time the UE attaches
  to its cell), and at the SRS occasion after a PDCCH order (`rtt pdcch_order`, as the gNB patched
  with patches/oai-2025.w36): a PRACH event and a RAR whose TA is the round trip floored to a TA step;
- an SRS impulse response every 8 frames per UE (1 536 taps, int16 I/Q, zero delay at index 768,
  peak ~31 dB over the mean): the round trip (sitl_scenarios.radio: distance, noise, the UE clock
  sawtooth, NLoS) less the UE's timing advance; out of coverage, and at `stale_prob` per occasion,
  a stale buffer (~9 dB) as OAI traces when no SRS was received;
- a DL PDU with a Timing Advance Command every 100 frames per UE: 31 inside the loop's dead band
  (±S/2), else 31 + round(residual / S); the UE applies a command with probability `apply_prob`
  within three SRS occasions (OAI's UE drops those that come after it prepared the target slot,
  and the gNB re-sends);
- SIB1 PDUs on RNTI 0xffff (no TA command).
"""

from __future__ import annotations

import asyncio
import logging
import math
import random
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estimator.ranging import TA_RAR_MAX
from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)

SIM_T_MESSAGES = """\
# the simulated gNB's T events (uavloc sitl_scenarios/gnb/ttrace.py); formats as OAI 2025.w36's
ID = GNB_PHY_UL_TICK
    DESC = gNodeB uplink tick
    GROUP = ALL:PHY:GNB
    FORMAT = int,gNB_ID : int,frame : int,slot
ID = GNB_MAC_DL_PDU_WITH_DATA
    DESC = NR MAC downlink PDU for an UE
    GROUP = ALL:MAC:GNB:WIRESHARK
    FORMAT = int,gNB_ID : int,CC_id : int,rnti : int,frame : int,slot : int,harq_pid : buffer,data
ID = ENB_PHY_INITIATE_RA_PROCEDURE
    DESC = eNodeB initiates a random access procedure after detecting enough energy for one of the preambles
    GROUP = ALL:PHY:ENB:WIRESHARK
    FORMAT = int,eNB_ID : int,frame : int,subframe : int,preamble : int,energy : int,delay
ID = GNB_MAC_DL_RAR_PDU_WITH_DATA
    DESC = NR MAC downlink PDU for RAR
    GROUP = ALL:MAC:GNB:WIRESHARK
    FORMAT = int,gNB_ID : int,CC_id : int,rnti : int,frame : int,slot : int,harq_pid : buffer,data
ID = GNB_PHY_UL_TIME_CHANNEL_ESTIMATE
    DESC = gNodeB channel estimation in the time domain
    GROUP = ALL:PHY:GRAPHIC:HEAVY:GNB
    FORMAT = int,gNB_ID : int,rnti : int,frame : int,subframe : int,antenna : buffer,chest_t
"""
_NAMES = [line.split("=", 1)[1].strip() for line in SIM_T_MESSAGES.splitlines() if line.startswith("ID =")]
ID = {name: i for i, name in enumerate(_NAMES)}

SRS_PERIOD_FRAMES = 8
TA_PERIOD_FRAMES = 100
SIB1_PERIOD_FRAMES = 16
N_TAPS = 1536
#: SRS peak amplitude and noise per I/Q component: the peak ~31 dB over the mean tap power
PEAK_AMPLITUDE = 8000.0
NOISE_SIGMA = 70.0
#: a stale buffer: a weak peak ~9 dB over the mean
STALE_AMPLITUDE = 330.0


def frame_bytes(t_wall_s: float, event_id: int, payload: bytes) -> bytes:
    """One T frame: int32 length, timespec (int64 s, int64 ns), int32 id, the fields' bytes."""
    s = math.floor(t_wall_s)
    ns = min(999_999_999, round((t_wall_s - s) * 1e9))
    body = struct.pack("<qqi", s, ns, event_id) + payload
    return struct.pack("<i", len(body)) + body


def fields_bytes(*values: int) -> bytes:
    return struct.pack(f"<{len(values)}i", *values)


def buffer_bytes(data: bytes) -> bytes:
    return struct.pack("<i", len(data)) + data


def chest_bytes(peak_samples: float, amplitude: float, rng: np.random.Generator) -> bytes:
    """An SRS impulse response as OAI traces it: N_TAPS × (int16 I, int16 Q), zero delay at N/2; a
    tap of `amplitude` at N/2 + peak split between its two nearest taps, plus Gaussian noise."""
    iq = rng.normal(0.0, NOISE_SIGMA, size=(N_TAPS, 2))
    pos = N_TAPS / 2 + peak_samples
    i0 = math.floor(pos)
    frac = pos - i0
    for i, w in ((i0, 1.0 - frac), (i0 + 1, frac)):
        if 0 <= i < N_TAPS:
            iq[i, 0] += amplitude * w
    return np.clip(np.round(iq), -32768, 32767).astype("<i2").tobytes()


@dataclass
class _Ue:
    rnti: int
    n_ta: int  # the UE's timing advance [TA steps]
    residual: float = 0.0  # the latest SRS residual [samples]
    apply: list[tuple[float, int]] = field(default_factory=list)  # (air time, command) the UE will apply
    attach: int = 0  # its attach number (SimulatedGnb.served_users) when it made its random access here


class SimulatedTServer:
    """The T server of a :class:`SimulatedGnb` (see the module docstring).

    gnb: the simulated gNB (sitl_scenarios.gnb.server.SimulatedGnb, which owns this server) whose
    users, radio model, UAV position and clocks it uses; host, port
    (0: ephemeral); seed; stale_prob: a stale SRS estimate per occasion; apply_prob: a TA command
    applied by the UE."""

    def __init__(self, gnb: Any, host: str, port: int, seed: int, *, stale_prob: float = 0.01,
                 apply_prob: float = 0.5, tick_s: float = 0.005) -> None:
        self.gnb = gnb
        self.host, self.port = host, port
        self.rng = np.random.default_rng(seed)
        self.pyrng = random.Random(seed)
        self.stale_prob, self.apply_prob, self.tick_s = stale_prob, apply_prob, tick_s
        self.step_samples = gnb.radio.ta_step_s * gnb.scenario.radio.fs_hz
        self.ues: dict[int, _Ue] = {}  # user index -> state
        self.events_sent = 0
        self.clients = 0
        self._server: asyncio.Server | None = None
        self._busy = asyncio.Lock()
        self._handlers: set[asyncio.Task] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self._stopping = False

    async def __aenter__(self) -> SimulatedTServer:
        try:
            self._server = await asyncio.start_server(self._on_connect, self.host, self.port)
        except OSError as exc:
            raise SimulatorError(f"simulated T tracer cannot listen on {self.host}:{self.port}: {exc}") from exc
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc_info) -> None:
        server, self._server = self._server, None
        if server is None:
            return
        server.close()
        self._stopping = True  # handlers leave their loops at the next tick
        for w in list(self._writers):
            w.close()
        if self._handlers:
            _done, pending = await asyncio.wait(list(self._handlers), timeout=2.0)
            for t in pending:
                t.cancel()
        await server.wait_closed()

    async def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        self._writers.add(writer)
        try:
            async with self._busy:  # one client at a time, as OAI's T server
                self.clients += 1
                await self._serve(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError, OSError) as exc:
            log.debug("T client left: %s", exc)
        finally:
            self._handlers.discard(task)
            self._writers.discard(writer)
            writer.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        wall = self.gnb.wall
        writer.write(frame_bytes(wall(), -1, buffer_bytes(SIM_T_MESSAGES.encode())))
        writer.write(frame_bytes(wall(), -2, b""))
        await writer.drain()
        if (await reader.readexactly(1))[0] != 1:
            raise ConnectionError("the client's first byte is not T_ENABLE")
        (n,) = struct.unpack("<i", await reader.readexactly(4))
        if n != len(_NAMES):
            raise ConnectionError(f"the client's mask has {n} flags, this server {len(_NAMES)} events")
        flags = struct.unpack(f"<{n}i", await reader.readexactly(4 * n))
        on = {i for i, f in enumerate(flags) if f}
        last_air, last_wall = float(self.gnb.clock()), wall()
        while not self._stopping:
            await asyncio.sleep(self.tick_s)
            now, now_wall = float(self.gnb.clock()), wall()
            out = self._events_between(last_air, now, last_wall, now_wall, on)
            last_air, last_wall = now, now_wall
            if out:
                writer.write(b"".join(out))
                self.events_sent += len(out)
                await writer.drain()

    # -- the gNB's habits, in air time -----------------------------------------------------------------
    def _events_between(self, t0: float, t1: float, w0: float, w1: float, on: set[int]) -> list[bytes]:
        """Every event of air time (t0, t1] (frames of 10 ms), each stamped with the wall time
        interpolated between w0 (at t0) and w1 (at t1)."""
        out: list[bytes] = []
        f0, f1 = math.floor(t0 / 0.01), math.floor(t1 / 0.01)
        for f in range(f0 + 1, f1 + 1):
            t_air = f * 0.01
            t_wall_s = w0 + (w1 - w0) * (t_air - t0) / (t1 - t0)
            if f % SIB1_PERIOD_FRAMES == 0 and ID["GNB_MAC_DL_PDU_WITH_DATA"] in on:
                sib1 = self.rng.bytes(100)
                out.append(frame_bytes(t_wall_s, ID["GNB_MAC_DL_PDU_WITH_DATA"],
                                       fields_bytes(0, 0, 0xFFFF, f % 1024, 1, 0) + buffer_bytes(sib1)))
            if f % SRS_PERIOD_FRAMES == 0:
                out += self._srs_occasion(f, t_air, t_wall_s, on)
            if f % TA_PERIOD_FRAMES == 0:
                out += self._ta_loop(f, t_air, t_wall_s, on)
        return out

    def _rtt_samples(self, k: int, t_air: float) -> float | None:
        uav = self.gnb._uav()
        if uav is None:
            return None
        raw = self.gnb.radio.measure(k, uav, t_air)
        if raw is None:
            return None
        self.gnb.truth.append(raw)
        return raw.ta * self.step_samples + raw.srs_peak

    def _srs_occasion(self, f: int, t_air: float, t_wall_s: float, on: set[int]) -> list[bytes]:
        out: list[bytes] = []
        served = self.gnb.served_users()  # a fleet's gNB: the UEs attached to its cell
        for k in [k for k, ue in self.ues.items() if served.get(k) != ue.attach]:
            del self.ues[k]  # gone to another cell (or attached again): a random access when back
        for k, attach in served.items():
            rtt = self._rtt_samples(k, t_air)
            ue = self.ues.get(k)
            if ue is None:
                if rtt is None:
                    continue
                out += self._random_access(k, f, rtt, t_wall_s, on)
                self.ues[k].attach = attach
                continue
            for when, cmd in [a for a in ue.apply if a[0] <= t_air]:
                ue.n_ta += cmd - 31
                ue.apply.remove((when, cmd))
            stale = rtt is None or self.pyrng.random() < self.stale_prob
            if not stale:
                ue.residual = rtt - self.step_samples * ue.n_ta
            if ID["GNB_PHY_UL_TIME_CHANNEL_ESTIMATE"] not in on:
                continue
            if stale:
                chest = chest_bytes(float(self.rng.integers(-700, 700)), STALE_AMPLITUDE, self.rng)
            else:
                chest = chest_bytes(ue.residual, PEAK_AMPLITUDE, self.rng)
            out.append(frame_bytes(t_wall_s, ID["GNB_PHY_UL_TIME_CHANNEL_ESTIMATE"],
                                   fields_bytes(0, ue.rnti, f % 1024, 0, 0) + buffer_bytes(chest)))
        return out

    def ordered(self, k: int | None) -> None:
        """A PDCCH order (`rtt pdcch_order`) made UE k do a random access: at its next SRS occasion a
        RAR with its absolute TA, the UE's TA starting over from it (as the patched OAI's)."""
        if k is not None:
            self.ues.pop(k, None)

    def _random_access(self, k: int, f: int, rtt: float, t_wall_s: float, on: set[int]) -> list[bytes]:
        rnti = self.gnb.current_rnti[k]
        ta = max(0, min(TA_RAR_MAX, math.floor(rtt / self.step_samples)))
        self.ues[k] = _Ue(rnti, ta)
        preamble = self.pyrng.randrange(64)
        out = []
        if ID["ENB_PHY_INITIATE_RA_PROCEDURE"] in on:
            out.append(frame_bytes(t_wall_s, ID["ENB_PHY_INITIATE_RA_PROCEDURE"],
                                   fields_bytes(0, f % 1024, 19, preamble, 440, ta)))
        if ID["GNB_MAC_DL_RAR_PDU_WITH_DATA"] in on:
            # subheader E=0 T=1 RAPID; MAC RAR: R | TA(12) | UL grant(27) | TC-RNTI(16)
            rar = bytes([0x40 | preamble, (ta >> 5) & 0x7F, (ta & 0x1F) << 3, 0, 0, 0, rnti >> 8, rnti & 0xFF])
            out.append(frame_bytes(t_wall_s, ID["GNB_MAC_DL_RAR_PDU_WITH_DATA"],
                                   fields_bytes(0, 0, 0x010F, (f + 1) % 1024, 10, 0) + buffer_bytes(rar + bytes(20))))
        return out

    def _ta_loop(self, f: int, t_air: float, t_wall_s: float, on: set[int]) -> list[bytes]:
        out = []
        for ue in self.ues.values():
            r = ue.residual
            cmd = 31 if abs(r) <= self.step_samples / 2 else int(min(63, max(0, 31 + round(r / self.step_samples))))
            if cmd != 31 and self.pyrng.random() < self.apply_prob:
                ue.apply.append((t_air + self.pyrng.uniform(0.01, 0.2), cmd))
            if ID["GNB_MAC_DL_PDU_WITH_DATA"] in on:
                # TA command MAC CE (LCID 61, TAG 0 | TA), then padding (LCID 63)
                pdu = bytes([61, cmd & 0x3F, 63]) + bytes(16)
                out.append(frame_bytes(t_wall_s, ID["GNB_MAC_DL_PDU_WITH_DATA"],
                                       fields_bytes(0, 0, ue.rnti, f % 1024, 0, 0) + buffer_bytes(pdu)))
        return out


__all__ = ["SIM_T_MESSAGES", "SimulatedTServer", "buffer_bytes", "chest_bytes", "fields_bytes", "frame_bytes"]

