"""Relative-motion factors from the autopilot's velocity: integration, σ model, per-keyframe σ in
the solvers (dense reference, online against batch), and what replay builds from a log."""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from estimator.batch import solve_batch
from estimator.factors import MotionFactor, dense_normal_equations
from estimator.linearize import linearize
from estimator.motion import (
    MAX_VEL_GAP_S,
    MOTION_SIGMA_FLOOR_M,
    integrate_velocity,
    motion_sigma_m,
)
from estimator.noise import NoiseModel
from estimator.numdiff import numerical_jacobian
from estimator.online import OnlineEstimator
from estimator.problem import pack_keyframes
from estimator.simulate import simulate
from estimator.types import Keyframe, SolverParams
from uavloc.errors import EstimatorError

NOISE = NoiseModel(sigma_gps_m=1.0, range_s0_m=3.0)


# --- integration of the velocity -------------------------------------------------------------------


def test_integration_is_exact_for_velocity_linear_between_records():
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.1, 0.3, 60))
    v = rng.normal(size=(60, 3))
    # v piecewise linear through the records: its integral from t_0, in closed form per interval
    def position(tq):
        out = np.zeros(3)
        for i in range(59):
            a, b = t[i], min(t[i + 1], tq)
            if b <= a:
                break
            s = b - a
            out += v[i] * s + (v[i + 1] - v[i]) * s * s / (2 * (t[i + 1] - t[i]))
        return out

    tk = np.sort(rng.uniform(t[0], t[-1], 12))
    disp, ok, _ = integrate_velocity(t, v, tk)
    assert not ok[0] and ok[1:].all()
    ref = np.array([position(b) - position(a) for a, b in itertools.pairwise(tk)])
    np.testing.assert_allclose(disp[1:], ref, atol=1e-12)


def test_integration_of_a_smooth_velocity_converges_to_the_displacement():
    t = np.arange(0.0, 20.0, 0.2)
    v = np.column_stack([5 * np.cos(t / 12), 5 * np.sin(t / 12), 0.1 * np.ones_like(t)])
    tk = np.arange(0.3, 19.5, 0.4)
    disp, ok, _ = integrate_velocity(t, v, tk)
    exact = np.column_stack([60 * np.sin(tk / 12), -60 * np.cos(tk / 12), 0.1 * tk])
    assert ok[1:].all()
    np.testing.assert_allclose(disp[1:], np.diff(exact, axis=0), atol=2e-4)


def test_a_gap_integrates_to_the_same_bits_from_any_earlier_start_of_the_records():
    """The flight keeps only the recent records; replay has the whole log: same bits."""
    rng = np.random.default_rng(11)
    t = np.round(np.cumsum(rng.uniform(0.15, 0.25, 400)), 6)
    v = rng.normal(size=(400, 3)) * 5
    tk = np.sort(rng.uniform(t[300], t[-1], 2))
    disp, ok, disc = integrate_velocity(t, v, tk)
    for first in (1, 57, 298):
        d2, ok2, disc2 = integrate_velocity(t[first:], v[first:], tk)
        assert ok2[1] and ok[1]
        np.testing.assert_array_equal(d2[1], disp[1])
        assert disc2[1] == disc[1]


def test_no_displacement_where_records_are_missing_or_far_apart():
    t = np.arange(0.0, 10.0, 0.2)
    v = np.ones((t.size, 3))
    v[20:30] = np.nan  # 4.0 .. 5.8 s: no velocity (a stretch longer than MAX_VEL_GAP_S)
    tk = np.array([-1.0, 1.0, 2.0, 4.5, 7.0, 7.05, 9.0, 12.0])
    disp, ok, _ = integrate_velocity(t, v, tk)
    # before the first record / across the hole / beyond the last record: none
    assert ok.tolist() == [False, False, True, False, False, True, True, False]
    np.testing.assert_allclose(disp[2], [1.0, 1.0, 1.0])
    np.testing.assert_allclose(disp[5], [0.05] * 3)
    assert np.all(disp[~ok] == 0.0)
    # a gap just within MAX_VEL_GAP_S is bridged
    t2 = np.array([0.0, MAX_VEL_GAP_S, 2 * MAX_VEL_GAP_S])
    _, ok2, _ = integrate_velocity(t2, np.ones((3, 3)), np.array([0.1, 1.9]))
    assert ok2[1]


def test_no_displacement_over_a_keyframe_gap_longer_than_the_limit():
    t = np.arange(0.0, 100.0, 0.2)
    _, ok, _ = integrate_velocity(t, np.zeros((t.size, 3)), np.array([1.0, 2.0, 90.0]), max_dt_s=60.0)
    assert ok.tolist() == [False, True, False]


def test_integration_rejects_malformed_records():
    with pytest.raises(EstimatorError, match="velocity records"):
        integrate_velocity(np.arange(3.0), np.ones((3, 2)), np.arange(2.0))


def test_motion_sigma_is_a_random_walk_in_the_integration_time():
    noise = NoiseModel(vel_sigma_mps=0.05, vel_tau_s=2.0)
    dt = np.array([0.0, 0.4, 4.0, 40.0])
    # σ_m² = 2 σ_v² τ_v Δt + σ_t²
    ref = np.sqrt(2 * 0.05**2 * 2.0 * dt + MOTION_SIGMA_FLOOR_M**2)
    np.testing.assert_allclose(motion_sigma_m(dt, noise), ref, rtol=1e-15)
    # the variance of a Gauss–Markov velocity error integrated over T: 2σ_v²τ_v²(T/τ_v − 1 + e^(−T/τ_v))
    def exact_var(span):
        return 2 * 0.05**2 * 2.0**2 * (span / 2.0 - 1 + math.exp(-span / 2.0))

    # one short gap: conservative; n independent factors over nΔt ≫ τ_v: the integral's variance
    n, step = 100, 0.4
    assert motion_sigma_m(step, noise) ** 2 > exact_var(step)
    assert exact_var(n * step) <= n * motion_sigma_m(step, noise) ** 2 <= 1.1 * exact_var(n * step)


def test_noise_model_velocity_keys_round_trip_the_log_header():
    n = NoiseModel(sigma_gps_m=1.5, vel_sigma_mps=0.03, vel_tau_s=1.5)
    back = NoiseModel.from_log_dict(json.loads(json.dumps(n.to_log_dict())))
    assert back == replace(n, gps_tau_s=0.0)
    assert "vel_sigma_mps" not in NoiseModel().to_log_dict()
    with pytest.raises(EstimatorError, match="vel_sigma_mps"):
        NoiseModel(vel_sigma_mps=-0.1)
    with pytest.raises(EstimatorError, match="vel_tau_s"):
        NoiseModel.from_log_dict({"vel_tau_s": "1"})


# --- the factor in the solvers ----------------------------------------------------------------------


def test_motion_factor_jacobian_matches_central_differences():
    rng = np.random.default_rng(3)
    f = MotionFactor(rng.normal(size=3), 0.07)
    x0, x1 = rng.normal(size=3) * 10, rng.normal(size=3) * 10
    j0, j1 = f.jacobian(x0, x1)
    np.testing.assert_allclose(j0, numerical_jacobian(lambda v: f.error(v, x1), x0), atol=1e-7)
    np.testing.assert_allclose(j1, numerical_jacobian(lambda v: f.error(x0, v), x1), atol=1e-7)


def _with_own_sigma(keyframes, rng):
    """Keyframes whose displacements carry their own σ (0.02–0.3 m), some without a displacement."""
    out = []
    for i, kf in enumerate(keyframes):
        if kf.odom_enu_m is None or i % 7 == 3:
            out.append(replace(kf, odom_enu_m=None))
        else:
            out.append(replace(kf, odom_sigma_m=float(rng.uniform(0.02, 0.3))))
    return out


@pytest.mark.parametrize("params", [SolverParams(loss="huber"), SolverParams(estimate_bias=True)],
                         ids=["huber", "nlos-bias"])
@pytest.mark.parametrize("tau_s", [0.0, 60.0], ids=["white", "gauss-markov"])
def test_per_keyframe_motion_sigma_matches_the_dense_reference(params, tau_s):
    noise = replace(NOISE, gps_tau_s=tau_s)
    rng = np.random.default_rng(5)
    sc = simulate(np.random.default_rng(4), n_users=3, n_keyframes=30, p_visible=0.8, odom_sigma_m=0.1, noise=noise)
    kfs = _with_own_sigma(sc.keyframes, rng)
    prob = pack_keyframes(kfs, 3, sc.user_up_m, noise, params)
    assert prob.use_motion and 0 < prob.odom_mask.sum() < 29
    x = sc.uav_enu_m + rng.normal(size=sc.uav_enu_m.shape) * 0.5
    theta = np.zeros((3, prob.p))
    theta[:, :2] = sc.users_enu_m[:, :2] + rng.normal(size=(3, 2)) * 3
    active = np.ones(3, dtype=bool)
    lin = linearize(prob, x, theta, active)
    h_ref, g_ref, cost_ref = dense_normal_equations(prob, x, theta, active)
    n = prob.n_keyframes
    # the keyframe part: diagonal blocks, the scalar·I links, the gradient
    for i in range(n):
        np.testing.assert_allclose(lin.hxx[i], h_ref[3 * i : 3 * i + 3, 3 * i : 3 * i + 3], rtol=1e-10, atol=1e-10)
        if i + 1 < n:
            np.testing.assert_allclose(np.eye(3) * lin.off[i], h_ref[3 * i : 3 * i + 3, 3 * i + 3 : 3 * i + 6],
                                       atol=1e-10)
    np.testing.assert_allclose(lin.gx.ravel(), g_ref[: 3 * n], rtol=1e-9, atol=1e-9)
    assert lin.cost == pytest.approx(cost_ref, rel=1e-12)


def test_own_sigma_overrides_the_params_sigma_and_none_falls_back_to_it():
    sc = simulate(np.random.default_rng(6), n_users=2, n_keyframes=10, odom_sigma_m=0.1)
    kfs = [replace(kf, odom_sigma_m=0.5) if i % 2 else kf for i, kf in enumerate(sc.keyframes)]
    p_none = pack_keyframes(kfs, 2, sc.user_up_m, NOISE, SolverParams())
    p_par = pack_keyframes(kfs, 2, sc.user_up_m, NOISE, SolverParams(motion_sigma_m=0.2))
    odd = np.arange(10) % 2 == 1
    assert p_none.odom_mask.tolist() == odd.tolist()  # only the keyframes with their own σ
    np.testing.assert_allclose(p_none.odom_weight()[odd], 4.0)
    assert p_par.odom_mask[1:].all()
    np.testing.assert_allclose(p_par.odom_weight()[1:], np.where(odd, 4.0, 25.0)[1:])


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "0.1", True])
def test_a_bad_motion_sigma_is_named(bad):
    kf = Keyframe(np.zeros(3), np.array([0]), np.array([10.0]), odom_enu_m=np.ones(3), odom_sigma_m=bad)
    with pytest.raises(EstimatorError, match="keyframe 1: odom_sigma_m"):
        pack_keyframes([Keyframe(np.zeros(3), np.array([0]), np.array([10.0])), kf], 1, np.zeros(1), NOISE,
                       SolverParams())
    with pytest.raises(EstimatorError, match="odom_sigma_m"):
        OnlineEstimator(1, np.zeros(1), NOISE).add_keyframe(kf)


def test_online_equals_batch_with_per_keyframe_motion_sigma():
    rng = np.random.default_rng(8)
    sc = simulate(np.random.default_rng(7), n_users=3, n_keyframes=60, odom_sigma_m=0.1, p_visible=0.9)
    kfs = _with_own_sigma(sc.keyframes, rng)
    tight = SolverParams(estimate_noise_scale=False, window=1000, step_tol_m=1e-10, step_tol_uav_m=1e-10,
                         step_tol_sigma=0.0, online_step_tol_m=1e-10, online_resolve_every=1)
    batch = solve_batch(kfs, 3, sc.user_up_m, NOISE, tight)
    on = OnlineEstimator(3, sc.user_up_m, NOISE, tight)
    for kf in kfs:
        est = on.add_keyframe(kf)
    np.testing.assert_allclose(est.users_enu_m, batch.users_enu_m, atol=1e-6)
    np.testing.assert_allclose(est.uav_enu_m, batch.uav_enu_m, atol=1e-6)
    np.testing.assert_allclose(est.cov_users_m2, batch.cov_users_m2, rtol=1e-5)


@pytest.mark.parametrize("tau_s", [0.0, 60.0], ids=["white-gps", "gauss-markov-gps"])
def test_online_marginalizes_per_keyframe_motion_links_close_to_batch(tau_s):
    rng = np.random.default_rng(10)
    noise = replace(NOISE, gps_tau_s=tau_s)
    sc = simulate(np.random.default_rng(9), n_users=3, n_keyframes=200, odom_sigma_m=0.05, noise=noise,
                  gps_tau_s=tau_s, dt_s=0.4)
    kfs = _with_own_sigma(sc.keyframes, rng)
    params = SolverParams(window=40, estimate_bias=False, estimate_noise_scale=False)
    batch = solve_batch(kfs, 3, sc.user_up_m, noise, params)
    on = OnlineEstimator(3, sc.user_up_m, noise, params)
    for kf in kfs:
        est = on.add_keyframe(kf)
    sigma = np.sqrt(np.trace(batch.cov_users_m2, axis1=1, axis2=2))
    assert np.all(np.linalg.norm(est.users_enu_m - batch.users_enu_m, axis=1) < 0.2 * sigma)
    np.testing.assert_allclose(est.cov_users_m2, batch.cov_users_m2, rtol=0.1)


def test_discretization_variance_counts_the_velocity_change_inside_the_gap():
    # records 1 s apart; the velocity turns by (0, 4, 0) m/s between t = 2 and 3, constant elsewhere
    t = np.arange(0.0, 6.0)
    v = np.zeros((6, 3))
    v[:, 0] = 5.0
    v[3:, 1] = 4.0
    _, ok, disc = integrate_velocity(t, v, np.array([0.5, 1.5, 2.25, 2.75, 4.5]))
    assert ok[1:].all()
    # (o |Δv|)² / 12 for the part o of the turning interval [2, 3] inside each gap
    np.testing.assert_allclose(disc, [0.0, 0.0, 0.25**2 * 16 / 12, 0.5**2 * 16 / 12, 0.25**2 * 16 / 12],
                               atol=1e-15)
    # a smooth turn at 5 Hz leaves millimetres
    t5 = np.arange(0.0, 10.0, 0.2)
    v5 = np.column_stack([5 * np.cos(t5 / 12), 5 * np.sin(t5 / 12), np.zeros_like(t5)])
    _, _, d5 = integrate_velocity(t5, v5, np.arange(0.1, 9.5, 0.4))
    assert np.sqrt(d5.max()) < 0.01


# --- replay ------------------------------------------------------------------------------------------


def test_replay_links_keyframes_by_the_logged_velocity_and_not_otherwise(tmp_path):
    from mission.cli import main
    from mission.log import read_mission_log
    from mission.replay import ReplayOptions, build_keyframes, replay
    from tests.test_replay_honest import _write

    with_vel, without = tmp_path / "v.jsonl", tmp_path / "n.jsonl"
    noise = NoiseModel(gps_tau_s=0.0, vel_sigma_mps=0.05, vel_tau_s=0.5)
    truth = _write(with_vel, noise, 0.0, with_vel=True)
    _write(without, noise, 0.0, with_vel=False)
    kfs = build_keyframes(read_mission_log(with_vel))
    assert kfs[0].odom_enu_m is None and all(kf.odom_enu_m is not None for kf in kfs[1:])
    # 0.4 s apart on a circle at 5 m/s: 2 m, with the header's σ_v, τ_v
    np.testing.assert_allclose([np.linalg.norm(kf.odom_enu_m) for kf in kfs[1:]], 2.0, rtol=1e-3)
    np.testing.assert_allclose([kf.odom_sigma_m for kf in kfs[1:]], motion_sigma_m(0.4, noise), rtol=0.05)
    assert all(kf.odom_enu_m is None for kf in build_keyframes(read_mission_log(with_vel), velocity=False))
    assert all(kf.odom_enu_m is None for kf in build_keyframes(read_mission_log(without)))

    on = replay(read_mission_log(with_vel), ReplayOptions(history=False))
    off = replay(read_mission_log(with_vel), ReplayOptions(history=False, velocity=False))
    plain = replay(read_mission_log(without), ReplayOptions(history=False))
    # the velocity smooths the white GPS out of the track: the users' covariance shrinks
    assert np.all(np.linalg.det(on.estimate.cov_users_m2) < np.linalg.det(off.estimate.cov_users_m2))
    np.testing.assert_array_equal(off.estimate.users_enu_m, plain.estimate.users_enu_m)
    assert np.all(np.linalg.norm(on.estimate.users_enu_m[:, :2] - truth[:, :2], axis=1) < 2.0)
    # the command line's switch
    out = []
    for flag in ([], ["--no-velocity"]):
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            assert main(["-q", "replay", str(with_vel), "--json", *flag]) == 0
        out.append(json.loads(buf.getvalue())["users"][0]["enu_m"])
    assert out[0] == pytest.approx(on.estimate.users_enu_m[0].tolist(), abs=1e-9)
    assert out[1] == pytest.approx(off.estimate.users_enu_m[0].tolist(), abs=1e-9)


# --- in flight ----------------------------------------------------------------------------------------


def test_flight_pipeline_keyframes_carry_the_velocity_displacement_replay_rebuilds(tmp_path):
    """The pipeline integrates the telemetry velocity as logged, between the rounds' position times,
    under the header's noise model: the keyframes it hands the estimator are replay's."""
    import asyncio

    from estimator.geodesy import Origin
    from mission.control.config import MissionUser
    from mission.control.pipeline import MeasurementPipeline
    from mission.control.state import FlightState
    from mission.gnb.oai import RttSample
    from mission.log import MissionLogWriter, read_mission_log
    from mission.replay import build_keyframes
    from mission.vehicle.telemetry import TelemetryBuffer

    origin = Origin(43.6143, 7.0716, 150.0)
    users = [MissionUser("ue1", 0x4601), MissionUser("ue2", 0x4602)]
    path = tmp_path / "m.jsonl"
    noise = NoiseModel(gps_tau_s=30.0, vel_sigma_mps=0.04, vel_tau_s=0.8)
    rng = np.random.default_rng(12)

    async def fly():
        writer = MissionLogWriter(path)
        writer.open()
        buf = TelemetryBuffer(256)
        flight = FlightState(event=lambda *a, **k: None)
        pipe = MeasurementPipeline(None, users, 2.0, 1.0, flight, buf, lambda: origin, writer,
                                   now=lambda: 0.0, mission_t=lambda t: t)
        writer.write_header(origin, [{"id": u.id, "rnti": u.rnti, "ground_alt_m": 150.0} for u in users],
                            {"mu": 1, "fs_hz": 46.08e6}, noise=noise)
        t_tel = 0.0

        def telemetry_until(t_end):
            nonlocal t_tel
            while t_tel <= t_end + 1e-9:
                a = t_tel / 12.0
                pos = np.array([60 * np.cos(a), 60 * np.sin(a), 35.0]) + rng.normal(size=3) * 0.5
                v = (-5 * np.sin(a), 5 * np.cos(a), 0.0)
                buf.append(t_tel, pos)
                lat, lon, alt = (float(x) for x in origin.enu_to_lla(pos))
                # a stretch of 2 s without velocity (records without vel_ned_mps)
                extra = {} if 6.0 < t_tel < 8.0 else {"vel_ned_mps": [v[1] + 0.01, v[0], -v[2]]}
                writer.write("telemetry", t_tel, lat_deg=lat, lon_deg=lon, alt_m=alt, **extra)
                t_tel = round(t_tel + 0.2, 6)

        for i in range(20):
            t = 0.45 + 0.5 * i
            telemetry_until(t + 1.2)  # the logged records after the round are there when it is placed
            samples = [(k, RttSample(users[k].rnti, 100, 1, 3.5, 46.08e6, None, 1e-7 * (k + 1), t + 0.01 * k),
                        t + 0.01 * k, 0.0) for k in range(2)]
            await pipe.place(samples)
        writer.close()
        return pipe.keyframes

    flown = asyncio.run(fly())
    rebuilt = build_keyframes(read_mission_log(path))
    assert len(flown) == len(rebuilt) == 20
    has = [kf.odom_enu_m is not None for kf in flown]
    assert has == [kf.odom_enu_m is not None for kf in rebuilt]
    # none for the first keyframe and across the stretch without velocity
    assert not has[0] and has[1] and not all(has[11:16]) and has[-1]
    for a, b in zip(flown, rebuilt, strict=True):
        assert a.t_s == b.t_s
        if a.odom_enu_m is not None:
            # bit for bit: the solver's discrete choices (bias selection, clock test) can turn a
            # last-bit difference into millimetres
            np.testing.assert_array_equal(a.odom_enu_m, b.odom_enu_m)
            assert a.odom_sigma_m == b.odom_sigma_m
            assert a.odom_sigma_m > motion_sigma_m(0.5, noise) * 0.999


# --- the built-in vehicle's velocity -----------------------------------------------------------------


def test_simulated_velocity_error_is_small_and_forgets_itself_and_leaves_the_gps_error_alone():
    from sitl_scenarios.vehicle.sensors import VEL_SIGMA_MPS, VEL_TAU_S, GpsError, VelocityError

    rng_a, rng_b = np.random.default_rng(4), np.random.default_rng(4)
    gps_a = GpsError(1.0, 120.0, rng_a)
    vel = VelocityError(rng_a)
    gps_b = GpsError(1.0, 120.0, rng_b)
    t = np.arange(0.0, 2000.0, 0.1)
    e = np.array([vel.sample(float(s)) for s in t])
    # the GPS error draws what it drew without the velocity error
    np.testing.assert_array_equal([gps_a.sample(float(s)) for s in t[:200]], [gps_b.sample(float(s)) for s in t[:200]])
    assert np.std(e) == pytest.approx(VEL_SIGMA_MPS, rel=0.1)
    # correlation exp(−lag/τ): about e⁻¹ at τ, gone at 5τ
    lag = round(VEL_TAU_S / 0.1)
    corr = [float(np.mean(e[:-k] * e[k:]) / np.mean(e * e)) for k in (lag, 5 * lag)]
    assert corr[0] == pytest.approx(math.exp(-1.0), abs=0.08) and abs(corr[1]) < 0.06
    # integrated over 40 s it errs like the random walk the estimator assumes, well inside its default σ_m
    span = round(40.0 / 0.1)
    drift = np.array([e[i : i + span].sum(axis=0) * 0.1 for i in range(0, len(e) - span, span)])
    assert np.std(drift) < motion_sigma_m(40.0, NoiseModel()) * 0.8
    assert np.std(drift) == pytest.approx(math.sqrt(2 * VEL_SIGMA_MPS**2 * VEL_TAU_S * 40.0), rel=0.3)


@pytest.mark.parametrize("tau_s", [0.0, 60.0], ids=["white-gps", "gauss-markov-gps"])
def test_online_filter_step_with_a_motion_factor_matches_dense_elimination(tau_s):
    """A keyframe linked by a motion factor is folded by the chain filter step (estimator.online_chain)
    instead of a window re-solve; against the dense reference (tests.dense_filter): v = [x_l, x_n, Θ],
    H = Ŝ on (x_l, Θ) + the GPS factor + the motion factor + the new ranges, all at x_n⁰ and the
    previous Θ."""
    from estimator.gps import GpsFactor, gps_phi
    from tests.dense_filter import add_ranges, assert_step_matches, step_to_dense

    noise = replace(NOISE, gps_tau_s=tau_s)
    sc = simulate(np.random.default_rng(31), n_users=3, n_keyframes=60, noise=noise, gps_tau_s=tau_s,
                  p_visible=0.8, odom_sigma_m=0.05)
    kfs = [replace(kf, odom_sigma_m=0.07) if kf.odom_enu_m is not None else kf for kf in sc.keyframes]
    params = SolverParams(online_resolve_every=1000, window=1000, online_max_step_m=100.0, estimate_noise_scale=False)
    j = next(i for i in range(40, 60) if 0 < kfs[i].user_idx.size < 3)
    on = OnlineEstimator(3, sc.user_up_m, noise, params)
    est, theta0, pi, x_l, h, g = step_to_dense(on, kfs, j)
    kf, g_l = kfs[j], kfs[j - 1].gps_enu_m
    phi = float(gps_phi(np.array([kfs[j - 1].t_s, kf.t_s]), tau_s)[1]) if tau_s else 0.0
    x0 = kf.gps_enu_m + phi * (x_l - g_l)
    dim = h.shape[0]

    def add(jac, e):  # H += JᵀJ, g −= Jᵀe
        h[:] += jac.T @ jac
        g[:] -= jac.T @ e

    gf = GpsFactor(kf.gps_enu_m, noise.sigma_gps_m, phi, g_l)
    jn, jl = gf.jacobian()
    jg = np.zeros((3, dim))
    jg[:, 0:3], jg[:, 3:6] = jl, jn
    add(jg, gf.error(x0, x_l))
    mf = MotionFactor(kf.odom_enu_m, 0.07)
    j0, j1 = mf.jacobian(x_l, x0)
    jm = np.zeros((3, dim))
    jm[:, 0:3], jm[:, 3:6] = j0, j1
    add(jm, mf.error(x_l, x0))
    add_ranges(h, g, on, kf, x0, theta0, pi, sc.user_up_m)
    assert_step_matches(on, est, h, g, theta0, x_l, x0)
