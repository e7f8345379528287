"""Issue 39 "Always kept": with `--view` the page outlives the mission. Once the mission has ended
the command keeps serving the finished mission (ended, its final estimate, status and reason)
until SIGINT, SIGTERM or SIGHUP, then exits with the mission's own exit code; without `--view`
nothing waits. Every wait here is bounded (a hang fails the test, it does not block the run)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request

import aiohttp
import pytest

from mission.runtime import ENDING_SIGNALS, BoundedRun
from mission.view.live import live_view
from tests.procs import stop_process
from tests.test_view_state import write_mission

#: guards against a hang, not timing assertions
HANG_GUARD_S = 20.0
#: the command must be gone this soon after the signal [wall s]
PROMPT_EXIT_S = 5.0


@contextlib.contextmanager
def _signals_restored():
    """BoundedRun leaves its late-signal handlers installed after a signal (the CLI process ends
    right after); the test process gets its own back."""
    saved = {s: signal.getsignal(s) for s in ENDING_SIGNALS}
    try:
        yield
    finally:
        for s, h in saved.items():
            signal.signal(s, h)


def _view_args() -> argparse.Namespace:
    return argparse.Namespace(view="127.0.0.1:0", view_tiles=None)


@pytest.mark.parametrize("signum", ENDING_SIGNALS, ids=[s.name for s in ENDING_SIGNALS])
def test_the_finished_mission_stays_served_until_a_signal_then_the_missions_code(tmp_path, capsys, signum):
    """In-process, as `uavloc sim` runs it (BoundedRun on the main thread): after the mission's
    last record the page still answers, a second and a third time a while later, with the ended
    mission; the signal ends the wait promptly and the run returns the mission's exit code (3
    here: not 130)."""
    runner = BoundedRun(shutdown_timeout_s=1.0)
    seen: dict[str, object] = {}

    async def client(url: str, serving: asyncio.Task) -> None:
        async with aiohttp.ClientSession() as s:
            for i in range(3):
                await asyncio.sleep(0.3)
                assert not serving.done(), "the view stopped serving after the mission ended"
                async with s.get(url + "api/frame") as r:
                    assert r.status == 200
                    seen[f"frame{i}"] = await r.json()
            async with s.ws_connect(url.replace("http://", "ws://") + "ws") as ws:  # a page opened now
                seen["ws"] = json.loads((await asyncio.wait_for(ws.receive(), HANG_GUARD_S)).data)
        seen["t_signal"] = time.monotonic()
        os.kill(os.getpid(), signum)

    async def main() -> int:
        async with live_view(_view_args(), title="t") as view:
            records = write_mission(tmp_path / "m.jsonl", listener=view.feed.on_record)
            seen["records"] = records
            view.mission_over()
            serving = asyncio.create_task(view.keep_serving(runner, 3))
            talk = asyncio.create_task(client(view.url, serving))
            async with asyncio.timeout(HANG_GUARD_S):
                await serving
                seen["t_done"] = time.monotonic()
                await talk
        return 3

    with _signals_restored():
        assert runner.run(main()) == 3
    err = capsys.readouterr().err
    assert "the mission is over; the live view stays at http://127.0.0.1:" in err and "until Ctrl-C" in err
    assert seen["t_done"] - seen["t_signal"] < PROMPT_EXIT_S
    end = seen["records"][-1]
    assert end["kind"] == "end"
    for name in ("frame0", "frame1", "frame2", "ws"):
        f = seen[name]
        assert f["ended"] and f["state"] == "LANDED" and f["final"], name
        assert f["status"] == end["status"] == "target_reached" and f["reason"] == "target reached", name
        assert [u["id"] for u in f["users"] if u["located"]] == ["ue1", "ue2"], name


def test_a_cancellation_ends_the_wait_and_without_view_nothing_waits(tmp_path):
    """Off the main thread no signal handler exists: a cancellation ends the wait. Without
    `--view` keep_serving returns at once."""
    async def main() -> tuple[bool, float]:
        async with live_view(argparse.Namespace(view=None, view_tiles=None)) as bare:
            t0 = time.monotonic()
            await asyncio.wait_for(bare.keep_serving(BoundedRun(), 1), HANG_GUARD_S)
            bare_s = time.monotonic() - t0
        async with live_view(_view_args()) as view:
            write_mission(tmp_path / "m.jsonl", listener=view.feed.on_record)
            serving = asyncio.create_task(view.keep_serving(BoundedRun(), 1))
            await asyncio.sleep(0.5)
            still = not serving.done()
            serving.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait_for(serving, HANG_GUARD_S)
        return still, bare_s

    still, bare_s = asyncio.run(main())
    assert still
    assert bare_s < 1.0


def _read_until(proc: subprocess.Popen, needle: str, lines: list[str], deadline: float) -> str:
    for line in proc.stderr:
        lines.append(line)
        if needle in line:
            return line
        if time.monotonic() > deadline:
            break
    raise AssertionError(f"no {needle!r} from the command:\n" + "".join(lines[-40:]))


@pytest.mark.sim
def test_uavloc_sim_with_view_keeps_the_page_and_exits_on_sigint_with_the_missions_code(tmp_path):
    """The command itself (`uavloc sim paper --view 127.0.0.1:0 --json`, a subprocess; any status
    will do): the result is printed, the page still answers after the mission is over, with the
    result's status; SIGINT then ends it promptly with the exit code the mission gave."""
    from mission.result import NORMAL_END
    from tests.fly_rig import REPO

    env = dict(os.environ, PYTHONUNBUFFERED="1", UAVLOC_RUNS=str(tmp_path / "runs"))
    proc = subprocess.Popen([sys.executable, "-m", "mission", "sim", "paper", "--speedup", "20", "--json",
                             "--planner", "lawnmower", "--out", str(tmp_path / "out"), "--view", "127.0.0.1:0"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    try:
        deadline = time.monotonic() + 300.0
        over = _read_until(proc, "the mission is over", lines, deadline)
        url = over.split("stays at ", 1)[1].split()[0]
        frames = []
        for _ in range(2):
            time.sleep(1.0)
            assert proc.poll() is None, "".join(lines[-40:])
            with urllib.request.urlopen(url + "api/frame", timeout=10) as r:
                frames.append(json.loads(r.read()))
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        out, rest = proc.communicate(timeout=60)
        exit_s = time.monotonic() - t0
    finally:
        stop_process(proc, 10.0, 10.0)
    err = "".join(lines) + rest
    doc = json.loads(out)
    assert "Traceback" not in err, err[-3000:]
    ok = doc["status"] in NORMAL_END and all(u["enu_m"] is not None for u in doc["users"])
    assert proc.returncode == (0 if ok else 1), (proc.returncode, doc["status"], err[-3000:])
    assert exit_s < PROMPT_EXIT_S, exit_s
    for f in frames:
        assert f["ended"] and f["status"] == doc["status"] and f["state"] == "LANDED"
        assert f["measurements"] == doc["measurements"]
