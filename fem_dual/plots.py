"""`--plot DIR`: pictures of a run (rank 0), written with matplotlib's Agg backend.

motion.png (x(t) and v(t)), phase.png (trajectory x1 against x2 for n >= 2, else the phase
portrait x against v), error.png (the estimated error per slab end and, with a reference, the
error at every output time, against t) and hamiltonian.png (H_d per slab). Many components get
20 distinct colours, every other curve dashed (curves that coincide stay visible), and a legend
outside the axes, which hides no curve.
"""
from __future__ import annotations

from pathlib import Path
from typing import List

import numpy as np

__all__ = ["write_plots"]

LEGEND_MAX = 20  # more components than this: no legend (the colours still differ)


def _axes(rows: int = 1, width: float = 9.0):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(rows, 1, figsize=(width, 3.2 * rows + 0.6), squeeze=False,
                             sharex=True)
    from cycler import cycler

    colours = plt.get_cmap("tab10").colors + plt.get_cmap("Dark2").colors[:6] \
        + plt.get_cmap("Set1").colors[:4]
    # 20 distinct colours, every other curve dashed: curves that coincide stay visible
    styles = cycler(color=list(colours)) + cycler(linestyle=["-", "--"] * 10)
    for ax in axes[:, 0]:
        ax.set_prop_cycle(styles)
        ax.grid(True, alpha=0.3)
    return plt, fig, axes[:, 0]


def _legend(ax, count: int) -> None:
    if 0 < count <= LEGEND_MAX:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")


def _save(plt, fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_plots(result, directory: Path) -> List[Path]:
    """The four pictures of `result` (a RunResult) in `directory`; returns their paths."""
    directory = Path(directory)
    t, x, v = result.t, result.x, result.v
    n = x.shape[1]
    title = f"{result.scene}, T = {result.T:g}, p = {result.degree}"
    paths = []

    plt, fig, (ax_x, ax_v) = _axes(2)
    for i in range(n):
        ax_x.plot(t, x[:, i], label=f"x{i + 1}")
        ax_v.plot(t, v[:, i], label=f"v{i + 1}")
    ax_x.set_ylabel("position x")
    ax_v.set_ylabel("velocity v")
    ax_v.set_xlabel("time t")
    ax_x.set_title(title)
    _legend(ax_x, n)
    _legend(ax_v, n)
    paths.append(_save(plt, fig, directory / "motion.png"))

    plt, fig, (ax,) = _axes(1, width=6.0)
    if n >= 2:
        ax.plot(x[:, 0], x[:, 1], "-", lw=1.2)
        ax.plot(x[:1, 0], x[:1, 1], "o", label="start")
        ax.set_xlabel("x1")
        ax.set_ylabel("x2")
        ax.set_title(f"trajectory, {title}")
    else:
        ax.plot(x[:, 0], v[:, 0], "-", lw=1.2)
        ax.plot(x[:1, 0], v[:1, 0], "o", label="start")
        ax.set_xlabel("x")
        ax.set_ylabel("v")
        ax.set_title(f"phase portrait, {title}")
    ax.legend(fontsize="small")
    paths.append(_save(plt, fig, directory / "phase.png"))

    plt, fig, (ax,) = _axes(1)
    if result.estimate_at_t is not None:
        ax.semilogy(t, np.maximum(result.estimate_at_t, 1e-17), "-", lw=1.5,
                    label="estimated error (no reference needed)")
    if result.error_at_t is not None:
        ax.semilogy(t, np.maximum(result.error_at_t, 1e-17), "-", lw=1,
                    label="error against the reference")
    ax.set_xlabel("time t")
    ax.set_ylabel("max error over x and v")
    ax.set_title(title)
    _legend(ax, 2)
    paths.append(_save(plt, fig, directory / "error.png"))

    plt, fig, (ax,) = _axes(1)
    per_slab = result.hamiltonian.get("per_slab", [])
    if per_slab:
        k = np.arange(len(per_slab))
        ax.plot(k, [h["min"] for h in per_slab], "v-", ms=3, label="min over the slab")
        ax.plot(k, [h["max"] for h in per_slab], "^-", ms=3, label="max over the slab")
    ax.set_xlabel("slab")
    ax.set_ylabel("auxiliary dual Hamiltonian H_d")
    ax.set_title(title)
    _legend(ax, 2)
    paths.append(_save(plt, fig, directory / "hamiltonian.png"))
    return paths
