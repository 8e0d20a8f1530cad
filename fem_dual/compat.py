"""Everything that depends on DOLFINx 0.5.2 specifics lives here, and nowhere else."""
from __future__ import annotations

import dataclasses
import functools
import logging
import os
from contextlib import contextmanager
from typing import Any, Callable, Dict, Iterator, List, Optional

import numpy as np
import ufl
from dolfinx import cpp as _cpp
from dolfinx import fem

from fem_dual import jit_lock
from fem_dual.jit_header import discard_precompiled, include_flags

jit_lock.install()  # a compilation that a killed process left behind is redone, not waited for


def _direct_value_numbering() -> None:
    """FFCx 0.5 numbers the scalar values of an expression graph by finding each operand's
    node with a scan that compares it with every node (UFL equality: quadratic in the graph):
    about 40 % of compiling the slab problems' expressions, more than the C compiler. The
    graph's own map from expression to node (unique nodes, numbered as they were added) gives
    the same node directly; an expression it lacks takes the scan."""
    from ffcx.ir.analysis import valuenumbering

    numberer = valuenumbering.ValueNumberer
    if getattr(numberer, "_fem_dual_direct", False):
        return
    scan = numberer.get_node_symbols

    def get_node_symbols(self, expr):
        index = getattr(self.G, "e2i", {}).get(expr)
        return type(self)._fem_dual_scan(self, expr) if index is None else self.V_symbols[index]

    numberer.get_node_symbols = get_node_symbols
    numberer._fem_dual_direct, numberer._fem_dual_scan = True, scan


_direct_value_numbering()

__all__ = ["function_space", "quiet_jit_logging", "CellPointEvaluator", "CompiledExpression",
           "compile_expression", "compile_form", "equispaced_coordinates",
           "vector_space", "vector_space_dg1", "constant", "destroy_petsc",
           "release_function_vector"]


def _drop_info(record: logging.LogRecord) -> bool:
    return record.levelno >= logging.WARNING


_JIT_LOGGERS = ("ffcx", "UFL", "dolfinx", "distutils", "setuptools")


@contextmanager
def quiet_jit_logging() -> Iterator[None]:
    """Compile forms quietly and leave the host's logging as it was. The JIT of 0.5.2 builds
    through setuptools, which resets the root logger to INFO and logs every compiler call, and
    FFCx sets its logger's level from its options: within the block a filter on the root logger
    (it survives that reset) drops what is below WARNING; afterwards the root logger and the JIT's
    loggers get back their levels, handlers and filters."""
    root = logging.getLogger()
    saved = [(log, log.level, list(log.handlers), list(log.filters))
             for log in [root] + [logging.getLogger(name) for name in _JIT_LOGGERS]]
    root.addFilter(_drop_info)
    try:
        yield
    finally:
        for log, level, handlers, filters in saved:
            log.setLevel(level)
            log.handlers[:] = handlers
            log.filters[:] = filters


def function_space(msh, element) -> fem.FunctionSpace:
    """fem.FunctionSpace, its element compiled quietly (FFCx sets its logger's level from its
    options on every JIT call: a space built outside `quiet_jit_logging` left it changed)."""
    with quiet_jit_logging():
        return fem.FunctionSpace(msh, element)


def vector_space(msh, degree: int, dim: int, family: str = "Lagrange") -> fem.FunctionSpace:
    """One blocked Lagrange (or "DG") space of `dim` components (0.5.2: ufl.VectorElement).
    On an interval, the first two dofs of a cell sit at its reference points 0 and 1."""
    return function_space(msh, ufl.VectorElement(family, msh.ufl_cell(), degree, dim=dim))


def vector_space_dg1(msh, dim: int) -> fem.FunctionSpace:
    """Discontinuous P1 with `dim` components; its cell dofs sit at reference points 0 and 1."""
    return vector_space(msh, 1, dim, "DG")


def destroy_petsc(*objects) -> None:
    """Destroy PETSc objects now (collective). petsc4py 3.18 does not destroy an object whose
    Python wrapper is dropped: it stashes it on its communicator's garbage list until a
    collective PETSc.garbage_cleanup(comm), which nothing calls (and cannot reach the
    communicators DOLFINx duplicates per mesh), so every dropped KSP, SNES, matrix and vector
    of a slab solver stayed allocated. None entries are skipped; destroying twice is
    harmless."""
    for obj in objects:
        if obj is not None:
            obj.destroy()


def release_function_vector(function: fem.Function) -> None:
    """Destroy the PETSc Vec that 0.5.2's `Function.vector` wraps around the dofs (made on first
    access, kept in `_petsc_x`); a later `.vector` makes a new one."""
    vec = getattr(function, "_petsc_x", None)
    if vec is not None:
        vec.destroy()
        function._petsc_x = None


def constant(msh, value) -> fem.Constant:
    """A fem.Constant of float64 whatever the input's dtype (0.5.2 rejects integer arrays)."""
    return fem.Constant(msh, np.asarray(value, dtype=np.float64))


class CellPointEvaluator:
    """Evaluates a UFL expression at fixed reference points of given cells.

    0.5.2's `fem.Expression.eval(cells)` returns a flat (cells, points * value_size) array; this
    reshapes it to (cells, points, value_size).

    0.5.2's `fem.Expression` packs the constants of the expression as given, while FFCx's
    kernel reads those left after it expands the derivatives: a constant that a derivative
    removes (the parameter of a force F = a in dG/dx) shifted every later constant into the
    wrong slot (`force --F a --param a=-2` read H's weight from a, and the DtP map was refused
    as singular). The derivatives are expanded first (`compile_expression`), so both see the
    same constants, and a kernel that reads another number of constants stops at set-up.
    """

    def __init__(self, expr: ufl.core.expr.Expr, ref_points: np.ndarray):
        self._points = np.asarray(ref_points, dtype=np.float64).reshape(-1, 1)
        self._expr = compile_expression(expr, self._points)
        self.value_size = self._expr.value_size
        self.expression = expr
        space = self._expr.argument_function_space
        # (with a test function, each point's values run over the value and the basis)
        self._width = self.value_size * (1 if space is None else space.element.space_dimension)

    def __call__(self, cells: np.ndarray) -> np.ndarray:
        """(cells, points, values) in a new array (the C++ eval, without 0.5.2's Python
        checks: see `into`)."""
        cells = np.asarray(cells, dtype=np.int32)
        points = self._points.shape[0]
        values = self.into(cells, np.zeros((len(cells), points * self._width)))
        return values.reshape(len(cells), points, self._width)

    @property
    def compiled(self) -> "CompiledExpression":
        """The compiled expression (its kernel and coefficients: fem_dual.native)."""
        return self._expr

    def into(self, cells: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Evaluate into `out` (int32 `cells`; float64 (cells, points * value_size), zeroed by
        the caller where the expression has an argument): 0.5.2's `eval` checks the shapes and
        allocates in Python on every call, which costs as much as the evaluation of a small
        expression; the C++ object does neither."""
        self._expr._cpp_object.eval(cells, out)
        return out


@dataclasses.dataclass
class CompiledExpression:
    """What a compiled UFL expression is to fem-dual: DOLFINx's C++ expression (`_cpp_object`,
    its `eval`), FFCx's `ufcx_expression` (the kernel), and the coefficients the kernel reads,
    in its order (the compiled loops of fem_dual.native pack them themselves)."""

    ufcx_expression: Any
    _cpp_object: Any
    coefficients: List[fem.Function]
    mesh: Any
    argument_function_space: Optional[fem.FunctionSpace]
    module: Any  # the FFCx module the kernel lives in (kept alive with it)

    @property
    def value_size(self) -> int:
        return self._cpp_object.value_size


# How long a process waits for another that compiles the same form or expression (FFCx's JIT
# lets one compile and the others wait, 10 s by default, then fail): the heaviest expressions
# take longer than that when two processes compile at once
JIT_TIMEOUT = 600


def jit_params() -> Dict[str, Any]:
    """The JIT parameters of every form and expression fem-dual compiles: JIT_TIMEOUT and
    `jit_flags`."""
    return {"timeout": JIT_TIMEOUT, "cffi_extra_compile_args": jit_flags()}


_PORTABLE: List[bool] = [False]  # the compiler refused the processor's flags: DOLFINx's own


def jit_flags() -> List[str]:
    """The C compiler's flags for FFCx's kernels: a user's own (`cffi_extra_compile_args` of
    DOLFINx's JIT parameter files, where they differ from its default -O2 -g0); else, where
    the processor can be named, `processor_flags` and the precompiled Python header
    (fem_dual.jit_header); else (or where the compiler refused those,
    `with_portable_fallback`) DOLFINx's -O2 -g0."""
    from dolfinx import jit

    default = list(jit.DOLFINX_DEFAULT_JIT_PARAMETERS["cffi_extra_compile_args"][0])
    parameters = jit.get_parameters()
    asked = list(parameters.get("cffi_extra_compile_args") or default)
    if asked != default:
        return asked
    own = None if _PORTABLE[0] else processor_flags()
    if own is None:
        return default
    return own + include_flags(own, parameters["cache_dir"])


@functools.lru_cache(maxsize=1)
def processor_flags() -> Optional[List[str]]:
    """-O3 -march=native with a define that names the processor (x86-64: a hash of its model
    and instruction sets in /proc/cpuinfo), or None where it cannot be named. The flags are
    part of FFCx's cache key, so a cache shared by machines of different processors holds a
    module for each instead of code that another cannot run. -march=native (fused multiply-
    adds, wider vectors) makes a curl3d density's kernel of gradient and Hessian about twice as
    fast (4 cells at p = 3: 35 -> 15 us)."""
    import hashlib
    import platform

    lines: List[str] = []
    if platform.machine() == "x86_64":
        try:
            with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as info:
                lines = [line for line in info
                         if line.split(":")[0].strip() in ("model name", "flags")]
        except OSError:
            pass
    if not lines:
        return None
    tag = hashlib.sha256("".join(sorted(set(lines))).encode()).hexdigest()[:16]
    return ["-O3", "-g0", "-march=native", f"-DFEM_DUAL_CPU={tag}"]


def compiler_failed(exc: BaseException) -> bool:
    """Whether `exc` is the C compiler failing on FFCx's generated code (cffi's CompileError or
    VerificationError; under MPI, DOLFINx's "Failed just-in-time compilation" on every rank)."""
    return (any(c.__name__ in ("CompileError", "VerificationError") for c in type(exc).__mro__)
            or str(exc).startswith("Failed just-in-time compilation"))


def _cache_dir():
    """FFCx's cache folder, DOLFINx's parameter (where the JIT compiles)."""
    from dolfinx import jit

    return jit.get_parameters()["cache_dir"]


def with_portable_fallback(compile_with: Callable[[Dict[str, Any]], Any]) -> Any:
    """compile_with(jit_params()); where the C compiler fails with the processor's flags, once
    more without the precompiled Python header if there was one (a damaged file, which gcc
    refuses: fem_dual.jit_header), then (a compiler that rejects -march=native) with
    DOLFINx's own flags, which every later compilation of the process then takes, unless
    those fail as well. Other failures are raised as they are."""
    own, flags = processor_flags(), jit_flags()

    def attempt():
        try:
            return True, compile_with(jit_params())
        except Exception as exc:  # noqa: BLE001 -- a compiler failure: its type or text
            if not compiler_failed(exc) or own is None or flags[:len(own)] != own:
                raise
            return False, None
    done, result = attempt()
    if not done and discard_precompiled(flags, _cache_dir()):
        done, result = attempt()
    if done:
        return result
    _PORTABLE[0] = True
    try:
        return compile_with(jit_params())
    except Exception:
        # DOLFINx's flags fail too: the code is at fault (a user's constant of inf), not the
        # processor's flags, which later compilations keep (one such failure took a process's
        # every later module to -O2 without the processor's instructions, compiled anew)
        _PORTABLE[0] = False
        raise


def equispaced_coordinates(msh) -> None:
    """Give the UFL domain of `msh` (a DOLFINx mesh or its `ufl.Mesh`) the coordinate element
    FFCx gives it when it compiles a form on it: Lagrange with equispaced points (the same map
    for degree 1). FFCx sets it in place, and only when it compiles (not when it finds the
    module in its cache), and the element is part of every later form's and expression's
    signature on that mesh: without this, which modules a process looks up would depend on
    whether an earlier one had to be compiled, and identical runs would compile new modules.
    Call it on a new mesh, before any form on it has numbered its domains for a signature (such
    a form keeps them under their former hash; compile_form makes it again)."""
    domain = msh.ufl_domain() if hasattr(msh, "ufl_domain") else msh
    sub = getattr(domain.ufl_coordinate_element(), "_sub_element", None)
    if sub is not None and sub.variant() is None:
        domain._ufl_coordinate_element = ufl.VectorElement(ufl.FiniteElement(
            sub.family(), sub.cell(), sub.degree(), sub.quadrature_scheme(),
            variant="equispaced"))


def _settled(form_or_expr) -> None:
    """equispaced_coordinates on every domain of a form or expression (a form's taken from its
    integrals and arguments, so that this does not number them: _analysed)."""
    if isinstance(form_or_expr, ufl.Form):
        terminals = form_or_expr.arguments() + form_or_expr.coefficients()
        domains = [itg.ufl_domain() for itg in form_or_expr.integrals()] + [
            t.ufl_function_space().ufl_domain() for t in terminals]
    else:
        domains = ufl.domain.extract_domains(form_or_expr)
    for domain in {id(d): d for d in domains if d}.values():
        equispaced_coordinates(domain)


def _analysed(form: ufl.Form) -> bool:
    """Whether `form` numbered its domains (for its signature) already: perhaps before one was
    settled, under the domain's former hash. Which cannot be told: the domain is changed in
    place, and a lookup of it in the numbering found it under its former hash for some of
    Python's hash seeds (a form key test failed for 4 of 8 seeds), so a numbered form is
    made again."""
    return getattr(form, "_domain_numbering", None) is not None


def compile_form(form: ufl.Form) -> fem.FormMetaClass:
    """`fem.form(form)` with `jit_params`, waiting for a concurrent compilation of the same form
    (JIT_TIMEOUT); its domains' coordinate elements settled first (equispaced_coordinates: a
    form that numbered its domains before, for its signature, is made again from its
    integrals)."""
    _settled(form)
    if _analysed(form):
        form = ufl.Form(form.integrals())
    return with_portable_fallback(lambda params: fem.form(form, jit_params=params))


# Compiled expressions by the signature of the expression as written (before its derivatives
# are expanded): FFCx keys its cache on the expanded expression, whose expansion and signature
# cost most of a slab problem's set-up (0.3-0.8 s of a pointwise curl3d simulation; the
# expression as written is a small DAG). An entry names the FFCx module and kernel and where
# the kernel's coefficients and constants sit among the written expression's; it is kept in
# memory and, beside FFCx's cache, on disk, so a new process finds it too.
_COMPILED: Dict[str, tuple] = {}
_MEMO_FORMAT = 1


def compile_expression(expr: ufl.core.expr.Expr, points: np.ndarray) -> CompiledExpression:
    """`expr` at the reference `points`, compiled by FFCx with its derivatives expanded
    (see CellPointEvaluator), or taken from a compilation of an expression with the same
    signature (the same UFL up to the numbering of its coefficients, constants and labels)."""
    from dolfinx import jit
    from ffcx.naming import compute_signature

    _settled(expr)
    params = jit.get_parameters()
    key = compute_signature([(expr, points)], f"fem-dual-{_MEMO_FORMAT};{ufl.__version__};"
                            f"{sorted((k, str(v)) for k, v in params.items())};{jit_flags()}")
    coefficients = ufl.algorithms.extract_coefficients(expr)
    constants = ufl.algorithms.analysis.extract_constants(expr)
    arguments = ufl.algorithms.extract_arguments(expr)
    found = _COMPILED.get(key) or _memo_load(key, params["cache_dir"])
    if found is None:
        found = _compile(expr, points, coefficients, constants, params["cache_dir"], key)
    ufcx, module, coefficient_index, constant_index = found
    _COMPILED[key] = found
    mesh = expr.ufl_domain().ufl_cargo()
    space = arguments[0].ufl_function_space() if arguments else None
    used = [coefficients[i] for i in coefficient_index]
    if len(constant_index) != ufcx.num_constants:
        raise RuntimeError(f"the compiled expression reads {ufcx.num_constants} constants where "
                           f"{len(constant_index)} are packed")
    address = module.ffi.cast("uintptr_t", module.ffi.addressof(ufcx))
    cpp = _cpp.fem.create_expression_float64(
        address, [f._cpp_object for f in used], [constants[i]._cpp_object for i in constant_index],
        mesh, None if space is None else space._cpp_object)
    return CompiledExpression(ufcx, cpp, used, mesh, space, module)


def _compile(expr, points, coefficients, constants, cache_dir, key) -> tuple:
    """Compile `expr` with its derivatives expanded (FFCx's JIT and cache), and note its entry."""
    from dolfinx import jit
    from ufl.algorithms import expand_derivatives

    expanded = expand_derivatives(expr)
    mesh = expr.ufl_domain().ufl_cargo()
    ufcx, module, _ = with_portable_fallback(lambda params: jit.ffcx_jit(
        mesh.comm, (expanded, points), form_compiler_params={"scalar_type": "double"},
        jit_params=params))
    kernel = ufcx.original_coefficient_positions
    expanded_coefficients = ufl.algorithms.extract_coefficients(expanded)
    coefficient_index = [coefficients.index(expanded_coefficients[kernel[i]])
                         for i in range(ufcx.num_coefficients)]
    constant_index = [constants.index(c)
                      for c in ufl.algorithms.analysis.extract_constants(expanded)]
    # the kernel's name in its module: FFCx names expressions "expression_<signature>", and a
    # module of one expression has one
    names = [name for name in dir(module.lib) if name.startswith("expression_")]
    if len(names) == 1 and getattr(module.lib, names[0]) is not None:
        _memo_save(key, cache_dir, {"format": _MEMO_FORMAT, "module": module.__name__,
                                    "kernel": names[0], "coefficients": coefficient_index,
                                    "constants": constant_index})
    return ufcx, module, coefficient_index, constant_index


def _memo_path(key: str, cache_dir) -> "os.PathLike":
    from pathlib import Path

    return Path(cache_dir) / "fem-dual-expressions" / f"{key}.json"


def _memo_load(key: str, cache_dir) -> Optional[tuple]:
    """The entry of `key` from disk with its module loaded; None where there is none, or its
    module is not (or no longer) a finished compilation in FFCx's cache."""
    import json
    from pathlib import Path

    try:
        entry = json.loads(_memo_path(key, cache_dir).read_text())
        if entry.get("format") != _MEMO_FORMAT:
            return None
        ready = Path(cache_dir) / f"{entry['module']}.c.cached"
        if not ready.exists():
            return None
        module = _load_module(Path(cache_dir), entry["module"])
        ufcx = getattr(module.lib, entry["kernel"])
        return ufcx, module, list(entry["coefficients"]), list(entry["constants"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError, ImportError):
        return None


def _load_module(cache_dir: "os.PathLike", name: str):
    """The compiled module `name` of FFCx's cache, loaded from its file. (FFCx's own loader
    lists the whole cache directory for every module, a few ms each in a cache of thousands.)"""
    import importlib.machinery
    import importlib.util

    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = cache_dir / f"{name}{suffix}"
        if path.exists():
            loader = importlib.machinery.ExtensionFileLoader(name, str(path))
            spec = importlib.util.spec_from_file_location(name, str(path), loader=loader)
            module = importlib.util.module_from_spec(spec)
            loader.exec_module(module)
            return module
    raise ImportError(f"no compiled module {name} in {cache_dir}")


def _memo_save(key: str, cache_dir, entry: dict) -> None:
    """Write the entry under another name, then rename it: concurrent writers each leave a
    whole file. A cache that cannot be written costs the next process a lookup, nothing else."""
    import json
    import tempfile

    path = _memo_path(key, cache_dir)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("w", dir=path.parent, delete=False,
                                         suffix=".tmp") as tmp:
            tmp.write(json.dumps(entry))
        os.replace(tmp.name, path)
    except OSError:
        pass
