"""Controller pieces that run without a vehicle: the estimator worker (off the event loop), the
loop-lag monitor, error selection, configuration and the result document."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from estimator.noise import NoiseModel
from estimator.online import OnlineEstimator
from estimator.refresh import RefreshedEstimator
from estimator.simulate import simulate
from estimator.types import SolverParams
from mission.control.config import STATUS_TARGET, ControllerConfig, MissionResult
from mission.control.estimator_worker import EstimatorWorker
from mission.control.flight import _first_error
from mission.control.loop import LoopLagMonitor
from mission.estimation import MissionEstimator
from mission.result import build_result
from sitl_scenarios.scenario import load_scenario
from uavloc.errors import EstimatorError, GnbError, VehicleError

N_USERS = 3
#: the mission's estimator for N_USERS users at height 0 (confirm=False in the workers below: no stop rule)
SETUP = MissionEstimator(N_USERS, np.zeros(N_USERS), NoiseModel(), SolverParams(), 1.0)


@pytest.fixture(scope="module")
def survey():
    return simulate(np.random.default_rng(4), n_users=N_USERS, n_keyframes=200, pattern="lawnmower")


async def _solve_all(keyframes, mode: str):
    """Solve every keyframe through an EstimatorWorker while a LoopLagMonitor runs."""
    worker = EstimatorWorker(SETUP, confirm=False, mode=mode)
    monitor = LoopLagMonitor(0.01)
    estimates = []
    done = asyncio.Event()

    def on_estimate(est):
        estimates.append(est)
        if len(estimates) == len(keyframes):
            done.set()

    async with asyncio.timeout(120):
        async with asyncio.TaskGroup() as tg:
            run = tg.create_task(worker.run(on_estimate))
            await worker.ready.wait()
            mon = tg.create_task(monitor.run())
            for kf in keyframes:  # one at a time: one estimate each
                worker.queue.put_nowait(kf)
                await worker.queue.join()
            await done.wait()
            mon.cancel()
            run.cancel()
    return estimates, monitor.summary()


@pytest.mark.slow
def test_the_estimator_solves_in_a_child_process_off_the_event_loop(survey):
    """The loop never runs the numpy work in process mode (the lag it saves is measured by
    benchmarks/controller.py, not asserted here: no wall-clock bounds in tests)."""
    import os

    async def go():
        worker = EstimatorWorker(SETUP, confirm=False, mode="process")
        got = []
        async with asyncio.TaskGroup() as tg:
            run = tg.create_task(worker.run(got.append))
            await worker.ready.wait()
            for kf in survey.keyframes[:20]:
                worker.queue.put_nowait(kf)
            await asyncio.wait_for(worker.queue.join(), 120)
            run.cancel()
        return worker, got

    worker, got = asyncio.run(go())
    assert worker.mode == "process" and worker.child_pid not in (None, os.getpid())
    # keyframes that queued up while the child was busy come back as one estimate
    assert 1 <= len(got) <= 20 and got[-1].keyframes_used == 20


def test_estimator_child_dying_mid_mission_falls_back_to_a_thread_with_every_keyframe(survey):
    """The estimator worker dying: its child is killed between keyframes; the worker solves on in
    a thread, re-fed with the keyframes so far, and its estimates stay those of one estimator."""
    import os
    import signal

    kfs = survey.keyframes[:30]

    async def go():
        worker = EstimatorWorker(SETUP, confirm=False, mode="process")
        got = []
        async with asyncio.TaskGroup() as tg:
            run = tg.create_task(worker.run(got.append))
            await worker.ready.wait()
            for kf in kfs[:15]:
                worker.queue.put_nowait(kf)
                await asyncio.wait_for(worker.queue.join(), 120)
            os.kill(worker.child_pid, signal.SIGKILL)
            for kf in kfs[15:]:
                worker.queue.put_nowait(kf)
                await asyncio.wait_for(worker.queue.join(), 120)
            run.cancel()
        return worker, got

    worker, got = asyncio.run(go())
    assert worker.mode == "thread" and len(got) == len(kfs)
    ref = RefreshedEstimator(N_USERS, np.zeros(N_USERS), NoiseModel(), SolverParams())
    direct = [ref.add_keyframe(kf) for kf in kfs]
    for a, c in zip(got, direct, strict=True):
        np.testing.assert_allclose(a.users_enu_m, c.users_enu_m, rtol=1e-9, atol=1e-9)


def test_worker_process_and_thread_give_the_estimates_of_the_refreshed_estimator(survey):
    kfs = survey.keyframes[:60]
    by_process, _ = asyncio.run(_solve_all(kfs, "process"))
    by_thread, _ = asyncio.run(_solve_all(kfs, "thread"))
    ref = RefreshedEstimator(N_USERS, np.zeros(N_USERS), NoiseModel(), SolverParams())
    direct = [ref.add_keyframe(kf) for kf in kfs]
    # same numbers up to BLAS summation order (multithreaded BLAS is not bitwise reproducible)
    for a, b, c in zip(by_process, by_thread, direct, strict=True):
        np.testing.assert_allclose(a.users_enu_m, c.users_enu_m, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(b.users_enu_m, c.users_enu_m, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(a.cov_users_m2, c.cov_users_m2, rtol=1e-7, atol=1e-12)


def test_worker_reports_estimator_errors_and_keeps_going(survey):
    bad = survey.keyframes[1].__class__(gps_enu_m=np.array([np.nan, 0.0, 0.0]), user_idx=np.array([0]),
                                        range_m=np.array([10.0]))
    errors = []

    async def go():
        worker = EstimatorWorker(SETUP, confirm=False, mode="thread")
        got = []
        async with asyncio.TaskGroup() as tg:
            run = tg.create_task(worker.run(got.append, errors.append))
            for kf in (survey.keyframes[0], bad, survey.keyframes[1]):
                worker.queue.put_nowait(kf)
            await asyncio.wait_for(worker.queue.join(), 30)
            run.cancel()
        return got

    got = asyncio.run(go())
    # the three queued together: the bad one is left out, the two others make the estimate
    assert len(errors) == 1 and isinstance(errors[0], EstimatorError) and "gps" in str(errors[0]).lower()
    assert len(got) == 1 and got[0].keyframes_used == 2


def test_first_error_prefers_cancellation_then_project_errors():
    boom = RuntimeError("bug")
    eg = BaseExceptionGroup("g", [boom, ExceptionGroup("inner", [GnbError("gnb down")])])
    assert isinstance(_first_error(eg), GnbError)
    eg2 = BaseExceptionGroup("g", [VehicleError("x"), asyncio.CancelledError()])
    assert isinstance(_first_error(eg2), asyncio.CancelledError)
    assert _first_error(BaseExceptionGroup("g", [boom])) is boom


def test_loop_lag_monitor_sees_a_blocked_loop():
    async def go():
        mon = LoopLagMonitor(0.005)
        async with asyncio.TaskGroup() as tg:
            t = tg.create_task(mon.run())
            await asyncio.sleep(0.03)
            import time

            time.sleep(0.1)  # block the loop on purpose
            await asyncio.sleep(0.03)
            t.cancel()
        return mon.summary()

    s = asyncio.run(go())
    assert s["max_s"] >= 0.08


def test_config_from_scenario_takes_the_mission_and_vehicle_sections():
    sc = load_scenario("three_users_nlos")
    cfg = ControllerConfig.from_mission(sc.mission_config(), time_scale=20.0)
    assert cfg.flight == sc.mission.flight and cfg.safety == sc.mission.safety
    assert (cfg.flight.cruise_speed_mps, cfg.time_scale) == (sc.vehicle.speed_mps, 20.0)


def test_result_document_follows_design_section_11(survey):
    from estimator.geodesy import Origin

    online = OnlineEstimator(N_USERS, np.zeros(N_USERS), NoiseModel(), SolverParams())
    for kf in survey.keyframes[:120]:
        est = online.add_keyframe(kf)
    res = build_result(status=STATUS_TARGET, reason="target reached", user_ids=["a", "b", "c"], estimate=est,
                       origin=Origin(43.6, 7.07, 150.0), truth_enu_m=survey.users_enu_m, flown_m=240.0,
                       measurements=360, keyframes=120, duration_s=80.0)
    doc = MissionResult(result=res, estimate=est).result.to_document()
    assert set(doc) >= {"status", "reason", "users", "flown_m", "measurements", "keyframes", "duration_s"}
    for u, truth in zip(doc["users"], survey.users_enu_m, strict=True):
        assert set(u) >= {"id", "lat_deg", "lon_deg", "alt_m", "enu_m", "cov_en_m2", "error_m"}
        assert u["error_m"] == pytest.approx(np.hypot(*(np.asarray(u["enu_m"][:2]) - truth[:2])))


def test_status_line_marks_an_ambiguous_user_instead_of_a_small_r95(tmp_path):
    from estimator.types import Estimate
    from sitl_scenarios.scenario import controller_from_scenario

    sc = load_scenario("three_users_nlos")
    ctl = controller_from_scenario(sc, None, None, tmp_path / "m.jsonl", planner="lawnmower")
    k = len(sc.users)
    users = np.array([[10.0, 20.0, 0.0]] * k)
    mirror = np.full((k, 3), np.nan)
    mirror[0] = [10.0, -20.0, 0.0]
    ctl.estimate = Estimate(users_enu_m=users, cov_users_m2=np.tile(np.eye(3) * 0.01, (k, 1, 1)),
                            info_users=np.eye(3 * k), bias_m=None, uav_enu_m=np.zeros((0, 3)),
                            ambiguous=np.array([True] + [False] * (k - 1)), mirror_enu_m=mirror,
                            n_ranges=np.full(k, 10))
    parts = ctl.status_line().split(" | ")
    assert parts[1] == f"{sc.users[0].id} AMBIGUOUS (10.0, 20.0) or (10.0, -20.0)"
    assert "r95" not in parts[1] and "r95" in parts[2]


def test_worker_takes_queued_keyframes_together_with_one_estimate(survey):
    """Keyframes that queued up while the estimator was busy are solved together: one estimate,
    the batch answer for all of them (an estimator that falls behind catches up)."""
    from estimator.batch import solve_batch
    from estimator.types import SOURCE_BATCH

    kfs = survey.keyframes[:50]

    async def go():
        worker = EstimatorWorker(SETUP, confirm=False, mode="thread")
        got = []
        async with asyncio.TaskGroup() as tg:
            for kf in kfs:  # all queued before the worker starts
                worker.queue.put_nowait(kf)
            run = tg.create_task(worker.run(got.append))
            await asyncio.wait_for(worker.queue.join(), 120)
            run.cancel()
        return got

    got = asyncio.run(go())
    assert len(got) == 1 and got[0].source == SOURCE_BATCH and got[0].keyframes_used == 50
    cold = solve_batch(kfs, N_USERS, np.zeros(N_USERS), NoiseModel(), SolverParams())
    np.testing.assert_allclose(got[0].users_enu_m, cold.users_enu_m, atol=1e-9)


def _fly_fixes(ctl, tau_s: float, seconds: float, seed: int = 4) -> None:
    """Feed the controller fixes of a UAV flying east at 5 m/s, 20 Hz, whose GPS error drifts
    (Gauss–Markov, σ 1 m per axis, correlation time tau_s), with the exact velocity."""
    from mission.vehicle import PositionFix

    rng = np.random.default_rng(seed)
    dt = 0.05
    phi = np.exp(-dt / tau_s)
    err = rng.normal(0.0, 1.0, 2)
    for i in range(int(seconds / dt)):
        err = phi * err + np.sqrt(1.0 - phi**2) * rng.normal(0.0, 1.0, 2)
        enu = np.array([5.0 * i * dt + err[0], err[1], 40.0])
        lat, lon, alt = (float(v) for v in ctl.origin.enu_to_lla(enu))
        ctl.crews[0].on_fix(PositionFix(ctl._t0_mono + i * dt, lat, lon, alt, 40.0, (0.0, 5.0, 0.0)))


@pytest.mark.parametrize("tau_s", [20.0, 150.0])
def test_flight_estimates_an_unknown_gps_correlation_time_from_the_take_off_telemetry(tmp_path, tau_s):
    """With an external autopilot the mission leaves τ_gps unknown (PX4's EKF output drifts for
    minutes, the built-in vehicle's for seconds); the flight's estimator then uses τ estimated from
    the telemetry logged before the survey — the estimate replay makes from the same records — not
    the estimator's fixed default, so that the live stop rule and the final answer agree."""
    from estimator.gps import estimate_gps_tau_s
    from mission.log import read_mission_log
    from mission.vehicle import GeoFix
    from sitl_scenarios.scenario import controller_from_scenario

    sc = load_scenario("paper")
    ctl = controller_from_scenario(sc, None, None, tmp_path / "m.jsonl", planner="lawnmower",
                                   external_vehicle=True)
    assert ctl.noise.gps_tau_s is None
    ctl._at_home(GeoFix(43.6143, 7.0716, 150.0))
    _fly_fixes(ctl, tau_s, 60.0)
    noise = ctl._flight_noise()
    mlog = read_mission_log(tmp_path / "m.jsonl")
    pos = ctl.origin.lla_to_enu(mlog.tel_lla[:, 0], mlog.tel_lla[:, 1], mlog.tel_lla[:, 2])
    vel = mlog.tel_vel_ned_mps
    from_log = estimate_gps_tau_s(mlog.tel_t_s, pos, np.column_stack([vel[:, 1], vel[:, 0], -vel[:, 2]]), 1.0)
    assert noise.gps_tau_s == from_log
    assert 0.5 * tau_s <= noise.gps_tau_s <= 2.0 * tau_s, noise.gps_tau_s
    (ev,) = [e for e in mlog.events if e.get("kind") == "gps_tau"]
    assert ev["gps_tau_s"] == noise.gps_tau_s
    assert f"estimated from {len(mlog.tel_t_s)} telemetry records" in ev["message"] and len(mlog.tel_t_s) > 200
    assert ctl._flight_noise() is ctl.noise  # once: the records are dropped


def test_flight_keeps_the_default_gps_correlation_time_without_telemetry_to_estimate_it(tmp_path):
    from mission.log import read_mission_log
    from mission.vehicle import GeoFix
    from sitl_scenarios.scenario import controller_from_scenario

    sc = load_scenario("paper")
    ctl = controller_from_scenario(sc, None, None, tmp_path / "m.jsonl", planner="lawnmower",
                                   external_vehicle=True)
    ctl._at_home(GeoFix(43.6143, 7.0716, 150.0))
    _fly_fixes(ctl, 100.0, 2.0)  # 10 records: too few
    assert ctl._flight_noise() is ctl.noise and ctl.noise.gps_tau_used_s == 60.0
    (ev,) = [e for e in read_mission_log(tmp_path / "m.jsonl").events if e.get("kind") == "gps_tau"]
    assert "assuming 60 s" in ev["message"]
    # the τ assumed is logged with its value: replay's final answer uses it (mission.replay.resolve_gps_tau)
    assert (ev["gps_tau_s"], ev["estimated"]) == (60.0, False)


def test_flight_uses_a_known_gps_correlation_time_as_given(tmp_path):
    from sitl_scenarios.scenario import controller_from_scenario

    sc = load_scenario("paper")
    ctl = controller_from_scenario(sc, None, None, tmp_path / "m.jsonl", planner="lawnmower")
    assert ctl.noise.gps_tau_s == sc.vehicle.gps_tau_s and ctl._flight_noise() is ctl.noise
