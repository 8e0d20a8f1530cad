"""Continua by the method of lines: the spatial operators M, K, D of UFL forms on the free dofs
of a DOLFINx space (:class:`SpatialSystem`), the built-in continua (Beck's column, Cauchy
elasticity without major symmetry) and the eigenvalue checks of their spectra.

Modules: ``system`` (SpatialSystem), ``dofs`` (dof layout, free dofs, gathers), ``initial``
(initial fields from expressions), ``fields`` (vertex functions for XDMF), ``beck`` and
``condense`` (Beck's column, theta condensed), ``flutter`` (eigenvalue flutter and buckling
loads), ``cauchy`` (the clamped square), ``spectrum`` (is the spectrum real).
"""
import importlib

_WHERE = {"BeckColumn": "beck", "BeckParameters": "beck", "CauchyElasticity": "cauchy",
          "CauchyParameters": "cauchy", "CondensedBeck": "condense",
          "condense_rotation": "condense", "FlutterResult": "flutter", "flutter_load": "flutter",
          "buckling_load": "flutter", "frequencies": "flutter", "SpectrumCheck": "spectrum",
          "spectrum_check": "spectrum", "DENSE_LIMIT": "system", "SpatialSystem": "system",
          "compile_form": "system"}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    """The names above, imported on first use: registering the continuum scenes (for the
    command line's validation) loads no DOLFINx."""
    if name not in _WHERE:
        raise AttributeError(f"module 'fem_dual.continua' has no attribute {name!r}")
    return getattr(importlib.import_module(f"fem_dual.continua.{_WHERE[name]}"), name)
