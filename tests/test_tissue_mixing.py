"""Elements cut by a tissue boundary store the volume-weighted mixture of the tissues'
energies (Mesh.material_fractions, eyefem.fem.solid.element_coeffs,
EyeGeometry.tissue_mixing; docs/convergence.md, "Tissue boundaries")."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from eyefem.fem.generators import box
from eyefem.fem.materials import MooneyRivlin
from eyefem.fem.mesh import hex_geometry, merge
from eyefem.fem.solid import SolidQ1P0
from eyefem.fem.terms import host_kernel

jax.config.update("jax_enable_x64", True)

COEFFS = np.stack([MooneyRivlin.from_terms("a", {"c10": 0.08, "c01": 0.01}).coeffs,
                   MooneyRivlin.from_terms("b", {"c10": 0.03, "c20": 0.2, "c11": 0.05}).coeffs])


def _two_material_box(fractions=None):
    """A 3 x 2 x 2 box of materials a and b (12 elements, alternating ids)."""
    mesh = box(1.5, 1.0, 1.0, 3, 2, 2)
    mesh = mesh.replace(material_ids=np.arange(mesh.n_elem) % 2, materials=("a", "b"))
    return mesh if fractions is None else mesh.replace(material_fractions=fractions)


def _state(mesh, seed=0):
    rng = np.random.default_rng(seed)
    return np.concatenate([0.08 * rng.standard_normal(3 * mesh.n_nodes),
                           0.01 * rng.standard_normal(mesh.n_elem)])


def _blocks(mesh, q):
    term = SolidQ1P0("solid", mesh, COEFFS, multiplier_offset=3 * mesh.n_nodes)
    q_loc = q[term.dofs]
    energy = host_kernel(term, "local_energy")(q_loc, term.params, term.data)
    g, H = host_kernel(term, "local_grad_hess")(q_loc, term.params, term.data)
    return term, np.asarray(energy), np.asarray(g), np.asarray(H)


def test_a_mixed_element_stores_the_fractions_mixture_of_its_tissues_energies():
    """Energy, gradient and Hessian of an element with fractions (f, 1 - f) are f times
    those of the element wholly a plus (1 - f) times wholly b: W is linear in c_rs, and
    the multiplier's term is the same in both (the fractions sum to 1)."""
    mesh = _two_material_box()
    f = np.random.default_rng(1).uniform(0.0, 1.0, mesh.n_elem)
    q = _state(mesh)
    _, e_mix, g_mix, h_mix = _blocks(mesh.replace(material_fractions=np.stack([f, 1 - f], 1)), q)
    _, e_a, g_a, h_a = _blocks(mesh.replace(material_ids=np.zeros(mesh.n_elem, int)), q)
    _, e_b, g_b, h_b = _blocks(mesh.replace(material_ids=np.ones(mesh.n_elem, int)), q)
    assert np.ptp(e_a - e_b) > 1e-3 * np.abs(e_a).max()  # the tissues differ
    np.testing.assert_allclose(e_mix, f * e_a + (1 - f) * e_b, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(g_mix, f[:, None] * g_a + (1 - f[:, None]) * g_b,
                               rtol=1e-11, atol=1e-13 * np.abs(g_a).max())
    np.testing.assert_allclose(h_mix, f[:, None, None] * h_a + (1 - f[:, None, None]) * h_b,
                               rtol=1e-11, atol=1e-13 * np.abs(h_a).max())


def test_whole_fractions_give_the_elements_of_their_material_exactly():
    """Fractions that put every element wholly in its material change nothing."""
    mesh = _two_material_box()
    q = _state(mesh, 2)
    _, e0, g0, h0 = _blocks(mesh, q)
    term, e1, g1, h1 = _blocks(mesh.replace(material_fractions=np.eye(2)[mesh.material_ids]), q)
    assert "mix" in term.data
    np.testing.assert_allclose(e1, e0, rtol=1e-14)
    np.testing.assert_allclose(g1, g0, rtol=1e-13, atol=1e-16)
    np.testing.assert_allclose(h1, h0, rtol=1e-13, atol=1e-16)


def test_mixed_kernel_residual_and_tangent_agree_with_autodiff_and_differences():
    """The closed-form Q1P0 blocks of mixed elements against autodiff of their energy and
    central differences of the gradient (every energy term's check), and the energy is
    unchanged by a rigid rotation of the deformed element (objectivity)."""
    f = np.random.default_rng(3).uniform(0.0, 1.0, 12)
    mesh = _two_material_box(np.stack([f, 1 - f], 1))
    q = _state(mesh, 4)
    term, energy, g, H = _blocks(mesh, q)
    q_loc = jnp.asarray(q[term.dofs])

    def total(ql):
        return jnp.sum(term.local_energy(ql, term.params, term.data))

    g_ad = np.asarray(jax.grad(total)(q_loc))
    np.testing.assert_allclose(g, g_ad, rtol=1e-10, atol=1e-12 * np.abs(g_ad).max())
    h = 1e-6
    for e, k in ((0, 3), (5, 17), (11, 24)):
        dq = np.zeros(q_loc.shape)
        dq[e, k] = h
        gp = np.asarray(jax.grad(total)(q_loc + dq))[e]
        gm = np.asarray(jax.grad(total)(q_loc - dq))[e]
        np.testing.assert_allclose(H[e, :, k], (gp - gm) / (2 * h), rtol=1e-6,
                                   atol=1e-7 * np.abs(H[e]).max())
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])
    x = mesh.nodes + q[: 3 * mesh.n_nodes].reshape(-1, 3)
    q_rot = np.concatenate([(x @ R.T - mesh.nodes).ravel(), q[3 * mesh.n_nodes:]])
    _, e_rot, _, _ = _blocks(mesh, q_rot)
    np.testing.assert_allclose(e_rot, energy, rtol=1e-11)


@pytest.mark.parametrize("fractions, message", [
    (np.ones((12, 3)) / 3, "shape (12, 3); expected (12, 2)"),
    (np.array([[1.2, -0.2]] + [[1.0, 0.0]] * 11), "element 0: material fractions [1.2, -0.2]"),
    (np.array([[1.0, 0.0]] * 7 + [[0.5, 0.4]] + [[1.0, 0.0]] * 4), "element 7"),
])
def test_fractions_that_are_not_a_partition_of_the_element_are_refused(fractions, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("(", r"\(")
                       .replace(")", r"\)").replace("]", r"\]")):
        _two_material_box(fractions)


def test_merge_keeps_the_fractions_under_the_joined_material_names():
    """A mixed part keeps its fractions under the merged materials' columns; a part
    without fractions is wholly its materials."""
    f = np.random.default_rng(5).uniform(0.0, 1.0, 12)
    mixed = _two_material_box(np.stack([f, 1 - f], 1))
    plain = box(1.0, 1.0, 1.0, 1, 1, 2)
    plain = plain.replace(material_ids=np.array([0, 1]), materials=("c", "a"))
    joined = merge(("p", plain), ("m", mixed))
    assert joined.materials == ("c", "a", "b")
    np.testing.assert_array_equal(joined.material_fractions[:2], [[1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(joined.material_fractions[2:, 0], 0.0)
    np.testing.assert_allclose(joined.material_fractions[2:, 1], f)
    np.testing.assert_allclose(joined.material_fractions[2:, 2], 1 - f)
    assert merge(("p", plain), ("q", plain)).material_fractions is None


@pytest.fixture(scope="module")
def mixed_eyes():
    from eyefem.eye.eyemodel import EyeGeometry, build_eye

    return {lv: (build_eye(EyeGeometry(), lv), build_eye(EyeGeometry(tissue_mixing=True), lv))
            for lv in ("coarse", "half", "default")}


def _tissue_volumes(mesh, fractions):
    _, dv, _ = hex_geometry(mesh.nodes, mesh.hexes)
    return dict(zip(mesh.materials, dv.sum(axis=1) @ fractions))


def test_the_mixed_eye_keeps_its_labels_and_gives_each_tissue_its_volume_on_every_level(
        mixed_eyes):
    """With tissue_mixing the elements keep their centroid's tissue as label, only the
    cut ones mix, and the cornea's and the limbus ring's volumes agree across the coarse,
    half and default levels within 3 % (recorded: cornea 53.6, 52.8, 52.9 mm^3; limbus
    35.8, 36.1, 36.7 mm^3), where the staircase's limbus ring is 40.9, 39.9, 36.2 mm^3
    (13 % apart)."""
    cornea, limbus, stair_limbus = [], [], []
    for plain, mixed in mixed_eyes.values():
        m = mixed.mesh
        np.testing.assert_array_equal(m.material_ids, plain.mesh.material_ids)
        f = m.material_fractions
        np.testing.assert_allclose(f.sum(axis=1), 1.0, rtol=1e-12)
        cut = f.max(axis=1) < 1.0 - 1e-12
        assert 0.02 < cut.mean() < 0.12  # the elements along the boundaries only
        whole = ~cut
        np.testing.assert_array_equal(np.argmax(f[whole], axis=1), m.material_ids[whole])
        v = _tissue_volumes(m, f)
        cornea.append(v["cornea"])
        limbus.append(v["limbus"])
        stair_limbus.append(_tissue_volumes(m, np.eye(len(m.materials))[m.material_ids])["limbus"])
    assert np.ptp(cornea) / np.mean(cornea) < 0.03
    assert np.ptp(limbus) / np.mean(limbus) < 0.03
    assert np.ptp(stair_limbus) / np.mean(stair_limbus) > 0.1


def test_tissue_mixing_needs_a_limbus_ring_and_a_yes_or_no():
    from eyefem.eye.eyemodel import EyeGeometry

    with pytest.raises(ValueError, match="tissue_mixing needs a limbus ring of fixed width"):
        EyeGeometry(tissue_mixing=True, limbus_width=None)
    with pytest.raises(ValueError, match="tissue_mixing = 'yes'; must be true or false"):
        EyeGeometry(tissue_mixing="yes")


def test_a_case_file_turns_tissue_mixing_on(tmp_path):
    """`tissue_mixing = true` in a surgical case file reaches the eye's solid term."""
    from eyefem.catalog import problems, schemas
    from eyefem.io.casefile import load_case

    case_path = tmp_path / "c.toml"
    case_path.write_text('[case]\nproblem = "surgery"\n[parameters]\nmesh = "coarse"\n'
                         'buckle = "band"\ntissue_mixing = true\n')
    case = load_case(case_path, schemas())
    setup = problems()[case.problem][1](case.parameters, case.materials)
    solid = setup.model.term("solid")
    assert "mix" in solid.data
    assert np.any(solid.data["mix"].max(axis=1) < 1.0)
