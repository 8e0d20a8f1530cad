# # Beck's column: a continuum under a follower load, in time by the dual principle
#
# A cantilever of bending stiffness $EI$ and mass per length $\rho A$ carries at its free tip a
# compressive load $P$ that turns with the tangent of the deflected axis. That follower load
# has no potential. DOLFINx assembles the Timoshenko beam on an interval mesh: the mass $M$, the
# stiffness $K(P) = K_{el} - P K_g + P K_f$ (non-symmetric through the follower part $K_f$). The
# rotation carries no mass, so it follows the deflection and is condensed. fem-dual integrates
# $M\ddot w + K(P) w = 0$ in time through the dual action, slab by slab, with an error estimate.
#
# Run it with `python3 demos/demo_beck.py` or `mpirun -n 2 python3 demos/demo_beck.py`. The
# beam is one-dimensional, so every rank holds it whole.

# +
from pathlib import Path

from mpi4py import MPI

from fem_dual import RunConfig, run
from fem_dual.continua import flutter_load, frequencies
from fem_dual.continua.flutter import beck_eigenvalues
from fem_dual.analysis.continuum_flutter import continuum_flutter
from fem_dual.mpi import print0

comm = MPI.COMM_WORLD
BECK = 20.0509536190  # Beck's flutter load (Euler-Bernoulli), EI/L^2
# -

# ## Frequencies without load, and the flutter load
#
# At $P = 0$ the first two cantilever frequencies are $\beta_k^2$ with $\beta_1 L = 1.87510407$
# and $\beta_2 L = 4.69409113$. As $P$ grows the first two frequencies approach each other and
# meet: beyond that load the motion grows (flutter). The eigenvalues of the pencil, taken in
# flexibility form, give the load.

# +
scene = RunConfig.create("beck", {"P": "0", "elements": "50"}, rtol=1e-3).scene
omega = frequencies(scene.condensed, 2)
print0(comm, f"Beck's column, 50 P2 elements: omega_1 = {omega[0]:.7f} (exact 3.5160153), "
             f"omega_2 = {omega[1]:.7f} (exact 22.0344916)")
found = flutter_load(lambda P: beck_eigenvalues(scene.condensed, P), step=2.0, P_max=40.0)
print0(comm, f"  flutter load from the eigenvalues: {found.load:.7f} EI/L^2 "
             f"(Beck {BECK}, relative error {abs(found.load - BECK) / BECK:.1e}), "
             f"flutter frequency^2 {found.omega2:.4f}")
# -

# ## The flutter load from dual simulations alone
#
# At each trial load the column starts in the span of its two slowest modes and moves for
# $T = 20$; the growth rate of that motion, fitted with its uncertainty, decides whether the load
# is past flutter, and the bracket is bisected on the simulations alone (`fem-dual flutter beck`
# does this at 100 elements). `out_beck/flutter/beck_modes.xdmf` holds the two mode shapes just
# below the load, `out_beck/flutter/beck_fields.xdmf` the flutter motion just above it.

# +
coarse = RunConfig.create("beck", {"elements": "20"}, T=20.0, slabs=20, cells=16, degree=5)
found = continuum_flutter(coarse, comm, out=Path("out_beck") / "flutter")
print0(comm, f"  20 elements: flutter load from the eigenvalues {found['eigen']:.6f}, from "
             f"{found['runs']} dual simulations {found['dual']:.6f} ({found['dual_s']:.1f} s)")
# -

# ## Motion under $P = 10$ with its error estimate
#
# The start is the static deflection under a uniform load, at rest. The beam is stiff: its
# frequencies run from 5 to $1.2\cdot 10^6$. Under `--rtol` the time slabs follow the modes that
# carry more than the tolerance and drop the faster ones, which are damped, never amplified.
# What is dropped is counted once in the estimate. `out_beck/beck_fields.xdmf` holds $w$,
# $\theta$ and their velocities on the beam at every time vertex for ParaView.
# `beck_system.npz` holds $M$, $K$ and the start vectors, so that anyone can check the motion.

# +
config = RunConfig.create("beck", {"P": "10", "elements": "50"}, T=2.0, rtol=1e-3,
                          degree=6, out="out_beck")
result = run(config, comm)
err, est, tm = result.error, result.estimate, result.timings
print0(comm, f"  P = 10, T = 2, rtol 1e-3: {len(result.slab_lengths)} slabs of "
             f"{result.cells} cells, degree {result.degree}")
print0(comm, f"  estimated error (no reference needed): w {est['x_max']:.2e}, "
             f"w' {est['v_max']:.2e}")
print0(comm, f"  error against the eigen-decomposition of the semi-discrete system: "
             f"w {err['x_max']:.2e}, w' {err['v_max']:.2e}")
print0(comm, f"  tip deflection at T: {result.final['x'][-1]:.6f}; run time "
             f"{tm['total_s']:.2f} s")
print0(comm, "  wrote " + ", ".join(result.output_files))
# -

# ## Energy without load
#
# At $P = 0$ the stiffness is symmetric and $\tfrac12 \dot w^T M \dot w + \tfrac12 w^T K w$ is
# conserved. Dropped modes can only take energy away.

# +
config = RunConfig.create("beck", {"P": "0", "elements": "20"}, T=2.0, rtol=1e-3)
result = run(config, comm)
energy = config.scene.energy
change = energy(result.final["x"], result.final["v"]) / energy(result.x0, result.v0) - 1
print0(comm, f"  P = 0: relative change of the energy over T = 2: {change:.1e}; max error "
             f"{max(result.error['x_max'], result.error['v_max']):.2e}")
# -
