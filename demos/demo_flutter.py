# # Flutter of the Ziegler column found by the dual solver, and Ziegler's destabilisation paradox
#
# The follower load $P$ of the Ziegler column ($m_1 = 2m_2$, $c_1 = c_2 = c$) destabilises it by
# flutter at $P_{cr}\,l/c = 7/2 - \sqrt 2 \approx 2.086$. Adding a little damping in both joints
# ($D = d\,[[2, -1], [-1, 1]]$) does not raise this load but *lowers* it: as $d \to 0$ the damped
# critical load tends to $41/28 \approx 1.464$ (Ziegler's paradox).
#
# fem-dual finds the critical load two independent ways: (a) from the eigenvalues of the
# first-order system; (b) from dual simulations alone: for each trial $P$ the motion is solved
# through the dual action (M q'' + D q' + K q = 0 has an explicit quadratic dual action), its growth
# rate is read off the recovered motion, and $P$ is bisected on its sign.
#
# Run: `python3 demos/demo_flutter.py` or `mpirun -n 2 python3 demos/demo_flutter.py`.

# +
from pathlib import Path

import numpy as np
from mpi4py import MPI

from fem_dual import RunConfig
from fem_dual.analysis.flutter import flutter
from fem_dual.mpi import print0

comm = MPI.COMM_WORLD
settings = dict(T=40.0, slabs=40, cells=16, degree=5, x0="0.1,-0.05", v0="0.02,0.03")
# -

# ## Critical load against joint damping

# +
dampings = [0.0, 0.002, 0.01, 0.03, 0.1, 0.3]
rows = []
for d in dampings:
    base = RunConfig.create("ziegler", {"d1": d, "d2": d}, **settings)
    found = flutter(base, comm)
    rows.append((d, found["eigen"], found["dual"]))
    gap = abs(found["dual"] - found["eigen"]) / found["eigen"]
    # both searches bisect to 1e-5 of the load: a difference of 0 means the same final bracket
    said = f"relative error {gap:.1e}" if gap > 0 else "in the eigenvalue load's 1e-5 bracket"
    print0(comm, f"d = {d:<6g} P_cr: eigenvalues {found['eigen']:.5f}, dual simulations "
                 f"{found['dual']:.5f} ({said}, {found['dual_s']:.2f} s)")
print0(comm, f"undamped theory 7/2 - sqrt(2) = {3.5 - np.sqrt(2):.5f}; "
             f"vanishing-damping limit 41/28 = {41 / 28:.5f}")
# -

# ## The plot

# +
if comm.rank == 0:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path("out_flutter")
    out.mkdir(exist_ok=True)
    d, eig, dual = np.array(rows).T
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(d[1:], eig[1:], "s--", label="eigenvalues")
    ax.plot(d[1:], dual[1:], "o", label="dual simulations")
    ax.axhline(eig[0], color="gray", ls=":", label="undamped 7/2 - sqrt(2)")
    ax.axhline(41 / 28, color="k", ls="-.", lw=0.8, label="41/28")
    ax.set_xscale("log")
    ax.set_xlabel("joint damping d")
    ax.set_ylabel("critical load P l / c")
    ax.set_title("Ziegler column: destabilisation by small damping")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "flutter.png", dpi=110)
    print0(comm, f"wrote {out / 'flutter.png'}; largest relative error of the dual loads "
                 f"against the eigenvalue loads {np.max(np.abs(dual - eig) / eig):.1e}")
# -
