"""`uavloc import --t-trace` says what is really wrong with a recording of the real gNB's T tracer
(OAI 2025.w36, ../shared/data/oai-2025.w36-ttrace): an empty file, a preamble cut at byte N, a
recording whose UEs attached before it began, a `--t-messages` beside the recording's own, a user
absent from the recording; and it reads the trace with the live trace mode's thresholds."""

from __future__ import annotations

import gzip
import json
import logging
from pathlib import Path

import pytest

from mission.gnb import GnbConfig
from mission.gnb.trace_rtt import TraceSettings
from mission.gnb.ttrace import EV_RAR, frame_head, recording_preamble, split_frames
from uavloc.errors import GnbProtocolError

TTRACE = "oai-2025.w36-ttrace"
RUN = "dora_ramp_0_300"


@pytest.fixture
def flight(shared_data, tmp_path) -> dict:
    """The recorded PX4 flight's tlog, the ramp's recording moved onto its clock, and the RNTI of
    the recording's UE."""
    from mission.gnb.ttrace import iter_recording

    tlog = tmp_path / "legs.tlog"
    tlog.write_bytes(gzip.decompress((shared_data / "px4-v1.18-sih" / "legs.tlog.gz").read_bytes()))
    data = gzip.decompress((shared_data / TTRACE / RUN / "rec.raw.gz").read_bytes())
    from mission.importer import read_tlog_gps

    track = read_tlog_gps(tlog, time_base="tlog")
    t0 = float((shared_data / TTRACE / RUN / "phases.txt").read_text().split()[0])
    rnti = next(ev.values["rnti"] for ev in iter_recording(data) if ev.name == "GNB_PHY_UL_TIME_CHANNEL_ESTIMATE")
    return {"tlog": tlog, "data": data, "offset": track.t_unix_s[0] + 20.0 - t0, "rnti": rnti,
            "t_messages": shared_data / TTRACE / "T_messages.txt"}


def _import(flight, tmp_path, rec: bytes, *extra: str, users: list[str] | None = None):
    from mission.cli import main

    path = tmp_path / "rec.raw"
    path.write_bytes(rec)
    out = tmp_path / "m.jsonl"
    rc = main(["import", "--tlog", str(flight["tlog"]), "--time-base", "tlog", "--t-trace", str(path),
               "--users", *(users or [f"ue1:{flight['rnti']:04x}"]), "--gnb-time-offset", f"{flight['offset']:.6f}",
               "--t-interval", "0.5", "-o", str(out), "--json", *extra])
    return rc, out


def _ranges(out: Path) -> list[float]:
    return [json.loads(line)["toa_s"] for line in out.read_text().splitlines() if '"rtt"' in line]


def test_an_empty_recording_says_it_is_empty(flight, tmp_path, capsys):
    rc, _ = _import(flight, tmp_path, b"")
    err = capsys.readouterr().err
    assert rc == 1 and "is empty (0 bytes)" in err and "before the UEs attach" not in err


@pytest.mark.parametrize("cut", [1000, 137_862, 137_870])
def test_a_preamble_cut_at_byte_n_says_so(flight, tmp_path, capsys, cut):
    """Cut inside the first chunk of T_messages.txt, right after it (before the end marker, event
    −2), and inside the end marker's frame."""
    assert len(split_frames(flight["data"])[0][0]) + 4 == 137_862  # the chunk's frame
    rc, _ = _import(flight, tmp_path, flight["data"][:cut])
    err = capsys.readouterr().err
    assert rc == 1 and f"cut inside the gNB's T_messages.txt preamble at byte {cut}" in err, err
    assert "before the UEs attach" not in err


def test_a_recording_cut_in_its_first_frame_header(flight, tmp_path, capsys):
    rc, _ = _import(flight, tmp_path, flight["data"][:10])
    assert rc == 1 and "cut at byte 10, inside its first frame" in capsys.readouterr().err


def test_ues_attached_before_the_recording_are_named(flight, tmp_path, capsys):
    """The recording without its RAR: the UE's SRS and TA commands are there, its absolute TA is not."""
    data = flight["data"]
    frames, _ = split_frames(data)
    db, skip = recording_preamble(data)
    rar = db.id_of(EV_RAR)
    kept = [f for i, f in enumerate(frames) if i < skip or frame_head(f)[1] != rar]
    assert len(kept) == len(frames) - 1
    rc, _ = _import(flight, tmp_path, b"".join(len(f).to_bytes(4, "little") + f for f in kept))
    err = capsys.readouterr().err
    assert rc == 1 and f"UE(s) {flight['rnti']:04x} sent SRS or TA commands" in err
    assert "attached before the recording began" in err and "start `record` first" in err


def test_t_messages_beside_the_recordings_own_is_ignored_with_a_warning(flight, tmp_path, caplog):
    """A T_messages.txt of another build (one event more at the top: every id shifted) given beside a
    recording that carries its own: the recording's wins, the ranges are those without the option."""
    rc, out = _import(flight, tmp_path, flight["data"])
    assert rc == 0
    want = _ranges(out)
    other = tmp_path / "T_messages_other.txt"
    other.write_text("ID = SOME_NEWER_EVENT\n    DESC = x\n    GROUP = ALL\n    FORMAT = int,a\n"
                     + flight["t_messages"].read_text())
    with caplog.at_level(logging.WARNING, logger="mission.importer"):
        rc, out = _import(flight, tmp_path, flight["data"], "--t-messages", str(other))
    assert rc == 0 and _ranges(out) == want
    assert any("differs from it and is ignored" in r.getMessage() for r in caplog.records)
    # the same file as the recording's own: no warning
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="mission.importer"):
        rc, _ = _import(flight, tmp_path, flight["data"], "--t-messages", str(flight["t_messages"]))
    assert rc == 0 and not [r for r in caplog.records if "--t-messages" in r.getMessage()]


def test_t_messages_decodes_a_recording_without_a_preamble(flight, tmp_path, capsys):
    data = flight["data"]
    _, skip = recording_preamble(data)
    frames, _ = split_frames(data)
    bare = b"".join(len(f).to_bytes(4, "little") + f for f in frames[skip:])
    rc, _ = _import(flight, tmp_path, bare)
    assert rc == 1 and "pass the gNB's T_messages.txt with --t-messages" in capsys.readouterr().err
    rc, out = _import(flight, tmp_path, bare, "--t-messages", str(flight["t_messages"]))
    assert rc == 0 and _ranges(out)


def test_a_user_absent_from_the_recording_is_named(flight, tmp_path, capsys, caplog):
    """One user with ranges and one absent: a warning naming the absent one, and the summary lists
    it; only absent users: an error naming them."""
    ue = f"ue1:{flight['rnti']:04x}"
    with caplog.at_level(logging.WARNING, logger="mission.importer"):
        rc, out = _import(flight, tmp_path, flight["data"], users=[ue, "ue2:beef"])
    assert rc == 0 and _ranges(out)
    doc = json.loads(capsys.readouterr().out)
    assert list(doc["users_without_ranges"]) == ["ue2"] and "no random access" in doc["users_without_ranges"]["ue2"]
    assert any("user ue2 (RNTI beef) has no range" in r.getMessage() for r in caplog.records)
    rc, _ = _import(flight, tmp_path, flight["data"], users=["ue2:beef", "ue3:beee"])
    err = capsys.readouterr().err
    assert rc == 1 and "no measurement of the given users" in err and "ue2: RNTI beef" in err and "ue3:" in err


def test_import_and_flight_read_the_trace_with_one_set_of_thresholds():
    """TraceSettings' defaults are `[gnb]`'s (mission.config.GnbSettings): what `uavloc import
    --t-trace` uses is what the live trace mode uses; 15 m of clock step = 4.61 RTT samples."""
    assert TraceSettings(mu=1, fs_hz=46.08e6) == GnbConfig().trace_settings()
    s = GnbConfig(trace_clock_step_m=30.0, trace_jump_tolerance_m=2.0).trace_settings()
    assert s.clock_step_samples == pytest.approx(9.22, abs=0.01) and s.rate_tolerance_samples == pytest.approx(0.61,
                                                                                                             abs=0.01)
    assert TraceSettings().clock_step_samples == pytest.approx(4.61, abs=0.01)


def test_recording_preamble_errors_are_protocol_errors():
    with pytest.raises(GnbProtocolError, match="empty"):
        recording_preamble(b"")
    with pytest.raises(GnbProtocolError, match="2 byte"):
        recording_preamble(b"\x00\x01")
