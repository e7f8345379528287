"""The rfsim channel of a real OAI pair, as numbers (pure: no sockets, files or clocks).

OAI's rfsimulator delays a link by a whole number of samples, the channel offset k. Its telnet
command `rfsimu setdistance <model> <metres>` takes integer metres (`%d`) and truncates
(radio/rfsimulator/simulator.c, `rfsimu_setdistance_cmd`, OAI 2025.w36):

    k = floor(m · fs / c),   exact distance = k · c / fs

so at fs = 46.08 Msps one sample is c / fs = 6.506 m of channel distance. The bridge puts the
whole round trip on the nrUE's downlink (its `rfsimu_channel_enB0`, the gNB's uplink stays at 0):
a UE at distance d then has an RTT of k samples with k ≈ 2d · fs / c, and a one-way range
k · c / (2 fs) (3.253 m per sample).

The pace of rfsim (simulated seconds per wall second) comes from `rfsimu vtime`, which prints the
next receive timestamp TS in samples: pace = Δ(TS / fs) / Δwall.
"""

from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass

from uavloc.errors import SimulatorError

SPEED_OF_LIGHT_MPS = 299_792_458.0  # OAI's own c in simulator.c


def sample_m(fs_hz: float) -> float:
    """Channel distance of one rfsim sample [m]: c / fs (6.506 m at 46.08 Msps)."""
    return SPEED_OF_LIGHT_MPS / float(fs_hz)


def offset_of_metres(metres: int, fs_hz: float) -> int:
    """The offset OAI sets for `setdistance <metres>` [samples]: k = floor(m · fs / c)."""
    return int(float(int(metres)) * float(fs_hz) / SPEED_OF_LIGHT_MPS)


def metres_for_offset(offset: int, fs_hz: float) -> int:
    """The smallest integer metres whose `setdistance` sets exactly `offset` samples."""
    if offset < 0:
        raise SimulatorError(f"an rfsim offset is a whole number of samples >= 0, got {offset}")
    m = math.ceil(offset * sample_m(fs_hz))
    while offset_of_metres(m, fs_hz) > offset:  # float edge: one metre less
        m -= 1
    while offset_of_metres(m, fs_hz) < offset:
        m += 1
    return m


def offset_for_round_trip(round_trip_m: float, fs_hz: float) -> int:
    """The whole-sample offset nearest a round trip 2d [m] (the nrUE's downlink carries it all)."""
    if not (math.isfinite(round_trip_m) and round_trip_m >= 0):
        raise SimulatorError(f"a round trip is a distance >= 0 m, got {round_trip_m!r}")
    return round(round_trip_m / sample_m(fs_hz))


def next_offset(current: int, target: int, max_step: int = 1) -> int:
    """One setting's offset on the way from `current` to `target` [samples]: at most `max_step`
    samples from `current` (a jump of many samples at once crashed a gNB: `Assertion prach_id < 8`
    after 19 samples)."""
    if max_step < 1:
        raise SimulatorError(f"a channel step is at least one sample, got {max_step}")
    return current + max(-max_step, min(max_step, target - current))


_VTIME = re.compile(r"vtime measurement: TS (\d+) sample_rate ([0-9.]+)")


def parse_vtime(text: str) -> float:
    """rfsim's virtual time [s] in an `rfsimu vtime` answer (`... TS <samples> sample_rate <Hz>`);
    SimulatorError when the answer has none."""
    m = _VTIME.search(text)
    if m is None or float(m.group(2)) <= 0:
        raise SimulatorError(f"no rfsimu vtime line in {text[:200]!r}")
    return int(m.group(1)) / float(m.group(2))


_SET = re.compile(r"new_offset (\d+), new \(exact\) distance ([0-9.]+) m")


def parse_set_offset(text: str) -> int:
    """The offset OAI reports having set in a `rfsimu setdistance` answer [samples]."""
    m = _SET.search(text)
    if m is None:
        raise SimulatorError(f"no rfsimu setdistance line in {text[:200]!r}")
    return int(m.group(1))


@dataclass
class PaceMeter:
    """rfsim's pace from (wall [s], rfsim virtual time [s]) pairs: the slope over the pairs of the
    last `window_s` wall seconds. pace = (v_n − v_0) / (w_n − w_0); None before `min_span_s`."""

    window_s: float = 10.0
    min_span_s: float = 2.0

    def __post_init__(self) -> None:
        self._pairs: deque[tuple[float, float]] = deque()

    def add(self, wall_s: float, vtime_s: float) -> None:
        if self._pairs and (wall_s <= self._pairs[-1][0] or vtime_s < self._pairs[-1][1]):
            self._pairs.clear()  # a clock that went back (a new rfsim): start again
        self._pairs.append((float(wall_s), float(vtime_s)))
        while len(self._pairs) > 2 and self._pairs[-1][0] - self._pairs[1][0] >= self.window_s:
            self._pairs.popleft()

    @property
    def span_s(self) -> float:
        return self._pairs[-1][0] - self._pairs[0][0] if len(self._pairs) > 1 else 0.0

    def pace(self) -> float | None:
        """Simulated seconds per wall second over the window, or None while it spans < min_span_s."""
        if self.span_s < self.min_span_s:
            return None
        (w0, v0), (w1, v1) = self._pairs[0], self._pairs[-1]
        return (v1 - v0) / (w1 - w0)


def world_speedup(requested: float, pace: float, floor: float = 0.05) -> float:
    """The built-in vehicle's speed-up under a real OAI pair: the requested one, but never faster
    than rfsim keeps (a range then changes no faster per second of gNB air time than the vehicle
    flies), rounded down to 0.05; SimulatorError when rfsim crawls below `floor`."""
    if not (math.isfinite(pace) and pace >= floor):
        raise SimulatorError(f"rfsim runs at {pace:.3g} × real time, below {floor:g}: the machine cannot carry "
                             "a real OAI gNB and nrUE in the loop now")
    return max(floor, math.floor(min(requested, pace) * 20.0) / 20.0)
