"""Failures surface (issue 12): a gNB that cannot measure the configured users stops the take-off
with the reason; a measurement module that disappears in flight sends the vehicle home after
gnb_lost_wait_s with the gNB's own words in the log; a bad mission file is refused by `uavloc fly`
before anything connects. End to end on the built-in vehicle and the simulated gNB."""

from __future__ import annotations

import asyncio

import pytest

from mission.cli import main
from mission.control.config import STATUS_ABORTED, STATUS_RETURNED
from mission.log import read_mission_log
from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission
from tests.test_mission_e2e import _run, _wait
from uavloc.errors import GnbPreflightError

SPEEDUP = 20.0




def _fly_with(tmp_path, prepare, **kw):
    """Fly `paper` after `prepare(sim)` changed the simulated gNB; (result, final vehicle state, log)."""
    sc = load_scenario("paper")
    log_path = tmp_path / "mission.jsonl"

    async def fly():
        async with SimulatedMission(sc, log_path, speedup=SPEEDUP, planner="lawnmower", **kw) as sim:
            prepare(sim)
            result = await sim.run()
            return result, sim.vehicle_sim.state()

    result, final = _run(fly())
    return result, final, read_mission_log(log_path)


@pytest.mark.sim
def test_no_take_off_when_the_gnb_lacks_the_rtt_module(tmp_path):
    def no_module(sim):
        sim.gnb_sim.rtt_module = "other"  # the gNB runs without the RTT telnet module

    result, final, mlog = _fly_with(tmp_path, no_module)
    assert result.status == STATUS_ABORTED and result.reason.startswith("not taking off"), result.reason
    assert "4601" in result.reason and "is not a softmodem command" in result.reason, result.reason
    assert not result.ok and result.not_located() == ["ue1"]
    kinds = [e.get("kind") for e in mlog.events]
    assert "arm" not in kinds and "takeoff" not in kinds and not final.armed and not final.in_air
    pre = next(e for e in mlog.events if e.get("kind") == "preflight_gnb")
    assert pre["ok"] is False and pre["rntis"] == ["4601"]


@pytest.mark.sim
def test_no_take_off_when_the_gnb_has_other_ues(tmp_path):
    def other_ue(sim):
        sim.gnb_sim.current_rnti[0] = 0x1234  # the UE the gNB serves is not the configured one

    result, final, mlog = _fly_with(tmp_path, other_ue)
    assert result.status == STATUS_ABORTED, result.reason
    assert "[1234]" in result.reason and "UE 4601 is not among them" in result.reason, result.reason
    assert not final.armed and "arm" not in [e.get("kind") for e in mlog.events]
    assert GnbPreflightError.__name__ in [e.get("error") for e in mlog.events if e.get("kind") == "abort"]


@pytest.mark.sim
def test_rtt_module_disappearing_in_flight_sends_the_vehicle_home_with_the_reason(tmp_path):
    wait_s = 10.0
    sc = load_scenario("paper")
    log_path = tmp_path / "mission.jsonl"

    async def fly():
        async with SimulatedMission(sc, log_path, speedup=SPEEDUP, planner="lawnmower",
                                    controller_overrides={"gnb_lost_wait_s": wait_s}) as sim:
            task = asyncio.create_task(sim.run())
            await _wait(lambda: sim.controller.measurements >= 5, 60, "5 measurements")
            t_gone = sim.gnb_sim.clock()
            sim.gnb_sim.faults.rtt_module_lost_at_s = t_gone  # the module is gone from now on
            result = await task
            return result, t_gone

    result, t_gone = _run(fly())
    assert result.status == STATUS_RETURNED and "gNB lost" in result.reason, result.reason
    assert "is not a softmodem command" in result.reason  # the gNB's own words
    assert result.landed and result.rtl_sent
    mlog = read_mission_log(log_path)
    ev = {e.get("kind"): e for e in mlog.events}
    assert "is not a softmodem command" in ev["gnb_lost"]["message"]
    assert ev["gnb_lost"]["t"] >= t_gone - 1.0
    # it flew on for gnb_lost_wait_s (mission seconds), then returned: nothing measured since
    assert ev["return"]["t"] - ev["gnb_lost"]["t"] >= wait_s
    assert ev["rtl"]["t"] >= ev["return"]["t"]
    # nothing measured since, but the round placed as the gNB went (its stamp is the measurement's
    # mission time, which the vehicle clock's mapping can put a few ms after the event's)
    assert sum(1 for t in mlog.rtt_t_s if t > ev["gnb_lost"]["t"]) <= len(sc.users)


@pytest.mark.parametrize(("extra", "words"), [
    ('[[users]]\nid = "ue9"\nrnti = "0x4609"\neast_m = 10.0\n', ["users[2].east_m", "never holds true positions"]),
    ('[flight]\nbudget_km = 1.0\n', ["flight.budget_km", "wrong unit", "'budget_m'"]),
    ('[radio]\nmu = 1\n', ["'radio'", "simulated world"]),
])
def test_fly_refuses_a_bad_mission_file_before_connecting(tmp_path, capsys, extra, words):
    from mission.config import example_mission_path

    text = example_mission_path().read_text(encoding="utf-8")
    if extra.startswith("[flight]"):
        text = text.replace("[flight]\n", "[flight]\nbudget_km = 1.0\n")
    elif extra.startswith("[["):
        text = text.replace("# Positions are offsets", extra + "\n# Positions are offsets")
    else:
        text += "\n" + extra
    bad = tmp_path / "bad.toml"
    bad.write_text(text, encoding="utf-8")
    # nothing listens on these: the mission file is refused before any connection is tried
    code = main(["fly", "--mission", str(bad), "--connect", "udpin://127.0.0.1:9", "--gnb", "127.0.0.1:9"])
    err = capsys.readouterr().err
    assert code == 1
    assert str(bad) in err
    for w in words:
        assert w in err, err


def test_fly_refuses_a_log_that_already_holds_a_mission_before_any_connection(tmp_path, capsys):
    """A log holds one mission: appending a second would make it unreadable for replay, and
    overwriting would lose the first. Refused before anything connects; the old log is untouched."""
    from mission.cli import main
    from mission.config import example_mission_path

    old = tmp_path / "mission.jsonl"
    old.write_text('{"type":"header","t":0.0}\n', encoding="utf-8")
    code = main(["fly", "--mission", str(example_mission_path()), "--connect", "udpin://127.0.0.1:9",
                 "--gnb", "127.0.0.1:9", "--log", str(old)])
    err = capsys.readouterr().err
    assert code == 1 and "already holds a mission" in err and str(old) in err, err
    assert old.read_text(encoding="utf-8") == '{"type":"header","t":0.0}\n'


@pytest.mark.sim
def test_a_full_disk_in_flight_sends_the_vehicle_home_and_keeps_the_log_whole(tmp_path):
    """Issue 21 #2: the mission log's disk fills during the survey: the vehicle is sent home (RTL
    seen on the vehicle), the log is whole up to the fault (no torn line), one clear message and
    no traceback, exit 1."""
    import subprocess

    import numpy as np

    from tests.fly_rig import REPO, external_fly_rig, tiny_disk, wait_for

    with tiny_disk(tmp_path) as disk, external_fly_rig(tmp_path, speedup=SPEEDUP) as rig:
        out = disk.path / "out"
        proc = subprocess.run(rig.fly_args("--out", str(out)), cwd=REPO, capture_output=True, text=True,
                              timeout=300, preexec_fn=disk.preexec)
        state = rig.vehicle.state()
        home = np.asarray(state.home_enu_m)

        def home_dist_m() -> float:
            return float(np.linalg.norm((rig.vehicle.state().pos_enu_m - home)[:2]))

        wait_for(lambda: home_dist_m() < 5.0, 60, "the vehicle back over home")
        raw = (out / "mission.jsonl").read_bytes()
        mlog = read_mission_log(out / "mission.jsonl")
        report_written = (out / "top_view.png").exists()
    err = proc.stderr + proc.stdout
    assert proc.returncode == 1, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    assert f"cannot write the mission log {out / 'mission.jsonl'}" in err, err[-3000:]
    assert state.mode == "return_to_launch" or not state.in_air, state.mode
    assert raw.endswith(b"\n") and len(raw) > disk.size_b // 2
    assert mlog.skipped_torn_line is None and len(mlog.rtt_t_s) > 5
    # sent home from the survey: far from home when the log stopped (and back over home since)
    last_enu = mlog.header.origin.lla_to_enu(*mlog.tel_lla[-1])
    assert np.linalg.norm(np.asarray(last_enu)[:2]) > 20.0
    assert not report_written  # no report half-written on the full disk


def test_fly_refuses_an_out_that_is_a_file_before_connecting(tmp_path):
    """Issue 21 #6: `fly --out FILE` was refused only after connecting (and with a traceback)."""
    import subprocess
    import sys

    from mission.config import example_mission_path
    from tests.fly_rig import REPO

    out = tmp_path / "results"
    out.write_text("not a folder\n", encoding="utf-8")
    # nothing listens on these: connecting would wait for the autopilot until the timeout
    proc = subprocess.run([sys.executable, "-m", "mission", "fly", "--mission", str(example_mission_path()),
                           "--connect", "udpin://127.0.0.1:9", "--gnb", "127.0.0.1:9", "--out", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert f"--out {out} is a file" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "waiting for an autopilot" not in proc.stderr
    assert out.read_text(encoding="utf-8") == "not a folder\n"


def test_sim_refuses_a_folder_holding_a_mission(tmp_path, capsys):
    """Issue 21 #9: `sim --out DIR` deleted an earlier mission.jsonl without a word; it is refused
    as `fly` refuses it, and the earlier log is untouched."""
    old = tmp_path / "mission.jsonl"
    old.write_text('{"type":"header","t":0.0}\n', encoding="utf-8")
    code = main(["sim", "paper", "--planner", "lawnmower", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 1 and f"mission log {old} already holds a mission" in err, err
    assert old.read_text(encoding="utf-8") == '{"type":"header","t":0.0}\n'
