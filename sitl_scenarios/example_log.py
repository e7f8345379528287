"""Generate an example mission log from a scenario, without a vehicle or a gNB process.

The UAV flies a fixed survey pattern (out from home, a circle around the users' centroid, back)
at the scenario's altitude; every Δ metres the radio model measures every user in coverage, the
GPS fix is the true position plus the vehicle's GPS error (white, or Gauss–Markov with
`vehicle.gps_tau_s`, like an autopilot's EKF output), telemetry carries the velocity
(`vel_ned_mps`), the UEs are the scenario's (commercial ones with their clock sawtooth), and
everything is written as a
`uavloc-mission/1` log with raw fields, `toa_s` and `truth`. Deterministic for a given seed.

    python -m sitl_scenarios.example_log --scenario paper --seed 1 -o example.jsonl
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from estimator.ranging import toa_s_from_raw
from mission.log import MissionLogWriter
from sitl_scenarios.radio import RadioModel
from sitl_scenarios.scenario import Scenario, load_scenario
from sitl_scenarios.vehicle.sensors import GpsError
from uavloc.errors import ScenarioError

log = logging.getLogger(__name__)

FIXED_START_UTC = "2026-01-01T00:00:00.000+00:00"


def survey_path_enu_m(scenario: Scenario, radius_m: float = 50.0, n_turns: float = 1.0) -> np.ndarray:
    """Waypoints (P, 3) [m, ENU]: climb at home, go to a circle of `radius_m` around the users'
    centroid, fly it `n_turns` times, come back home."""
    alt = scenario.mission.flight.altitude_m
    users = np.array([[u.east_m, u.north_m] for u in scenario.users])
    c = users.mean(axis=0)
    angles = np.linspace(0.0, 2 * np.pi * n_turns, max(int(72 * n_turns), 8) + 1)
    circle = np.c_[c[0] + radius_m * np.cos(angles), c[1] + radius_m * np.sin(angles), np.full(len(angles), alt)]
    home = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, alt]])
    return np.vstack([home, circle, [[0.0, 0.0, alt]]])


def path_direction(path_enu_m: np.ndarray, s_m: float) -> np.ndarray:
    """(3,) unit direction of the path at arc length s_m (the segment that starts at or before it;
    zeros on a zero-length one). By arc length, not by the nearest segment: the way out and the way
    back of the path overlap, and the nearest segment there may be the one flown the other way."""
    ab = np.diff(path_enu_m, axis=0)
    seg = np.linalg.norm(ab, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    i = int(np.clip(np.searchsorted(cum, s_m, side="right") - 1, 0, len(seg) - 1))
    return ab[i] / seg[i] if seg[i] > 1e-9 else np.zeros(3)


def densify(path_enu_m: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step_m` along a polyline (P, 3) and their arc length [m]."""
    seg = np.linalg.norm(np.diff(path_enu_m, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s_new = np.arange(0.0, s[-1] + 1e-9, step_m)
    pts = np.stack([np.interp(s_new, s, path_enu_m[:, j]) for j in range(3)], axis=1)
    return pts, s_new


def generate(scenario: Scenario, out: Path, seed: int | None = None, radius_m: float = 50.0,
             n_turns: float = 1.0, start_utc: str = FIXED_START_UTC) -> dict:
    """Write the example log to `out` (replaced if present). Returns counts."""
    seed = scenario.seed if seed is None else seed
    rng = np.random.default_rng(seed)
    radio = RadioModel(scenario, np.random.default_rng(rng.integers(2**63)))
    origin = scenario.origin_geo
    speed = scenario.vehicle.speed_mps
    sigma_gps = scenario.vehicle.gps_sigma_m
    tau_s = scenario.vehicle.gps_tau_s
    path = survey_path_enu_m(scenario, radius_m, n_turns)
    tel_pts, tel_s = densify(path, speed * 0.2)  # telemetry at 5 Hz (the controller's telemetry_log_hz)
    kf_pts, kf_s = densify(path, scenario.mission.flight.delta_m)
    out = Path(out)
    if out.exists():
        out.unlink()
    n_rtt = 0
    with MissionLogWriter(out) as w:
        w.write_header(
            origin,
            [{"id": u.id, "rnti": u.rnti, "ground_alt_m": origin.alt_m + u.up_m} for u in scenario.users],
            {"mu": scenario.radio.mu, "fs_hz": scenario.radio.fs_hz},
            noise=scenario.noise_model(),
            config={"generator": "sitl_scenarios.example_log", "scenario": scenario.name, "seed": seed,
                    "delta_m": scenario.mission.flight.delta_m},
            start_utc=start_utc,
        )
        truth_lat, truth_lon, truth_alt = origin.enu_to_lla(
            np.array([[u.east_m, u.north_m, u.up_m] for u in scenario.users]))
        w.write("truth", 0.0, users=[
            {"id": u.id, "lat_deg": float(truth_lat[k]), "lon_deg": float(truth_lon[k]), "alt_m": float(truth_alt[k])}
            for k, u in enumerate(scenario.users)])
        w.write("event", 0.0, message="takeoff")
        events = sorted([(s / speed, "tel", p, s) for s, p in zip(tel_s, tel_pts, strict=True)]
                        + [(s / speed, "kf", p, s) for s, p in zip(kf_s, kf_pts, strict=True) if p[2] > 1.0],
                        key=lambda e: e[0])
        gps_err = GpsError(sigma_gps, tau_s, rng)
        for t, kind, p, s_m in events:
            gps = p + gps_err.sample(t)
            lat, lon, alt = (float(x) for x in origin.enu_to_lla(gps))
            if kind == "tel":
                # the autopilot's velocity: speed along the path (north, east, down)
                v = speed * path_direction(path, s_m)
                w.write("telemetry", t, lat_deg=lat, lon_deg=lon, alt_m=alt,
                        vel_ned_mps=[round(float(v[1]), 3), round(float(v[0]), 3), round(float(-v[2]), 3)])
                continue
            for k, u in enumerate(scenario.users):
                raw = radio.measure(k, p, t)
                if raw is None:
                    continue
                w.write("rtt", t, user=u.id, uav={"lat_deg": lat, "lon_deg": lon, "alt_m": alt},
                        toa_s=toa_s_from_raw(raw.ta, raw.mu, raw.srs_peak, raw.fs_hz),
                        ta=raw.ta, mu=raw.mu, srs_peak=raw.srs_peak, fs_hz=raw.fs_hz, snr_db=round(raw.snr_db, 2))
                n_rtt += 1
        w.write("event", float(kf_s[-1] / speed), message="landed")
    log.info("wrote %s: %d rtt records over %.0f m", out, n_rtt, kf_s[-1])
    return {"rtt": n_rtt, "flown_m": float(kf_s[-1])}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="paper", help="scenario file or bundled name (default: paper)")
    ap.add_argument("--seed", type=int, help="random seed (default: the scenario's)")
    ap.add_argument("--radius", type=float, default=50.0, help="survey circle radius [m]")
    ap.add_argument("--turns", type=float, default=1.0, help="circle turns")
    ap.add_argument("-o", "--out", type=Path, required=True, help="output mission log (replaced)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        generate(load_scenario(args.scenario), args.out, args.seed, args.radius, args.turns)
    except ScenarioError as exc:
        log.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
