"""Pure UFL of the dual formulation: the pre-dual Lagrangian and each scene's force, H and DtP map."""

import importlib

LINEAR_FORMS = ("aux_potential", "dtp", "dtp_map", "force")


def linear_forms_on_use(module: str):
    """A module `__getattr__` (PEP 562) for a linear scene's forms module: the dual forms of
    `forms.linear`, imported on first use."""

    def __getattr__(name: str):
        if name in LINEAR_FORMS:
            return getattr(importlib.import_module("fem_dual.forms.linear"), name)
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__
