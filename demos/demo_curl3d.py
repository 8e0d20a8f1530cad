# # A three-dimensional curl force through its dual action
#
# The force $F(x) = -(yz, 2xz, xy)$ (reference, section 3.2) has
# $\operatorname{curl} F \neq 0$: no potential exists. With
# $H = \tfrac{\alpha}{2}|x - \bar x|^2 + \tfrac{\beta}{2}|v - \bar v|^2$ the dual-to-primal map is
# explicit,
#
# $$ \hat v = \bar v - (m\dot\eta + \xi)/\beta, \qquad
#    A(\eta)\,\hat x = \alpha\bar x - \dot\xi, \quad
#    A(\eta) = \begin{bmatrix}\alpha & -\eta_z & -2\eta_y\\ -\eta_z & \alpha & -\eta_x\\
#    -2\eta_y & -\eta_x & \alpha\end{bmatrix}, $$
#
# but nonlinear in $\eta$, so the dual action is solved by Newton (PETSc SNES) on each time slab,
# from the zero dual state, with the exact Jacobian from UFL. The reference is scipy's DOP853 at
# rtol = atol = 1e-13.
#
# Run: `python3 demos/demo_curl3d.py` or `mpirun -n 2 python3 demos/demo_curl3d.py`.

# +
from mpi4py import MPI

from fem_dual import RunConfig, SolveError, run
from fem_dual.mpi import print0

comm = MPI.COMM_WORLD
# -

# ## The default problem: $x_0 = (0.3, 0.2, 0.1)$, $v_0 = 0$, $T = 2$

# +
result = run(RunConfig.create("curl3d", T=2.0, cells=80, degree=3, out="out_curl3d"), comm)
print0(comm, f"curl3d, T = 2, one slab of 80 cells, degree 3: x(T) = {result.final['x']}")
print0(comm, f"  max error against DOP853: x {result.error['x_max']:.2e}, "
             f"v {result.error['v_max']:.2e}")
print0(comm, f"  Newton iterations per slab {result.solver['newton_iterations']}, "
             f"final residual {result.solver['residual_norms'][-1]:.1e}")
print0(comm, f"  run time {result.timings['total_s']:.2f} s "
             f"(compile {result.timings['compile_s']:.2f} s)")
print0(comm, "  wrote " + ", ".join(result.output_files))
# -

# ## Newton's quadratic convergence
#
# Residual norms of the first slab: each is roughly the square of the one before.

# +
history = result.solver["residual_histories"][0]
print0(comm, "  residuals: " + "  ".join(f"{r:.1e}" for r in history))
# -

# ## Blow-up in finite time
#
# The solution blows up near $t \approx 9.5$. Slabs of length 0.5 follow it until Newton can no
# longer converge on a slab; the run stops there with a message naming the slab, and keeps what
# was computed before (the command line exits with status 3).

# +
try:
    run(RunConfig.create("curl3d", T=12.0, cells=20, degree=3, slabs=24), comm)
except SolveError as exc:
    done = exc.partial
    print0(comm, f"  stopped as expected: {exc}")
    print0(comm, f"  kept {len(done.slab_lengths)} slabs up to t = {done.t[-1]:g}, "
                 f"max error there {done.error['x_max']:.2e}")
# -
