"""The named choices of a run that are validated before anything heavy is loaded (the command
line answers bad input without importing DOLFINx or PETSc)."""

__all__ = ["BASES", "RECOVERIES"]

# the base state of H on a slab: see fem_dual.slab.problem
BASES = ("start", "zero", "predictor", "rk4")
# how the primal state is read from the dual solution: see fem_dual.slab.recovery
RECOVERIES = ("momentum", "dtp")
