"""Hand-coded residuals/tangents vs autodiff vs finite differences, plus closed forms."""

import numpy as np
import pytest

from eyefem.fem.materials import MooneyRivlin, invariant_derivatives
from eyefem.fem.mesh import HEX_CORNERS
from eyefem.verify.handcoded import q1p0_residual_tangent, stress_and_tangent
from eyefem.verify.tangents import format_table, random_deformation, verify_tangents


@pytest.fixture(scope="module")
def checks():
    return {s: verify_tangents(seed=s) for s in (0, 1, 2)}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_term_agrees(checks, seed):
    for c in checks[seed]:
        assert c.r_hand < 1e-8 and c.K_hand < 1e-8, c
        assert c.K_fd < 1e-5, c
    names = {c.name for c in checks[seed]}
    assert {"solid_q1p0_generalised", "follower_pressure", "orbit_spring", "suture_bar",
            "fluid_cavity", "rigid_contact", "surface_contact_sliding",
            "surface_contact_sticking", "tied_suture_bar", "surface_contact_smoothed",
            "surface_contact_nodal_normals", "solid_q1p0_shortened_loop",
            "solid_q1p0_incompatible_modes", "buckle_contact_nodes", "buckle_contact_faces",
            "buckle_contact_sponge_end"} <= names
    assert "FAIL" not in format_table(checks[seed])


def test_hand_tangent_is_objective():
    """Rotating the deformed element rotates residual and tangent: r' = Q r, K' = Q K Q^T."""
    rng = np.random.default_rng(5)
    X = HEX_CORNERS * 0.5
    c = MooneyRivlin.from_terms("m", {"c10": 0.5, "c01": 0.2, "c20": 0.1}).coeffs
    F = random_deformation(rng)
    u = X @ F.T - X + 0.05 * rng.standard_normal((8, 3))
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))
    r1, K1 = q1p0_residual_tangent(X, u, 0.3, c)
    r2, K2 = q1p0_residual_tangent(X, (X + u) @ Q.T - X, 0.3, c)
    R = np.kron(np.eye(8), Q)
    np.testing.assert_allclose(r2[:24], R @ r1[:24], atol=1e-12 * np.abs(r1).max())
    np.testing.assert_allclose(K2[:24, :24], R @ K1[:24, :24] @ R.T, atol=1e-11 * np.abs(K1).max())
    assert r2[24] == pytest.approx(r1[24], abs=1e-14)


@pytest.mark.parametrize("terms", [{"c10": 25.0}, {"c10": 25.0, "c01": 5.0}])
def test_equibiaxial_closed_form_from_hand_stress(terms):
    """sigma_11 - sigma_33 = 2 (l^2 - l^-4)(W1 + l^2 W2) for F = diag(l, l, l^-2)."""
    mat = MooneyRivlin.from_terms("m", terms)
    for lam in (1.2, 2.0, 5.8):
        F = np.diag([lam, lam, lam**-2])
        S, _ = stress_and_tangent(F, 0.0, mat.coeffs)
        sig = F @ S @ F.T
        w1, w2 = invariant_derivatives(2 * lam**2 + lam**-4, lam**4 + 2 * lam**-2, mat.coeffs)
        assert sig[0, 0] - sig[2, 2] == pytest.approx(
            2 * (lam**2 - lam**-4) * (w1 + lam**2 * w2), rel=1e-12)


def test_q1p0_kernel_in_chunks_equals_the_kernel_at_once(monkeypatch):
    """The Q1P0 tangent kernel evaluated over chunks of elements in turn (KERNEL_CHUNK,
    eyefem.fem.solid.chunked; padded last chunk) gives the blocks of the whole at once,
    element by element, to round-off."""
    import jax

    from eyefem.fem import solid
    from eyefem.fem.generators import box

    jax.config.update("jax_enable_x64", True)
    mesh = box(2.0, 1.0, 1.0, 5, 3, 3)  # 45 elements: chunks of 7 leave 4 padded
    coeffs = MooneyRivlin.from_terms("default", {"c10": 0.1, "c01": 0.02}).coeffs[None]
    term = solid.SolidQ1P0("solid", mesh, coeffs, multiplier_offset=3 * mesh.n_nodes)
    rng = np.random.default_rng(0)
    q = np.concatenate([0.05 * rng.standard_normal(3 * mesh.n_nodes),
                        0.01 * rng.standard_normal(mesh.n_elem)])
    backend = jax.default_backend()
    monkeypatch.setitem(solid.KERNEL_CHUNK, backend, None)
    whole = jax.jit(term.grad_hess_condensed)(q, term.params, term.data, term.dofs, 1e4)
    monkeypatch.setitem(solid.KERNEL_CHUNK, backend, 7)
    parts = jax.jit(term.grad_hess_condensed)(q, term.params, term.data, term.dofs, 1e4)
    assert len(parts) == len(whole) == 4
    for a, b in zip(parts, whole):
        assert a.shape == b.shape and a.shape[0] == mesh.n_elem
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12,
                                   atol=1e-14 * float(np.abs(np.asarray(b)).max()))


def test_adjoint_kernels_in_chunks_equal_the_kernels_at_once(monkeypatch):
    """The adjoint's kernels (k tangent-vector products, the residual's design derivative
    along k columns: sums over the elements) accumulated over chunks of elements in turn
    (eyefem.solve.model.SUM_CHUNK, eyefem.fem.solid.chunked_sum; with and without a
    remainder) equal the kernels over all elements at once to round-off."""
    import jax

    from eyefem.fem import solid
    from eyefem.fem.generators import box
    from eyefem.solve import model as model_mod

    jax.config.update("jax_enable_x64", True)
    mesh = box(2.0, 1.0, 1.0, 5, 3, 3)  # 45 elements
    coeffs = MooneyRivlin.from_terms("default", {"c10": 0.1, "c01": 0.02}).coeffs[None]
    term = solid.SolidQ1P0("solid", mesh, coeffs, multiplier_offset=3 * mesh.n_nodes)
    rng = np.random.default_rng(1)
    n = 3 * mesh.n_nodes + mesh.n_elem
    q = np.concatenate([0.05 * rng.standard_normal(3 * mesh.n_nodes),
                        0.01 * rng.standard_normal(mesh.n_elem)])
    V = rng.standard_normal((n, 3))
    kernels = {
        "hvp_many": jax.vmap(model_mod._hvp(term), in_axes=(None, 1, None, None, None),
                             out_axes=1),
        "params_vjp_many": jax.vmap(model_mod._params_vjp(term),
                                    in_axes=(None, 1, None, None, None)),
    }
    backend = jax.default_backend()
    for name, fn in kernels.items():
        whole = jax.jit(fn)(q, V, term.params, term.data, term.dofs)
        for chunk in (7, 9):  # 6 chunks and 3 left over; 5 chunks exactly
            monkeypatch.setitem(model_mod.SUM_CHUNK, backend, chunk)
            parts = jax.jit(model_mod._over_chunks(term, fn))(q, V, term.params, term.data,
                                                              term.dofs)
            for a, b in zip(jax.tree_util.tree_leaves(parts), jax.tree_util.tree_leaves(whole)):
                b = np.asarray(b)
                assert np.abs(b).max() > 0, name
                np.testing.assert_allclose(np.asarray(a), b, rtol=0,
                                           atol=1e-13 * float(np.abs(b).max()), err_msg=name)


def test_closed_form_cofactor_and_determinant_of_the_q1p0_kernel():
    """The tangent kernel's closed-form cof F = det(F) F^-T and det F (the 2 x 2 minors,
    eyefem.fem.solid.cofactor / det3) equal LAPACK's determinant and inverse to round-off,
    for general, nearly singular and inverted F, batched over leading axes; and the
    kernel's blocks are those of autodiff of the element energy (the kernel's check)."""
    import jax

    from eyefem.fem import solid
    from eyefem.fem.generators import box
    from eyefem.fem.terms import Term

    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(3)
    F = np.concatenate([np.eye(3) + 0.3 * rng.standard_normal((40, 3, 3)),
                        np.diag([1.0, 1.0, 1e-6])[None],  # nearly singular
                        np.diag([1.0, 1.0, -0.5])[None]])  # inverted
    F = F.reshape(6, 7, 3, 3)
    det, inv = np.linalg.det(F), np.linalg.inv(F)
    cof = np.asarray(solid.cofactor(F))
    np.testing.assert_allclose(cof, det[..., None, None] * np.swapaxes(inv, -1, -2),
                               rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(solid.det3(F)), det, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(solid.det3(F, cof)), det, rtol=1e-12, atol=1e-15)
    mesh = box(1.0, 1.0, 1.0, 2, 2, 1)
    coeffs = MooneyRivlin.from_terms("m", {"c10": 0.1, "c01": 0.02, "c11": 0.01}).coeffs[None]
    term = solid.SolidQ1P0("solid", mesh, coeffs, multiplier_offset=3 * mesh.n_nodes)
    q = np.concatenate([0.1 * rng.standard_normal(3 * mesh.n_nodes),
                        0.01 * rng.standard_normal(mesh.n_elem)])
    q_loc = q[term.dofs]
    g, H = jax.jit(term.local_grad_hess)(q_loc, term.params, term.data)  # not eager: 20 s
    g_ad, H_ad = jax.jit(lambda *a: Term.local_grad_hess(term, *a))(q_loc, term.params,
                                                                   term.data)
    np.testing.assert_allclose(np.asarray(g), np.asarray(g_ad), rtol=1e-11,
                               atol=1e-13 * float(np.abs(g_ad).max()))
    np.testing.assert_allclose(np.asarray(H), np.asarray(H_ad), rtol=1e-11,
                               atol=1e-13 * float(np.abs(H_ad).max()))
