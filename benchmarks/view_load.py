"""The live view under load: `uavloc sim paper --view 127.0.0.1:0` alone, then with 50 pollers on
loopback asking /api/frame in bounded loops (each waits for its answer; a 429 is answered after the
server's refused_delay_s), alternately; prints each run's wall time [s] and largest gap between
ranges during the survey [mission s] (the mission's own `survey_time` event).

    python benchmarks/view_load.py [--pairs N] [--pollers 50]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import aiohttp

REPO = Path(__file__).resolve().parents[1]


async def _poll(url: str, n: int, stop: threading.Event, counts: dict) -> None:
    async def one(session: aiohttp.ClientSession) -> None:
        while not stop.is_set():
            try:
                async with session.get(url + "api/frame", timeout=aiohttp.ClientTimeout(total=10)) as r:
                    await r.read()
                    counts[r.status] = counts.get(r.status, 0) + 1
            except (aiohttp.ClientError, TimeoutError):
                await asyncio.sleep(0.2)

    async with aiohttp.ClientSession() as session:
        await asyncio.gather(*(one(session) for _ in range(n)))


def run(pollers: int) -> dict:
    out = Path(tempfile.mkdtemp(prefix="view-load-"))
    t0 = time.monotonic()
    p = subprocess.Popen([sys.executable, "-m", "mission", "sim", "paper", "--json", "--out", str(out),
                          "--view", "127.0.0.1:0"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    stop, counts, poll_thread = threading.Event(), {}, None
    for line in p.stderr:
        m = re.search(r"live view at (http://\S+)", line)
        if m:
            if pollers:
                poll_thread = threading.Thread(target=asyncio.run, args=(_poll(m.group(1), pollers, stop, counts),),
                                               daemon=True)
                poll_thread.start()
            break
    for line in p.stderr:  # the page outlives the mission (until Ctrl-C): end it once the mission is over
        if "the mission is over" in line:
            break
    wall = time.monotonic() - t0
    p.send_signal(signal.SIGINT)
    p.communicate(timeout=60)
    stop.set()
    if poll_thread is not None:
        poll_thread.join(30)
    events = [json.loads(x) for x in (out / "mission.jsonl").read_text().splitlines() if '"survey_time"' in x]
    return {"pollers": pollers, "wall_s": wall, "largest_gap_s": events[-1]["largest_gap_s"],
            "survey_s": events[-1]["survey_s"], "answers": counts, "rc": p.returncode}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--pollers", type=int, default=50)
    args = ap.parse_args()
    runs = []
    for _ in range(args.pairs):
        for n in (0, args.pollers):
            r = run(n)
            runs.append(r)
            print(json.dumps(r), flush=True)
    for n in (0, args.pollers):
        sel = [r for r in runs if r["pollers"] == n]
        print(f"pollers {n:3d}: wall median {statistics.median(r['wall_s'] for r in sel):.1f} s, "
              f"largest gap median {statistics.median(r['largest_gap_s'] for r in sel):.2f} s")


if __name__ == "__main__":
    main()
