"""SpatialSystem: free-dof restriction, maps between free vectors and fields, initial fields
from expressions, gathered copies and export."""
import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from dolfinx.fem import petsc as fem_petsc
from mpi4py import MPI
from scipy.sparse import csr_matrix

from fem_dual.continua import SpatialSystem
from fem_dual.continua.dofs import gather_csr
from fem_dual.errors import InputError


def clamped_vector_system(n=4, degree=2, damping=False):
    msh = mesh.create_unit_square(MPI.COMM_WORLD, n, n)
    V = fem.FunctionSpace(msh, ufl.VectorElement("Lagrange", msh.ufl_cell(), degree))
    msh.topology.create_connectivity(1, 2)
    facets = mesh.exterior_facet_indices(msh.topology)
    bc = fem.dirichletbc(np.zeros(2), fem.locate_dofs_topological(V, 1, facets), V)
    u, w = ufl.TrialFunction(V), ufl.TestFunction(V)
    k = ufl.inner(ufl.grad(u), ufl.grad(w)) * ufl.dx + u[0].dx(1) * w[1] * ufl.dx
    d = 0.1 * ufl.inner(u, w) * ufl.dx if damping else None
    return SpatialSystem(V, [bc], ufl.inner(u, w) * ufl.dx, k, d)


def mixed_interval_system(n=6):
    msh = mesh.create_interval(MPI.COMM_WORLD, n, [0.0, 2.0])
    el = ufl.FiniteElement("Lagrange", msh.ufl_cell(), 2)
    W = fem.FunctionSpace(msh, ufl.MixedElement([el, ufl.FiniteElement("Lagrange",
                                                                        msh.ufl_cell(), 1)]))
    left = mesh.locate_entities_boundary(msh, 0, lambda x: np.isclose(x[0], 0.0))
    dofs = [fem.locate_dofs_topological(W.sub(i), 0, left) for i in range(2)]
    (a, b), (da, db) = ufl.split(ufl.TrialFunction(W)), ufl.split(ufl.TestFunction(W))
    m = a * da * ufl.dx + b * db * ufl.dx
    k = a.dx(0) * da.dx(0) * ufl.dx + (a.dx(0) - b) * db * ufl.dx
    return SpatialSystem(W, dofs, m, k)


@pytest.mark.serial
@pytest.mark.parametrize("build", [clamped_vector_system, mixed_interval_system])
def test_restriction_is_the_free_block_of_the_full_matrix(build):
    S = build()
    A = fem_petsc.assemble_matrix(S.forms["k"])
    A.assemble()
    full = gather_csr(A).toarray()
    M, K, D = S.dense()
    assert np.array_equal(K, full[np.ix_(S.free, S.free)])
    assert S.n == S.free.size and not np.any(D)
    constrained = np.setdiff1d(np.arange(S.layout.owned), S.free)
    x = S.layout.coordinates[constrained]
    on_boundary = np.isclose(x, 0.0).any(axis=1) | np.isclose(x, 1.0).any(axis=1)
    assert constrained.size and np.all(on_boundary)
    A.destroy()


@pytest.mark.mpi
def test_damping_form_is_assembled_when_given():
    S = clamped_vector_system(damping=True)
    M, K, D = S.dense()
    assert S.has_damping and np.allclose(D, 0.1 * M, rtol=0, atol=1e-15)


@pytest.mark.mpi
def test_free_vector_and_function_round_trip_with_ghosts():
    S = clamped_vector_system()
    q = S.interpolate(["sin(pi*x)*sin(pi*y)", "x*y*(1-x)*(1-y)"])
    u = S.to_function(q)
    assert np.array_equal(S.from_function(u), q)
    # ghosts hold their owners' values: an owned re-interpolation agrees on every local dof
    imap = S.V.dofmap.index_map
    total = (imap.size_local + imap.num_ghosts) * S.V.dofmap.index_map_bs
    x = S.layout.coordinates
    exact = np.where(S.layout.field == 0, np.sin(np.pi * x[:, 0]) * np.sin(np.pi * x[:, 1]),
                     x[:, 0] * x[:, 1] * (1 - x[:, 0]) * (1 - x[:, 1]))
    assert u.x.array.size == total
    boundary = np.isclose(x, 0.0).any(axis=1) | np.isclose(x, 1.0).any(axis=1)
    assert np.allclose(u.x.array[~boundary], exact[~boundary], atol=1e-14)
    assert np.all(u.x.array[boundary] == 0.0)


@pytest.mark.mpi
def test_interpolate_takes_parameters_and_the_mesh_coordinates():
    S = mixed_interval_system()
    q = S.interpolate(["a*x**2", "cos(x)"], {"a": 3.0})
    x = S.coordinates[:, 0]
    assert np.allclose(q, np.where(S.field == 0, 3.0 * x**2, np.cos(x)), atol=1e-14)
    assert np.allclose(S.interpolate(["2", "0"]), np.where(S.field == 0, 2.0, 0.0))


@pytest.mark.mpi
@pytest.mark.parametrize("exprs, message", [
    (["x", "y"], "coordinate 'y' does not exist"),
    (["x"], "1 expression(s) for 2 field components"),
    (["x, x", "0"], "2 components"),
    (["b*x", "0"], "unknown name 'b'"),
    (["m*x", "0"], "parameter 'm'"),
    (["__import__('os')", "0"], "not allowed"),
])
def test_interpolate_refuses_bad_text(exprs, message):
    S = mixed_interval_system()
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        S.interpolate(exprs)


@pytest.mark.mpi
def test_export_npz_holds_the_gathered_system(tmp_path):
    S = clamped_vector_system(damping=True)
    q = S.interpolate(["x*(1-x)*y", "0"])
    path = MPI.COMM_WORLD.bcast(str(tmp_path / "system.npz"), root=0)
    S.export_npz(path, q, 2 * q)
    M, K, D = S.dense()
    if MPI.COMM_WORLD.rank == 0:
        data = np.load(path)
        for name, A in (("M", M), ("K", K), ("D", D)):
            B = csr_matrix((data[f"{name}_data"], data[f"{name}_indices"],
                            data[f"{name}_indptr"]), shape=tuple(data[f"{name}_shape"]))
            assert np.array_equal(B.toarray(), A)
        x, field = data["coordinates"], data["field"]
        assert x.shape == (S.n, 2) and field.shape == (S.n,)
        assert np.allclose(data["u0"], np.where(field == 0, x[:, 0] * (1 - x[:, 0]) * x[:, 1], 0))
        assert np.array_equal(data["v0"], 2 * data["u0"])


@pytest.mark.mpi
def test_export_to_a_missing_folder_raises_on_every_rank(tmp_path):
    S = mixed_interval_system()
    path = MPI.COMM_WORLD.bcast(str(tmp_path / "missing" / "x.npz"), root=0)
    with pytest.raises(InputError, match="cannot write"):
        S.export_npz(path, S.zeros(), S.zeros())


@pytest.mark.mpi
def test_dense_refuses_large_systems():
    S = clamped_vector_system()
    with pytest.raises(ValueError, match="limit"):
        S.dense(limit=10)


@pytest.mark.mpi
def test_gather_and_scatter_are_inverse():
    S = clamped_vector_system()
    q = S.offset + np.arange(S.n_local, dtype=float)
    g = S.gather(q)
    if MPI.COMM_WORLD.rank == 0:
        assert np.array_equal(g, np.arange(S.n, dtype=float))
    assert np.array_equal(S.scatter(g), q)
