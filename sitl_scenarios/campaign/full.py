"""Full mode: one whole mission against the built-in MAVLink vehicle and the simulated OAI gNB.

Each run starts its own simulators on ports the OS chooses (UDP for MAVLink, TCP for the gNB's
telnet), so any number of runs can share a machine, and flies the mission controller exactly as
`uavloc sim` does, with the run's planner, estimator settings and seed. The estimator runs in a
thread of the run's own process (a campaign's unit of parallelism is the worker process; Dask's
worker processes are daemons and may not start children). Its mission log (in a
temporary folder) is then read back for the record:

- metres flown: the controller's own odometer (mission.vehicle.telemetry.odometer_m, dead band
  max(5 m, 8 σ_gps)) over the logged telemetry from the first waypoint on, read at each estimate;
- the accuracy track: every logged estimate against the scenario's truth (AccuracyTrack);
- replans: the waypoint records and their solve times.
"""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path

import numpy as np

from estimator.types import SolverParams
from sitl_scenarios.campaign.outcome import AccuracyTrack, Outcome
from sitl_scenarios.scenario import Scenario


def fly_full(sc: Scenario, planner_name: str, params: SolverParams, seed: int, targets_m: tuple[float, ...],
             speedup: float, gnb_transport: str = "telnet", gnb_mode: str = "rtt") -> Outcome:
    """Fly one scenario with the built-in vehicle and simulated gNB (its telnet server or its REST
    API: gnb_transport; its RTT command or its T tracer: gnb_mode); the Outcome of its mission log."""
    from mission.log import read_mission_log
    from sitl_scenarios.sim_runner import SimulatedMission

    with tempfile.TemporaryDirectory(prefix="uavloc-campaign-") as tmp:
        log_path = Path(tmp) / "mission.jsonl"

        async def main():
            async with SimulatedMission(sc, log_path=log_path, seed=seed, speedup=speedup, planner=planner_name,
                                        gnb_transport=gnb_transport, gnb_mode=gnb_mode,
                                        controller_overrides={"params": params,
                                                                      "estimator_mode": "thread"}) as sim:
                return await sim.run()

        result = asyncio.run(main())
        mlog = read_mission_log(log_path)
    return outcome_from_log(mlog, result, targets_m, sc.mission.noise.sigma_gps_m)


def outcome_from_log(mlog, result, targets_m: tuple[float, ...], sigma_gps_m: float) -> Outcome:
    """Outcome of a finished simulated mission from its parsed log and MissionResult: the accuracy
    track over its logged estimates, and the row's final figures from its Result."""
    from mission.vehicle.telemetry import odometer_m

    out = Outcome()
    out.plan_times_s = [float(w.get("solve_time_s") or 0.0) for w in mlog.waypoints]
    out.estimator_errors = [str(e.get("message", "")) for e in mlog.events if e.get("kind") == "estimator_error"]
    times = [e for e in mlog.events if e.get("kind") == "survey_time"]
    out.hover_s = sum(float(e.get("hover_s") or 0.0) for e in times)
    out.survey_s = sum(float(e.get("survey_s") or 0.0) for e in times)
    origin = mlog.header.origin
    truth = result.result.truth_enu_m()
    if truth is None or not mlog.estimates:
        return out.take_result(result.result)
    track = AccuracyTrack(truth, targets_m)
    # metres flown at time t: the odometer over the telemetry from the first waypoint on; a
    # fleet's, each vehicle's odometer over its own track, summed
    t0 = mlog.waypoints[0]["t"] if mlog.waypoints else 0.0
    odometers = []  # (times (T_v,), metres (T_v,)) of each vehicle
    for v in np.unique(mlog.tel_vehicle):
        sel = (mlog.tel_t_s >= t0) & (mlog.tel_vehicle == v)
        if sel.any():
            enu = np.asarray(origin.lla_to_enu(*mlog.tel_lla[sel].T), float).reshape(-1, 3)
            odometers.append((mlog.tel_t_s[sel], odometer_m(enu, max(5.0, 8.0 * sigma_gps_m))))
    ids = {u.id: k for k, u in enumerate(mlog.header.users)}
    k_users = len(ids)
    for rec in mlog.estimates:
        users_en = np.full((k_users, 2), np.nan)
        cov = np.full((k_users, 2, 2), np.nan)
        for u in rec.get("users", []):
            k = ids[u["id"]]
            users_en[k] = np.asarray(origin.lla_to_enu(u["lat_deg"], u["lon_deg"], u["alt_m"]), float)[:2]
            cov[k] = np.asarray(u["cov_en_m2"], float)
        at_m = float(sum(np.interp(rec["t"], tel_t, metres) for tel_t, metres in odometers))
        track.update(users_en, cov, at_m, float(rec["t"]) - t0)
    return track.fill(out).take_result(result.result)
