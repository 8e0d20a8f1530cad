"""PETSc options are input: checked before any work, and refused when a solver leaves them unused.

Two checks, each ending in one InputError line (exit 2) that names the option and its value:

1. `check_options(options, path)`, before anything is compiled: the values of the option kinds
   known here (solver, preconditioner, line-search types and matrix solver packages against what
   this PETSc build has registered; integers, finite reals, booleans), and what a solver path
   cannot honour (SNES options without a SNES; PETSc preconditioners, factorisations or Krylov
   methods the matrix-free Kronecker operator cannot serve). Deterministic: every MPI rank raises
   the same error.

2. `require_used(...)`, after the solver's set-up and before the options are removed: every
   option the user gave (`--petsc-option`, or PETSC_OPTIONS under the solver's prefix) must have
   been queried by PETSc (PetscOptionsUsed, through ctypes on the libpetsc petsc4py loaded),
   except the few PETSc reads only while solving (SOLVE_TIME). Combined over the ranks.

Paths: "forms" (a linear scene's assembled slab matrix, one KSP), "snes" (a nonlinear scene's
Newton), "kronecker" (a linear scene's matrix-free CG with its own preconditioner).
"""
from __future__ import annotations

import ctypes
import difflib
import math
import re
from typing import Dict, Iterable, List, Mapping, Optional, Tuple

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from fem_dual.errors import InputError


def solver_prefix(scene_name: str) -> str:
    """The PETSc options prefix of a scene's slab solver."""
    return "dual_" + scene_name.replace("-", "_") + "_"

__all__ = ["PATHS", "SOLVE_TIME", "SNES_TYPES", "check_options", "check_user_options",
           "user_options", "options_used", "require_used", "available_types", "solver_packages",
           "last_line"]

PATHS = ("forms", "kronecker", "snes")

# Options PETSc reads only inside KSPSolve / SNESSolve (measured on PETSc 3.18: none of them is
# queried by setFromOptions or set-up); the solvers keep the options set while they solve.
SOLVE_TIME = {
    "forms": {"ksp_converged_reason"},
    "kronecker": {"ksp_converged_reason"},
    "snes": {"ksp_converged_reason", "snes_converged_reason", "snes_view", "snes_view_pre",
             "snes_view_solution", "snes_test_jacobian", "snes_test_jacobian_display",
             "snes_test_jacobian_display_threshold", "snes_test_jacobian_view",
             "snes_test_local_min", "snes_compare_explicit", "snes_compare_operator",
             "snes_compare_coloring", "snes_compare_coloring_display"},
}

# Types that need an object made in code (a Python context, shell callbacks): from an option
# they fail at set-up, or crash.
_CODE_TYPES = {"ksp_type": {"python"}, "pc_type": {"python", "shell"},
               "snes_type": {"python", "shell"}, "snes_linesearch_type": {"shell"}}
_LINE_SEARCHES = ("basic", "bt", "cp", "l2", "nleqerr", "ncglinear", "none", "shell")
# The SNES types that run on a slab's residual and Jacobian (measured on curl3d, PETSc 3.18); the
# others need a DM, subdomains, user sweeps or a nonlinear preconditioner the solver does not set
# up: they fail (qn, ncg, ngmres, nrichardson, fas, nasm, patch, composite) or crash PETSc
# (aspin when its type is set, ngs when it solves).
SNES_TYPES = ("anderson", "ksponly", "ksptransposeonly", "ms", "newtonls", "newtontr",
              "vinewtonrsls", "vinewtonssls")

# Value kinds by the option name's last words (an option matches `tail` or `..._tail`)
_INT_TAILS = {"max_it": 0, "restart": 1, "levels": 0, "max_funcs": 0, "max_fail": 0,
              "max_linear_solve_fail": 0, "lag_jacobian": -2, "lag_preconditioner": -2,
              "bcgsl_ell": 1, "asm_overlap": 0, "bjacobi_blocks": 1, "bjacobi_local_blocks": 1,
              "sor_its": 1, "sor_lits": 1, "gmres_restart": 1, "lgmres_augment": 0,
              "chebyshev_esteig_steps": 1, "check_norm_iteration": -1, "grid_sequence": 0,
              "coarse_eq_limit": 1, "qn_m": 1, "ngmres_m": 1, "anderson_m": 1, "fcg_mmax": 1,
              "matsolve_batch_size": 1}
_REAL_TAILS = {"rtol": (0.0, 1.0), "atol": (0.0, None), "stol": (0.0, None),
               "divtol": (0.0, None), "divergence_tolerance": (None, None), "trtol": (0.0, None),
               "linesearch_damping": (0.0, None), "linesearch_maxstep": (0.0, None),
               "linesearch_minlambda": (0.0, None), "linesearch_alpha": (0.0, None),
               "linesearch_ltol": (0.0, None), "factor_shift_amount": (0.0, None),
               "factor_fill": (0.0, None), "factor_zeropivot": (0.0, None),
               "sor_omega": (0.0, 2.0), "richardson_scale": (None, None),
               "gmres_haptol": (0.0, None), "tr_delta0": (0.0, None)}
_BOOL_TAILS = ("error_if_not_converged", "initial_guess_nonzero", "reuse_preconditioner", "knoll",
               "diagonal_scale", "diagonal_scale_fix", "converged_use_initial_residual_norm",
               "converged_use_min_initial_residual_norm", "constant_null_space",
               "lag_jacobian_persists", "lag_preconditioner_persists", "snes_ksp_ew",
               "snes_mf", "snes_mf_operator", "factor_reuse_ordering", "factor_reuse_fill",
               "factor_in_place", "factor_pivot_in_blocks", "pc_use_amat",
               "linesearch_keeplambda", "snes_force_iteration", "cg_single_reduction",
               "converged_maxits", "use_explicittranspose", "ksp_converged_reason_view_cancel")
_TRUE = {"", "1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}
_INT = re.compile(r"[+-]?\d+")
PETSC_INT_MAX = 2**31 - 1  # PetscInt of Debian's PETSc 3.18 (32-bit indices)
_REAL = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
_NAME = re.compile(r"[A-Za-z0-9_]+")
_MUMPS = re.compile(r"(.*_)?mat_mumps_(i?)cntl_\d+")

# Options a misspelling is compared with (the user's own ones are added)
COMMON = ("ksp_type", "pc_type", "ksp_rtol", "ksp_atol", "ksp_divtol", "ksp_max_it",
          "ksp_monitor", "ksp_monitor_true_residual", "ksp_view", "ksp_converged_reason",
          "ksp_error_if_not_converged", "ksp_initial_guess_nonzero", "ksp_gmres_restart",
          "ksp_norm_type", "pc_factor_mat_solver_type", "pc_factor_mat_ordering_type",
          "pc_factor_shift_type", "pc_factor_levels", "snes_type", "snes_rtol", "snes_atol",
          "snes_stol", "snes_max_it", "snes_monitor", "snes_view", "snes_converged_reason",
          "snes_linesearch_type", "snes_linesearch_monitor", "snes_linesearch_max_it",
          "snes_max_funcs", "snes_lag_jacobian", "snes_error_if_not_converged")


def last_line(exc: BaseException) -> str:
    """The last line of a PETSc error (PETSc's own message), without the rank tag."""
    lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
    text = lines[-1] if lines else ""
    return re.sub(r"^\[\d+\]\s*", "", text) or f"PETSc error {getattr(exc, 'ierr', '?')}"


def _destroy(obj) -> None:
    try:
        obj.destroy()
    except PETSc.Error:  # some types cannot be destroyed unset up (KSPReset_PIPELCG, 3.18)
        pass


def _matches(key: str, tail: str) -> bool:
    return key == tail or key.endswith("_" + tail)


# --- what this PETSc build has --------------------------------------------------------------

_TYPES: Dict[str, List[str]] = {}


def _registered(kind: str, name: str) -> bool:
    """Whether PETSc has `name` registered as a KSP, PC or line-search type (setType on
    COMM_SELF: unknown types are PETSc error 86; SNES types are not probed: aspin crashes)."""
    opts = PETSc.Options()
    obj = None
    try:
        if kind == "ksp_type":
            obj = PETSc.KSP().create(PETSc.COMM_SELF)
            obj.setType(name)
        elif kind == "pc_type":
            obj = PETSc.PC().create(PETSc.COMM_SELF)
            obj.setType(name)
        else:  # line searches have no petsc4py class: a SNES of our own reads the option
            obj = PETSc.SNES().create(PETSc.COMM_SELF)
            obj.setOptionsPrefix("fem_dual_check_")
            opts["fem_dual_check_snes_linesearch_type"] = name
            try:
                obj.setFromOptions()
            finally:
                opts.delValue("fem_dual_check_snes_linesearch_type")
        return True
    except PETSc.Error:
        return False
    finally:
        if obj is not None:
            _destroy(obj)


def available_types(kind: str) -> List[str]:
    """The types of `kind` (ksp_type, pc_type, snes_linesearch_type) this PETSc build has
    registered, sorted."""
    if kind not in _TYPES:
        if kind == "snes_linesearch_type":
            names = _LINE_SEARCHES
        else:
            cls = {"ksp_type": PETSc.KSP, "pc_type": PETSc.PC}[kind]
            names = [v for k, v in vars(cls.Type).items() if k.isupper() and isinstance(v, str)]
        _TYPES[kind] = sorted({n for n in names if _registered(kind, n)})
    return _TYPES[kind]


def solver_packages() -> List[str]:
    """The matrix solver packages (pc_factor_mat_solver_type) this PETSc build has registered
    for any matrix and factorisation (MatSolverTypeGet)."""
    if "mat_solver_type" not in _TYPES:
        names = [v for k, v in vars(PETSc.Mat.SolverType).items()
                 if k.isupper() and isinstance(v, str)]
        lib = _libpetsc()
        found = []
        if lib is None:
            found = names
        else:
            PETSc.Mat().createAIJ([1, 1], nnz=1, comm=PETSc.COMM_SELF).destroy()  # registered
            get = lib.MatSolverTypeGet
            get.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_int,
                            ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int),
                            ctypes.c_void_p]
            get.restype = ctypes.c_int
            for name in names:
                flag, mflag = ctypes.c_int(0), ctypes.c_int(0)
                if get(name.encode(), b"seqaij", 1, ctypes.byref(flag), ctypes.byref(mflag),
                       None) == 0 and flag.value:
                    found.append(name)
        _TYPES["mat_solver_type"] = sorted(set(found) | {"petsc"})
    return _TYPES["mat_solver_type"]


_LIB: List[Optional[ctypes.CDLL]] = []


def _libpetsc() -> Optional[ctypes.CDLL]:
    """The libpetsc petsc4py loaded (its path from /proc/self/maps), or None."""
    if not _LIB:
        lib = None
        try:
            with open("/proc/self/maps") as maps:
                paths = [ln.split()[-1] for ln in maps
                         if re.search(r"/libpetsc[^/]*\.so", ln.split()[-1] if ln.split() else "")]
            if paths:
                lib = ctypes.CDLL(paths[0])
                lib.PetscOptionsUsed.argtypes = [ctypes.c_void_p, ctypes.c_char_p,
                                                 ctypes.POINTER(ctypes.c_int)]
                lib.PetscOptionsUsed.restype = ctypes.c_int
        except (OSError, AttributeError):
            lib = None
        _LIB.append(lib)
    return _LIB[0]


# --- the checks --------------------------------------------------------------------------------

def user_options(prefix: str, overrides: Optional[Mapping[str, str]] = None
                 ) -> Dict[str, Tuple[str, str]]:
    """The options the user gave this solver: key (without the prefix) -> (value, origin), origin
    "--petsc-option" for `overrides` (they win) or "PETSC_OPTIONS" for what the options database
    holds under `prefix` (the environment variable, an options file). Does not mark options
    used."""
    given: Dict[str, Tuple[str, str]] = {}
    low = prefix.lower()
    for name, value in PETSc.Options().getAll().items():
        if name.lower().startswith(low) and len(name) > len(prefix):
            given[name[len(prefix):]] = ("" if value is None else str(value), "PETSC_OPTIONS")
    for key, value in (overrides or {}).items():
        given[key] = (str(value), "--petsc-option")
    return given


def _show(key: str, value: str, origin: Optional[str], prefix: str) -> str:
    if origin == "PETSC_OPTIONS":
        return f"-{prefix}{key}{' ' + value if value else ''} (PETSC_OPTIONS)"
    return f"{key}={value}"


def check_options(options: Mapping[str, str], path: str, *, prefix: str = "",
                  origins: Optional[Mapping[str, str]] = None) -> None:
    """Refuse the first option (in the mapping's order) whose value is not of its kind or that
    the solver `path` cannot honour: InputError naming it and its value.

    Args:
        options: option names without the leading dash and without the solver prefix -> values.
        path: "forms", "snes" or "kronecker".
        prefix, origins: only for the message (where each option came from).
    """
    if path not in PATHS:
        raise ValueError(f"path {path!r} is not one of {PATHS}")
    for key, value in options.items():
        key, value = str(key), str(value)
        problem = _problem(key, value.strip(), path)
        if problem:
            origin = (origins or {}).get(key)
            raise InputError(f"PETSc option {_show(key, value, origin, prefix)}: {problem}")


def check_user_options(prefix: str, overrides: Optional[Mapping[str, str]], path: str
                       ) -> Dict[str, Tuple[str, str]]:
    """check_options on what the user gave the solver under `prefix` (`overrides`, the
    --petsc-option dict, and PETSC_OPTIONS under the prefix); returns them (see user_options).
    Deterministic: call it on every rank (RunConfig.create does, before anything runs)."""
    given = user_options(prefix, overrides)
    check_options({k: v for k, (v, _) in given.items()}, path, prefix=prefix,
                  origins={k: origin for k, (_, origin) in given.items()})
    return given


def _problem(key: str, value: str, path: str) -> Optional[str]:
    """Why the option cannot be taken, or None."""
    if not _NAME.fullmatch(key):
        return "not a PETSc option name (letters, digits and _ only)"
    if "python" in key.split("_"):
        return "options that load Python code by name are not taken"
    if path != "snes" and (key.startswith("snes_") or "_snes_" in key):
        return (f"the {path} solver of a linear scene has no SNES (SNES options apply to "
                "nonlinear scenes)")
    if path == "kronecker":
        problem = _kronecker_problem(key, value)
        if problem:
            return problem
    for kind in ("snes_linesearch_type", "ksp_type", "pc_type", "snes_type"):
        if _matches(key, kind):
            return _type_problem(kind, value)
    if _matches(key, "mat_solver_type") or _matches(key, "factor_mat_solver_package"):
        packages = solver_packages()
        if value.lower() not in packages:
            return (f"not a matrix solver package of this PETSc build (one of: "
                    f"{', '.join(packages)})")
        return None
    mumps = _MUMPS.fullmatch(key)
    if mumps:
        return _int_problem(value, None) if mumps.group(2) else _real_problem(value, None, None)
    for tail, low in _INT_TAILS.items():
        if _matches(key, tail):
            return _int_problem(value, low)
    for tail, (low, high) in _REAL_TAILS.items():
        if _matches(key, tail):
            return _real_problem(value, low, high)
    for tail in _BOOL_TAILS:
        if _matches(key, tail):
            if value.lower() not in _TRUE | _FALSE:
                return "not a boolean (true, false, 1, 0, yes, no, on, off)"
            return None
    return None


def _type_problem(kind: str, value: str) -> Optional[str]:
    what = {"ksp_type": "a KSP (Krylov) type", "pc_type": "a preconditioner (PC) type",
            "snes_type": "a SNES type", "snes_linesearch_type": "a SNES line-search type"}[kind]
    if value in _CODE_TYPES[kind]:
        return f"{what} that needs an object made in code; not available from options"
    if kind == "snes_type":
        if value not in SNES_TYPES:
            return (f"not a SNES type this solver can run (one of: {', '.join(SNES_TYPES)}; "
                    "the others need a DM, subdomains or callbacks it does not set up)")
        return None
    if not value or not _registered(kind, value):
        known = [t for t in available_types(kind) if t not in _CODE_TYPES[kind]]
        return f"not {what} of this PETSc build (one of: {', '.join(known)})"
    return None


def _int_problem(value: str, low: Optional[int]) -> Optional[str]:
    if not _INT.fullmatch(value):
        return "not an integer"
    if low is not None and int(value) < low:
        return f"must be at least {low}"
    if int(value) > PETSC_INT_MAX:  # PETSc would wrap it (ksp_max_it=2147483648 ran as -1)
        return f"exceeds PETSc's integer range (at most {PETSC_INT_MAX})"
    return None


def _real_problem(value: str, low: Optional[float], high: Optional[float]) -> Optional[str]:
    if not _REAL.fullmatch(value) or not math.isfinite(float(value)):
        return "not a finite real number"
    number = float(value)
    if low is not None and number < low:
        return f"must be at least {low:g}"
    if high is not None and number >= high:
        return f"must be less than {high:g}"
    return None


def _kronecker_problem(key: str, value: str) -> Optional[str]:
    """What the matrix-free Kronecker CG cannot honour: it has no matrix entries (no PETSc
    preconditioner, factorisation or matrix option applies; its own fast-diagonalisation
    preconditioner is turned off by pc_type=none) and no transpose."""
    if key == "pc_type":
        if value == "none":
            return None
        return ("the kronecker path is matrix-free CG with its own fast-diagonalisation "
                "preconditioner (no matrix entries to build a PETSc preconditioner from): only "
                "pc_type=none (no preconditioner) is taken; --assembly forms for PETSc's")
    if key.startswith(("pc_", "mat_")):
        return ("the kronecker path is matrix-free with its own preconditioner: PETSc "
                "preconditioner and matrix options do not apply (--assembly forms for them)")
    if key == "ksp_type":
        if value in ("preonly", "none"):
            return ("the kronecker path's preconditioner is not an exact inverse: it needs a "
                    "Krylov method (cg, the default, or gmres, minres, ...)")
        if value and _registered("ksp_type", value) and value not in _CODE_TYPES["ksp_type"]:
            failure = _kronecker_krylov(value)
            if failure:
                return (f"this Krylov method cannot run on the kronecker path's matrix-free "
                        f"operator and preconditioner ({failure})")
    return None


_KRYLOV: Dict[str, Optional[str]] = {}


class _Tridiagonal:  # a small SPD operator that offers what the Kronecker operator offers: mult
    def mult(self, mat, x, y) -> None:
        a = x.array_r
        y.array[:] = 3.0 * a - np.roll(a, 1) - np.roll(a, -1)


class _Scaling:  # ... and a preconditioner that offers apply only
    def apply(self, pc, x, y) -> None:
        y.array[:] = x.array_r / 3.0


def _kronecker_krylov(ksp_type: str) -> Optional[str]:
    """None if `ksp_type` solves a small system with an operator and a preconditioner that offer
    only mult and apply (as the Kronecker path's do), else PETSc's complaint. On COMM_SELF with
    no options read: the same answer on every rank, no output."""
    if ksp_type not in _KRYLOV:
        A = PETSc.Mat().createPython([6, 6], _Tridiagonal(), comm=PETSc.COMM_SELF)
        A.setUp()
        ksp = PETSc.KSP().create(PETSc.COMM_SELF)
        x, b = A.createVecs()
        try:
            ksp.setOperators(A)
            ksp.setType(ksp_type)
            pc = ksp.getPC()
            pc.setType(PETSc.PC.Type.PYTHON)
            pc.setPythonContext(_Scaling())
            ksp.setTolerances(rtol=1e-10, max_it=50)
            b.set(1.0)
            ksp.setUp()
            ksp.solve(b, x)
            _KRYLOV[ksp_type] = None
        except PETSc.Error as exc:
            _KRYLOV[ksp_type] = last_line(exc)
        finally:
            for obj in (ksp, A, x, b):
                _destroy(obj)
    return _KRYLOV[ksp_type]


def options_used(names: Iterable[str], comm: MPI.Comm = MPI.COMM_WORLD) -> Dict[str, bool]:
    """Whether PETSc queried each full option name (prefix included, no dash) on any rank of
    `comm` (PetscOptionsUsed; every name counts as used when libpetsc cannot be found). The names
    of all ranks are answered (a rank may pass none). Collective."""
    names = sorted(set().union(*comm.allgather(set(names))))
    flags = np.ones(len(names), dtype=np.int32)
    lib = _libpetsc() if names else None
    if lib is not None:
        for i, name in enumerate(names):
            used = ctypes.c_int(0)
            if lib.PetscOptionsUsed(None, name.encode(), ctypes.byref(used)) == 0:
                flags[i] = 1 if used.value else 0
    total = np.zeros_like(flags)
    comm.Allreduce(flags, total, op=MPI.MAX)
    return {name: bool(flag) for name, flag in zip(names, total)}


def require_used(given: Mapping[str, Tuple[str, str]], prefix: str, path: str,
                 comm: MPI.Comm = MPI.COMM_WORLD,
                 values: Optional[Mapping[str, str]] = None) -> None:
    """InputError naming the options of `given` (key -> (value, origin), see user_options) that
    no rank's solver queried under `prefix`, but for SOLVE_TIME. Call it after the solver's set-up
    and before its options are removed, on every rank. `values`: the option values in force
    (hints). Collective."""
    keys = [k for k in given if k not in SOLVE_TIME[path]]
    used = options_used([prefix + k for k in keys], comm)
    unused = [k for k in keys if not used[prefix + k]]
    if not unused:
        return
    shown = ", ".join(unused if all(given[k][1] == "--petsc-option" for k in unused)
                      else [_show(k, given[k][0], given[k][1], prefix) for k in unused])
    hints, plain = [], []
    for key in unused:
        if key.lower().startswith(prefix.lower()):
            hints.append(f"give {key[len(prefix):]} without the prefix {prefix}, which the "
                         "solver adds")
            continue
        close = [] if key in COMMON else difflib.get_close_matches(
            key, sorted((set(COMMON) | set(given)) - {key}), n=1, cutoff=0.8)
        if close:
            hints.append(f"{key}: did you mean {close[0]}?")
        else:
            plain.append(key)
    ksp_type = (values or {}).get("ksp_type", "")
    if ksp_type in ("preonly", "none") and any(k.startswith("ksp_") for k in plain):
        hints.append(f"ksp_type={ksp_type} is a direct solve: no iterations, tolerances or "
                     "Krylov settings")
    raise InputError(f"PETSc option(s) not used by the {path} solver: {shown}"
                     + ("; " + "; ".join(hints) if hints else ""))
