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


@pytest.fixture(autouse=True)
def _fresh_o1_bookkeeping(request):
    """mission.gnb keeps, per (host, port), this process's last `o1 stats` and any it left
    unanswered: right for the one real gNB the `oai` tests share (a request one test abandons runs
    in the next), stale for a simulated gNB, whose ephemeral port a later test may get again."""
    if request.node.get_closest_marker("oai") is None:
        from mission import gnb

        gnb._O1_LAST_SENT.clear()
        gnb._O1_UNANSWERED.clear()


# --- real PX4 SITL (tests marked `px4`) ----------------------------------------------------------

#: PX4 instances the tests may use (API link UDP 14540+i, GCS link to 14690+i)
PX4_INSTANCES = range(11, 20)
_px4_next = iter(())


@pytest.fixture(scope="session")
def px4_launcher(tmp_path_factory):
    """A working copy of ../shared/px4-sitl (module commands linked to `px4`), made once per
    session; skips when the bundle or `bc` is missing."""
    from sitl_scenarios.px4_sitl import DEFAULT_BUNDLE, materialize, missing_requirement

    why = missing_requirement(DEFAULT_BUNDLE)
    if why is not None:
        pytest.skip(why)
    return materialize(DEFAULT_BUNDLE, tmp_path_factory.mktemp("px4-sitl") / "px4-sitl")


@pytest.fixture
def px4(px4_launcher, tmp_path):
    """A fresh PX4 SITL (SIH quadrotor) for one test: its own instance (11-19, one not in use),
    speed factor tests.px4.PX4_SPEED, a fresh working directory; stopped after the test. Skips
    when PX4 does not print `Ready for takeoff!` in time."""
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
    sitl = Px4Sitl(px4_launcher, instance, PX4_SPEED, tmp_path / "px4-work", output=tmp_path / "px4.log")
    sitl.start()
    try:
        if not sitl.wait_ready(READY_TIMEOUT_S):
            tail = "".join(sitl.lines[-8:])
            pytest.skip(f"PX4 SITL (instance {instance}) did not print 'Ready for takeoff!' within "
                        f"{READY_TIMEOUT_S:g} s; its last lines:\n{tail}")
        yield sitl
    finally:
        sitl.stop()
