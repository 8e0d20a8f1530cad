"""A scaled column with joint dampers (damping that is not modal), from its lowest mode, in modal
and in physical coordinates: the error against the reference beside the run's own estimate.

    .venv/bin/python benchmarks/damped_column.py LINKS P T SLABS D
    .venv/bin/python benchmarks/damped_column.py 40 9.5 2.5 20 1e-3     # about 60 s

Prints one line per coordinate system: status, slabs, max error (x and v, absolute), the
estimate, their ratio (below 1: the estimate holds) and the run time.
"""
import dataclasses
import sys

import numpy as np

from fem_dual import RunConfig, SolveError, run
from fem_dual.scenes.column import lowest_mode, scaled_column


def main(argv) -> int:
    links, P, T, slabs, d = int(argv[0]), float(argv[1]), float(argv[2]), int(argv[3]), \
        float(argv[4])
    scene = dataclasses.replace(scaled_column(links, P), d=d)
    for coordinates in ("modal", "physical"):
        config = RunConfig.create(scene, x0=lowest_mode(scene), v0=np.zeros(links), T=T,
                                  slabs=slabs, cells=4, degree=4, coordinates=coordinates)
        try:
            r = run(config)
        except SolveError as exc:
            print(f"{coordinates}: refused (exit 3): {str(exc)[:120]}")
            continue
        error = max(r.error["x_max"], r.error["v_max"])
        print(f"{coordinates}: {r.status} slabs={len(r.slab_lengths)} error={error:.3g} "
              f"estimate={r.error_estimate:.3g} ratio={error / r.error_estimate:.2f} "
              f"time={r.timings['total_s']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
