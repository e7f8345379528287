"""The trace mode's PDCCH order for a UE the T trace has no absolute TA of (mission.gnb.trace_order):
when it is sent, how often, and the check of the trace's first range against the order's answer."""

from __future__ import annotations

import pytest

from mission.gnb.trace_order import ORDER_SPACING_S, ORDER_TRIES, TraceOrders


def orders() -> TraceOrders:
    return TraceOrders(tolerance_m=5.0, max_rate_mps=30.0)


def test_only_a_ue_without_an_absolute_ta_is_ordered_spaced_and_at_most_tries_times():
    o = orders()
    assert not o.wanted(0x4601, unknown=False, now_s=0.0)
    assert o.wanted(0x4601, unknown=True, now_s=0.0) and o.status(0x4601) == ""
    t = 0.0
    for n in range(ORDER_TRIES):
        assert o.wanted(0x4601, True, t)
        o.sending(0x4601, t)
        o.failed(0x4601, "error rnti 4601 timeout after 1000 ms: no preamble")
        assert not o.wanted(0x4601, True, t + ORDER_SPACING_S - 0.01), n
        t += ORDER_SPACING_S
    assert not o.wanted(0x4601, True, t + 100.0)
    assert o.wanted(0xB0B2, True, t)  # another UE has tries of its own
    events = o.drain()
    assert [e.what for e in events] == ["failed"] * ORDER_TRIES and o.drain() == []
    assert "timeout after 1000 ms" in events[0].message and events[0].fields() == {"rnti": "4601", "order": "failed"}


def test_a_stock_gnb_is_never_asked_again():
    o = orders()
    o.sending(0x4601, 0.0)
    o.not_served("`rtt pdcch_order` is not a softmodem command")
    assert not o.wanted(0x4601, True, 100.0) and not o.wanted(0xB0B2, True, 100.0)
    assert "no PDCCH order command" in o.status(0xB0B2)


@pytest.mark.parametrize(("trace_m", "dt_s", "ok"), [
    (97.59, 1.0, True),            # the same range
    (97.59 + 34.0, 1.0, True),     # 5 m + 30 m/s · 1 s
    (97.59 + 36.0, 1.0, False),    # beyond it
    (97.59 + 39.03, 0.4, False),   # one TA step too many: the UE did not apply the RAR's TA
])
def test_the_traces_first_range_after_the_order_is_checked_against_its_answer(trace_m, dt_s, ok):
    o = orders()
    o.sending(0x4601, 10.0)
    o.answered(0x4601, 97.59, 10.2)
    assert not o.wanted(0x4601, unknown=False, now_s=20.0)
    assert o.check(0x4601, 50.0, 10.1) is not None  # stamped before the order: withheld
    why = o.check(0x4601, trace_m, 10.2 + dt_s)
    assert (why is None) is ok
    events = o.drain()
    assert [e.what for e in events] == ["ordered", "agree" if ok else "disagree"]
    assert events[0].fields() == {"rnti": "4601", "order": "ordered", "order_range_m": 97.59}
    if ok:
        assert o.check(0x4601, trace_m + 100.0, 30.0) is None  # checked once; the tracker's gates follow
    else:
        assert "did not apply the RAR's TA" in why
        assert o.check(0x4601, trace_m, 12.0) is not None  # withheld until a new order agrees
        assert o.wanted(0x4601, unknown=False, now_s=10.0 + ORDER_SPACING_S)
        o.sending(0x4601, 15.0)
        o.answered(0x4601, 97.59, 15.2)
        assert o.check(0x4601, 97.59, 16.0) is None


def test_a_ue_whose_ta_a_t_gap_made_unknown_is_ordered_like_one_that_attached_early():
    """After a T connection gap the continuity check cannot prove (mission.gnb.trace_rtt), the UE
    has no absolute TA: on a patched gNB an ordered access gives it again, as for a UE that attached
    before the trace began; a UE whose TA is known is not ordered."""
    from mission.gnb.trace_rtt import TraceRttTracker, _Ue

    tr = TraceRttTracker()
    tr.unknown_rntis.add(0x4601)
    tr._ues[0x4602] = _Ue(ta=3, rar_t_air_s=0.0)
    assert tr.without_absolute_ta(0x4601) and not tr.without_absolute_ta(0x4602)
    tr._ues[0x4602].lost = "in 7.28 s its round trip may have moved ±29.6 samples"
    assert tr.without_absolute_ta(0x4602)
    assert not tr.without_absolute_ta(0x4603)  # never seen: nothing to order
