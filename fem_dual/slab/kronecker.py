"""Linear scenes of many degrees of freedom: the slab problem as Kronecker sums (time x space),
applied matrix-free and solved by CG with a fast-diagonalisation preconditioner.

For M q'' + D q' + K q = 0 the dual unknowns are W_xi, W_eta (time dofs x n). With
a = K^T eta - xi', b = D^T eta - M eta' - xi, the DtP map is x^ = xbar + A^-1 a, v^ = vbar + B^-1 b
and, by stationarity, the first variation of the action is

    dS[dw] = int (da . x^ + db . v^) dt - x0 . dxi(0) - M v0 . deta(0),

a sum of products (1D time matrix) x (n x n coefficient matrix). The 1D matrices of one slab (on
s in [0, 1], dofs ordered by s, so banded) are S = int phi_i' phi_j', C = int phi_i' phi_j,
G = C^T, Mm = int phi_i phi_j, e = int phi_i', m = int phi_i; the same formula with the element
matrices of one cell gives the cell residuals that carry the momenta x^, M v^ at the cell ends
(the superconvergent recovery of fem_dual.slab.recovery). Nothing is compiled per n: this is the path
for columns of hundreds of links, where the forms path would unroll n x n constants in FFCx.

The action is convex: CG (fem_dual.slab.kronecker_solver), preconditioned by the exact inverse
of the symmetric, undamped, energy-weighted slab problem, which decouples into the modes of the
pencil (Ke, M), Ke the scene's energy stiffness: n independent banded 1D solves. Under MPI each
rank owns a share of the n components: it computes its columns of every product and the modes
of its columns; the vectors (time dofs x 2n, small) are all-gathered once per product.
"""
from __future__ import annotations

import weakref
from typing import Dict, List, Mapping, Optional, Tuple

import numpy as np
import scipy.linalg as sla
from mpi4py import MPI
from scipy import sparse
from scipy.sparse import csgraph

from fem_dual.slab.time_space import TimeMatrices
from fem_dual.slab.recovery import VertexValues, times_last
from fem_dual.slab.superposition import (Bases, checked, first, refused, select,
                                         stable_or_raise)

__all__ = ["TimeMatrices", "KroneckerProblem", "KroneckerSampler", "KroneckerSuperposition",
           "decoupled_blocks", "probes"]

DENSE_TIME = 64  # free time dofs up to which the operator multiplies dense time matrices


class KroneckerProblem:
    """The slab problem of a linear scene in Kronecker form (see the module docstring).

    Attributes mirror SlabProblem where the driver uses them: set_slab, num_dofs, n, comm,
    mesh.cells, degree.
    """

    class _Mesh:
        def __init__(self, cells: int):
            self.cells = cells

    def __init__(self, scene, degree: int, cells: int, comm: MPI.Comm = MPI.COMM_WORLD,
                 base: str = "start"):
        self.scene, self.degree, self.comm, self.base = scene, degree, comm, base
        self.n = n = scene.n
        self.mesh = self._Mesh(cells)
        self.time = TimeMatrices(degree, cells)
        size = self.time.size
        self.free = self.time.free
        self.nf = len(self.free)
        self.time_free = {k: (v[self.free][:, self.free] if k not in ("e", "m")
                              else v[self.free]) for k, v in self.time.glob.items()}
        # the operator's time matrices: dense where they are small (a sparse product's own
        # overhead then outweighs its work)
        self.time_operator = {k: (v.toarray() if hasattr(v, "toarray") else v)
                              for k, v in self.time_free.items()} \
            if self.nf <= DENSE_TIME else self.time_free
        counts = [n // comm.size + (1 if r < n % comm.size else 0) for r in range(comm.size)]
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self.mine = np.arange(self.offsets[comm.rank], self.offsets[comm.rank + 1])
        self.set_scene_constants(scene)
        self.dt, self.t0 = 1.0, 0.0
        self.x0 = self.v0 = self.xbar = self.vbar = np.zeros(n)
        self.W = np.zeros((size, 2 * n))  # the whole dual state (xi | eta), on every rank

    def set_scene_constants(self, scene) -> None:
        self.scene = scene
        self.c, kinds = _scene_products(scene)
        M = self.c["M"]
        self._mass = None if np.array_equal(M, np.eye(self.n)) else sla.cho_factor(M)
        # right factors of the residual's products, for all columns and for this rank's own
        # (each matrix's structure found once: two factors each, answer and companion alike)
        self._right = {name: (_RightFactor(value.T, slice(None), kinds[name]),
                              _RightFactor(value.T, self.mine, kinds[name]))
                       for name, value in self.c.items()}
        # the quadratic form of H_d: Y K^T, Y D^T, Y A, Y B at the cost their structure allows
        self.hamiltonian_factors = {"K": self._right["K"][0], "D": self._right["D"][0],
                                    "A": _RightFactor(self.c["A"], slice(None), kinds["A"]),
                                    "B": _RightFactor(self.c["B"], slice(None), kinds["B"])}
        self._block_probes = None

    def block_probes(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(blocks, starts, gathers): `decoupled_blocks` of the scene's matrices and their
        `probes`, once per scene."""
        if self._block_probes is None:
            blocks = decoupled_blocks(self.c)
            self._block_probes = (blocks, *probes(blocks))
        return self._block_probes

    def velocity(self, mv: np.ndarray) -> np.ndarray:
        """v from rows of momenta M v (a Cholesky factor of M kept per scene; none for M = I)."""
        if self._mass is None:
            return mv
        return sla.cho_solve(self._mass, mv.T).T

    @property
    def num_dofs(self) -> int:
        return self.time.size * 2 * self.n

    def set_slab(self, x0: np.ndarray, v0: np.ndarray, dt: float, t0: float = 0.0) -> None:
        self.x0, self.v0 = np.asarray(x0, float), np.asarray(v0, float)
        if self.base == "start":
            self.xbar, self.vbar = self.x0, self.v0
        self.dt, self.t0 = float(dt), float(t0)
        self.W[:] = 0.0

    def residual(self, T: Mapping, Wxi, Weta, affine: bool, cols: Optional[np.ndarray] = None,
                 apply=None) -> Tuple[np.ndarray, np.ndarray]:
        """dS for the trial values (Wxi, Weta) tested with the rows of the time matrices T
        (global or per cell); `affine` adds the base-state terms; only the output components
        `cols` (default all). `apply(X, W)` multiplies a time matrix with W."""
        dt, n = self.dt, self.n
        own = cols is not None  # the operator asks for this rank's columns, the sampler for all
        apply = apply or (lambda X, W: X @ W)
        both = np.concatenate([Wxi, Weta], axis=-1)
        products: Dict[str, np.ndarray] = {}  # each time matrix on both fields, once

        def right(X, W, name):
            factor = self._right[name][own]
            if factor.zero:
                return 0.0
            if X not in products:
                products[X] = apply(T[X], both)
            return factor(products[X][..., :n] if W is Wxi else products[X][..., n:])

        r_xi = (-right("C", Weta, "AiKt") + right("S", Wxi, "Ai") / dt
                - dt * right("Mm", Weta, "BiDt") + dt * right("Mm", Wxi, "Bi")
                + right("G", Weta, "BiM"))
        r_eta = (dt * right("Mm", Weta, "KAiKt") - right("G", Wxi, "KAi")
                 + dt * right("Mm", Weta, "DBiDt") - dt * right("Mm", Wxi, "DBi")
                 - right("G", Weta, "DBiM") - right("C", Weta, "MBiDt")
                 + right("C", Wxi, "MBi") + right("S", Weta, "MBiM") / dt)
        if affine:
            b_xi, b_eta = self.base_terms(T, slice(None) if cols is None else cols)
            r_xi, r_eta = r_xi + b_xi, r_eta + b_eta
        return r_xi, r_eta

    def base_terms(self, T: Mapping, cols=slice(None)) -> Tuple[np.ndarray, np.ndarray]:
        """The part of dS that the base state (xbar, vbar) contributes: dS at the zero dual
        state, without the initial conditions."""
        c, dt, xbar, vbar = self.c, self.dt, self.xbar, self.vbar
        e, m = T["e"], T["m"]
        b_xi = -np.multiply.outer(e, xbar[cols]) - dt * np.multiply.outer(m, vbar[cols])
        b_eta = (dt * np.multiply.outer(m, (c["K"] @ xbar + c["D"] @ vbar)[cols])
                 - np.multiply.outer(e, (c["M"] @ vbar)[cols]))
        return b_xi, b_eta


_LAST_PRODUCTS: List = [None, None, None]  # (weak reference to a scene, its products, kinds)


def _scene_products(scene) -> Tuple[Dict[str, np.ndarray], Dict[str, Tuple[bool, bool]]]:
    """The coefficient matrices of a scene's slab residual and the (zero, diagonal) structure
    of each (`_RightFactor`), computed once per scene object (a simulation and its error
    companion share them; the products took 0.12 s for a 200-link column, 248 structure checks
    of 450 x 450 matrices 64 ms of a cauchy2d run)."""
    ref, products, kinds = _LAST_PRODUCTS
    if ref is not None and ref() is scene:
        return products, kinds
    c = scene.constants()
    M, K, D, A, B = (np.asarray(c[k], float) for k in ("M", "K", "D", "A", "B"))
    Ai, Bi = c["Ainv"], c["Binv"]
    products = {"M": M, "K": K, "D": D, "A": A, "B": B, "Ai": Ai, "Bi": Bi,
                "Ke": scene.energy_stiffness(),
                "AiKt": _product(Ai, K.T), "BiDt": _product(Bi, D.T), "BiM": _product(Bi, M),
                "KAi": _product(K, Ai), "KAiKt": _product(K, Ai, K.T), "DBi": _product(D, Bi),
                "DBiDt": _product(D, Bi, D.T), "DBiM": _product(D, Bi, M),
                "MBi": _product(M, Bi), "MBiDt": _product(M, Bi, D.T),
                "MBiM": _product(M, Bi, M)}
    kinds = {name: (not C.any(), _is_diagonal(C)) for name, C in products.items()}
    _LAST_PRODUCTS[:] = [weakref.ref(scene), products, kinds]
    return products, kinds


def _is_diagonal(C: np.ndarray) -> bool:
    """Whether every entry off the diagonal is 0 (and the diagonal finite), by counting: no n^2
    temporary (119 calls on 450 dofs took 0.08 s)."""
    d = np.diag(C)
    return np.count_nonzero(C) == np.count_nonzero(d) and bool(np.isfinite(d).all())


def _product(*factors: np.ndarray) -> np.ndarray:
    """The product of n x n matrices, at O(n) when all are diagonal (modal coordinates)."""
    if all(_is_diagonal(f) for f in factors):
        d = np.ones(len(factors[0]))
        for f in factors:
            d = d * np.diag(f)
        return np.diag(d)
    out = factors[0]
    for f in factors[1:]:
        out = out @ f
    return out


class _RightFactor:
    """Y @ C[:, cols] for a coefficient matrix C of the slab problem, at the cost its structure
    allows: nothing when C is zero (no damping), a scaling of Y's own columns when C is diagonal
    (modal coordinates), a dense product otherwise."""

    def __init__(self, C: np.ndarray, cols, structure: Optional[Tuple[bool, bool]] = None):
        """`structure`: (zero, diagonal) of C where known (of C or of its transpose)."""
        self.zero, self.diagonal = structure or (not C.any(), _is_diagonal(C))
        self.cols = cols
        if self.diagonal:
            self.d = np.diag(C)[cols]
        else:
            self.C = np.ascontiguousarray(C[:, cols])

    def __call__(self, Y: np.ndarray) -> np.ndarray:
        if self.diagonal:
            return Y[..., self.cols] * self.d
        return Y @ self.C if Y.ndim <= 2 else times_last(Y, self.C)  # (a stack: one BLAS call)


class KroneckerSampler:
    """Vertex values of the current dual state: momenta of the cell residuals (order 2p), the
    dual Hamiltonian from them and the nodal duals. Rank 0 returns them, the others None."""

    def __init__(self, problem: KroneckerProblem, with_dual: bool = True):
        self.p = problem
        self.with_dual = with_dual
        self.s = np.linspace(0.0, 1.0, problem.time.cells + 1)

    def __call__(self) -> Optional[VertexValues]:
        """Collective; the values on rank 0, None elsewhere."""
        linear = self.linear_part()
        if linear is None:
            return None
        return self.values(linear, self.p.xbar, self.p.vbar)

    def linear_part(self) -> Optional[np.ndarray]:
        """(vertices, 4n): x, v, xi, eta at the vertices, linear in the slab's start state.
        Collective: every rank computes the momenta of its own components, rank 0 gathers them
        (None elsewhere)."""
        p, t = self.p, self.p.time
        n = p.n
        Wc = p.W[t.cell_dofs]  # (cells, p + 1, 2n)

        def apply(X, W):  # an element matrix on every cell's (p + 1, n) block
            return np.einsum("ij,cjk->cik", X, W)

        r_xi, r_eta = p.residual(t.element, Wc[..., :n], Wc[..., n:], affine=True, apply=apply,
                                 cols=p.mine)
        k = len(p.mine)
        x = np.empty((t.cells + 1, k))
        mv = np.empty((t.cells + 1, k))
        x[:-1], mv[:-1] = r_xi[:, 0], r_eta[:, 0]  # left ends of the cells: +r
        right_x, right_mv = -r_xi[:, -1], -r_eta[:, -1]  # right ends: -r
        x[1:-1] = 0.5 * (x[1:-1] + right_x[:-1])
        mv[1:-1] = 0.5 * (mv[1:-1] + right_mv[:-1])
        x[-1], mv[-1] = right_x[-1], right_mv[-1]
        parts = p.comm.gather((x, mv), root=0)
        if parts is None:
            return None
        x = np.concatenate([q[0] for q in parts], axis=1)
        v = self.p.velocity(np.concatenate([q[1] for q in parts], axis=1))
        return np.hstack([x, v, p.W[::t.degree]])

    def values(self, linear: np.ndarray, xbar: np.ndarray, vbar: np.ndarray,
               hamiltonian: bool = True) -> VertexValues:
        """VertexValues from the linear part (vertices, 4n), or of many slabs (slabs,
        vertices, 4n) with their base states (slabs, 1, n), with H_d = xi.v + eta.F(x)
        - eta.D v + H(x - xbar, v - vbar) (left zero without `hamiltonian`)."""
        n, f = self.p.n, self.p.hamiltonian_factors
        x, v, xi, eta = (linear[..., k * n:(k + 1) * n] for k in range(4))
        if hamiltonian:
            dx, dv = x - xbar, v - vbar

            def dot(a, factor, b):  # a . (b C) over the last axis (C zero: 0)
                return 0.0 if factor.zero else np.einsum("...j,...j->...", a, factor(b))

            ham = (np.einsum("...j,...j->...", xi, v) - dot(eta, f["K"], x) - dot(eta, f["D"], v)
                   + 0.5 * dot(dx, f["A"], dx) + 0.5 * dot(dv, f["B"], dv))
        else:
            ham = np.zeros(linear.shape[:-1])
        values = VertexValues(s=self.s, x=x, v=v, hamiltonian=ham)
        if self.with_dual:
            values.xi, values.eta = xi, eta
        return values


def decoupled_blocks(c: Mapping) -> np.ndarray:
    """The block of each component (n,) of a slab problem whose matrices M, K, D, A, B couple
    only components within blocks (modal coordinates: one block per mode or per complex pair;
    a coupled problem is one block)."""
    coupling = sum(np.abs(np.asarray(c[k])) for k in ("M", "K", "D", "A", "B")) != 0
    return csgraph.connected_components(sparse.csr_matrix(coupling), directed=False)[1]


def probes(blocks: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Start states that solve every unit start state of a block-decoupled slab problem at once:
    (probes (P, 2n), gathers (P, 4n)). Probe (c, part) puts 1 on the c-th component of every
    block, in the positions (part 0) or the velocities (part 1); its response in a field
    component belongs to the unit start state gathers[p, column] (2n: none). So P = 2 x the
    largest block instead of 2n solves."""
    n = len(blocks)
    rank = np.zeros(n, dtype=int)  # each component's place within its block
    members: Dict[int, List[int]] = {}
    for j, b in enumerate(blocks):
        rank[j] = len(members.setdefault(int(b), []))
        members[int(b)].append(j)
    starts, gathers = [], []
    for place in range(int(rank.max()) + 1):
        owner = np.array([members[int(b)][place] if place < len(members[int(b)]) else -1
                          for b in blocks])  # the c-th member of each component's block
        for part in (0, 1):
            z = np.zeros(2 * n)
            z[part * n + np.flatnonzero(rank == place)] = 1.0
            column = np.where(owner >= 0, part * n + owner, 2 * n)
            starts.append(z)
            gathers.append(np.tile(column, 4))
    return np.array(starts), np.array(gathers)


class KroneckerSuperposition(Bases):
    """Slabs of a Kronecker problem from its 2n unit start states (see fem_dual.slab.superposition):
    x, v, xi, eta at the vertices are linear in z = (x0, v0), H_d follows from them. A problem
    that decouples into blocks (modal coordinates) solves 2 x its largest block probes
    (`probes`) instead of the 2n unit start states."""

    def __init__(self, problem: KroneckerProblem, solver: KroneckerSolver,
                 sampler: KroneckerSampler, T: float = 0.0):
        self.problem, self.solver, self.sampler = problem, solver, sampler
        self.T = T
        self._bases: Dict[float, Optional[Tuple[np.ndarray, Optional[np.ndarray]]]] = {}
        self._shared: set = set()
        self.basis_solves = 0
        n = problem.n
        self.blocks, starts, gathers = problem.block_probes()
        if len(starts) < 2 * n:
            self.starts, self.gathers = starts, gathers
        else:  # coupled: the unit start states, a dense basis
            self.starts, self.gathers = np.eye(2 * n), None

    @staticmethod
    def solves_per_basis(problem: KroneckerProblem) -> int:
        """Slab solves that one slab length's basis costs."""
        return min(2 * problem.n, len(problem.block_probes()[1]))

    def ensure(self, dt: float) -> None:
        """Solve the basis of slabs of length dt unless it is at hand, and check its slab map.
        Collective."""
        if refused(self._bases, dt):
            return
        p, n = self.problem, self.problem.n
        responses = []
        for z in self.starts:
            p.set_slab(z[:n], z[n:], dt)
            self.solver.solve()
            self.basis_solves += 1
            linear = self.sampler.linear_part()  # collective
            if linear is not None:
                responses.append(linear)
        self._bases[dt] = (np.stack(responses), self.gathers) if responses else None
        ends = None
        if responses:  # the slab map: end states (x, v) of the unit start states
            ends = self._linear(np.eye(2 * n), dt, last=True)[:, -1, :2 * n].T
        checked(self._bases, dt, lambda: stable_or_raise(
            p.comm, p.scene, ends, dt, self.T, None if self.gathers is None else self.blocks))

    def _linear(self, Z: np.ndarray, dt: float, last: bool = False) -> np.ndarray:
        """(slabs, vertices, 4n): x, v, xi, eta of the start states Z (slabs, 2n); with `last`
        at the slab's end only."""
        responses, gathers = self._bases[dt]
        if last:
            responses = responses[:, -1:]
        if gathers is None:
            return np.tensordot(Z, responses, axes=1)
        padded = np.hstack([Z, np.zeros((len(Z), 1))])  # column 2n: no start state
        return np.einsum("kpc,pvc->kvc", padded[:, gathers], responses)

    def batch(self, Z: np.ndarray, dt: float, fields: bool = True,
              last: bool = False) -> Optional[VertexValues]:
        """Vertex values of the slabs of length dt from the start states Z (slabs, 2n), with a
        leading slab axis, on rank 0 (None elsewhere); without `fields` only x and v (H_d
        zero, no dual fields); with `last` only at the slab's end. Collective the first time
        a slab length is seen."""
        self.ensure(dt)
        if self._bases[dt] is None:
            return None
        p, n = self.problem, self.problem.n
        linear = self._linear(Z, dt, last)
        if p.base == "start":
            xbar, vbar = Z[:, None, :n], Z[:, None, n:]
        else:
            xbar, vbar = p.xbar, p.vbar
        values = self.sampler.values(linear, xbar, vbar, hamiltonian=fields)
        if last:
            values.s = values.s[-1:]
        return select(values, fields, False)

    def __call__(self, x0: np.ndarray, v0: np.ndarray, dt: float) -> Optional[VertexValues]:
        return first(self.batch(np.concatenate([x0, v0])[None], dt))
