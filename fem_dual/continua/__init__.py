"""Continua by the method of lines: spatial operators M, K, D on a DOLFINx mesh (free dofs of
homogeneous Dirichlet conditions), built-in continua (Beck's column, non-symmetric Cauchy
elasticity) and the eigenvalue checks of their spectra."""
from fem_dual.continua.system import DENSE_LIMIT, SpatialSystem, compile_form

__all__ = ["SpatialSystem", "DENSE_LIMIT", "compile_form"]
