"""The T-tracer path held to the real gNB: OAI 2025.w36's recordings (../shared/data/oai-2025.w36-ttrace)
replayed through the parser and the RTT tracker give every steady state's round trip to the sample."""

from __future__ import annotations

import gzip
import struct
from pathlib import Path

import numpy as np
import pytest

from estimator.ranging import C_MPS
from mission.gnb.trace_rtt import TraceRttTracker, TraceSettings
from mission.gnb.ttrace import (
    EV_DL_PDU,
    EV_RAR,
    EV_SRS_CHEST,
    RANGING_EVENTS,
    TMessagesAssembler,
    decode_event,
    iter_recording,
    parse_t_messages,
    rar_grants,
    split_frames,
    srs_peak,
    ta_commands,
)
from uavloc.errors import GnbProtocolError

TTRACE = "oai-2025.w36-ttrace"


def _recording(shared_data: Path, run: str) -> bytes:
    return gzip.decompress((shared_data / TTRACE / run / "rec.raw.gz").read_bytes())


def _phases(shared_data: Path, run: str) -> list[tuple[float, str, int]]:
    out = []
    for line in (shared_data / TTRACE / run / "phases.txt").read_text().splitlines():
        t, label, rtt = line.split()
        out.append((float(t), label, int(rtt)))
    return out


def _track(data: bytes, **settings) -> tuple[TraceRttTracker, list]:
    tr = TraceRttTracker(TraceSettings(**settings))
    out = [r for ev in iter_recording(data) if (r := tr.feed(ev)) is not None]
    return tr, out


def _in_phase(out, phases, i, tail_s: float | None = None):
    t0 = phases[i][0]
    t1 = phases[i + 1][0] if i + 1 < len(phases) else out[-1].t_wall_s + 1e-6
    if tail_s is not None:
        t0 = max(t0, t1 - tail_s)
    return [r for r in out if t0 <= r.t_wall_s < t1]


# -- the wire ----------------------------------------------------------------------------------


def test_the_servers_own_t_messages_gives_the_ids(shared_data):
    data = _recording(shared_data, "dora_attach_300")
    frames, _ = split_frames(data)
    asm = TMessagesAssembler()
    for body in frames[:2]:
        assert asm.feed(body)
    assert asm.db is not None
    own = parse_t_messages((shared_data / TTRACE / "T_messages.txt").read_text())
    assert asm.db == own
    # the README's table: ids are positions of the ID lines
    assert (own.id_of(EV_SRS_CHEST), own.id_of(EV_DL_PDU), own.id_of(EV_RAR)) == (34, 48, 50)
    assert own.id_of("GNB_PHY_UL_SRS_TOA_NS") is None  # 2025.w36 has no such event


def test_the_client_mask_turns_on_only_the_ranging_events(shared_data):
    db = parse_t_messages((shared_data / TTRACE / "T_messages.txt").read_text())
    mask = db.mask(RANGING_EVENTS)
    assert mask[0] == 1
    (n,) = struct.unpack_from("<i", mask, 1)
    flags = struct.unpack_from(f"<{n}i", mask, 5)
    assert n == len(db.events) and len(mask) == 5 + 4 * n
    assert {i for i, f in enumerate(flags) if f} == {db.id_of(e) for e in RANGING_EVENTS} - {None}


def test_a_stream_cut_anywhere_gives_the_same_events(shared_data):
    data = _recording(shared_data, "dora_attach_300")[:200_000]
    whole, used = split_frames(data)
    got, buf = [], b""
    rng = np.random.default_rng(1)
    pos = 0
    while pos < len(data):
        step = int(rng.integers(1, 9000))
        buf += data[pos:pos + step]
        pos += step
        frames, n = split_frames(buf)
        got += frames
        buf = buf[n:]
    assert got == whole and len(buf) == len(data) - used


def test_malformed_frames_are_named_errors(shared_data):
    db = parse_t_messages((shared_data / TTRACE / "T_messages.txt").read_text())
    with pytest.raises(GnbProtocolError, match="frame length"):
        split_frames(struct.pack("<i", -5) + b"x" * 20)
    body = struct.pack("<qqi", 1, 2, db.id_of(EV_SRS_CHEST)) + struct.pack("<ii", 0, 1)
    with pytest.raises(GnbProtocolError, match="ends before its field"):
        decode_event(body, db)
    with pytest.raises(GnbProtocolError, match="not in this T_messages"):
        decode_event(struct.pack("<qqi", 1, 2, 9999), db)
    with pytest.raises(GnbProtocolError, match="no event"):
        parse_t_messages("# nothing here\n")
    with pytest.raises(GnbProtocolError, match="type,name"):
        parse_t_messages("ID = X\n    FORMAT = int,a : complex,b\n")
    with pytest.raises(GnbProtocolError, match="wants"):
        ta_commands(bytes([0x01, 0x30, 0x00]))


def test_mac_pdus_of_the_real_gnb(shared_data):
    """The RAR's TA and TC-RNTI, and TA commands only in the UE's PDUs (SIB1 rides on 0xffff)."""
    events = list(iter_recording(_recording(shared_data, "dora_attach_300")))
    rars = [g for ev in events if ev.name == EV_RAR for g in rar_grants(ev.values["data"])]
    assert [(g.ta, g.rapid) for g in rars] == [(8, rars[0].rapid)]
    ue = rars[0].tc_rnti
    cmds = [c for ev in events if ev.name == EV_DL_PDU and ev.values["rnti"] == ue
            for c in ta_commands(ev.values["data"])]
    assert len(cmds) == 36 and set(cmds) == {31}


def test_srs_peaks_and_their_prominence(shared_data):
    peaks = [srs_peak(ev.values["chest_t"]) for ev in iter_recording(_recording(shared_data, "dora_attach_300"))
             if ev.name == EV_SRS_CHEST]
    assert len(peaks) == 451 and all(p.n == 1536 for p in peaks)
    assert {round(p.peak) for p in peaks} == {-4}
    assert min(p.peak_to_mean_db for p in peaks) > 28


# -- the round trip, to the sample --------------------------------------------------------------


@pytest.mark.parametrize("run", ["dora_0_150_300", "dora_0_150_300_ue_debug", "dora_jump_0_300_reattach",
                                 "dora_attach_300"])
def test_every_steady_state_gives_its_rtt_to_the_sample(shared_data, run):
    phases = _phases(shared_data, run)
    tr, out = _track(_recording(shared_data, run))
    expected = {rtt for _, _, rtt in phases}
    for i, (_, label, rtt) in enumerate(phases):
        steady = _in_phase(out, phases, i, tail_s=1.0)
        assert steady, f"{run} {label}: no RTT in the phase's last second"
        assert {round(r.rtt_samples) for r in steady} == {rtt}, label
        assert all(abs(r.rtt_samples - rtt) < 0.01 for r in steady)
    # half-changed distances (the gNB's side set, the UE's not yet: 23, 69 samples) and stale SRS
    # never come out: every RTT is one of the phases' own
    assert {round(r.rtt_samples) for r in out} <= expected
    assert tr.counts.malformed == 0


def test_only_applied_ta_commands_count(shared_data):
    """Summing every command doubles the range (0 / 94 / 188); the applied ones alone give 0 / 46 / 92."""
    tr, out = _track(_recording(shared_data, "dora_0_150_300"))
    assert tr.counts.ta_applied == 4 and tr.counts.ta_dropped == 4
    assert out[-1].ta == 8 and round(out[-1].peak) == -4


def test_the_ramp_gives_each_of_its_26_steps(shared_data):
    run = "dora_ramp_0_300"
    phases = _phases(shared_data, run)
    tr, out = _track(_recording(shared_data, run))
    assert len(phases) == 27
    for i, (_, label, rtt) in enumerate(phases):
        steady = _in_phase(out, phases, i, tail_s=0.4)
        assert steady and {round(r.rtt_samples) for r in steady} == {rtt}, label
        # in between, only what a UAV flying away could show: the last step's value or this one's
        before = phases[i - 1][2] if i else rtt
        assert all(min(rtt, before) - 1 <= round(r.rtt_samples) <= max(rtt, before) for r in _in_phase(out, phases, i))
    assert tr.counts.ta_applied == 8


def test_stale_srs_after_the_ue_left_is_no_range(shared_data):
    tr, out = _track(_recording(shared_data, "dora_jump_0_300_reattach"))
    assert tr.counts.srs_stale == 4
    assert {round(r.rtt_samples) for r in out} == {0, 92}
    ue = out[-1].rnti
    assert "stale" in tr.why_none(ue) or tr.latest(ue) is not None


def test_the_reattach_and_the_attach_at_300_m_agree(shared_data):
    _, attach = _track(_recording(shared_data, "dora_attach_300"))
    _, jump = _track(_recording(shared_data, "dora_jump_0_300_reattach"))
    assert attach[0].ta == 8 and jump[-1].ta == 8  # RAR 8 against RAR 0 plus two applied 35s
    assert round(attach[-1].rtt_samples) == round(jump[-1].rtt_samples) == 92


def test_without_srs_there_is_no_range_and_the_tracker_says_why(shared_data):
    """SA without a core: periodic SRS is never configured; TA commands alone are not a range."""
    tr, out = _track(_recording(shared_data, "sa_no_core"))
    assert out == [] and tr.counts.srs == 0 and tr.counts.rars == 2
    assert all("no SRS" in tr.why_none(r) for r in tr.ues())


def test_a_ue_attached_before_the_trace_began_is_named(shared_data):
    data = _recording(shared_data, "dora_attach_300")
    frames, _ = split_frames(data)
    db = parse_t_messages((shared_data / TTRACE / "T_messages.txt").read_text())
    tr = TraceRttTracker()
    for body in frames[2:]:
        ev = decode_event(body, db)
        if ev.name != EV_RAR:
            assert tr.feed(ev) is None
    (ue,) = tr.unknown_rntis
    assert "attached before the T trace began" in tr.why_none(ue)


def test_a_malformed_event_is_counted_not_raised(shared_data):
    from mission.gnb.ttrace import TEvent

    tr = TraceRttTracker()
    assert tr.feed(TEvent(48, EV_DL_PDU, 1.0, {"rnti": 0x4601, "frame": 1, "slot": 0, "data": b"\x01\x30"})) is None
    assert tr.counts.malformed == 1 and "wants" in tr.counts.last_malformed
    assert tr.feed(TEvent(34, EV_SRS_CHEST, 1.0, {"rnti": 0x4601, "frame": 1, "chest_t": b"\x00"})) is None
    assert tr.counts.malformed == 2 and "not int16 I/Q" in tr.counts.last_malformed


def test_uavloc_import_t_trace_puts_the_real_gnbs_ranges_on_a_track(shared_data, tmp_path):
    """`uavloc import --t-trace`: the ramp's recording, moved onto the recorded PX4 flight's clock,
    becomes rtt records whose ranges are the ramp's RTTs (every one of them a steady or a stepping
    value of the ramp), one per UE every --t-interval."""
    import json

    from mission.cli import main
    from mission.importer import read_tlog_gps
    from mission.log import read_mission_log

    tlog = tmp_path / "legs.tlog"
    tlog.write_bytes(gzip.decompress((shared_data / "px4-v1.18-sih" / "legs.tlog.gz").read_bytes()))
    rec = tmp_path / "rec.raw"
    rec.write_bytes(_recording(shared_data, "dora_ramp_0_300"))
    track = read_tlog_gps(tlog, time_base="tlog")
    phases = _phases(shared_data, "dora_ramp_0_300")
    offset = track.t_unix_s[0] + 20.0 - phases[0][0]
    _, out = _track(rec.read_bytes())
    ue = out[0].rnti
    dest = tmp_path / "mission.jsonl"
    rc = main(["import", "--tlog", str(tlog), "--time-base", "tlog", "--t-trace", str(rec), "--users", f"ue1:{ue:04x}",
               "--gnb-time-offset", f"{offset:.6f}", "--t-interval", "0.5", "-o", str(dest)])
    assert rc == 0
    rtts = [json.loads(line) for line in dest.read_text().splitlines() if '"rtt"' in line]
    span_s = out[-1].t_wall_s - out[0].t_wall_s
    assert span_s / 0.5 * 0.7 < len(rtts) <= span_s / 0.5 + 1
    one_sample_m = C_MPS / (2 * 46.08e6)
    allowed = {rtt for _, _, rtt in phases} | {rtt - 1 for _, _, rtt in phases}
    for r in rtts:
        samples = 2 * r["toa_s"] * 46.08e6
        assert abs(samples - round(samples)) < 0.01 and round(samples) in allowed, r
        assert r["fs_hz"] == 46.08e6 and abs(r["toa_s"] * C_MPS - samples * one_sample_m) < 1e-6
    assert read_mission_log(dest).header.fs_hz == 46.08e6


def test_uavloc_import_needs_one_source_of_ranges(tmp_path, capsys):
    from mission.cli import main

    rc = main(["import", "--tlog", "x.tlog", "--users", "ue1:4601", "-o", str(tmp_path / "m.jsonl")])
    assert rc == 1 and "either --gnb-log FILE or --t-trace REC.raw" in capsys.readouterr().err


# -- what the shared recordings lack: a longer distance, two UEs, a noisy channel (tests/data) ------

MORE = Path(__file__).parent / "data" / "oai-2025.w36-ttrace-more"


def _more(run: str) -> tuple[bytes, list[tuple[float, str, list[int]]]]:
    data = gzip.decompress((MORE / run / "rec.raw.gz").read_bytes())
    phases = []
    for line in (MORE / run / "phases.txt").read_text().splitlines():
        parts = line.split()
        rtts = [int(p.split("=")[1]) for p in parts if p.startswith("rtt_rfsim=")]
        phases.append((float(parts[0]), parts[1], rtts))
    return data, phases


def _between(out, t0: float, t1: float):
    return [r for r in out if t0 <= r.t_wall_s < t1]


def test_600_m_to_the_sample_and_no_jump_a_vehicle_cannot_fly():
    """0 → 450 → 600 m: the 450 m level comes by a jump no vehicle flies (138 samples at once) and is
    held for the whole of its 15 s; 600 m reads 184 (TA 15, peak +4) to the sample."""
    data, phases = _more("long_600")
    tr, out = _track(data)
    (t0, _, (r0,)), (t450, _, _), (t600, _, (r600,)), (t_end, _, _) = phases
    assert {round(r.rtt_samples) for r in _between(out, t0, t450)} == {r0}
    tail = _between(out, t_end - 5.0, t_end)
    assert tail and all(abs(r.rtt_samples - r600) < 0.01 for r in tail) and tail[-1].ta == 15
    assert {round(r.rtt_samples) for r in _between(out, t600, t_end + 1.0)} == {r600}
    assert {round(r.rtt_samples) for r in out} == {0, 184}
    assert tr.counts.held_rate > 0 and tr.counts.ta_applied == 3


def test_two_ues_each_rar_floors_its_round_trip_and_without_srs_nothing_more():
    data, phases = _more("two_ues")
    events = list(iter_recording(data))
    rars = [g for ev in events if ev.name == EV_RAR for g in rar_grants(ev.values["data"])]
    assert [g.ta for g in rars] == [0, 0, 2, 6]
    # the re-attach's absolute TA floors each UE's round trip: 12·TA ≤ RTT < 12·(TA + 1)
    _, _, (rtt1, rtt2) = phases[2]
    assert 12 * rars[2].ta <= rtt1 < 12 * (rars[2].ta + 1) and 12 * rars[3].ta <= rtt2 < 12 * (rars[3].ta + 1)
    tr, out = _track(data)
    assert out == [] and tr.counts.rars == 4 and tr.counts.srs == 0
    assert len(tr.ues()) == 4 and all("no SRS" in tr.why_none(r) for r in tr.ues())


def test_a_noisy_channel_gives_its_round_trip_within_a_sample():
    """OAI's CI AWGN channel: the SRS response is a plateau whose highest tap wanders ±3; its centre
    gives 0 and 46 samples within one, at ~24 dB over the mean (not stale)."""
    data, phases = _more("noisy_150")
    tr, out = _track(data)
    (t0, _, (r0,)), (t150, _, (r150,)), (t_end, _, _) = phases
    assert tr.counts.srs_stale == 0 and tr.counts.rars == 1 and tr.counts.prach == 6
    for (a, b, rtt) in ((t0, t150, r0), (t150 + 0.5 * (t_end - t150), t_end, r150)):
        got = np.array([r.rtt_samples for r in _between(out, a, b)])
        assert len(got) >= 10 and np.all(np.abs(got - rtt) <= 1.05) and abs(np.median(got) - rtt) <= 1.0
    peaks = [srs_peak(ev.values["chest_t"]) for ev in iter_recording(data) if ev.name == EV_SRS_CHEST]
    assert 20 < np.median([p.peak_to_mean_db for p in peaks]) < 28
