"""The live view's server (mission/view/server.py) over real sockets, without a browser: access
token, loopback-only Host names, frames over the WebSocket while records are written, a client
that never reads, the recorded-log API, and `uavloc view` on a bad log."""

from __future__ import annotations

import asyncio
import json

import aiohttp
import numpy as np
import pytest

from mission.cli import main as cli_main
from mission.log import MissionLogWriter
from mission.view.address import parse_view_address
from mission.view.server import LiveFeed, LogFeed, ViewServer
from tests.test_view_state import ORIGIN, USERS, lla, write_mission
from uavloc.errors import MissionError


@pytest.mark.parametrize("text, expect", [
    ("9360", ("127.0.0.1", 9360)),
    ("0", ("127.0.0.1", 0)),
    ("0.0.0.0:9361", ("0.0.0.0", 9361)),
    ("localhost:9362", ("localhost", 9362)),
    ("[::1]:9363", ("::1", 9363)),
])
def test_view_address(text, expect):
    assert parse_view_address(text) == expect


@pytest.mark.parametrize("text", ["abc", "127.0.0.1:", "70000", "host:-1"])
def test_bad_view_address_is_a_clear_error(text):
    with pytest.raises(MissionError, match="--view"):
        parse_view_address(text)


@pytest.mark.parametrize("args", [["--view", "nowhere"], ["--view", "9360", "--view-tiles", "ftp://x/{z}/{x}/{y}"]])
def test_bad_view_options_are_usage_errors_before_anything_starts(args, capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main(["sim", "paper", *args])
    assert exc.value.code == 2
    assert "--view" in capsys.readouterr().err


def test_bad_tile_url_is_refused():
    with pytest.raises(MissionError, match="lacks"):
        ViewServer(LiveFeed(), tiles_url="http://tiles.local/{z}/{x}.png")
    with pytest.raises(MissionError, match="http"):
        ViewServer(LiveFeed(), tiles_url="file:///tmp/{z}/{x}/{y}.png")


async def _status(session, url, **kw) -> int:
    async with session.get(url, **kw) as r:
        await r.read()
        return r.status


def test_requests_without_the_token_are_refused_on_a_non_loopback_address():
    async def main():
        async with ViewServer(LiveFeed(), "0.0.0.0", 0) as server:
            assert server.token and f"?token={server.token}" in server.url
            base = f"http://127.0.0.1:{server.port}"
            async with aiohttp.ClientSession() as s:
                for path in ("/", "/static/view.js", "/api/info", "/api/frame", "/ws"):
                    assert await _status(s, base + path) == 403, path
                    assert await _status(s, base + path + "?token=wrong" + server.token[:-1]) == 403, path
                assert await _status(s, f"{base}/api/info?token={server.token}") == 200
            # the page sets the token as a cookie; the script, the API and the socket then need no query
            # (unsafe: the client's jar takes cookies from an IP address, as a browser does)
            async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as s:
                async with s.get(f"{base}/?token={server.token}") as r:
                    assert r.status == 200
                    assert "Content-Security-Policy" in r.headers
                assert await _status(s, f"{base}/static/view.js") == 200
                assert await _status(s, f"{base}/api/frame") == 200
                async with s.ws_connect(f"{base}/ws") as ws:
                    msg = await ws.receive(timeout=5)
                    assert json.loads(msg.data)["version"] == 0

    asyncio.run(main())


def test_loopback_needs_no_token_but_refuses_other_host_names():
    async def main():
        async with ViewServer(LiveFeed(), "127.0.0.1", 0) as server:
            assert server.token is None and "token" not in server.url
            base = f"http://127.0.0.1:{server.port}"
            async with aiohttp.ClientSession() as s:
                assert await _status(s, base + "/") == 200
                assert await _status(s, base + "/static/view.css") == 200
                assert await _status(s, base + "/static/secret.py") == 404
                # DNS rebinding: a page from another site resolving its name to 127.0.0.1
                assert await _status(s, base + "/api/info", headers={"Host": "evil.example:80"}) == 403

    asyncio.run(main())


def test_three_js_is_served_from_the_package_and_the_import_map_is_allowed_by_its_hash():
    import base64
    import hashlib
    import re
    from importlib import resources

    async def main():
        async with ViewServer(LiveFeed(), "127.0.0.1", 0) as server:
            base = f"http://127.0.0.1:{server.port}"
            async with aiohttp.ClientSession() as s:
                async with s.get(base + "/") as r:
                    html, csp = await r.text(), r.headers["Content-Security-Policy"]
                for name in ("three.module.min.js", "OrbitControls.js"):
                    async with s.get(base + "/static/vendor/" + name) as r:
                        assert r.status == 200 and r.content_type == "text/javascript"
                        body = await r.read()
                    assert body == resources.files("mission.view").joinpath(f"static/vendor/{name}").read_bytes()
                assert await _status(s, base + "/static/vendor/LICENSE") == 404
                assert await _status(s, base + "/static/vendor/..%2Fview.js") == 404
                assert await _status(s, base + "/static/view3d.js") == 200
        return html, csp

    html, csp = asyncio.run(main())
    (imap,) = re.findall(r'<script type="importmap">(.*?)</script>', html, re.S)
    digest = base64.b64encode(hashlib.sha256(imap.encode()).digest()).decode()
    script_src = re.search(r"script-src ([^;]*)", csp).group(1).split()
    assert script_src == ["'self'", f"'sha256-{digest}'"]  # no 'unsafe-inline', no other origin
    assert "three.module.min.js" in imap and "OrbitControls.js" in imap


def test_live_frames_follow_the_log_writer_and_slow_clients_skip_frames(tmp_path):
    """Two clients read and acknowledge every frame and rebuild the track incrementally (they
    share the frames built for a cursor); one reads but never acknowledges (a stalled page); one
    never reads at all. The writer goes on record after record; the stalled client got only its
    first frame and the final one, which still completes its picture; each reading client's
    picture equals the server's whole state."""
    async def main():
        feed = LiveFeed()
        async with ViewServer(feed, "127.0.0.1", 0, max_rate_hz=50.0) as server:
            base = f"http://127.0.0.1:{server.port}"
            async with aiohttp.ClientSession() as s1, aiohttp.ClientSession() as s2:
                idle = await s2.ws_connect(f"{base}/ws")  # never read
                stalled = await s2.ws_connect(f"{base}/ws")  # reads, never acknowledges
                sockets = [await s1.ws_connect(f"{base}/ws") for _ in range(2)]
                stalled_frames: list = []

                async def stalled_reader():
                    async for msg in stalled:
                        stalled_frames.append(json.loads(msg.data))
                        if stalled_frames[-1].get("ended"):
                            return
                tracks: list[list] = [[], []]
                frames: list[list] = [[], []]

                async def reader(i):
                    track = tracks[i]
                    async for msg in sockets[i]:
                        f = json.loads(msg.data)
                        frames[i].append(f)
                        part = f["track"]
                        track[:] = part["items"] if part["from"] == 0 else track + part["items"]
                        if f.get("ended"):
                            return
                        await sockets[i].send_str("ack")

                rd = asyncio.gather(reader(0), reader(1))
                st = asyncio.create_task(stalled_reader())
                with MissionLogWriter(tmp_path / "m.jsonl") as w:
                    w.subscribe(feed.on_record)
                    w.write_header(ORIGIN, USERS, {"mu": 1})
                    for i in range(3000):
                        w.write("telemetry", 0.1 * i, **lla(0.01 * i, 0.0, 30.0))
                        if i % 100 == 0:
                            await asyncio.sleep(0.005)
                await server.close()
                await asyncio.wait_for(rd, 10)
                await asyncio.wait_for(st, 10)
                await idle.close()
        assert feed.state.records == 3001
        full, _ = feed.state.frame()
        for track, fr in zip(tracks, frames, strict=True):
            assert len(track) == 3000
            assert track == full["track"]["items"]
            assert fr[-1]["ended"]
            assert 2 <= len(fr) < 3001  # frames were skipped, not queued per record
        assert len(stalled_frames) == 2 and stalled_frames[-1]["ended"]
        first, last = stalled_frames
        assert first["track"]["items"] + last["track"]["items"] == full["track"]["items"]

    asyncio.run(main())


def test_recorded_log_frames_at_the_chosen_time(tmp_path):
    records = write_mission(tmp_path / "m.jsonl")
    est = [r for r in records if r["type"] == "estimate"]

    async def main():
        async with ViewServer(LogFeed(records), "127.0.0.1", 0) as server:
            base = f"http://127.0.0.1:{server.port}"
            async with aiohttp.ClientSession() as s:
                async with s.get(f"{base}/api/info") as r:
                    info = await r.json()
                assert info["mode"] == "log" and info["t_end_s"] == 13.0
                async with s.get(f"{base}/api/frame", params={"t": str(est[1]["t"])}) as r:
                    f = await r.json()
                assert await _status(s, f"{base}/api/frame?t=nan") == 400
                assert await _status(s, f"{base}/api/frame?t=soon") == 400
                assert await _status(s, f"{base}/ws") == 404
        return f

    f = asyncio.run(main())
    u1 = f["users"][0]
    expect = ORIGIN.lla_to_enu(est[1]["users"][0]["lat_deg"], est[1]["users"][0]["lon_deg"], 150.0)
    np.testing.assert_allclose(u1["enu_m"][:2], expect[:2], atol=0.01)
    assert f["t"] == est[1]["t"]


def test_view_command_refuses_a_malformed_log_with_its_line(tmp_path, caplog):
    p = tmp_path / "m.jsonl"
    write_mission(p)
    lines = p.read_text().splitlines()
    lines[3] = '{"type": "telemetry", "t": 1.0, "lat_deg": 95}'
    p.write_text("\n".join(lines) + "\n")
    assert cli_main(["view", str(p), "--port", "0"]) == 1
    assert "m.jsonl:4" in caplog.text


@pytest.mark.sim
def test_fly_view_follows_a_flight_to_the_end(tmp_path):
    """`uavloc fly --view 127.0.0.1:0` against a vehicle and a gNB it did not start (the built-in
    vehicle and the simulated gNB stand in): a WebSocket viewer (no browser) follows the flight to
    LANDED; the last frame's users are the JSON result's; a real flight draws no truth, no buildings."""
    from tests.fly_rig import external_fly_rig
    from tests.test_view_browser import _Proc

    frames: list[dict] = []

    async def follow(url: str) -> None:
        async with aiohttp.ClientSession() as s, s.ws_connect(url.replace("http://", "ws://") + "ws") as ws:
            async for msg in ws:
                frames.append(json.loads(msg.data))
                if frames[-1]["ended"]:
                    return
                await ws.send_str("ack")

    with external_fly_rig(tmp_path, speedup=20.0) as rig:
        proc = _Proc(["fly", "--connect", rig.connect, "--gnb", rig.gnb, "--scenario", "paper", "--planner",
                      "lawnmower", "--log", str(tmp_path / "fly.jsonl"), "--json", "--view", "127.0.0.1:0"])
        try:
            asyncio.run(asyncio.wait_for(follow(proc.url()), 300))
            out, _ = proc.close_after_mission()
        finally:
            proc.stop()
    assert proc.p.returncode == 0, "".join(proc.lines)[-3000:]
    doc = json.loads(out)
    last = frames[-1]
    assert last["state"] == "LANDED" and last["status"] == doc["status"]
    assert "SURVEY" in {f["state"] for f in frames}
    assert last["measurements"] == doc["measurements"]
    (u,) = last["users"]
    assert u["r95_m"] == pytest.approx(doc["users"][0]["error_bound_95_m"], rel=1e-9)
    static = next(f["static"] for f in frames if "static" in f)
    assert static["command"] == "fly" and static["geofence"] and static["truth"] == {} and static["buildings"] == []


def test_every_route_shares_one_request_budget_and_answers_429_beyond_it(tmp_path):
    """Issue 21 #7: 50 clients polling /api/frame slowed the mission (only the WebSocket was
    limited). All routes take from one token bucket; with the clock held still exactly `burst`
    requests pass, the rest get 429 with Retry-After; time refills it at the rate."""
    records = write_mission(tmp_path / "m.jsonl")
    now = [100.0]

    async def main():
        feed = LiveFeed()
        async with ViewServer(feed, "127.0.0.1", 0, max_requests_hz=10.0, request_burst=20,
                              refused_delay_s=0.1, clock=lambda: now[0]) as server:
            for rec in records:
                feed.on_record(rec)
            base = f"http://127.0.0.1:{server.port}"
            routes = ["/", "/static/view.js", "/api/info", "/api/frame"]
            async with aiohttp.ClientSession() as s:
                async def get(path):
                    async with s.get(base + path) as r:
                        await r.read()
                        return r.status, r.headers.get("Retry-After")

                # 50 polling clients at once: 20 answered, 30 refused
                first = await asyncio.gather(*(get(routes[i % 4]) for i in range(50)))
                now[0] += 0.5  # 5 tokens back
                second = await asyncio.gather(*(get("/api/frame") for _ in range(8)))
                refused = server.requests_refused
        return first, second, refused

    first, second, refused = asyncio.run(main())
    assert sorted(st for st, _ in first).count(200) == 20
    assert all(st == 429 and int(ra) >= 1 for st, ra in first if st != 200)
    assert [st for st, _ in second].count(200) == 5
    assert refused == 30 + 3


def test_malformed_http_requests_print_no_traceback(tmp_path):
    """Issue 21 #6: each malformed request to the live view printed an aiohttp traceback on the
    mission's console; `uavloc view` now answers 400 and prints nothing of it."""
    import socket
    import subprocess
    import sys

    from tests.fly_rig import REPO
    from tests.procs import stop_process

    log_path = tmp_path / "m.jsonl"
    write_mission(log_path)
    proc = subprocess.Popen([sys.executable, "-m", "mission", "view", str(log_path), "--port", "0"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stderr.readline()
        port = int(first.split("http://127.0.0.1:", 1)[1].split("/", 1)[0])
        bad = [b"GARBAGE\r\n\r\n", b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: abc\r\n\r\n",
               b"\x00\x01\x02\xff\r\n\r\n",
               b"GET /api/frame HTTP/1.1\r\nHost: localhost\r\nX: " + b"a" * 20000 + b"\r\n\r\n"]
        answers = []
        for payload in bad:
            with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
                sock.sendall(payload)
                answers.append(sock.recv(64))
    finally:
        stop_process(proc, 5.0)
    _out, err = proc.communicate(timeout=10)
    assert all(a.startswith(b"HTTP/1.") and b" 400 " in a for a in answers), answers
    assert "Traceback" not in err and "Error handling request" not in err, err[-3000:]
