"""The live view in a real browser: Debian's Chromium driven by Playwright (marker `browser`).

One simulated mission (`uavloc sim paper --view 127.0.0.1:0 --json --out DIR`, a subprocess) is
watched by a page from the first frame to the last; the tests then check what the page showed:
no console errors, user markers and ellipses that changed during the mission, and at the end the
ellipse radius equal to the JSON result's `error_bound_95_m`. `uavloc view LOG` on the same
mission's log: the slider shows the estimate of the chosen time.

Set UAVLOC_VIEW_SCREENSHOTS=DIR to keep screenshots of the page mid-mission and at the end.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from estimator.geodesy import Origin
from estimator.types import CHI2_2DOF_95
from tests.procs import stop_process

pytestmark = pytest.mark.browser

REPO = Path(__file__).resolve().parents[1]
# WebGL (the 3-D pane) on SwiftShader, Chromium's software renderer, headless without a GPU
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-quic",
                 "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync"]
#: guards against a hung subprocess or page, not timing assertions
HANG_GUARD_S = 300.0


def _chromium() -> str | None:
    for cand in (os.environ.get("UAVLOC_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium"),
                 shutil.which("chromium-browser")):
        if cand and Path(cand).exists():
            return cand
    return None


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    exe = _chromium()
    if exe is None:
        pytest.skip("no Chromium found (Debian package `chromium`; or set UAVLOC_CHROMIUM)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("playwright is not installed (pip install -e '.[test]')")
    profile = tmp_path_factory.mktemp("chromium-profile")
    with sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(str(profile), executable_path=exe, headless=True,
                                                    args=CHROMIUM_ARGS, viewport={"width": 1280, "height": 800})
        try:
            yield ctx
        finally:
            ctx.close()


def _screens_dir(tmp_path: Path) -> Path:
    d = os.environ.get("UAVLOC_VIEW_SCREENSHOTS")
    return Path(d) if d else tmp_path


class _Proc:
    """A uavloc subprocess whose stderr is read in a thread (the URL line is picked out)."""

    def __init__(self, args: list[str]):
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.p = subprocess.Popen([sys.executable, "-m", "mission", *args], cwd=REPO, env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self.urls: queue.Queue[str] = queue.Queue()
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for line in self.p.stderr:
            self.lines.append(line)
            m = re.search(r" at (http://\S+)", line)
            if m and "uavloc:" in line:
                self.urls.put(m.group(1))

    def url(self) -> str:
        try:
            return self.urls.get(timeout=HANG_GUARD_S)
        except queue.Empty:
            self.stop()
            raise AssertionError("no view URL printed:\n" + "".join(self.lines[-30:])) from None

    def close_after_mission(self) -> tuple[str, str]:
        """Once the command says the mission is over (its page stays until Ctrl-C): SIGINT, and its
        (stdout, stderr) once it exited."""
        deadline = time.monotonic() + HANG_GUARD_S
        while not any("the mission is over" in line for line in self.lines):
            if self.p.poll() is not None or time.monotonic() > deadline:
                raise AssertionError("the command did not keep its page after the mission:\n"
                                     + "".join(self.lines[-30:]))
            time.sleep(0.1)
        self.p.send_signal(signal.SIGINT)
        out, _ = self.p.communicate(timeout=60)
        self._t.join(10)
        return out, "".join(self.lines)

    def stop(self) -> None:
        stop_process(self.p, grace_s=10)


def _watch(page) -> list[str]:
    errors: list[str] = []
    page.on("console", lambda m: errors.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(f"page error: {e}"))
    return errors


JS_SNAPSHOT = """() => ({
  conn: document.getElementById('conn').textContent,
  state: document.getElementById('m-state').textContent,
  frames: Number(document.body.dataset.frames || 0),
  ellipses: [...document.querySelectorAll('#ellipses ellipse')].map(e => ({
     id: e.dataset.user, rx: Number(e.getAttribute('rx')), ry: Number(e.getAttribute('ry')),
     cx: Number(e.getAttribute('cx')), cy: Number(e.getAttribute('cy')), r95: Number(e.dataset.r95M)})),
  markers: [...document.querySelectorAll('#markers [data-marker]')].map(
     m => [m.getAttribute('cx'), m.getAttribute('cy')]),
  r95_text: Object.fromEntries([...document.querySelectorAll('#users tbody tr')].map(
     tr => [tr.dataset.user, tr.querySelector('.r95').textContent])),
  vehicle: (document.getElementById('vehicle') || {getAttribute: () => null}).getAttribute('transform'),
  health: Object.fromEntries([...document.querySelectorAll('#health .v')].map(
     v => [v.id, {text: v.textContent, value: v.dataset.value, warn: v.parentElement.classList.contains('warn')}])),
  target: document.getElementById('m-target').textContent,
})"""


@pytest.fixture(scope="module")
def live_mission(browser, tmp_path_factory):
    """Fly `sim paper` with --view and watch it from a page until the mission ends."""
    tmp = tmp_path_factory.mktemp("live")
    screens = _screens_dir(tmp)
    out = tmp / "out"
    proc = _Proc(["sim", "paper", "--json", "--speedup", "20", "--out", str(out), "--view", "127.0.0.1:0"])
    page = browser.new_page()
    errors = _watch(page)
    snapshots = []
    mid_shot = None
    try:
        page.goto(proc.url())
        deadline = time.monotonic() + HANG_GUARD_S
        while time.monotonic() < deadline:
            snap = page.evaluate(JS_SNAPSHOT)
            last = snapshots[-1] if snapshots else None
            if last is None or snap["ellipses"] != last["ellipses"] or snap["vehicle"] != last["vehicle"]:
                snapshots.append(snap)
            n_distinct = len({json.dumps(s["ellipses"]) for s in snapshots if s["ellipses"]})
            if mid_shot is None and n_distinct >= 4 and snap["state"].startswith("SURVEY"):
                mid_shot = screens / "view-live-mid.png"
                page.screenshot(path=str(mid_shot))
            if "mission ended" in snap["conn"] or "connection lost" in snap["conn"]:
                break
            page.wait_for_timeout(150)
        final = page.evaluate(JS_SNAPSHOT)
        end_shot = screens / "view-live-end.png"
        page.screenshot(path=str(end_shot))
        stdout, _ = proc.close_after_mission()
    finally:
        page.close()
        proc.stop()
    return {"snapshots": snapshots, "final": final, "errors": errors, "doc": json.loads(stdout),
            "log": out / "mission.jsonl", "stderr": "".join(proc.lines), "rc": proc.p.returncode,
            "mid_shot": mid_shot, "end_shot": end_shot, "target_m": _target_radius(out / "mission.jsonl")}


def _target_radius(log_path: Path) -> float:
    header = json.loads(log_path.read_text().splitlines()[0])
    return float(header["config"]["controller"]["flight"]["target_radius_m"])


def test_live_page_loads_and_runs_without_console_errors(live_mission):
    assert live_mission["rc"] == 0, live_mission["stderr"][-3000:]
    assert live_mission["errors"] == []
    assert "mission ended" in live_mission["final"]["conn"]
    assert live_mission["final"]["frames"] >= 3


def test_user_marker_and_ellipse_update_during_the_mission(live_mission):
    snaps = [s for s in live_mission["snapshots"] if s["ellipses"]]
    radii = {round(s["ellipses"][0]["rx"], 6) for s in snaps}
    centres = {(round(s["ellipses"][0]["cx"], 3), round(s["ellipses"][0]["cy"], 3)) for s in snaps}
    markers = {json.dumps(s["markers"]) for s in snaps}
    vehicles = {s["vehicle"] for s in live_mission["snapshots"] if s["vehicle"]}
    assert len(radii) >= 3 and len(centres) >= 3 and len(markers) >= 3, snaps[-3:]
    assert len(vehicles) >= 5
    # the uncertainty shrank from the first ellipse shown to the last
    assert snaps[-1]["ellipses"][0]["rx"] < snaps[0]["ellipses"][0]["rx"]
    assert live_mission["mid_shot"] is not None and live_mission["mid_shot"].exists()


def test_ellipse_radius_shown_at_the_end_is_the_json_results_bound(live_mission):
    from mission.result import NORMAL_END

    doc = live_mission["doc"]
    final = live_mission["final"]
    # any normal end draws its bounds (a busy machine may end the survey at the GPS floor instead)
    assert doc["status"] in NORMAL_END and all(u["error_bound_95_m"] is not None for u in doc["users"])
    for u in doc["users"]:
        shown = [e for e in final["ellipses"] if e["id"] == u["id"]]
        assert len(shown) == 1
        # the drawn ellipse (world units are metres) and the number in the panel
        assert shown[0]["rx"] == pytest.approx(u["error_bound_95_m"], rel=1e-9)
        assert shown[0]["r95"] == pytest.approx(u["error_bound_95_m"], rel=1e-9)
        assert final["r95_text"][u["id"]] == f"{u['error_bound_95_m']:.2f}"
        # and the centre is the JSON result's position
        assert [shown[0]["cx"], shown[0]["cy"]] == pytest.approx(u["enu_m"][:2], abs=0.006)


def test_the_strip_shows_the_last_telemetry_records_health(live_mission):
    """Each field of the instrument strip at the end is the last telemetry record's value, as
    written to the mission log (ages and the rate: from the records, at the state's time)."""
    records = [json.loads(line) for line in live_mission["log"].read_text().splitlines()]
    last = [r for r in records if r["type"] == "telemetry"][-1]
    h = live_mission["final"]["health"]
    num = {k: float(v["value"]) for k, v in h.items() if v["value"] not in ("", "true", "false") and k not in
           ("h-mode", "h-gps")}
    vn, ve, vd = last["vel_ned_mps"]
    assert num["h-rel-alt"] == pytest.approx(last["rel_alt_m"], abs=1e-3)
    assert num["h-amsl"] == pytest.approx(last["alt_m"], abs=1e-3)
    assert num["h-gs"] == pytest.approx(float(np.hypot(vn, ve)), abs=1e-3)
    assert num["h-climb"] == pytest.approx(-vd, abs=1e-3)
    assert num["h-hdg"] == pytest.approx(last["heading_deg"], abs=1e-3)
    assert num["h-bat"] == pytest.approx(last["battery_pct"], abs=1e-3)
    assert h["h-bat"]["text"] == f"{last['battery_pct']:.0f} % · {last['battery_voltage_v']:.2f} V"
    assert h["h-mode"]["text"] == last["flight_mode"] and last["flight_mode"]
    assert h["h-armed"]["text"] == ("armed" if last["armed"] else "disarmed")
    assert h["h-gps"]["text"] == f"3D fix · {last['gps_satellites']} sats" and last["gps_fix_type"] == 3
    assert h["h-rel-alt"]["text"] == f"{last['rel_alt_m']:.1f} m"
    t_end = max(r["t"] for r in records)
    rtt = [r["t"] for r in records if r["type"] == "rtt"]
    assert num["h-veh-age"] == pytest.approx(t_end - last["t"], abs=0.01)
    assert num["h-gnb-age"] == pytest.approx(t_end - max(rtt), abs=0.01)
    assert num["h-rate"] == sum(1 for t in rtt if t > t_end - 60.0)
    # mid-mission the vehicle was live: a strip seen in SURVEY had a fresh vehicle record
    survey = [s for s in live_mission["snapshots"]
              if s["state"].startswith("SURVEY") and s["health"]["h-veh-age"]["value"]]
    assert survey and all(not s["health"]["h-veh-age"]["warn"] for s in survey)
    target = live_mission["target_m"]
    users = live_mission["doc"]["users"]
    within = sum(1 for u in users if u["error_bound_95_m"] <= target and not u.get("ambiguous"))
    assert live_mission["final"]["target"].startswith(f"{target:g} m: {within}/{len(users)} users within")


def test_the_missions_log_header_carries_the_scenarios_area(live_mission):
    """What the page and the exports draw: the fence and the altitude band of the scenario."""
    from mission.log import read_mission_log
    from sitl_scenarios.scenario import load_scenario

    sc = load_scenario("paper")
    h = read_mission_log(live_mission["log"]).header
    ring = np.array(h.geofence)
    back = h.origin.lla_to_enu(ring[:, 0], ring[:, 1], h.origin.alt_m)[:, :2]
    np.testing.assert_allclose(back, sc.geofence.polygon_enu_m, atol=0.01)
    assert h.altitude_band_m == {"min_m": sc.mission.flight.alt_min_m, "max_m": sc.mission.flight.alt_max_m}
    assert h.max_distance_m == sc.geofence.max_distance_m and h.buildings == [] and h.no_fly_zones == []


@contextlib.contextmanager
def _view_log(log_path: Path):
    proc = _Proc(["view", str(log_path), "--port", "0"])
    try:
        yield proc.url()
    finally:
        proc.stop()


def test_view_log_slider_shows_the_estimate_of_the_chosen_time(live_mission, browser, tmp_path):
    log_path = live_mission["log"]
    records = [json.loads(line) for line in log_path.read_text().splitlines()]
    origin = Origin(**records[0]["origin"])
    estimates = [r for r in records if r["type"] == "estimate" and not r.get("final")]
    assert len(estimates) >= 10
    # the mid-mission estimate, and a time just after it (before the next record of any kind)
    i_rec = records.index(estimates[len(estimates) // 2])
    chosen = records[i_rec]
    t_next = min(r["t"] for r in records[i_rec + 1:])
    t_pick = round(chosen["t"] + 0.4 * (t_next - chosen["t"]), 6) if t_next > chosen["t"] else chosen["t"]
    assert all(r["t"] <= t_pick for r in records[:i_rec + 1])
    u = chosen["users"][0]
    expect_en = origin.lla_to_enu(u["lat_deg"], u["lon_deg"], u["alt_m"])[:2]
    expect_r95 = float(np.sqrt(CHI2_2DOF_95 * np.linalg.eigvalsh(np.array(u["cov_en_m2"]))[-1]))

    with _view_log(log_path) as url:
        page = browser.new_page()
        errors = _watch(page)
        try:
            page.goto(url)
            page.wait_for_function("() => document.body.dataset.sliderT !== undefined")
            page.evaluate("""(t) => { const s = document.getElementById('slider');
                                      s.value = String(t); s.dispatchEvent(new Event('input')); }""", t_pick)
            page.wait_for_function("(t) => Math.abs(Number(document.body.dataset.sliderT) - t) < 1e-9", arg=t_pick)
            snap = page.evaluate(JS_SNAPSHOT)
            page.screenshot(path=str(_screens_dir(tmp_path) / "view-log-slider.png"))
        finally:
            page.close()
    assert errors == []
    (shown,) = [e for e in snap["ellipses"] if e["id"] == u["id"]]
    assert [shown["cx"], shown["cy"]] == pytest.approx(expect_en, abs=0.006)
    assert shown["rx"] == pytest.approx(expect_r95, rel=1e-9)
    # not the final answer: the slider really went back in time
    final = live_mission["doc"]["users"][0]["error_bound_95_m"]
    assert abs(shown["rx"] - final) > 1e-6


@contextlib.contextmanager
def _server_in_thread(feed, **kw):
    """A ViewServer on its own event loop in a thread (the test thread drives the browser)."""
    import asyncio

    from mission.view.server import ViewServer

    started: queue.Queue = queue.Queue()
    loop = asyncio.new_event_loop()
    stop = asyncio.Event()

    async def main():
        async with ViewServer(feed, "127.0.0.1", 0, **kw) as server:
            started.put(server)
            await stop.wait()

    t = threading.Thread(target=loop.run_until_complete, args=(main(),), daemon=True)
    t.start()
    server = started.get(timeout=30)
    try:
        yield server
    finally:
        loop.call_soon_threadsafe(stop.set)
        t.join(30)
        loop.close()


def test_a_page_opened_before_the_mission_starts_draws_it_when_records_come(browser, tmp_path):
    from mission.view.server import LiveFeed
    from tests.test_view_state import write_mission

    records = write_mission(tmp_path / "m.jsonl")
    feed = LiveFeed()
    with _server_in_thread(feed) as server:
        page = browser.new_page()
        errors = _watch(page)
        try:
            page.goto(server.url)
            page.wait_for_function("() => document.getElementById('conn').textContent === 'live'")
            page.wait_for_function("() => Number(document.body.dataset.frames || 0) >= 1")
            for rec in records:
                feed.on_record(rec)  # from this thread: handed over to the server's loop
            page.wait_for_function("() => document.getElementById('m-state').textContent.startsWith('LANDED')")
            snap = page.evaluate(JS_SNAPSHOT)
            n_buildings = page.evaluate("() => document.querySelectorAll('#buildings polygon').length")
            n_nofly = page.evaluate("() => document.querySelectorAll('#area polygon.nofly').length")
        finally:
            page.close()
    assert errors == []
    assert n_buildings == 1 and n_nofly == 1
    assert sorted(e["id"] for e in snap["ellipses"]) == ["ue1", "ue2"]


def _solid_png(rgb: tuple[int, int, int], size: int = 8) -> bytes:
    """A size x size PNG of one colour (a map tile)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    rows = b"".join(b"\x00" + bytes(rgb) * size for _ in range(size))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", size, size, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


#: the tiles' colour: magenta, found nowhere else on the page
TILE_RGB = (255, 0, 255)
_PNG = _solid_png(TILE_RGB)


@contextlib.contextmanager
def _tile_server():
    """A local tile server that records the tiles asked for."""
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    asked: list[str] = []

    class Tiles(BaseHTTPRequestHandler):
        def do_GET(self):
            asked.append(self.path)
            self.send_response(200)
            self.send_header("Content-Type", "image/png")
            self.send_header("Content-Length", str(len(_PNG)))
            self.end_headers()
            self.wfile.write(_PNG)

        def log_message(self, *args):
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Tiles)
    t = threading.Thread(target=httpd.serve_forever, daemon=True)
    t.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_port}/tiles/{{z}}/{{x}}/{{y}}.png", asked
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.mark.parametrize("with_tiles", [False, True])
def test_the_page_loads_nothing_but_its_own_files_and_the_tiles_it_was_given(browser, tmp_path, with_tiles):
    from mission.view.server import LiveFeed
    from tests.test_view_state import write_mission

    records = write_mission(tmp_path / "m.jsonl")
    feed = LiveFeed()
    for rec in records:
        feed.state.apply(rec)
    with _tile_server() as (tiles_url, asked), \
            _server_in_thread(feed, tiles_url=tiles_url if with_tiles else None) as server:
        page = browser.new_page()
        errors = _watch(page)
        requests: list[str] = []
        page.on("request", lambda r: requests.append(r.url))
        try:
            page.goto(server.url)
            page.wait_for_function("() => document.getElementById('m-state').textContent.startsWith('LANDED')")
            if with_tiles:
                page.wait_for_function("() => document.querySelectorAll('#tiles image').length > 0")
                page.wait_for_timeout(300)
            n_images = page.evaluate("() => document.querySelectorAll('#tiles image').length")
            shot = page.locator("#map").screenshot()
        finally:
            page.close()
    assert errors == []
    own = f"http://127.0.0.1:{server.port}/"
    foreign = [u for u in requests if not u.startswith(own)]
    # the map's pixels: with tiles, mostly the tiles' colour (under the grid and the drawing)
    from io import BytesIO

    from PIL import Image

    px = np.asarray(Image.open(BytesIO(shot)).convert("RGB"), float)
    tile_share = float(np.mean(np.linalg.norm(px - np.array(TILE_RGB), axis=2) < 60))
    if with_tiles:
        assert tile_share > 0.5, tile_share
        assert n_images > 0 and asked
        assert foreign and all(u.startswith(tiles_url.split("/tiles/")[0] + "/tiles/") for u in foreign)
        # the tiles asked for cover the mission area: zoom level and indices around the origin
        z, x, y = (int(v) for v in asked[0].removesuffix(".png").split("/")[-3:])
        lat, lon = np.radians(43.6143), 7.0716
        assert abs(x - (lon + 180) / 360 * 2**z) < 4
        assert abs(y - (1 - np.log(np.tan(lat) + 1 / np.cos(lat)) / np.pi) / 2 * 2**z) < 4
    else:
        assert tile_share == 0.0
        assert n_images == 0 and foreign == [] and asked == []


@pytest.mark.parametrize("corr, inside, outside", [(4.0, (1, 1), (-1, 1)), (-4.0, (-1, 1), (1, 1))])
def test_an_ellipse_is_drawn_along_its_major_axis_north_up(browser, corr, inside, outside):
    """Σ = [[5, ±4], [±4, 5]]: the major axis points north-east (+) or north-west (−); on the
    page north is up, so a point 0.8 a along the major axis is on the ellipse, across it is not."""
    from mission.view.server import LiveFeed
    from tests.test_view_state import ORIGIN, USERS, lla

    feed = LiveFeed()
    est = {"id": "ue1", **lla(0, 0), "cov_en_m2": [[5, corr], [corr, 5]]}
    feed.state.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS[:1]})
    feed.state.apply({"type": "estimate", "t": 1, "users": [est]})
    with _server_in_thread(feed) as server:
        page = browser.new_page()
        try:
            page.goto(server.url)
            page.wait_for_function("() => document.querySelectorAll('#ellipses ellipse').length === 1")
            hits = page.evaluate("""([inside, outside]) => {
                const e = document.querySelector('#ellipses ellipse');
                const a = Number(e.getAttribute('rx'));
                const origin = document.querySelector('#markers .home').getBoundingClientRect();
                const cx = origin.x + origin.width / 2, cy = origin.y + origin.height / 2;
                const world = document.getElementById('world').getCTM();  // metres -> pixels
                const hit = ([de, dn]) => {
                    const k = 0.8 * a / Math.SQRT2;
                    const x = cx + world.a * de * k, y = cy + world.d * dn * k;
                    return document.elementsFromPoint(x, y).includes(e);
                };
                return [hit(inside), hit(outside), world.d < 0];
            }""", [list(inside), list(outside)])
        finally:
            page.close()
    assert hits == [True, False, True]


def _color_distance(rgba, hex_color: str) -> float:
    want = [int(hex_color[i:i + 2], 16) for i in (1, 3, 5)]
    return float(np.linalg.norm(np.subtract(rgba[:3], want)))


@pytest.mark.parametrize("view", ["top", "orbit", "side"])
def test_the_3d_pane_draws_the_vehicle_and_the_users_where_they_project(browser, view):
    """WebGL (SwiftShader): the pixels where the vehicle and each user's marker project are theirs
    (the vehicle dark, a user its colour), not the background; the buildings are extruded."""
    from mission.view.server import LiveFeed
    from tests.test_view_state import ORIGIN, USERS, lla

    feed = LiveFeed()
    feed.state.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS,
                      "altitude_band_m": {"min_m": 10.0, "max_m": 60.0}})
    for i in range(20):
        feed.state.apply({"type": "telemetry", "t": 1.0 + i, **lla(2.0 * i, 1.0 * i, 30.0),
                          "vel_ned_mps": [1.0, 2.0, 0.0], "heading_deg": 63.0})
    users = {"ue1": (-30.0, 40.0), "ue2": (50.0, -20.0)}
    feed.state.apply({"type": "estimate", "t": 21, "users": [
        {"id": uid, **lla(e, n), "cov_en_m2": [[9.0, 0.0], [0.0, 4.0]]} for uid, (e, n) in users.items()]})
    with _server_in_thread(feed) as server:
        page = browser.new_page()
        errors = _watch(page)
        try:
            page.goto(server.url)
            page.wait_for_function("() => window.uavloc3d && (window.uavloc3d.ready || window.uavloc3d.error)")
            assert page.evaluate("() => window.uavloc3d.error || null") is None
            page.wait_for_function("() => document.querySelectorAll('#ellipses ellipse').length === 2")
            page.evaluate("(v) => window.uavloc3d.setView(v)", view)
            probe = page.evaluate("""(users) => {
                const api = window.uavloc3d, f = window.uavlocState.frame;
                const s = Math.max(1.5, 100 / 120);
                const v = f.vehicle.enu_m;
                const pts = {vehicle: api.project(v[0], v[1], v[2])};
                for (const u of f.users) pts[u.id] = api.project(u.enu_m[0], u.enu_m[1], u.enu_m[2] + 0.9 * s);
                const names = Object.keys(pts);
                const px = api.pixels(names.map((k) => pts[k]));
                const box = document.getElementById('view3d').getBoundingClientRect();
                return {pts, px: Object.fromEntries(names.map((k, i) => [k, px[i]])), bg: api.background,
                        w: box.width, h: box.height, corner: api.pixels([[2, box.height - 2]])[0]};
            }""", list(users))
        finally:
            page.close()
    assert errors == []
    for name, (x, y, _z) in probe["pts"].items():
        assert 0 < x < probe["w"] and 0 < y < probe["h"], (name, x, y)
    bg = probe["bg"]
    for name, rgba in probe["px"].items():
        assert float(np.abs(np.subtract(rgba[:3], bg[:3])).max()) > 40, (name, rgba)
    assert max(probe["px"]["vehicle"][:3]) < 110, probe["px"]["vehicle"]  # the dark vehicle
    assert _color_distance(probe["px"]["ue1"], "#d35400") < 110, probe["px"]["ue1"]
    assert _color_distance(probe["px"]["ue2"], "#16a085") < 110, probe["px"]["ue2"]


JS_FLEET = """() => {
  const css = (node, prop) => node ? getComputedStyle(node)[prop] : null;
  const pts = (node) => node ? node.getAttribute('points').trim().split(/\\s+/).filter(Boolean).length : 0;
  const lines = (k) => k === 0 ? [document.getElementById('track'), document.getElementById('est-track'),
                                  document.getElementById('leg')]
                               : [...document.querySelectorAll(`#fleet-lines g[data-vehicle="${k}"] > *`)];
  const out = {legendFleet: document.getElementById('legend').classList.contains('fleet'),
               fleetLegendHidden: document.getElementById('fleet-legend').hidden,
               items: [...document.querySelectorAll('#fleet-legend .vitem')].map(b => ({
                 vehicle: b.dataset.vehicle, text: b.textContent, condition: b.dataset.condition,
                 warn: b.classList.contains('warn'), on: b.classList.contains('on')})),
               homes: [...document.querySelectorAll('#markers .home')].map(h => ({
                 vehicle: h.dataset.home, stroke: css(h, 'stroke')})),
               vehicles: [...document.querySelectorAll('#markers .vehicle')].map(v => ({
                 vehicle: v.dataset.vehicle, id: v.id, fill: css(v, 'fill')})),
               labels: [...document.querySelectorAll('#markers .vlabel')].map(t => t.textContent),
               events: [...document.querySelectorAll('#events li[data-vehicle]')].map(li => li.textContent),
               strip: document.getElementById('h-bat').textContent,
               heading: document.querySelector('#panel h2').textContent,
               lines: {}};
  for (const k of [0, 1]) {
    const [track, est, leg] = lines(k);
    out.lines[k] = {track: pts(track), est: pts(est), stroke: css(track, 'stroke'), estStroke: css(est, 'stroke'),
                    leg: leg ? leg.getAttribute('visibility') : null, legStroke: css(leg, 'stroke')};
  }
  return out;
}"""


def _rgb(hex_color: str) -> str:
    return "rgb({}, {}, {})".format(*(int(hex_color[i:i + 2], 16) for i in (1, 3, 5)))


def test_a_fleet_draws_each_vehicle_in_its_colour_with_a_legend_of_ids_and_health(browser, tmp_path):
    """Two vehicles (tests/test_view_state.py fleet_records): mid-survey each has its own coloured
    track, estimated track, leg, marker and home, and a legend entry with its id, battery, mode and
    condition; uav2's link loss shows in its entry; clicking it puts uav2 in the strip."""
    from mission.view.server import LiveFeed
    from tests.test_view_state import fleet_records

    recs = fleet_records()
    feed = LiveFeed()
    with _server_in_thread(feed) as server:
        page = browser.new_page()
        errors = _watch(page)
        try:
            page.goto(server.url)
            page.wait_for_function("() => Number(document.body.dataset.frames || 0) >= 1")
            for rec in recs:
                feed.on_record(rec)
                if rec["type"] == "estimate":
                    break
            page.wait_for_function("() => document.querySelectorAll('#fleet-lines polyline.est-track').length === 1"
                                   " && document.querySelectorAll('#fleet-legend .vitem').length === 2")
            page.wait_for_function(f"() => Number(document.body.dataset.version) === {feed.state.version}")
            mid = page.evaluate(JS_FLEET)
            page.screenshot(path=str(_screens_dir(tmp_path) / "view-fleet.png"))
            page.click('#fleet-legend .vitem[data-vehicle="1"]')
            page.wait_for_function("() => document.getElementById('h-vehicle').textContent.includes('uav2')")
            picked = page.evaluate(JS_FLEET)
            for rec in recs[recs.index(next(r for r in recs if r["type"] == "estimate")) + 1:]:
                feed.on_record(rec)
            page.wait_for_function("() => document.getElementById('m-state').textContent.startsWith('LANDED')")
            end = page.evaluate(JS_FLEET)
        finally:
            page.close()
    assert errors == []
    blue, green = _rgb("#2f6fdb"), _rgb("#1e8e3e")
    assert mid["legendFleet"] and not mid["fleetLegendHidden"]
    # 11 fixes each by the estimate (t = 11.5); the estimate's track: 3 keyframes of uav1, 2 of uav2
    assert mid["lines"]["0"]["track"] == 11 and mid["lines"]["1"]["track"] == 11
    assert mid["lines"]["0"]["est"] == 3 and mid["lines"]["1"]["est"] == 2
    assert mid["lines"]["0"]["stroke"] == mid["lines"]["0"]["estStroke"] == mid["lines"]["0"]["legStroke"] == blue
    assert mid["lines"]["1"]["stroke"] == mid["lines"]["1"]["estStroke"] == green
    assert mid["lines"]["0"]["leg"] == "visible" and mid["lines"]["1"]["leg"] == "hidden"  # uav2 returned
    assert [(v["vehicle"], v["fill"]) for v in mid["vehicles"]] == [("0", blue), ("1", green)]
    assert mid["vehicles"][0]["id"] == "vehicle" and mid["labels"] == ["uav1", "uav2"]
    assert [(h["vehicle"], h["stroke"]) for h in mid["homes"]] == [("0", blue), ("1", green)]
    (i1, i2) = mid["items"]
    assert i1["text"] == "uav1 · 80 % · OFFBOARD · flying" and not i1["warn"] and i1["on"]
    assert i2["text"].startswith("uav2 · 40 % · OFFBOARD · returning") and i2["condition"] == "returning"
    assert any(e.startswith("9.4 suav2 vehicle link lost") for e in mid["events"]), mid["events"]
    assert picked["strip"].startswith("40 %") and picked["items"][1]["on"] and not picked["items"][0]["on"]
    assert mid["strip"].startswith("80 %")
    assert [i["condition"] for i in end["items"]] == ["landed", "landed"]


def test_one_vehicle_keeps_the_colours_and_the_legend_of_before_fleets(browser, tmp_path):
    from mission.view.server import LiveFeed
    from tests.test_view_state import write_mission

    feed = LiveFeed()
    for rec in write_mission(tmp_path / "m.jsonl"):
        feed.state.apply(rec)
        if rec["type"] == "estimate":
            break
    with _server_in_thread(feed) as server:
        page = browser.new_page()
        errors = _watch(page)
        try:
            page.goto(server.url)
            page.wait_for_function("() => document.getElementById('m-state').textContent.startsWith('SURVEY')")
            snap = page.evaluate(JS_FLEET)
        finally:
            page.close()
    assert errors == []
    assert not snap["legendFleet"] and snap["fleetLegendHidden"] and snap["items"] == [] and snap["labels"] == []
    assert snap["lines"]["0"]["stroke"] == _rgb("#2f6fdb") and snap["lines"]["0"]["estStroke"] == _rgb("#e67e22")
    assert snap["lines"]["0"]["legStroke"] == _rgb("#8e44ad") and snap["lines"]["0"]["leg"] == "visible"
    assert snap["lines"]["1"]["track"] == 0
    assert snap["vehicles"] == [{"vehicle": None, "id": "vehicle", "fill": _rgb("#1d232a")}]
    assert snap["homes"] == [{"vehicle": None, "stroke": _rgb("#1d232a")}]
    assert snap["heading"] == "vehicle"


def test_the_3d_pane_draws_each_vehicle_of_a_fleet_in_its_colour(browser):
    """WebGL (SwiftShader), from above: where each vehicle projects, the pixel is nearer its own
    colour than the other vehicle's."""
    from mission.view.server import LiveFeed
    from tests.test_view_state import FLEET, ORIGIN, USERS, lla

    feed = LiveFeed()
    feed.state.apply({"type": "header", "t": 0, "origin": ORIGIN.to_dict(), "users": USERS, "vehicles": FLEET,
                      "altitude_band_m": {"min_m": 10.0, "max_m": 60.0}})
    for i in range(10):
        feed.state.apply({"type": "telemetry", "t": 1.0 + i, "vehicle": 0, **lla(-40.0 + 2 * i, 0, 30.0),
                          "heading_deg": 90.0})
        feed.state.apply({"type": "telemetry", "t": 1.0 + i, "vehicle": 1, **lla(50.0, -20.0 + 3 * i, 30.0),
                          "heading_deg": 0.0})
    with _server_in_thread(feed) as server:
        page = browser.new_page()
        errors = _watch(page)
        try:
            page.goto(server.url)
            page.wait_for_function("() => window.uavloc3d && (window.uavloc3d.ready || window.uavloc3d.error)")
            assert page.evaluate("() => window.uavloc3d.error || null") is None
            page.wait_for_function("() => document.querySelectorAll('#markers .vehicle').length === 2")
            page.evaluate("() => window.uavloc3d.setView('top')")
            px = page.evaluate("""() => {
                const api = window.uavloc3d;
                const pts = window.uavlocState.frame.vehicles.map((v) => api.project(...v.vehicle.enu_m));
                return api.pixels(pts);
            }""")
        finally:
            page.close()
    assert errors == []
    blue, green = "#2f6fdb", "#1e8e3e"
    assert _color_distance(px[0], blue) < _color_distance(px[0], green), px
    assert _color_distance(px[1], green) < _color_distance(px[1], blue), px
