"""Continua by the method of lines: the spatial operators M, K, D of UFL forms on the free dofs
of a DOLFINx space (:class:`SpatialSystem`), the built-in continua (Beck's column, Cauchy
elasticity without major symmetry) and the eigenvalue checks of their spectra.

Modules: ``system`` (SpatialSystem), ``dofs`` (dof layout, free dofs, gathers), ``initial``
(initial fields from expressions), ``fields`` (vertex functions for XDMF), ``beck`` and
``condense`` (Beck's column, theta condensed), ``flutter`` (eigenvalue flutter and buckling
loads), ``cauchy`` (the clamped square), ``spectrum`` (is the spectrum real).
"""
from fem_dual.continua.beck import BeckColumn, BeckParameters
from fem_dual.continua.cauchy import CauchyElasticity, CauchyParameters
from fem_dual.continua.condense import CondensedBeck, condense_rotation
from fem_dual.continua.flutter import FlutterResult, buckling_load, flutter_load, frequencies
from fem_dual.continua.spectrum import SpectrumCheck, spectrum_check
from fem_dual.continua.system import DENSE_LIMIT, SpatialSystem, compile_form

__all__ = ["SpatialSystem", "DENSE_LIMIT", "compile_form", "BeckParameters", "BeckColumn",
           "CondensedBeck", "condense_rotation", "FlutterResult", "flutter_load",
           "buckling_load", "frequencies", "CauchyParameters", "CauchyElasticity",
           "SpectrumCheck", "spectrum_check"]
