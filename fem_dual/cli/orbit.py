"""`fem-dual orbit`: a periodic orbit from the dual principle, and its continuation."""
from __future__ import annotations

import json
import sys

from fem_dual import faults
from fem_dual.cli.streams import escaped, json_out, stdout_to_stderr, world
from fem_dual.errors import InputError, SolveError

__all__ = ["orbit"]


def orbit(args, params, comm) -> int:
    """`fem-dual orbit`: rank 0 solves (an orbit's time mesh is small), the others wait for its
    exit status. Exit 0 ok, 2 bad input, 3 no orbit (the JSON says what was reached)."""
    from fem_dual.config import RunConfig
    from fem_dual.analysis.orbit_input import Energy, parse_continuation, parse_mode

    if args.F is not None:
        if args.scene != "force":
            raise InputError(f"--F gives the force of scene force, not of {args.scene}")
        params["F"] = args.F
    mode, energy = parse_mode(args.mode)
    from fem_dual.scenes.base import parse_number

    from fem_dual.inputs import MIN_T

    period = parse_number("period", args.period)
    if not period > 0:
        raise InputError(f"period={args.period!r} must be positive")
    if period < MIN_T:
        raise InputError(f"period={args.period!r} is too small (at least {MIN_T:g})")
    from fem_dual.inputs import whole_number

    if whole_number("degree", args.degree) > 8:  # (before a run's limits, which name slabs)
        raise InputError(f"degree={args.degree} is too large for orbits (at most 8)")
    if whole_number("cells", args.cells) > 4096:
        raise InputError(f"cells={args.cells} is too large for orbits (at most 4096)")
    config = RunConfig.create(args.scene, params, T=args.period, cells=args.cells,
                              degree=args.degree, x0=args.x0, v0=args.v0, check_petsc=False)
    from fem_dual.analysis.orbit_input import check_resolution

    check_resolution(config.scene, config.x0, config.v0, config.T, config.cells)
    continuation = (None if args.continuation is None
                    else parse_continuation(args.continuation, config.scene))
    if continuation is not None:  # every member's parameters, before any work
        from fem_dual.inputs import scene_of

        for value in continuation[1]:
            member = scene_of(config.scene.name, {**params, continuation[0]: value})
            member_has, why = Energy.find(member, config.x0) if mode == "energy" else (1, "")
            if member_has is None:
                raise InputError(f"mode energy: {config.scene.name} at {continuation[0]}="
                                 f"{value:.6g} has no energy: {why}")
    has, why = Energy.find(config.scene, config.x0) if mode == "energy" else (None, "")
    if mode == "energy" and has is None:
        raise InputError(f"mode energy needs a scene with an energy (linear with K symmetric "
                         f"and no damping, or a force with a potential); {config.scene.name} "
                         f"with these parameters has none: {why}")
    if has is not None and has.linear and not energy > 0:
        raise InputError(f"energy={energy:g} must be positive for {config.scene.name} (its "
                         "energy is 1/2 v.M v + 1/2 x.K x)")
    config.check_petsc()  # last: it imports PETSc
    comm = world(comm)
    dirs = {}
    for option, value in (("out", args.out), ("plot", args.plot)):
        if value is not None:
            from fem_dual.output import check_output_dir_on_root

            dirs[option] = check_output_dir_on_root(comm, value, f"--{option}")
    status = 0
    if comm.rank == 0:
        try:
            status = _orbit_on_root(args, config, params, mode, energy, continuation, dirs)
        except InputError as exc:
            print(f"fem-dual: error: {escaped(exc)}", file=sys.stderr)
            status = InputError.exit_status
        except Exception as exc:  # a bug: say so, and end the ranks that wait for rank 0
            if comm.size == 1:
                raise
            import traceback

            traceback.print_exc()
            print(f"fem-dual: internal error on rank 0: {escaped(exc)}", file=sys.stderr)
            comm.Abort(1)
    return int(comm.bcast(status, root=0))


def _orbit_on_root(args, config, params, mode, energy, continuation, dirs):
    from fem_dual.compat import quiet_jit_logging
    from fem_dual.analysis.orbit import orbit_family, orbit_summary, write_orbit_files

    with stdout_to_stderr(args.json), quiet_jit_logging():  # (expressions compile lazily)
        try:
            record = orbit_family(config.scene, params, config.x0, config.v0, config.T,
                                  config.degree, config.cells, mode, energy, continuation,
                                  with_estimate=not args.no_estimate,
                                  progress=lambda line: print(f"fem-dual: {line}",
                                                              file=sys.stderr, flush=True))
        except SolveError as exc:
            record = {"status": "interrupted" if isinstance(exc, faults.Interrupted) else
                      "failed", "message": str(exc), "scene": config.scene.name}
    problem = write_orbit_files(record, dirs) if record.get("period") is not None else None
    if problem:
        record["status"], record["message"] = "failed", problem
    if args.json:
        print(json.dumps(record, allow_nan=False), file=json_out(), flush=True)
    else:
        print(orbit_summary(record))
    if record["status"] == "interrupted":
        print(f"fem-dual: stopped: {escaped(record['message'])}", file=sys.stderr)
        return 128 + faults.requested()
    if record["status"] != "ok":
        what = "output failed" if problem else "no orbit"
        print(f"fem-dual: {what}: {escaped(record['message'])}", file=sys.stderr)
        return SolveError.exit_status
    return 0
