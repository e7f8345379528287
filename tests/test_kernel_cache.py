"""The planner's kernels kept on disk between missions (mission.kernel_cache): loaded, not
compiled, by the next process; named by their C source, so a changed kernel is compiled anew."""

from __future__ import annotations

import subprocess
import sys

import casadi as ca
import numpy as np
import pytest

from mission.kernel_cache import cached_kernel, kernel_cache_dir
from planner import make_planner, objective
from planner.objective import Shape


def test_a_kernel_is_compiled_once_and_loaded_after(tmp_path):
    x = ca.SX.sym("x", 3)
    f = cached_kernel("uavloc_cache_test", [x], [ca.sumsqr(x) + ca.sin(x[0])], tmp_path)
    (lib,) = [p for p in tmp_path.iterdir() if p.suffix == ".so"]
    mtime = lib.stat().st_mtime_ns
    g = cached_kernel("uavloc_cache_test", [x], [ca.sumsqr(x) + ca.sin(x[0])], tmp_path)
    assert lib.stat().st_mtime_ns == mtime  # loaded, not compiled again
    v = np.array([0.3, -1.2, 2.0])
    want = float(np.sum(v * v) + np.sin(v[0]))
    assert float(f(v)) == pytest.approx(want, rel=1e-14) and float(g(v)) == pytest.approx(want, rel=1e-14)
    # another expression under the same name: another library, never the stale one
    h = cached_kernel("uavloc_cache_test", [x], [ca.sumsqr(x)], tmp_path)
    assert float(h(v)) == pytest.approx(float(np.sum(v * v)), rel=1e-14)
    assert len([p for p in tmp_path.iterdir() if p.suffix == ".so"]) == 2
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".build-")]  # nothing left behind


def test_the_planner_kernels_from_the_cache_equal_the_interpreted_ones(tmp_path):
    """The objective's value-gradient-Hessian kernel through the cache against the SX virtual
    machine, on random inputs."""
    shape = Shape(2, True, "E", 2, 4)
    interpreted = objective.kernel("vgh", shape, compiled=False)
    names = [interpreted.name_in(i) for i in range(interpreted.n_in())]
    sx_in = [ca.SX.sym(n, interpreted.sparsity_in(i)) for i, n in enumerate(names)]
    cached = cached_kernel("uavloc_vgh_test", sx_in, interpreted.call(sx_in), tmp_path)
    rng = np.random.default_rng(5)
    args = [rng.uniform(0.5, 2.0, interpreted.size_in(i)) for i in range(interpreted.n_in())]
    for a, b in zip(interpreted.call(args), cached.call(args), strict=True):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-10, atol=1e-12)


def test_a_second_process_loads_what_the_first_compiled(tmp_path):
    script = (
        "import casadi as ca; from mission.kernel_cache import cached_kernel; from pathlib import Path\n"
        "x = ca.SX.sym('x', 4)\n"
        f"f = cached_kernel('uavloc_proc_test', [x], [ca.sumsqr(ca.sin(x))], Path({str(tmp_path)!r}))\n"
        "print(float(f([1, 2, 3, 4])))\n"
    )
    out = [subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
           for _ in range(2)]
    assert out[0] == out[1] and float(out[0]) == pytest.approx(float(np.sum(np.sin([1, 2, 3, 4]) ** 2)))
    assert len([p for p in tmp_path.iterdir() if p.suffix == ".so"]) == 1


def test_the_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("UAVLOC_KERNEL_CACHE", str(tmp_path / "k"))
    assert kernel_cache_dir() == tmp_path / "k"
    monkeypatch.setenv("UAVLOC_KERNEL_CACHE", "off")
    assert kernel_cache_dir() is None
    monkeypatch.delenv("UAVLOC_KERNEL_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert kernel_cache_dir() == tmp_path / "xdg" / "uavloc" / "kernels"


def test_a_cache_that_cannot_compile_says_so(tmp_path, monkeypatch):
    """No C compiler: a RuntimeError naming it (planner.objective then interprets the kernel)."""
    monkeypatch.setenv("CC", "no-such-compiler-uavloc")
    x = ca.SX.sym("x", 2)
    with pytest.raises(RuntimeError, match="no-such-compiler-uavloc"):
        cached_kernel("uavloc_nocc_test", [x], [ca.sumsqr(x)], tmp_path)


def test_the_active_planner_solves_with_cached_kernels(tmp_path, monkeypatch, caplog):
    """IPOPT's problem asks CasADi for derivatives of the value kernel (its multipliers at the
    solution); a cached library carries none of its own, so they are CasADi's finite differences.
    Without them every solve failed at IPOPT's set-up and the planner fell back to its ring (a live
    PX4 mission then ended 'floor reached')."""
    import functools

    from planner import active
    from tests.test_planner import u_constraints
    from tests.test_planner_active import NOISE, _estimate_two_users

    monkeypatch.setattr(objective, "compile_hook", functools.partial(cached_kernel, cache_dir=tmp_path))
    monkeypatch.setattr(objective, "_KERNELS", {})
    monkeypatch.setattr(active, "_SOLVERS", {})
    planner = make_planner("casadi", u_constraints(), NOISE)
    from planner import PlanningState

    with caplog.at_level("WARNING"):
        r = planner.plan(PlanningState(np.array([0.0, -60.0, 30.0]), _estimate_two_users(ambiguous=False), 100.0))
    assert not [rec for rec in caplog.records if "IPOPT failed" in rec.getMessage()]
    assert r.status.startswith("ipopt"), r.status
    assert [p for p in tmp_path.iterdir() if p.suffix == ".so"]


# -- a damaged cache is never loaded (issue 49) -------------------------------------------------

#: a process that loads the kernel `uavloc_damage_test` from the cache folder argv[1], prints its
#: value at (1, 2, 3, 4) and its warnings (logging to stderr)
_LOADER = (
    "import logging, sys; logging.basicConfig(level=logging.WARNING, format='%(message)s')\n"
    "import casadi as ca; from pathlib import Path; from mission.kernel_cache import cached_kernel\n"
    "x = ca.SX.sym('x', 4)\n"
    "f = cached_kernel('uavloc_damage_test', [x], [ca.sumsqr(ca.sin(x))], Path(sys.argv[1]))\n"
    "print(float(f([1, 2, 3, 4])))\n"
)
_WANT = float(np.sum(np.sin([1, 2, 3, 4]) ** 2))


def _load_in_a_process(cache, timeout_s=120.0):
    """Load the kernel in a process of its own (a damaged library may kill it) -> CompletedProcess."""
    return subprocess.run([sys.executable, "-c", _LOADER, str(cache)], capture_output=True, text=True,
                          timeout=timeout_s)


def _library(cache):
    (lib,) = [p for p in cache.iterdir() if p.suffix == ".so"]
    return lib


def _assert_rebuilt(proc, lib, why):
    """The process loaded the kernel (exit 0, its value) after one warning naming `why`."""
    assert proc.returncode == 0, proc.stderr
    assert float(proc.stdout) == pytest.approx(_WANT)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and why in lines[0] and "compiled it again" in lines[0], proc.stderr
    sidecar = lib.with_name(lib.name + ".sha256")
    from mission.kernel_cache import _digest

    assert sidecar.read_text().split() == [str(n) for n in _digest(lib)]
    assert not [p for p in lib.parent.iterdir() if ".loading-" in p.name or p.name.startswith(".")]


@pytest.fixture
def filled_cache(tmp_path):
    proc = _load_in_a_process(tmp_path)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    return tmp_path


@pytest.mark.parametrize("damage, why", [
    ("truncated", "bytes"),           # half of the library: dlopen would die of SIGBUS
    ("garbage", "SHA-256"),           # as many bytes, none of them a library
    ("no sidecar", "no size and hash"),
])
def test_a_damaged_library_is_compiled_again_not_loaded(filled_cache, damage, why):
    lib = _library(filled_cache)
    data = lib.read_bytes()
    if damage == "truncated":
        lib.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        lib.write_bytes(np.random.default_rng(3).bytes(len(data)))
    else:
        lib.with_name(lib.name + ".sha256").unlink()
    _assert_rebuilt(_load_in_a_process(filled_cache), lib, why)
    assert lib.read_bytes() == data
    second = _load_in_a_process(filled_cache)  # and from then on loaded in silence
    assert second.returncode == 0 and second.stderr == "", second.stderr


def test_a_library_that_killed_its_loader_is_not_loaded_again(filled_cache, tmp_path_factory):
    """A verified library whose loading kills the process (here its constructor aborts; in the
    field a library damaged after its hash was written): the first process dies, leaving its
    loading marker; the next one discards the library, compiles it again and loads it."""
    from mission.kernel_cache import _digest

    lib = _library(filled_cache)
    src = tmp_path_factory.mktemp("bomb") / "bomb.c"
    src.write_text("#include <stdlib.h>\n__attribute__((constructor)) static void bomb(void) { abort(); }\n")
    subprocess.run(["cc", "-shared", "-fPIC", str(src), "-o", str(lib)], check=True, timeout=60)
    size, sha = _digest(lib)
    lib.with_name(lib.name + ".sha256").write_text(f"{size} {sha}\n")
    died = _load_in_a_process(filled_cache)
    assert died.returncode < 0, (died.returncode, died.stderr)  # killed by its signal
    assert [p for p in filled_cache.iterdir() if ".loading-" in p.name]
    _assert_rebuilt(_load_in_a_process(filled_cache), lib, "died while loading")


def test_a_loading_marker_of_a_live_process_is_not_a_crash(filled_cache):
    """Several processes load the same library at once: a marker whose process still runs is left
    alone (the library is loaded, not compiled again)."""
    lib = _library(filled_cache)
    mtime = lib.stat().st_mtime_ns
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        marker = lib.with_name(f"{lib.name}.loading-{sleeper.pid}")
        marker.touch()
        proc = _load_in_a_process(filled_cache)
        assert proc.returncode == 0 and proc.stderr == "", proc.stderr
        assert lib.stat().st_mtime_ns == mtime and marker.exists()
    finally:
        sleeper.kill()
        sleeper.wait()
