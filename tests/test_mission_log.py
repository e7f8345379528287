"""Mission log `uavloc-mission/1`: writer round trip, torn last line, and every kind of bad line."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from estimator.geodesy import Origin
from estimator.noise import NoiseModel
from estimator.ranging import toa_s_from_raw
from mission.log import FORMAT, MissionLogWriter, read_mission_log
from uavloc.errors import MissionLogError

ORIGIN = Origin(43.6143, 7.0716, 150.0)
UAV = {"lat_deg": 43.6144, "lon_deg": 7.0717, "alt_m": 190.0}


def header(**over):
    h = {
        "type": "header", "t": 0, "format": FORMAT, "start_utc": "2026-11-23T10:00:00+00:00",
        "origin": ORIGIN.to_dict(), "users": [{"id": "ue1", "rnti": 17921, "ground_alt_m": 150.0}],
        "radio": {"mu": 1, "fs_hz": 46.08e6},
    }
    h.update(over)
    return h


def rtt(**over):
    r = {"type": "rtt", "t": 1.5, "user": "ue1", "uav": dict(UAV), "toa_s": 2.5e-7}
    r.update(over)
    return r


def write_lines(path, objs, tail=""):
    path.write_text("".join(json.dumps(o) + "\n" for o in objs) + tail)
    return path


def test_writer_round_trip_flushes_each_line(tmp_path):
    p = tmp_path / "m.jsonl"
    with MissionLogWriter(p) as w:
        w.write_header(ORIGIN, [{"id": "ue1", "rnti": 17921, "ground_alt_m": 150.0}],
                       {"mu": 1, "fs_hz": 46.08e6}, noise=NoiseModel(1.0, 2.0, 0.5, 0.01))
        w.write("rtt", 1.0, user="ue1", uav=UAV, toa_s=np.float64(3e-7), ta=np.int64(2))
        # flushed: another reader sees it before close
        assert len(p.read_text().splitlines()) == 2
        w.write("telemetry", 1.1, **UAV)
        w.write("truth", 1.2, users=[{"id": "ue1", **UAV}])
    log = read_mission_log(p)
    assert log.header.noise == NoiseModel(1.0, 2.0, 0.5, 0.01)
    assert log.rtt_toa_s.tolist() == [3e-7]
    assert log.rtt_user.tolist() == [0]
    assert log.tel_lla.shape == (1, 3)
    assert log.truth_lla[0, 2] == 190.0


def test_writer_appends_never_truncates(tmp_path):
    p = tmp_path / "m.jsonl"
    for _ in range(2):
        with MissionLogWriter(p) as w:
            w.write("event", 0.0, message="hello")
    assert len(p.read_text().splitlines()) == 2


def test_writer_refuses_nan_and_writes_nothing(tmp_path):
    p = tmp_path / "m.jsonl"
    with MissionLogWriter(p) as w:
        with pytest.raises(MissionLogError, match="NaN"):
            w.write("rtt", 1.0, user="ue1", uav=UAV, toa_s=float("nan"))
        with pytest.raises(MissionLogError, match="unknown record type"):
            w.write("bogus", 1.0)
    assert p.read_text() == ""


def test_defaults_when_noise_absent(tmp_path):
    log = read_mission_log(write_lines(tmp_path / "m.jsonl", [header(), rtt()]))
    assert log.header.noise == NoiseModel(1.0, 3.0, 0.0, 0.0)
    assert not log.header.has_noise


def test_toa_from_raw_fields_when_absent(tmp_path):
    r = rtt(ta=5, srs_peak=3.5)
    del r["toa_s"]
    log = read_mission_log(write_lines(tmp_path / "m.jsonl", [header(), r]))
    assert log.rtt_toa_s[0] == pytest.approx(toa_s_from_raw(5, 1, 3.5, 46.08e6))


def test_torn_last_line_is_skipped_with_a_warning(tmp_path, caplog):
    p = write_lines(tmp_path / "m.jsonl", [header(), rtt()], tail='{"type": "rtt", "t": 2.0, "us')
    with caplog.at_level(logging.WARNING):
        log = read_mission_log(p)
    assert len(log.rtt_t_s) == 1
    assert log.skipped_torn_line == 3
    assert "torn" in caplog.text


def test_rnti_as_hex_string(tmp_path):
    h = header(users=[{"id": "ue1", "rnti": "0x4601", "ground_alt_m": 150.0}])
    assert read_mission_log(write_lines(tmp_path / "m.jsonl", [h])).header.users[0].rnti == 0x4601


def _raw_rtt(**raw):
    r = rtt(**raw)
    del r["toa_s"]
    return r


def _rtt_without_toa():
    r = rtt()
    del r["toa_s"]
    return r


BAD = [
    ("missing header", [rtt()], 1, "first record must be the header"),
    ("wrong version", [header(format="uavloc-mission/2")], 1, "uavloc-mission/2"),
    ("unknown user", [header(), rtt(user="ue9")], 2, "unknown user 'ue9'"),
    ("nan toa", [header(), rtt(toa_s=float("nan"))], 2, "finite"),
    ("negative toa", [header(), rtt(toa_s=-1e-9)], 2, "outside"),
    ("lat out of range", [header(), rtt(uav={**UAV, "lat_deg": 95.0})], 2, "lat_deg"),
    ("uav not object", [header(), rtt(uav=[1, 2, 3])], 2, "'uav' must be an object"),
    ("no toa no raw", [header(), _rtt_without_toa()], 2, "neither 'toa_s' nor"),
    ("bad raw ta", [header(), _raw_rtt(ta=99999)], 2, "0..3846"),
    ("bad raw peak", [header(), _raw_rtt(ta=0, srs_peak=-1.0)], 2, "negative round trip"),
    ("unknown type", [header(), {"type": "bogus", "t": 1}], 2, "unknown record type 'bogus'"),
    ("missing t", [header(), {"type": "event", "message": "x"}], 2, "missing field 't'"),
    ("string t", [header(), {"type": "event", "t": "1"}], 2, "must be a number"),
    ("second header", [header(), header()], 2, "second header"),
    ("no users", [header(users=[])], 1, "non-empty list"),
    ("bad estimate cov", [header(), {"type": "estimate", "t": 1, "users": [
        {"id": "ue1", **UAV, "cov_en_m2": [[1, 0]]}]}], 2, "2x2"),
    ("truth unknown user", [header(), {"type": "truth", "t": 1, "users": [{"id": "x", **UAV}]}], 2, "unknown user"),
    ("non-object line", [header(), [1, 2]], 2, "must be a JSON object"),
]


@pytest.mark.parametrize(("name", "objs", "lineno", "match"), BAD, ids=[b[0] for b in BAD])
def test_bad_lines_are_named_by_line_number(tmp_path, name, objs, lineno, match):
    p = write_lines(tmp_path / "m.jsonl", objs)
    with pytest.raises(MissionLogError, match=rf"m\.jsonl:{lineno}: .*{match or ''}"):
        read_mission_log(p)


def test_raw_ta_without_mu_anywhere(tmp_path):
    h = header(radio={})
    with pytest.raises(MissionLogError, match=r":2: .*no 'mu'"):
        read_mission_log(write_lines(tmp_path / "m.jsonl", [h, _raw_rtt(ta=5)]))


def test_malformed_line_in_the_middle_is_an_error_not_a_skip(tmp_path):
    p = tmp_path / "m.jsonl"
    p.write_text(json.dumps(header()) + "\n" + '{"type": "rtt", "t"\n' + json.dumps(rtt()) + "\n")
    with pytest.raises(MissionLogError, match=r":2: not valid JSON"):
        read_mission_log(p)


def test_newline_terminated_garbage_at_the_end_is_an_error(tmp_path):
    p = tmp_path / "m.jsonl"
    p.write_text(json.dumps(header()) + "\n" + "garbage\n")
    with pytest.raises(MissionLogError, match=r":2: not valid JSON"):
        read_mission_log(p)


def test_empty_and_missing_files(tmp_path):
    (tmp_path / "e.jsonl").write_text("")
    with pytest.raises(MissionLogError, match="no header"):
        read_mission_log(tmp_path / "e.jsonl")
    with pytest.raises(MissionLogError, match="cannot open"):
        read_mission_log(tmp_path / "absent.jsonl")


def test_binary_file_is_a_clear_error(tmp_path):
    (tmp_path / "b.jsonl").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(MissionLogError, match="UTF-8"):
        read_mission_log(tmp_path / "b.jsonl")


def test_a_refused_write_keeps_the_log_whole_and_stops_it_once(tmp_path):
    """Issue 21 #2: the file system refusing a line (file size limit) cuts it off again: the
    error names the file, later records are dropped without raising, the log reads whole."""
    import subprocess
    import sys

    from tests.fly_rig import REPO, tiny_disk

    script = (
        "import sys\n"
        "from mission.log import MissionLogWriter\n"
        "from uavloc.errors import MissionLogError\n"
        "w = MissionLogWriter(sys.argv[1]); w.open()\n"
        "try:\n"
        "    for i in range(10000):\n"
        "        w.write('event', float(i), message='x' * 100)\n"
        "except MissionLogError as exc:\n"
        "    print(exc)\n"
        "w.write('event', 1e4, message='after the fault'); w.close()\n"
        "print('dropped', w.dropped)\n")
    with tiny_disk(tmp_path, 20_000) as disk:
        path = disk.path / "m.jsonl"
        proc = subprocess.run([sys.executable, "-c", script, str(path)], cwd=REPO, capture_output=True, text=True,
                              timeout=60, preexec_fn=disk.preexec)
        raw = path.read_bytes()
    assert proc.returncode == 0, proc.stderr
    assert f"cannot write the mission log {path}" in proc.stdout and "dropped 1" in proc.stdout, proc.stdout
    lines = raw.split(b"\n")
    assert lines[-1] == b"" and len(lines) > 50
    assert all(json.loads(line)["message"] == "x" * 100 for line in lines[:-1])


def test_a_line_nested_too_deeply_is_an_error_naming_the_line(tmp_path):
    """Issue 21 #6: a line of JSON nested 100 000 deep raised RecursionError out of the reader."""
    p = tmp_path / "deep.jsonl"
    with MissionLogWriter(p) as w:
        w.write_header(Origin(43.6, 7.07, 150.0), [{"id": "ue1", "rnti": 0x4601, "ground_alt_m": 150.0}],
                       {"mu": 1, "fs_hz": 61.44e6})
    with p.open("a", encoding="utf-8") as fh:
        fh.write("[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(MissionLogError, match=r"deep\.jsonl:2: JSON nested too deeply"):
        read_mission_log(p)


def test_records_out_of_time_order_are_refused_naming_both_lines(tmp_path):
    """Issue 21 #8: a shuffled log replayed "ok" with 4 597 m flown (truth 254 m). Telemetry
    records whose time goes back are refused (not sorted), naming both lines."""
    example = Path(__file__).resolve().parents[1] / "sitl_scenarios" / "data" / "example_paper.jsonl"
    lines = example.read_text(encoding="utf-8").splitlines(keepends=True)
    tel = [i for i, line in enumerate(lines) if '"type":"telemetry"' in line]
    i, j = tel[10], tel[40]
    lines[i], lines[j] = lines[j], lines[i]
    p = tmp_path / "shuffled.jsonl"
    p.write_text("".join(lines), encoding="utf-8")
    with pytest.raises(MissionLogError, match=rf"shuffled\.jsonl:{tel[11] + 1}: telemetry record .* earlier than "
                                              rf"the one on line {i + 1} .* out of time order"):
        read_mission_log(p)
    assert len(read_mission_log(example).tel_t_s) > 40  # the log as written reads


def test_range_records_permuted_among_their_own_lines_are_refused(tmp_path):
    """Issue 39: range records permuted among their own lines (telemetry in order) replayed with
    exit 0 to 4 665 m flown; now refused, naming the line. A trigger's small disorder (each record
    carries its measurement's own time) still reads."""
    example = Path(__file__).resolve().parents[1] / "sitl_scenarios" / "data" / "example_paper.jsonl"
    lines = example.read_text(encoding="utf-8").splitlines(keepends=True)
    rtt = [i for i, line in enumerate(lines) if '"type":"rtt"' in line]
    order = np.random.default_rng(4).permutation(rtt)
    shuffled = list(lines)
    for dst, src in zip(rtt, order, strict=True):
        shuffled[dst] = lines[src]
    p = tmp_path / "shuffled.jsonl"
    p.write_text("".join(shuffled), encoding="utf-8")
    with pytest.raises(MissionLogError, match=r"shuffled\.jsonl:\d+: rtt record .* range records out of time order"):
        read_mission_log(p)
    # two neighbours swapped (a fraction of a second apart): a trigger's own disorder, read as it is
    swapped = list(lines)
    swapped[rtt[5]], swapped[rtt[6]] = swapped[rtt[6]], swapped[rtt[5]]
    q = tmp_path / "swapped.jsonl"
    q.write_text("".join(swapped), encoding="utf-8")
    assert len(read_mission_log(q).rtt_t_s) == len(rtt)
