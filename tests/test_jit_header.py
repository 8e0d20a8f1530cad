"""Python.h precompiled for FFCx's compilations (fem_dual.jit_header): gcc reads it, the numbers
are those of the text, and a damaged one is removed and the text used instead."""
import subprocess
import sys
from pathlib import Path

import pytest

from fem_dual import jit_header

SCRIPT = f"""
import sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
from test_compiled_expressions import _expression, _values
from fem_dual import compat
mode, power = sys.argv[1], int(sys.argv[2])
if mode == "text":  # the same processor flags, without the header
    compat.include_flags = lambda flags, cache_dir: []
if mode == "verbose":  # gcc lists what it includes, a precompiled header with "!"
    own = compat.processor_flags() + ["-H"]
    compat.processor_flags = lambda: own
flags = compat.jit_flags()
calls = []
original = compat._compile
compat._compile = lambda *a: calls.append(1) or original(*a)
print(repr(_values(_expression(0.3, 2.0, power)[0]).tolist()))
print(flags)
print(len(calls))
"""


def _run(cache: Path, mode: str, power: int = 3) -> subprocess.CompletedProcess:
    env = {"XDG_CACHE_HOME": str(cache), "PATH": "/usr/bin:/bin", "HOME": str(cache)}
    done = subprocess.run([sys.executable, "-c", SCRIPT, mode, str(power)], capture_output=True,
                          text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return done


def _precompiled(cache: Path):
    return sorted((cache / "fenics" / "fem-dual-python-h").glob("*/cffi_python.h.gch"))


@pytest.mark.serial
def test_gcc_reads_the_precompiled_header(tmp_path):
    done = _run(tmp_path, "verbose")
    used = [line for line in done.stderr.splitlines() if line.startswith("! ")]
    assert used and "fem-dual-python-h/" in used[0], done.stderr[-2000:]
    assert used[0].endswith("cffi_python.h.gch")
    assert "-include" in done.stdout.splitlines()[1]


@pytest.mark.serial
def test_the_numbers_are_those_of_the_text(tmp_path):
    with_header = _run(tmp_path / "a", "header").stdout.splitlines()
    without = _run(tmp_path / "b", "text").stdout.splitlines()
    assert with_header[0] == without[0]  # (every digit)
    assert "-include" in with_header[1] and "-include" not in without[1]
    assert len(_precompiled(tmp_path / "a")) == 1


@pytest.mark.serial
def test_a_damaged_precompiled_header_is_removed_and_the_text_serves(tmp_path):
    """gcc refuses a truncated precompiled header with an error (not the text): the
    compilation is done again with the same flags after removing it, and the next process
    builds it again."""
    first = _run(tmp_path, "header").stdout.splitlines()
    (gch,) = _precompiled(tmp_path)
    gch.write_bytes(gch.read_bytes()[:100_000])
    again = _run(tmp_path, "header", power=4).stdout.splitlines()  # a new module: compiled
    assert again[1] == first[1] and again[2] == "1"  # the same flags (not DOLFINx's own)
    assert again[0] != first[0] and not gch.exists()
    _run(tmp_path, "header", power=5)
    assert _precompiled(tmp_path) == [gch] and gch.read_bytes()[:4] == b"gpch"
    header = gch.with_suffix("")
    header.write_text("garbage that gcc refuses\n")  # text damaged: written again
    damaged = _run(tmp_path, "header", power=6).stdout.splitlines()
    assert damaged[1] == first[1] and header.read_bytes() == jit_header.HEADER.read_bytes()


@pytest.mark.serial
def test_a_cache_moved_elsewhere_keeps_its_modules_and_others_read_them(tmp_path):
    """The header's path in the flags (hence in FFCx's module names) is relative to the cache;
    its files are readable by every user of a shared cache, like FFCx's."""
    import shutil

    def modules(cache):
        return sorted(p.name for p in (cache / "fenics").glob("libffcx_*.so"))
    first = _run(tmp_path / "a", "header").stdout.splitlines()
    shutil.copytree(tmp_path / "a", tmp_path / "b c")
    moved = _run(tmp_path / "b c", "header").stdout.splitlines()
    assert moved[:2] == first[:2]
    assert modules(tmp_path / "b c") == modules(tmp_path / "a")  # found, not compiled again
    for path in (tmp_path / "a" / "fenics" / "fem-dual-python-h").rglob("cffi_python.h*"):
        assert path.stat().st_mode & 0o044 == 0o044, path


def test_no_header_where_the_cache_cannot_take_it(tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    assert jit_header.include_flags(["-O3", "-g0"], blocked) == []
