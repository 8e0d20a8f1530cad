"""Validate before allocating, for every scene and every API entry point.

- A scene's number of dofs is checked against the memory rule (fem_dual.scenes.base: its dense
  n x n matrices within DENSE_BUDGET) before anything sized by n exists: exit 2 in a process
  whose address space is capped well below what the refused size would take.
- Masses, stiffnesses and lengths are finite and normal (a subnormal one has no finite
  reciprocal), and so are the matrices built from them that the run inverts.
- A Scene object handed to RunConfig.create is validated like one built from its name.
- API misuse is an InputError naming the argument, never an AttributeError or TypeError from
  inside.
"""
import math
import resource
import subprocess
import sys

import numpy as np
import pytest

from fem_dual import RunConfig, run
from fem_dual.cli import main
from fem_dual.config import DENSE_BUDGET, MAX_DOFS
from fem_dual.errors import InputError
from fem_dual.scenes import get_scene
from fem_dual.scenes.base import TINY, dense_bytes
from fem_dual.scenes.column import Column
from fem_dual.scenes.curl import Curl2D
from fem_dual.scenes.force import ExpressionForce
from fem_dual.scenes.linear import GeneralLinear
from fem_dual.scenes.ziegler import Ziegler

pytestmark = pytest.mark.serial
FEM_DUAL = [sys.executable, "-m", "fem_dual.cli"]
ADDRESS_SPACE = 2_000_000_000  # bytes: an import of dolfinx fits, a refused scene would not


def _capped():
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


def _one_line_error(err: str) -> str:
    assert err.startswith("fem-dual: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    return err


# -- the memory rule ------------------------------------------------------------------------------

def test_max_dofs_is_the_largest_within_the_budget():
    assert dense_bytes(MAX_DOFS) <= DENSE_BUDGET < dense_bytes(MAX_DOFS + 1)
    assert Column.check_size(MAX_DOFS) == MAX_DOFS
    with pytest.raises(InputError, match=rf"links={MAX_DOFS + 1} is too large: .* GiB .* at most "
                                         rf"{MAX_DOFS}"):
        Column.check_size(MAX_DOFS + 1)
    with pytest.raises(InputError, match="dofs=1001 is too large"):  # typed matrices: 1000
        GeneralLinear.check_size(1001)


@pytest.mark.parametrize("argv, named", [
    (["run", "linear", "--param", "dofs=100000", "--param", "M=1"], "dofs=100000 is too large"),
    (["run", "column", "--param", "links=1e12", "--param", "m=1"], "links=1000000000000 is too "
                                                                    "large"),
    (["run", "column", "--param", "links=1e12", "--param", "A=1"], "links=1000000000000 is too "
                                                                    "large"),
])
def test_too_many_dofs_refused_before_allocating(argv, named, tmp_path):
    """Exit 2 and one line, in a process capped at 2 GB of address space, not an allocation of
    74.5 GiB (exit 1, MemoryError)."""
    proc = subprocess.run(FEM_DUAL + argv + ["--cells", "4", "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, stdin=subprocess.DEVNULL,
                          preexec_fn=_capped, timeout=300)
    err = _one_line_error(proc.stderr)
    assert proc.returncode == 2, proc.stderr
    assert named in err and "GiB" in err and f"at most {MAX_DOFS}" in err, err
    assert proc.stdout == "" and not (tmp_path / "out").exists()


# -- finite, normal numbers -----------------------------------------------------------------------

@pytest.mark.parametrize("argv, named", [
    (["linear", "--param", "M=1e-320"], "M has the subnormal entry 1e-320"),
    (["linear", "--param", "K=1e-320"], "K has the subnormal entry 1e-320"),
    (["linear", "--param", "M=1e-160"], "B = M^2"),  # H's default weight: its inverse overflows
    (["linear", "--param", "M=1e-300", "--param", "K=1e300"], "M=1e-300"),
    (["column", "--param", "m=1e-320"], "m has the subnormal entry 1e-320"),
    (["column", "--param", "l=1e-160"], "l=1e-160 is out of range: l^2 = 1e-320"),
    (["column", "--param", "links=1e300"], "links=1e+300 is too large"),
    (["ziegler", "--param", "m1=1e-320"], "m1=1e-320 is subnormal"),
    (["ziegler", "--param", "l=1e-320"], "l=1e-320 is subnormal"),
    (["ziegler", "--param", "l=1e300"], "l=1e+300 is out of range: l^2 = inf"),
    (["curl2d", "--param", "m=1e-320"], "m=1e-320 is subnormal"),
    (["curl2d", "--param", "beta=1e-320"], "beta=1e-320 is subnormal"),
    (["force", "--F", "a*x", "--x0", "1", "--param", "a=1e-320"], "a=1e-320 is subnormal"),
    # unchecked, these end as Newton failures with infinite residuals (exit 3, "use smaller
    # slabs")
    (["curl3d", "--v0", "1e300,0,0"], "v0=1e+300"),
    (["curl3d", "--param", "alpha=1e300"], "alpha=1e+300 is out of range"),
    (["curl3d", "--param", "beta=1e-300"], "beta=1e-300 is out of range"),
    (["force", "--F", "exp(x)", "--x0", "700"], "the force at x0=700.0"),
])
def test_subnormal_and_overflowing_parameters(argv, named, capsys):
    """Each is exit 2 with one line naming it; unchecked, each ends in a traceback
    (LinAlgError, OverflowError), a solve failure or a message naming M for m1."""
    capsys.readouterr()
    assert main(["run"] + argv + ["--cells", "4"]) == 2
    captured = capsys.readouterr()
    err = _one_line_error(captured.err)
    assert named in err, err
    assert captured.out == ""


def test_normal_extremes_are_accepted():
    """The rule refuses subnormal numbers, not small ones: TINY itself is a normal mass."""
    assert RunConfig.create("curl2d", {"m": repr(TINY)}).scene.m == TINY
    assert RunConfig.create("ziegler", {"m1": "1e-150", "m2": "1e-150"}).scene.m1 == 1e-150
    with pytest.raises(InputError, match="B = M"):  # B = M^2 ~ 1e-320: Binv overflows
        RunConfig.create("ziegler", {"m1": "1e-160", "m2": "1e-160"})
    assert RunConfig.create("ziegler", {"P": "0", "c1": "0"}).scene.P == 0.0


# -- scene objects are validated like scene names -------------------------------------------------

@pytest.mark.parametrize("scene, named", [
    (Ziegler(m1=-1.0), "m1=-1.0 must be positive"),
    (Ziegler(m1="2"), "m1='2' is not a number"),
    (Ziegler(m1=True), "m1=True is not a number"),
    (Ziegler(l=1e-320), "l=1e-320 is subnormal"),
    (Ziegler(weights="x"), "weights='x' is not one of"),
    (Ziegler(A=np.eye(3)), "A has shape (3, 3), expected (2, 2)"),
    (Ziegler(A=((1.0, float("nan")), (0.0, 1.0))), "A=1.0,nan,0.0,1.0 is not finite"),
    (Ziegler(c1=float("inf")), "c1=inf is not finite"),
    (Column(links=10 ** 12), "links=1000000000000 is too large"),
    (Column(links="3"), "links='3' is not a whole number"),
    (Column(links=1), "links=1 must be at least 2"),
    (Column(links=3, m=(1.0, 2.0)), "m=1.0,2.0 has 2 entries, expected one number or 3"),
    (Column(m=-1.0), "m=-1.0 must be positive"),
    (GeneralLinear(M=((1e-320, 0.0), (0.0, 1e-320))), "M has the subnormal entry 1e-320"),
    (GeneralLinear(dofs=2, M=((1.0, 2.0), (2.0, 1.0))), "is not positive definite"),
    (Curl2D(m=-1.0), "m=-1.0 must be positive"),
    (ExpressionForce(F="x", m=0.0), "m=0.0 must be positive"),
    (ExpressionForce(F=3), "F=3 is not a force"),
    (ExpressionForce(F="a*x", values=(("a", float("nan")),)), "a=nan is not finite"),
])
def test_scene_objects_are_validated(scene, named):
    """Unchecked, RunConfig.create(Ziegler(m1=-1.0)) runs to "ok" and a Column of 1e12 links
    ends in MemoryError."""
    with pytest.raises(InputError) as info:
        RunConfig.create(scene, x0=[1.0] if isinstance(scene, ExpressionForce) else None)
    assert named in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_valid_scene_objects_and_classes():
    scene = Ziegler(m1=3.0)
    config = RunConfig.create(scene)
    assert config.scene is scene and config.scene.checked() is scene
    assert RunConfig.create(Ziegler, {"m1": "3"}).scene == scene  # a class takes parameters
    with pytest.raises(InputError, match="m1=-1.0 must be positive"):
        RunConfig.create(Ziegler, {"m1": "-1"})
    with pytest.raises(InputError, match="give parameters with the scene name"):
        RunConfig.create(scene, {"m1": "2"})


# -- API misuse: InputError naming the argument ---------------------------------------------------

@pytest.mark.parametrize("call, named", [
    (lambda: RunConfig.create(None), "scene must be a scene name or a Scene object, not None"),
    (lambda: RunConfig.create(123), "scene must be a scene name or a Scene object, not int"),
    (lambda: RunConfig.create(["ziegler"]), "scene must be a scene name or a Scene object"),
    (lambda: get_scene(["ziegler"]), "scene must be a scene name"),
    (lambda: run(None), "config must be a RunConfig"),
    (lambda: RunConfig.create("ziegler", out=123), "out must be a path, not int 123"),
    (lambda: RunConfig.create("ziegler", out=""), "out must be a path, not ''"),
    (lambda: RunConfig.create("ziegler", petsc=["ksp_type=cg"]),
     "petsc must be a mapping of option names to values, not list"),
    (lambda: RunConfig.create("ziegler", petsc={"ksp_type": None}), "petsc: option ksp_type"),
    (lambda: RunConfig.create("ziegler", petsc={1: "cg"}), "petsc: option name 1"),
    (lambda: RunConfig.create("ziegler", [("m1", "2")]),
     "params must be a mapping of parameter names to values, not list"),
    (lambda: RunConfig.create("ziegler", {1: "2"}), "params: parameter name 1"),
    (lambda: Ziegler.from_params("m1=2"), "params must be a mapping"),
])
def test_api_misuse(call, named):
    with pytest.raises(InputError) as info:
        call()
    assert named in str(info.value) and "\n" not in str(info.value), str(info.value)


NAN = float("nan")


@pytest.mark.parametrize("keyword, value, named", [
    ("T", "abc", "T='abc' is not a number"),
    ("T", True, "T=True is not a number"),
    ("T", NAN, "T=nan is not finite"),
    ("T", [1.0], "T=[1.0] is not a number"),
    ("cells", True, "cells=True is not a whole number"),
    ("cells", [4], "cells=[4] is not a whole number"),
    ("cells", 4.5, "cells='4.5' is not a whole number"),
    ("degree", np.array([[2], [3]]), "degree=array([[2], [3]]) is not a whole number"),
    ("degree", "None", "degree='None' is not a whole number"),
    ("slabs", 0, "slabs='0' must be at least 1"),
    ("max_halvings", "x", "max-halvings='x' is not a whole number"),
    ("x0", [1.0, 2.0, 3.0], "x0=1.0,2.0,3.0 has 3 entries, expected 2"),
    ("x0", {1: 2, 3: 4}, "x0={1: 2, 3: 4} is not a vector"),
    ("x0", [np.True_, 0.0], "x0=True is not a number"),
    ("v0", [NAN, 0.0], "v0=nan is not finite"),
    ("v0", 1j, "v0=1j has 1 entries, expected 2"),
    ("v0", [1j, 0.0], "v0=1j is not a number"),
    ("rtol", "x", "rtol='x' is not a number"),
    ("superpose", 1, "superpose=1 is not one of"),
    ("staging", None, "staging=None is not one of"),
    ("recovery", ["momentum"], "recovery=['momentum'] is not one of"),
    ("assembly", np.array([["a"], ["b"]]), "assembly=array("),
    ("base", 3, "base=3 is not one of"),
    ("coordinates", None, "coordinates=None is not one of"),
    ("reference", True, "reference=True is not one of"),
    ("t_eval", [], "t-eval has no times"),
    ("t_eval", {0.1: 1}, "t-eval={0.1: 1} is not a list of times"),
    ("t_eval", "0.1,nan", "t-eval='nan' is not finite"),
    ("t_eval", [0.1, 99.0], "t-eval time 99.0 lies outside"),
])
def test_keyword_misuse(keyword, value, named):
    with pytest.raises(InputError) as info:
        RunConfig.create("ziegler", **{keyword: value})
    message = str(info.value)
    assert "\n" not in message, message
    assert named in message, message


def test_atol_misuse():
    with pytest.raises(InputError, match="atol=nan is not finite"):
        RunConfig.create("ziegler", rtol=1e-3, atol=NAN)
    with pytest.raises(InputError, match="atol=True is not a number"):
        RunConfig.create("ziegler", rtol=1e-3, atol=True)


def test_petsc_values_spelt_for_petsc():
    config = RunConfig.create("ziegler", petsc={"-ksp_rtol": 1e-12, "ksp_max_it": 50,
                                                "ksp_monitor": "", "ksp_view": False})
    assert config.petsc == {"ksp_rtol": "1e-12", "ksp_max_it": "50", "ksp_monitor": "",
                            "ksp_view": "false"}
    assert math.isfinite(config.T)
