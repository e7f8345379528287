"""A fleet's mission log (docs/fleet.md, docs/design.md §10): records naming their vehicle, read
back per vehicle, each vehicle's keyframes built from its own records, and replay's answer the
batch solve of those keyframes. An old log (no vehicle fields) reads and replays as before."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from estimator.geodesy import Origin
from estimator.gps import estimate_gps_tau_s
from estimator.noise import NoiseModel
from estimator.ranging import C_MPS
from mission.estimation import MissionEstimator
from mission.keyframes import TriggerRecords, VelocityRecords, build_keyframe, build_keyframes_of
from mission.log import MissionLogWriter, read_mission_log
from mission.replay import ReplayOptions, build_keyframes, replay, resolve_gps_tau, result_of_log
from sitl_scenarios.example_log import generate
from sitl_scenarios.scenario import scenario_from_dict, user_tables
from uavloc.errors import MissionLogError

ORIGIN = Origin(47.3977, 8.5456, 488.0)
USERS_ENU_M = np.array([[40.0, 10.0, 0.0], [120.0, 60.0, 0.0], [230.0, -20.0, 0.0]])
USER_IDS = ["a", "b", "c"]
#: which users each vehicle's cell serves: b is ranged by both
SERVES = {0: [0, 1], 1: [1, 2]}
CENTRES_EN_M = {0: np.array([60.0, 20.0]), 1: np.array([190.0, 20.0])}
RADIUS_M, ALT_M, OMEGA = 70.0, 30.0, 0.05  # circle [m], height [m], rate [rad/s]
TEL_DT_S, TRIGGER_DT_S, DURATION_S = 0.5, 3.0, 150.0


def _truth_enu_m(v: int, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,) [m, ENU], velocity (3,) [m/s, ENU]) of vehicle v at t: a circle of its own."""
    a = OMEGA * t + np.pi * v
    c = CENTRES_EN_M[v]
    pos = np.array([c[0] + RADIUS_M * np.cos(a), c[1] + RADIUS_M * np.sin(a), ALT_M])
    vel = np.array([-RADIUS_M * OMEGA * np.sin(a), RADIUS_M * OMEGA * np.cos(a), 0.0])
    return pos, vel


def _lla(pos_enu_m: np.ndarray) -> dict:
    lat, lon, alt = ORIGIN.enu_to_lla(np.asarray(pos_enu_m, float).reshape(1, 3))
    return {"lat_deg": float(np.atleast_1d(lat)[0]), "lon_deg": float(np.atleast_1d(lon)[0]),
            "alt_m": float(np.atleast_1d(alt)[0])}


def _fleet_records(seed: int = 3) -> list[tuple[float, int, str, dict]]:
    """(t, order, type, fields) of a two-vehicle flight, sorted by time: each vehicle's telemetry
    every TEL_DT_S (GPS error: a per-vehicle offset plus white noise; the true velocity), and a
    trigger every TRIGGER_DT_S ranging the users its cell serves, one position per trigger."""
    rng = np.random.default_rng(seed)
    out: list[tuple[float, int, str, dict]] = []
    for v in (0, 1):
        offset = rng.normal(0.0, 1.0, 3) * [1, 1, 0.5]
        t0 = 0.2 * v  # the two vehicles' telemetry interleaves
        for t in np.arange(t0, DURATION_S, TEL_DT_S):
            pos, vel = _truth_enu_m(v, t)
            gps = pos + offset + rng.normal(0.0, 0.3, 3)
            out.append((round(float(t), 6), len(out), "telemetry",
                        {**_lla(gps), "vel_ned_mps": [vel[1], vel[0], -vel[2]], "vehicle": v}))
        for t in np.arange(5.0 + 1.5 * v, DURATION_S - 5.0, TRIGGER_DT_S):
            pos, _ = _truth_enu_m(v, t)
            uav = _lla(pos + offset + rng.normal(0.0, 0.3, 3))
            for i, k in enumerate(SERVES[v]):
                ti = round(float(t) + 0.05 * i, 6)
                p_i, _ = _truth_enu_m(v, ti)
                d = float(np.linalg.norm(p_i - USERS_ENU_M[k])) + rng.normal(0.0, 1.5)
                out.append((ti, len(out), "rtt", {"user": USER_IDS[k], "uav": uav, "toa_s": d / C_MPS, "vehicle": v}))
        out.append((2.0 + v, len(out), "waypoint", {"enu_m": [0.0, 0.0, ALT_M], "vehicle": v}))
        out.append((1.0 + v, len(out), "event", {"kind": "takeoff", "message": "take-off", "vehicle": v}))
    out.sort(key=lambda r: (r[0], r[1]))
    return out


def _write_fleet_log(path: Path, vehicle_field: bool = True, n_vehicles: int = 2) -> Path:
    """The two-vehicle flight as a mission log, through MissionLogWriter (the controller's writer)."""
    users = [{"id": u, "rnti": 0x4601 + i, "ground_alt_m": ORIGIN.alt_m} for i, u in enumerate(USER_IDS)]
    noise = NoiseModel(sigma_gps_m=1.0, gps_tau_s=None)
    vehicles = [{"id": f"uav{v + 1}", "home": Origin(*(float(x) for x in _lla([10.0 * v, 0.0, 0.0]).values()))}
                for v in range(n_vehicles)] if n_vehicles > 1 else None
    with MissionLogWriter(path) as w:
        w.write_header(ORIGIN, users, {"mu": 1, "fs_hz": 61.44e6}, noise=noise,
                       start_utc="2026-01-01T00:00:00.000+00:00", vehicles=vehicles)
        for t, _, rtype, fields in _fleet_records():
            if not vehicle_field:
                fields = {k: v for k, v in fields.items() if k != "vehicle"}
            w.write(rtype, t, **fields)
        w.write("truth", DURATION_S, users=[{"id": u, **_lla(p)} for u, p in zip(USER_IDS, USERS_ENU_M, strict=True)])
        w.write("event", DURATION_S, kind="end", status="ok", reason="done", message="mission end: ok (done)")
    return path


@pytest.fixture(scope="module")
def fleet_log(tmp_path_factory) -> Path:
    return _write_fleet_log(tmp_path_factory.mktemp("fleet") / "fleet.jsonl")


def _direct_keyframes(path: Path, noise: NoiseModel) -> dict[int, list]:
    """Each vehicle's keyframes built as the flight builds them: build_keyframe per trigger from the
    records as written, with that vehicle's previous position time and its own telemetry velocity."""
    recs = [json.loads(line) for line in path.read_text().splitlines()]
    user_index = {u: i for i, u in enumerate(USER_IDS)}
    out: dict[int, list] = {}
    for v in (0, 1):
        tel = [r for r in recs if r["type"] == "telemetry" and r["vehicle"] == v]
        velocity = VelocityRecords.from_ned(np.array([r["t"] for r in tel]), np.array([r["vel_ned_mps"] for r in tel]))
        rtt = [r for r in recs if r["type"] == "rtt" and r["vehicle"] == v]
        triggers, cur = [], []
        for r in rtt:  # one position per trigger
            if cur and r["uav"] != cur[0]["uav"]:
                triggers.append(cur)
                cur = []
            cur.append(r)
        triggers.append(cur)
        prev, kfs = None, []
        for records in triggers:
            trig = TriggerRecords.from_records(records, user_index)
            kfs.append(build_keyframe(trig, ORIGIN, prev, velocity, noise, vehicle=v))
            prev = trig.position_t_s
        out[v] = kfs
    return out


def _same_keyframe(a, b) -> bool:
    def same(x, y):
        return (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))
    return (np.array_equal(a.gps_enu_m, b.gps_enu_m) and np.array_equal(a.user_idx, b.user_idx)
            and np.array_equal(a.range_m, b.range_m) and same(a.odom_enu_m, b.odom_enu_m)
            and a.odom_sigma_m == b.odom_sigma_m and a.t_s == b.t_s and a.vehicle == b.vehicle)


def test_reader_keeps_each_records_vehicle(fleet_log):
    mlog = read_mission_log(fleet_log)
    recs = [json.loads(line) for line in fleet_log.read_text().splitlines()]
    assert [v.id for v in mlog.header.vehicles] == ["uav1", "uav2"]
    assert mlog.header.vehicles[1].home is not None and mlog.n_vehicles == 2
    tel_v = [r["vehicle"] for r in recs if r["type"] == "telemetry"]
    rtt_v = [r["vehicle"] for r in recs if r["type"] == "rtt"]
    np.testing.assert_array_equal(mlog.tel_vehicle, tel_v)
    np.testing.assert_array_equal(mlog.rtt_vehicle, rtt_v)
    assert mlog.tel_vehicle.shape == mlog.tel_t_s.shape and mlog.rtt_vehicle.shape == mlog.rtt_t_s.shape
    assert set(np.unique(mlog.tel_vehicle)) == {0, 1}
    np.testing.assert_array_equal(mlog.vehicle_telemetry(1), np.flatnonzero(np.array(tel_v) == 1))
    assert {e.get("vehicle") for e in mlog.events if e.get("kind") == "takeoff"} == {0, 1}


def test_keyframes_per_vehicle_are_the_flights_builder_per_vehicle(fleet_log):
    mlog = read_mission_log(fleet_log)
    noise = resolve_gps_tau(mlog, mlog.header.noise)
    kfs = build_keyframes(mlog, noise=noise)
    direct = _direct_keyframes(fleet_log, noise)
    for v in (0, 1):
        mine = [kf for kf in kfs if kf.vehicle == v]
        assert len(mine) == len(direct[v]) > 10
        assert all(_same_keyframe(a, b) for a, b in zip(mine, direct[v], strict=True))
        # every keyframe but each vehicle's first is linked to its own vehicle's previous one
        assert mine[0].odom_enu_m is None and all(kf.odom_enu_m is not None for kf in mine[1:])
    assert [kf.t_s for kf in kfs] == sorted(kf.t_s for kf in kfs)  # time order across vehicles
    assert {kf.vehicle for kf in kfs[:4]} == {0, 1}  # interleaved, not one vehicle after the other


def test_a_trigger_never_mixes_vehicles(fleet_log):
    mlog = read_mission_log(fleet_log)
    for kf in build_keyframes(mlog):
        assert set(kf.user_idx.tolist()) <= set(SERVES[kf.vehicle])


def test_replay_estimate_is_the_batch_solve_of_those_keyframes(fleet_log):
    mlog = read_mission_log(fleet_log)
    res = replay(mlog, ReplayOptions(history=True))
    direct = _direct_keyframes(fleet_log, res.noise)
    expected = MissionEstimator(mlog.n_users, mlog.user_up_m(), res.noise, res.params).final(direct[0] + direct[1])
    np.testing.assert_array_equal(res.estimate.users_enu_m, expected.users_enu_m)
    np.testing.assert_array_equal(res.estimate.cov_users_m2, expected.cov_users_m2)
    assert res.error_m is not None and np.all(res.error_m < 6.0)  # GPS offsets of ~1 m per vehicle
    # the final answer's track is each keyframe's own vehicle's, near the fleet's GPS
    assert np.all(np.linalg.norm(res.estimate.uav_enu_m - res.kf_gps_enu_m, axis=1) < 5.0)
    doc = result_of_log(mlog, res).to_document()
    assert doc["status"] == "ok" and doc["keyframes"] == len(direct[0]) + len(direct[1])


def test_flown_metres_are_each_vehicles_own_track_summed(fleet_log):
    mlog = read_mission_log(fleet_log)
    res = replay(mlog, ReplayOptions(history=True))
    # two circles at OMEGA·R m/s over the survey window: no jumps between the two vehicles' tracks
    survey_s = res.kf_t_s.max() - res.kf_t_s[0]
    assert res.flown_m == pytest.approx(2 * RADIUS_M * OMEGA * survey_s, rel=0.1)
    assert np.all(np.diff(res.history.flown_m) >= -1e-9)


def test_gps_tau_pools_each_vehicles_own_pairs(fleet_log):
    mlog = read_mission_log(fleet_log)
    tau = resolve_gps_tau(mlog, mlog.header.noise).gps_tau_s
    # the same estimate over the vehicles' series one after the other, a NaN velocity row between
    # them so no pair spans two vehicles
    pos = ORIGIN.lla_to_enu(*mlog.tel_lla.T)
    vel = mlog.tel_vel_ned_mps[:, [1, 0, 2]] * [1, 1, -1]
    ix = [mlog.vehicle_telemetry(0), mlog.vehicle_telemetry(1)]
    t = np.concatenate([mlog.tel_t_s[ix[0]], [np.nan], mlog.tel_t_s[ix[1]]])
    p = np.concatenate([pos[ix[0]], np.zeros((1, 3)), pos[ix[1]]])
    vv = np.concatenate([vel[ix[0]], np.full((1, 3), np.nan), vel[ix[1]]])
    assert tau is not None and tau == estimate_gps_tau_s(t, p, vv, 1.0)
    # mixing the interleaved series (no vehicle) would pair fixes of two vehicles 140 m apart
    assert estimate_gps_tau_s(mlog.tel_t_s, pos, vel, 1.0) != tau


def test_one_vehicle_log_without_vehicle_fields_replays_as_before(tmp_path):
    scenario = scenario_from_dict({
        "name": "three", "seed": 7,
        **user_tables([{"id": "a", "rnti": 0x4601, "east_m": 40.0, "north_m": 10.0},
                       {"id": "b", "rnti": 0x4602, "east_m": -20.0, "north_m": 50.0}]),
        "flight": {"altitude_m": 35.0}, "vehicle": {"gps_tau_s": 120.0}})
    path = tmp_path / "old.jsonl"
    generate(scenario, path)
    assert '"vehicle"' not in path.read_text()
    mlog = read_mission_log(path)
    assert mlog.header.vehicles == [] and mlog.n_vehicles == 1
    assert not mlog.tel_vehicle.any() and not mlog.rtt_vehicle.any()
    assert mlog.tel_vehicle.shape == mlog.tel_t_s.shape
    res = replay(mlog)
    assert all(kf.vehicle == 0 for kf in res.keyframes)
    # the builder over the whole log's triggers in file order, as before fleets
    groups, cur = [], [0]
    for i in range(1, len(mlog.rtt_t_s)):
        if np.array_equal(mlog.rtt_uav_lla[i], mlog.rtt_uav_lla[cur[0]]) and mlog.rtt_user[i] not in mlog.rtt_user[cur]:
            cur.append(i)
        else:
            groups.append(cur)
            cur = [i]
    groups.append(cur)
    triggers = [TriggerRecords(mlog.rtt_t_s[g], mlog.rtt_user[g], mlog.rtt_uav_lla[g], mlog.rtt_toa_s[g])
                for g in groups]
    old = build_keyframes_of(triggers, mlog.header.origin, None,
                             VelocityRecords.from_ned(mlog.tel_t_s, mlog.tel_vel_ned_mps), res.noise)
    assert len(old) == len(res.keyframes)
    assert all(_same_keyframe(a, b) for a, b in zip(old, res.keyframes, strict=True))
    # the same log with every record naming vehicle 0 is the same log
    named = tmp_path / "named.jsonl"
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    named.write_text("".join(json.dumps({**r, "vehicle": 0} if r["type"] in ("telemetry", "rtt", "event") else r)
                             + "\n" for r in lines))
    res0 = replay(read_mission_log(named))
    np.testing.assert_array_equal(res0.estimate.users_enu_m, res.estimate.users_enu_m)
    np.testing.assert_array_equal(res0.estimate.cov_users_m2, res.estimate.cov_users_m2)
    assert res0.flown_m == res.flown_m and res0.noise == res.noise
    np.testing.assert_array_equal(res0.history.bound_95_m, res.history.bound_95_m)


def test_header_vehicles_merge_with_the_mission_files_bands(tmp_path):
    area = {"vehicles": [{"id": "uav1", "alt_min_m": 20.0, "alt_max_m": 35.0},
                         {"id": "uav2", "alt_min_m": 40.0, "alt_max_m": 55.0}]}
    with MissionLogWriter(tmp_path / "h.jsonl") as w:
        rec = w.write_header(ORIGIN, [{"id": "a", "rnti": 1, "ground_alt_m": 488.0}], {"mu": 1}, area=area,
                             vehicles=[{"id": "uav1", "home": ORIGIN}, {"id": "uav2", "home": _lla([30.0, 0, 0])}])
    assert rec["vehicles"][0] == {"id": "uav1", "alt_min_m": 20.0, "alt_max_m": 35.0, "home": ORIGIN.to_dict()}
    header = read_mission_log(tmp_path / "h.jsonl").header
    assert header.vehicles[1].alt_min_m == 40.0 and header.vehicles[1].home.lat_deg == pytest.approx(ORIGIN.lat_deg)
    with MissionLogWriter(tmp_path / "bad.jsonl") as w, pytest.raises(MissionLogError, match="uav9"):
        w.write_header(ORIGIN, [{"id": "a", "rnti": 1, "ground_alt_m": 488.0}], {"mu": 1}, area=area,
                       vehicles=[{"id": "uav1"}, {"id": "uav9"}])


def _with_line(path: Path, lineno: int, edit) -> Path:
    lines = path.read_text().splitlines()
    rec = json.loads(lines[lineno - 1])
    lines[lineno - 1] = json.dumps(edit(rec))
    out = path.with_name(f"bad-{lineno}-{abs(hash(str(edit(rec)))) % 10**6}.jsonl")
    out.write_text("\n".join(lines) + "\n")
    return out


def _first_line_of(path: Path, rtype: str) -> int:
    return next(i for i, line in enumerate(path.read_text().splitlines(), start=1) if json.loads(line)["type"] == rtype)


@pytest.mark.parametrize(("rtype", "value", "words"), [
    ("rtt", 2, ["'vehicle' = 2", "out of range", "2 vehicles"]),
    ("telemetry", -1, ["'vehicle' = -1", "out of range"]),
    ("rtt", "1", ["'vehicle' must be an integer", "'1'"]),
    ("event", 1.0, ["'vehicle' must be an integer", "1.0"]),
    ("waypoint", True, ["'vehicle' must be an integer", "True"]),
])
def test_a_bad_vehicle_names_the_file_and_line(fleet_log, rtype, value, words):
    lineno = _first_line_of(fleet_log, rtype)
    bad = _with_line(fleet_log, lineno, lambda r: {**r, "vehicle": value})
    with pytest.raises(MissionLogError) as err:
        read_mission_log(bad)
    assert f"{bad}:{lineno}:" in str(err.value)
    for w in words:
        assert w in str(err.value)


def test_a_vehicle_in_a_log_without_vehicles_is_refused(tmp_path):
    path = _write_fleet_log(tmp_path / "one.jsonl", n_vehicles=1)  # records name vehicle 1, header none
    with pytest.raises(MissionLogError, match=r"one\.jsonl:\d+: .*'vehicle' = 1 .*lists no vehicles"):
        read_mission_log(path)


@pytest.mark.parametrize(("edit", "words"), [
    (lambda h: {**h, "vehicles": []}, ["'vehicles' must be a non-empty list"]),
    (lambda h: {**h, "vehicles": [{"id": "uav1"}, {"id": "uav1"}]}, ["vehicle ids", "not unique"]),
    (lambda h: {**h, "vehicles": [{"id": "uav1"}, {"name": "x"}]}, ["vehicles[1]", "string 'id'"]),
    (lambda h: {**h, "vehicles": [{"id": "uav1", "home": {"lat_deg": 95, "lon_deg": 0, "alt_m": 0}}, {"id": "u"}]},
     ["vehicles[0].home", "lat_deg"]),
])
def test_a_bad_vehicles_header_names_the_key(fleet_log, edit, words):
    bad = _with_line(fleet_log, 1, edit)
    with pytest.raises(MissionLogError) as err:
        read_mission_log(bad)
    assert f"{bad}:1:" in str(err.value)
    for w in words:
        assert w in str(err.value)


def test_estimate_uav_vehicle_is_checked(fleet_log):
    lineno = _first_line_of(fleet_log, "truth")
    est = {"type": "estimate", "t": 1.0, "users": [], "uav_lla": [[47.0, 8.0, 500.0]] * 2}
    lines = fleet_log.read_text().splitlines()
    for uv, ok in (([0, 1], True), ([0, 2], False), ([0], False)):
        path = fleet_log.with_name(f"est-{len(uv)}-{uv[-1]}.jsonl")
        path.write_text("\n".join([*lines[:lineno - 1], json.dumps({**est, "uav_vehicle": uv}), *lines[lineno - 1:]])
                        + "\n")
        if ok:
            read_mission_log(path)
        else:
            with pytest.raises(MissionLogError, match=rf"{path.name}:{lineno}: estimate uav_vehicle"):
                read_mission_log(path)


def test_time_order_is_checked_per_vehicle(tmp_path):
    """Two vehicles' telemetry may interleave in time; one vehicle's going back is refused."""
    path = _write_fleet_log(tmp_path / "order.jsonl")
    lines = path.read_text().splitlines()
    tel = [i for i, line in enumerate(lines) if json.loads(line)["type"] == "telemetry"]
    a, b = json.loads(lines[tel[0]]), json.loads(lines[tel[1]])
    assert a["vehicle"] != b["vehicle"]
    # vehicle 1's record written before vehicle 0's earlier one: fine (each vehicle's own order holds)
    lines[tel[0]], lines[tel[1]] = json.dumps(b), json.dumps(a)
    path.write_text("\n".join(lines) + "\n")
    read_mission_log(path)
    same = [i for i in tel if json.loads(lines[i])["vehicle"] == 0][:2]
    r0, r1 = json.loads(lines[same[0]]), json.loads(lines[same[1]])
    lines[same[0]], lines[same[1]] = json.dumps(r1), json.dumps(r0)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MissionLogError, match=r"telemetry record of vehicle 0 .* out of time order"):
        read_mission_log(path)


def test_report_draws_each_vehicles_own_track(fleet_log, tmp_path, capsys):
    from mission.cli import main
    from mission.report.figures import _est_tracks
    from mission.report.inputs import inputs_from_replay

    out = tmp_path / "report"
    assert main(["replay", str(fleet_log), "--json", "--out", str(out)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["status"] == "ok" and doc["keyframes"] > 20
    gj = json.loads((out / "mission.geojson").read_text())
    for kind in ("gps_track", "estimated_uav_track"):
        lines = [f for f in gj["features"] if f["properties"]["kind"] == kind]
        assert sorted(f["properties"]["vehicle"] for f in lines) == [0, 1]
        for f in lines:
            lon, lat, alt = np.array(f["geometry"]["coordinates"]).T
            en = ORIGIN.lla_to_enu(lat, lon, alt)[:, :2]
            # every point on its own vehicle's circle: no line joins the two vehicles' tracks
            r = np.linalg.norm(en - CENTRES_EN_M[f["properties"]["vehicle"]], axis=1)
            assert np.all(np.abs(r - RADIUS_M) < 6.0), kind
    assert (out / "mission.plan").is_file() and (out / "mission.vehicle1.plan").is_file()
    inp = inputs_from_replay(replay(read_mission_log(fleet_log)))
    assert inp.vehicles() == [0, 1] and len(_est_tracks(inp)) == 2


def test_one_vehicles_ranges_use_its_own_telemetry_alone(fleet_log, tmp_path):
    """Vehicle 1 flies and logs telemetry but ranges nobody: vehicle 0's keyframes are unchanged."""
    lines = [line for line in fleet_log.read_text().splitlines()
             if not (json.loads(line)["type"] == "rtt" and json.loads(line).get("vehicle") == 1)]
    path = tmp_path / "v0.jsonl"
    path.write_text("\n".join(lines) + "\n")
    mlog = read_mission_log(path)
    noise = resolve_gps_tau(read_mission_log(fleet_log), mlog.header.noise)
    kfs = build_keyframes(mlog, noise=noise)
    direct = _direct_keyframes(fleet_log, noise)[0]
    assert len(kfs) == len(direct) and all(_same_keyframe(a, b) for a, b in zip(kfs, direct, strict=True))


def test_delta_reselection_spaces_each_vehicles_own_keyframes(fleet_log):
    mlog = read_mission_log(fleet_log)
    kfs = build_keyframes(mlog, delta_m=25.0)
    for v in (0, 1):
        gps = np.array([kf.gps_enu_m for kf in kfs if kf.vehicle == v])
        assert len(gps) > 5 and np.all(np.linalg.norm(np.diff(gps, axis=0), axis=1) >= 25.0)
    # one selector over both vehicles would keep nearly every keyframe: they are 130 m apart
    assert len(kfs) < 0.5 * len(build_keyframes(mlog))
