"""Controller benchmarks: event-loop lag while the estimator works, and a full `uavloc sim`.

    python benchmarks/controller.py [--users 3] [--keyframes 300] [--skip-sim]
    python benchmarks/controller.py --viewers 5 [--scenario three_users_nlos] [--rounds 3]

1. Event-loop lag: the controller's :class:`EstimatorWorker` solves keyframes of a simulated
   survey (estimator.simulate) back to back in its worker thread, while a
   :class:`LoopLagMonitor` measures how late a 10 ms `asyncio.sleep` wakes up. For contrast the
   same keyframes are solved inline on the event loop (what the worker thread prevents).
   Target: lag < 20 ms.
2. A whole `uavloc sim three_users_nlos --json` in a subprocess (imports, MAVSDK, simulators, real
   estimator and planner), wall time. Target: < 60 s.
3. Viewers mode (`--viewers N`): the same simulated mission from this process (SimulatedMission:
   controller here, the world (built-in vehicle, simulated gNB) and the estimator in child
   processes), once bare and once
   with the live view (`--view`: LiveFeed on the mission log writer + ViewServer in the mission's
   loop) watched by N WebSocket viewers in another process (N − 1 read every frame, one reads a
   frame per second: a slow client). Rounds alternate bare / viewers so both meet the same load.
   The controller's own LoopLagMonitor gives the event-loop lag. Target: p99 ≤ 20 ms with viewers
   (the median of the rounds' p99: the machine's load changes between rounds; every round is shown).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import subprocess
import sys
import time
from pathlib import Path

# benchmarks/ holds scripts named like packages (planner.py): the repository root replaces this
# folder on sys.path so that imports find the packages
_HERE = Path(__file__).resolve().parent
REPO = _HERE.parent
sys.path[:] = [str(REPO)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]

import numpy as np  # noqa: E402

from estimator.noise import NoiseModel  # noqa: E402
from estimator.online import OnlineEstimator  # noqa: E402
from estimator.simulate import simulate  # noqa: E402
from estimator.types import SolverParams  # noqa: E402
from mission.control.estimator_worker import EstimatorWorker  # noqa: E402
from mission.control.loop import LoopLagMonitor  # noqa: E402
from mission.estimation import MissionEstimator  # noqa: E402


async def lag_with_worker(keyframes, n_users: int, noise: NoiseModel, params: SolverParams,
                          mode: str) -> tuple[dict, list]:
    """Lag while EstimatorWorker (mode "process" or "thread") solves every keyframe."""
    worker = EstimatorWorker(MissionEstimator(n_users, np.zeros(n_users), noise, params, 1.0), confirm=False, mode=mode)
    monitor = LoopLagMonitor(0.01)
    done = asyncio.Event()
    count = 0

    def on_estimate(_est) -> None:
        nonlocal count
        count += 1
        if count == len(keyframes):
            done.set()

    async with asyncio.TaskGroup() as tg:
        mon = tg.create_task(monitor.run())
        run = tg.create_task(worker.run(on_estimate))
        await worker.ready.wait()
        monitor.lags_s.clear()  # measure while solving, not while the child process starts
        for kf in keyframes:
            worker.queue.put_nowait(kf)
        await done.wait()
        mon.cancel()
        run.cancel()
    return monitor.summary(), worker.solve_s


async def lag_idle(duration_s: float) -> dict:
    """Lag of the same loop doing nothing else for duration_s: the floor the machine's load sets."""
    monitor = LoopLagMonitor(0.01)
    async with asyncio.TaskGroup() as tg:
        mon = tg.create_task(monitor.run())
        await asyncio.sleep(duration_s)
        mon.cancel()
    return monitor.summary()


async def lag_inline(keyframes, n_users: int, noise: NoiseModel, params: SolverParams) -> dict:
    """Lag when the same keyframes are solved on the event loop itself."""
    online = OnlineEstimator(n_users, np.zeros(n_users), noise, params)
    monitor = LoopLagMonitor(0.01)
    async with asyncio.TaskGroup() as tg:
        mon = tg.create_task(monitor.run())
        await asyncio.sleep(0.05)
        for kf in keyframes:
            online.add_keyframe(kf)
            await asyncio.sleep(0)
        mon.cancel()
    return monitor.summary()


def _load() -> str:
    try:
        return Path("/proc/loadavg").read_text().split()[0]
    except OSError:
        return "?"


def fmt(s: dict) -> str:
    return (f"max {1e3 * s['max_s']:6.1f} ms  p99 {1e3 * s['p99_s']:6.1f} ms  "
            f"median {1e3 * s['median_s']:5.2f} ms  ({s['samples']} samples)")


# -- viewers mode ---------------------------------------------------------------------------------


async def _viewer_clients(url: str, n: int) -> dict:
    """N WebSocket viewers of a live view (the last one slow); returns what they received."""
    import aiohttp

    ws_url = url.replace("http://", "ws://").split("?")[0].rstrip("/") + "/ws"
    stats = [{"frames": 0, "bytes": 0, "track": 0} for _ in range(n)]

    async def viewer(i: int, session, ws) -> None:
        track = 0
        stats[i]["ended"] = False
        try:
            async for msg in ws:
                if msg.type != aiohttp.WSMsgType.TEXT:
                    break
                frame = json.loads(msg.data)
                part = frame["track"]
                track = len(part["items"]) + (0 if part["from"] == 0 else track)
                stats[i]["frames"] += 1
                stats[i]["bytes"] += len(msg.data)
                stats[i]["track"] = track
                if frame.get("ended"):
                    stats[i]["ended"] = True
                    return
                if i == n - 1:
                    await asyncio.sleep(1.0)  # the slow client
                with contextlib.suppress(aiohttp.ClientError):  # closing: still read what arrived
                    await ws.send_str("ack")
        except aiohttp.ClientError:
            pass  # the server closed while this (slow) client was still reading

    async with aiohttp.ClientSession() as session:
        sockets = [await session.ws_connect(ws_url, max_msg_size=0) for _ in range(n)]
        print("connected", flush=True)
        await asyncio.gather(*(viewer(i, session, ws) for i, ws in enumerate(sockets)))
    return {"viewers": stats}


async def _mission_lag(scenario, viewers: int, seed: int) -> tuple[dict, dict | None, float]:
    """One simulated mission in this loop; with `viewers`, the live view and N viewer clients."""
    import tempfile

    from mission.view.server import LiveFeed, ViewServer
    from sitl_scenarios.sim_runner import SimulatedMission

    class TimedFeed(LiveFeed):
        """LiveFeed that adds up the time spent taking records."""

        record_s = 0.0

        def on_record(self, rec: dict) -> None:
            t0 = time.perf_counter()
            super().on_record(rec)
            self.record_s += time.perf_counter() - t0

    class TimedServer(ViewServer):
        """ViewServer that adds up the time spent building frames and their JSON."""

        frame_s = 0.0

        def _frame_text(self, cursor):
            t0 = time.perf_counter()
            out = super()._frame_text(cursor)
            self.frame_s += time.perf_counter() - t0
            return out

    with tempfile.TemporaryDirectory(prefix="uavloc-bench-") as tmp:
        async with SimulatedMission(scenario, log_path=Path(tmp) / "m.jsonl", seed=seed, speedup=10.0) as sim:
            if not viewers:
                result = await sim.run()
                return result.loop_lag, None, result.wall_s
            feed = TimedFeed()
            sim.controller.log_writer.subscribe(feed.on_record)
            async with TimedServer(feed, "127.0.0.1", 0) as server:
                proc = await asyncio.create_subprocess_exec(
                    sys.executable, __file__, "--viewer-client", server.url, str(viewers),
                    stdout=asyncio.subprocess.PIPE)
                line = await asyncio.wait_for(proc.stdout.readline(), 60)
                if line.strip() != b"connected":
                    raise RuntimeError(f"viewer clients did not connect: {line!r}")
                result = await sim.run()
            out, _ = await asyncio.wait_for(proc.communicate(), 60)
            clients = json.loads(out.decode().strip().splitlines()[-1])
            clients["frames_sent"] = server.frames_sent
            clients["records"] = feed.state.records
            clients["record_s"], clients["frame_s"] = feed.record_s, server.frame_s
            return result.loop_lag, clients, result.wall_s


def viewers_mode(args) -> int:
    from sitl_scenarios.scenario import load_scenario

    scenario = load_scenario(args.scenario)
    print(f"event-loop lag of a whole `sim {args.scenario}` mission (speedup 10, in-process), "
          f"bare vs. live view with {args.viewers} WebSocket viewers (1 slow), {args.rounds} rounds, "
          f"load {_load()}:")
    idle = asyncio.run(lag_idle(10.0))
    print(f"  idle loop, 10 s:       {fmt(idle)}   <- this machine's floor now")
    bare, viewed = [], []
    for r in range(args.rounds):
        for v in (0, args.viewers):
            lag, clients, wall = asyncio.run(_mission_lag(scenario, v, args.seed))
            (viewed if v else bare).append(lag)
            label = f"{v} viewers" if v else "no view  "
            print(f"  round {r + 1}, {label}: {fmt(lag)}  wall {wall:5.1f} s")
            if clients:
                per = ", ".join(f"{c['frames']} frames/{c['bytes'] / 1e3:.0f} kB" for c in clients["viewers"])
                print(f"    {clients['records']} log records -> {clients['frames_sent']} frames sent; "
                      f"per viewer: {per}")
                print(f"    the view's own work on the loop: {1e3 * clients['record_s']:.0f} ms on records "
                      f"({1e6 * clients['record_s'] / max(clients['records'], 1):.0f} us each), "
                      f"{1e3 * clients['frame_s']:.0f} ms on frames and their JSON "
                      f"({1e6 * clients['frame_s'] / max(clients['frames_sent'], 1):.0f} us each), "
                      f"in {wall:.1f} s of mission")
                fast = clients["viewers"][:-1]
                print(f"    the fast viewers got the final frame with the whole GPS track: "
                      f"{all(c['ended'] and c['track'] == fast[0]['track'] for c in fast)} "
                      f"({fast[0]['track']} points); the slow one: {clients['viewers'][-1]['track']} points")
    # the machine's load varies from round to round: judge on the median over rounds, show the worst too
    p99_bare = float(np.median([s["p99_s"] for s in bare]))
    p99_view = float(np.median([s["p99_s"] for s in viewed]))
    print(f"  p99, median over rounds: no view {1e3 * p99_bare:.1f} ms, {args.viewers} viewers "
          f"{1e3 * p99_view:.1f} ms (ratio {p99_view / max(p99_bare, 1e-9):.2f}); worst round: no view "
          f"{1e3 * max(s['p99_s'] for s in bare):.1f} ms, {args.viewers} viewers "
          f"{1e3 * max(s['p99_s'] for s in viewed):.1f} ms")
    ok = p99_view <= 0.020
    print(f"  target p99 <= 20 ms with {args.viewers} viewers (median over rounds): {'met' if ok else 'NOT met'}")
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--users", type=int, default=3)
    ap.add_argument("--keyframes", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--skip-sim", action="store_true", help="skip the full `uavloc sim` run")
    ap.add_argument("--scenario", default="three_users_nlos")
    ap.add_argument("--viewers", type=int, default=0,
                    help="viewers mode: event-loop lag of a mission with the live view and N viewers")
    ap.add_argument("--rounds", type=int, default=3, help="viewers mode: rounds of (bare, viewers)")
    ap.add_argument("--viewer-client", nargs=2, metavar=("URL", "N"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.viewer_client:
        print(json.dumps(asyncio.run(_viewer_clients(args.viewer_client[0], int(args.viewer_client[1])))))
        return 0
    if args.viewers:
        return viewers_mode(args)

    noise = NoiseModel()
    params = SolverParams()
    sc = simulate(np.random.default_rng(args.seed), n_users=args.users, n_keyframes=args.keyframes,
                  pattern="lawnmower", noise=noise)
    print(f"event-loop lag, {args.users} users, {args.keyframes} keyframes solved back to back "
          f"(window {params.window}):")
    t0 = time.monotonic()
    worker_lag, solve_s = asyncio.run(lag_with_worker(sc.keyframes, args.users, noise, params, "process"))
    busy_s = time.monotonic() - t0
    solve = np.asarray(solve_s)
    idle = asyncio.run(lag_idle(busy_s))
    thread_lag, _ = asyncio.run(lag_with_worker(sc.keyframes, args.users, noise, params, "thread"))
    print(f"  idle loop, same duration:      {fmt(idle)}   <- this machine's floor (load {_load()})")
    print(f"  estimator in a child process:  {fmt(worker_lag)}   <- the controller's default")
    print(f"    (keyframe round trip: median {1e3 * np.median(solve):.1f} ms, max {1e3 * solve.max():.1f} ms)")
    print(f"  estimator in a worker thread:  {fmt(thread_lag)}   <- GIL shared with the loop")
    inline = asyncio.run(lag_inline(sc.keyframes, args.users, noise, params))
    print(f"  estimator inline on the loop:  {fmt(inline)}")
    ok = worker_lag["max_s"] < 0.020
    print(f"  target max lag < 20 ms with the estimator worker: {'met' if ok else 'NOT met'}")

    if not args.skip_sim:
        print(f"\nfull `uavloc sim {args.scenario} --json` (subprocess, default speedup and planner):")
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-m", "mission", "-q", "sim", args.scenario, "--json"],
                              cwd=REPO, capture_output=True, text=True, timeout=600)
        wall = time.monotonic() - t0
        if proc.returncode != 0:
            print(proc.stderr[-3000:])
            print(f"  FAILED with exit code {proc.returncode} after {wall:.1f} s")
            return 1
        doc = json.loads(proc.stdout)
        print(f"  wall {wall:.1f} s (target < 60 s): status {doc['status']}, {doc['measurements']} ranges, "
              f"{doc['flown_m']:.0f} m flown")
        for u in doc["users"]:
            err = u.get("error_m")
            print(f"    {u['id']}: E {u['enu_m'][0]:+7.1f} N {u['enu_m'][1]:+7.1f}  "
                  f"95% bound {u.get('error_bound_95_m') or float('nan'):.2f} m  error "
                  f"{err if err is None else round(err, 2)} m")
        ok = ok and wall < 60.0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
