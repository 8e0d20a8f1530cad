"""Python.h, precompiled for the C compiler that builds FFCx's kernels.

Every module FFCx compiles is C that cffi wraps for Python: it starts by including Python.h
(pyconfig.h, then Py_LIMITED_API, then Python.h), which gcc parses afresh for each module:
0.09 s of the 0.2-0.3 s a small kernel's module takes to compile. fem-dual passes
`-include fem-dual-python-h/<key>/cffi_python.h` (relative to FFCx's cache, where cffi compiles),
a copy of fem_dual/cffi_python.h (the same lines), and builds its precompiled form
(`cffi_python.h.gch`, gcc's) beside it once per cache, compiler and set of flags. gcc takes the
precompiled form where it is valid for the compilation and the text otherwise (another
compiler): the same declarations either way, and the same object code (checked on 33 modules of
curl3d, orbits and continua). The guards of pyconfig.h and Python.h then skip the module's own
includes. A truncated precompiled form makes gcc fail instead:
fem_dual.compat.with_portable_fallback then removes it (`discard_precompiled`) and compiles
again with the text; a header whose text differs from the package's is written again.
"""
from __future__ import annotations

import functools
import hashlib
import os
import shlex
import shutil
import subprocess
import sysconfig
import tempfile
from pathlib import Path
from typing import List, Sequence

__all__ = ["include_flags", "discard_precompiled", "HEADER"]

HEADER = Path(__file__).with_name("cffi_python.h")  # cffi's preamble, as a header file
FOLDER = "fem-dual-python-h"  # in FFCx's cache
BUILD_SECONDS = 120  # a precompilation that takes longer is given up (the text still serves)


def include_flags(flags: Sequence[str], cache_dir) -> List[str]:
    """["-include", header] for FFCx's compilations with `flags` (the header and, where the
    compiler makes one, its precompiled form written into `cache_dir` if not there yet), or []
    where cffi does not use the limited API or the header cannot be written (the compilations
    then parse Python.h themselves)."""
    return list(_include(tuple(flags), str(Path(cache_dir).expanduser())))


@functools.lru_cache(maxsize=8)
def _include(flags: tuple, cache_dir: str) -> tuple:
    try:
        from cffi import recompiler
    except ImportError:
        return ()
    if not getattr(recompiler, "USE_LIMITED_API", False):
        return ()
    try:
        text = HEADER.read_bytes()
    except OSError:  # (an install without the package's data)
        return ()
    command = _compiler() + [f"-I{sysconfig.get_paths()['include']}", *flags]
    key = hashlib.sha256("\0".join(command + _identity(command[0])).encode() + text)
    # relative to the cache, where cffi compiles (its build changes into the folder it is
    # given, FFCx's cache): the path is part of the flags, hence of FFCx's module names, and
    # a cache moved elsewhere keeps them
    relative = f"{FOLDER}/{key.hexdigest()[:16]}/cffi_python.h"
    header = Path(cache_dir) / relative
    try:
        if not (header.exists() and header.read_bytes() == text):  # (damaged: written again)
            header.parent.mkdir(parents=True, exist_ok=True)
            _write(header, text)
    except OSError:
        return ()
    precompiled = header.with_name("cffi_python.h.gch")
    if not _is_precompiled(precompiled):
        _precompile(command, header, precompiled)
    return ("-include", relative)


def discard_precompiled(flags: Sequence[str], cache_dir) -> bool:
    """Remove the precompiled header that `flags` include from `cache_dir` (a damaged one,
    which gcc refuses with an error instead of reading the text: a truncated file); whether
    `flags` include one (the same answer on every rank, whichever removed the file). The text
    stays, so the same flags compile with it."""
    flags = list(flags)
    if "-include" not in flags[:-1]:
        return False
    try:
        (Path(cache_dir).expanduser() / (flags[flags.index("-include") + 1] + ".gch")).unlink()
    except OSError:
        pass
    return True


def _identity(program: str) -> List[str]:
    """The compiler's file, size and time (another gcc after an upgrade: another key, and a
    precompiled header of its own)."""
    found = shutil.which(program)
    if found is None:
        return [program]
    try:
        info = os.stat(found)
    except OSError:
        return [program]
    return [os.path.realpath(found), str(info.st_size), str(info.st_mtime_ns)]


def _is_precompiled(path: Path) -> bool:
    """Whether `path` is a gcc precompiled header (its magic; a file cut short is caught by
    gcc, and then removed: discard_precompiled)."""
    try:
        with open(path, "rb") as handle:
            return handle.read(4) == b"gpch"
    except OSError:
        return False


def _compiler() -> List[str]:
    """The compiler and flags cffi's build (distutils' customize_compiler) compiles with: CC,
    CFLAGS and CCSHARED of the interpreter, CC and CFLAGS of the environment taking over."""
    get = sysconfig.get_config_var
    cc = os.environ.get("CC") or get("CC") or "cc"
    cflags = get("CFLAGS") or ""
    if os.environ.get("CFLAGS"):
        cflags += " " + os.environ["CFLAGS"]
    if os.environ.get("CPPFLAGS"):
        cflags += " " + os.environ["CPPFLAGS"]
    return shlex.split(cc) + shlex.split(cflags) + shlex.split(get("CCSHARED") or "")


def _precompile(command: List[str], header: Path, target: Path) -> None:
    """Compile `header` into `target`; a compiler that cannot (not gcc, a failure) leaves none,
    silently."""
    def build(tmp: str) -> bool:
        done = subprocess.run(command + ["-x", "c-header", str(header), "-o", tmp],
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, timeout=BUILD_SECONDS, check=False)
        return done.returncode == 0 and _is_precompiled(Path(tmp))
    try:
        _replace(target, build)
    except (OSError, subprocess.SubprocessError):
        pass


def _write(path: Path, data: bytes) -> None:
    """Write `path` whole (_replace)."""
    _replace(path, lambda tmp: Path(tmp).write_bytes(data) == len(data))


def _replace(path: Path, make) -> None:
    """make(tmp) writes a file of another name beside `path` and says whether it is whole; if so
    it is renamed over `path` (concurrent processes each leave a whole file) with the mode a
    file made by open() has (mkstemp makes them private; a cache shared by users reads them,
    as it reads FFCx's modules)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    os.close(fd)
    try:
        if make(tmp):
            mask = os.umask(0)
            os.umask(mask)
            os.chmod(tmp, 0o666 & ~mask)
            os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
