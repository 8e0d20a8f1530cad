"""The registry of scenes by name."""
from __future__ import annotations

from typing import Dict, Type

from fem_dual.errors import InputError
from fem_dual.scenes.base import Scene
from fem_dual.scenes.curl import (Curl2D, Curl2DLifted, Curl2DUFL, Curl3D, Curl3DUFL,
                                  ForceScene)
from fem_dual.scenes.column import Column
from fem_dual.scenes.linear import GeneralLinear, LinearScene
from fem_dual.scenes.ziegler import Ziegler

__all__ = ["SCENES", "get_scene", "register", "Scene", "ForceScene", "LinearScene"]

SCENES: Dict[str, Type[Scene]] = {}


def register(cls: Type[Scene]) -> Type[Scene]:
    """Add a scene class to the registry (usable as a decorator)."""
    SCENES[cls.name] = cls
    return cls


for _cls in (Ziegler, Column, GeneralLinear, Curl3D, Curl2D, Curl2DLifted, Curl3DUFL, Curl2DUFL):
    register(_cls)


def get_scene(name: str) -> Type[Scene]:
    """The scene class called `name`, or InputError listing the known ones."""
    try:
        return SCENES[name]
    except KeyError:
        raise InputError(f"unknown scene {name!r} (known: {', '.join(SCENES)})") from None
