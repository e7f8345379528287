"""A real OAI gNB and nrUE in the loop of `uavloc sim --oai` (docs/oai-in-the-loop.md).

:class:`OaiInTheLoop` is what :class:`sitl_scenarios.sim_runner.SimulatedMission` enters before the
world when it is given an OAI build, in this order (each step needs the one before):

1. the gNB (sitl_scenarios.oai.pair.OaiPair.start_gnb), its confs written, its T server on a free port;
2. uavloc's gNB adapter in trace mode, whose T client connects on entering (a UE attached before it
   has no absolute TA in the trace); or, on a build patched with patches/oai-2025.w36, in rtt mode
   (each range a `rtt pdcch_order`: the gNB loads the telnet module rtt, the nrUE hears the order);
3. the nrUE at rfsim offset 0 (in `--do-ra` mode a UE started 57 samples or more away did not
   attach), its C-RNTI read from the gNB's log: the scenario's users get those RNTIs;
4. rfsim's pace (`rfsimu vtime` on the nrUE over PACE_PROBE_S wall seconds): the world runs at
   `min(--speedup, pace)` (sitl_scenarios.oai.channel.world_speedup);
5. (after the world started) the bridge (sitl_scenarios.oai.bridge), which walks each channel out to
   the vehicle's true distance one sample at a time and then follows it.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

import numpy as np

from sitl_scenarios.oai.bridge import ChannelBridge, ChannelSetting, ClockSawtooth, HeldNlosExcess, channel_excess
from sitl_scenarios.oai.channel import PaceMeter, world_speedup
from sitl_scenarios.oai.conf import build_missing, check_scenario, rtt_missing
from sitl_scenarios.oai.group import GnbGroup
from sitl_scenarios.oai.pair import AttachLost, OaiPair, UeTelnet
from sitl_scenarios.scenario import Scenario
from uavloc.errors import ScenarioError, SimulatorError

log = logging.getLogger(__name__)

#: how long rfsim's pace is measured before the world starts [wall s]
PACE_PROBE_S = 4.0
#: how many times the gNB and nrUE are started when the gNB drops its pre-configured UE
ATTACH_ATTEMPTS = 3


def scenario_with_rntis(scenario: Scenario, rntis: list[int]) -> Scenario:
    """The scenario whose users (in order) have the C-RNTIs the real gNB gave them."""
    users = tuple(dataclasses.replace(u, rnti=int(r)) for u, r in zip(scenario.mission.users, rntis, strict=True))
    return dataclasses.replace(scenario, mission=dataclasses.replace(scenario.mission, users=users))


class OaiInTheLoop:
    """See the module docstring. build: the OAI build folder; run_dir: where the confs and OAI's
    logs go; scenario: the scenario (refused unless OAI can fly it: conf.check_scenario); rtt: the
    adapter measures in rtt mode (ScenarioError naming the patch's README when the build is not
    patched: conf.rtt_missing)."""

    def __init__(self, build: str | Path, run_dir: Path, scenario: Scenario, rtt: bool = False) -> None:
        self.build = Path(build).expanduser()
        why = build_missing(self.build)
        if why is not None:
            raise SimulatorError(why)
        check_scenario(scenario)
        if rtt and (why := rtt_missing(self.build)) is not None:
            raise ScenarioError(why)
        self.rtt = rtt
        self.scenario = scenario
        self.run_dir = Path(run_dir)
        n = len(scenario.users)
        #: one gNB + nrUE pair per user (--do-ra takes one UE per gNB); one user's in run_dir itself
        self.pairs = [OaiPair(self.build, self.run_dir if n == 1 else self.run_dir / f"user{k + 1}", rtt=rtt)
                      for k in range(n)]
        self.ues: list[UeTelnet] = []
        self.rntis: list[int] = []
        self.pace_at_start: float | None = None
        self.bridge: ChannelBridge | None = None

    @property
    def pair(self) -> OaiPair:
        """The first user's pair."""
        return self.pairs[0]

    async def start_radio(self, stack: contextlib.AsyncExitStack,
                          make_client: Callable[[int, int], contextlib.AbstractAsyncContextManager]) -> object:
        """Steps 1–4; the gNB adapter entered (returned; with several users a GnbGroup of one adapter
        per pair). make_client(telnet port, T port): uavloc's gNB adapter, not entered (entering
        connects its T client). The adapters close, then the pairs, when `stack` unwinds."""
        stack.callback(lambda: [p.close() for p in self.pairs])
        clients = []
        for k in range(len(self.pairs)):
            client, ue_port = await self._attach(stack, k, make_client)
            clients.append(client)
            self.ues.append(await stack.enter_async_context(UeTelnet(ue_port)))
        meters = [PaceMeter(min_span_s=0.5 * PACE_PROBE_S) for _ in self.ues]
        t_end = time.monotonic() + PACE_PROBE_S
        while True:
            for meter, ue in zip(meters, self.ues, strict=True):
                meter.add(time.time(), await ue.vtime_s())
            if time.monotonic() >= t_end:
                break
            await asyncio.sleep(0.5)
        paces = [m.pace() for m in meters]
        if any(p is None for p in paces):
            raise SimulatorError("rfsim's pace could not be measured (rfsimu vtime gave no span)")
        self.pace_at_start = min(paces)  # the world follows the slowest rfsim
        log.info("rfsim runs at %s × real time", ", ".join(f"{p:.2f}" for p in paces))
        if len(clients) == 1:
            return clients[0]
        return GnbGroup(clients, self.rntis)

    async def _attach(self, stack: contextlib.AsyncExitStack, k: int, make_client) -> tuple[object, int]:
        """User k's pair: its gNB, its adapter (entered in `stack`), its nrUE attached; (adapter, the
        nrUE's telnet port). A gNB that dropped its one pre-configured UE before the attach
        (AttachLost: a loaded machine's MAC missed the RA window) is started again with the adapter
        and the UE, at most ATTACH_ATTEMPTS times in all, each in a folder of its own (`attempt2/`)."""
        for attempt in range(1, ATTACH_ATTEMPTS + 1):
            pair = self.pairs[k]
            client_stack = contextlib.AsyncExitStack()
            try:
                pair.spawn_gnb()  # from the loop's thread, which outlives it (PR_SET_PDEATHSIG)
                await asyncio.to_thread(pair.wait_gnb)
                ports = pair.ports
                client = await client_stack.enter_async_context(make_client(ports.gnb_telnet, ports.t))
                pair.start_ue(0)
                rnti = await pair.wait_attached(set())
            except AttachLost as exc:
                await client_stack.aclose()
                pair.close()
                if attempt == ATTACH_ATTEMPTS:
                    raise SimulatorError(f"{exc}, {attempt} times: this machine is too loaded for OAI's no-core "
                                         "mode now") from None
                log.warning("%s: starting the OAI gNB and nrUE again (attempt %d of %d)", exc, attempt + 1,
                            ATTACH_ATTEMPTS)
                self.pairs[k] = OaiPair(self.build, pair.run_dir / f"attempt{attempt + 1}", rtt=self.rtt)
                continue
            except BaseException:
                await client_stack.aclose()
                raise
            stack.push_async_callback(client_stack.aclose)
            break
        if rnti in self.rntis:  # the gNBs draw C-RNTIs independently
            raise SimulatorError(f"two OAI gNBs gave their UEs the same C-RNTI {rnti:04x}: run again")
        self.rntis.append(rnti)
        log.info("OAI nrUE of %s attached as C-RNTI %04x at rfsim offset 0", self.scenario.users[k].id, rnti)
        return client, ports.ue_telnet[0]

    def speedup(self, requested: float) -> float:
        """The world's speed-up: never faster than rfsim (channel.world_speedup)."""
        assert self.pace_at_start is not None
        return world_speedup(requested, self.pace_at_start)

    async def start_bridge(self, stack: contextlib.AsyncExitStack, position: Callable[[], Awaitable[np.ndarray | None]],
                           sink: Callable[[ChannelSetting], None], speedup: float,
                           walk_first: bool = True, seed: int = 0) -> ChannelBridge:
        """Step 5: the bridge, walked out to the vehicle's distance (walk_first; else as soon as the
        position is known), running until `stack` unwinds (it says when rfsim falls behind the
        world's `speedup`); behind the scenario's buildings the channel carries an NLoS excess
        path (HeldNlosExcess, seeded by `seed`), and a user with a UE clock sawtooth (a commercial UE)
        carries it (ClockSawtooth, at the world's time), both added to the one-way distance."""
        users = np.array([[u.east_m, u.north_m, u.up_m] for u in self.scenario.users], float)
        sc = self.scenario
        nlos = (HeldNlosExcess(users, sc.buildings, sc.radio.nlos_excess_mean_m, seed)
                if sc.buildings and sc.radio.nlos_excess_mean_m > 0 else None)
        amps = [float(u.sawtooth_amplitude_m) for u in sc.users]
        saw = (ClockSawtooth(amps, [float(u.sawtooth_period_s) for u in sc.users], speedup, seed + 1)
               if any(a > 0 for a in amps) else None)
        excess = channel_excess(nlos, saw)
        self.bridge = ChannelBridge(self.ues, [u.id for u in sc.users], users, position, sc.radio.fs_hz, sink=sink,
                                    world_speedup=speedup, walk_first=walk_first, excess=excess)
        return await stack.enter_async_context(self.bridge)

    def header(self, speedup: float) -> dict:
        """The log header's `oai` section: the gNB is a real OAI (its version, binaries, command
        lines: each pair's), the run folder, how many gNB + nrUE pairs, the UEs' RNTIs, rfsim's pace
        at the start (the slowest pair's), the world's speed-up, and whether the gNB serves the
        patch's PDCCH order (`rtt_order`: the rtt mode)."""
        return {"real_gnb": True, **self.pair.version(), "rtt_order": self.rtt, "run_dir": str(self.run_dir),
                "pairs": len(self.pairs),
                "command_lines": [" ".join(c) for p in self.pairs for c in p.command_lines],
                "rntis": [f"{r:04x}" for r in self.rntis], "channel": "nrUE downlink (rfsimu_channel_enB0) = 2 d",
                "pace_at_start": round(float(self.pace_at_start or 0.0), 4), "speedup": speedup}

