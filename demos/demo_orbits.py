# # Periodic orbits from the dual principle: a curl-force family and Ziegler's modes up to flutter
#
# `fem-dual orbit` makes the dual fields periodic and the period an unknown of the dual action
# (fem_dual.analysis.orbit). Two families, each followed by continuation from the orbit before:
#
# 1. The non-conservative curl force $F = (-x - a y^2,\; -2y - a x^2)$ (curl $= a(y - x)$),
#    the orbit born from the $x$-mode, as the curl strength $a$ grows from 0 to 1: its period,
#    its Floquet multipliers (stability) and the error estimate of each orbit.
# 2. Ziegler's column: the period of its slow mode as the follower load $P$ grows towards the
#    flutter load $7/2 - \sqrt 2 \approx 2.086$, against $2\pi/\omega$ from the eigenvalues;
#    past it there is no orbit, and the continuation stops there (exit 3 on the command line).
#
# Run: `python3 demos/demo_orbits.py` or `mpirun -n 2 python3 demos/demo_orbits.py` (rank 0
# solves: an orbit's time mesh is small).

# +
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from mpi4py import MPI

from fem_dual.inputs import scene_of
from fem_dual.analysis.orbit import orbit_family

comm = MPI.COMM_WORLD
out = Path("out_orbits")
# -

# ## 1. A family of a curl force


# +
def curl_family():
    force = {"F": "-x - a*y**2, -2*y - a*x**2", "a": 0.0}
    scene = scene_of("force", force)
    return orbit_family(scene, force, np.array([0.5, 0.0]), np.zeros(2), 6.3, degree=4,
                        cells=48, continuation=("a", np.linspace(0.0, 1.0, 11)))


def ziegler_family():
    scene = scene_of("ziegler", {"P": 0.0})
    lam, V = sla.eig(scene.stiffness_matrix(), scene.mass_matrix())
    slow = V.real[:, int(np.argmin(lam.real))]
    return orbit_family(scene, {}, 0.1 * slow / np.abs(slow).max(), np.zeros(2),
                        2 * np.pi / np.sqrt(lam.real.min()), degree=4, cells=48,
                        continuation=("P", np.linspace(0.0, 2.2, 12)), with_estimate=False)


curl = ziegler = None
if comm.rank == 0:
    curl = curl_family()
    for step in curl["continuation"]:
        moduli = sorted(abs(complex(*m)) for m in step["nontrivial_multipliers"])
        print(f"a = {step['a']:4.2f}: period {step['period']:.12f}, estimated error "
              f"{step['estimate']['period']:.1e}, closure {step['closure']:.1e}, nontrivial "
              f"multipliers {complex(*step['nontrivial_multipliers'][0]):.6f}, max modulus "
              f"{moduli[-1]:.6f} ({'stable' if moduli[-1] < 1 + 1e-6 else 'unstable'})")
    print(f"curl family: status {curl['status']}")
# -

# ## 2. Ziegler's slow mode towards flutter

# +
if comm.rank == 0:
    ziegler = ziegler_family()
    for step in ziegler["continuation"]:
        scene = scene_of("ziegler", {"P": step["P"]})
        lam = sla.eigvals(scene.stiffness_matrix(), scene.mass_matrix())
        exact = 2 * np.pi / np.sqrt(lam.real.min())
        line = f"P = {step['P']:4.2f}: period {step['period']:.12f}"
        if step["status"] == "ok":
            line += f", error against 2 pi/omega {abs(step['period'] - exact):.1e}"
        print(line)
    print(f"Ziegler: {ziegler['status']}: {ziegler.get('message', '')[:160]}")
# -

# ## Pictures

# +
if comm.rank == 0:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(exist_ok=True)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    steps = curl["continuation"]
    a = [s["a"] for s in steps]
    axes[0].plot(np.array(curl["x"])[:, 0], np.array(curl["x"])[:, 1], "k-")
    axes[0].set(title=f"curl force, a = {a[-1]:g}: the orbit", xlabel="x", ylabel="y")
    moduli = np.array([sorted(abs(complex(*m)) for m in s["nontrivial_multipliers"])
                       for s in steps])
    angles = [abs(np.angle(complex(*s["nontrivial_multipliers"][0]))) for s in steps]
    axes[1].plot(a, [s["period"] for s in steps], "o-", label="period")
    twin = axes[1].twinx()
    twin.plot(a, angles, "s--r", label="multiplier angle")
    axes[1].set(title="curl family: period and stability", xlabel="a", ylabel="period")
    twin.set_ylabel("angle of the nontrivial multipliers (|.| = 1: stable)")
    z = ziegler["continuation"]
    ok = [s for s in z if s["status"] == "ok"]
    axes[2].plot([s["P"] for s in ok], [s["period"] for s in ok], "o", label="fem-dual orbit")
    P = np.linspace(0.0, 2.08, 200)
    exact = [2 * np.pi / np.sqrt(sla.eigvals(
        scene_of("ziegler", {"P": p}).stiffness_matrix(),
        scene_of("ziegler", {"P": p}).mass_matrix()).real.min()) for p in P]
    axes[2].plot(P, exact, "-", label="2 pi / omega (eigenvalues)")
    axes[2].axvline(3.5 - np.sqrt(2), color="grey", ls=":", label="flutter load")
    axes[2].set(title="Ziegler: slow-mode period", xlabel="P", ylabel="period")
    axes[2].legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(out / "orbits.png", dpi=110)
    print(f"wrote {out / 'orbits.png'}")
# -
