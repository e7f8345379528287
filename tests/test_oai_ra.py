"""Random-access attribution (mission.gnb.oai_ra) on constructed logs: interleaved UEs, ambiguous MAC CEs,
reestablishments, expiry, malformed lines, and a fuzz (only GnbProtocolError ever escapes)."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mission.gnb.log_follower import StockLog
from mission.gnb.oai_ra import RandomAccess, RaTracker, RntiChange, parse_prach_line, parse_stamp
from sitl_scenarios.gnb.ra import OaiRaLog
from uavloc.errors import GnbProtocolError


def prach(t, frame, preamble, delay):
    return (f"{t:.6f} [NR_PHY] A [RAPROC] {frame}.19 Initiating RA procedure with preamble {preamble}, energy 44.5 dB "
            f"(I0 0, thres 200), delay {delay} start symbol 8 freq index 0")


def init(t, frame, tc):
    return f"{t:.6f} [NR_MAC] A {frame}.19 UE RA-RNTI 010b TC-RNTI {tc:04x}: initiating RA procedure"


def msg2(t, frame, tc, preamble, ta):
    return (f"{t:.6f} [NR_MAC] A UE {tc:04x}: {frame + 1}.10 Generating RA-Msg2 DCI, RA RNTI 0x10b, state 1, "
            f"preamble_index(RAPID) {preamble}, timing_offset = {ta} (estimated distance {ta * 39.1:.1f} [m])")


def ce(t, old):
    return f"{t:.6f} [NR_MAC] A Received a MAC CE for C-RNTI with {old:04x}"


def create(t, tc):
    return (f"{t:.6f} [NR_RRC] A [--] (cellID 0, UE ID 1 RNTI {tc:04x}) Create UE context: CU UE ID 1 DU UE ID 1 "
            f"(rnti: {tc:04x}, random ue id 1)")


def reestab(t, tc, old):
    return f"{t:.6f} [NR_RRC] I Reestablishment RNTI {tc:04x} req C-RNTI {old:04x} physCellId 0 cause otherFailure"


T0 = 1_796_145_000.0


def ras(events):
    return [(e.kind, e.ue_rnti, e.tc_rnti, e.timing_offset, e.prach_delay)
            for e in events if isinstance(e, RandomAccess)]


def test_two_ues_in_the_same_slot_are_told_apart_by_preamble_and_tc_rnti():
    lines = [prach(T0, 10, 5, 3), prach(T0, 10, 40, 9), init(T0, 10, 0x1111), init(T0, 10, 0x2222),
             msg2(T0 + 0.001, 10, 0x2222, 40, 9), msg2(T0 + 0.001, 10, 0x1111, 5, 3),
             create(T0 + 0.01, 0x2222), create(T0 + 0.01, 0x1111)]
    assert ras(RaTracker().feed_all(lines)) == [("initial", 0x2222, 0x2222, 9, 9), ("initial", 0x1111, 0x1111, 3, 3)]


def test_a_mac_ce_with_two_accesses_pending_settles_neither():
    t = RaTracker()
    ev = t.feed_all([prach(T0, 1, 5, 0), init(T0, 1, 0xA), msg2(T0, 1, 0xA, 5, 0),
                     prach(T0, 1, 6, 7), init(T0, 1, 0xB), msg2(T0, 1, 0xB, 6, 7),
                     ce(T0 + 0.01, 0x4601)])
    assert ev == [] and t.ambiguous_ce == 1
    # the other access proves itself; the C-RNTI one is never reported
    assert ras(t.feed(create(T0 + 0.02, 0xB))) == [("initial", 0xB, 0xB, 7, 7)]
    assert ras(t.feed_all([f"{T0 + 5:.6f} [NR_MAC] I Frame.Slot 128.0"])) == [] and t.dropped == 1


def test_a_reestablishment_ties_the_new_rnti_to_the_old_one():
    ev = RaTracker().feed_all([prach(T0, 2, 9, 8), init(T0, 2, 0x5B00), msg2(T0, 2, 0x5B00, 9, 8),
                               reestab(T0 + 0.01, 0x5B00, 0x5A08), create(T0 + 0.02, 0x5B00)])
    assert ras(ev) == [("reestablishment", 0x5A08, 0x5B00, 8, 8)]
    (change,) = [e for e in ev if isinstance(e, RntiChange)]
    assert (change.old, change.new) == (0x5A08, 0x5B00)


def test_the_msg2_without_the_l1_line_is_still_paired_by_its_proof():
    ev = RaTracker().feed_all([msg2(T0, 3, 0x77, 1, 12), create(T0 + 0.01, 0x77)])
    assert ras(ev) == [("initial", 0x77, 0x77, 12, None)]


def test_proof_lines_for_unknown_accesses_prove_nothing():
    assert RaTracker().feed_all([create(T0, 0x77), ce(T0, 0x4601), reestab(T0, 0x77, 0x4601)]) == [
        RntiChange(old=0x4601, new=0x77, t_s=pytest.approx(T0), proof=reestab(T0, 0x77, 0x4601))]


@pytest.mark.parametrize("line", [
    "[NR_PHY] A [RAPROC] 1.19 Initiating RA procedure with preamble 99, energy 44.5 dB (I0 0, thres 200), delay 3 x",
    "[NR_PHY] A [RAPROC] Initiating RA procedure with preamble 1, energy ? dB, delay x",
    "[NR_MAC] A 1.19 UE RA-RNTI zz TC-RNTI 11: initiating RA procedure",
])
def test_malformed_random_access_lines_raise(line):
    with pytest.raises(GnbProtocolError):
        RaTracker().feed(line)


def test_the_stock_log_skips_a_malformed_line_and_keeps_the_rest(tmp_path):
    p = tmp_path / "gnb.log"
    p.write_text("\n".join([prach(T0, 1, 99, 3).replace("preamble 99", "preamble 199"),
                            prach(T0, 1, 5, 4), init(T0, 1, 0xC), msg2(T0, 1, 0xC, 5, 4), create(T0, 0xC)]) + "\n")
    log = StockLog(p, history=True)
    assert ras(log.feed()) == [("initial", 0xC, 0xC, 4, 4)]
    assert parse_prach_line(prach(T0, 1, 5, 4)).delay == 4 and parse_stamp(prach(T0, 1, 5, 4))[1] == "wall_clock"


def test_the_simulators_lines_are_read_back():
    import random

    out = []
    log = OaiRaLog(None, lambda: T0, random.Random(1))
    log._write = lambda lines: out.extend(f"{T0:.6f} {ln}" for ln in lines)  # type: ignore[method-assign]
    log.connected(5, 0x4601, 0x1234, 1)
    log.initial(7, 0x2345, 11, 1)
    log.reestablishment(9, 0x2345, 0x3456, 12, 1)
    ev = RaTracker().feed_all(out)
    assert ras(ev) == [("connected", 0x4601, 0x1234, 0, 0), ("initial", 0x2345, 0x2345, 11, 11),
                       ("reestablishment", 0x2345, 0x3456, 12, 12)]


_TOKENS = ["[RAPROC]", "Initiating RA procedure with preamble", "TC-RNTI", "initiating RA procedure",
           "Generating RA-Msg2 DCI", "timing_offset =", "preamble_index(RAPID)", "Received a MAC CE for C-RNTI with",
           "Reestablishment RNTI", "req C-RNTI", "Create UE context:", "(rnti:", "UE", "RA", "1.19", "delay",
           "energy", "dB", ",", "12", "ffff", "x", "-3", "1796145000.000001", "\x1b[32m", "[m]", "(", ")"]


@settings(max_examples=100, deadline=None)
@given(st.lists(st.lists(st.sampled_from(_TOKENS), max_size=14).map(" ".join), max_size=12))
def test_fuzz_only_protocol_errors_escape(lines):
    t = RaTracker()
    for line in lines:
        with contextlib.suppress(GnbProtocolError):
            t.feed(line)
