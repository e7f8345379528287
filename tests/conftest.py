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
    ~/.cache: the first test that plans compiles them, the rest load them."""
    import os

    folders = {"UAVLOC_RUNS": "uavloc-runs", "UAVLOC_KERNEL_CACHE": "kernel-cache"}
    old = {name: os.environ.get(name) for name in folders}
    for name, folder in folders.items():
        os.environ[name] = str(tmp_path_factory.mktemp(folder))
    yield
    for name, value in old.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


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


@pytest.fixture
def px4(px4_build, tmp_path):
    """A fresh PX4 SITL (SIH quadrotor) of the user's build for one test: its own instance (1-8,
    one not in use), speed factor tests.px4.PX4_SPEED, a fresh working directory; stopped after the
    test. Skips when PX4 does not print `Ready for takeoff!` in time."""
    from sitl_scenarios.px4_sitl import Px4Sitl, instance_busy
    from tests.px4 import PX4_SPEED, READY_TIMEOUT_S

    global _px4_next
    instance = None
    for _ in range(2 * len(PX4_INSTANCES)):
        candidate = next(_px4_next, None)
        if candidate is None:
            _px4_next = iter(PX4_INSTANCES)
            continue
        if not instance_busy(candidate):
            instance = candidate
            break
    if instance is None:
        pytest.skip(f"every PX4 instance {PX4_INSTANCES.start}-{PX4_INSTANCES.stop - 1} is in use")
    sitl = Px4Sitl(px4_build, instance, PX4_SPEED, tmp_path / "px4-work", output=tmp_path / "px4.log")
    sitl.start()
    try:
        if not sitl.wait_ready(READY_TIMEOUT_S):
            tail = "".join(sitl.lines[-8:])
            pytest.skip(f"PX4 SITL (instance {instance}) did not print 'Ready for takeoff!' within "
                        f"{READY_TIMEOUT_S:g} s; its last lines:\n{tail}")
        yield sitl
    finally:
        sitl.stop()
