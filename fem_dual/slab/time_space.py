"""The 1D time space of a slab: P_p Lagrange (GLL-warped nodes) on `cells` equal cells of the
unit interval s in [0, 1], its element and global time matrices, and the exact interpolation
of a lower degree's functions into it (the error companion's start)."""
from __future__ import annotations

import basix
import numpy as np
from scipy import sparse

__all__ = ["TimeMatrices"]


class TimeMatrices:
    """1D P_p matrices of the unit interval with `cells` equal cells, dofs ordered by s."""

    def __init__(self, degree: int, cells: int):
        p = degree
        element = basix.create_element(basix.ElementFamily.P, basix.CellType.interval, p,
                                       basix.LagrangeVariant.gll_warped)
        points, weights = basix.make_quadrature(basix.CellType.interval, 2 * p)
        tab = element.tabulate(1, points)
        phi, dphi = tab[0, :, :, 0], tab[1, :, :, 0]  # (points, p + 1)
        position = np.array([0, p] + list(range(1, p)))  # basix dof -> position in the cell
        order = np.argsort(position)  # local dofs sorted by s
        phi, dphi = phi[:, order], dphi[:, order]
        h = 1.0 / cells
        self.element = {  # per cell, in s-order, for a cell of length h
            "S": (dphi.T * weights) @ dphi / h, "C": (dphi.T * weights) @ phi,
            "Mm": (phi.T * weights) @ phi * h, "e": dphi.T @ weights,
            "m": phi.T @ weights * h}
        self.element["G"] = self.element["C"].T
        self.cells, self.degree = cells, p
        self.size = cells * p + 1
        self.cell_dofs = np.arange(cells)[:, None] * p + np.arange(p + 1)  # (cells, p + 1)
        rows = np.repeat(self.cell_dofs, p + 1, axis=1).ravel()
        cols = np.tile(self.cell_dofs, (1, p + 1)).ravel()
        self.glob = {}
        for name in ("S", "C", "G", "Mm"):
            values = np.tile(self.element[name].ravel(), cells)
            self.glob[name] = sparse.csr_matrix((values, (rows, cols)),
                                                shape=(self.size, self.size))
        for name in ("e", "m"):
            vec = np.zeros(self.size)
            np.add.at(vec, self.cell_dofs.ravel(), np.tile(self.element[name], cells))
            self.glob[name] = vec
        self.free = np.arange(self.size - 1)  # s = 1 is the Dirichlet dof xi = eta = 0
        self._basix, self._order = element, order

    def nodes(self) -> np.ndarray:
        """(p + 1,) the reference nodes of a cell, in s-order."""
        return np.asarray(self._basix.points)[:, 0][self._order]

    def interpolation(self, coarse: "TimeMatrices") -> np.ndarray:
        """(size, coarse.size): the values at this space's dofs of a function of `coarse`, a
        space of lower or equal degree on the same cells (exact: P_q is in P_p for q <= p)."""
        if coarse.cells != self.cells or coarse.degree > self.degree:
            raise ValueError("interpolation: the coarse space must share the cells and have "
                             "no higher degree")
        values = coarse._basix.tabulate(0, self.nodes()[:, None])[0, :, :, 0][:, coarse._order]
        out = np.zeros((self.size, coarse.size))
        for fine, rough in zip(self.cell_dofs, coarse.cell_dofs):
            out[np.ix_(fine, rough)] = values  # (shared vertices: the same value twice)
        return out
