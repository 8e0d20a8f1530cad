"""The interpolation error estimate between output vertices against the true interpolation
error, on exact vertex values (the reference at the vertices), for a few forces and vertex
spacings: the max over the times of the error and of the estimate (README, "Output at any
time"). `--safety inf` gives the distance of the Hermites 7 and 5 without the contraction.

    .venv/bin/python benchmarks/dense_estimate.py [--safety 2]
"""
import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import fem_dual.integrate.dense as dense  # noqa: E402
from fem_dual.inputs import scene_of  # noqa: E402

CASES = [("force", {"F": "-100*x"}, [1.0], [0.0], 2.0),
         ("force", {"F": "-x - x**3"}, [1.5], [0.0], 10.0),
         ("force", {"F": "-x - 0.5*sin(40*x)"}, [1.0], [0.0], 5.0),
         ("curl2d", {}, None, None, 4.0), ("curl3d", {}, None, None, 6.0)]
FRACTIONS = np.array([0.1, 0.25, 0.5, 0.75, 0.9])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--safety", type=float, default=dense.GAP_SAFETY)
    dense.GAP_SAFETY = parser.parse_args().safety
    print("scene   force                       intervals  max error  max estimate  ratio")
    for name, params, x0, v0, T in CASES:
        scene = scene_of(name, params)
        x0 = np.array(x0 if x0 is not None else scene.default_x0, dtype=float)
        v0 = np.array(v0 if v0 is not None else scene.default_v0, dtype=float)
        for intervals in (4, 8, 16, 32, 64, 128):
            t = np.linspace(0, T, intervals + 1)
            X, V = scene.reference(x0, v0)(t)  # (a new flow each time: it continues in time)
            times = (t[:-1, None] + np.diff(t)[:, None] * FRACTIONS).ravel()
            xs, vs, est = dense.hermite_estimate(scene, t, X, V, times)
            xr, vr = scene.reference(x0, v0)(times)
            err = np.maximum(np.abs(xs - xr).max(axis=1), np.abs(vs - vr).max(axis=1))
            print(f"{name:7s} {params.get('F', ''):27s} {intervals:9d}  {err.max():9.2e}  "
                  f"{est.max():12.2e}  {est.max() / err.max():5.2f}")


if __name__ == "__main__":
    main()
