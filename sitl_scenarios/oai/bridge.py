"""The bridge between the simulated world and a real OAI pair's rfsim channel (docs/oai-in-the-loop.md).

Every `period_s` the bridge asks the world for the built-in vehicle's TRUE position p (the world
process knows it), and for each user u at position x_u sets that UE's rfsim channel so that its
round trip follows

    2 d_u = 2 ‖p − x_u‖,   target offset k* = round(2 d_u · fs / c)   [whole samples]

all of it on the nrUE's downlink (`rfsimu setdistance rfsimu_channel_enB0 <m>` on the nrUE's own
telnet; the gNB's uplink stays at 0, so the gNB's telnet stays free for uavloc's discovery). An
offset set on one side alone is the whole round trip (tests/test_oai_live_trace.py). Each setting
moves the offset at most `max_step` samples (1: a sample is 6.506 m of round trip, 3.253 m of
range at 46.08 Msps; jumps of many samples crashed a gNB); a 10 Hz bridge keeps up with a range
changing 32 m/s. Every setting is handed to `sink` as a :class:`ChannelSetting` (the mission log's
`channel` record). Every `pace_every_s` it reads rfsim's virtual time on every UE (`rfsimu vtime`;
each gNB + nrUE pair is an rfsim of its own) into a :class:`PaceMeter` each; the pace is the
slowest.

:func:`plan_offsets` is the pure part (tested everywhere); :class:`ChannelBridge` is the loop, an
async context manager owning its task.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass

import numpy as np

from sitl_scenarios.oai.channel import (
    PaceMeter,
    metres_for_offset,
    next_offset,
    offset_for_round_trip,
    sample_m,
)
from uavloc.errors import SimulatorError

log = logging.getLogger(__name__)


#: rfsim slower than this fraction of the world's speed-up is said (a warning)
SLOW_FRACTION = 0.8


@dataclass(frozen=True)
class ChannelSetting:
    """One rfsim distance the bridge set: when (monotonic and UNIX [s]), for which user, the offset
    OAI set [samples of round trip], the fs it counts at [Hz], the true distance it followed [m],
    rfsim's pace then, and what it added beyond the distance [m, one way]: the NLoS excess path and
    a UE clock sawtooth (channel_excess)."""

    t_mono_s: float
    t_wall_s: float
    user: str
    offset: int
    fs_hz: float
    true_range_m: float
    pace: float | None = None
    #: what the channel carries on top of the distance [m, one way] (NLoS excess, clock sawtooth)
    excess_m: float = 0.0

    @property
    def round_trip_m(self) -> float:
        return self.offset * sample_m(self.fs_hz)

    @property
    def range_m(self) -> float:
        """The one-way range this channel gives: half the round trip."""
        return 0.5 * self.round_trip_m

    def record(self) -> dict:
        """The fields of the mission log's `channel` record (mission.channel)."""
        out = {"user": self.user, "offset": self.offset, "side": "downlink", "fs_hz": self.fs_hz,
               "round_trip_m": round(self.round_trip_m, 4), "range_m": round(self.range_m, 4),
               "true_range_m": round(self.true_range_m, 4), "t_wall": round(self.t_wall_s, 6)}
        if self.pace is not None:
            out["pace"] = round(self.pace, 4)
        if self.excess_m > 0:
            out["excess_m"] = round(self.excess_m, 4)
        return out


def plan_offsets(uav_enu_m: np.ndarray, users_enu_m: np.ndarray, current: Sequence[int], fs_hz: float,
                 max_step: int = 1, excess_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true distances d (K,) [m], target offsets k* (K,), next offsets (K,)) for a UAV at (3,)
    uav_enu_m and K users at (K, 3) users_enu_m, from the (K,) offsets set now; excess_m (K,): a
    one-way excess path (NLoS) each user's round trip carries too: k* = round(2 (d + e) fs / c)."""
    d = np.linalg.norm(np.asarray(users_enu_m, float).reshape(-1, 3) - np.asarray(uav_enu_m, float).reshape(1, 3),
                       axis=1)
    e = np.zeros_like(d) if excess_m is None else np.asarray(excess_m, float).reshape(d.shape)
    target = np.array([offset_for_round_trip(2.0 * (x + y), fs_hz) for x, y in zip(d, e, strict=True)], int)
    nxt = np.array([next_offset(int(c), int(t), max_step) for c, t in zip(current, target, strict=True)], int)
    return d, target, nxt


class HeldNlosExcess:
    """The NLoS excess path of each user's channel [m, one way], as the simulated gNB's radio truth
    has it (sitl_scenarios.radio: e ~ Exp(mean) while the line of sight from the UAV to the user
    is blocked by a building, 0 in LoS), but held: one draw per blocked episode (a channel that
    jumped every setting would be a noise the bridge cannot walk). Seeded."""

    def __init__(self, users_enu_m: np.ndarray, buildings: Sequence, mean_m: float, seed: int) -> None:
        self.users_enu_m = np.asarray(users_enu_m, float).reshape(-1, 3)
        self.buildings = list(buildings)
        self.mean_m = float(mean_m)
        self.rng = np.random.default_rng(seed)
        self.held: list[float | None] = [None] * len(self.users_enu_m)

    def __call__(self, uav_enu_m: np.ndarray) -> np.ndarray:
        """(K,) the excess of each user now [m]."""
        from sitl_scenarios.radio import line_of_sight_blocked

        out = np.zeros(len(self.users_enu_m))
        for k, user in enumerate(self.users_enu_m):
            if self.mean_m > 0 and self.buildings and line_of_sight_blocked(uav_enu_m, user, self.buildings):
                if self.held[k] is None:
                    self.held[k] = float(self.rng.exponential(self.mean_m))
                out[k] = self.held[k]
            else:
                self.held[k] = None
        return out


class ClockSawtooth:
    """Each user's UE clock sawtooth on its channel [m, one way], as the simulated gNB's radio truth
    has it (sitl_scenarios.radio.RadioModel.sawtooth_m: saw(t) = A_k · frac(t / P_k + φ_k), a
    commercial UE's 12 m every 15 s), at the world's time t = (now − start) · speedup [s]. The
    phases φ_k are drawn from a generator seeded by `seed`, in user order. A reset (A_k back to 0) is
    walked by the bridge one sample per setting, as any other move."""

    def __init__(self, amplitudes_m: Sequence[float], periods_s: Sequence[float], speedup: float, seed: int,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.amplitudes_m = np.asarray(amplitudes_m, float)
        self.periods_s = np.asarray(periods_s, float)
        self.phases = np.random.default_rng(seed).random(len(self.amplitudes_m))
        self.speedup = float(speedup)
        self.clock = clock
        self.start_s = clock()

    def at(self, t_s: float) -> np.ndarray:
        """(K,) saw(t) of each user at world time t_s [m]."""
        periods = np.where(self.periods_s > 0, self.periods_s, 1.0)
        phase = t_s / periods + self.phases
        return np.where(self.amplitudes_m > 0, self.amplitudes_m * (phase - np.floor(phase)), 0.0)

    def __call__(self) -> np.ndarray:
        """(K,) each user's sawtooth now [m]."""
        return self.at((self.clock() - self.start_s) * self.speedup)


def channel_excess(nlos: Callable[[np.ndarray], np.ndarray] | None,
                   saw: Callable[[], np.ndarray] | None) -> Callable[[np.ndarray], np.ndarray] | None:
    """The bridge's `excess` (K,) [m, one way] at a vehicle position: the NLoS excess path plus the
    UE clock sawtooth, either absent (None: neither)."""
    if nlos is None and saw is None:
        return None

    def excess(uav_enu_m: np.ndarray) -> np.ndarray:
        e = 0.0 if nlos is None else nlos(uav_enu_m)
        return np.asarray(e + (0.0 if saw is None else saw()), float)

    return excess


class ChannelBridge:
    """See the module docstring. ues: one object per user with `set_distance(metres) -> offset` and
    `vtime_s()` (sitl_scenarios.oai.pair.UeTelnet); user_ids, users_enu_m (K, 3): the users in the
    world's frame; position: the vehicle's true position (3,) in that frame, awaited (None while
    unknown: an external autopilot before its first report)."""

    def __init__(self, ues: Sequence, user_ids: Sequence[str], users_enu_m: np.ndarray,
                 position: Callable[[], Awaitable[np.ndarray | None]], fs_hz: float, *, period_s: float = 0.1,
                 max_step: int = 1, pace_every_s: float = 1.0, sink: Callable[[ChannelSetting], None] | None = None,
                 world_speedup: float | None = None, walk_first: bool = True,
                 excess: Callable[[np.ndarray], np.ndarray] | None = None,
                 clock: Callable[[], float] = time.monotonic, wall: Callable[[], float] = time.time) -> None:
        self.ues = list(ues)
        self.user_ids = list(user_ids)
        self.users_enu_m = np.asarray(users_enu_m, float).reshape(-1, 3)
        self.position = position
        self.fs_hz = float(fs_hz)
        self.period_s = period_s
        self.max_step = max_step
        self.pace_every_s = pace_every_s
        self.sink = sink
        #: the world's speed-up: rfsim falling below it (SLOW_FRACTION of it) is said, once a minute
        self.world_speedup = world_speedup
        #: walk the channels out before entering returns (False: the loop does, as soon as the
        #: position is known: an autopilot reports it only once the mission connected)
        self.walk_first = walk_first
        #: each user's one-way excess now (channel_excess: NLoS path, clock sawtooth), or None
        self.excess = excess
        self._slow_said_s = -float("inf")
        self.clock = clock
        self.wall = wall
        #: the offset set on each UE's downlink now [samples] (each UE attaches at 0)
        self.offsets = [0] * len(self.ues)
        self.settings: list[ChannelSetting] = []
        #: rfsim's pace on each UE's link (one rfsim per gNB + nrUE pair)
        self.paces = [PaceMeter() for _ in self.ues]
        #: the largest gap between a channel and its target while following (after the walk-out) [samples]
        self.lag_max = 0
        self._following = False
        self._task: asyncio.Task | None = None
        self._last_pace_s = -float("inf")

    async def step(self) -> bool:
        """One round: every UE's channel one step toward its target; True when all are there."""
        got = await self.position()
        if got is None or not np.all(np.isfinite(got)):
            return False  # an autopilot that has not reported its position yet
        pos = np.asarray(got, float).reshape(3)
        e = None if self.excess is None else self.excess(pos)
        d, target, nxt = plan_offsets(pos, self.users_enu_m, self.offsets, self.fs_hz, self.max_step, e)
        for i, ue in enumerate(self.ues):
            if self._following:
                self.lag_max = max(self.lag_max, abs(int(target[i]) - int(nxt[i])))
            if nxt[i] == self.offsets[i]:
                continue
            set_k = await ue.set_distance(metres_for_offset(int(nxt[i]), self.fs_hz))
            if set_k != nxt[i]:
                raise SimulatorError(f"OAI set offset {set_k} on UE {self.user_ids[i]}'s downlink, not {nxt[i]}")
            self.offsets[i] = set_k
            s = ChannelSetting(self.clock(), self.wall(), self.user_ids[i], set_k, self.fs_hz, float(d[i]),
                               self.pace(), 0.0 if e is None else float(e[i]))
            self.settings.append(s)
            if self.sink is not None:
                self.sink(s)
        return bool(np.all(np.asarray(self.offsets) == target))

    def pace(self) -> float | None:
        """The slowest rfsim's pace over the meters' window (None until measured)."""
        got = [p for p in (m.pace() for m in self.paces) if p is not None]
        return min(got) if got else None

    async def measure_pace(self) -> float | None:
        """Read rfsim's virtual time on every UE into its pace meter; the slowest pace so far."""
        for meter, ue in zip(self.paces, self.ues, strict=True):
            meter.add(self.wall(), await ue.vtime_s())
        self._last_pace_s = now = self.clock()
        pace = self.pace()
        if (pace is not None and self.world_speedup is not None and pace < SLOW_FRACTION * self.world_speedup
                and now - self._slow_said_s >= 60.0):
            self._slow_said_s = now
            log.warning("rfsim now runs at %.2f × real time, slower than the world's %g ×: the gNB sees the vehicle "
                        "move %.1f × faster per second of its air time", pace, self.world_speedup,
                        self.world_speedup / pace)
        return pace

    async def walk_out(self, timeout_s: float = 120.0) -> None:
        """Step until every channel is at its target (the UEs attached at 0)."""
        deadline = self.clock() + timeout_s
        while not await self.step():
            if self.clock() > deadline:
                raise SimulatorError(f"the rfsim channel did not reach the vehicle's distance within {timeout_s:g} s")
            await asyncio.sleep(self.period_s)

    async def _run(self) -> None:
        while True:
            t0 = self.clock()
            if await self.step():
                self._following = True
            if self.clock() - self._last_pace_s >= self.pace_every_s:
                await self.measure_pace()
            await asyncio.sleep(max(0.0, self.period_s - (self.clock() - t0)))

    async def __aenter__(self) -> ChannelBridge:
        if self.walk_first:
            await self.walk_out()
        self._following = self.walk_first  # else: the loop walks out first, the lag counts after
        self._task = asyncio.create_task(self._run(), name="uavloc-oai-bridge")
        self._task.add_done_callback(self._ended)
        return self

    def _ended(self, task: asyncio.Task) -> None:
        if not task.cancelled() and task.exception() is not None:
            log.error("the rfsim bridge stopped: the channel no longer follows the vehicle (%s)", task.exception())

    async def __aexit__(self, *exc: object) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            # an error of the loop was logged when it ended (_ended); the mission's end is not its
            await asyncio.gather(task, return_exceptions=True)
            log.info("rfsim bridge: %d settings, largest lag %d sample(s)", len(self.settings), self.lag_max)

    def failed(self) -> BaseException | None:
        """The loop's error when it ended on one (an nrUE gone, OAI refusing an offset)."""
        task = self._task
        if task is not None and task.done() and not task.cancelled():
            return task.exception()
        return None
