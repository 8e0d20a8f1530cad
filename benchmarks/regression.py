#!/usr/bin/env python3
"""Regression harness for the fem-dual command line: record the JSON of a fixed set of CLI runs,
then rerun them (after a refactor) and prove every number unchanged.

    python3 benchmarks/regression.py record  --bin .venv/bin --dir OUT
    python3 benchmarks/regression.py compare --bin .venv/bin --dir OUT [--only NAME ...]
    python3 benchmarks/regression.py list

Standalone: the Python standard library only (it never imports fem_dual; the one step that
needs h5py, cutting an output series short to simulate an interrupted run, and the dump of
HDF5 files are run by `<bin>/python`).

Each run gets a fresh temporary directory as its working directory; "{tmp}" in a command (or
in `files`/`write` paths) stands for it, and every string of the output has that directory
replaced by "<TMP>". A run is recorded as OUT/<name>.json: the command, its exit code, its
stdout parsed as JSON (or the text when it is not JSON), the first line of stderr when the
exit code is not 0, the JSON of the steps before it (first run of a resume), and the files
asked for.

`compare` reruns and checks, per run: the same exit code; every number within
|a - b| <= rtol * max(|a|, |b|) + atol (defaults rtol 1e-12, atol 1e-300: relative, the floor
only so that 0 == 0; `--vector-scale` measures numbers inside a list of numbers against the
largest magnitude of that list instead, for refactors that move round-off in near-zero
components); the same strings, booleans and nulls; the same keys (keys that only the new output
has are reported, not failed); the same list lengths. Ignored: anything under "timings", keys
ending in "_s", keys containing "version", "compiled_loops_unavailable". One line per run
(PASS/FAIL and the worst relative difference of any number), then "N passed, M failed"; exit 1
on any failure.

Options of a run (third element of a RUNS entry):
  mpi=N          run under `mpirun -n N` (OMPI_ALLOW_RUN_AS_ROOT and oversubscription are set)
  resume={...}   first run the command without "--resume" (recorded as step "first"), then cut
                 the HDF5 series of every scene in the --out directory to `keep` slabs and
                 remove the trajectory files (what `kill -9` after `keep` flushed slabs leaves;
                 keep=None leaves the complete run), then run the command (with --resume)
  write={name: text}  files written into the temporary directory before the run
  files=[path, ...]   output files recorded too (.csv parsed to numbers, .h5 dumped through
                 <bin>/python and h5py, .json loaded)
  timeout=S      seconds before the run is killed (default 600)
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# ---------------------------------------------------------------------------------------------
# The runs
# ---------------------------------------------------------------------------------------------

HENON_HEILES = "-x - 2*x*y, -y - x**2 + y**2"
SWIRL = "-x - a*y**3, a*x - y"

# a scene declared in a Python file (README "Your own force"; tests/scenes/test_force.py::FileSwirl)
SWIRL_SCENE_FILE = '''\
import dataclasses, ufl
from typing import ClassVar
from fem_dual.scenes import ForceScene
from fem_dual.forms import implicit
from fem_dual.forms.predual import isotropic_quadratic


@dataclasses.dataclass(frozen=True)
class FileSwirl(ForceScene):
    name: ClassVar[str] = "file-swirl"
    n: ClassVar[int] = 2
    forms: ClassVar = implicit.make(
        lambda x, c: ufl.as_vector([-x[0] - c["a"] * x[1] ** 3, c["a"] * x[0] - x[1]]),
        lambda dx, dv, c: isotropic_quadratic(dx, dv, c["alpha"], c["beta"]))
    default_T: ClassVar[float] = 2.0
    default_x0: ClassVar[tuple] = (1.0, 0.0)
    default_v0: ClassVar[tuple] = (0.0, 0.5)
    a: float = 0.5
'''

# a non-symmetric K, SPD M, a small D: 3 dofs stay on the forms/pointwise path (Kronecker from 5)
LINEAR3 = ["--param", "dofs=3", "--param", "M=2,0,0,0,1,0,0,0,1",
           "--param", "K=3,-1,0,-1,2,-1,0.2,-1,1", "--param", "D=0.02,0,0,0,0.01,0,0,0,0.01"]

# (name, argv after `fem-dual`, options)
RUNS = [
    # 1. every scene
    ("ziegler", ["run", "ziegler", "--T", "20", "--slabs", "10", "--cells", "20", "--degree", "3",
                 "--json"], {}),
    ("column3", ["run", "column", "--param", "links=3", "--param", "d=0.02", "--T", "10",
                 "--slabs", "5", "--cells", "16", "--degree", "3", "--json"], {}),
    ("linear3", ["run", "linear", *LINEAR3, "--x0", "0.1,0,-0.05", "--T", "5", "--slabs", "5",
                 "--cells", "10", "--degree", "3", "--json"], {}),
    ("curl3d", ["run", "curl3d", "--T", "2", "--cells", "8", "--degree", "3", "--json"], {}),
    ("curl2d", ["run", "curl2d", "--T", "2", "--slabs", "4", "--cells", "10", "--degree", "3",
                "--json"], {}),
    ("curl2d-lifted", ["run", "curl2d-lifted", "--T", "2", "--slabs", "4", "--cells", "20",
                       "--degree", "3", "--json"], {}),
    ("curl2d-ufl", ["run", "curl2d-ufl", "--T", "2", "--slabs", "4", "--cells", "10", "--degree",
                    "3", "--json"], {}),
    ("curl3d-ufl", ["run", "curl3d-ufl", "--T", "2", "--cells", "8", "--degree", "3", "--json"],
     {}),
    ("force-henon-heiles", ["run", "force", "--F", HENON_HEILES, "--x0", "0.1,0.2", "--v0",
                            "0.3,0", "--T", "3", "--slabs", "3", "--cells", "8", "--degree", "3",
                            "--json"], {}),
    # 2. tolerances, bases, assemblies, staging, recovery
    ("curl3d-rtol", ["run", "curl3d", "--T", "8", "--rtol", "1e-8", "--cells", "4", "--degree",
                     "4", "--json"], {}),
    ("ziegler-rtol", ["run", "ziegler", "--T", "50", "--rtol", "1e-8", "--cells", "8",
                      "--degree", "4", "--json"], {}),
    ("curl3d-rk4-rtol", ["run", "curl3d", "--T", "8", "--rtol", "1e-8", "--cells", "4",
                         "--degree", "4", "--base", "rk4", "--json"], {}),
    ("curl2d-predictor", ["run", "curl2d", "--T", "2", "--slabs", "4", "--cells", "10",
                          "--degree", "3", "--base", "predictor", "--json"], {}),
    ("curl3d-forms", ["run", "curl3d", "--T", "2", "--slabs", "4", "--cells", "8", "--degree",
                      "3", "--assembly", "forms", "--json"], {}),
    ("column6-kronecker", ["run", "column", "--param", "links=6", "--rtol", "1e-6", "--cells",
                           "4", "--degree", "4", "--assembly", "kronecker", "--json"], {}),
    # 200 cells x 3^2 = 1800 > 800: each of the 2 slabs is solved as 3 stages
    ("ziegler-staged", ["run", "ziegler", "--T", "20", "--slabs", "2", "--cells", "200",
                        "--degree", "3", "--json"], {}),
    ("ziegler-staging-off", ["run", "ziegler", "--T", "20", "--slabs", "2", "--cells", "200",
                             "--degree", "3", "--staging", "off", "--json"], {}),
    ("ziegler-dtp", ["run", "ziegler", "--T", "10", "--slabs", "2", "--cells", "20", "--degree",
                     "4", "--recovery", "dtp", "--json"], {}),
    # 3. --t-eval, list and START:STOP:COUNT (the second also writes --csv, recorded)
    ("force-swirl-teval-list", ["run", "force", "--F", SWIRL, "--param", "a=0.5", "--x0", "1,0",
                                "--v0", "0,0.5", "--T", "4", "--rtol", "1e-8", "--cells", "4",
                                "--degree", "4", "--t-eval", "0.5,1.25,3.9", "--json"], {}),
    ("curl2d-teval-range-csv", ["run", "curl2d", "--T", "2", "--slabs", "4", "--cells", "10",
                                "--degree", "3", "--t-eval", "0:2:9", "--csv",
                                "{tmp}/motion.csv", "--json"], {"files": ["motion.csv"]}),
    # 4. --out, then --resume from a series cut to `keep` slabs (what kill -9 leaves)
    ("ziegler-resume", ["run", "ziegler", "--T", "20", "--slabs", "10", "--cells", "16",
                        "--degree", "5", "--superpose", "no", "--out", "{tmp}/out", "--json",
                        "--resume"], {"resume": {"keep": 4}, "files": ["out/ziegler.h5"]}),
    ("curl3d-rtol-resume", ["run", "curl3d", "--T", "8", "--rtol", "1e-8", "--cells", "4",
                            "--degree", "4", "--out", "{tmp}/out", "--json", "--resume"],
     {"resume": {"keep": 3}}),
    # 5. a scene declared in a file
    ("scene-file-swirl", ["run", "file-swirl", "--scene-file", "{tmp}/swirl.py", "--slabs", "2",
                          "--cells", "8", "--degree", "3", "--param", "a=0.7", "--json"],
     {"write": {"swirl.py": SWIRL_SCENE_FILE}}),
    # 6. periodic orbit with continuation, flutter load
    ("orbit-ziegler-continue", ["orbit", "ziegler", "--x0", "0.1,0.16", "--period", "13",
                                "--continue", "P=0:1.5:3", "--json"], {}),
    ("flutter-ziegler", ["flutter", "ziegler", "--json"], {}),
    # 7. under mpirun -n 2
    ("mpi2-ziegler-forms", ["run", "ziegler", "--T", "4", "--slabs", "2", "--cells", "8",
                            "--degree", "3", "--assembly", "forms", "--json"], {"mpi": 2}),
    ("mpi2-curl3d", ["run", "curl3d", "--T", "2", "--slabs", "4", "--cells", "8", "--degree",
                     "3", "--json"], {"mpi": 2}),
    # 8. a failed solve (exit 3: past curl3d's blow-up near t = 9.5) and bad input (exit 2)
    ("curl3d-blowup-exit3", ["run", "curl3d", "--T", "12", "--json"], {}),
    ("bad-T-exit2", ["run", "ziegler", "--T", "-1", "--json"], {}),
    ("bad-petsc-exit2", ["run", "ziegler", "--T", "2", "--petsc-option", "ksp_type=bogus",
                         "--json"], {}),
]

# ---------------------------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------------------------

ENV = {"OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1",
       "OMPI_MCA_rmaps_base_oversubscribe": "1"}
TMP_TOKEN = "<TMP>"

# cut every extendable dataset of /steps and /restart to `keep` rows (argv: h5 file, keep)
_TRUNCATE_H5 = r"""
import sys, h5py
path, keep = sys.argv[1], int(sys.argv[2])
with h5py.File(path, "a", locking=False) as h5:
    for group in ("steps", "restart"):
        for name in h5[group]:
            ds = h5[group][name]
            if len(ds) < keep:
                sys.exit(f"{path}:{group}/{name} holds {len(ds)} rows, fewer than {keep}")
            ds.resize(keep, axis=0)
"""

# every dataset as a list, every attribute (JSON text parsed), as one JSON object on stdout
_DUMP_H5 = r"""
import json, sys, h5py, numpy as np
def plain(value):
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str):
        try:
            return json.loads(value)
        except ValueError:
            return value
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
out = {}
with h5py.File(sys.argv[1], "r", locking=False) as h5:
    out["attrs"] = {k: plain(v) for k, v in h5.attrs.items()}
    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            out[name] = {"shape": list(obj.shape), "data": plain(obj[()]),
                         "attrs": {k: plain(v) for k, v in obj.attrs.items()}}
    h5.visititems(visit)
json.dump(out, sys.stdout)
"""


def _subst(items, tmp: str):
    return [a.replace("{tmp}", tmp) for a in items]


def _normalise(obj, tmps):
    """Every string with the temporary directory replaced by TMP_TOKEN."""
    if isinstance(obj, str):
        for t in tmps:
            obj = obj.replace(t, TMP_TOKEN)
        return obj
    if isinstance(obj, list):
        return [_normalise(o, tmps) for o in obj]
    if isinstance(obj, dict):
        return {_normalise(k, tmps): _normalise(v, tmps) for k, v in obj.items()}
    return obj


def _command(bindir: Path, argv, options) -> list:
    mpi = options.get("mpi")
    exe = str(bindir / "fem-dual")
    return (["mpirun", "-n", str(mpi), exe] if mpi else [exe]) + list(argv)


def _execute(bindir: Path, argv, options, tmp: str) -> dict:
    """One command in `tmp`: exit code, stdout (JSON or text), first stderr line if it failed."""
    cmd = _command(bindir, _subst(argv, tmp), options)
    env = dict(os.environ, **ENV)
    tic = time.perf_counter()
    try:
        done = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True,
                              timeout=options.get("timeout", 600))
        code, out, err = done.returncode, done.stdout, done.stderr
    except subprocess.TimeoutExpired as exc:
        code, out, err = "timeout", exc.stdout or "", exc.stderr or ""
        out = out.decode() if isinstance(out, bytes) else out
        err = err.decode() if isinstance(err, bytes) else err
    seconds = time.perf_counter() - tic
    rec = {"exit_code": code, "seconds": round(seconds, 3)}
    try:
        rec["stdout_json"] = json.loads(out)
    except ValueError:
        rec["stdout_json"] = None
        rec["stdout_text"] = out
    if code != 0:
        lines = [line for line in err.splitlines() if line.strip()]
        rec["stderr_first_line"] = lines[0] if lines else ""
    rec["stderr_tail"] = err[-2000:]  # for the reader; never compared
    return rec


def _read_file(bindir: Path, path: Path):
    if not path.exists():
        return {"missing": True}
    if path.suffix == ".csv":
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
        def num(s):
            try:
                return float(s)
            except ValueError:
                return s
        return [[num(c.strip()) for c in row] for row in rows]
    if path.suffix == ".json":
        return json.loads(path.read_text())
    if path.suffix == ".h5":
        done = subprocess.run([str(bindir / "python"), "-c", _DUMP_H5, str(path)],
                              capture_output=True, text=True)
        if done.returncode != 0:
            return {"dump_failed": done.stderr.strip().splitlines()[-1:]}
        return json.loads(done.stdout)
    return path.read_text()


def _truncate(bindir: Path, out_dir: Path, keep: int) -> None:
    """What `kill -9` leaves after `keep` flushed slabs: series rows cut, no trajectory."""
    series = [p for p in out_dir.glob("*.h5") if not p.name.endswith("_trajectory.h5")]
    if not series:
        raise RuntimeError(f"no series to cut in {out_dir}")
    for h5 in series:
        done = subprocess.run([str(bindir / "python"), "-c", _TRUNCATE_H5, str(h5), str(keep)],
                              capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"cutting {h5} failed: {done.stderr.strip()[-500:]}")
    for p in out_dir.glob("*_trajectory.*"):
        p.unlink()


def _out_dir(argv, tmp: str) -> Path:
    argv = _subst(argv, tmp)
    out = Path(argv[argv.index("--out") + 1])
    return out if out.is_absolute() else Path(tmp) / out


def options_record(options) -> dict:
    """The options as stored with a record (written files by their sha256)."""
    rec = {k: v for k, v in options.items() if k != "write"}
    if "write" in options:
        rec["write"] = {f: hashlib.sha256(t.encode()).hexdigest()
                        for f, t in options["write"].items()}
    return json.loads(json.dumps(rec))


def execute_run(bindir: Path, name: str, argv, options, keep_tmp: bool = False) -> dict:
    tmp = tempfile.mkdtemp(prefix=f"fem-dual-regression-{name}-")
    tmps = sorted({tmp, os.path.realpath(tmp)}, key=len, reverse=True)
    try:
        for fname, text in options.get("write", {}).items():
            Path(tmp, fname).write_text(text)
        record = {"name": name, "argv": list(argv),
                  "options": options_record(options),
                  "command": " ".join(_command(bindir, argv, options)), "steps": {}}
        tic = time.perf_counter()
        resume = options.get("resume")
        if resume is not None:
            first = [a for a in argv if a != "--resume"]
            step = _execute(bindir, first, options, tmp)
            record["steps"]["first"] = _normalise(step, tmps)
            if step["exit_code"] == 0 and resume.get("keep") is not None:
                _truncate(bindir, _out_dir(argv, tmp), int(resume["keep"]))
        rec = _execute(bindir, argv, options, tmp)
        record.update(_normalise(rec, tmps))
        record["files"] = {f: _normalise(_read_file(bindir, Path(tmp, f)), tmps)
                           for f in options.get("files", [])}
        record["seconds"] = round(time.perf_counter() - tic, 3)
        return record
    finally:
        if keep_tmp:
            print(f"    kept {tmp}", file=sys.stderr)
        else:
            shutil.rmtree(tmp, ignore_errors=True)


# ---------------------------------------------------------------------------------------------
# Comparing
# ---------------------------------------------------------------------------------------------

def ignored(path) -> bool:
    """Keys that are not compared: timings, *_s, versions, compiled_loops_unavailable."""
    for key in path:
        if not isinstance(key, str):
            continue
        if key == "timings" or key.endswith("_s") or "version" in key.lower() \
                or key == "compiled_loops_unavailable":
            return True
    return False


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _fmt(path) -> str:
    return "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in path) or "."


class Comparison:
    def __init__(self, rtol: float, atol: float, vector_scale: bool):
        self.rtol, self.atol, self.vector_scale = rtol, atol, vector_scale
        self.worst = 0.0
        self.worst_at = ""
        self.failures: list = []
        self.new_keys: list = []
        self.numbers = 0

    def fail(self, path, what):
        self.failures.append(f"{_fmt(path)}: {what}")

    def number(self, old, new, path, scale=0.0):
        self.numbers += 1
        if isinstance(old, float) and isinstance(new, float) and math.isnan(old) \
                and math.isnan(new):
            return
        if old == new:
            return
        if not (math.isfinite(old) and math.isfinite(new)):
            self.worst = math.inf
            self.worst_at = _fmt(path)
            self.fail(path, f"{old!r} -> {new!r}")
            return
        diff = abs(old - new)
        size = max(abs(old), abs(new), scale)
        rel = diff / size if size > 0 else 0.0
        if rel > self.worst:
            self.worst, self.worst_at = rel, _fmt(path)
        if diff > self.rtol * size + self.atol:
            self.fail(path, f"{old!r} -> {new!r} (rel {rel:.2e})")

    def walk(self, old, new, path=(), scale=0.0):
        if ignored(path):
            return
        if _is_number(old) and _is_number(new):
            self.number(old, new, path, scale)
        elif isinstance(old, dict) and isinstance(new, dict):
            for k in old:
                if ignored(path + (k,)):
                    continue
                if k not in new:
                    self.fail(path + (k,), "missing in the new output")
                else:
                    self.walk(old[k], new[k], path + (k,))
            for k in new:
                if k not in old and not ignored(path + (k,)):
                    self.new_keys.append(_fmt(path + (k,)))
        elif isinstance(old, list) and isinstance(new, list):
            if len(old) != len(new):
                self.fail(path, f"length {len(old)} -> {len(new)}")
                return
            inner = 0.0
            if self.vector_scale and all(_is_number(o) for o in old + new):
                finite = [abs(o) for o in old + new if math.isfinite(o)]
                inner = max(finite, default=0.0)
            for i, (o, n) in enumerate(zip(old, new)):
                self.walk(o, n, path + (i,), inner)
        elif type(old) is not type(new) or old != new:
            self.fail(path, f"{_short(old)} -> {_short(new)}")


def _short(x, n=120) -> str:
    s = json.dumps(x) if not isinstance(x, str) else repr(x)
    return s if len(s) <= n else s[:n] + "..."


COMPARED = ("exit_code", "stdout_json", "stdout_text", "stderr_first_line")


def _compare_outputs(old: dict, new: dict, cmp: Comparison, path: tuple) -> None:
    if old.get("exit_code") != new.get("exit_code"):  # exactly, and not a relative difference
        cmp.fail(path + ("exit_code",), f"{old.get('exit_code')} -> {new.get('exit_code')}")
    for key in COMPARED:
        if key != "exit_code" and (key in old or key in new):
            cmp.walk(old.get(key), new.get(key), path + (key,))


def compare_records(old: dict, new: dict, cmp: Comparison) -> None:
    _compare_outputs(old, new, cmp, ())
    for step in sorted(set(old.get("steps", {})) | set(new.get("steps", {}))):
        o, n = old.get("steps", {}).get(step), new.get("steps", {}).get(step)
        if o is None or n is None:
            cmp.fail(("steps", step), "step missing")
            continue
        _compare_outputs(o, n, cmp, ("steps", step))
    cmp.walk(old.get("files", {}), new.get("files", {}), ("files",))


# ---------------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------------

def _selected(only):
    names = [r[0] for r in RUNS]
    assert len(set(names)) == len(names), "run names must be unique"
    if not only:
        return RUNS
    unknown = [n for n in only if n not in names]
    if unknown:
        sys.exit(f"unknown run(s): {', '.join(unknown)}; `list` shows them")
    return [r for r in RUNS if r[0] in only]


def _check_bin(bindir: Path) -> None:
    if not (bindir / "fem-dual").exists():
        sys.exit(f"no fem-dual in {bindir}")


def cmd_record(args) -> int:
    bindir = Path(args.bin).resolve()
    _check_bin(bindir)
    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    total = time.perf_counter()
    for name, argv, options in _selected(args.only):
        record = execute_run(bindir, name, argv, options, args.keep_tmp)
        record["recorded_with"] = str(bindir)
        (out / f"{name}.json").write_text(json.dumps(record, indent=1) + "\n")
        status = record.get("stdout_json") or {}
        status = status.get("status") if isinstance(status, dict) else None
        print(f"{name:<26} exit {record['exit_code']!s:>3}  {record['seconds']:7.2f} s"
              f"  status {status}", flush=True)
    print(f"recorded {len(_selected(args.only))} runs into {out} in "
          f"{time.perf_counter() - total:.1f} s")
    return 0


def cmd_compare(args) -> int:
    bindir = Path(args.bin).resolve()
    _check_bin(bindir)
    store = Path(args.dir)
    passed = failed = 0
    total = time.perf_counter()
    for name, argv, options in _selected(args.only):
        path = store / f"{name}.json"
        if not path.exists():
            print(f"{name:<26} FAIL  no record {path}", flush=True)
            failed += 1
            continue
        old = json.loads(path.read_text())
        cmp = Comparison(args.rtol, args.atol, args.vector_scale)
        if old.get("argv") != list(argv) or old.get("options") != options_record(options):
            cmp.fail(("argv",), "the run's definition changed since it was recorded; "
                     "record it again")
        new = execute_run(bindir, name, argv, options, args.keep_tmp)
        compare_records(old, new, cmp)
        ok = not cmp.failures
        passed += ok
        failed += not ok
        worst = f"{cmp.worst:.2e}" if cmp.numbers else "-"
        print(f"{name:<26} {'PASS' if ok else 'FAIL'}  worst rel {worst:>8}"
              f"  ({cmp.numbers} numbers, {new['seconds']:.2f} s)"
              + (f"  at {cmp.worst_at}" if cmp.worst > 0 else ""), flush=True)
        for line in cmp.failures[:args.show]:
            print(f"    {line}")
        if len(cmp.failures) > args.show:
            print(f"    ... {len(cmp.failures) - args.show} more differences")
        if cmp.new_keys:
            print(f"    new keys (allowed): {', '.join(cmp.new_keys[:20])}"
                  + (" ..." if len(cmp.new_keys) > 20 else ""))
        if not ok and new.get("exit_code") not in (0, old.get("exit_code")):
            print("    stderr: " + new.get("stderr_tail", "").strip()[-400:].replace(
                "\n", "\n    stderr: "))
    print(f"{passed} passed, {failed} failed ({time.perf_counter() - total:.1f} s)")
    return 1 if failed else 0


def cmd_list(args) -> int:
    for name, argv, options in _selected(args.only):
        opts = {k: v for k, v in options.items() if k != "write"}
        if "write" in options:
            opts["write"] = sorted(options["write"])
        line = " ".join(_command(Path("<bin>"), [_q(a) for a in argv], options))
        print(f"{name:<26} {line}" + (f"   {opts}" if opts else ""))
    return 0


def _q(a: str) -> str:
    return f'"{a}"' if (" " in a or "*" in a) else a


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("record", "compare", "list"):
        p = sub.add_parser(name)
        if name != "list":
            p.add_argument("--bin", required=True, help="directory holding fem-dual and python")
            p.add_argument("--dir", required=True, help="directory of the records")
            p.add_argument("--keep-tmp", action="store_true",
                           help="keep each run's temporary directory")
        p.add_argument("--only", nargs="+", metavar="NAME", help="only these runs")
        if name == "compare":
            p.add_argument("--rtol", type=float, default=1e-12)
            p.add_argument("--atol", type=float, default=1e-300)
            p.add_argument("--vector-scale", action="store_true",
                           help="numbers inside a list of numbers relative to the list's "
                                "largest magnitude")
            p.add_argument("--show", type=int, default=10,
                           help="differences shown per failed run")
    args = parser.parse_args(argv)
    return {"record": cmd_record, "compare": cmd_compare, "list": cmd_list}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
