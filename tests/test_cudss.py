"""The cuDSS backend (a GPU): solves of symmetric indefinite systems against scipy, the
refactorisation of one pattern shared by two factorisations, and the saddle-point solver
on cuDSS against SuperLU. Skipped where there is no GPU, CuPy or cuDSS (CI has none;
they run on a GPU machine: docs/performance.md, "The whole Newton iteration on a GPU")."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from eyefem.solve import cudss

pytestmark = pytest.mark.skipif(not cudss.available(), reason="needs a CUDA GPU, CuPy and "
                                "cuDSS (libcudss.so.0): none on this machine")


def _indefinite(n_side=14, shift=2.0):
    """A 3-D Laplacian (n_side^3 unknowns) shifted by ``shift`` times the identity: sparse,
    symmetric, indefinite (its spectrum spans 0..12 in 7-point units)."""
    one = sp.diags([-np.ones(n_side - 1), 2 * np.ones(n_side), -np.ones(n_side - 1)],
                   [-1, 0, 1])
    eye = sp.identity(n_side)
    lap = (sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye)
           + sp.kron(sp.kron(eye, eye), one))
    return sp.csr_matrix(lap - shift * sp.identity(n_side**3))


def test_cudss_solves_a_symmetric_indefinite_system():
    A = _indefinite()
    rng = np.random.default_rng(0)
    b = rng.standard_normal(A.shape[0])
    B = rng.standard_normal((A.shape[0], 4))
    fact = cudss.CuDSS(A)
    x, X = fact.solve(b), fact.solve(B)
    assert x.shape == b.shape and X.shape == B.shape
    np.testing.assert_allclose(x, spla.spsolve(A.tocsc(), b), rtol=1e-9, atol=1e-11)
    assert np.linalg.norm(A @ X - B) / np.linalg.norm(B) < 1e-10


def test_two_factorisations_of_one_pattern_stay_valid():
    """The second factorisation of a pattern reuses its analysis; the first, used again
    (an adjoint solve on an older tangent), is refactorised first."""
    A1 = _indefinite(shift=2.0)
    A2 = _indefinite(shift=0.5)
    b = np.random.default_rng(1).standard_normal(A1.shape[0])
    f1 = cudss.CuDSS(A1)
    f2 = cudss.CuDSS(A2)
    for A, f in ((A1, f1), (A2, f2), (A1, f1)):
        assert np.linalg.norm(A @ f.solve(b) - b) / np.linalg.norm(b) < 1e-10


def test_saddle_point_solver_on_cudss_matches_superlu():
    from eyefem.fem.generators import box
    from eyefem.fem.materials import MooneyRivlin
    from eyefem.solve.assembly import Assembler
    from eyefem.solve.model import node_dofs, solid_model

    mesh = box(3.0, 2.0, 2.0, 6, 4, 4)
    model = solid_model(mesh, {"default": MooneyRivlin("default", [[0, 0.01], [0.05, 0]])})
    held = np.zeros(model.n_dof, bool)
    held[node_dofs(mesh.node_sets["x0"])] = True
    q = np.zeros(model.n_dof)
    q[: 3 * mesh.n_nodes] = 0.02 * np.random.default_rng(2).standard_normal(3 * mesh.n_nodes)
    asm = Assembler(model, held)
    _, K, B, D, low_rank = asm.assemble(q, model.theta0())
    f = np.random.default_rng(3).standard_normal(asm.n_p)
    x_gpu, y_gpu = asm.solver(K, B, D, low_rank, "cudss").solve(f)
    x_cpu, y_cpu = asm.solver(K, B, D, low_rank, "superlu").solve(f)
    np.testing.assert_allclose(x_gpu, x_cpu, rtol=1e-8, atol=1e-10 * np.abs(x_cpu).max())
    np.testing.assert_allclose(y_gpu, y_cpu, rtol=1e-8, atol=1e-10 * np.abs(y_cpu).max())
