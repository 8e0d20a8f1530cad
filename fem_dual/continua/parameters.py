"""The check every continuum's parameters share: finite numbers, whole sizes, named choices."""
from __future__ import annotations

import math
from dataclasses import fields
from typing import Mapping, Sequence

import numpy as np

from fem_dual.errors import InputError

__all__ = ["check_fields"]


def check_fields(params, model: str, whole: Sequence[str] = ("elements", "degree"),
                 choices: Mapping[str, Sequence[str]] = {}) -> None:
    """InputError naming the first field of the dataclass `params` (of the continuum `model`)
    that is not a finite number, a whole number >= 1 (the fields `whole`) or one of its
    `choices`."""
    for f in fields(params):
        value = getattr(params, f.name)
        if f.name in choices:
            if value not in choices[f.name]:
                raise InputError(f"{model}: {f.name} must be one of {tuple(choices[f.name])}, "
                                 f"got {value!r}")
        elif f.name in whole:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InputError(f"{model}: {f.name} must be a whole number >= 1, got {value!r}")
        elif (isinstance(value, bool) or not isinstance(value, (int, float))
              or not math.isfinite(value)):
            raise InputError(f"{model}: {f.name} must be a finite number, got {value!r}")
