"""An orbit's record for people: the text `fem-dual orbit` prints, its files and its plots."""
from __future__ import annotations

from typing import Any, Dict, List, Optional

import numpy as np

__all__ = ["orbit_summary", "write_orbit_files", "plot_orbit"]


def orbit_summary(record: Dict[str, Any]) -> str:
    """The text `fem-dual orbit` prints (the JSON holds everything)."""
    if record.get("period") is None:
        return f"{record.get('scene', '')}: no orbit ({record.get('status')})"
    lines = []
    for step in record.get("continuation", []):
        name = record["continuation_parameter"]
        mods = ", ".join(f"{abs(complex(*m)):.6g}" for m in step["nontrivial_multipliers"])
        lines.append(f"{name} = {step[name]:<10.6g} period {step['period']:.12g}  "
                     f"|multipliers| {mods}  closure {step['closure']:.2g}")
    est = record.get("estimate") or {}
    mult = ", ".join(f"{re:.10g}{im:+.10g}i" for re, im in record["nontrivial_multipliers"])
    verdict = "" if record.get("status") == "ok" else " -- NOT AN ORBIT (status failed)"
    lines += [f"{record['scene']}: periodic orbit ({record['mode']}), p = {record['degree']}, "
              f"{record['cells']} cells{verdict}",
              f"  period     {record['period']:.15g}" + (
                  f"  (estimated error {est['period']:.2g})" if "period" in est else ""),
              f"  mu         {record['mu']:.3g}",
              f"  x(0)       {record['x'][0]}",
              f"  v(0)       {record['v'][0]}",
              f"  multipliers {mult} (and the pair at 1; fem-dual's slab maps" + (
                  f", estimated error {est['multipliers']:.2g}" if "multipliers" in est else "")
              + (f", DOP853 differs by {record['check']['multipliers']:.2g}"
                 if record.get("check") else "") + ")",
              f"  closure    {record['closure']:.3g} (DOP853 over one period from x(0), v(0))",
              f"  Newton     {record['newton']['iterations']} iterations; solve "
              f"{record['timings']['solve_s'] * 1e3:.1f} ms"]
    if record.get("energy") is not None:
        target = record.get("energy_target")
        lines.append(f"  energy     {record['energy']:.15g}" + (
            f"  (asked {target:.15g}, off by {abs(record['energy'] - target):.2g})"
            if target is not None else "") + (
            f"  (estimated error {est['energy']:.2g})" if "energy" in est else ""))
    return "\n".join(lines)


def write_orbit_files(record: Dict[str, Any], dirs: Dict[str, Any]) -> Optional[str]:
    """orbit.csv and orbit.json into dirs["out"], orbit.png (and continuation.png) into
    dirs["plot"]; the reason a write failed, or None. orbit.json comes last and says what
    failed when a write before it did (status "failed", never an "ok" beside a failure)."""
    import json
    from pathlib import Path

    problem = None
    try:
        if dirs.get("out") is not None:
            out = Path(dirs["out"])
            n = len(record["x"][0])
            head = ",".join(["t"] + [f"x{i + 1}" for i in range(n)] + [f"v{i + 1}" for i in
                                                                       range(n)])
            table = np.column_stack([record["t"], record["x"], record["v"]])
            np.savetxt(out / "orbit.csv", table, delimiter=",", header=head, comments="",
                       fmt="%.17g")
        if dirs.get("plot") is not None:
            plot_orbit(record, Path(dirs["plot"]))
    except OSError as exc:
        problem = f"writing the output failed: {exc}"
    if dirs.get("out") is None:
        return problem
    written = record if problem is None else {**record, "status": "failed", "message": problem}
    try:
        (Path(dirs["out"]) / "orbit.json").write_text(json.dumps(written, allow_nan=False)
                                                      + "\n")
    except OSError as exc:
        problem = problem or f"writing the output failed: {exc}"
    return problem


def plot_orbit(record: Dict[str, Any], directory) -> List[Any]:
    """orbit.png: the orbit against t and its projection on (x1, x2) or (x, v); with a
    continuation, continuation.png: the period and the multipliers' moduli along it."""
    from pathlib import Path

    from fem_dual.plots import _axes, _save

    directory = Path(directory)
    t, x, v = (np.array(record[k]) for k in ("t", "x", "v"))
    n = x.shape[1]
    plt, fig, axes = _axes(1, 10.0)
    fig.clf()
    left, right = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    for i in range(n):
        left.plot(t, x[:, i], label=f"x{i + 1}")
    left.set_xlabel("t")
    left.set_title(f"{record['scene']}: period {record['period']:.10g}")
    left.legend(fontsize="small")
    if n >= 2:
        right.plot(x[:, 0], x[:, 1])
        right.set_xlabel("x1")
        right.set_ylabel("x2")
    else:
        right.plot(x[:, 0], v[:, 0])
        right.set_xlabel("x")
        right.set_ylabel("v")
    right.set_title("orbit")
    paths = [_save(plt, fig, directory / "orbit.png")]
    steps = record.get("continuation")
    if steps:
        name = record["continuation_parameter"]
        plt, fig, axes = _axes(2)
        p = [s[name] for s in steps]
        axes[0].plot(p, [s["period"] for s in steps], "o-")
        axes[0].set_ylabel("period")
        moduli = np.array([[abs(complex(*m)) for m in s["nontrivial_multipliers"]]
                           for s in steps])
        for j in range(moduli.shape[1]):
            axes[1].plot(p, moduli[:, j], ".-")
        axes[1].set_ylabel("|multiplier|")
        axes[1].set_xlabel(name)
        paths.append(_save(plt, fig, directory / "continuation.png"))
    return paths
