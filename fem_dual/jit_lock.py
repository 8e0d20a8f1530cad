"""A cache entry that a killed compilation left behind, found and compiled again.

FFCx's JIT marks a module being compiled by creating its C file exclusively, and a compiled one by
a `.c.cached` file beside it; a process that finds the C file without the marker waits for the
marker up to its timeout (fem_dual.compat.JIT_TIMEOUT, 600 s), then fails. A process killed while
it compiled leaves the C file without a marker, and every later run waited the whole timeout.

fem-dual's processes hold an advisory lock (`flock` on `<module>.lock` in the cache) from their
look into the cache until FFCx has compiled the module or given up. A process that finds the C
file without the marker and takes the lock knows that no fem-dual process is compiling it: it
removes the C file and compiles the module itself (a marker without its C file, left by a
compilation that collided with another, is removed alike). A process that finds the lock held
waits for the marker or for the lock to come free, whichever comes first, up to FFCx's timeout.
Where no lock can be made (the file system has no `flock`, a FIFO sits at its path) FFCx's own
protocol runs unchanged. Another program compiling the same module at that moment without the
lock is not seen.
"""
from __future__ import annotations

import fcntl
import os
import stat
import time
from pathlib import Path
from typing import IO, Dict, Optional

__all__ = ["install"]

_HELD: Dict[str, IO] = {}  # module name -> its lock file, while this process may compile it
POLL_SECONDS = 0.2  # how often a process waiting for another's compilation looks again


def install() -> None:
    """Wrap FFCx's cache lookup and its compile entry points (once per process)."""
    from ffcx.codegeneration import jit

    if getattr(jit, "_fem_dual_locks", False):
        return
    lookup = jit.get_cached_module

    def get_cached_module(module_name, object_names, cache_dir, timeout):
        c_file = Path(cache_dir) / f"{module_name}.c"
        ready = c_file.with_suffix(".c.cached")
        deadline = time.monotonic() + float(timeout)
        # another process compiles it: wait for its marker, or for its lock to come free (the
        # process ended without the marker: this one compiles the module itself)
        while True:
            taken = _take(cache_dir, module_name)
            if taken is None:  # no lock can be made here: FFCx's protocol
                return lookup(module_name, object_names, cache_dir, timeout)
            if taken:
                break
            if ready.exists() or time.monotonic() > deadline:
                return lookup(module_name, object_names, cache_dir, timeout)
            time.sleep(POLL_SECONDS)
        if c_file.exists() and not ready.exists():
            c_file.unlink()  # left by a compilation that did not finish
        elif ready.exists() and not c_file.exists():
            ready.unlink()  # a marker without its module's source: compiled again
        return lookup(module_name, object_names, cache_dir, timeout)

    for name in ("compile_forms", "compile_expressions", "compile_elements"):
        setattr(jit, name, _releasing(getattr(jit, name)))
    jit.get_cached_module = get_cached_module
    jit._fem_dual_locks = True


def _releasing(compile_objects):
    """`compile_objects` that gives back the locks its lookups took, when it ends either way
    (after FFCx's own clean-up of a failed compilation)."""
    def compile_and_release(*args, **kwargs):
        before = set(_HELD)
        try:
            return compile_objects(*args, **kwargs)
        finally:
            for module_name in set(_HELD) - before:
                _release(module_name)
    return compile_and_release


def _take(cache_dir, module_name: str) -> Optional[bool]:
    """True: this process now holds the module's lock; False: another process holds it; None:
    no lock can be made here (the cache cannot be written, no `flock`, no regular file)."""
    if module_name in _HELD:
        return True
    try:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        fd = os.open(Path(cache_dir) / f"{module_name}.lock",
                     os.O_WRONLY | os.O_CREAT | os.O_NONBLOCK | os.O_CLOEXEC, 0o644)
    except OSError:
        return None
    if not stat.S_ISREG(os.fstat(fd).st_mode):  # (a FIFO or device put there)
        os.close(fd)
        return None
    handle = os.fdopen(fd, "a")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        return False
    except OSError:
        handle.close()
        return None
    _HELD[module_name] = handle
    return True


def _release(module_name: str) -> None:
    handle = _HELD.pop(module_name, None)
    if handle is not None:
        try:
            fcntl.flock(handle, fcntl.LOCK_UN)
        finally:
            handle.close()
