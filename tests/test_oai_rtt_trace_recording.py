"""A T recording of the real OAI gNB patched with patches/oai-2025.w36 (`rtt pdcch_order`), replayed
through uavloc's trace decoding (never skipped): the UE attached before the recording began, then
nine PDCCH orders at 45.5, 71.6 and 97.6 m of rfsim distance (tests/data/README.md says how it
was made).

- the SRS of that UE before the first order gives no range: its random access is not in the trace;
- every ordered access is on the trace (PRACH, then a RAR whose 12-bit TA is the preamble's delay,
  an absolute TA within half a TA step of the rfsim round trip), and the tracker restarts the UE
  from it;
- the ranges after every order are the rfsim distance within one sample (3.253 m), also after
  the first order at 71.6 m, where the nrUE did not apply the RAR's TA 2 (its log: received; its
  SRS peak stayed at +22, the whole round trip, until a MAC TA command 33 moved it to −2): the
  tracker sees that from the peak and takes TA 0 (taking the RAR's TA as applied ranged it 24
  samples, 78.1 m, too far).
"""

from __future__ import annotations

import gzip
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

from estimator.ranging import one_way_m_per_sample
from mission.gnb.trace_rtt import TraceRtt, TraceRttTracker
from mission.gnb.ttrace import EV_PRACH, EV_RAR, EV_SRS_CHEST, TEvent, iter_recording, rar_grants

DATA = Path(__file__).parent / "data" / "oai-2025.w36-rtt"
REC = DATA / "orders_7_11_15.rec.raw.gz"
TELNET = DATA / "orders_7_11_15.telnet.txt"
FS_HZ = 46.08e6
#: one round-trip sample, one way [m]
SAMPLE_M = one_way_m_per_sample(FS_HZ)
#: TA step at μ = 1 [samples at fs] (N_FFT / 128)
TA_STEP_SAMPLES = 12
#: the order after which the nrUE did not apply the RAR's TA (0-based), see the module docstring
NOT_APPLIED = 3


@dataclass
class Order:
    """One `rtt pdcch_order` of the session: when it was sent [UNIX s], the distance the gNB's
    rfsimulator had been set to [m] and its offset [samples, one way]."""

    t_s: float
    distance_m: float
    offset: int


@dataclass
class Access:
    """What the trace shows of one ordered access: the PRACH's delay, the RAR's TA and the ranges
    the tracker gave until the next access or distance change [m]."""

    prach_delay: int
    rar_ta: int
    rtts: list[TraceRtt]

    def ranges_m(self) -> list[float]:
        return [r.rtt_samples * SAMPLE_M for r in self.rtts]


def _session() -> tuple[str, list[Order], list[float]]:
    """(RNTI, the orders, the times of the gNB-side distance changes) of the telnet log."""
    text = TELNET.read_text()
    rnti = re.search(r"attached rnti ([0-9a-f]{4})", text).group(1)
    orders, changes = [], []
    dist, offset = 0.0, 0
    for line in text.splitlines():
        t_s = float(line.split()[0])
        if " gnb > rfsimu setdistance" in line:
            m = re.search(r"new_offset (\d+), new \(exact\) distance ([0-9.]+) m", line)
            offset, dist = int(m.group(1)), float(m.group(2))
            changes.append(t_s)
        elif f" gnb > rtt pdcch_order {rnti}" in line:
            assert f"rnti {rnti} ta " in line, line  # every order was answered
            orders.append(Order(t_s, dist, offset))
    return rnti, orders, changes


def _replay() -> tuple[TraceRttTracker, list[TEvent], list[Access]]:
    """Feed the whole recording to the tracker; (tracker, the SRS events of the UE before its first
    RAR, one Access per RAR)."""
    rnti = int(_session()[0], 16)
    changes = _session()[2]
    tracker = TraceRttTracker()
    before: list[TEvent] = []
    accesses: list[Access] = []
    delay = None
    for ev in iter_recording(gzip.decompress(REC.read_bytes())):
        got = tracker.feed(ev)
        if ev.name == EV_PRACH:
            delay = int(ev.values["delay"])
        elif ev.name == EV_RAR:
            (grant,) = rar_grants(bytes(ev.values["data"]))
            assert grant.tc_rnti == rnti and delay is not None
            accesses.append(Access(delay, grant.ta, []))
            delay = None
        elif ev.name == EV_SRS_CHEST and int(ev.values["rnti"]) == rnti and not accesses:
            before.append(ev)
            assert got is None and tracker.latest(rnti) is None
        # a range counts for the latest access until the next gNB-side distance change
        if got is not None and accesses and not any(accesses[-1].rtts and
                                                    accesses[-1].rtts[0].t_wall_s < c <= got.t_wall_s
                                                    for c in changes):
            accesses[-1].rtts.append(got)
    return tracker, before, accesses


@pytest.fixture(scope="module")
def replay():
    return _replay()


def test_the_session_is_nine_orders_at_three_distances():
    rnti, orders, _ = _session()
    assert rnti == "fc25"
    assert [(o.offset, round(o.distance_m, 3)) for o in orders] == [(7, 45.541)] * 3 + [(11, 71.565)] * 3 + [
        (15, 97.589)] * 3


def test_the_ues_srs_before_the_first_order_gives_no_range(replay):
    """It attached before the recording: its SRS are there, its random access is not."""
    tracker, before, accesses = replay
    rnti = int(_session()[0], 16)
    assert len(before) >= 20 and accesses and all(int(e.values["rnti"]) == rnti for e in before)
    assert before[-1].t_wall_s < _session()[1][0].t_s + 1.0
    assert tracker.counts.srs_unknown_ue == len(before)


def test_every_order_is_an_ordered_access_with_an_absolute_ta(replay):
    """One PRACH and RAR per order; the RAR's TA is the preamble's delay and within half a TA step of
    the rfsim round trip (2·offset samples)."""
    _, orders, _ = _session()
    _, _, accesses = replay
    assert len(accesses) == len(orders) == 9
    for order, acc in zip(orders, accesses, strict=True):
        assert acc.rar_ta == acc.prach_delay
        assert abs(TA_STEP_SAMPLES * acc.rar_ta - 2 * order.offset) <= TA_STEP_SAMPLES / 2, (order, acc.rar_ta)
    assert [a.rar_ta for a in accesses] == [1, 1, 1, 2, 2, 2, 3, 3, 3]


def test_the_ranges_after_each_order_are_the_rfsim_distance_to_one_sample(replay):
    _, orders, _ = _session()
    _, _, accesses = replay
    for i, (order, acc) in enumerate(zip(orders, accesses, strict=True)):
        ranges = acc.ranges_m()
        assert len(ranges) >= 3, (i, order)
        assert all(abs(r - order.distance_m) <= SAMPLE_M for r in ranges), (i, order.distance_m, ranges)
        # the first range rests on the RAR's absolute TA (on none where the UE did not apply it)
        assert acc.rtts[0].ta == (0 if i == NOT_APPLIED else acc.rar_ta), i


def test_the_order_whose_rar_ta_the_nrue_did_not_apply_is_seen_from_the_srs_peak(replay):
    """That order's ranges: the SRS peak +22 samples (the whole round trip) on TA 0, then −2 on TA 2
    once the gNB's TA command 33 was applied; the only access of the nine taken as not applied."""
    tracker, _, accesses = replay
    acc = accesses[NOT_APPLIED]
    assert acc.rar_ta == 2
    assert {(r.ta, round(r.peak)) for r in acc.rtts} == {(0, 22), (2, -2)}
    assert tracker.counts.rar_ta_not_applied == 1
