"""Reproduce benchmarks/column_scale.py --links 200 exactly; save M, K, x0, T, fem-dual's
x, v at all output times, and the driver's own (chained expm) reference values at those times."""
import os
WORK = os.environ.get("HP_WORK", "/tmp/hp_reference")  # scratch directory for the .npz files
os.makedirs(WORK, exist_ok=True)

import sys, json
import numpy as np
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from mpi4py import MPI
from fem_dual.reference import LinearFlow
from scipy.linalg import expm

REC = {"t": [], "x": [], "v": []}
class RecFlow(LinearFlow):
    def __call__(self, t):
        x, v = super().__call__(t)
        REC["t"].append(np.array(t)); REC["x"].append(x.copy()); REC["v"].append(v.copy())
        return x, v
pass

from fem_dual import RunConfig
from fem_dual.integrate.simulation import Simulation
from fem_dual.analysis.flutter import critical_load, eigen_rate
from column_scale import column_params

links, ratio = 200, 0.5
unloaded = RunConfig.create("column", column_params(links)).scene
P_cr = critical_load(eigen_rate(unloaded), 1e-9, first=1.0, rel_width=1e-6)
scene = RunConfig.create("column", column_params(links, ratio * P_cr)).scene
M, K = scene.mass_matrix(), scene.stiffness_matrix()
lam, U = np.linalg.eig(np.linalg.solve(M, K))
k = int(np.argmin(np.abs(lam)))
omega = float(np.sqrt(abs(lam[k].real)))
x0 = np.real(U[:, k]); x0 = 0.1 * x0 / np.abs(x0).max()
T = 10.0 * 2 * np.pi / omega
config = RunConfig.create(scene, T=T, slabs=160, cells=4, degree=4, x0=x0, v0=np.zeros(links),
                          assembly="kronecker", base="auto", coordinates="auto")
A = scene.first_order_matrix()
print("D present:", hasattr(scene, "damping_matrix") and np.abs(scene.damping_matrix()).max() if hasattr(scene, "damping_matrix") else None)
sim = Simulation.for_config(config, MPI.COMM_WORLD)
res = sim.run(config)
rt = res.t; rx, rv = scene.reference(x0, np.zeros(links))(res.t)
assert np.array_equal(rt, res.t), (rt.shape, res.t.shape)
# a direct (unchained) expm at a few times, as a second float64 reference
idx = [int(np.argmin(np.abs(res.t - f * T))) for f in (0.25, 0.5, 0.75, 1.0)]
z0 = np.concatenate([x0, np.zeros(links)])
dx = np.array([(expm(res.t[i] * A) @ z0)[:links] for i in idx])
dv = np.array([(expm(res.t[i] * A) @ z0)[links:] for i in idx])
np.savez(WORK + "/femdual.npz", M=M, K=K, A=A, x0=x0, T=T, omega=omega, lam_k=lam[k],
         t=res.t, x=res.x, v=res.v, ref_x=rx, ref_v=rv, idx=np.array(idx), direct_x=dx, direct_v=dv,
         error_estimate=res.error_estimate, lam=lam)
print(json.dumps({"T": T, "omega": omega, "P": ratio * P_cr, "nt": len(res.t), "idx": idx,
                  "t_idx": [float(res.t[i]) for i in idx], "error": res.error,
                  "error_estimate": res.error_estimate, "estimate": res.estimate,
                  "modal": config.modal, "base": config.base_state}, indent=1))
