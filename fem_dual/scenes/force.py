"""`force`: a particle under a force typed as text, `--F "EXPR, EXPR[, ...]"`.

The text is parsed by the whitelist of fem_dual.expression into UFL (the forms: the implicit DtP
map of forms.implicit, whose G is derived by UFL) and into numpy (the DOP853 reference); it is
never evaluated as Python. The number of components is n. Parameters are the names given with
`--param` beside m, alpha, beta; every one becomes a fem.Constant, so changing a value never
recompiles a form.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, ClassVar, Dict, Mapping, Optional, Tuple

import numpy as np

from fem_dual.errors import InputError
from fem_dual.scenes.base import parse_number, require_normal, require_positive, show
from fem_dual.scenes.curl import ForceScene

if TYPE_CHECKING:  # the parser imports UFL: only when a force is parsed
    from fem_dual.expression import ForceExpression

__all__ = ["ExpressionForce"]


@dataclasses.dataclass(frozen=True)
class ExpressionForce(ForceScene):
    """A particle of mass m under F(x) given as text (`F`), with parameters `values`."""

    name: ClassVar[str] = "force"
    default_T: ClassVar[float] = 1.0
    summary: ClassVar[str] = ('your own force: --F "EXPR, ..." (x, y, z or x1..xn; + - * / **, '
                              "sin cos tan exp log sqrt sinh cosh tanh atan abs, pi; parameters "
                              "by --param)")

    F: str = ""
    values: Tuple[Tuple[str, float], ...] = ()  # the --param values besides m, alpha, beta

    @classmethod
    def from_params(cls, params: Optional[Mapping[str, object]] = None) -> "ExpressionForce":
        """Build from NAME -> value with the force text under "F" (InputError if missing)."""
        params = cls._params_dict(params)
        text = params.pop("F", None)
        if text is None or not str(text).strip():
            raise InputError('scene force needs its force: --F "EXPR, EXPR, ..." (one '
                             "expression per component)")
        own = {k: parse_number(k, params.pop(k)) for k in ("m", "alpha", "beta") if k in params}
        values = {k: parse_number(k, v) for k, v in params.items()}
        for name in values:
            if name in ("M", "Binv", "D"):  # the constants of the forms themselves
                raise InputError(f"parameter name {name!r} is reserved (the mass matrix, H's "
                                 "inverse weight and the damping matrix); use another name")
        from fem_dual.expression import check_parameter_names, parse_force

        expression = parse_force(str(text), values)
        check_parameter_names(values, expression.n)
        unused = sorted(set(values) - set(expression.parameters))
        if unused:
            raise InputError(f"parameter {unused[0]!r} does not appear in the force "
                             f"{str(text)[:60]!r}")
        return cls(F=str(text), values=tuple(sorted(values.items())), **own).checked()

    @classmethod
    def listing(cls) -> str:
        return (f"{cls.name}: {cls.summary}\n  n = the number of components of --F  "
                f"T={cls.default_T:g}  x0 required  v0=0\n  parameters: m=1.0, alpha=1.0, "
                "beta=1.0, and any NAME=VALUE the force uses")

    @functools.cached_property
    def expression(self) -> ForceExpression:
        from fem_dual.expression import parse_force

        return parse_force(self.F, dict(self.values))

    @property
    def n(self) -> int:  # type: ignore[override]
        return self.expression.n

    @functools.cached_property
    def forms(self):  # type: ignore[override]
        from fem_dual.forms import implicit
        from fem_dual.forms.predual import isotropic_aux

        return implicit.make(self.expression.ufl, isotropic_aux)

    @property
    def default_x0(self) -> Tuple[float, ...]:  # type: ignore[override]
        raise InputError("scene force needs its start state: --x0 a,b,... (and --v0, default 0)")

    @property
    def default_v0(self) -> Tuple[float, ...]:  # type: ignore[override]
        return (0.0,) * self.n

    def check_values(self) -> None:
        """The force text a string, its parameters (name, number) pairs: a scene object built
        in Python is checked like one from the command line (before n is read from F)."""
        super().check_values()
        if not isinstance(self.F, str) or not self.F.strip():
            raise InputError(f"F={show(repr(self.F))} is not a force: give the text \"EXPR, EXPR, "
                             "...\" (one expression per component)")
        try:
            pairs = [(name, value) for name, value in self.values]
        except (TypeError, ValueError):
            raise InputError(f"values={show(self.values)} is not a sequence of (name, number) "
                             "pairs") from None
        for name, value in pairs:
            if not isinstance(name, str):
                raise InputError(f"values: parameter name {show(name)} is not a string")
            require_normal(name, value)

    def validate(self) -> None:
        require_positive(self, "m", "alpha", "beta")

    def constants(self) -> Dict[str, np.ndarray]:
        values = {name: np.array(value, dtype=float) for name, value in self.values}
        values.update(m=np.array(self.m), alpha=np.array(self.alpha),
                      beta=np.array(self.beta), M=self.mass_matrix(),
                      Binv=np.eye(self.n) / self.beta)
        return values

    @functools.cached_property
    def _values(self) -> Dict[str, float]:
        """The values of every name the expression may use (read-only)."""
        return dict(self.values, m=self.m, alpha=self.alpha, beta=self.beta)

    def force_numpy(self, x: np.ndarray) -> np.ndarray:
        return self.expression.numpy(np.asarray(x, dtype=float), self._values)

    def kinks(self, x: np.ndarray) -> Optional[np.ndarray]:
        """(points, kinks): the arguments of the force's abs at the points `x` (points, n), whose
        sign changes are where its derivative jumps; None for a force without abs."""
        if not self.expression.kinks:
            return None
        return self.expression.kink_values(np.asarray(x, dtype=float), self._values)

    def force_branch(self, signs):
        """F(x) on one branch of its kinks (`kinks` order, a sign each): smooth across them."""
        values = self._values
        return lambda x: self.expression.branch(np.asarray(x, dtype=float), values, signs)

    def force_jacobian_numpy(self, x: np.ndarray) -> np.ndarray:
        return self.expression.jacobian(np.asarray(x, dtype=float), self._values)

    def parameters(self) -> Dict[str, object]:
        return {"F": self.F, "m": self.m, "alpha": self.alpha, "beta": self.beta,
                **dict(self.values)}
