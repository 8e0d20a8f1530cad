"""User input, parsed and checked: numbers, choices, paths, PETSc options, times, scenes.

Each check raises InputError with one line that names the bad value (exit status 2).
"""
from __future__ import annotations

import math
import numbers
import os
from collections.abc import Mapping as abc_Mapping
from pathlib import Path
from typing import Dict, Optional, Sequence, Union

import numpy as np

import fem_dual.continua.scenes  # noqa: F401 (registers the continuum scenes: beck, ...)
from fem_dual.errors import InputError
from fem_dual.scenes import Scene, get_scene
from fem_dual.scenes.base import DECIMAL, STATE_MAX, parse_number, show

__all__ = ["quoted", "whole_number", "choice", "within_state_max", "scene_of", "described",
           "output_path", "petsc_options", "tolerance_value", "parse_times", "Number", "MIN_T",
           "MAX_TIMES", "ROUNDOFF_REL"]

Number = Union[int, float, str]
MAX_TIMES = 1_000_000  # --t-eval: at most this many times
MIN_T = 1e-150  # shorter final times overflow 1/dt^2 in the forms (and subnormals lose digits)
# The estimate does not resolve errors below this fraction of the motion's scale (round-off of
# the assembled slab systems and of the recovery): it reports at least this much.
ROUNDOFF_REL = 1e-12


def quoted(value) -> str:
    """The repr of a value, on one short line (a string keeps its quotes, a list its brackets)."""
    return show(repr(value))


def whole_number(name: str, value: Number, minimum: int = 1) -> int:
    """A whole number of at least `minimum` (text: a plain decimal, "1e3" too), or InputError
    naming `name`."""
    if not isinstance(value, (str, numbers.Real)) or isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name}={quoted(value)} is not a whole number")
    text = str(value).strip()
    if isinstance(value, str) and not DECIMAL.fullmatch(text):
        raise InputError(f"{name}={quoted(text)} is not a whole number")
    try:
        as_float = float(text)
    except ValueError:
        raise InputError(f"{name}={quoted(text)} is not a whole number") from None
    if not math.isfinite(as_float) or as_float != int(as_float):
        raise InputError(f"{name}={quoted(text)} is not a whole number")
    if int(as_float) < minimum:
        raise InputError(f"{name}={quoted(text)} must be at least {minimum}")
    return int(as_float)


def choice(name: str, value, choices: Sequence[str]) -> str:
    """`value` if it is one of `choices` (strings), else InputError naming `name`."""
    if not isinstance(value, str) or value not in choices:
        raise InputError(f"{name}={quoted(value)} is not one of {', '.join(choices)}")
    return value


def within_state_max(what: str, values: np.ndarray, advice: str) -> None:
    """InputError when an entry of `values` (the start state, the force there) exceeds
    STATE_MAX, where the dual action's squares overflow (it ended as a Newton failure with an
    infinite residual, exit 3)."""
    size = float(np.abs(values).max(initial=0.0))
    if size > STATE_MAX:
        raise InputError(f"{what}: an entry of size {size:.3g} is beyond {STATE_MAX:g}, where "
                         f"the dual action's squares overflow; {advice}")


def scene_of(scene, params) -> Scene:
    """The validated scene of `scene`: a name (with `params`), a Scene class (with `params`) or a
    Scene object (without), which is validated like one built from its name."""
    if isinstance(scene, str):
        return get_scene(scene).from_params(params)
    if isinstance(scene, type) and issubclass(scene, Scene):
        return scene.from_params(params)
    if isinstance(scene, Scene):
        if params is not None and (not isinstance(params, abc_Mapping) or len(params)):
            raise InputError("give parameters with the scene name, not with a Scene object")
        return scene.checked()
    raise InputError(f"scene must be a scene name or a Scene object, not {described(scene)}")


def described(value) -> str:
    """A value named by what it is: None, or its type and short repr."""
    return "None" if value is None else f"{type(value).__name__} {quoted(value)}"


def output_path(out) -> Optional[Path]:
    if out is None:
        return None
    if (not isinstance(out, (str, os.PathLike)) or isinstance(out, bytes)
            or isinstance(os.fspath(out), bytes)):
        raise InputError(f"out must be a path, not {described(out)}")
    text = os.fspath(out)
    if not text.strip() or "\0" in text:
        raise InputError(f"out must be a path, not {quoted(text)}")
    return Path(text)


def petsc_options(petsc) -> Dict[str, str]:
    """PETSc options as NAME -> text; values strings, or numbers and booleans spelt for PETSc."""
    if petsc is None:
        return {}
    if not isinstance(petsc, abc_Mapping):
        raise InputError(f"petsc must be a mapping of option names to values, not "
                         f"{type(petsc).__name__}")
    options = {}
    for key, value in petsc.items():
        if not isinstance(key, str):
            raise InputError(f"petsc: option name {quoted(key)} is not a string")
        key = key.lstrip("-")
        if not key or any(ch.isspace() for ch in key):
            raise InputError(f"PETSc option {key!r} is not an option name")
        if isinstance(value, (bool, np.bool_)):
            value = "true" if value else "false"
        elif isinstance(value, (int, np.integer)):
            value = str(int(value))
        elif isinstance(value, (float, np.floating)):
            if not math.isfinite(value):
                raise InputError(f"petsc: option {key}={value!r} is not finite")
            value = repr(float(value))
        elif not isinstance(value, str):
            raise InputError(f"petsc: option {key} has the value {described(value)}; give a "
                             "string ('' for a flag), a number or a boolean")
        options[key] = value
    return options


def tolerance_value(name: str, value: Number) -> float:
    """A tolerance: finite, positive and below 1; a relative one no finer than the error
    estimate resolves (ROUNDOFF_REL of the motion's scale)."""
    tol = parse_number(name, value)
    if not 0.0 < tol < 1.0:
        raise InputError(f"{name}={value!r} must lie between 0 and 1 (exclusive)")
    if name == "rtol" and tol < ROUNDOFF_REL:
        raise InputError(f"rtol={value!r} is below what the error estimate resolves "
                         f"({ROUNDOFF_REL:g} of the motion's scale)")
    return tol


def parse_times(text: "str | Sequence[float]", T: float) -> np.ndarray:
    """Times in [0, T] from "t1,t2,..." or "START:STOP:COUNT" (COUNT equispaced, both ends
    included), or a sequence of numbers; InputError naming the bad piece."""
    if isinstance(text, str) and ":" in text:
        parts = text.split(":")
        if len(parts) != 3:
            raise InputError(f"t-eval={text!r} is not START:STOP:COUNT")
        start, stop = parse_number("t-eval start", parts[0]), parse_number("t-eval stop", parts[1])
        count = whole_number("t-eval count", parts[2])
        if count > MAX_TIMES:
            raise InputError(f"t-eval count={count} is too large (at most {MAX_TIMES})")
        times = np.linspace(start, stop, count)
    else:
        if isinstance(text, (abc_Mapping, set, frozenset, bytes, bool, np.bool_)):
            raise InputError(f"t-eval={quoted(text)} is not a list of times")
        items = (text.split(",") if isinstance(text, str)
                 else list(np.ravel(np.asarray(text, dtype=object))))
        if not items:
            raise InputError("t-eval has no times")
        if len(items) > MAX_TIMES:
            raise InputError(f"t-eval has {len(items)} times (at most {MAX_TIMES})")
        times = np.array([parse_number("t-eval", item) for item in items])
    bad = times[(times < 0) | (times > T)]
    if len(bad):
        raise InputError(f"t-eval time {bad[0]!r} lies outside [0, T={T:g}]")
    return times
