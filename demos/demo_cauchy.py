# # Cauchy elasticity: an elastic square without strain energy, in time by the dual principle
#
# A Cauchy elastic material has a stress that is a function of the strain, but its elasticity
# tensor lacks the major symmetry $C_{ijkl} = C_{klij}$: there is no strain energy, and closed
# strain cycles do net work. In plane strain, in Voigt order,
# $C = [[\lambda+2\mu, \lambda+\delta, 0], [\lambda-\delta, \lambda+2\mu, 0], [0, 0, \mu]]$.
# DOLFINx assembles the mass $M$ and the non-symmetric stiffness $K$ of the unit square clamped
# on its boundary; fem-dual integrates $M\ddot u + K u = 0$ in time through the dual action,
# with an error estimate.
#
# Run it with `python3 demos/demo_cauchy.py` or `mpirun -n 2 python3 demos/demo_cauchy.py`.
# The dense part runs whole on every rank; the sparse part is partitioned by DOLFINx.

# +
import numpy as np
import scipy.sparse as sps
from mpi4py import MPI
from scipy.sparse.linalg import expm_multiply

from fem_dual import RunConfig, run
from fem_dual.continua.cauchy import real_spectrum_guaranteed
from fem_dual.mpi import print0

comm = MPI.COMM_WORLD
lam, mu, delta = 1.0, 1.0, 1.0
# -

# ## The work of a closed strain cycle
#
# Along a circle of radius $r$ in the $\varepsilon_{11}$–$\varepsilon_{22}$ plane the stress
# does the work $\oint \sigma : d\varepsilon = -2\delta\,\pi r^2$: zero only for the symmetric
# tensor ($\delta = 0$), so no energy function exists.

# +
C = np.array([[lam + 2 * mu, lam + delta], [lam - delta, lam + 2 * mu]])  # the normal block
r, steps = 1e-3, 20000
phase = np.linspace(0.0, 2 * np.pi, steps + 1)
strain = r * np.stack([np.cos(phase), np.sin(phase)], axis=1)
stress = strain @ C.T
middle = 0.5 * (stress[1:] + stress[:-1])
work = float(np.sum(middle * np.diff(strain, axis=0)))
print0(comm, f"work of a strain cycle of radius {r:g}: {work:.6e} (-2 delta pi r^2 = "
             f"{-2 * delta * np.pi * r ** 2:.6e})")
print0(comm, f"real spectrum guaranteed (|delta| <= lam + mu): "
             f"{real_spectrum_guaranteed(lam, mu, delta)}")
# -

# ## Motion on the dense path, against the exact motion
#
# Eight P1 elements a side (98 free dofs): small enough for the eigen-decomposition of the
# semi-discrete system, which fem-dual computes as an independent reference. The start is
# $u_0 = 0.01(\sin\pi x \sin\pi y, \sin\pi x \sin 2\pi y)$ at rest.

# +
params = {"lam": str(lam), "mu": str(mu), "delta": str(delta)}
config = RunConfig.create("cauchy2d", params, T=1.0, rtol=1e-6)
result = run(config, comm)
err, est = result.error, result.estimate
print0(comm, f"cauchy2d, delta = {delta:g}, T = 1, rtol 1e-6: {len(result.slab_lengths)} slabs, "
             f"{result.timings['total_s']:.2f} s")
print0(comm, f"  estimated error (no reference needed): u {est['x_max']:.2e}, "
             f"u' {est['v_max']:.2e}")
print0(comm, f"  error against the eigen-decomposition of the semi-discrete system: "
             f"u {err['x_max']:.2e}, u' {err['v_max']:.2e}")
# -

# ## A symmetric tensor conserves the energy
#
# With $\delta = 0$ the stiffness is symmetric and $\tfrac12 \dot u^T M \dot u + \tfrac12 u^T K
# u$ is conserved by the motion; the dual solution keeps it to the tolerance.

# +
config = RunConfig.create("cauchy2d", {**params, "delta": "0"}, T=2.0, rtol=1e-8)
result = run(config, comm)
energy = config.scene.energy
change = energy(result.final["x"], result.final["v"]) / energy(result.x0, result.v0) - 1
print0(comm, f"  delta = 0: relative change of the energy over T = 2: {change:.1e}")
# -

# ## The sparse, distributed path
#
# Twenty elements a side (722 free dofs) is beyond the dense limit: each slab is one CG solve
# of the space-time system, distributed by DOLFINx's partition of the mesh, with no n x n
# matrix. `out_cauchy/cauchy2d_fields.xdmf` holds the displacement and the velocity at every
# time vertex for ParaView; `cauchy2d_system.npz` holds M, K, D as CSR parts with the start
# vectors, from which anyone can compute the exact motion (here by `expm_multiply`).

# +
config = RunConfig.create("cauchy2d", {**params, "elements": "20"}, T=0.05, slabs=2, cells=4,
                          degree=3, out="out_cauchy")
result = run(config, comm)
print0(comm, f"cauchy2d, 20 elements a side, {result.dofs_per_slab} space-time unknowns a slab, "
             f"{comm.size} rank(s): CG iterations {result.solver['ksp_iterations']}, "
             f"{result.timings['total_s']:.2f} s")
if comm.rank == 0:
    arrays = np.load("out_cauchy/cauchy2d_system.npz")

    def csr(name):
        return sps.csr_matrix((arrays[f"{name}_data"], arrays[f"{name}_indices"],
                               arrays[f"{name}_indptr"]), shape=tuple(arrays[f"{name}_shape"]))

    Ms, Ks = csr("M").tocsc(), csr("K").tocsc()
    n = Ms.shape[0]
    A = sps.bmat([[None, sps.identity(n)], [-sps.linalg.spsolve(Ms, Ks), None]], format="csr")
    z = expm_multiply(A * config.T, np.concatenate([arrays["u0"], arrays["v0"]]))
    print(f"  estimated error {result.error_estimate:.2e}; error against the exact motion of "
          f"the exported system: u {np.abs(result.final['x'] - z[:n]).max():.2e}, "
          f"u' {np.abs(result.final['v'] - z[n:]).max():.2e}")
print0(comm, "  wrote " + ", ".join(result.output_files))
# -
