# # The Ziegler column through its dual action
#
# The linearised Ziegler column (two rigid links, point masses $m_1, m_2$, rotational springs
# $c_1, c_2$, a tangential follower load $P$ at the tip) obeys $M\ddot q + K q = 0$ with a
# non-symmetric $K$: the follower load is a curl force and no potential exists. Its initial-value
# problem is nevertheless the Euler-Lagrange system of the dual action (reference, eq.
# ZieglerDualAction)
#
# $$ S[\xi,\eta] = \int_0^T \tfrac12 |K^T\eta - \dot\xi|^2_{A^{-1}}
#    + \tfrac12 |M\dot\eta + \xi|^2_{B^{-1}}\,dt - q_0\cdot\xi(0) - M v_0\cdot\eta(0), $$
#
# with $\xi(T) = \eta(T) = 0$, and the motion is the dual-to-primal image
# $\hat q = A^{-1}(K^T\eta - \dot\xi)$, $\hat v = -B^{-1}(M\dot\eta + \xi)$ (here around the base
# state of each time slab). fem-dual discretises $(\xi, \eta)$ with Lagrange elements on a 1D
# mesh of each time slab; the action is quadratic, so each slab is one symmetric positive-definite
# linear solve.
#
# Run it with `python3 demos/demo_ziegler.py` or `mpirun -n 2 python3 demos/demo_ziegler.py`.

# +
from mpi4py import MPI

from fem_dual import RunConfig, run
from fem_dual.mpi import print0

comm = MPI.COMM_WORLD
# -

# ## One run over $T = 20$ in 10 slabs
#
# Each slab restarts from the state recovered at the end of the previous one, which is also the
# base state of $H$. Forms compile once; the matrix is assembled and factored once, since equal
# slabs share it. The output directory receives `ziegler.xdmf` (the slab mesh once, then
# $\xi, \eta, \hat q, \hat v$ and $\mathscr H_d$ at its vertices for every slab, with the physical
# time in the field `t`) and `ziegler_trajectory.xdmf` (the path in the $(\theta_1, \theta_2)$
# plane). XDMF stores vertex values only, so the P3 fields are written as their vertex values.

# +
config = RunConfig.create("ziegler", T=20.0, cells=80, degree=3, slabs=10, out="out_ziegler")
result = run(config, comm)
err, ham, tm = result.error, result.hamiltonian, result.timings
print0(comm, f"Ziegler column, P = {result.parameters['P']}, T = {result.T}: "
             f"{result.slabs} slabs x {result.cells} cells, degree {result.degree}")
print0(comm, f"  final state q(T) = {result.final['x']}, v(T) = {result.final['v']}")
print0(comm, f"  estimated error (no reference needed): q {result.estimate['x_max']:.2e}, "
             f"v {result.estimate['v_max']:.2e}")
print0(comm, f"  max error against the matrix exponential: q {err['x_max']:.2e}, "
             f"v {err['v_max']:.2e}; at T {err['final']:.2e}")
print0(comm, f"  auxiliary dual Hamiltonian: relative drift per slab {ham['drift']:.2e}")
print0(comm, f"  run time {tm['total_s']:.2f} s (compile {tm['compile_s']:.2f} s, "
             f"solve {tm['solve_s']:.3f} s)")
print0(comm, "  wrote " + ", ".join(result.output_files))
# -

# ## Observed order of convergence
#
# Evaluated with the one-sided derivative $\dot\xi$ (degree $p - 1$), $\hat q$ would converge
# like $h^p$ at the vertices. fem-dual reads the motion from the momenta of the dual Lagrangian,
# $\partial L_d/\partial\dot\xi = -\hat q$ and $\partial L_d/\partial\dot\eta = -M\hat v$, at
# both ends of every cell (the cell residuals of the action): a superconvergent flux, so the
# vertex error falls like $h^{2p}$ (`--recovery dtp` shows the $h^p$ of the DtP formula).
# The coarsest levels are the coarsest the acceptance rule lets through as asked (a coarser
# slab would be retried shorter, see "Error estimate" in the README).

# +
for degree, cells in ((2, (20, 40, 80)), (3, (10, 20, 40))):
    errors = [run(RunConfig.create("ziegler", T=20.0, cells=c, degree=degree, slabs=10), comm)
              .error["x_max"] for c in cells]
    rates = [f"{(errors[i] / errors[i + 1]):.2f}" for i in range(2)]
    print0(comm, f"  degree {degree}: errors {', '.join(f'{e:.2e}' for e in errors)}; "
                 f"error ratios on halving h: {', '.join(rates)} (2^(2p) = {4 ** degree})")
# -
