"""Build the compiled loops: the C sources in fem_dual/native/src into one shared library.

`make install` runs `python3 -m fem_dual.native.build`, which compiles the library into the
package (fem_dual/native/_lib/libfem_dual_native.so) with the compiler the FFCx JIT uses (the
interpreter's sysconfig CC), `-O3 -fPIC -shared` and `-Wall -Wextra`, and writes a stamp
beside it: the fingerprint of the sources and flags it was built from, and the library's own
hash. fem_dual.native loads that library where the stamp matches the sources and the file;
otherwise (a plain `pip install`, a source edited since, a damaged file) it compiles the same
sources with the same flags into the user's cache, so every build computes the same numbers.

cffi reads the library's interface from src/fem_dual_native.h with its preprocessor lines
removed (`declarations`).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path
from typing import List, Optional

__all__ = ["SOURCE_DIR", "HEADER", "FLAGS", "WARNINGS", "PACKAGED", "sources", "declarations",
           "fingerprint", "compiler", "compile_library", "current", "cached", "main"]

SOURCE_DIR = Path(__file__).resolve().parent / "src"
HEADER = SOURCE_DIR / "fem_dual_native.h"
FLAGS = ("-O3", "-fPIC", "-shared")  # no -march=native: the same code on every machine
WARNINGS = ("-Wall", "-Wextra")  # (they change no code: the sources compile without any)
PACKAGED = Path(__file__).resolve().parent / "_lib" / "libfem_dual_native.so"


def sources() -> List[Path]:
    """The C sources, in a fixed order."""
    return sorted(SOURCE_DIR.glob("*.c"))


def declarations() -> str:
    """The library's interface for cffi's cdef: fem_dual_native.h without its preprocessor
    lines (the include guard and <stdint.h>, whose types cffi knows)."""
    lines = HEADER.read_text().splitlines()
    return "\n".join(line for line in lines if not line.lstrip().startswith("#")) + "\n"


def fingerprint() -> str:
    """sha256 of what the library is built from: every source and header (name and text) and
    the flags."""
    digest = hashlib.sha256(" ".join(FLAGS).encode())
    for path in sorted(SOURCE_DIR.glob("*.[ch]")):
        digest.update(b"\0" + path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def compiler() -> str:
    """The C compiler: the interpreter's sysconfig CC (the one the FFCx JIT uses through cffi),
    else cc or gcc on PATH.

    Raises:
        OSError: none is found.
    """
    name = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(name) is not None:
        return name
    found = shutil.which("cc") or shutil.which("gcc")
    if not found:
        raise OSError("no C compiler (cc, gcc) on PATH")
    return found


def _stamp(target: Path) -> Path:
    return target.with_name(target.name + ".json")


def _hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def compile_library(target: Path, extra: tuple = ()) -> str:
    """Compile the sources into `target`, with the stamp beside it (target + ".json"); returns
    what the compiler printed (its warnings). Library and stamp are written under other names,
    then renamed: processes that compile at once each leave whole files.

    Args:
        target: the library's path.
        extra: flags after the build's own (tests: -Werror).

    Raises:
        OSError: no compiler, or it failed (its messages in the exception).
    """
    cc = compiler()
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        built = Path(tmp) / target.name
        command = [cc, *FLAGS, *WARNINGS, *extra, "-o", str(built),
                   *(str(path) for path in sources()), "-lm"]
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=300)
        except subprocess.TimeoutExpired as exc:
            raise OSError(f"{cc} took longer than {exc.timeout} s") from exc
        if done.returncode != 0:
            raise OSError(f"{' '.join(command)} failed:\n{done.stderr.strip()}")
        stamp = Path(tmp) / "stamp"
        stamp.write_text(json.dumps({"sources": fingerprint(), "library": _hash(built)}))
        os.replace(built, target)
        os.replace(stamp, _stamp(target))
    return done.stderr


def current(target: Path) -> bool:
    """Whether `target` is the library its stamp describes (not damaged, truncated or
    replaced: one that dlopen accepts may still kill the process at a call) and was built from
    the present sources and flags."""
    try:
        stamp = json.loads(_stamp(target).read_text())
        return stamp["sources"] == fingerprint() and stamp["library"] == _hash(target)
    except (OSError, ValueError, KeyError, TypeError):
        return False


def cached() -> Path:
    """The library in the user's cache ($XDG_CACHE_HOME/fem-dual, by default ~/.cache/fem-dual)
    for the present sources and flags."""
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(root) / "fem-dual" / f"native-{fingerprint()[:16]}.so"


def main(argv: Optional[List[str]] = None) -> int:
    """Build the library into the package (`make install`). Without a C compiler it says so and
    succeeds: the numpy loops then run, with the same answers to round-off."""
    del argv
    try:
        cc = compiler()
    except OSError as exc:
        print(f"fem_dual.native: {exc}: the numpy loops will run", file=sys.stderr)
        return 0
    try:
        messages = compile_library(PACKAGED)
    except OSError as exc:
        print(f"fem_dual.native: {exc}", file=sys.stderr)
        return 1
    if messages.strip():
        print(messages, file=sys.stderr)
    print(f"fem_dual.native: built {PACKAGED} with {cc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
