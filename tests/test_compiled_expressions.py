"""Compiled expressions are found again by the signature of the expression as written
(fem_dual.compat.compile_expression): the same UFL on new objects reuses one compilation, in
this process and in a new one, binds the new objects' coefficients and constants, and anything
that is not the same expression compiles anew."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import ufl
from dolfinx import fem, jit, mesh
from mpi4py import MPI

from fem_dual import compat

POINTS = np.array([[0.2], [0.7]])


def _expression(a: float, b: float, power: int = 3):
    """d/du of a * u^power + b * u (a variable derivative, as the slab's density), on a new
    mesh, function and constants: (the derivative, u, the constants)."""
    msh = mesh.create_unit_interval(MPI.COMM_SELF, 2)
    u = fem.Function(fem.FunctionSpace(msh, ("Lagrange", 1)))
    u.interpolate(lambda x: 1.0 + x[0])
    ca, cb = fem.Constant(msh, a), fem.Constant(msh, b)
    var = ufl.variable(u)
    return ufl.diff(ca * var ** power + cb * var, var), u, (ca, cb)


def _values(expr) -> np.ndarray:
    compiled = compat.compile_expression(expr, POINTS)
    out = np.zeros((2, len(POINTS)))
    compiled._cpp_object.eval(np.arange(2, dtype=np.int32), out)
    return out


def _exact(a, b, power=3):
    s = np.array([0.2, 0.7])
    u = 1.0 + np.concatenate([0.5 * s, 0.5 + 0.5 * s])  # the two cells of [0, 1]
    return (power * a * u ** (power - 1) + b).reshape(2, 2)


def test_the_same_expression_on_new_objects_compiles_once_and_binds_its_own_values(monkeypatch):
    first, _, _ = _expression(2.0, 1.0)
    assert np.allclose(_values(first), _exact(2.0, 1.0), rtol=1e-14)
    calls = []
    monkeypatch.setattr(compat, "_compile", lambda *a: calls.append(a) or 1 / 0)
    again, _, _ = _expression(-3.0, 0.5)  # other constants, another mesh: the same UFL
    assert np.allclose(_values(again), _exact(-3.0, 0.5), rtol=1e-14)
    assert not calls


def test_another_expression_compiles_anew(monkeypatch):
    """Without the entries on disk (this process's own only): the same expression compiles
    once, another (u^4 instead of u^3) again."""
    monkeypatch.setattr(compat, "_COMPILED", {})
    monkeypatch.setattr(compat, "_memo_load", lambda key, cache_dir: None)
    compiled = []
    original = compat._compile
    monkeypatch.setattr(compat, "_compile", lambda *a: compiled.append(1) or original(*a))
    _values(_expression(1.0, 1.0, power=3)[0])
    _values(_expression(2.0, -1.0, power=3)[0])
    assert len(compiled) == 1
    assert np.allclose(_values(_expression(1.5, 0.5, power=4)[0]), _exact(1.5, 0.5, 4),
                       rtol=1e-14)
    assert len(compiled) == 2


def test_a_constant_the_derivative_removes_keeps_the_others_in_their_slots():
    """c0 u + d/du (c1 u + c2 u): the expanded expression keeps c0, c1, c2; a kernel bound to
    the wrong slots would not give c0 u + c1 + c2."""
    msh = mesh.create_unit_interval(MPI.COMM_SELF, 2)
    u = fem.Function(fem.FunctionSpace(msh, ("Lagrange", 1)))
    c0, c1, c2 = (fem.Constant(msh, v) for v in (5.0, 2.0, 3.0))
    var = ufl.variable(u)
    expr = c0 * u + ufl.diff(c1 * var + c2 * var, var)  # c0 u + (c1 + c2)
    u.x.array[:] = 0.0
    assert np.allclose(_values(expr), 5.0)
    u.x.array[:] = 1.0
    assert np.allclose(_values(expr), 10.0)


@pytest.mark.serial
def test_a_new_process_finds_the_compilation_and_a_damaged_entry_compiles_again(tmp_path):
    script = f"""
import sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
import numpy as np
from test_compiled_expressions import _expression, _values, _exact
from fem_dual import compat
calls = []
original = compat._compile
compat._compile = lambda *a: calls.append(1) or original(*a)
assert np.allclose(_values(_expression(0.7, -1.0)[0]), _exact(0.7, -1.0), rtol=1e-14)
print(len(calls))
"""
    env = {"XDG_CACHE_HOME": str(tmp_path), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}

    def fresh() -> int:
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                              env=env, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        return int(done.stdout.split()[-1])
    assert fresh() == 1  # an empty cache: compiled
    assert fresh() == 0  # found by the new process
    entries = list((tmp_path / "fenics" / "fem-dual-expressions").glob("*.json"))
    assert len(entries) == 1
    entry = json.loads(entries[0].read_text())
    entries[0].write_text(json.dumps({**entry, "kernel": "expression_missing"}))
    assert fresh() == 1  # an entry that names no kernel: compiled again, the answer right
    assert fresh() == 0
    entries[0].write_text("{not json")
    assert fresh() == 1
    assert jit.get_parameters()["cache_dir"] != tmp_path  # (this process's cache untouched)


def test_kernels_are_compiled_for_the_processor_and_keyed_by_it(monkeypatch):
    """On x86-64 Linux the kernels take -O3 -march=native and a define naming the processor
    (a hash of /proc/cpuinfo's model and flags); elsewhere DOLFINx's -O2 -g0; a user's own
    flags (DOLFINx's JIT parameter files) are kept."""
    import platform

    flags = compat.jit_flags()
    if platform.machine() == "x86_64" and Path("/proc/cpuinfo").exists():
        assert flags[:3] == ["-O3", "-g0", "-march=native"]
        assert flags[3].startswith("-DFEM_DUAL_CPU=") and len(flags[3]) == 15 + 16
    assert compat.jit_params()["cffi_extra_compile_args"] == flags
    compat.processor_flags.cache_clear()
    try:
        monkeypatch.setattr(platform, "machine", lambda: "aarch64")
        assert compat.jit_flags() == ["-O2", "-g0"]
    finally:
        compat.processor_flags.cache_clear()
    own = {**jit.get_parameters(), "cffi_extra_compile_args": ["-O1", "-DMINE"]}
    monkeypatch.setattr(jit, "get_parameters", lambda *a, **k: own)
    assert compat.jit_flags() == ["-O1", "-DMINE"]


@pytest.mark.serial
def test_a_compiler_that_refuses_the_processor_flags_compiles_with_dolfinx_own(tmp_path):
    """A C compiler that rejects -march=native: the kernels are compiled with -O2 -g0 and
    the run's numbers are right."""
    fake = tmp_path / "cc"
    fake.write_text("#!/bin/sh\nfor a in \"$@\"; do [ \"$a\" = -march=native ] && "
                    "{ echo 'cc: error: unrecognized option -march=native' >&2; exit 1; }; done\n"
                    "exec gcc \"$@\"\n")
    fake.chmod(0o755)
    script = f"""
import sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
import numpy as np
from test_compiled_expressions import _expression, _values, _exact
from fem_dual import compat
assert np.allclose(_values(_expression(0.3, 2.0)[0]), _exact(0.3, 2.0), rtol=1e-14)
print(compat.jit_flags())
"""
    env = {"XDG_CACHE_HOME": str(tmp_path), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path),
           "CC": str(fake)}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split("\n")[-2] == "['-O2', '-g0']"


@pytest.mark.serial
def test_a_cache_shared_with_another_processor_holds_a_module_for_each(tmp_path):
    """A process whose processor is named otherwise (another -DFEM_DUAL_CPU) compiles its own
    module beside the first one instead of loading it; each then finds its own."""
    script = f"""
import sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
import numpy as np
from test_compiled_expressions import _expression, _values, _exact
from fem_dual import compat
if sys.argv[1] != "native":
    compat.jit_flags = lambda: ["-O2", "-g0", "-DFEM_DUAL_CPU=" + sys.argv[1]]
calls = []
original = compat._compile
compat._compile = lambda *a: calls.append(1) or original(*a)
assert np.allclose(_values(_expression(0.3, 2.0)[0]), _exact(0.3, 2.0), rtol=1e-14)
print(len(calls))
"""
    env = {"XDG_CACHE_HOME": str(tmp_path), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}

    def fresh(cpu: str) -> int:
        done = subprocess.run([sys.executable, "-c", script, cpu], capture_output=True,
                              text=True, env=env, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        return int(done.stdout.split()[-1])

    def modules() -> int:
        return len(list((tmp_path / "fenics").glob("libffcx_expressions_*.so")))
    assert fresh("native") == 1 and modules() == 1
    assert fresh("otherchip") == 1 and modules() == 2  # compiled again, beside
    assert fresh("native") == 0 and fresh("otherchip") == 0
    assert modules() == 2


@pytest.mark.serial
def test_a_compiler_that_always_fails_ends_the_run_in_one_line(tmp_path):
    fake = tmp_path / "cc"
    fake.write_text("#!/bin/sh\necho 'cc: error: broken' >&2\nexit 1\n")
    fake.chmod(0o755)
    env = {"XDG_CACHE_HOME": str(tmp_path), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path),
           "CC": str(fake)}
    done = subprocess.run([sys.executable, "-m", "fem_dual.cli", "run", "curl2d", "--T", "0.5"],
                          capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 3
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith(f"fem-dual: error: the C compiler ({fake}) failed")
    assert "Traceback" not in done.stderr


def _form_signature_after(compile_first: bool, cache_dir: Path, monkeypatch,
                          signed_early: bool = False) -> str:
    """The signature FFCx compiles a form on a new interval mesh under (its module's key), after
    another form on the same mesh was compiled (a cache miss, `compile_first`) or not, its own
    signature asked for before anything was compiled (`signed_early`) or not."""
    msh = mesh.create_unit_interval(MPI.COMM_SELF, 2)
    V = fem.FunctionSpace(msh, ("Lagrange", 2))
    u, w, c = ufl.TrialFunction(V), ufl.TestFunction(V), fem.Constant(msh, 2.0)
    first, second = u * w * ufl.dx, c * u.dx(0) * w.dx(0) * ufl.dx  # both made before compiling
    monkeypatch.setattr(compat, "jit_params", lambda: {"cache_dir": str(cache_dir),
                                                       "cffi_extra_compile_args": ["-O0"]})
    seen = []
    compile_jit = jit.ffcx_jit

    def recording(comm, ufl_object, *args, **kwargs):
        if isinstance(ufl_object, ufl.Form):
            seen.append(ufl_object.signature())
        return compile_jit(comm, ufl_object, *args, **kwargs)

    monkeypatch.setattr(fem.forms.jit, "ffcx_jit", recording)
    if signed_early:
        second.signature()
    if compile_first:
        compat.compile_form(first)
    compat.compile_form(second)
    return seen[-1]


def test_a_forms_key_does_not_depend_on_what_the_process_compiled_before(tmp_path, monkeypatch):
    """FFCx gives a mesh's coordinate element equispaced points in place when it compiles (not
    when it finds the module): a form's signature, and so its module, must not depend on
    whether another form on the mesh was compiled before it in the process (else runs compile
    new modules run after run)."""
    alone = _form_signature_after(False, tmp_path / "alone", monkeypatch)
    after = _form_signature_after(True, tmp_path / "after", monkeypatch)
    signed = _form_signature_after(True, tmp_path / "signed", monkeypatch, signed_early=True)
    assert alone == after == signed


def test_the_direct_value_numbering_generates_the_code_of_the_scan(monkeypatch):
    """FFCx's value numbering finds operands through the graph's map (fem_dual.compat), not its
    quadratic scan: the generated C is the same character for character."""
    from ffcx.compiler import compile_ufl_objects
    from ffcx.ir.analysis import valuenumbering
    from ffcx.parameters import get_parameters

    density, u, _ = _expression(2.0, 1.0, power=5)
    expr = ufl.as_vector([density, density * u, ufl.sin(density) * ufl.exp(u), density ** 2])
    numberer = valuenumbering.ValueNumberer
    scan, scanned = numberer._fem_dual_scan, []
    monkeypatch.setattr(numberer, "_fem_dual_scan", lambda *a: scanned.append(a) or scan(*a))

    def code() -> str:
        return compile_ufl_objects([(expr, POINTS)], prefix="x", parameters=get_parameters())[1]

    direct = code()
    assert numberer._fem_dual_direct and not scanned  # (no operand needed the scan)
    monkeypatch.setattr(numberer, "get_node_symbols", scan)
    assert code() == direct


def test_code_that_fails_with_every_flag_leaves_the_processor_flags_to_later_modules(
        monkeypatch):
    """A compilation that fails with DOLFINx's own flags too (a constant of inf in the C) is the
    code's fault: the process keeps the processor's flags for what it compiles next. One that
    only the processor's flags fail moves the process to DOLFINx's own."""
    class CompileError(Exception):
        pass

    monkeypatch.setattr(compat, "_PORTABLE", [False])
    monkeypatch.setattr(compat, "processor_flags", lambda: ["-O3", "-DTEST_CPU"])
    monkeypatch.setattr(compat, "include_flags", lambda flags, cache_dir: [])
    seen = []

    def always(params):
        seen.append(params["cffi_extra_compile_args"])
        raise CompileError("gcc: 'inf' undeclared")
    with pytest.raises(CompileError):
        compat.with_portable_fallback(always)
    assert seen[0] == ["-O3", "-DTEST_CPU"] and seen[-1] != seen[0]  # (DOLFINx's tried too)
    assert compat._PORTABLE == [False] and compat.jit_flags() == ["-O3", "-DTEST_CPU"]

    def processor_only(params):
        if "-DTEST_CPU" in params["cffi_extra_compile_args"]:
            raise CompileError("gcc: unrecognized -march")
        return "built"
    assert compat.with_portable_fallback(processor_only) == "built"
    assert compat._PORTABLE == [True] and "-DTEST_CPU" not in compat.jit_flags()
