"""A user-defined force: only F (UFL) and H are written; everything else comes from the library."""
import dataclasses
from typing import ClassVar

import numpy as np
import pytest
import ufl

from fem_dual import RunConfig, run
from fem_dual.scenes import SCENES, ForceScene, register
from fem_dual.forms import implicit
from fem_dual.forms.predual import isotropic_quadratic
from helpers import observed_rates


def swirl_force(x, c):
    """A curl force: curl F = a (1 + 3 y^2) != 0."""
    return ufl.as_vector([-x[0] - c["a"] * x[1] ** 3, c["a"] * x[0] - x[1]])


def swirl_h(dx, dv, c):
    return isotropic_quadratic(dx, dv, c["alpha"], c["beta"])


@dataclasses.dataclass(frozen=True)
class Swirl(ForceScene):
    name: ClassVar[str] = "test-swirl"
    n: ClassVar[int] = 2
    forms: ClassVar = implicit.make(swirl_force, swirl_h)
    default_T: ClassVar[float] = 4.0
    default_x0: ClassVar[tuple] = (1.0, 0.0)
    default_v0: ClassVar[tuple] = (0.0, 0.5)
    a: float = 0.5


@pytest.fixture(scope="module", autouse=True)
def registered():
    register(Swirl)
    yield
    SCENES.pop(Swirl.name)


@pytest.mark.mpi
def test_user_force_converges_to_the_reference():
    errors = [run(RunConfig.create("test-swirl", cells=c, degree=3, slabs=4, base="start"))
              .error["x_max"] for c in (3, 6, 12)]
    assert errors[-1] < 1e-8
    assert np.all(observed_rates(errors) > 5.5), errors  # order 2p


def test_reference_of_a_user_force_evaluates_its_ufl():
    scene = Swirl.from_params({"a": "0.7"})
    x = np.array([0.3, -0.8])
    expected = np.array([-x[0] - 0.7 * x[1] ** 3, 0.7 * x[0] - x[1]])
    assert np.allclose(scene.force_numpy(x), expected, rtol=1e-15, atol=0)


def test_user_force_parameters_are_validated():
    from fem_dual import InputError
    with pytest.raises(InputError, match="beta"):
        Swirl.from_params({"beta": "0"})


@pytest.mark.parametrize("name", ["M", "Binv", "D"])
def test_the_forms_own_constant_names_are_not_parameters(name, capsys):
    """A parameter named as a constant the forms read (D: the damping matrix) is bad input,
    exit 2 naming it, not a UFL traceback."""
    from fem_dual.cli import main

    assert main(["run", "force", "--F", f"-{name}*x", "--param", f"{name}=2", "--x0", "1",
                 "--slabs", "2"]) == 2
    err = capsys.readouterr().err
    assert f"{name!r}" in err and "reserved" in err and "Traceback" not in err


def test_parameters_that_derivatives_remove_are_not_a_wrong_answer():
    """The worst case of the constant slots: with constants in the wrong slots of the kernel
    this run ends ok with an estimate of 1.0e-8, 0.048 off; its answer is within its estimate."""
    r = run(RunConfig.create("force", {"F": "a + b*x + c*x**2 - x**3", "a": "0.1", "b": "0.2",
                                       "c": "0.3"}, x0="0.5"))
    assert r.status == "ok"
    assert max(r.error["x_max"], r.error["v_max"]) <= r.error_estimate


@pytest.mark.parametrize("a", [-2.0, 0.5])
def test_a_parameter_that_derivatives_remove_keeps_the_other_constants_in_place(a):
    """F = a leaves G_x = alpha without a: DOLFINx 0.5.2's Expression packs a anyway, and a
    kernel bound without it would slide every later constant into the wrong slot (exit 3, 'DtP
    map is near singular', for a < 1). F = -x - a is F = -x about x = -a: the same motion
    shifted, to round-off."""
    common = dict(T=2, cells=4, degree=4, staging="off")
    r = run(RunConfig.create("force", {"F": "a", "a": str(a)}, x0="0.5", **common))
    assert r.status == "ok" and r.error["x_max"] <= r.error_estimate
    shifted = run(RunConfig.create("force", {"F": "-x-a", "a": str(a)}, x0="0.5", **common))
    plain = run(RunConfig.create("force", {"F": "-x"}, x0=str(0.5 + a), **common))
    assert np.abs((shifted.x + a) - plain.x).max() <= 1e-12
