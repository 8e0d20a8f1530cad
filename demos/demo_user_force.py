# # Your own force: a swirl with a cubic twist, typed as text
#
# $F(x, y) = (-x - a y^3,\; a x - y)$ has $\nabla\times F = a(1 + 3y^2) \ne 0$: a curl force, with
# no potential. fem-dual takes it as text (parsed by a whitelist into UFL for the forms and numpy
# for the reference, never evaluated as Python), chooses the slab lengths for a tolerance, and
# gives the state at any time, each number with its estimated error.
#
# Run: `python3 demos/demo_user_force.py` or `mpirun -n 2 python3 demos/demo_user_force.py`.
# The same from the command line:
#
#     fem-dual run force --F "-x - a*y**3, a*x - y" --param a=0.5 --x0 1,0 --v0 0,0.5 \
#         --T 4 --rtol 1e-8 --cells 4 --degree 4 --t-eval 0:4:9 --plot out_user_force

# +
from pathlib import Path

import numpy as np
from mpi4py import MPI

from fem_dual import RunConfig, run
from fem_dual.mpi import print0
from fem_dual.plots import write_plots

comm = MPI.COMM_WORLD
config = RunConfig.create("force", {"F": "-x - a*y**3, a*x - y", "a": "0.5"}, T=4.0,
                          x0="1,0", v0="0,0.5", rtol=1e-8, cells=4, degree=4,
                          out="out_user_force")
result = run(config, comm)
# -

# ## The answer, its estimated error, and the error against DOP853 at 1e-13

# +
print0(comm, f"x(T) = {np.array2string(result.x[-1], precision=10)}   "
             f"{len(result.slab_lengths)} slabs chosen for rtol 1e-8")
print0(comm, f"estimated error {result.error_estimate:.2e}, error against the reference "
             f"{max(result.error['x_max'], result.error['v_max']):.2e}")
times = np.linspace(0.0, 4.0, 9)
x, v = result.at(times)  # Hermite of degree 7 with the force at the vertices: order 2p
print0(comm, "state at t = 0, 0.5, ..., 4:\n" + np.array2string(np.hstack([x, v]), precision=6))
# -

# ## Pictures: motion, trajectory, error against t, H_d per slab

# +
if comm.rank == 0:
    out = Path("out_user_force")
    paths = write_plots(result, out)
    (out / "motion.png").replace(out / "user_force.png")
    print(f"wrote {', '.join(str(p) for p in [out / 'user_force.png'] + paths[1:])} and "
          f"{', '.join(result.output_files)}")
# -
