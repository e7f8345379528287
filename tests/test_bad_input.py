"""Every `uavloc` subcommand with bad arguments and bad files, as a user runs it (a subprocess):
exit 1 (bad input) or 2 (usage), one clear message naming the file, key or value, no traceback,
and a mission log already there left as it was and readable (issue 21).

Nothing here flies a mission: each case is refused before anything connects or starts, except
the probe of a server that answers with random bytes."""

from __future__ import annotations

import random
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from mission.config import example_mission_path
from mission.log import read_mission_log

REPO = Path(__file__).resolve().parents[1]
EXAMPLE_LOG = REPO / "sitl_scenarios" / "data" / "example_paper.jsonl"
MISSION = str(example_mission_path())
#: nothing listens on these: a command that tried to connect would fail differently (or wait)
NOWHERE = ["--connect", "udpin://127.0.0.1:9", "--gnb", "127.0.0.1:9"]


@dataclass(frozen=True)
class Case:
    """argv after `uavloc` ({d}: the test's folder, whose files `setup` made); the exit code; the
    words the message must hold ({d} likewise)."""

    id: str
    argv: list[str]
    code: int
    words: list[str]
    setup: Callable[[Path], None] | None = None


def _write(name: str, data: str | bytes) -> Callable[[Path], None]:
    def make(d: Path) -> None:
        (d / name).write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))

    return make


def _both(*makers: Callable[[Path], None]) -> Callable[[Path], None]:
    def make(d: Path) -> None:
        for m in makers:
            m(d)

    return make


def _log_lines() -> list[str]:
    return EXAMPLE_LOG.read_text(encoding="utf-8").splitlines(keepends=True)


def _shuffled_log() -> str:
    lines = _log_lines()
    rest = lines[1:]
    random.Random(1).shuffle(rest)
    return "".join(lines[:1] + rest)


def _deep_log() -> str:
    return _log_lines()[0] + "[" * 100_000 + "]" * 100_000 + "\n"


def _bad_line_log() -> str:
    lines = _log_lines()
    lines[3] = '{"type": "telemetry", "t": 1.0, "lat_deg": 95}\n'
    return "".join(lines)


#: a fleet (issue 41) whose two vehicles share an id
FLEET_SAME_ID = (example_mission_path().read_text(encoding="utf-8")
                 + '\n[[vehicles]]\nid = "uav-a"\n\n[[vehicles]]\nid = "uav-a"\n')
#: a fleet whose vehicles have no addresses: `uavloc fly` cannot reach them
FLEET_NO_ADDRESS = (example_mission_path().read_text(encoding="utf-8")
                    + '\n[[vehicles]]\nid = "uav-a"\n\n[[vehicles]]\nid = "uav-b"\n')
HEADER_ONLY = _log_lines()[0]
OLD_LOG = _write("mission.jsonl", HEADER_ONLY)
NOT_A_FOLDER = _write("results", "not a folder\n")

CASES = [
    # -- the dispatcher --
    Case("no-command", [], 2, ["required: COMMAND"]),
    Case("unknown-command", ["fly-away"], 2, ["invalid choice: 'fly-away'"]),
    # -- sim --
    Case("sim-unknown-scenario", ["sim", "nosuch"], 1, ["'nosuch'", "paper"]),
    Case("sim-bad-seed", ["sim", "paper", "--seed", "abc"], 2, ["--seed", "'abc'"]),
    Case("sim-speedup-zero", ["sim", "paper", "--speedup", "0"], 2, ["--speedup", "(0, 10000)"]),
    Case("sim-bad-planner", ["sim", "paper", "--planner", "teleport"], 1, ["'teleport'", "lawnmower"]),
    Case("sim-view-port", ["sim", "paper", "--view", "127.0.0.1:70000"], 2, ["--view", "70000"]),
    Case("sim-out-is-a-file", ["sim", "paper", "--out", "{d}/results"], 1, ["{d}/results is a file"], NOT_A_FOLDER),
    Case("sim-out-holds-a-mission", ["sim", "paper", "--out", "{d}"], 1,
         ["{d}/mission.jsonl already holds a mission"], OLD_LOG),
    Case("sim-scenario-not-toml", ["sim", "{d}/bad.toml"], 1, ["{d}/bad.toml"], _write("bad.toml", "name = [\n")),
    Case("sim-scenario-unknown-key", ["sim", "{d}/bad.toml"], 1, ["warp"],
         _write("bad.toml", 'name = "x"\nwarp = 9\n')),
    # -- fly --
    Case("fly-no-connect", ["fly", "--mission", MISSION, "--gnb", "127.0.0.1:9"], 2, ["--connect"]),
    Case("fly-gnb-port-letters", ["fly", "--mission", MISSION, "--connect", "udpin://127.0.0.1:9", "--gnb",
                                  "127.0.0.1:abc"], 2, ["--gnb", "'abc'"]),
    Case("fly-gnb-port-range", ["fly", "--mission", MISSION, "--connect", "udpin://127.0.0.1:9", "--gnb",
                                "127.0.0.1:99999"], 2, ["--gnb", "127.0.0.1:99999"]),
    Case("fly-missing-mission", ["fly", "--mission", "{d}/nosuch.toml", *NOWHERE], 1, ["{d}/nosuch.toml"]),
    Case("fly-mission-not-toml", ["fly", "--mission", "{d}/bad.toml", *NOWHERE], 1, ["{d}/bad.toml"],
         _write("bad.toml", "[flight\n")),
    Case("fly-fleet-duplicate-id", ["fly", "--mission", "{d}/fleet.toml", *NOWHERE], 1,
         ["{d}/fleet.toml", "vehicles[1].id", "'uav-a'", "duplicate vehicle id"], _write("fleet.toml", FLEET_SAME_ID)),
    Case("fly-fleet-without-addresses", ["fly", "--mission", "{d}/fleet.toml"], 1,
         ["{d}/fleet.toml", "vehicles[0].connect (uav-a)", "vehicles[1].gnb (uav-b)"],
         _write("fleet.toml", FLEET_NO_ADDRESS)),
    Case("sim-fleet-one-connect", ["sim", "two_uavs", "--connect", "udpin://127.0.0.1:9"], 1,
         ["--connect", "'two_uavs'", "2 vehicles", "one URL per vehicle", "1 given"]),
    Case("sim-one-vehicle-two-connects", ["sim", "paper", "--connect", "udpin://127.0.0.1:9,udpin://127.0.0.1:8"], 1,
         ["--connect", "'paper'", "one vehicle", "2 given"]),
    Case("fly-out-is-a-file", ["fly", "--mission", MISSION, *NOWHERE, "--out", "{d}/results"], 1,
         ["{d}/results is a file"], NOT_A_FOLDER),
    Case("fly-log-holds-a-mission", ["fly", "--mission", MISSION, *NOWHERE, "--log", "{d}/mission.jsonl"], 1,
         ["{d}/mission.jsonl already holds a mission"], OLD_LOG),
    Case("fly-oracle", ["fly", "--mission", MISSION, *NOWHERE, "--planner", "oracle"], 1,
         ["oracle", "true positions"]),
    Case("fly-view-port", ["fly", "--mission", MISSION, *NOWHERE, "--view", "localhost:-3"], 2, ["--view"]),
    # -- replay --
    Case("replay-missing", ["replay", "{d}/nosuch.jsonl"], 1, ["{d}/nosuch.jsonl"]),
    Case("replay-empty", ["replay", "{d}/m.jsonl"], 1, ["{d}/m.jsonl", "empty"], _write("m.jsonl", "")),
    Case("replay-binary", ["replay", "{d}/m.jsonl"], 1, ["{d}/m.jsonl", "UTF-8"],
         _write("m.jsonl", b"\xff\xfe\x00garbage\n")),
    Case("replay-bad-line", ["replay", "{d}/m.jsonl"], 1, ["{d}/m.jsonl:4", "lat_deg"],
         _write("m.jsonl", _bad_line_log())),
    Case("replay-nested", ["replay", "{d}/m.jsonl"], 1, ["{d}/m.jsonl:2", "nested too deeply"],
         _write("m.jsonl", _deep_log())),
    Case("replay-shuffled", ["replay", "{d}/m.jsonl"], 1, ["{d}/m.jsonl:", "out of time order"],
         _write("m.jsonl", _shuffled_log())),
    Case("replay-header-only", ["replay", "{d}/mission.jsonl"], 1, ["{d}/mission.jsonl", "no rtt records"],
         OLD_LOG),
    Case("replay-bad-delta", ["replay", str(EXAMPLE_LOG), "--delta", "many"], 2, ["--delta", "'many'"]),
    Case("replay-unknown-loss", ["replay", str(EXAMPLE_LOG), "--loss", "squared"], 1, ["'squared'", "huber"]),
    # -- calibrate --
    Case("calibrate-missing", ["calibrate", "{d}/nosuch.jsonl"], 1, ["{d}/nosuch.jsonl"]),
    Case("calibrate-nested", ["calibrate", "{d}/m.jsonl"], 1, ["{d}/m.jsonl:2", "nested too deeply"],
         _write("m.jsonl", _deep_log())),
    Case("calibrate-bad-users", ["calibrate", str(EXAMPLE_LOG), "--users", "ue1=north"], 1, ["--users ue1", "'north'"]),
    # -- import --
    Case("import-missing-tlog", ["import", "--tlog", "{d}/nosuch.tlog", "--gnb-log", "{d}/gnb.log", "--users",
                                 "ue1:4601", "-o", "{d}/out.jsonl"], 1, ["{d}/nosuch.tlog"],
         _write("gnb.log", "nothing\n")),
    Case("import-bad-user", ["import", "--tlog", "{d}/x.tlog", "--gnb-log", "{d}/gnb.log", "--users", "ue1",
                             "-o", "{d}/out.jsonl"], 1, ["'ue1'"], _both(_write("x.tlog", b""),
                                                                         _write("gnb.log", ""))),
    Case("import-noise-nested", ["import", "--tlog", "{d}/x.tlog", "--gnb-log", "{d}/gnb.log", "--users",
                                 "ue1:4601", "-o", "{d}/out.jsonl", "--noise", "{d}/n.json"], 1, ["{d}/n.json"],
         _both(_write("x.tlog", b""), _write("gnb.log", ""), _write("n.json", "[" * 100_000))),
    # -- gnb probe --
    Case("probe-port-letters", ["gnb", "probe", "--gnb", "127.0.0.1:abc"], 2, ["--gnb", "'abc'"]),
    Case("probe-port-range", ["gnb", "probe", "--gnb", "127.0.0.1:70000"], 2, ["--gnb", "127.0.0.1:70000"]),
    Case("probe-bad-count", ["gnb", "probe", "--gnb", "127.0.0.1:9", "--count", "0"], 2, ["--count", "[1, 1000]"]),
    Case("probe-stock-without-log", ["gnb", "probe", "--gnb", "127.0.0.1:9", "--mode", "stock"], 1,
         ["--gnb-log"]),
    Case("probe-nothing-listening", ["gnb", "probe", "--gnb", "127.0.0.1:9", "--timeout", "0.5"], 1,
         ["127.0.0.1:9", "cannot connect"]),
    # -- view --
    Case("view-port-range", ["view", str(EXAMPLE_LOG), "--port", "70000"], 2, ["--port", "70000"]),
    Case("view-port-letters", ["view", str(EXAMPLE_LOG), "--port", "http"], 2, ["--port", "'http'"]),
    Case("view-missing", ["view", "{d}/nosuch.jsonl"], 1, ["{d}/nosuch.jsonl"]),
    Case("view-nested", ["view", "{d}/m.jsonl"], 1, ["{d}/m.jsonl:2", "nested too deeply"],
         _write("m.jsonl", _deep_log())),
    Case("view-bad-tiles", ["view", str(EXAMPLE_LOG), "--tiles", "ftp://x/{z}"], 2, ["--tiles"]),
    # -- campaign --
    Case("campaign-missing", ["campaign", "{d}/nosuch.toml"], 1, ["{d}/nosuch.toml"]),
    Case("campaign-not-toml", ["campaign", "{d}/c.toml"], 1, ["{d}/c.toml"], _write("c.toml", "[campaign\n")),
    Case("campaign-bad-workers", ["campaign", "{d}/c.toml", "--workers", "many"], 2, ["--workers", "'many'"]),
]


def run_uavloc(argv: list[str], timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mission", *argv], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout_s)


def assert_refused(proc: subprocess.CompletedProcess, code: int, words: list[str]) -> None:
    """Exit `code`; no traceback anywhere; one message (argparse's `error:` line for usage, the
    CLI's `uavloc CMD:` line for bad input, the probe's verdict on stdout) holding every word."""
    out = proc.stdout + proc.stderr
    assert proc.returncode == code, f"exit {proc.returncode}, wanted {code}:\n{out[-3000:]}"
    assert "Traceback" not in out, out[-3000:]
    if code == 2:
        messages = [ln for ln in proc.stderr.splitlines() if " error: " in ln]
    else:
        messages = [ln for ln in proc.stderr.splitlines() if ln.startswith("uavloc ")]
        messages += [ln for ln in proc.stdout.splitlines() if ln.startswith("gNB not ready")]
    assert len(messages) == 1, proc.stderr[-3000:]
    for w in words:
        assert w in messages[0], f"{w!r} not in {messages[0]!r}"


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_refused_with_one_clear_message(case: Case, tmp_path: Path) -> None:
    d = str(tmp_path)
    if case.setup is not None:
        case.setup(tmp_path)
    before = {p: p.read_bytes() for p in tmp_path.glob("*.jsonl")}
    proc = run_uavloc([a.replace("{d}", d) for a in case.argv])
    assert_refused(proc, case.code, [w.replace("{d}", d) for w in case.words])
    for p, data in before.items():  # a log already there is left as it was, and reads if it did
        assert p.read_bytes() == data, p
    if OLD_LOG is case.setup:
        read_mission_log(tmp_path / "mission.jsonl")


@pytest.fixture
def random_bytes_server() -> Iterator[int]:
    """A TCP server on an ephemeral port answering every connection and line with seeded random bytes."""
    srv = socket.create_server(("127.0.0.1", 0))
    srv.settimeout(0.2)
    rng = random.Random(21)
    stop = threading.Event()

    def serve(conn: socket.socket) -> None:
        with conn:
            try:
                conn.sendall(bytes(rng.randrange(256) for _ in range(300)))
                while not stop.is_set() and conn.recv(1024):
                    conn.sendall(bytes(rng.randrange(256) for _ in range(200)))
            except OSError:
                pass

    def accept() -> None:
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        yield srv.getsockname()[1]
    finally:
        stop.set()
        thread.join(2)
        srv.close()


def test_a_probe_of_a_server_sending_random_bytes_says_what_it_got(random_bytes_server: int) -> None:
    """Issue 21 #12: the probe said "no answer" of a server that answered with noise."""
    proc = run_uavloc(["gnb", "probe", "--gnb", f"127.0.0.1:{random_bytes_server}", "--timeout", "1"])
    out = proc.stdout + proc.stderr
    assert proc.returncode == 1 and "Traceback" not in out, out[-3000:]
    assert f"127.0.0.1:{random_bytes_server} sent" in out and "byte(s) but no" in out, out[-3000:]
    assert "telnet server" in out and "no answer" not in out, out[-3000:]
