"""The registry of scenes by name."""
from __future__ import annotations

from typing import Dict, Type

from fem_dual.errors import InputError
from fem_dual.scenes.base import Scene
from fem_dual.scenes.ziegler import Ziegler

__all__ = ["SCENES", "get_scene", "Scene"]

SCENES: Dict[str, Type[Scene]] = {cls.name: cls for cls in (Ziegler,)}


def get_scene(name: str) -> Type[Scene]:
    """The scene class called `name`, or InputError listing the known ones."""
    try:
        return SCENES[name]
    except KeyError:
        raise InputError(f"unknown scene {name!r} (known: {', '.join(SCENES)})") from None
