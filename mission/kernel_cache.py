"""The planner's compiled kernels, kept on disk between missions.

CasADi's JIT (planner.objective.jit_function) compiles the objective's kernels once per process:
about 8 s of the C compiler before every take-off (`planner_prepared` in the mission log), in
every campaign worker and in every `uavloc sim`. :func:`cached_kernel` is a
planner.objective.compile_hook that keeps the shared library instead, named by a hash of the C
source CasADi generates for the kernel (and of the compiler flags and CasADi's version): a kernel
whose expression changes gets a new name, so a stale library is never loaded. The first mission
compiles, the next ones load in milliseconds.

Where: $UAVLOC_KERNEL_CACHE, else $XDG_CACHE_HOME/uavloc/kernels, else ~/.cache/uavloc/kernels.
UAVLOC_KERNEL_CACHE=off compiles in every process as before (into the system's temporary folder).
Several processes may fill the cache at once: each compiles into a file of its own and renames it
into place, which is atomic.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import shlex
import subprocess
import tempfile
from pathlib import Path

import casadi as ca

log = logging.getLogger(__name__)

#: the environment variable naming the cache folder ("off": no cache)
CACHE_ENV = "UAVLOC_KERNEL_CACHE"


def kernel_cache_dir() -> Path | None:
    """The cache folder (module docstring), or None when the cache is off."""
    env = os.environ.get(CACHE_ENV, "").strip()
    if env.lower() in ("off", "0", "no", "none"):
        return None
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME", "").strip() or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "uavloc" / "kernels"


def _source(name: str, fun: ca.Function) -> str:
    """The C source CasADi generates for `fun` (what its JIT would compile)."""
    cg = ca.CodeGenerator(f"{name}.c", {"with_header": False})
    cg.add(fun)
    return cg.dump()


def _compile(source: str, library: Path, flags: tuple[str, ...]) -> None:
    """Compile C source into the shared library `library`, atomically (a file of this process's
    own, renamed into place). Raises RuntimeError with the compiler's words when it fails."""
    library.parent.mkdir(parents=True, exist_ok=True)
    compiler = shlex.split(os.environ.get("CC", "cc"))
    with tempfile.TemporaryDirectory(dir=library.parent, prefix=".build-") as tmp:
        c_path, so_path = Path(tmp) / "kernel.c", Path(tmp) / library.name
        c_path.write_text(source)
        try:
            proc = subprocess.run([*compiler, *flags, "-fPIC", "-shared", str(c_path), "-o", str(so_path), "-lm"],
                                  capture_output=True, text=True, timeout=600)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise RuntimeError(f"the C compiler {compiler[0]!r} could not run: {exc}") from exc
        if proc.returncode != 0:
            raise RuntimeError(f"the C compiler failed ({proc.returncode}): {proc.stderr.strip()[:500]}")
        os.replace(so_path, library)


def cached_kernel(name: str, inputs: list, outputs: list, cache_dir: Path,
                  flags: tuple[str, ...] = ("-O1",)) -> ca.Function:
    """A planner.objective.compile_hook: the kernel `name` from the cache's shared library, compiled
    into it first when absent (module docstring). RuntimeError when it cannot be compiled or loaded
    (the planner then interprets the kernel)."""
    fun = ca.Function(name, inputs, outputs)
    source = _source(name, fun)
    key = hashlib.sha256("\0".join([ca.__version__, " ".join(flags), source]).encode()).hexdigest()[:20]
    library = Path(cache_dir) / f"{name}-{key}.so"
    if not library.exists():
        log.debug("compiling planner kernel %s into %s", name, library)
        try:
            _compile(source, library, flags)
        except OSError as exc:  # the cache folder cannot be written
            raise RuntimeError(f"cannot write the kernel cache {library.parent}: {exc}") from exc
    # IPOPT's set-up asks CasADi for derivatives of the value kernel (the Lagrangian's gradient, for
    # the multipliers at the solution; the steps use the vgh kernel's exact ones): a library
    # carries no derivative code, so they are finite differences, else every solve fails
    return ca.external(name, str(library), {"enable_fd": True})


def use_kernel_cache() -> Path | None:
    """Have planner.objective compile its kernels through the cache (module docstring); returns
    the folder, or None when the cache is off (the kernels then compile in the system's temporary
    folder, as CasADi's JIT keeps its C source in the current directory while a kernel lives and
    leaves it there when the process is killed). Idempotent; a hook set by the caller stays."""
    from planner import objective

    if objective.compile_hook is not objective.jit_function:
        return None
    cache = kernel_cache_dir()
    if cache is None:
        objective.compile_hook = functools.partial(objective.jit_function,
                                                   directory=os.path.join(tempfile.gettempdir(), ""))
        return None
    objective.compile_hook = functools.partial(cached_kernel, cache_dir=cache, flags=objective.JIT_FLAGS)
    return cache
