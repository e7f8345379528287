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

A damaged library must never be loaded: a truncated one makes dlopen touch pages past its end
(SIGBUS, the process dies without a word), a garbage one fails with many lines of CasADi's. So:

- written atomically: each process compiles into a build folder of its own beside the cache,
  fsyncs the library and renames it into place, then writes its sidecar `<library>.sha256`
  ("<size> <sha256>") the same way; several processes may fill the cache at once;
- verified before loading: a library without its sidecar, or whose size or SHA-256 differ from
  it, is compiled anew (one warning says why), never loaded;
- a crash while loading does not recur: a marker `<library>.loading-<pid>` is written before the
  dlopen and removed after; a marker whose process is gone means that process died loading the
  library, and the next one compiles it anew;
- a verified library that still does not load (another C library, a folder mounted noexec) is a
  RuntimeError in one line, and the planner interprets the kernel.
"""

from __future__ import annotations

import contextlib
import functools
import glob
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


def _fsync_folder(folder: Path) -> None:
    """Make a rename in `folder` durable (a crash after it finds the new name, not the old)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _write_atomically(path: Path, data: bytes) -> None:
    """Write `data` to `path` whole or not at all: a temporary file of this process in the same
    folder, fsync, rename into place (atomic), fsync the folder."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_folder(path.parent)


def _digest(path: Path) -> tuple[int, str]:
    """(size [bytes], SHA-256 hex) of the file at `path`."""
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
            size += len(chunk)
    return size, h.hexdigest()


def _sidecar(library: Path) -> Path:
    """The file beside a library holding its size and SHA-256 ("<size> <sha256>\\n")."""
    return library.with_name(library.name + ".sha256")


def _compile(source: str, library: Path, flags: tuple[str, ...]) -> None:
    """Compile C source into the shared library `library`, atomically (a build folder of this
    process's own beside it, fsync, rename into place), then write its sidecar (size and SHA-256).
    Raises RuntimeError with the compiler's words when it fails."""
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
        with open(so_path, "rb") as f:
            os.fsync(f.fileno())
        size, sha = _digest(so_path)
        os.replace(so_path, library)
    _fsync_folder(library.parent)
    # after the library: a library without its sidecar is unverified, never loaded
    _write_atomically(_sidecar(library), f"{size} {sha}\n".encode())


def _damage(library: Path) -> str | None:
    """Why the cached `library` must not be loaded (a phrase), or None when its size and SHA-256
    match its sidecar's."""
    try:
        words = _sidecar(library).read_text().split()
    except FileNotFoundError:
        return "it has no size and hash beside it"
    except OSError as exc:
        return f"its size and hash cannot be read: {exc.strerror}"
    if len(words) != 2 or not words[0].isdigit():
        return "the size and hash beside it are unreadable"
    try:
        size, sha = _digest(library)
    except OSError as exc:
        return f"it cannot be read: {exc.strerror}"
    if size != int(words[0]):
        return f"it has {size} bytes, {words[0]} were written"
    if sha != words[1]:
        return "its SHA-256 differs from the one written"
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _crashed_loads(library: Path) -> list[Path]:
    """The loading markers of `library` whose process is gone: it died while loading it."""
    found = []
    for marker in library.parent.glob(f"{glob.escape(library.name)}.loading-*"):
        pid = marker.name.rsplit("-", 1)[-1]
        if not pid.isdigit() or (int(pid) != os.getpid() and not _alive(int(pid))):
            found.append(marker)
    return found


def _load(name: str, library: Path) -> ca.Function:
    """dlopen the library behind a marker file (removed once loaded): a process that dies while
    loading it leaves the marker, and the next one discards the library (:func:`_crashed_loads`)."""
    marker = library.with_name(f"{library.name}.loading-{os.getpid()}")
    marker.touch()
    _fsync_folder(library.parent)
    try:
        # IPOPT's set-up asks CasADi for derivatives of the value kernel (the Lagrangian's gradient,
        # for the multipliers at the solution; the steps use the vgh kernel's exact ones): a library
        # carries no derivative code, so they are finite differences, else every solve fails
        return ca.external(name, str(library), {"enable_fd": True})
    finally:
        with contextlib.suppress(OSError):
            marker.unlink()


def cached_kernel(name: str, inputs: list, outputs: list, cache_dir: Path,
                  flags: tuple[str, ...] = ("-O1",)) -> ca.Function:
    """A planner.objective.compile_hook: the kernel `name` from the cache's shared library, compiled
    into it first when absent (module docstring). A library that is damaged (size or SHA-256 not
    those written beside it), unverified (nothing written beside it), that a previous process died
    loading, or that does not load is compiled anew, and one warning says why. RuntimeError when it
    cannot be compiled or loaded (the planner then interprets the kernel)."""
    fun = ca.Function(name, inputs, outputs)
    source = _source(name, fun)
    key = hashlib.sha256("\0".join([ca.__version__, " ".join(flags), source]).encode()).hexdigest()[:20]
    library = Path(cache_dir) / f"{name}-{key}.so"
    reason = None
    crashed = _crashed_loads(library)
    if crashed:
        reason = "a previous process died while loading it"
        for marker in crashed:
            with contextlib.suppress(OSError):
                marker.unlink()
    elif library.exists():
        reason = _damage(library)
    if reason is not None or not library.exists():
        log.debug("compiling planner kernel %s into %s", name, library)
        try:
            _compile(source, library, flags)
        except OSError as exc:  # the cache folder cannot be written
            raise RuntimeError(f"cannot write the kernel cache {library.parent}: {exc}") from exc
        except RuntimeError as exc:
            if reason is None:
                raise
            raise RuntimeError(f"the cached library {library} was discarded ({reason}) and could not be "
                               f"compiled again: {exc}") from exc
        if reason is not None:
            log.warning("the cached planner kernel %s was discarded (%s); compiled it again", library, reason)
    try:
        return _load(name, library)
    except RuntimeError as exc:
        # verified yet not loadable (another C library, a folder mounted noexec): say it in one line
        first = str(exc).strip().splitlines()
        raise RuntimeError(f"cannot load {library}: {first[1].strip() if len(first) > 1 else first[0]}") from exc


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
