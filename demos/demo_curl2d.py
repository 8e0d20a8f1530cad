# # A two-dimensional curl force: implicit, lifted and user-defined dual maps
#
# For $F(x, y) = -k(xy^2, x^3)$ (reference, section 3.1) stationarity of the pre-dual Lagrangian in
# the position is the implicit system $G(\hat x) = 0$,
#
# $$ G(x, y) = \begin{bmatrix} \alpha(x - \bar x) + \dot\xi_x - k\eta_x y^2 - 3k\eta_y x^2 \\
#    \alpha(y - \bar y) + \dot\xi_y - 2k\eta_x xy \end{bmatrix}. $$
#
# fem-dual solves it pointwise at the quadrature points by a local Newton and enters the action with
# the Newton-linearised map $\hat x = X - G_x(X)^{-1}G(X; \xi, \eta, \dot\xi)$: equal to $X$ where
# $G = 0$, with the exact derivative, so the UFL Jacobian is the exact second variation of the
# reduced action and the global Newton iteration converges quadratically. Three declarations of the
# same motion are compared:
#
# - `curl2d`: $G$ written by hand, as in the reference;
# - `curl2d-ufl`: only $F$ and $H$ written, $G$ and $DF$ derived by UFL (how a user adds a force);
# - `curl2d-lifted`: the quadratic lifting $r = y^2$, $s = x^2$ with multipliers $\lambda, \mu$,
#   whose augmented DtP map is explicit.
#
# Run: `python3 demos/demo_curl2d.py` or `mpirun -n 2 python3 demos/demo_curl2d.py`.

# +
import numpy as np
from mpi4py import MPI

from fem_dual import RunConfig, run
from fem_dual.mpi import print0

comm = MPI.COMM_WORLD
# -

# ## $x_0 = (1, 1)$, $v_0 = 0$, $T = 2$ in 4 slabs of 40 cells, degree 3

# +
results = {}
for scene in ("curl2d", "curl2d-ufl", "curl2d-lifted"):
    out = "out_curl2d" if scene == "curl2d" else None
    r = run(RunConfig.create(scene, T=2.0, cells=40, degree=3, slabs=4, out=out), comm)
    results[scene] = r
    print0(comm, f"{scene:14s} x(T) = {np.array2string(r.x[-1], precision=10)}  "
                 f"max error against DOP853 x {r.error['x_max']:.2e} v {r.error['v_max']:.2e}  "
                 f"Newton its {r.solver['newton_iterations']}  {r.timings['total_s']:.2f} s")
gap_ufl = np.abs(results["curl2d"].x - results["curl2d-ufl"].x).max()
gap_lift = np.abs(results["curl2d"].x - results["curl2d-lifted"].x).max()
print0(comm, f"  hand-derived vs UFL-derived G: {gap_ufl:.1e}; vs lifted: {gap_lift:.1e}")
print0(comm, "  wrote " + ", ".join(results["curl2d"].output_files))
# -
