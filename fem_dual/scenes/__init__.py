"""The registry of scenes by name."""
from __future__ import annotations

from typing import Dict, List, Type

from fem_dual.errors import InputError
from fem_dual.scenes.base import Scene, show
from fem_dual.scenes.curl import (Curl2D, Curl2DLifted, Curl2DUFL, Curl3D, Curl3DUFL,
                                  ForceScene)
from fem_dual.scenes.column import Column
from fem_dual.scenes.force import ExpressionForce
from fem_dual.scenes.linear import GeneralLinear, LinearScene
from fem_dual.scenes.ziegler import Ziegler

__all__ = ["SCENES", "get_scene", "register", "load_scene_file", "Scene", "ForceScene", "LinearScene",
           "ExpressionForce"]

SCENES: Dict[str, Type[Scene]] = {}


def register(cls: Type[Scene]) -> Type[Scene]:
    """Add a scene class to the registry (usable as a decorator)."""
    SCENES[cls.name] = cls
    return cls


for _cls in (Ziegler, Column, GeneralLinear, Curl3D, Curl2D, Curl2DLifted, Curl3DUFL, Curl2DUFL,
             ExpressionForce):
    register(_cls)


def load_scene_file(path: str) -> List[str]:
    """Run a Python file that declares scenes (subclasses of Scene or ForceScene with a `name`)
    and register them; returns their names. The file is the user's own code, run as such; a
    file that cannot be read, fails, or declares no scene is InputError (one line)."""
    import contextlib
    import importlib.util
    import inspect
    import os
    import sys
    from pathlib import Path

    if not isinstance(path, (str, os.PathLike)) or not str(path).strip() or "\0" in str(path):
        raise InputError(f"scene-file must be a path, not {show(path)}")
    file = Path(path)
    if not file.is_file():
        raise InputError(f"scene-file={path!r} is not a file")
    if file.suffix != ".py":
        raise InputError(f"scene-file={path!r} is not a Python file (*.py)")
    spec = importlib.util.spec_from_file_location(f"fem_dual_user_{file.stem}", file)
    module = importlib.util.module_from_spec(spec)
    try:  # the file's prints go to stderr: stdout carries the JSON
        with contextlib.redirect_stdout(sys.stderr):
            spec.loader.exec_module(module)
    except (Exception, SystemExit) as exc:  # the user's code: any failure is bad input, named
        raise InputError(f"scene-file={path!r} failed: {type(exc).__name__}: {exc}") from None
    found = [cls for _, cls in inspect.getmembers(module, inspect.isclass)
             if issubclass(cls, Scene) and cls.__module__ == module.__name__
             and not inspect.isabstract(cls) and isinstance(getattr(cls, "name", None), str)]
    if not found:
        raise InputError(f"scene-file={path!r} declares no scene (a Scene or ForceScene "
                         "subclass with a name)")
    for cls in found:
        if cls.name in SCENES and SCENES[cls.name].__module__ != module.__name__:
            raise InputError(f"scene-file={path!r}: scene {cls.name!r} exists already")
        register(cls)
    return [cls.name for cls in found]


def get_scene(name: str) -> Type[Scene]:
    """The scene class called `name`, or InputError listing the known ones."""
    if not isinstance(name, str):
        raise InputError(f"scene must be a scene name (known: {', '.join(SCENES)}), not "
                         f"{show(name)}")
    try:
        return SCENES[name]
    except KeyError:
        raise InputError(f"unknown scene {name!r} (known: {', '.join(SCENES)})") from None
