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
