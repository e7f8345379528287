"""A fleet's simulators (docs/fleet.md): the built-in vehicles at their launch points with their own
system ids, and simulated gNBs sharing one cell attachment, talked to over their real TCP protocols."""

from __future__ import annotations

import asyncio
import re
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from mission.gnb import GnbConfig, OaiGnbClient
from mission.gnb.oai import PROMPT_GNB
from mission.gnb.tracer import TTracerClient
from sitl_scenarios import sim_runner
from sitl_scenarios.fleet import scenario_launch_points_enu_m, vehicle_home
from sitl_scenarios.gnb import SharedCells, SimulatedGnb
from sitl_scenarios.scenario import load_scenario, scenario_from_dict, user_tables
from sitl_scenarios.sim_runner import SimulatedMission
from sitl_scenarios.vehicle import VehicleSimulator
from uavloc.errors import GnbNoMeasurementError, SimulatorError

RNTI_A, RNTI_B = 0x4601, 0x4602


def run(coro, timeout_s: float = 20.0):
    """Run a test coroutine under a hard timeout: a hang is a failure, not a stuck test run."""

    async def guarded():
        async with asyncio.timeout(timeout_s):
            return await coro

    return asyncio.run(guarded())


def two_cells_scenario_dict() -> dict:
    """Two vehicles; UE a next to vehicle 0's gNB, UE b next to vehicle 1's and in reach of both."""
    users = [{"id": "a", "rnti": hex(RNTI_A), "east_m": 10.0, "north_m": 0.0},
             {"id": "b", "rnti": hex(RNTI_B), "east_m": 140.0, "north_m": 0.0}]
    return {"name": "two-cells", "seed": 5, **user_tables(users), "vehicles": [{"id": "uav1"}, {"id": "uav2"}],
            "radio": {"coverage_m": 200.0, "s0_m": 1.0, "ue_sawtooth_amplitude_m": 0.0}}


def two_cells_scenario():
    return scenario_from_dict(two_cells_scenario_dict())


def client_config(gnb: SimulatedGnb, **kw) -> GnbConfig:
    base = {"port": gnb.port, "request_timeout_s": 0.5, "connect_timeout_s": 0.5, "retries": 1,
            "backoff_initial_s": 0.005, "backoff_max_s": 0.02}
    base.update(kw)
    return GnbConfig(**base)


async def ask(gnb: SimulatedGnb, line: str) -> str:
    """One request over the gNB's telnet port; its answer without the prompt."""
    r, w = await asyncio.open_connection("127.0.0.1", gnb.port)
    try:
        w.write(line.encode() + b"\n")
        return (await r.readuntil(PROMPT_GNB.encode())).decode()[: -len(PROMPT_GNB)]
    finally:
        w.close()


async def until(condition, timeout_s: float = 5.0) -> None:
    """Poll `condition()` until it holds (the T server's occasions come in real time)."""
    async with asyncio.timeout(timeout_s):
        while not condition():
            await asyncio.sleep(0.02)


# ---------------------------------------------------------------------------------------------
# the built-in vehicles


def test_each_vehicle_has_its_system_id_and_takes_off_from_its_launch_point():
    sc = load_scenario("two_uavs")
    launch = scenario_launch_points_enu_m(sc)
    assert launch.shape == (2, 3) and np.linalg.norm(launch[0] - launch[1]) == pytest.approx(20.0)
    sims = [VehicleSimulator.from_scenario(sc, i, target=None, bind=("127.0.0.1", 0)) for i in range(2)]
    assert [s.system_id for s in sims] == [1, 2]
    assert [s.param("MAV_SYS_ID") for s in sims] == [1.0, 2.0]
    for i, s in enumerate(sims):
        home_enu_m = sc.origin_geo.lla_to_enu(s.origin.lat_deg, s.origin.lon_deg, s.origin.alt_m)
        np.testing.assert_allclose(home_enu_m, launch[i], atol=1e-6)
        assert s.origin == vehicle_home(sc, i)
    with pytest.raises(SimulatorError, match="vehicle index must be 0..1"):
        VehicleSimulator.from_scenario(sc, 2)


def test_a_vehicle_fault_strikes_the_vehicle_it_names():
    sc = scenario_from_dict({**two_cells_scenario_dict(), "faults": {"vehicle": [
        {"kind": "gps_loss", "at_s": 5.0, "vehicle": "uav2"}, {"kind": "link_pause", "at_s": 1.0, "duration_s": 2.0}]}})
    kinds = [[ev.kind for ev in VehicleSimulator.from_scenario(sc, i, target=None)._faults.scheduled]
             for i in range(2)]
    assert kinds == [["link_pause"], ["gps_loss"]]


def test_vehicle_0_of_a_one_vehicle_scenario_is_as_before():
    sc = load_scenario("paper")
    sim = VehicleSimulator.from_scenario(sc, target=None)
    assert sim.system_id == 1 and sim.origin == sc.origin_geo


def test_vehicle_2_speaks_mavlink_as_system_2():
    sc = load_scenario("two_uavs")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        gcs.settimeout(0.2)
        sim = VehicleSimulator.from_scenario(sc, 1, speedup=5.0, target=("127.0.0.1", gcs.getsockname()[1]),
                                             bind=("127.0.0.1", 0))
        parser = mavlink.MAVLink(None)
        with sim:
            deadline = time.monotonic() + 5.0
            beat = None
            while beat is None and time.monotonic() < deadline:
                try:
                    data = gcs.recv(4096)
                except TimeoutError:
                    continue
                beat = next((m for m in parser.parse_buffer(data) or [] if m.get_type() == "HEARTBEAT"), None)
    assert beat is not None and beat.get_srcSystem() == 2


# ---------------------------------------------------------------------------------------------
# gNBs over one cell attachment


def test_a_ue_is_served_by_one_gnb_of_the_fleet_and_reattaches_with_a_random_access(tmp_path: Path):
    sc = two_cells_scenario()
    # gNB 0 over UE a; gNB 1 40 m up over UE b, which gNB 0 also reaches (≈ 145 m of 200)
    where = np.array([[0.0, 0.0, 40.0], [150.0, 0.0, 40.0]])
    cells = SharedCells.of_scenario(sc, lambda: where)
    logs = [tmp_path / "gnb0.log", tmp_path / "gnb1.log"]

    async def body():
        async with SimulatedGnb(sc, lambda: where[0], port=0, log_path=logs[0], cell=cells.cell(0), t_port=0) as g0, \
                SimulatedGnb(sc, lambda: where[1], port=0, log_path=logs[1], cell=cells.cell(1), seed=6) as g1, \
                OaiGnbClient(client_config(g0)) as c0, OaiGnbClient(client_config(g1)) as c1, \
                TTracerClient("127.0.0.1", g0.t_port) as tracer:
            assert await c0.discover() == [RNTI_A]
            assert await c1.discover() == [RNTI_B]
            assert await c1.request("ci get_single_rnti") == f"single UE RNTI {RNTI_B:04x}\n"
            assert (await c1.measure(RNTI_B)).range_m == pytest.approx(41.2, abs=6.0)
            with pytest.raises(GnbNoMeasurementError, match="not connected"):
                await c0.measure(RNTI_B)  # in gNB 0's reach, but gNB 1's UE
            # as for an RNTI it does not have: the same line as for one no gNB has
            assert await c0.request(f"rtt pdcch_order {RNTI_B:04x}") == f"error rnti {RNTI_B:04x} not connected\n"
            assert await c0.request("rtt pdcch_order 0999") == "error rnti 0999 not connected\n"
            await until(lambda: tracer.tracker.counts.rars >= 1)  # UE a's random access in gNB 0's trace
            await asyncio.sleep(0.2)  # SRS occasions of gNB 0: no other random access
            rars_before = tracer.tracker.counts.rars
            log_before = logs[0].read_text() if logs[0].exists() else ""

            where[1] = [600.0, 0.0, 40.0]  # gNB 1 flies out of UE b's reach
            assert await c1.discover() == []
            assert await c0.discover() == [RNTI_A, RNTI_B]
            got = await c0.measure(RNTI_B)
            where[1] = [150.0, 0.0, 40.0]  # back over b: a connected UE does not reselect
            assert await c0.discover() == [RNTI_A, RNTI_B] and await c1.discover() == []
            await until(lambda: tracer.tracker.counts.rars >= 2)
            return rars_before, log_before, got, tracer.tracker.counts.rars, tracer.tracker.ues()

    rars_before, log_before, got, rars_after, traced = run(body())
    assert rars_before == 1 and rars_after == 2 and set(traced) == {RNTI_A, RNTI_B}  # the RAR of b's attach
    assert "RA-Msg2" not in log_before  # the UEs the fleet started with attached before the log
    assert got.range_m == pytest.approx(float(np.linalg.norm([140.0, 0.0, -40.0])), abs=6.0)
    text = logs[0].read_text()
    assert text.count("Generating RA-Msg2") == 1 and f"(rnti: {RNTI_B:04x}" in text  # b keeps its RNTI
    assert "RA-Msg2" not in (logs[1].read_text() if logs[1].exists() else "")
    assert cells.attachment.attaches.tolist() == [1, 2]


def test_a_gnb_that_stops_leaves_the_air_and_its_ues_attach_to_the_others():
    sc = two_cells_scenario()
    where = np.array([[0.0, 0.0, 40.0], [150.0, 0.0, 40.0]])
    cells = SharedCells.of_scenario(sc, lambda: where)

    async def body():
        async with SimulatedGnb(sc, lambda: where[0], port=0, cell=cells.cell(0)) as g0:
            async with SimulatedGnb(sc, lambda: where[1], port=0, cell=cells.cell(1)):
                assert await ask(g0, "ci get_single_rnti") == f"single UE RNTI {RNTI_A:04x}\n"
            return await ask(g0, "ci get_single_rnti"), cells.update().tolist()

    assert run(body()) == ("different number of UEs\n", [0, 0])
    assert not cells.on_air.any()  # gNB 0 has stopped too


def test_a_crashing_ci_on_another_cells_ue_crashes_the_gnb_as_oai():
    """`ci force_reestab <rnti>` of a UE another cell serves is an RNTI this gNB does not have."""
    sc = two_cells_scenario()
    where = np.array([[0.0, 0.0, 40.0], [150.0, 0.0, 40.0]])
    cells = SharedCells.of_scenario(sc, lambda: where)

    async def body():
        async with SimulatedGnb(sc, lambda: where[0], port=0, cell=cells.cell(0)) as g0:
            r, w = await asyncio.open_connection("127.0.0.1", g0.port)
            w.write(f"ci force_reestab {RNTI_B:04x}\n".encode())
            got = await r.read()
            w.close()
            return got, g0.crashed

    got, crashed = run(body())
    assert got == b"" and crashed is not None and f"{RNTI_B:04x}" in crashed


def test_shared_cells_refuse_positions_of_another_fleet():
    sc = two_cells_scenario()
    cells = SharedCells.of_scenario(sc, lambda: np.zeros((3, 3)))
    with pytest.raises(SimulatorError, match=r"expected \(2, 3\)"):
        cells.update()
    with pytest.raises(SimulatorError, match="cell index must be 0..1"):
        cells.cell(2)


# ---------------------------------------------------------------------------------------------
# SimulatedMission of a fleet


def test_a_simulated_fleet_starts_a_vehicle_and_a_gnb_per_vehicle(tmp_path: Path, monkeypatch):
    """two_uavs: two built-in vehicles, two gNBs sharing one attachment, the controller given lists
    (a stand-in here: the fleet's controller is built elsewhere)."""
    sc = load_scenario("two_uavs")
    seen = {}

    def controller(scenario, vehicle, gnb, log_path, **kwargs):
        seen.update(vehicle=vehicle, gnb=gnb, truth=kwargs["truth"])
        return None

    monkeypatch.setattr(sim_runner, "controller_from_scenario", controller)

    async def body():
        async with SimulatedMission(sc, tmp_path / "m.jsonl", speedup=5.0) as m:
            assert [s.system_id for s in m.vehicle_sims] == [1, 2]
            assert len(m.vehicles) == len(m.gnb_sims) == len(m.gnb_clients) == 2
            assert m.vehicle_sim is m.vehicle_sims[0] and m.gnb_client is m.gnb_clients[0]
            assert len({c.config.port for c in m.gnb_clients}) == 2
            # on the ground at their launch points (10 m east and west of the origin)
            np.testing.assert_allclose(m._fleet_positions()[:, :2], scenario_launch_points_enu_m(sc)[:, :2],
                                       atol=0.5)
            listed = [await c.discover() for c in m.gnb_clients]
            await m.kill_gnb(1)
            assert m.gnb_sims[1] is None and m.gnb_sim is m.gnb_sims[0]
            listed.append(await m.gnb_clients[0].discover())
            return listed

    listed = run(body())
    # on the ground a gNB reaches ~120 m (sitl_scenarios.radio.reach_m): the groups, 350 m and more
    # away, attach once the vehicles are in the air
    assert listed == [[], [], []]
    assert isinstance(seen["vehicle"], list) and isinstance(seen["gnb"], list) and len(seen["gnb"]) == 2
    home = vehicle_home(sc, 0)  # the mission's frame: vehicle 0's home, 10 m east of the origin
    truth = seen["truth"](home)
    np.testing.assert_allclose(truth[0, :2], [-360.0 - 10.0, 80.0], atol=0.01)


def test_a_one_vehicle_mission_hands_the_controller_its_single_vehicle_and_gnb(tmp_path: Path, monkeypatch):
    seen = {}
    monkeypatch.setattr(sim_runner, "controller_from_scenario",
                        lambda scenario, vehicle, gnb, log_path, **kw: seen.update(vehicle=vehicle, gnb=gnb))

    async def body():
        async with SimulatedMission(load_scenario("paper"), tmp_path / "m.jsonl", speedup=5.0) as m:
            assert m.cells is None and m.gnb_sim.cell is None and m.vehicle_sim.origin == m.scenario.origin_geo
            return m.vehicles, m.gnb_clients

    vehicles, clients = run(body())
    assert seen["vehicle"] is vehicles[0] and seen["gnb"] is clients[0] and len(vehicles) == len(clients) == 1


def test_a_gnb_on_the_ground_reaches_less_far_than_one_in_the_air():
    """The two-ray breakpoint (sitl_scenarios.radio.reach_m): in the air the cell's coverage, on the
    ground √(R0 d_bp); a cell whose vehicle lands loses its far UEs, which attach to a cell in the air."""
    from sitl_scenarios.radio import CellAttachment, reach_m

    assert float(reach_m(450.0, 40.5)) == 450.0
    landed = float(reach_m(450.0, 0.5))
    lam_m = 299_792_458.0 / 3.31968e9
    assert landed == pytest.approx(np.sqrt(450.0 * 4.0 * 0.5 * 1.5 / lam_m)) and 100.0 < landed < 140.0
    users = np.array([[300.0, 0.0, 0.0], [-300.0, 0.0, 0.0]])
    cells = CellAttachment(users, 450.0)
    air = np.array([[250.0, 0.0, 40.0], [-250.0, 0.0, 40.0]])
    assert cells.update(air).tolist() == [0, 1]
    # vehicle 0 lands 300 m from its UE, vehicle 1 flies over to it: the UE changes cells once
    assert cells.update(np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 40.0]])).tolist() == [1, 1]
    assert cells.attaches.tolist() == [2, 1]


def test_a_fleet_whose_launch_points_leave_the_fence_is_refused_before_any_vehicle_arms(tmp_path: Path):
    """two_uavs with separation_m = 500 and a third vehicle (issue 49), past the scenario's own check
    (which refuses it at load, tests/test_fleet_config.py): the flight holds every vehicle to the home
    check, none arms, the error names uav2 and uav3, and the aborted fleet's result has its vehicles."""
    import dataclasses

    from mission.log import read_mission_log
    from mission.status import mission_document

    sc = load_scenario("two_uavs")
    m = sc.mission
    m = dataclasses.replace(m, vehicles=(*m.vehicles, dataclasses.replace(m.vehicles[0], id="uav3")),
                            safety=dataclasses.replace(m.safety, separation_m=500.0))
    sc = dataclasses.replace(sc, mission=m)

    async def body():
        async with SimulatedMission(sc, tmp_path / "m.jsonl", speedup=20.0, planner="lawnmower") as sim:
            return await sim.run()

    res = run(body(), timeout_s=90.0)
    assert res.status == "aborted", res.reason
    assert res.reason.startswith("not taking off: no vehicle of the fleet arms: "), res.reason
    # the homes are the vehicles' GPS fixes at (-145.8, ±252.5): a few metres of GPS error
    assert re.search(r"uav2's home \(-14\d\.\d, 25\d\.\d\) m is outside the geofence polygon", res.reason)
    assert re.search(r"uav3's home \(-14\d\.\d, -25\d\.\d\) m is outside the geofence polygon", res.reason)
    assert "uav1" not in res.reason
    kinds = [e.get("kind") for e in read_mission_log(tmp_path / "m.jsonl").events]
    assert "abort" in kinds and "arm" not in kinds and "takeoff" not in kinds
    doc = mission_document(res)
    assert [v["id"] for v in doc["vehicles"]] == ["uav1", "uav2", "uav3"]
    assert doc["separation_breaches"] == 0 and not any(v["landed"] is None for v in doc["vehicles"])


def test_a_fleet_not_through_preflight_in_time_aborts_naming_the_state_and_the_vehicles(tmp_path: Path):
    """PREFLIGHT, once every home is known, has a wall bound (ControllerConfig.preflight_timeout_s;
    each vehicle's wait for its home has ready_timeout_s): a fleet not through it (here a bound no
    gNB probe meets) aborts, naming PREFLIGHT and what each vehicle still waits for."""
    async def body():
        async with SimulatedMission(load_scenario("two_uavs"), tmp_path / "m.jsonl", speedup=20.0,
                                    planner="lawnmower", controller_overrides={"preflight_timeout_s": 0.001}) as sim:
            return await sim.run()

    res = run(body(), timeout_s=60.0)
    assert res.status == "aborted", res.reason
    assert res.reason == ("PREFLIGHT not done within 0.001 s (wall): still waiting for uav1: its gNB's probe, "
                          "uav2: its gNB's probe"), res.reason
    assert [v.id for v in res.result.vehicles] == ["uav1", "uav2"] and res.result.separation_breaches == 0
