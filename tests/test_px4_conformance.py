"""The built-in vehicle held to the recorded real PX4 (v1.18 SITL, SIH quadrotor).

The recorded flights (../shared/data/px4-v1.18-sih/, `legs` and `gpsloss`) are reduced to figures
by sitl_scenarios.px4_conformance; `tests/data/px4_figures.json` holds them, so these tests run
away from ../shared too (and check the file against the recordings where they are present). The
built-in vehicle flies the same procedures over MAVLink (pymavlink, the recorded commands, at a
speedup) and its own telemetry log is measured by the same code. Every figure must agree within
TOLERANCE (15 %); the mode/heartbeat sequences must be PX4's.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from sitl_scenarios.px4_conformance import (
    fly_builtin,
    gpsloss_figures,
    legs_figures,
    read_telemetry,
    stream_rates_hz,
)

pytestmark = [pytest.mark.sim, pytest.mark.slow]

FIGURES = Path(__file__).parent / "data" / "px4_figures.json"
RECORDING = "px4-v1.18-sih"
TOLERANCE = 0.15
#: the legs flight at this speedup (kinematics), the GPS-loss flight at this one (its 50 Hz
#: streams carried in full: the stream rates are measured on it)
LEGS_SPEEDUP, GPSLOSS_SPEEDUP = 16.0, 2.0
#: streams the recorded PX4 GCS link carries that the built-in vehicle does not send (nothing of
#: uavloc reads them): actuator, attitude and global position targets, estimator and sensor
#: reports, Remote ID
NOT_MODELLED = {"ATTITUDE_TARGET", "DISTANCE_SENSOR", "ESTIMATOR_STATUS", "OPEN_DRONE_ID_LOCATION",
                "OPEN_DRONE_ID_SYSTEM", "POSITION_TARGET_GLOBAL_INT", "SCALED_PRESSURE", "SERVO_OUTPUT_RAW"}
#: what the built-in vehicle streams beyond the recorded link: SYSTEM_TIME times uavloc's telemetry
#: (mission.vehicle; PX4 sends it on its API link)
API_LINK_ONLY = {"SYSTEM_TIME"}
LEGS = ["15m_east", "40m_north", "80m_east", "300m_north"]

PX4 = json.loads(FIGURES.read_text())


def _close(builtin: float, px4: float) -> bool:
    return math.isfinite(builtin) and abs(builtin - px4) <= TOLERANCE * abs(px4)


@pytest.fixture(scope="module")
def builtin_legs(tmp_path_factory) -> dict:
    return legs_figures(fly_builtin("legs", tmp_path_factory.mktemp("legs") / "legs.tlog", speedup=LEGS_SPEEDUP))


@pytest.fixture(scope="module")
def builtin_gpsloss_tlog(tmp_path_factory) -> Path:
    return fly_builtin("gpsloss", tmp_path_factory.mktemp("gpsloss") / "gpsloss.tlog", speedup=GPSLOSS_SPEEDUP,
                       gps_loss_below_mps=PX4["gpsloss"]["speed_at_loss_mps"])


def test_the_figures_file_is_what_the_recordings_give(shared_data):
    rec = shared_data / RECORDING
    assert legs_figures(rec / "legs.tlog.gz") == PX4["legs"]
    got = gpsloss_figures(rec / "gpsloss.tlog.gz")
    assert {k: round(v, 4) if isinstance(v, float) else v for k, v in got.items()} == PX4["gpsloss"]


@pytest.mark.parametrize("figure", ["height_m", "t50_s", "t90_s", "peak_climb_mps"])
def test_takeoff_climb_within_15_percent_of_px4(builtin_legs, figure):
    b, p = builtin_legs["takeoff"][figure], PX4["legs"]["takeoff"][figure]
    assert _close(b, p), f"take-off {figure}: built-in {b:.3f}, PX4 {p:.3f}"


@pytest.mark.parametrize(("leg", "figure"), [(leg, f) for leg in LEGS
                                              for f in ("peak", "p99", "stop_s", "settle_s", "overshoot")])
def test_leg_within_15_percent_of_px4(builtin_legs, leg, figure):
    b, p = builtin_legs["legs"][LEGS.index(leg)][figure], PX4["legs"]["legs"][LEGS.index(leg)][figure]
    assert _close(b, p), f"leg {leg} {figure}: built-in {b:.3f}, PX4 {p:.3f}"


@pytest.mark.parametrize("figure", ["height_m", "return_p99_mps", "descent_peak_mps", "descent_mean_mps",
                                    "to_landed_s"])
def test_rtl_within_15_percent_of_px4(builtin_legs, figure):
    b, p = builtin_legs["rtl"][figure], PX4["legs"]["rtl"][figure]
    assert _close(b, p), f"RTL {figure}: built-in {b:.3f}, PX4 {p:.3f}"


def test_mode_and_heartbeat_sequence_is_px4s(builtin_legs):
    """[armed, main mode, sub mode, system status] at each change: LOITER standby, TAKEOFF selected
    disarmed, armed and climbing, LOITER, RTL, disarmed in LOITER."""
    assert builtin_legs["modes"] == PX4["legs"]["modes"]


def test_streams_are_px4s_and_their_rates_within_15_percent(builtin_gpsloss_tlog):
    px4 = PX4["legs"]["rates_hz"]
    builtin = stream_rates_hz(read_telemetry(builtin_gpsloss_tlog))
    assert set(builtin) - API_LINK_ONLY <= set(px4), set(builtin) - API_LINK_ONLY - set(px4)
    assert set(px4) - set(builtin) == NOT_MODELLED
    off = {k: (builtin[k], px4[k]) for k in set(px4) & set(builtin) if not _close(builtin[k], px4[k])}
    assert not off, f"stream rates [Hz] (built-in, PX4) off by more than {TOLERANCE:.0%}: {off}"


@pytest.mark.parametrize("figure", [k for k, v in PX4["gpsloss"].items() if isinstance(v, float)])
def test_gps_loss_within_15_percent_of_px4(builtin_gpsloss_tlog, figure):
    """PX4 keeps its position from dead reckoning for a while (published at its full rate), then
    lands blind where it is and disarms."""
    b, p = gpsloss_figures(builtin_gpsloss_tlog)[figure], PX4["gpsloss"][figure]
    assert _close(b, p), f"GPS loss {figure}: built-in {b:.3f}, PX4 {p:.3f}"


def test_gps_loss_failsafe_modes_are_px4s(builtin_gpsloss_tlog):
    """After the fix went: AUTO.LAND with system status CRITICAL, then disarmed in LOITER, UNINIT
    (its pre-arm checks fail without GPS)."""
    assert gpsloss_figures(builtin_gpsloss_tlog)["modes_after_loss"] == PX4["gpsloss"]["modes_after_loss"]
