"""Shared test fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """../shared/data beside the checkout; tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(autouse=True, scope="session")
def _private_folders(tmp_path_factory):
    """Folders of this test session, not the user's (subprocesses inherit them): missions flown
    without --out keep their log under $UAVLOC_RUNS (mission.commands.outdir), not ~/uavloc-runs;
    the planner's compiled kernels go to $UAVLOC_KERNEL_CACHE (mission.kernel_cache), not
    ~/.cache: the first test that plans compiles them, the rest load them. Under pytest-xdist
    (`-n 2`, the README's command) the workers share one kernel cache (mission.kernel_cache
    writes atomically and verifies what it loads), so a kernel is compiled once per run."""
    import os

    if os.environ.get("PYTEST_XDIST_WORKER"):
        kernels = tmp_path_factory.getbasetemp().parent / "kernel-cache-shared"
        kernels.mkdir(exist_ok=True)
    else:
        kernels = tmp_path_factory.mktemp("kernel-cache")
    folders = {"UAVLOC_RUNS": tmp_path_factory.mktemp("uavloc-runs"), "UAVLOC_KERNEL_CACHE": kernels}
    old = {name: os.environ.get(name) for name in folders}
    for name, folder in folders.items():
        os.environ[name] = str(folder)
    yield
    for name, value in old.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


#: markers of tests that run the user's own peer builds (fixed PX4 ports, one OAI gNB per module):
#: under pytest-xdist's `--dist loadgroup` they all run on one worker, one after the other
PEER_MARKERS = ("px4", "ardupilot", "oai")


def pytest_itemcollected(item):
    """xdist groups: the peer tests on one worker (above); and the tests of a module that share a
    module- or class-scoped fixture (a flight, a browser) on one worker, which builds it once —
    spread over both, each worker built it again (about 150 worker-seconds of the README's run).
    Marked as each item is collected: pytest-xdist's worker reads the marks in its own
    pytest_collection_modifyitems, which runs before a conftest's."""
    if any(item.get_closest_marker(m) is not None for m in PEER_MARKERS):
        item.add_marker(pytest.mark.xdist_group("peers"))
    elif _shares_a_module_fixture(item):
        item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::", 1)[0]))


def _shares_a_module_fixture(item) -> bool:
    info = getattr(item, "_fixtureinfo", None)  # pytest's own record of the item's fixtures
    if info is None:
        return False
    return any(d.scope in ("module", "class") for defs in info.name2fixturedefs.values() for d in defs)


@pytest.fixture(autouse=True)
def _fresh_o1_bookkeeping(request):
    """mission.gnb.client keeps, per (host, port), this process's last `o1 stats` and any it left
    unanswered: right for the one real gNB the `oai` tests share (a request one test abandons runs
    in the next), stale for a simulated gNB, whose ephemeral port a later test may get again."""
    if request.node.get_closest_marker("oai") is None:
        from mission.gnb import client as gnb

        gnb._O1_LAST_SENT.clear()
        gnb._O1_UNANSWERED.clear()


# --- the user's PX4 SITL build (tests marked `px4`) ----------------------------------------------

#: PX4 instances the tests may use: API link UDP 14540+i, GCS link on 18570+i (PX4's stock ports;
#: above 9 every instance would send its API link to the same port 14549)
PX4_INSTANCES = range(1, 9)
_px4_next = iter(())


@pytest.fixture(scope="session")
def px4_build():
    """The PX4 build folder UAVLOC_PX4 names (build/px4_sitl_default); skips, naming UAVLOC_PX4,
    when it is unset or not a px4_sitl build."""
    from sitl_scenarios.px4_sitl import build_from_env, missing_requirement

    build = build_from_env()
    why = missing_requirement(build)
    if why is not None:
        pytest.skip(why)
    return build


def _free_px4_instance(taken: tuple[int, ...] = ()) -> int:
    """The next PX4 instance of PX4_INSTANCES (round robin over the session) that no PX4 server
    runs as and whose ports are free, other than `taken`; skips the test when there is none."""
    from sitl_scenarios.px4_sitl import instance_busy

    global _px4_next
    for _ in range(2 * len(PX4_INSTANCES)):
        candidate = next(_px4_next, None)
        if candidate is None:
            _px4_next = iter(PX4_INSTANCES)
            continue
        if candidate not in taken and not instance_busy(candidate):
            return candidate
    pytest.skip(f"every PX4 instance {PX4_INSTANCES.start}-{PX4_INSTANCES.stop - 1} is in use")


def _wait_px4_ready(sitl) -> None:
    """Skips when PX4 does not print `Ready for takeoff!` in time, with its last lines."""
    from tests.px4 import READY_TIMEOUT_S

    if not sitl.wait_ready(READY_TIMEOUT_S):
        tail = "".join(sitl.lines[-8:])
        pytest.skip(f"PX4 SITL (instance {sitl.instance}) did not print 'Ready for takeoff!' within "
                    f"{READY_TIMEOUT_S:g} s; its last lines:\n{tail}")


@pytest.fixture
def px4(px4_build, tmp_path):
    """A fresh PX4 SITL (SIH quadrotor) of the user's build for one test: its own instance (1-8,
    one not in use), speed factor tests.px4.PX4_SPEED, a fresh working directory; stopped after the
    test. Skips when PX4 does not print `Ready for takeoff!` in time."""
    from sitl_scenarios.px4_sitl import Px4Sitl
    from tests.px4 import PX4_SPEED

    instance = _free_px4_instance()
    sitl = Px4Sitl(px4_build, instance, PX4_SPEED, tmp_path / "px4-work", output=tmp_path / "px4.log")
    sitl.start()
    try:
        _wait_px4_ready(sitl)
        yield sitl
    finally:
        sitl.stop()


#: SIH's default home (PX4_HOME_LAT/LON/ALT unset): lat, lon [deg], alt [m AMSL]
PX4_SIH_HOME = (47.3977433, 8.5455916, 489.0)
#: how far east of the first the second vehicle of `px4_pair` takes off [m]
PX4_PAIR_EAST_M = 20.0


@pytest.fixture
def px4_pair(px4_build, tmp_path):
    """Two fresh PX4 SITLs (SIH quadrotors) for one test, as `px4` starts one: each its own free
    instance, speed factor tests.px4.PX4_SPEED, its own working directory; the first at SIH's
    default home, the second PX4_PAIR_EAST_M east of it (same altitude). Both start at once; skips
    when either does not print `Ready for takeoff!` in time; both stopped after the test."""
    from estimator.geodesy import Origin
    from sitl_scenarios.px4_sitl import Px4Sitl
    from tests.px4 import PX4_SPEED

    first = _free_px4_instance()
    second = _free_px4_instance(taken=(first,))
    lat, lon, alt = Origin(*PX4_SIH_HOME).enu_to_lla([PX4_PAIR_EAST_M, 0.0, 0.0])
    homes = (PX4_SIH_HOME, (float(lat), float(lon), float(alt)))
    sitls = [Px4Sitl(px4_build, instance, PX4_SPEED, tmp_path / f"px4-work-{i}", home=home,
                     output=tmp_path / f"px4-{i}.log")
             for i, (instance, home) in enumerate(zip((first, second), homes, strict=True))]
    try:
        for sitl in sitls:
            sitl.start()
        for sitl in sitls:
            _wait_px4_ready(sitl)
        yield sitls
    finally:
        for sitl in sitls:
            sitl.stop()
