"""`uavloc import`: tlog GPS track, gNB log lines, alignment by time, the mission log written, and
the clear errors (no GPS, clocks that do not overlap, GPS jumps)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from estimator.geodesy import Origin
from estimator.ranging import C_MPS, toa_s_from_raw
from mission.cli import main
from mission.gnb.oai import format_msg2_line, format_rtt_line
from mission.importer import (
    ImportUser,
    import_flight,
    interpolate_track,
    parse_gnb_log,
    parse_timestamp,
    read_tlog_gps,
    split_stamp,
)
from mission.log import read_mission_log
from uavloc.errors import ImportDataError

#: the GPS part of ../shared/data/ardupilot_vtol_sitl.tlog (see tests/data/README.md): in the checkout,
#: so these tests run in a fresh clone
VTOL = Path(__file__).resolve().parent / "data" / "ardupilot_vtol_sitl_gps.tlog"
USERS_ENU = np.array([[-40.0, -150.0, 0.0], [50.0, -300.0, 0.0], [10.0, -20.0, 0.0]])
RNTIS = [0x4601, 0x4602, 0x4603]


# ---------------------------------------------------------------------------------------------
# helpers


def write_tlog(path, records):
    """A tlog: per message a big-endian uint64 UNIX time [µs] then the MAVLink 2 bytes."""
    from pymavlink.dialects.v20 import common as mav

    link = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    with open(path, "wb") as fh:
        for t_s, msg_fn in records:
            msg = msg_fn(mav)
            fh.write(struct.pack(">Q", round(t_s * 1e6)) + bytes(msg.pack(link)))


def gpi(boot_ms, lat, lon, alt_m):
    return lambda mav: mav.MAVLink_global_position_int_message(
        boot_ms, round(lat * 1e7), round(lon * 1e7), round(alt_m * 1000), 0, 0, 0, 0, 0)


def pymavlink_fixes(path):
    """GLOBAL_POSITION_INT read straight with pymavlink: (time_boot_s, lat, lon, alt) in file order."""
    from pymavlink import mavutil

    m = mavutil.mavlink_connection(str(path))
    rows = []
    while (msg := m.recv_match(type="GLOBAL_POSITION_INT")) is not None:
        rows.append((msg.time_boot_ms / 1000, msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000))
    m.close()
    return np.array(rows)


def radio_model(origin: Origin, seed: int = 11):
    from sitl_scenarios.radio import RadioModel
    from sitl_scenarios.scenario import scenario_from_dict, user_tables

    sc = scenario_from_dict({
        "name": "vtol-import",
        "origin": origin.to_dict(),
        **user_tables([{"id": f"ue{k + 1}", "rnti": RNTIS[k], "east_m": float(e), "north_m": float(n),
                        "up_m": float(u)} for k, (e, n, u) in enumerate(USERS_ENU)]),
        "radio": {"mu": 1, "fs_hz": 46.08e6, "oversampling": 8, "s0_m": 1.5, "coverage_m": 2000.0,
                  "ue_sawtooth_amplitude_m": 0.0},
    })
    return RadioModel(sc, np.random.default_rng(seed))


def simulated_gnb_log(path, track, origin, period_s=0.5, seed=11):
    """gNB log made by the simulated gNB's radio model along the tlog's track: per user every
    `period_s`, an rtt reply line (stamped with UNIX seconds), with noise lines and a UE that is not
    one of ours in between. Returns (times, rnti, true UAV ENU) of the rtt lines written."""
    radio = radio_model(origin, seed)
    t0, t1 = track.t_unix_s[0], track.t_unix_s[-1]
    times = np.arange(t0 + 0.05, t1, period_s)
    pos, ok = interpolate_track(track, origin, times, 3.0)
    written = []
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("[GNB_APP]   Initialized RAN Context: RC.nb_nr_inst = 1\n")  # no stamp, not a measurement
        for i, (t, p) in enumerate(zip(times, pos, strict=True)):
            if not ok[i]:
                continue
            k = i % len(RNTIS)
            raw = radio.measure(k, p, t - t0)
            fh.write(f"{t:.6f} {format_rtt_line(raw.rnti, raw.ta, raw.mu, raw.srs_peak, raw.fs_hz, raw.snr_db)}\n")
            written.append((t, raw.rnti, p))
            if i % 50 == 0:
                fh.write(f"{t + 0.01:.6f} [NR_MAC]   Frame.Slot 12.3 UE RNTI 4601 CU-UE-ID 1 in-sync\n")
                fh.write(f"{t + 0.02:.6f} rnti 7777 ta 10 mu 1 srs_peak 1.0000 fs 46080000\n")  # not our UE
                fh.write(f"{t + 0.03:.6f} error rnti 4602 not reachable\n")
    return written


# ---------------------------------------------------------------------------------------------
# the public VTOL tlog


def test_tlog_track_is_what_pymavlink_reads():
    path = VTOL
    track = read_tlog_gps(path)
    raw = pymavlink_fixes(path)
    assert track.n_raw == len(raw) == 807
    # the link reordered a few messages: the track is the same fixes in autopilot-clock order
    ordered = raw[np.argsort(raw[:, 0], kind="stable")]
    assert np.all(np.diff(track.time_boot_s) > 0)
    np.testing.assert_array_equal(track.time_boot_s, ordered[:, 0])
    np.testing.assert_array_equal(track.lla, ordered[:, 1:])
    assert track.time_base == "system"
    np.testing.assert_allclose(np.diff(track.t_unix_s), np.diff(track.time_boot_s), atol=1e-6)
    assert track.home_lla is not None and track.home_lla[0] == pytest.approx(-35.3609626, abs=1e-7)


def test_import_vtol_flight_writes_track_and_aligned_ranges(tmp_path):
    path = VTOL
    track = read_tlog_gps(path)
    origin = Origin(*track.home_lla)
    written = simulated_gnb_log(tmp_path / "gnb.log", track, origin)
    out = tmp_path / "mission.jsonl"
    truth = origin.enu_to_lla(USERS_ENU)
    truth_args = [f"ue{k + 1}={truth[0][k]:.9f},{truth[1][k]:.9f},{truth[2][k]:.3f}" for k in range(3)]
    rc = main(["import", "--tlog", str(path), "--gnb-log", str(tmp_path / "gnb.log"), "-o", str(out),
               "--users", "ue1:4601", "ue2:4602", "ue3:0x4603", "--truth", *truth_args])
    assert rc == 0
    mlog = read_mission_log(out)
    # telemetry: every fix, in order, exactly as pymavlink reads it
    ordered = pymavlink_fixes(path)
    ordered = ordered[np.argsort(ordered[:, 0], kind="stable")]
    np.testing.assert_allclose(mlog.tel_lla, ordered[:, 1:], atol=1e-9)
    np.testing.assert_allclose(mlog.tel_t_s, ordered[:, 0] - ordered[0, 0], atol=1e-6)
    assert mlog.header.origin.lat_deg == pytest.approx(-35.3609626)
    # ranges: one per rtt line of our users, at the interpolated true position of the measurement time
    assert len(mlog.rtt_t_s) == len(written)
    t_rel = np.array([w[0] for w in written]) - track.t_unix_s[0]
    np.testing.assert_allclose(mlog.rtt_t_s, t_rel, atol=1e-5)
    uav_enu = origin.lla_to_enu(mlog.rtt_uav_lla[:, 0], mlog.rtt_uav_lla[:, 1], mlog.rtt_uav_lla[:, 2])
    np.testing.assert_allclose(uav_enu, np.array([w[2] for w in written]), atol=1e-3)
    assert [mlog.header.users[k].rnti for k in mlog.rtt_user] == [w[1] for w in written]
    # the ranges are the true distances up to noise (σ = 1.5 m) and SRS quantization
    d = np.linalg.norm(uav_enu - USERS_ENU[mlog.rtt_user], axis=1)
    err = C_MPS * mlog.rtt_toa_s - d
    assert abs(np.mean(err)) < 0.3 and 1.2 < np.std(err) < 1.9
    assert mlog.truth_lla is not None


def test_imported_vtol_flight_localizes_the_users(tmp_path):
    """Estimator over the imported log: each rtt record is a keyframe (GPS prior at the interpolated
    UAV position, one range), as replay builds them from a log whose users were ranged one by one."""
    from estimator.batch import solve_batch
    from estimator.noise import NoiseModel
    from estimator.types import Keyframe

    path = VTOL
    track = read_tlog_gps(path)
    origin = Origin(*track.home_lla)
    simulated_gnb_log(tmp_path / "gnb.log", track, origin)
    meas, _ = parse_gnb_log((tmp_path / "gnb.log").read_text().splitlines())
    import_flight(track, meas, [ImportUser(f"ue{k + 1}", RNTIS[k]) for k in range(3)], tmp_path / "m.jsonl",
                  noise=NoiseModel(sigma_gps_m=1.0, range_s0_m=1.5))
    mlog = read_mission_log(tmp_path / "m.jsonl")
    uav = origin.lla_to_enu(mlog.rtt_uav_lla[:, 0], mlog.rtt_uav_lla[:, 1], mlog.rtt_uav_lla[:, 2])
    kfs = [Keyframe(gps_enu_m=uav[i], user_idx=np.array([mlog.rtt_user[i]]),
                    range_m=np.array([C_MPS * mlog.rtt_toa_s[i]]), t_s=float(mlog.rtt_t_s[i]))
           for i in range(len(uav))]
    est = solve_batch(kfs, 3, mlog.user_up_m(), mlog.header.noise)
    err = np.linalg.norm(est.users_enu_m[:, :2] - USERS_ENU[:, :2], axis=1)
    assert np.all(err < 3.0), err
    assert np.all(est.error_bound_95_m() < 5.0), est.error_bound_95_m()


def test_replay_of_the_imported_vtol_flight(tmp_path):
    from mission.replay import ReplayOptions, replay

    path = VTOL
    track = read_tlog_gps(path)
    origin = Origin(*track.home_lla)
    simulated_gnb_log(tmp_path / "gnb.log", track, origin)
    meas, _ = parse_gnb_log((tmp_path / "gnb.log").read_text().splitlines())
    truth = origin.enu_to_lla(USERS_ENU)
    import_flight(track, meas, [ImportUser(f"ue{k + 1}", RNTIS[k]) for k in range(3)], tmp_path / "m.jsonl",
                  truth_lla={f"ue{k + 1}": (float(truth[0][k]), float(truth[1][k]), float(truth[2][k]))
                             for k in range(3)})
    result = replay(read_mission_log(tmp_path / "m.jsonl"), ReplayOptions(history=False))
    assert result.error_m is not None
    assert np.all(result.error_m < 3.0), result.error_m


# ---------------------------------------------------------------------------------------------
# errors


def test_tlog_without_gps_is_a_clear_error(tmp_path):
    path = tmp_path / "nogps.tlog"
    write_tlog(path, [(1.7e9 + i, lambda mav: mav.MAVLink_heartbeat_message(2, 12, 0, 0, 3, 3)) for i in range(5)])
    with pytest.raises(ImportDataError, match="no GPS track"):
        read_tlog_gps(path)


def test_tlog_with_only_no_fix_messages_is_a_clear_error(tmp_path):
    path = tmp_path / "nofix.tlog"
    write_tlog(path, [(1.7e9 + i, gpi(1000 * i, 0.0, 0.0, 0.0)) for i in range(5)])
    with pytest.raises(ImportDataError, match="with a GPS fix"):
        read_tlog_gps(path)


def test_gps_jump_is_a_clear_error(tmp_path):
    path = tmp_path / "jump.tlog"
    recs = [(1.7e9 + 0.2 * i, gpi(200 * i, 47.0 + 1e-6 * i, 8.0, 500.0)) for i in range(20)]
    recs[10] = (recs[10][0], gpi(2000, 47.01, 8.0, 500.0))  # 1.1 km away for one fix
    write_tlog(path, recs)
    with pytest.raises(ImportDataError, match="GPS jump"):
        read_tlog_gps(path)
    read_tlog_gps(path, max_speed_mps=1e5)  # accepted when the user says the vehicle is that fast


def test_autopilot_reboot_is_a_clear_error(tmp_path):
    path = tmp_path / "reboot.tlog"
    recs = [(1.7e9 + i, gpi(100_000 + 1000 * i, 47.0, 8.0, 500.0)) for i in range(5)]
    recs += [(1.7e9 + 5 + i, gpi(1000 * i, 47.0, 8.0, 500.0)) for i in range(5)]
    write_tlog(path, recs)
    with pytest.raises(ImportDataError, match="rebooted"):
        read_tlog_gps(path)


def test_clocks_that_do_not_overlap_are_a_clear_error(tmp_path):
    path = tmp_path / "ok.tlog"
    write_tlog(path, [(1.7e9 + 0.2 * i, gpi(200 * i, 47.0 + 1e-6 * i, 8.0, 500.0)) for i in range(50)])
    track = read_tlog_gps(path)
    assert track.time_base == "tlog"
    later = track.t_unix_s[-1] + 3600.0
    lines = [f"{later + i:.3f} rnti 4601 ta 5 mu 1 srs_peak 2.0 fs 46080000" for i in range(3)]
    meas, _ = parse_gnb_log(lines)
    with pytest.raises(ImportDataError, match=r"clocks do not overlap.*-36\d\d\.\d s"):
        import_flight(track, meas, [ImportUser("ue1", 0x4601)], tmp_path / "m.jsonl")
    # with the offset given, they do
    meas, _ = parse_gnb_log(lines, time_offset_s=-3600.0 - 8.0)
    s = import_flight(track, meas, [ImportUser("ue1", 0x4601)], tmp_path / "m.jsonl")
    assert s.measurements == 3


def test_measurements_of_other_ues_only_is_a_clear_error(tmp_path):
    path = tmp_path / "ok.tlog"
    write_tlog(path, [(1.7e9 + 0.2 * i, gpi(200 * i, 47.0, 8.0, 500.0)) for i in range(50)])
    track = read_tlog_gps(path)
    meas, _ = parse_gnb_log([f"{track.t_unix_s[5]:.3f} rnti 7777 ta 5 mu 1 srs_peak 2.0 fs 46080000"])
    with pytest.raises(ImportDataError, match="RNTIs 7777"):
        import_flight(track, meas, [ImportUser("ue1", 0x4601)], tmp_path / "m.jsonl")


def test_cli_reports_import_errors_with_exit_code_1(tmp_path, capsys):
    path = tmp_path / "nogps.tlog"
    write_tlog(path, [(1.7e9, lambda mav: mav.MAVLink_heartbeat_message(2, 12, 0, 0, 3, 3))])
    (tmp_path / "g.log").write_text("")
    rc = main(["import", "--tlog", str(path), "--gnb-log", str(tmp_path / "g.log"), "--users", "a:4601",
               "-o", str(tmp_path / "m.jsonl")])
    assert rc == 1
    assert "no GPS track" in capsys.readouterr().err
    rc = main(["import", "--tlog", str(path), "--gnb-log", str(tmp_path / "g.log"), "--users", "a:zz",
               "-o", str(tmp_path / "m.jsonl")])
    assert rc == 1 and "not hexadecimal" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# gNB log lines


@pytest.mark.parametrize("token, expected", [
    ("1533737170.125", 1533737170.125),
    ("[1533737170.125]", 1533737170.125),
    ("2018-08-08T14:06:10.125Z", 1533737170.125),
    ("2018-08-08T16:06:10.125+02:00", 1533737170.125),
    ("2018-08-08T14:06:10.125", 1533737170.125),
    ("[2018-08-08T14:06:10.125000123Z]", 1533737170.125),
    ("[NR_MAC]", None),
    ("163.7", None),
    ("rnti", None),
])
def test_timestamps(token, expected):
    got = parse_timestamp(token)
    assert got == (pytest.approx(expected, abs=1e-6) if expected is not None else None)


def test_iso_stamp_with_a_space_and_no_stamp():
    assert split_stamp("2018-08-08 14:06:10.5 rnti 4601 ta 1") == (pytest.approx(1533737170.5), "rnti 4601 ta 1")
    assert split_stamp("[NR_MAC] hello") == (None, "[NR_MAC] hello")


def test_msg2_lines_with_srs_refinement_and_plain_msg2():
    msg2 = format_msg2_line(0x4601, 163, 7, 0x10B, 22, 3, 1)
    lines = [
        f"1700000000.000 {msg2}",
        "1700000000.010 [PHY] rxAnt 0, SRS ToA peak estimator 12.5, snr 20",
        f"1700000001.000 {format_msg2_line(0x4602, 200, 3, 0x10B, 5, 7, 1)}",
        "1700000005.000 [PHY] rxAnt 0, SRS ToA peak estimator 3.0",  # too late: no Msg2 to refine
    ]
    meas, summary = parse_gnb_log(lines, mu=1, fs_hz=46.08e6)
    assert [m.source for m in meas] == ["msg2+srs", "msg2"]
    assert meas[0].toa_s == pytest.approx(toa_s_from_raw(3, 1, 12.5, 46.08e6))
    assert meas[0].t_unix_s == 1700000000.0
    assert meas[1].toa_s == pytest.approx(toa_s_from_raw(7, 1))
    assert summary.unpaired_srs == 1


def test_msg2_without_numerology_and_measurement_without_stamp_are_errors():
    msg2 = format_msg2_line(0x4601, 163, 7, 0x10B, 22, 3, 1)
    with pytest.raises(ImportDataError, match="--mu"):
        parse_gnb_log([f"1700000000.0 {msg2}"])
    with pytest.raises(ImportDataError, match=r"gNB log:2: a measurement line without a leading time stamp"):
        parse_gnb_log(["1700000000.0 hello", "rnti 4601 ta 5 mu 1 srs_peak 2.0 fs 46080000"])
    with pytest.raises(ImportDataError, match=r"gNB log:1: .*ta outside"):
        parse_gnb_log(["1700000000.0 rnti 4601 ta 99999 mu 1 srs_peak 2.0 fs 46080000"])


def test_import_summary_json(tmp_path, capsys):
    path = tmp_path / "ok.tlog"
    write_tlog(path, [(1.7e9 + 0.2 * i, gpi(200 * i, 47.0 + 2e-6 * i, 8.0, 500.0 + 0.1 * i)) for i in range(50)])
    (tmp_path / "g.log").write_text("".join(
        f"{1.7e9 + 0.2 * i + 0.1:.3f} rnti 4601 ta 5 mu 1 srs_peak 2.0 fs 46080000\n" for i in range(40)))
    rc = main(["import", "--tlog", str(path), "--gnb-log", str(tmp_path / "g.log"), "--users", "ue1:4601:495.5",
               "-o", str(tmp_path / "m.jsonl"), "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["fixes"] == 50 and doc["measurements"] == 40 and doc["per_user"] == {"ue1": 40}
    mlog = read_mission_log(tmp_path / "m.jsonl")
    assert mlog.header.users[0].ground_alt_m == 495.5
    assert mlog.header.origin.lat_deg == pytest.approx(47.0)  # no HOME_POSITION: the first fix
    # halfway between fixes i and i+1
    np.testing.assert_allclose(mlog.rtt_uav_lla[:, 0], 47.0 + 2e-6 * (np.arange(40) + 0.5), atol=1e-9)
