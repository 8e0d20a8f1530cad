"""`fem-dual bench`, `flutter` and `stress`: the analyses a user runs beside `run`."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, List

from fem_dual.cli.streams import json_out, print0
from fem_dual.errors import InputError

if TYPE_CHECKING:
    from mpi4py import MPI

__all__ = ["bench", "flutter", "stress"]


def _int_list(name: str, text: str) -> List[int]:
    from fem_dual.inputs import whole_number

    return [whole_number(name, item) for item in text.split(",")]


def bench(args, params, comm: MPI.Comm) -> int:
    from fem_dual.analysis import bench as bm
    from fem_dual.config import RunConfig
    from fem_dual.output import check_output_dir_on_root

    slabs = _int_list("slabs", args.slabs)
    base = RunConfig.create(args.scene, params, T=args.T, slabs=slabs[0], x0=args.x0,
                            v0=args.v0, base=args.base, coordinates=args.coordinates)
    degrees, cells = _int_list("degrees", args.degrees), _int_list("cells", args.cells)
    repeats = _int_list("repeats", args.repeats)
    if len(repeats) != 1 or repeats[0] > 100:
        raise InputError(f"repeats={args.repeats!r} must be one whole number from 1 to 100")
    repeats = repeats[0]
    for degree in degrees:  # every configuration is valid before anything runs
        for n in cells:
            for k in slabs:
                RunConfig.create(base.scene, T=base.T, cells=n, degree=degree, slabs=k,
                                 x0=base.x0, v0=base.v0)
    rtols = [RunConfig.create(base.scene, T=base.T, rtol=item, x0=base.x0, v0=base.v0).rtol
             for item in args.rtols.split(",") if args.rtols.strip()]
    out = check_output_dir_on_root(comm, args.out)
    skipped: List[str] = []
    rows = bm.bench(base, degrees, cells, repeats=repeats, comm=comm, slabs=slabs,
                    skipped=skipped, rtols=rtols)
    for line in skipped:
        print0(comm, f"fem-dual bench: left out {line}", file=sys.stderr)
    if comm.rank == 0:
        bm.write_csv(rows, out / "bench.csv")
        bm.plot(rows, out / "bench.png", f"{args.scene}, T = {base.T:g}")
        if args.json:
            print(json.dumps({"rows": rows}, allow_nan=False), file=json_out(), flush=True)
        else:
            print(bm.table(rows))
            peers = [m for m in ("DOP853", "DOP853-f", "Radau", "LSODA", "expm")
                     if any(r["method"] == m for r in rows)]
            for peer in peers:
                for target in (1e-4, 1e-6, 1e-8, 1e-10):  # (the speed issue's range: to 1e-10)
                    ratio = bm.ratio_at(rows, target, peer)
                    text = "not reached by both" if ratio is None else f"{ratio:.2f}"
                    print(f"wall-time ratio fem-dual / {peer} at max error <= {target:g}: "
                          f"{text}")
            for target in (1e-4, 1e-6, 1e-8, 1e-10):
                best = bm.ratio_same_times(rows, target)
                if best is not None:
                    what = (f"{best['slabs']} slabs" if best["method"] == "fem-dual"
                            else f"rtol {best['rtol']:g}")
                    print(f"wall-time ratio fem-dual / expm at the same output times, max error "
                          f"<= {target:g}: {best['ratio']:.2f} (p={best['degree']}, {what} x "
                          f"{best['cells']} cells, {best['samples']} times, "
                          f"{best['wall_s'] * 1e3:.3g} ms vs {best['expm_wall_s'] * 1e3:.3g} ms)")
            print(f"wrote {out / 'bench.csv'}, {out / 'bench.png'}")
    return 0


def flutter(args, params, comm: MPI.Comm) -> int:
    from fem_dual.config import RunConfig
    from fem_dual.analysis.flutter import flutter
    import fem_dual.continua.scenes  # noqa: F401 (registers beck)
    from fem_dual.scenes import SCENES

    scene = SCENES.get(args.scene)
    continuum = bool(getattr(scene, "continuum", False))
    if continuum:  # the discretisation whose eigenvalue load is within 1e-4 of Beck's
        given = [f"--param {name}" for name in ("P",) if name in params] + [
            f"--{name}" for name in ("x0", "u0", "v0") if getattr(args, name, None) is not None]
        if given:
            raise InputError(f"flutter {args.scene}: {', '.join(given)} not taken: the search "
                             "sets the load and starts in the two slowest modes at each load")
        params = {**getattr(scene, "flutter_params", {}), **params}
    elif args.out is not None:
        raise InputError("flutter --out: the mode shapes and the flutter motion are written for "
                         "continuum scenes (beck)")
    two = scene is not None and not continuum and scene.n == 2
    x0 = args.x0 if args.x0 is not None else ("0.1,-0.05" if two else None)
    v0 = args.v0 if args.v0 is not None else ("0.02,0.03" if two else None)
    base = RunConfig.create(args.scene, params, T=args.T, cells=args.cells, degree=args.degree,
                            slabs=args.slabs, x0=x0, v0=v0)
    if continuum:
        from fem_dual.analysis.continuum_flutter import continuum_flutter

        found = continuum_flutter(base, comm, None if args.out is None else Path(args.out))
    else:
        found = flutter(base, comm)
    if args.json:
        print0(comm, json.dumps(found, allow_nan=False), file=json_out(), flush=True)
    else:
        gap = abs(found["dual"] - found["eigen"]) / found["eigen"]
        print0(comm, f"critical load of {args.scene}: eigenvalues {found['eigen']:.6f} "
                     f"({found['eigen_s']:.3f} s), dual simulations {found['dual']:.6f} "
                     f"({found['dual_s']:.2f} s); relative gap {gap:.2e}")
        for path in found.get("files", []):
            print0(comm, f"wrote {path}")
    return 0


def stress(args, comm: MPI.Comm) -> int:
    """Exit 0 when every case behaved as it must, 1 when one FAILed."""
    import dataclasses

    from fem_dual.analysis import stress as st

    if args.list:
        print0(comm, "\n".join(f"{c.name}{' (slow)' if c.slow else ''}: {c.expected}"
                                for c in st.CASES))
        return 0
    rows = st.stress(args.case, slow=args.slow, comm=comm)
    passed = all(r.status != "FAIL" for r in rows)
    if args.json:
        print0(comm, json.dumps({"rows": [dataclasses.asdict(r) for r in rows],
                                 "passed": passed}, allow_nan=False), file=json_out(),
                flush=True)
    else:
        print0(comm, st.table(rows))
        print0(comm, f"{sum(r.status != 'FAIL' for r in rows)} of {len(rows)} cases behaved as "
                     "they must" + ("" if passed else "; FAIL marks the others"))
    return 0 if passed else 1
