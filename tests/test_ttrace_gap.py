"""A dropped T connection (issue 50): the TA commands the gNB sent meanwhile are missed. Replayed
from OAI 2025.w36's ramp recording (../shared/data/oai-2025.w36-ttrace/dora_ramp_0_300: 0 → 300 m
in 26 steps, 8 TA commands applied) with a window of events cut out: the tracker told of the gap
re-bases the UE's TA by the steps its SRS peak proves were missed, and gives no range when the
peak cannot tell."""

from __future__ import annotations

import functools
import gzip
from pathlib import Path

import pytest

from mission.gnb.trace_rtt import TraceRtt, TraceRttTracker, TraceSettings
from mission.gnb.ttrace import iter_recording

RUN = "oai-2025.w36-ttrace/dora_ramp_0_300"


@functools.cache
def _events(path: Path) -> tuple:
    return tuple(iter_recording(gzip.decompress(path.read_bytes())))


@pytest.fixture
def events(shared_data: Path) -> tuple:
    return _events(shared_data / RUN / "rec.raw.gz")


def _replay(events, cut_s: tuple[float, float] | None = None, told: bool = True):
    """(tracker, {(frame, slot, t_wall_s): TraceRtt}) of the recording, the events stamped within
    cut_s (wall seconds from its first event) dropped; told: the tracker hears of the gap."""
    tr = TraceRttTracker(TraceSettings())
    t0 = events[0].t_wall_s
    out: dict[tuple, TraceRtt] = {}
    in_gap = False
    for ev in events:
        dt = ev.t_wall_s - t0
        if cut_s is not None and cut_s[0] <= dt < cut_s[1]:
            in_gap = True
            continue
        if in_gap:
            in_gap = False
            if told:
                tr.connection_gap()
        r = tr.feed(ev)
        if r is not None:
            out[(r.frame, r.slot, r.t_wall_s)] = r
    return tr, out


def _after(out: dict, events, t_s: float) -> list[TraceRtt]:
    return [r for k, r in out.items() if k[2] - events[0].t_wall_s >= t_s]


def test_a_short_gap_that_hid_an_applied_ta_command_is_re_based(events):
    """The command at 7.57 s (TA 1 -> 2) falls in a 0.3 s cut: the peak's step proves it."""
    _, full = _replay(events)
    tr, cut = _replay(events, (7.45, 7.75))
    (g,) = tr.drain_gaps()
    assert g.proven and g.missed_steps == 1 and "+1 TA step" in g.message, g
    after = _after(cut, events, 7.75)
    assert len(after) > 1000
    # every range after the gap is the uncut replay's own
    assert all(r.rtt_samples == full[k].rtt_samples for k, r in cut.items() if k in full)
    assert set(cut) <= set(full) and round(after[-1].rtt_samples) == 92


def test_a_short_gap_without_a_command_is_proven_consistent(events):
    _, full = _replay(events)
    tr, cut = _replay(events, (10.0, 10.3))
    (g,) = tr.drain_gaps()
    assert g.proven and g.missed_steps == 0 and "no TA command was missed" in g.message
    assert abs(g.moved_samples) < 1.0 and g.budget_samples < 6.0
    assert all(r.rtt_samples == full[k].rtt_samples for k, r in cut.items() if k in full)
    assert tr.counts.gaps == tr.counts.gap_proven == 1


def test_untold_the_missed_command_makes_every_later_range_a_step_short(events):
    """What the tracker did before it was told of gaps: TA 1 kept, ranges 12 samples (39 m) short."""
    _, full = _replay(events)
    _, cut = _replay(events, (7.45, 7.75), told=False)
    wrong = [full[k].rtt_samples - r.rtt_samples for k, r in cut.items() if k in full and k[2] - events[0].t_wall_s > 9]
    assert wrong and set(wrong) == {12.0}


def test_a_gap_too_long_for_the_peak_to_tell_gives_no_range(events):
    """A 2 s cut (6 s of air time here: rfsim ran 3 × real time): the round trip may have moved more
    than half a TA step, so the TA is unknown and the UE gives no range (until it re-attaches)."""
    tr, cut = _replay(events, (7.0, 9.0))
    (g,) = tr.drain_gaps()
    assert not g.proven and g.budget_samples >= 6.0 and "unknown" in g.message
    assert _after(cut, events, 9.0) == []
    (ue,) = tr.ues()
    assert tr.latest(ue) is None and "absolute TA is unknown" in tr.why_none(ue)
    assert tr.counts.gap_lost == 1


def test_the_adapter_says_what_each_ues_first_srs_after_a_reconnect_proved():
    """OaiGnbClient in trace mode against the simulated gNB's T server through the cuttable relay of
    `sim --oai` (sitl_scenarios.oai.t_relay): cut, reconnects refused for 0.2 s, the client comes
    back, and each UE's TA is proven (no command missed) with its range still within a sample."""
    import asyncio
    import contextlib

    from mission.gnb import GnbConfig, OaiGnbClient
    from sitl_scenarios.gnb import SimulatedGnb, static_position
    from sitl_scenarios.oai.t_relay import TRelay
    from tests.test_gnb_trace import UAV_ENU_M, _scenario, _true_range_m
    from uavloc.errors import GnbNoMeasurementError

    sc = _scenario()
    one_sample_m = 299_792_458.0 / (2 * sc.radio.fs_hz)

    async def measured(client) -> dict:
        out: dict = {}
        for _ in range(100):
            await asyncio.sleep(0.05)
            for r in (0x4601, 0x4602, 0x4603):
                with contextlib.suppress(GnbNoMeasurementError):
                    out[r] = await client.measure(r)
            if len(out) == 3:
                return out
        return out

    async def main():
        async with SimulatedGnb(sc, static_position(UAV_ENU_M), port=0, t_port=0) as gnb, \
                TRelay(gnb.t_port) as relay:
            cfg = GnbConfig.of(sc.mission.gnb, "127.0.0.1", gnb.port, transport="telnet", mode="trace",
                               t_port=relay.port, backoff_initial_s=0.01, backoff_max_s=0.1)
            async with OaiGnbClient(cfg) as client:
                assert len(await measured(client)) == 3
                relay.cut(0.2)
                gaps: list = []
                for _ in range(100):
                    await asyncio.sleep(0.05)
                    gaps += client.trace_gaps()
                    if len(gaps) == 3:
                        break
                return client.tracer.reconnects, gaps, await measured(client), relay.connections

    reconnects, gaps, after, connections = asyncio.run(main())
    assert reconnects == 1 and connections == 2 and sorted(g.rnti for g in gaps) == [0x4601, 0x4602, 0x4603]
    assert all(g.proven and g.missed_steps == 0 and g.gap_s < 1.0 for g in gaps), gaps
    assert len(after) == 3
    for k in range(3):
        assert abs(after[0x4601 + k].range_m - _true_range_m(sc, k)) <= one_sample_m
