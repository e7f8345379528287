"""`uavloc sim paper --oai` against the user's own OAI build (`UAVLOC_OAI`, marker `oai`): the world's
gNB is a real nr-softmodem and the user a real nr-uesoftmodem over rfsim, the bridge putting the
built-in vehicle's true distance on the nrUE's downlink (docs/oai-in-the-loop.md). About 3 minutes
and 1.7 cores while it flies, each. Skipped with the sentence of tests/test_oai_live.py when unset;
the rtt-mode flight also when the build is not patched with patches/oai-2025.w36 (its sentence)."""

from __future__ import annotations

import asyncio
import os
import subprocess
from pathlib import Path

import pytest

from mission.channel import channel_residuals
from mission.log import read_mission_log
from sitl_scenarios.oai.conf import rtt_missing
from sitl_scenarios.scenario import load_scenario
from sitl_scenarios.sim_runner import SimulatedMission
from tests.test_oai_live import BUILD_ENV, oai_build_missing

pytestmark = pytest.mark.oai


def _fly_paper(tmp_path: Path, **options):
    """Fly paper with the real OAI gNB (SimulatedMission options, e.g. gnb_mode) and check what
    both modes must give: target reached, the user inside its bound, every range carrying its TA,
    the ranges within a sample of the channel, no OAI process left.
    -> (the user's result, the mission log, the channel residuals' document)."""
    log_path = tmp_path / "mission.jsonl"

    async def body():
        async with asyncio.timeout(900):
            async with SimulatedMission(load_scenario("paper"), log_path, oai=os.environ[BUILD_ENV],
                                        speedup=10.0, **options) as sim:
                result = await sim.run()
                return sim, result

    sim, result = asyncio.run(body())
    pids = [p.pid for p in sim.oai.pair.procs.values()]
    assert result.status == "target_reached", result.reason
    (user,) = result.result.users
    assert user.error_m is not None and user.error_m <= user.error_bound_95_m, user
    mlog = read_mission_log(log_path)
    assert all(r.get("ta") is not None for r in mlog.rtt_raw)  # every range from a TA + SRS peak
    res = channel_residuals(mlog.rtt_t_s, mlog.rtt_user, mlog.rtt_toa_s, mlog.channel, mlog.header.user_index())
    doc = res.to_dict()
    assert res.n >= 50 and doc["within_one_sample"] >= 0.8 and abs(doc["mean_m"]) < 1.0, doc
    # no OAI process of this run is left
    left = subprocess.run(["ps", "-o", "stat=,args=", "-g", ",".join(map(str, pids))], capture_output=True, text=True)
    assert all(ln.split()[0].startswith("Z") for ln in left.stdout.splitlines()), left.stdout
    return user, mlog, doc


def test_paper_flies_to_target_with_every_range_from_a_real_oai_gnb(tmp_path):
    why = oai_build_missing()
    if why is not None:
        pytest.skip(why)
    user, mlog, doc = _fly_paper(tmp_path)
    oai = mlog.header.config["oai"]
    assert oai["real_gnb"] and "nr-softmodem" in oai["command_lines"][0] and "--T_port" in oai["command_lines"][0]
    assert mlog.header.config["gnb_mode"] == "trace" and mlog.header.config["speedup"] <= oai["pace_at_start"]
    steps = [abs(b["offset"] - a["offset"]) for a, b in zip(mlog.channel, mlog.channel[1:], strict=False)]
    assert max(steps) == 1
    print(f"paper with a real OAI gNB: error {user.error_m:.2f} m, bound {user.error_bound_95_m:.2f} m; "
          f"residual vs channel {doc}")


def test_paper_flies_to_target_with_every_range_a_pdcch_order_of_the_patched_gnb(tmp_path):
    """`--gnb-mode rtt` on a build patched with patches/oai-2025.w36: each range is a `rtt
    pdcch_order` answer (TA of the ordered access + SRS peak), within one sample of the channel."""
    why = oai_build_missing()
    if why is None:
        why = rtt_missing(Path(os.environ[BUILD_ENV]).expanduser())
    if why is not None:
        pytest.skip(why)
    user, mlog, doc = _fly_paper(tmp_path, gnb_mode="rtt")
    oai = mlog.header.config["oai"]
    assert oai["rtt_order"] and "ci,o1,rtt" in oai["command_lines"][0]
    assert oai["command_lines"][1].startswith("NRUE_PDCCH_ORDER_CSS=1 ")
    assert mlog.header.config["gnb_mode"] == "rtt"
    print(f"paper with the patched OAI gNB in rtt mode: error {user.error_m:.2f} m, bound "
          f"{user.error_bound_95_m:.2f} m; residual vs channel {doc}")
