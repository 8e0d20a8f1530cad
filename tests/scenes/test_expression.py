"""The force-expression parser: valid forces, UFL against numpy, and hostile input (whitelist,
limits, one-line messages). Pure UFL on a `ufl.Mesh`: no dolfinx objects, no JIT, no MPI."""
from __future__ import annotations

import ast
import string
import time
import warnings

import numpy as np
import pytest
import ufl
from hypothesis import given, settings
from hypothesis import strategies as st
from ufl.algorithms import expand_derivatives

import fem_dual.expression as expression
import fem_dual.forms.curl2d as curl2d_forms
from fem_dual.errors import InputError
from fem_dual.expression import (FUNCTIONS, MAX_COMPONENTS, RESERVED, SCENE_PARAMETERS,
                                 ForceExpression, check_parameter_names, coordinate_names,
                                 parse_force)
from fem_dual.forms import implicit
from fem_dual.forms.predual import isotropic_quadratic

pytestmark = pytest.mark.serial

ALL_FUNCTIONS = ("sin(x) + cos(y) * tan(x/2) - atan(x - y), "
                 "exp(-x) * log(1 + y) - sqrt(x*y) + abs(y - 2*z), "
                 "sinh(x) + cosh(z) / tanh(1 + x)")
VALUES = {"k": 2.5, "m": 1.5, "alpha": 0.7, "beta": 3.0}
RNG_SEED = 20240611


def points(n, count=8):
    return np.random.default_rng(RNG_SEED).uniform(0.2, 0.9, size=(count, n))


def ufl_on_numbers(force: ForceExpression, x, values) -> np.ndarray:
    """The trick of ForceScene.force_numpy: UFL folds everything when x and c are numbers."""
    F = force.ufl(np.asarray(x, dtype=float), dict(values))
    return np.array([F[i]((0.0,)) for i in range(force.n)])


class Symbolic:
    """x as a ufl.variable of a vector coefficient and parameters as ufl.Constants, the way
    forms.implicit uses a force; evaluates UFL expressions by UFL's own evaluator."""

    def __init__(self, n, names=tuple(VALUES)):
        mesh = ufl.Mesh(ufl.VectorElement("Lagrange", ufl.interval, 1))
        space = ufl.FunctionSpace(mesh, ufl.VectorElement("Lagrange", ufl.interval, 1, dim=n))
        self.n, self.u = n, ufl.Coefficient(space)
        self.x = ufl.variable(self.u)
        self.c = {name: ufl.Constant(mesh) for name in names}
        self.space = space

    def vector(self):
        return ufl.Coefficient(self.space)

    def evaluate(self, expr, x, values=VALUES, extra=()):
        mapping = {self.u: tuple(x), **{self.c[k]: v for k, v in values.items()}, **dict(extra)}
        return np.array([expr[i]((0.0,), mapping) for i in range(expr.ufl_shape[0])])


def rejected(text, known=(), piece=None) -> str:
    """The InputError message of parse_force(text), checked to be one printable line."""
    with pytest.raises(InputError) as info:
        parse_force(text, known)
    message = str(info.value)
    assert message.startswith("force expression: ")
    assert "\n" not in message and message.isprintable(), message
    if piece is not None:
        assert piece in message, message
    return message


# --- valid forces -------------------------------------------------------------------------------

def test_coordinate_names():
    assert coordinate_names(1) == ("x", "x1")
    assert coordinate_names(3) == ("x", "y", "z", "x1", "x2", "x3")
    assert coordinate_names(5) == ("x1", "x2", "x3", "x4", "x5")
    with pytest.raises(ValueError):
        coordinate_names(0)


def test_curl3d():
    force = parse_force("-(y*z), -(2*x*z), -(x*y)")
    assert (force.n, force.parameters) == (3, ())
    for x in points(3):
        expected = -np.array([x[1] * x[2], 2 * x[0] * x[2], x[0] * x[1]])
        assert np.array_equal(force.numpy(x, {}), expected)


def test_curl2d_matches_its_hand_written_forms():
    force = parse_force("-k*x*y**2, -k*x**3", known_parameters=["k"])
    assert (force.n, force.parameters) == (2, ("k",))
    for x in points(2):
        hand = curl2d_forms.force(ufl.as_vector([float(v) for v in x]), {"k": 2.5})
        expected = np.array([hand[i]((0.0,)) for i in range(2)])
        assert np.allclose(force.numpy(x, VALUES), expected, rtol=1e-15, atol=0)
        assert np.allclose(ufl_on_numbers(force, x, VALUES), expected, rtol=1e-15, atol=0)


def test_five_components_use_indexed_coordinates():
    force = parse_force("x2, -x1, x4*x5, -x3*x5, x1**2 - x5")
    x = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    assert np.array_equal(force.numpy(x, {}), [2.0, -1.0, 20.0, -15.0, -4.0])


def test_both_spellings_of_the_coordinates_mix_for_n_le_3():
    mixed, plain = parse_force("x*x2 + y, x1 - 3*y"), parse_force("x*y + y, x - 3*y")
    for x in points(2):
        assert np.array_equal(mixed.numpy(x, {}), plain.numpy(x, {}))


def test_the_largest_force():
    text = ", ".join(f"-x{i}" for i in range(1, MAX_COMPONENTS + 1))
    force = parse_force(text)
    x = np.arange(1.0, MAX_COMPONENTS + 1)
    assert force.n == MAX_COMPONENTS and np.array_equal(force.numpy(x, {}), -x)


def test_pi_unary_signs_and_scene_parameters_need_no_param():
    force = parse_force("-pi*x + +y - -m, alpha*(-x) / beta")
    assert force.parameters == ("alpha", "beta", "m")
    x = np.array([0.3, 0.4])
    expected = [-np.pi * 0.3 + 0.4 + 1.5, 0.7 * -0.3 / 3.0]
    assert np.allclose(force.numpy(x, VALUES), expected, rtol=1e-15, atol=0)


def test_parameters_are_the_used_ones_sorted():
    force = parse_force("x * w + a, y", known_parameters=["w", "a", "unused"])
    assert force.parameters == ("a", "w")


def test_whitespace_and_tabs_around_and_inside():
    force = parse_force("  \tx ,\ty  ")
    assert force.n == 2 and np.array_equal(force.numpy([1.0, 2.0], {}), [1.0, 2.0])


def test_numpy_returns_inf_and_nan_quietly():
    force = parse_force("1/x, log(x), sqrt(-1 - x)")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        values = force.numpy([0.0, 0.0, 0.0], {})
    assert values[0] == np.inf and values[1] == -np.inf and np.isnan(values[2])


# --- UFL ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("text", [ALL_FUNCTIONS, "-k*x*y**2, -k*x**3",
                                  "x**-2 + y**0.5 - 2**x, m*alpha/beta - x/y + pi",
                                  "-(x + y)**3 / (1 + k), -x**2**0.5"])
def test_ufl_agrees_with_numpy(text):
    force = parse_force(text, ["k"])
    symbolic = Symbolic(force.n)
    F = force.ufl(symbolic.x, symbolic.c)
    for x in points(force.n):
        expected = force.numpy(x, VALUES)
        assert np.all(np.isfinite(expected))
        assert np.allclose(symbolic.evaluate(F, x), expected, rtol=1e-14, atol=0)
        assert np.allclose(ufl_on_numbers(force, x, VALUES), expected, rtol=1e-14, atol=0)


def test_ufl_derivative_matches_finite_differences():
    force = parse_force(ALL_FUNCTIONS.replace("y", "(k*y)"), ["k"])
    symbolic = Symbolic(force.n)
    eta = symbolic.vector()
    G = expand_derivatives(ufl.diff(ufl.dot(eta, force.ufl(symbolic.x, symbolic.c)),
                                    symbolic.x))
    h, e = 1e-6, np.array([0.6, -1.3, 0.8])
    for x in points(force.n, count=3):
        steps = [force.numpy(x + h * d, VALUES) - force.numpy(x - h * d, VALUES)
                 for d in np.eye(force.n)]
        jacobian = np.column_stack(steps) / (2 * h)
        got = symbolic.evaluate(G, x, extra={eta: tuple(e)})
        assert np.allclose(got, jacobian.T @ e, rtol=1e-7, atol=1e-8)


def test_plugs_into_the_implicit_forms():
    force = parse_force("-k*x*y**2, -k*x**3", ["k"])
    forms = implicit.make(force.ufl, lambda dx, dv, c: isotropic_quadratic(dx, dv, c["alpha"],
                                                                         c["beta"]))
    s = Symbolic(2)
    xi, eta, dxi, xbar = s.vector(), s.vector(), s.vector(), s.vector()
    G = expand_derivatives(forms.position_equations(s.x, xi, eta, dxi, xbar, s.c))
    x, v = np.array([0.5, -0.3]), {xi: (0.1, 0.2), eta: (0.7, -0.4), dxi: (1.0, 2.0),
                                   xbar: (0.2, 0.1)}
    k, a = VALUES["k"], VALUES["alpha"]
    expected = [a * (x[0] - 0.2) + 1.0 - k * 0.7 * x[1] ** 2 - 3 * k * -0.4 * x[0] ** 2,
                a * (x[1] - 0.1) + 2.0 - 2 * k * 0.7 * x[0] * x[1]]
    assert np.allclose(s.evaluate(G, x, extra=v), expected, rtol=1e-14, atol=1e-15)


def test_ufl_structure_powers_and_abs():
    s = Symbolic(2)
    F = parse_force("x**2, abs(y)").ufl(s.x, {})
    assert isinstance(F[0], ufl.algebra.Power)
    assert F[0].ufl_operands[1] == ufl.constantvalue.IntValue(2)
    assert isinstance(F[1], ufl.algebra.Abs)


def test_ufl_refuses_what_folds_to_a_division_by_zero():
    F = parse_force("x/(0*x)")
    with pytest.raises(InputError, match="cannot be built"):
        F.ufl(Symbolic(1).x, {})


# --- names --------------------------------------------------------------------------------------

def test_reserved_and_scene_parameters():
    assert {"x", "y", "z", "pi"} | set(FUNCTIONS) <= set(RESERVED)
    assert SCENE_PARAMETERS == ("m", "alpha", "beta")
    assert "e" not in RESERVED and parse_force("e*x", ["e"]).parameters == ("e",)


@pytest.mark.parametrize("name", ["sin", "x", "y", "z", "x1", "x4", "x1000", "pi", "abs"])
def test_parameter_names_must_not_clash(name):
    with pytest.raises(InputError, match=f"'{name}'"):
        check_parameter_names([name], 2)
    rejected("x", [name], f"'{name}'")


@pytest.mark.parametrize("name", ["2k", "k-1", "lambda", "", "k\n", "\u0445"])
def test_parameter_names_must_be_identifiers(name):
    with pytest.raises(InputError) as info:
        check_parameter_names([name])
    assert "\n" not in str(info.value)


def test_parameter_names_checked():
    assert check_parameter_names(["k", "m", "k", "w2"], 3) == ("k", "m", "w2")
    assert check_parameter_names("k") == ("k",)


# --- hostile input ------------------------------------------------------------------------------

HOSTILE = [
    ("__import__('os').system('echo hi')", "__import__"),
    ("().__class__.__bases__[0].__subclasses__()", "__subclasses__"),
    ("x.real", "'x.real'"), ("[x for x in y]", "[x for x in y]"), ("lambda: 1", "lambda"),
    ("x if y else z", "x if y else z"), ("x < y", "x < y"), ("x and y", "x and y"),
    ("sin(x, y)", "sin(x, y)"), ("sin(x=1)", "sin(x=1)"), ("sin()", "sin()"),
    ("sin(*x)", "sin(*x)"), ("sin", "'sin'"), ("print(x)", "'print'"), ("open('f')", "'open'"),
    ("eval('1')", "'eval'"), ("exec('x')", "'exec'"), ("x @ y", "x @ y"), ("x // y", "x // y"),
    ("x % y", "x % y"), ("x << y", "x << y"), ("x ^ y", "x ^ y"), ("~x", "~x"),
    ("not x", "not x"), ('"a"', '"a"'), ('b"a"', 'b"a"'), ("f'{x}'", "f'{x}'"),
    ("True", "True"), ("None", "None"), ("...", "Ellipsis"), ("1j", "1j"), ("x + 2j", "2j"),
    ("x[0]", "x[0]"), ("{x}", "{x}"), ("{x: y}", "{x: y}"), ("[x, y]", "[x, y]"),
    ("(x := 1)", "x := 1"), ("await x", "await x"), ("(yield x)", "yield x"),
    ("(x, y)", "(x, y)"), ("x, (y, z)", "(y, z)"), ("x, *y", "x, *y"), ("x,,y", "x,,y"),
    ("x,", "'x,'"), (",x", "',x'"), ("x, ,y", "x, ,y"), ("", "empty"), ("   ", "empty"),
    ("x +* y", "column 4"), ("sin(x", "sin(x"), ("x/0", "x/0"), ("x/(0.0)", "x/(0.0)"),
    ("x/-0", "x/-0"), ("1/-0.0", "1/-0.0"), ("x/(1-1)", "x/(1-1)"), ("x**1e6", "x**1e6"),
    ("x**-1001", "x**-1001"), ("2**10**10", "2**10**10"), ("10**10**10", "10**10**10"),
    ("1e999", "1e999"), ("1" * 400, "1111"), ("1" * 5000, "syntax error"),
    ("10.0**400*x", "10.0**400"), ("sqrt(-1)*x", "sqrt(-1)"), ("log(0) + x", "log(0)"),
    ("(-8)**(1/3)", "(-8)**(1/3)"), ("q", "'q'"), ("x, w", "'w'"), ("x, z", "'z'"),
    ("x, y, x4", "'x4'"), ("x0", "'x0'"), ("x" + "9" * 5000, "x999"), ("e*x", "exp(1)"),
    ("__builtins__", "'__builtins__'"), ("x\n+ y", "\\n"), ("x\r", "\\r"), ("x\x00", "\\x00"),
    ("\u0445 + y", "\u0445"), ("\uff58", "\uff58"), ("x\u2028", "\\u2028"),
    ("x * \u202e y", "\\u202e"),
]


@pytest.mark.parametrize("text, piece", HOSTILE)
def test_hostile_input_is_one_line_naming_the_piece(text, piece):
    rejected(text, piece=piece)


@pytest.mark.parametrize("text, piece", [
    ("x" * 10_001, "10001"), ("(" * 10_000 + "x" + ")" * 10_000, "20001"),
    ("-" * 100_000 + "x", "100001"), ("(" * 4_000 + "x" + ")" * 4_000, "nested"),
    ("-" * 9_000 + "x", "nested"), ("-(" * 150 + "x" + ")" * 150, "nested"),
    ("sin(" * 150 + "x" + ")" * 150, "nested"), ("+".join(["x"] * 150), "nested"),
    ("x**" * 3_000 + "x", "nested"), ("x+x," * 2_400 + "x", "nodes"),
    ("x," * MAX_COMPONENTS + "x", "1001 components"),
], ids=lambda value: value[:12] if isinstance(value, str) else None)
def test_limits_are_quick(text, piece):
    start = time.perf_counter()
    rejected(text, piece=piece)
    assert time.perf_counter() - start < 2.0


def test_huge_exponent_towers_return_at_once():
    for text in ("2**10**10", "10**10**10**10", "x**(10**10)", "(x+1)**9**9**9"):
        start = time.perf_counter()
        rejected(text, piece="exponent")
        assert time.perf_counter() - start < 1.0


def test_chains_below_the_depth_limit_pass():
    assert parse_force("+".join(["x"] * 90)).numpy([1.0], {}) == [90.0]


def test_unknown_name_lists_the_allowed_ones():
    message = rejected("x*q, y", ["k"], "'q'")
    assert "x, y, x1..x2" in message and "alpha, beta, k, m" in message and "pi" in message


def test_the_syntax_error_column_counts_in_the_original_text():
    rejected("  x +* y", piece="syntax error at column 6")


def test_known_parameters_cannot_smuggle_code():
    rejected("x", ["__import__('os')"], "not a plain ASCII identifier")


TOKENS = ["x", "y", "z", "x1", "k", "sin", "(", ")", ",", "+", "-", "*", "/", "**", "0", "1e308",
          "0.0", "2", ".", "[", "]", "'", "=", "lambda", ":", " ", "__class__", "e", "\u0445"]


@settings(max_examples=300, deadline=None, derandomize=True, database=None)
@given(st.one_of(st.lists(st.sampled_from(TOKENS), max_size=16).map("".join),
                 st.text(alphabet=string.printable + "\u0445\u2028", max_size=24)))
def test_anything_is_a_force_or_an_input_error(text):
    try:
        force = parse_force(text, ["k"])
    except InputError as error:
        assert "\n" not in str(error) and str(error).isprintable()
        return
    assert 1 <= force.n <= MAX_COMPONENTS
    with np.errstate(all="ignore"):
        force.numpy(np.full(force.n, 0.5), {"k": 2.0, **VALUES})


def test_the_package_never_evaluates_code():
    from pathlib import Path

    sources = sorted(Path(expression.__file__).parent.glob("*.py"))
    assert len(sources) > 1  # every module of the package, not its __init__ alone
    for source in sources:
        tree = ast.parse(source.read_text())
        names = {node.id for node in ast.walk(tree) if isinstance(node, ast.Name)}
        attributes = {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute)}
        assert not names & {"eval", "exec", "compile", "__import__", "builtins",
                            "importlib"}, source
        assert not attributes & {"eval", "exec", "__import__", "import_module"}, source


def test_jacobian_is_exact_forward_mode():
    """ForceExpression.jacobian differentiates every operator and function in forward mode:
    it equals a Richardson-extrapolated central difference to round-off, and exact formulas
    where they are known (polynomials, abs)."""
    from fem_dual.expression import parse_force

    text = ("-x - x**3 - 2*x*y**2 + 2**x + x**y, -2*sin(3*y)/3 + abs(x)*exp(y)/sqrt(2+x**2)"
            " + atan(x*y)**2 + tan(y)*cosh(x) - sinh(y)/tanh(x) + log(1+x*x) + k*x/y")
    force = parse_force(text, ["k"])
    x, values = np.array([0.3, -0.7]), {"k": 1.5}
    J = force.jacobian(x, values)

    def F(p):
        return force.numpy(p, values)

    def central(h):
        return np.column_stack([(F(x + h * e) - F(x - h * e)) / (2 * h) for e in np.eye(2)])
    richardson = (4 * central(5e-4) - central(1e-3)) / 3
    assert np.abs(J - richardson).max() <= 1e-9 * np.abs(J).max()
    poly = parse_force("x**3*y - abs(y), 7")
    assert np.array_equal(poly.jacobian(np.array([2.0, -3.0]), {}),
                          np.array([[3 * 4.0 * -3.0, 8.0 + 1.0], [0.0, 0.0]]))
