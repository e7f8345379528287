"""Fault injection of the built-in vehicle as MAVSDK sees it: link pause, GPS loss, low battery,
and the same faults scheduled from a scenario's `[[faults.vehicle]]`."""

from __future__ import annotations

import asyncio

import pytest
from mavsdk.asyncio.plugins.param import ParamAsync
from mavsdk.plugins.telemetry import FixType, FlightMode

from sitl_scenarios.scenario import VehicleConfig
from sitl_scenarios.vehicle import FaultEvent, faults_from_scenario
from tests.test_vehicle_mavsdk import first, vehicle_link
from uavloc.errors import ScenarioError


def test_link_pause_disconnects_then_reconnects() -> None:
    """MAVSDK declares the link lost while the vehicle is silent (its timeout is about 3 wall
    seconds; the pause lasts 6), and back only once the heartbeats resume; meanwhile the vehicle
    keeps flying (here: sitting) on its own. Checked by the order of events, not by how long each
    took (a loaded machine delays them all)."""
    speedup = 4.0

    async def run() -> None:
        async with vehicle_link("builtin", speedup=speedup) as link:
            states = link.system.is_connected_state()
            assert await link.system.is_connected()
            t_pause_s = link.sim.state().t_s
            link.sim.pause_link(6.0 * speedup)  # 6 wall seconds
            assert not link.sim.state().link_up
            await first(states, lambda c: c is False, 30.0)
            await first(states, lambda c: c is True, 30.0)
            state = link.sim.state()
            assert state.link_up and state.t_s >= t_pause_s + 6.0 * speedup  # only after the pause
            # telemetry flows again
            await first(link.telemetry.subscribe_position(), lambda p: True, 10.0)

    asyncio.run(run())


def test_gps_loss_shows_in_health_and_fix_then_recovers() -> None:
    async def run() -> None:
        async with vehicle_link("builtin", speedup=5.0) as link:
            tel = link.telemetry
            await first(tel.subscribe_health(), lambda h: h.is_global_position_ok and h.is_armable, 10.0)
            link.sim.lose_gps()
            health = await first(tel.subscribe_health(), lambda h: not h.is_global_position_ok, 5.0)
            assert not health.is_armable
            await first(tel.subscribe_gps_info(), lambda g: g.fix_type == FixType.NO_FIX, 5.0)
            link.sim.restore_gps()
            await first(tel.subscribe_health(), lambda h: h.is_global_position_ok and h.is_armable, 5.0)
            await first(tel.subscribe_gps_info(), lambda g: g.fix_type == FixType.FIX_3D, 5.0)

    asyncio.run(run())


def test_low_battery_in_battery_stream_and_critical_triggers_rtl() -> None:
    """The battery stream shows the drop; with COM_LOW_BAT_ACT = 3 (set through MAVSDK's param
    plugin, an INT32 in PX4's byte-wise encoding) a critical level makes the vehicle return."""
    async def run() -> None:
        async with vehicle_link("builtin", speedup=25.0) as link:
            tel, act = link.telemetry, link.action
            param = ParamAsync(link.system)
            full = await first(tel.subscribe_battery(), lambda b: b.remaining_percent > 0, 5.0)
            assert full.remaining_percent == pytest.approx(100.0, abs=1.0)
            await param.set_param_int("COM_LOW_BAT_ACT", 3)
            assert await param.get_param_int("COM_LOW_BAT_ACT") == 3
            assert link.sim.param("COM_LOW_BAT_ACT") == 3
            await first(tel.subscribe_health(), lambda h: h.is_global_position_ok and h.is_home_position_ok, 10.0)
            await act.set_takeoff_altitude(10.0)
            await act.arm()
            await act.takeoff()
            await first(tel.subscribe_position(), lambda p: p.relative_altitude_m > 9.0, 10.0)
            # PX4 switches takeoff -> hold only once the climb has settled; wait for that, not for the
            # altitude alone (the mode can still read "takeoff" at 9.x m on a loaded machine)
            await first(tel.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 10.0)

            link.sim.set_battery_pct(12.0)  # low, not critical: warning only
            low = await first(tel.subscribe_battery(), lambda b: b.remaining_percent < 15.0, 5.0)
            assert low.remaining_percent == pytest.approx(12.0, abs=1.0)
            assert low.voltage_v < full.voltage_v
            assert link.sim.state().mode == "hold"

            link.sim.set_battery_pct(6.0)  # critical
            await first(tel.subscribe_flight_mode(), lambda m: m == FlightMode.RETURN_TO_LAUNCH, 5.0)

    asyncio.run(run())


def test_scheduled_faults_from_scenario_table() -> None:
    faults = faults_from_scenario({
        "vehicle": [
            {"kind": "gps_loss", "at_s": 3.0, "duration_s": 20.0},
            {"kind": "low_battery", "at_s": 4.0, "battery_pct": 14.0},
        ],
        "gnb": {"drop_every": 3},  # someone else's: ignored here
    })
    assert faults == [FaultEvent("gps_loss", 3.0, 20.0, None), FaultEvent("low_battery", 4.0, None, 14.0)]

    async def run() -> None:
        async with vehicle_link("builtin", speedup=10.0, faults=faults,
                                vehicle=VehicleConfig(gps_sigma_m=0.5)) as link:
            tel = link.telemetry
            await first(tel.subscribe_health(), lambda h: h.is_global_position_ok, 5.0)
            await first(tel.subscribe_health(), lambda h: not h.is_global_position_ok, 5.0)
            await first(tel.subscribe_battery(), lambda b: b.remaining_percent < 15.0, 5.0)
            await first(tel.subscribe_health(), lambda h: h.is_global_position_ok, 5.0)
            assert link.sim.state().t_s > 23.0

    asyncio.run(run())


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ({"vehicle": {"kind": "gps_loss"}}, "expected a list"),
        ({"vehicle": [{"kind": "meteor", "at_s": 1.0}]}, r"vehicle\[0\].kind' = 'meteor': must be one of"),
        ({"vehicle": [{"kind": "gps_loss", "at_s": 1.0, "durration_s": 3.0}]}, "unknown key"),
        ({"vehicle": [{"kind": "gps_loss"}]}, "at_s"),
        ({"vehicle": [{"kind": "link_pause", "at_s": 1.0}]}, "positive duration"),
        ({"vehicle": [{"kind": "low_battery", "at_s": 1.0, "battery_pct": 120.0}]}, "battery_pct"),
        ({"vehicle": [{"kind": "gps_loss", "at_s": "soon"}]}, "at_s' = 'soon': expected a number"),
        ({"vehicle": [{"kind": "gps_loss", "at_s": float("inf")}]}, "finite number"),
    ],
)
def test_bad_fault_tables_are_scenario_errors(table: dict, match: str) -> None:
    with pytest.raises(ScenarioError, match=match):
        faults_from_scenario(table)
