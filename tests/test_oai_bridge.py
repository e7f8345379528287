"""The logic of `uavloc sim --oai` that needs no OAI (runs everywhere, fast): the rfsim channel's
arithmetic (OAI's own truncation), the bridge's stepping, the configuration files and command
lines, rfsim's pace, the nrUE telnet's answers (recorded transcripts served on loopback), the
`channel` log record and the residuals of ranges against it. The live flight is
tests/test_oai_sim_live.py."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
import re

import numpy as np
import pytest

from mission.channel import ChannelResiduals, channel_residuals, check_channel_record
from mission.log import MissionLogWriter, read_mission_log
from mission.log_checks import LineError
from sitl_scenarios.oai.bridge import ChannelBridge, ChannelSetting, plan_offsets
from sitl_scenarios.oai.channel import (
    PaceMeter,
    metres_for_offset,
    next_offset,
    offset_for_round_trip,
    offset_of_metres,
    parse_set_offset,
    parse_vtime,
    sample_m,
    world_speedup,
)
from sitl_scenarios.oai.conf import (
    CONF_DIR,
    OaiPorts,
    build_missing,
    check_scenario,
    gnb_command,
    gnb_conf,
    ue_command,
    ue_conf,
    with_srs,
    with_telnet_and_rfsim,
)
from sitl_scenarios.oai.loop import scenario_with_rntis
from sitl_scenarios.oai.pair import UeTelnet
from sitl_scenarios.scenario import load_scenario
from uavloc.errors import ScenarioError, SimulatorError

FS = 46.08e6
PORTS = OaiPorts(gnb_telnet=40001, t=40002, rfsim=40003, ue_telnet=(40004,))


# -- the channel's arithmetic -------------------------------------------------------------------

@pytest.mark.parametrize(("metres", "offset"), [(300, 46), (1000, 153), (600, 92), (150, 23), (6, 0), (7, 1)])
def test_offset_of_metres_is_oais_truncation(metres, offset):
    # the recorded answers: "setdistance ... 300" -> new_offset 46, 1000 -> 153, 600 -> 92 (09_setdistance)
    assert offset_of_metres(metres, FS) == offset


def test_metres_for_offset_sets_exactly_that_offset_and_is_the_smallest():
    for k in range(0, 400):
        m = metres_for_offset(k, FS)
        assert offset_of_metres(m, FS) == k
        assert k == 0 or offset_of_metres(m - 1, FS) == k - 1
    with pytest.raises(SimulatorError, match="whole number"):
        metres_for_offset(-1, FS)


def test_a_sample_and_the_nearest_offset():
    assert sample_m(FS) == pytest.approx(6.5059, abs=1e-4)
    assert offset_for_round_trip(150.0, FS) == 23  # 23.06 samples
    assert offset_for_round_trip(2 * 3.3, FS) == 1 and offset_for_round_trip(3.0, FS) == 0
    with pytest.raises(SimulatorError):
        offset_for_round_trip(math.nan, FS)


@pytest.mark.parametrize(("current", "target", "step", "expected"),
                         [(0, 23, 1, 1), (23, 0, 1, 22), (5, 5, 1, 5), (0, 23, 3, 3), (10, 11, 3, 11)])
def test_next_offset_moves_at_most_a_step(current, target, step, expected):
    assert next_offset(current, target, step) == expected


def test_next_offset_refuses_a_step_under_one_sample():
    with pytest.raises(SimulatorError, match="at least one sample"):
        next_offset(0, 5, 0)


def test_plan_offsets_puts_the_round_trip_on_the_channel():
    users = np.array([[60.0, 45.0, 0.0], [0.0, 0.0, 0.0]])
    d, target, nxt = plan_offsets(np.array([0.0, 0.0, 40.0]), users, [0, 6], FS)
    assert d == pytest.approx([math.sqrt(60**2 + 45**2 + 40**2), 40.0])
    assert list(target) == [round(2 * d[0] / sample_m(FS)), 12] and list(nxt) == [1, 7]


# -- parsing OAI's answers (recorded transcripts, ../shared/data/oai-2025.w36) -----------------

SET_ANSWER = ("softmodem_5Gue> \nrfsimu_setdistance_cmd: new_offset 46, new (exact) distance 299.272 m, "
              "new delay 0.000998 ms\n")
VTIME_ANSWER = "softmodem_5Gue> rfsimu_vtime_cmd: vtime measurement: TS 92160000 sample_rate 46080000.000\n"


def test_answers_are_parsed():
    assert parse_set_offset(SET_ANSWER) == 46
    assert parse_vtime(VTIME_ANSWER) == pytest.approx(2.0)
    for bad in ("softmodem_5Gue> ", "rfsimu_vtime_cmd: vtime measurement: TS 5 sample_rate 0.000"):
        with pytest.raises(SimulatorError):
            parse_vtime(bad)
    with pytest.raises(SimulatorError, match="no rfsimu setdistance line"):
        parse_set_offset("softmodem_5Gue> ")


def test_ue_telnet_reads_the_late_lines_over_a_socket():
    """An nrUE telnet server as OAI answers: the prompt at once, the rfsimu line after it (split)."""
    async def body():
        async def serve(reader, writer):
            while line := (await reader.readline()).decode():
                writer.write(b"softmodem_5Gue> ")
                await writer.drain()
                await asyncio.sleep(0.02)
                if line.startswith("rfsimu setdistance rfsimu_channel_enB0 "):
                    k = offset_of_metres(int(line.split()[-1]), FS)
                    text = f"\nrfsimu_setdistance_cmd: new_offset {k}, new (exact) distance {k * sample_m(FS):.3f} m"
                    writer.write(text.encode())
                    await writer.drain()
                    await asyncio.sleep(0.02)
                    writer.write(b", new delay 0.000998 ms\n")
                elif line.startswith("rfsimu vtime"):
                    writer.write(VTIME_ANSWER.split("> ", 1)[1].encode())
                await writer.drain()
            writer.close()

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        async with server, UeTelnet(port, request_timeout_s=2.0) as ue:
            got = [await ue.set_distance(metres_for_offset(k, FS)) for k in (1, 2, 46)]
            return got, await ue.vtime_s()

    got, vtime = asyncio.run(body())
    assert got == [1, 2, 46] and vtime == pytest.approx(2.0)


# -- the bridge ---------------------------------------------------------------------------------

@dataclasses.dataclass
class OaiLikeUe:
    """An nrUE's rfsim channel as OAI sets it (integer metres, truncated), with a clock of samples."""

    offsets: list = dataclasses.field(default_factory=list)
    vtime: float = 0.0

    async def set_distance(self, metres: int) -> int:
        self.offsets.append(offset_of_metres(metres, FS))
        return self.offsets[-1]

    async def vtime_s(self) -> float:
        self.vtime += 0.05
        return self.vtime


def test_the_bridge_walks_out_one_sample_at_a_time_and_follows():
    ue, sunk = OaiLikeUe(), []
    users = np.array([[60.0, 45.0, 0.0]])
    # on the ground 75 m from the user, then climbing away along east
    track = [np.array([0.0, 0.0, 0.0])] * 40 + [np.array([float(x), 0.0, 40.0]) for x in range(0, 40)]
    calls = []

    async def position():
        calls.append(1)
        return track[min(len(calls), len(track)) - 1]

    async def body():
        bridge = ChannelBridge([ue], ["ue1"], users, position, FS, period_s=0.0, sink=sunk.append)
        async with bridge:
            assert bridge.offsets == [offset_for_round_trip(150.0, FS)]  # 75 m away, on the ground
            while len(bridge.settings) < 23 + 1 and bridge.failed() is None:
                await asyncio.sleep(0)
            for _ in range(300):
                await asyncio.sleep(0)
        return bridge

    bridge = asyncio.run(body())
    steps = np.diff([0, *ue.offsets])
    assert ue.offsets[:23] == list(range(1, 24)) and np.all(np.abs(steps) == 1)
    assert sunk == bridge.settings and bridge.failed() is None
    last = bridge.settings[-1]
    assert abs(2 * last.true_range_m - last.round_trip_m) <= 0.5 * sample_m(FS) + 1e-9
    assert [s.t_mono_s for s in sunk] == sorted(s.t_mono_s for s in sunk)


def test_the_bridge_waits_for_an_autopilots_first_position():
    """With --connect the position is the autopilot's report: None (or NaN) until it has one."""
    ue, reports = OaiLikeUe(), [None, np.full(3, np.nan), np.array([0.0, 0.0, 20.0])]

    async def position():
        return reports.pop(0) if len(reports) > 1 else reports[0]

    async def body():
        bridge = ChannelBridge([ue], ["ue1"], np.zeros((1, 3)), position, FS)
        return [await bridge.step() for _ in range(3)] + [await bridge.step() for _ in range(10)]

    done = asyncio.run(body())
    assert done[:2] == [False, False] and ue.offsets[0] == 1 and done[-1] and ue.offsets[-1] == 6  # 40 m


def test_a_setting_oai_did_not_take_stops_the_bridge():
    class Refusing(OaiLikeUe):
        async def set_distance(self, metres: int) -> int:
            return 0

    async def position():
        return np.array([100.0, 0.0, 0.0])

    async def body():
        await ChannelBridge([Refusing()], ["ue1"], np.zeros((1, 3)), position, FS).step()

    with pytest.raises(SimulatorError, match="not 1"):
        asyncio.run(body())


# -- pace ---------------------------------------------------------------------------------------

def test_pace_is_the_slope_over_the_window():
    meter = PaceMeter(window_s=10.0, min_span_s=2.0)
    meter.add(100.0, 5.0)
    meter.add(101.0, 5.4)
    assert meter.pace() is None  # 1 s of wall
    for k in range(2, 30):
        meter.add(100.0 + k, 5.0 + 0.4 * k)
    assert meter.pace() == pytest.approx(0.4) and meter.span_s <= 10.0 + 1e-9
    meter.add(200.0, 1.0)  # a new rfsim: its clock restarted
    assert meter.pace() is None


@pytest.mark.parametrize(("requested", "pace", "expected"), [(10.0, 1.21, 1.2), (0.5, 1.3, 0.5), (10.0, 0.43, 0.4)])
def test_the_world_never_outruns_rfsim(requested, pace, expected):
    assert world_speedup(requested, pace) == pytest.approx(expected)


def test_a_crawling_rfsim_is_said():
    with pytest.raises(SimulatorError, match="cannot carry"):
        world_speedup(10.0, 0.01)


# -- configuration files and command lines ------------------------------------------------------

def test_the_confs_carry_this_runs_ports_and_srs():
    g, u = gnb_conf(PORTS), ue_conf(PORTS, 0)
    assert re.search(r"listenport\s*=\s*40001;", g) and "serverport = 40003;" in g
    assert re.search(r"gNBs\s*=\s*\(\s*\{\s*do_SRS = 1;", g) and g.count("do_SRS") == 1
    assert re.search(r"listenport\s*=\s*40004;", u) and "serverport = 40003;" in u
    recorded = (CONF_DIR / "gnb.conf").read_text()
    assert "9099" in recorded and "9099" not in g  # the recording's fixed port is gone
    assert with_srs("gNBs = ( { do_SRS = 0; } );") == "gNBs = ( { do_SRS = 1; } );"
    assert "serverport = 7;" in with_telnet_and_rfsim("telnetsrv = { listenport = 1; };", 2, 7)
    with pytest.raises(ScenarioError, match="telnetsrv"):
        with_telnet_and_rfsim("rfsimulator: { };", 2, 7)


def test_command_lines_run_oai_unprivileged_with_its_t_server_on_this_runs_port(tmp_path):
    g = gnb_command(tmp_path, tmp_path / "gnb.conf", PORTS)
    u = ue_command(tmp_path, tmp_path / "ue0.conf")
    for cmd in (g, u):
        assert cmd[:8] == ["setpriv", "--bounding-set", "-sys_nice", "--inh-caps", "-sys_nice", "nice", "-n", "19"]
        assert "--do-ra" in cmd and "-E" in cmd
    assert g[g.index("--T_port") + 1] == "40002" and "--T_stdout" in g and "--T_nowait" in g
    assert "9090" not in " ".join(g + u) and "2021" not in " ".join(g + u)
    assert u[u.index("--rbconfig-file") + 1] == "rbconfig.raw"


def test_what_oai_cannot_fly_is_refused(tmp_path):
    check_scenario(load_scenario("paper"))
    check_scenario(load_scenario("three_users_nlos"))  # a gNB + nrUE pair per user
    with pytest.raises(ScenarioError, match="one UE per gNB"):
        check_scenario(load_scenario("five_commercial_ues"))
    paper = load_scenario("paper")
    mu2 = dataclasses.replace(paper, world=dataclasses.replace(paper.world, radio=dataclasses.replace(
        paper.radio, mu=2)))
    with pytest.raises(ScenarioError, match="mu = 2"):
        check_scenario(mu2)
    assert "no such folder" in build_missing(tmp_path / "nope")
    assert "lacks nr-softmodem" in build_missing(tmp_path)
    assert scenario_with_rntis(paper, [0xE4A0]).mission.users[0].rnti == 0xE4A0


def test_the_sim_commands_oai_argument(tmp_path, monkeypatch):
    """`--oai` bare takes UAVLOC_OAI; a missing or incomplete build is said before anything starts
    (a ScenarioError: exit 1 at the CLI)."""
    from sitl_scenarios.commands.sim import oai_argument

    monkeypatch.delenv("UAVLOC_OAI", raising=False)
    assert oai_argument(None) is None
    with pytest.raises(ScenarioError, match="UAVLOC_OAI, which is not set"):
        oai_argument("")
    with pytest.raises(ScenarioError, match="no such folder"):
        oai_argument(str(tmp_path / "nope"))
    monkeypatch.setenv("UAVLOC_OAI", str(tmp_path))
    with pytest.raises(ScenarioError, match="lacks nr-softmodem"):
        oai_argument("")


# -- the log's channel records and the residuals ------------------------------------------------

def _setting(t, k, d=0.0):
    return ChannelSetting(t, 1e9 + t, "ue1", k, FS, d)


def test_a_channel_record_round_trips_through_the_log(tmp_path):
    from estimator.geodesy import Origin

    path = tmp_path / "m.jsonl"
    with MissionLogWriter(path) as w:
        w.write_header(Origin(43.6, 7.07, 150.0), [{"id": "ue1", "rnti": 0x4601, "ground_alt_m": 150.0}],
                       {"mu": 1, "fs_hz": FS})
        w.write("channel", 1.0, **_setting(1.0, 23, 75.0).record())
    mlog = read_mission_log(path)
    assert mlog.channel[0]["offset"] == 23 and mlog.channel[0]["range_m"] == pytest.approx(23 * sample_m(FS) / 2, 1e-4)
    with pytest.raises(LineError, match="offset"):
        check_channel_record({**json.loads(json.dumps(_setting(1.0, 1).record())), "offset": -1}, {"ue1": 0})
    with pytest.raises(LineError, match="unknown user"):
        check_channel_record({**_setting(1.0, 1).record(), "user": "x"}, {"ue1": 0})


def test_residuals_take_the_channel_in_force_at_each_stamp():
    c = 299_792_458.0
    ch = [{"t": t, **_setting(t, k).record()} for t, k in ((1.0, 10), (2.0, 11), (3.0, 14))]
    half = sample_m(FS) / 2
    # ranges: before any setting (left out), on 10, on 11 plus a sample, on 14 minus 2 samples
    r = np.array([5.0, 10 * half, 11 * half + half, 14 * half - 2 * half])
    res = channel_residuals(np.array([0.5, 1.5, 2.5, 3.5]), np.zeros(4, int), r / c, ch, {"ue1": 0})
    assert isinstance(res, ChannelResiduals) and res.n == 3
    assert res.residual_m == pytest.approx([0.0, half, -2 * half], abs=1e-3)  # the record's 0.1 mm
    doc = res.to_dict()
    assert doc["within_one_sample"] == pytest.approx(2 / 3, abs=1e-4) and doc["mean_m"] == pytest.approx(-half / 3,
                                                                                                         abs=1e-3)
    assert channel_residuals(np.zeros(0), np.zeros(0, int), np.zeros(0), [], {"ue1": 0}) is None


def test_closing_the_pair_ends_each_process_group_and_counts_its_cpu(tmp_path):
    """OaiPair.close ends what each OAI process forked too (nr-softmodem's T process outlives it):
    here a shell whose child ignores SIGTERM and outlives it, in a session of its own as OAI is started."""
    import subprocess
    import time

    from sitl_scenarios.oai.pair import OaiPair

    pair = OaiPair(tmp_path, tmp_path)
    proc = subprocess.Popen(["sh", "-c", "(trap '' TERM; exec sleep 30) & wait"], start_new_session=True)
    pair.procs["gnb"], pair._t_start = proc, time.monotonic()
    time.sleep(0.1)
    assert set(pair.cpu_s()) == {"gnb"} and pair.cpu_s()["gnb"] >= 0.0
    pair.close()
    time.sleep(0.1)
    states = subprocess.run(["ps", "-o", "stat=", "-g", str(proc.pid)], capture_output=True, text=True).stdout
    assert all(s.startswith("Z") for s in states.split()) and pair.exited() == ["gnb"]  # dead, maybe not reaped


#: the gNB's lines of an attach (a live run, 2026-12-07) and of one lost under load (the same day)
ATTACHED_LOG = """1796673410.357218 [NR_MAC] I Added new CFRA process for UE RNTI e4a0 with initial CellGroup
1796673417.172256 [NR_PHY] A [RAPROC] 237.19 Initiating RA procedure with preamble 63, energy 44.0 dB
1796673417.183216 [NR_MAC] A (rnti 0xe4a0) CFRA procedure succeeded!
"""
LOST_LOG = """1796674234.391581 [NR_MAC] I Added new CFRA process for UE RNTI bb38 with initial CellGroup
1796674237.177836 [NR_MAC] A 201.19 UE RA-RNTI 010f TC-RNTI bb38: initiating RA procedure
1796674237.182786 [NR_MAC] W exceeded RA window: preamble at 201.19 now 203.0 (diff 21), ra_ResponseWindow 5/20 slots
1796674237.182799 [NR_MAC] E UE RA-RNTI 010f TC-RNTI bb38: exceeded RA window, cannot schedule Msg2
1796674237.182903 [NR_MAC] I Remove NR rnti 0xbb38
1796674237.198613 [NR_MAC] W random access with preamble 63: no pre-configured RA process found
"""


def test_the_attach_is_read_from_the_gnbs_log():
    from sitl_scenarios.oai.pair import attach_state

    assert attach_state(ATTACHED_LOG, set()) == (0xE4A0, None)
    assert attach_state(ATTACHED_LOG.splitlines(True)[0], set()) == (None, None)  # still waiting
    rnti, lost = attach_state(LOST_LOG, set())
    assert rnti is None and "removed its pre-configured UE bb38" in lost and "missed the RA window" in lost


def test_the_nlos_excess_is_held_while_a_building_blocks_the_view():
    from sitl_scenarios.oai.bridge import HeldNlosExcess

    sc = load_scenario("three_users_nlos")
    users = np.array([[u.east_m, u.north_m, u.up_m] for u in sc.users])
    ex = HeldNlosExcess(users, sc.buildings, 10.0, seed=7)
    behind = np.array([150.0, 62.0, 20.0])  # east of ue1's building, low
    first = ex(behind)
    assert first[0] > 0 and np.all(ex(behind + np.array([1.0, 0.0, 0.0])) == first)  # held
    assert ex(np.array([80.0, 60.0, 40.0]))[0] == 0.0  # over ue1: LoS
    again = ex(behind)
    assert again[0] > 0 and again[0] != first[0]  # a new episode, a new draw
    d, target, _ = plan_offsets(behind, users[:1], [0], FS, excess_m=again[:1])
    assert target[0] == offset_for_round_trip(2 * (d[0] + again[0]), FS)


def test_a_commercial_ues_clock_sawtooth_rides_on_its_channel_as_the_radio_truth_has_it():
    """five_commercial_ues' ue1 (12 m every 15 s) through the bridge's excess: saw(t) =
    A · frac(t / P + φ) at the world's time (wall × speed-up), the same function as the simulated
    gNB's RadioModel.sawtooth_m for the same phase; an ideal UE gets none; the NLoS excess adds."""
    from sitl_scenarios.oai.bridge import ClockSawtooth, channel_excess
    from sitl_scenarios.radio import RadioModel

    sc = load_scenario("five_commercial_ues")
    now = [100.0]
    amps = [sc.users[0].sawtooth_amplitude_m, 0.0]
    periods = [sc.users[0].sawtooth_period_s, 15.0]
    saw = ClockSawtooth(amps, periods, speedup=4.0, seed=3, clock=lambda: now[0])
    radio = RadioModel(sc, np.random.default_rng(0))
    radio.sawtooth_phase[0] = saw.phases[0]
    for wall_s in (0.0, 1.3, 2.0, 3.74, 9.9):
        now[0] = 100.0 + wall_s
        got = saw()
        assert got[0] == pytest.approx(radio.sawtooth_m(0, 4.0 * wall_s), abs=1e-12) and got[1] == 0.0
        assert 0.0 <= got[0] < amps[0] == 12.0
    # a period of the world's time is P / speed-up of wall time: the same value again
    now[0] = 100.0 + 1.0
    first = saw()[0]
    now[0] = 100.0 + 1.0 + periods[0] / 4.0
    assert saw()[0] == pytest.approx(first, abs=1e-9)
    assert channel_excess(None, None) is None
    both = channel_excess(lambda pos: np.array([5.0, 0.0]), saw)
    assert both(np.zeros(3)) == pytest.approx(np.array([5.0 + first, 0.0]))


def test_a_group_of_gnbs_measures_each_ue_at_its_own_gnb():
    """GnbGroup routes a UE to the adapter of its gNB (each gNB of --do-ra serves one UE)."""
    from sitl_scenarios.oai.group import GnbGroup
    from uavloc.errors import GnbError, GnbNoMeasurementError

    class OneUeGnb:  # what the group uses of an OaiGnbClient in trace mode
        mode, mode_reason, clock_refused = "trace", "configured", 1

        def __init__(self, rnti):
            self.rnti = rnti

        async def discover(self):
            return [self.rnti]

        async def measure(self, rnti):
            assert rnti == self.rnti
            return ("range of", rnti)

        def clock_offset(self):
            return None

        def drain_trace_orders(self):
            return [f"order of {self.rnti:04x}"]

    group = GnbGroup([OneUeGnb(0x11), OneUeGnb(0x22)], [0x11, 0x22])
    assert group.drain_trace_orders() == ["order of 0011", "order of 0022"]

    async def body():
        return await group.discover(), await group.measure(0x22)

    assert asyncio.run(body()) == ([0x11, 0x22], ("range of", 0x22))
    assert group.mode == "trace" and group.clock_refused == 2
    with pytest.raises(GnbNoMeasurementError, match="no gNB of the group serves UE 0033"):
        asyncio.run(group.measure(0x33))
    with pytest.raises(GnbError, match="distinct RNTI"):
        GnbGroup([OneUeGnb(1), OneUeGnb(1)], [1, 1])


def test_the_bridge_takes_the_slowest_rfsim_and_says_when_it_falls_behind_the_world(caplog):
    """Each gNB + nrUE pair is an rfsim of its own: the pace is the slowest; below 0.8 × the
    world's speed-up it is said."""
    fast, slow = OaiLikeUe(), OaiLikeUe()
    slow.vtime_s = None  # replaced below: 0.25 simulated s per wall s

    wall = [1000.0]

    async def slow_vtime():
        return 0.25 * (wall[0] - 1000.0)

    async def fast_vtime():
        return 1.0 * (wall[0] - 1000.0)

    slow.vtime_s, fast.vtime_s = slow_vtime, fast_vtime

    async def position():
        return np.zeros(3)

    async def body():
        bridge = ChannelBridge([fast, slow], ["ue1", "ue2"], np.zeros((2, 3)), position, FS, world_speedup=0.4,
                               wall=lambda: wall[0])
        for _ in range(4):
            await bridge.measure_pace()
            wall[0] += 1.0
        return bridge.pace()

    with caplog.at_level("WARNING", logger="sitl_scenarios.oai.bridge"):
        pace = asyncio.run(body())
    assert pace == pytest.approx(0.25)
    assert "rfsim now runs at 0.25 × real time, slower than the world's 0.4 ×" in caplog.text
