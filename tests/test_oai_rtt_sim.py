"""`uavloc sim --oai --gnb-mode rtt` without OAI: which builds serve the rtt mode (patched with
patches/oai-2025.w36), what an unpatched one is told, and what the patched one is started with
(the gNB's telnet module rtt, the nrUE's NRUE_PDCCH_ORDER_CSS=1). Fake build folders whose
"binaries" are shell scripts; the live flight is tests/test_oai_sim_live.py."""

from __future__ import annotations

import os
import stat

import pytest

from sitl_scenarios.oai.conf import (
    BUILD_FILES,
    RTT_MODULE_FILE,
    RTT_PATCH_MARK,
    OaiPorts,
    gnb_command,
    rtt_missing,
)
from sitl_scenarios.oai.loop import OaiInTheLoop
from sitl_scenarios.oai.pair import OaiPair
from sitl_scenarios.scenario import load_scenario
from uavloc.errors import ScenarioError

PORTS = OaiPorts(gnb_telnet=40001, t=40002, rfsim=40003, ue_telnet=(40004,))
#: a stand-in nr-uesoftmodem: says what the order's variable is in its environment, then exits
UE_SCRIPT = "#!/bin/sh\necho \"NRUE_PDCCH_ORDER_CSS=${NRUE_PDCCH_ORDER_CSS:-unset}\"\n"


def fake_build(folder, patched: bool, module: bool | None = None):
    """A build folder with every file uavloc needs; nr-softmodem carries the patch's mark when
    `patched`; libtelnetsrv_rtt.so is there when `module` (default: patched)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in BUILD_FILES:
        (folder / name).write_bytes(b"")
    (folder / "nr-softmodem").write_bytes(b"\x7fELF..." + (RTT_PATCH_MARK + b" %04x" if patched else b"stock") + b"...")
    ue = folder / "nr-uesoftmodem"
    ue.write_text(UE_SCRIPT)
    ue.chmod(ue.stat().st_mode | stat.S_IXUSR)
    if patched if module is None else module:
        (folder / RTT_MODULE_FILE).write_bytes(b"")
    return folder


@pytest.mark.parametrize(("patched", "module", "said"), [
    (False, False, "no libtelnetsrv_rtt.so"),
    (False, True, "its nr-softmodem has no PDCCH order"),
    (True, True, None),
])
def test_only_a_patched_build_serves_the_rtt_mode(tmp_path, patched, module, said):
    why = rtt_missing(fake_build(tmp_path, patched, module))
    if said is None:
        assert why is None
    else:
        assert said in why and "patches/oai-2025.w36/README.md" in why and "--gnb-mode trace" in why


def test_the_patched_gnb_loads_the_rtt_telnet_module(tmp_path):
    plain = gnb_command(tmp_path, tmp_path / "gnb.conf", PORTS)
    rtt = gnb_command(tmp_path, tmp_path / "gnb.conf", PORTS, rtt=True)
    assert plain[plain.index("--telnetsrv.shrmod") + 1] == "ci,o1"
    assert rtt[rtt.index("--telnetsrv.shrmod") + 1] == "ci,o1,rtt"
    assert [a for a in rtt if a != "ci,o1,rtt"] == [a for a in plain if a != "ci,o1"]


@pytest.mark.parametrize(("rtt", "expected"), [(True, "1"), (False, "unset")])
def test_the_nrue_hears_the_order_only_in_rtt_mode(tmp_path, monkeypatch, rtt, expected):
    """The nrUE is started (as OAI is: setpriv, nice 19) with NRUE_PDCCH_ORDER_CSS=1 in rtt mode
    only; the command line in the log header says so."""
    monkeypatch.delenv("NRUE_PDCCH_ORDER_CSS", raising=False)
    pair = OaiPair(fake_build(tmp_path / "build", patched=True), tmp_path / "run", rtt=rtt)
    (tmp_path / "run").mkdir()
    try:
        pair.start_ue(0)
        assert pair.procs["ue0"].wait(timeout=10) == 0
    finally:
        pair.close()
    assert (tmp_path / "run" / "ue0.log").read_text().strip() == f"NRUE_PDCCH_ORDER_CSS={expected}"
    assert (pair.command_lines[0][0] == "NRUE_PDCCH_ORDER_CSS=1") is rtt
    assert "NRUE_PDCCH_ORDER_CSS" not in os.environ


def test_rtt_mode_of_an_unpatched_build_is_refused_naming_the_patch(tmp_path, monkeypatch):
    """Before anything starts: the sim command's --oai check, and SimulatedMission itself."""
    from sitl_scenarios.commands.sim import oai_argument
    from sitl_scenarios.sim_runner import SimulatedMission

    stock = str(fake_build(tmp_path / "stock", patched=False))
    assert oai_argument(stock) == stock and oai_argument(stock, "trace") == stock
    with pytest.raises(ScenarioError, match=r"no libtelnetsrv_rtt\.so.*patches/oai-2025\.w36/README\.md"):
        oai_argument(stock, "rtt")
    with pytest.raises(ScenarioError, match="uavloc-rtt-pdcch-order.patch"):
        SimulatedMission(load_scenario("paper"), tmp_path / "m.jsonl", oai=stock, gnb_mode="rtt")
    sim = SimulatedMission(load_scenario("paper"), tmp_path / "t" / "m.jsonl", oai=stock)
    assert sim.gnb_mode == "trace" and not sim.oai.rtt


def test_rtt_mode_of_a_patched_build_runs_every_pair_with_the_order(tmp_path):
    from sitl_scenarios.sim_runner import SimulatedMission

    build = str(fake_build(tmp_path / "patched", patched=True))
    sim = SimulatedMission(load_scenario("paper"), tmp_path / "m.jsonl", oai=build, gnb_mode="rtt")
    assert sim.gnb_mode == "rtt" and sim.oai.rtt and all(p.rtt for p in sim.oai.pairs)
    loop = OaiInTheLoop(build, tmp_path / "three", load_scenario("three_users_nlos"), rtt=True)
    assert len(loop.pairs) == 3 and all(p.rtt for p in loop.pairs)
    loop.pace_at_start = 1.0
    header = loop.header(1.0)
    assert header["rtt_order"] is True and header["real_gnb"] is True
    # the trace mode stays the default of a patched build
    assert SimulatedMission(load_scenario("paper"), tmp_path / "d" / "m.jsonl", oai=build).gnb_mode == "trace"
