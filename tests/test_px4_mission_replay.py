"""The mission uavloc flew on the real PX4 v1.18 SITL (../shared/data/px4-v1.18-sih/mission.*:
`uavloc sim three_users_nlos --connect ... --seed 3`), replayed from its mission log: the same
answer as the flight printed (mission.uavloc-output.txt), and an honest one (every user's true
error inside its 95 % bound). Skips, saying where it looked, away from ../shared."""

from __future__ import annotations

import json
import re

import pytest

from mission.cli import main

RECORDING = "px4-v1.18-sih"
#: "  ue1: lat 43.6148450  lon 7.0725950  alt 149.8 m  (E +80.4 m, N +60.3 m)  95% bound 3.89 m  error 0.52 m"
_USER = re.compile(r"^\s+(\S+): lat (\S+)\s+lon (\S+)\s+alt (\S+) m\s+\(E (\S+) m, N (\S+) m\)\s+"
                   r"95% bound (\S+) m\s+error (\S+) m$")
#: "mission target_reached (target reached): 342 ranges, 114 keyframes, 257 m flown"
_SUMMARY = re.compile(r"^mission (\S+) .*: (\d+) ranges, (\d+) keyframes, (\d+) m flown$")


def _printed(text: str) -> tuple[re.Match, list[re.Match]]:
    lines = text.splitlines()
    summary = _SUMMARY.match(lines[0])
    users = [m for m in map(_USER.match, lines[1:]) if m]
    assert summary and users, lines[:5]
    return summary, users


def test_the_recorded_px4_mission_replays_to_its_printed_answer_and_is_honest(shared_data, capsys):
    rec = shared_data / RECORDING
    summary, printed = _printed((rec / "mission.uavloc-output.txt").read_text())
    assert main(["replay", str(rec / "mission.jsonl"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    # the log's end record says how the mission ended (written before it carried `reason`: its message)
    assert (doc["status"], doc["reason"]) == (summary.group(1), "target reached") == ("target_reached",
                                                                                      "target reached")
    assert (doc["measurements"], doc["keyframes"]) == (int(summary.group(2)), int(summary.group(3)))
    # the flight's odometer ran on its own telemetry; the replay's over the log's (both printed in m)
    assert doc["flown_m"] == pytest.approx(int(summary.group(4)), abs=1.5)
    assert [u["id"] for u in doc["users"]] == [m.group(1) for m in printed]
    for u, m in zip(doc["users"], printed, strict=True):
        # the printed answer's digits came from a replay that estimated τ again from the whole log;
        # replay now uses the τ the flight logged (the next test): the same answer within decimetres
        east, north, bound = (float(m.group(i)) for i in (5, 6, 7))
        assert abs(u["enu_m"][0] - east) < 0.5 and abs(u["enu_m"][1] - north) < 0.5, u["id"]
        assert u["error_bound_95_m"] == pytest.approx(bound, abs=0.05), u["id"]
        # honest: the true error is inside the 95 % bound the estimate claims
        assert u["error_m"] <= u["error_bound_95_m"], u


def test_the_recorded_px4_mission_replays_with_the_tau_its_flight_used(shared_data, capsys):
    """The log as recorded: replay uses the τ the flight estimated at take-off (its `gps_tau` event,
    154 s; the whole log's telemetry gives another), the stop rule's; the answer is as honest, its
    status the one it supports, and within a few decimetres of the one printed."""
    from mission.log import read_mission_log
    from mission.replay import resolve_gps_tau

    rec = shared_data / RECORDING
    mlog = read_mission_log(rec / "mission.jsonl")
    assert resolve_gps_tau(mlog, mlog.header.noise).gps_tau_s == mlog.gps_tau_s == pytest.approx(154.476, abs=1e-3)
    _, printed = _printed((rec / "mission.uavloc-output.txt").read_text())
    assert main(["replay", str(rec / "mission.jsonl"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["status"] == doc["status_logged"] == "target_reached"
    for u, m in zip(doc["users"], printed, strict=True):
        east, north, bound = (float(m.group(i)) for i in (5, 6, 7))
        assert abs(u["enu_m"][0] - east) < 0.5 and abs(u["enu_m"][1] - north) < 0.5, u["id"]
        assert u["error_bound_95_m"] == pytest.approx(bound, abs=0.05) and u["error_m"] <= u["error_bound_95_m"], u
