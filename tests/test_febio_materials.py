"""FEBio's materials (issue 77): the nearly incompressible uncoupled Mooney-Rivlin with
U(J) = k/2 (ln J)^2 on the element's volume ratio, and the coupled neo-Hookean and
Mooney-Rivlin (eyefem.fem.materials, eyefem.fem.solid_compressible), against closed forms,
finite differences, rigid rotations, the incompressible limit and FEBio's own regression
results.
"""

import os
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq

from eyefem.fem import generators
from eyefem.fem.materials import (CoupledMooneyRivlin, MooneyRivlin, UncoupledMooneyRivlin,
                                  febio_neo_hookean, mooney_rivlin)
from eyefem.fem.mesh import Mesh
from eyefem.fem.solid import SolidQ1P0
from eyefem.fem.solid_compressible import SolidCompressible
from eyefem.io.febio import FebError, write_feb
from eyefem.io.febio_read import build_model, read_feb, solution_norm
from eyefem.solve.problem import Setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage, solve


# --------------------------------------------------------------------------- closed forms
def uncoupled_stress(lam, mu, c1, c2, k):
    """Principal Cauchy stresses (3,) of W = c1 (I1bar - 3) + c2 (I2bar - 3) + k/2 ln^2 J
    at F = diag(lam, mu, mu): dev[(2/J)((c1 + I1bar c2) bbar - c2 bbar^2)] + k ln J / J."""
    J = lam * mu * mu
    b = J ** (-2.0 / 3.0) * np.array([lam ** 2, mu ** 2, mu ** 2])
    t = 2.0 / J * ((c1 + b.sum() * c2) * b - c2 * b * b)
    return t - t.mean() + k * np.log(J) / J


def coupled_stress(lam, mu, c1, c2, lmb):
    """Principal Cauchy stresses of FEBio's coupled Mooney-Rivlin (FECoupledMooneyRivlin::
    Stress): (2/J)((c1 + I1 c2) b - c2 b^2 - (c1 + 2 c2)) + lam ln J / J."""
    J = lam * mu * mu
    b = np.array([lam ** 2, mu ** 2, mu ** 2])
    return 2.0 / J * ((c1 + b.sum() * c2) * b - c2 * b * b - (c1 + 2 * c2)) \
        + lmb * np.log(J) / J


def uniaxial_closed_form(stress, lam):
    """(lateral stretch, axial force on a unit face) of uniaxial stress: the lateral stretch
    from sigma_yy = 0 (a scalar root find), the force sigma_xx mu^2."""
    mu = brentq(lambda m: stress(lam, m)[1], 0.2, 2.0, xtol=1e-15, rtol=1e-15)
    return mu, stress(lam, mu)[0] * mu * mu


def solve_uniaxial(mat, lam, n=2):
    """A unit cube of n^3 hexahedra with symmetry planes x = y = z = 0, x = 1 moved to lam:
    (lateral stretch of the face y = 1, axial reaction on x = 1, N)."""
    mesh = generators.box(1.0, 1.0, 1.0, n, n, n, material=mat.name)
    model = solid_model(mesh, {mat.name: mat})
    held = [node_dofs(mesh.node_set(s), c) for s, c in (("x0", "x"), ("y0", "y"), ("z0", "z"))]
    pull = node_dofs(mesh.node_set("x1"), "x")
    dofs = np.concatenate(held + [pull])
    vals = np.r_[np.zeros(sum(len(h) for h in held)), np.full(len(pull), lam - 1.0)]
    q = np.asarray(solve(model, [Stage("pull", 4, (dofs, vals))]).q)
    u = q[: 3 * mesh.n_nodes].reshape(-1, 3)
    lateral = 1.0 + u[mesh.node_set("y1"), 1]
    assert np.ptp(lateral) < 1e-10  # homogeneous
    force = float(model.gradient(q, model.theta0())[pull].sum())
    return model, float(lateral.mean()), force


UNCOUPLED = (1.0, 0.5, 10.0)  # c1, c2, k (MPa): Poisson's ratio about 0.39
NEO = (3.0, 0.3)  # E (MPa), v
COUPLED = (0.6, 0.2, 4.0)  # c1, c2, k of FEBio's coupled Mooney-Rivlin


@pytest.mark.parametrize("lam", [1.3, 0.8])
def test_uncoupled_mooney_rivlin_uniaxial(lam):
    c1, c2, k = UNCOUPLED
    mat = MooneyRivlin.from_terms("rubber", {"c10": c1, "c01": c2, "k": k})
    assert isinstance(mat, UncoupledMooneyRivlin) and mat.k == k
    model, mu, force = solve_uniaxial(mat, lam)
    assert [type(t) for t in model.terms] == [SolidCompressible]
    assert model.n_dof == 3 * model.mesh.n_nodes  # no multipliers
    mu_ref, f_ref = uniaxial_closed_form(lambda a, m: uncoupled_stress(a, m, c1, c2, k), lam)
    assert abs(mu - mu_ref) < 1e-9
    assert abs(force - f_ref) < 1e-9 * abs(f_ref)
    # compressible: the volume changes (J = 1.113 in tension, 0.89 in compression)
    assert abs(lam * mu * mu - 1.0) > 0.05


@pytest.mark.parametrize("lam", [1.3, 0.8])
def test_coupled_neo_hookean_uniaxial(lam):
    E, v = NEO
    mat = febio_neo_hookean("gel", E, v)
    mu0 = E / (2 * (1 + v))
    assert mat.c1 == pytest.approx(mu0 / 2) and mat.c2 == 0.0
    assert mat.lam == pytest.approx(v * E / ((1 + v) * (1 - 2 * v)))
    _, mu, force = solve_uniaxial(mat, lam)
    mu_ref, f_ref = uniaxial_closed_form(
        lambda a, m: coupled_stress(a, m, mat.c1, 0.0, mat.lam), lam)
    assert abs(mu - mu_ref) < 1e-9
    assert abs(force - f_ref) < 1e-9 * abs(f_ref)


def test_coupled_mooney_rivlin_uniaxial():
    c1, c2, k = COUPLED
    _, mu, force = solve_uniaxial(CoupledMooneyRivlin("rubber", c1, c2, k), 1.25)
    mu_ref, f_ref = uniaxial_closed_form(lambda a, m: coupled_stress(a, m, c1, c2, k), 1.25)
    assert abs(mu - mu_ref) < 1e-9
    assert abs(force - f_ref) < 1e-9 * abs(f_ref)


def test_small_strain_moduli():
    """The coupled laws' initial moduli: neo-Hookean's E and v come back from a small
    uniaxial stretch (sigma_xx / eps -> E, -eps_yy / eps_xx -> v)."""
    E, v = NEO
    mat = febio_neo_hookean("gel", E, v)
    eps = 1e-6
    mu, _ = uniaxial_closed_form(lambda a, m: coupled_stress(a, m, mat.c1, 0.0, mat.lam),
                                 1 + eps)
    s = coupled_stress(1 + eps, mu, mat.c1, 0.0, mat.lam)[0]
    assert s / eps == pytest.approx(E, rel=1e-5)
    assert (1 - mu) / eps == pytest.approx(v, rel=1e-5)
    assert mat.bulk_modulus == pytest.approx(E / (3 * (1 - 2 * v)))


# --------------------------------------------------------------------------- the element
def _element_term():
    """One distorted hexahedron with every part of the energy on: c10, c01, c20 (uncoupled),
    k, and coupled constants (c1, c2, lam)."""
    rng = np.random.default_rng(7)
    box = generators.box(1.0, 1.2, 0.8, 1, 1, 1)
    X = box.nodes[box.hexes[0]] + 0.08 * rng.standard_normal((8, 3))
    mesh = Mesh(X, np.arange(8)[None], np.array([0]), ("m",))
    c = np.zeros((1, 4, 4))
    c[0, 1, 0], c[0, 0, 1], c[0, 2, 0] = 0.8, 0.3, 0.2
    term = SolidCompressible("solid", mesh, c, np.array([5.0]), np.array([[0.4, 0.2, 3.0]]))
    u = 0.15 * rng.standard_normal(24)
    return term, u


def test_residual_and_tangent_against_finite_differences():
    term, u = _element_term()
    p, d = term.params, term.data
    e = jax.jit(lambda x: term.local_energy(x[None], p, d)[0])
    kernel = jax.jit(term.local_grad_hess)  # compiled: eager JAX takes 10 s a call here
    g, H = (np.asarray(a)[0] for a in kernel(jnp.asarray(u)[None], p, d))
    # exact derivatives of the energy (autodiff) and the kernel's closed-form contraction
    assert np.allclose(g, jax.jit(jax.grad(e))(jnp.asarray(u)), rtol=0,
                       atol=1e-12 * np.abs(g).max())
    assert np.allclose(H, jax.jit(jax.hessian(e))(jnp.asarray(u)), rtol=0,
                       atol=1e-11 * np.abs(H).max())
    assert np.allclose(H, H.T, atol=1e-12 * np.abs(H).max())
    # central differences of the energy and of the residual
    h = 1e-6
    basis = np.eye(24)
    energy = lambda x: float(e(jnp.asarray(x)))  # noqa: E731
    g_fd = np.array([(energy(u + h * b) - energy(u - h * b)) / (2 * h) for b in basis])
    assert np.abs(g_fd - g).max() < 1e-7 * np.abs(g).max()
    grad = lambda x: np.asarray(kernel(jnp.asarray(x)[None], p, d)[0][0])  # noqa: E731
    H_fd = np.stack([(grad(u + h * b) - grad(u - h * b)) / (2 * h) for b in basis], axis=1)
    assert np.abs(H_fd - H).max() < 1e-6 * np.abs(H).max()


def _rotation(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_rigid_rotation_invariance():
    term, u = _element_term()
    p, d = term.params, term.data
    energy = jax.jit(lambda v: term.local_energy(v[None], p, d)[0])
    force = jax.jit(lambda v: term.local_grad_hess(v[None], p, d)[0][0])
    X = term.mesh.nodes
    R = _rotation([1.0, -2.0, 0.5], 0.9)
    x = X + u.reshape(8, 3)
    u_rot = ((x @ R.T) - X).ravel()
    e0, e1 = (float(energy(jnp.asarray(v))) for v in (u, u_rot))
    assert e1 == pytest.approx(e0, rel=1e-12)
    g0, g1 = (np.asarray(force(jnp.asarray(v))).reshape(8, 3) for v in (u, u_rot))
    assert np.allclose(g1, g0 @ R.T, atol=1e-11 * np.abs(g0).max())  # forces rotate with it
    rigid = ((X @ R.T) - X).ravel()  # a rotation alone stores nothing, pushes nothing
    assert abs(float(energy(jnp.asarray(rigid)))) < 1e-13
    assert np.abs(np.asarray(force(jnp.asarray(rigid)))).max() < 1e-12


def _clamped_block(mat):
    """A 2 x 1 x 1 block of 4 x 2 x 2 hexahedra clamped on x = 0, its face x = 2 pulled
    0.4 mm along x and 0.2 mm along z (an inhomogeneous state): (u (n, 3), reaction (3,))."""
    mesh = generators.box(2.0, 1.0, 1.0, 4, 2, 2, material=mat.name)
    model = solid_model(mesh, {mat.name: mat})
    clamp = node_dofs(mesh.node_set("x0"), "xyz")
    end = mesh.node_set("x1")
    dofs = np.r_[clamp, node_dofs(end, "x"), node_dofs(end, "z")]
    vals = np.r_[np.zeros(len(clamp)), np.full(len(end), 0.4), np.full(len(end), 0.2)]
    q = np.asarray(solve(model, [Stage("pull", 4, (dofs, vals))]).q)
    r = model.gradient(q, model.theta0())
    return q[: 3 * mesh.n_nodes].reshape(-1, 3), r[node_dofs(end, "xyz")].reshape(-1, 3).sum(0)


def test_large_bulk_modulus_recovers_the_incompressible_element():
    """k -> infinity: U(Jbar) drives each element's Jbar to 1, the Q1P0 element's
    constraint; the difference falls like mu / k."""
    u_inc, f_inc = _clamped_block(mooney_rivlin("rubber", 1.0, 0.2))
    errs = []
    for k in (1e2, 1e4):
        u, f = _clamped_block(MooneyRivlin.from_terms("rubber", {"c10": 1.0, "c01": 0.2, "k": k}))
        errs.append((np.abs(u - u_inc).max() / np.abs(u_inc).max(),
                     np.linalg.norm(f - f_inc) / np.linalg.norm(f_inc)))
    assert errs[1][0] < 2e-4 and errs[1][1] < 2e-4
    assert errs[1][0] < errs[0][0] / 50 and errs[1][1] < errs[0][1] / 50


def test_mixed_materials_split_between_the_elements():
    """A block of an exactly incompressible and a nearly incompressible material: the
    first keeps Q1P0 elements with multipliers, the second the displacement element."""
    mesh = generators.box(2.0, 1.0, 1.0, 2, 1, 1, material="a")
    mesh = Mesh(mesh.nodes, mesh.hexes, np.array([0, 1]), ("a", "b"), mesh.node_sets,
                mesh.face_sets)
    mats = {"a": mooney_rivlin("a", 1.0, 0.0),
            "b": MooneyRivlin.from_terms("b", {"c10": 1.0, "k": 20.0})}
    model = solid_model(mesh, mats)
    assert [(type(t), t.name, list(t.elements)) for t in model.terms] == [
        (SolidQ1P0, "solid", [0]), (SolidCompressible, "solid_compressible", [1])]
    assert model.n_dof == 3 * mesh.n_nodes + 1
    assert list(model.multiplier_dofs) == [3 * mesh.n_nodes]


def test_material_constructors():
    assert type(MooneyRivlin.from_terms("r", {"c10": 1.0, "k": 0.0})) is MooneyRivlin
    assert type(mooney_rivlin("r", 1.0, 0.0)) is MooneyRivlin
    for bad in (-1.0, float("inf")):
        with pytest.raises(ValueError, match="bulk modulus"):
            MooneyRivlin.from_terms("r", {"c10": 1.0, "k": bad})
    with pytest.raises(ValueError, match="-1 < v < 0.5"):
        febio_neo_hookean("g", 1.0, 0.5)
    with pytest.raises(ValueError, match="c1 > 0"):
        CoupledMooneyRivlin("r", 0.0, 0.1, 1.0)


def test_case_files_read_k_for_verification_only(tmp_path):
    from eyefem.catalog import schemas
    from eyefem.io.casefile import CaseError, load_case

    text = ('[case]\nproblem = "{p}"\n[parameters]\n[materials.{m}]\nc10 = 1.0\nk = 50.0\n')
    f = tmp_path / "u.toml"
    f.write_text(text.format(p="uniaxial", m="rubber"))
    case = load_case(f, schemas())
    assert isinstance(case.materials["rubber"], UncoupledMooneyRivlin)
    assert case.materials["rubber"].k == 50.0
    f.write_text(text.format(p="surgery", m="sclera"))
    with pytest.raises(CaseError, match="exactly incompressible"):
        load_case(f, schemas())


# --------------------------------------------------------------------------- FEBio decks
def _setup(mat):
    mesh = generators.box(1.0, 1.0, 1.0, 2, 2, 2, material=mat.name)
    model = solid_model(mesh, {mat.name: mat})
    held = [node_dofs(mesh.node_set(s), c) for s, c in (("x0", "x"), ("y0", "y"), ("z0", "z"))]
    pull = node_dofs(mesh.node_set("x1"), "x")
    stage = Stage("pull", 2, (np.concatenate(held + [pull]),
                              np.r_[np.zeros(sum(len(h) for h in held)), np.full(len(pull), 0.2)]))
    return Setup("cube", model, [stage], lambda *a: {}, lambda *a: {})


@pytest.mark.parametrize("mat, febio_type", [
    (MooneyRivlin.from_terms("rubber", {"c10": 1.0, "c01": 0.5, "k": 10.0}), "Mooney-Rivlin"),
    (febio_neo_hookean("rubber", 3.0, 0.3), "neo-Hookean"),
    (CoupledMooneyRivlin("rubber", 0.6, 0.2, 4.0), "coupled Mooney-Rivlin"),
])
def test_febio_laws_written_and_read_back(tmp_path, mat, febio_type):
    deck = tmp_path / "cube.feb"
    assert write_feb(_setup(mat), deck) == []
    assert f'type="{febio_type}"' in deck.read_text()
    _, mats, loads = read_feb(deck)
    back = mats["rubber"]
    assert type(back) is type(mat)
    if isinstance(mat, CoupledMooneyRivlin):
        assert (back.c1, back.c2, back.lam) == pytest.approx((mat.c1, mat.c2, mat.lam),
                                                             rel=1e-12)
    else:
        assert back.k == mat.k and np.array_equal(back.coeffs, mat.coeffs)
        assert loads.bulk_moduli == {"rubber": mat.k}


def _deck(tmp_path, mat=None, edit=None):
    deck = tmp_path / "cube.feb"
    write_feb(_setup(mat or MooneyRivlin.from_terms("rubber", {"c10": 1.0, "k": 10.0})), deck)
    if edit:
        deck.write_text(edit(deck.read_text()))
    return deck


def test_deck_mooney_rivlin_uses_its_bulk_modulus(tmp_path):
    mesh, mats, loads = read_feb(_deck(tmp_path))
    model, stage = build_model(mesh, mats, loads)
    assert [type(t) for t in model.terms] == [SolidCompressible]
    q = np.asarray(solve(model, [stage]).q)
    mu_ref, _ = uniaxial_closed_form(lambda a, m: uncoupled_stress(a, m, 1.0, 0.0, 10.0), 1.2)
    assert 1.0 + q[3 * mesh.node_set("y1") + 1].mean() == pytest.approx(mu_ref, abs=1e-9)


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.replace('type="Mooney-Rivlin"', 'type="Shenoy"'), "type 'Shenoy' is not supported"),
    (lambda s: s.replace("<c1>", "<pressure_model>NIKE3D</pressure_model><c1>"),
     "pressure_model"),
    (lambda s: s.replace("<c1>", "<laugon>2</laugon><c1>"), "laugon"),
    (lambda s: s.replace("<c1>", "<mystery>1</mystery><c1>"), "parameter <mystery>"),
    (lambda s: s.replace('<SolidDomain ', '<SolidDomain three_field="off" '), "three_field"),
    (lambda s: s.replace('<SolidDomain ', '<SolidDomain elem_type="HEX8G1" '), "HEX8G1"),
    (lambda s: s.replace("<analysis>", "<use_three_field_hex>0</use_three_field_hex><analysis>"),
     "use_three_field_hex"),
])
def test_deck_refusals_name_what_is_not_implemented(tmp_path, edit, message):
    with pytest.raises(FebError, match=message):
        read_feb(_deck(tmp_path, edit=edit))


def test_deck_augmented_lagrangian_is_exactly_incompressible(tmp_path):
    """<laugon>1</laugon>: FEBio's augmentations drive each element's Jbar to 1, the Q1P0
    constraint; eyefem's export writes it for its incompressible materials."""
    deck = _deck(tmp_path, edit=lambda s: s.replace("<c1>", "<laugon>1</laugon><c1>"))
    _, mats, _ = read_feb(deck)
    assert type(mats["rubber"]) is MooneyRivlin
    deck = tmp_path / "inc.feb"
    write_feb(_setup(mooney_rivlin("rubber", 1.0, 0.0)), deck)
    assert "<laugon>1</laugon>" in deck.read_text()
    assert type(read_feb(deck)[1]["rubber"]) is MooneyRivlin


def test_deck_neo_hookean_out_of_range(tmp_path):
    deck = _deck(tmp_path, febio_neo_hookean("rubber", 3.0, 0.3),
                 edit=lambda s: re.sub(r"<v>[^<]*</v>", "<v>0.5</v>", s))
    with pytest.raises(FebError, match="0 <= v < 0.5"):
        read_feb(deck)


# FEBio's own answers to its regression decks (febiosoftware/TestSuite, Verify/*.feb): the
# test task logs the L2 norm of the solution vector (the displacements of every dof with
# an equation: neither fixed nor prescribed) at the last step (FELogSolutionNorm), and
# code/linuxGoldStandards.py records it (commit e8ac0860ef05). The decks are not part of
# eyefem; set EYEFEM_FEBIO_VERIFY to a checkout's Verify folder to run them.
FEBIO_SOLUTION_NORMS = {"mi03": 1.1783901556, "tu01": 14.9958440769, "mi26": 2.02115312832,
                        "mi27": 4.17586115304, "mi30": 1881.63452986,
                        # the further laws (eyefem.fem.materials.FEBIO_LAWS)
                        "mi02": 1.41848905154, "ma01": 7.73149507271, "ma02": 7.50244860312,
                        "ma03": 8.67037056864, "ma11": 10.5130342097, "ma12": 7.88551331741,
                        "ma47": 1.18909671349, "ma48": 8.13977478303, "ma61": 3.60823970452,
                        "ma73": 1.40538741563, "fi02": 0.836223007889,
                        "fi06": 4.53416034107, "fi11": 4.52684046357,
                        "ma20": 0.493408719039, "ma23": 0.185712126746}
"""The FEBio gold norms of the decks the test solves (all one step). The tolerance is
FEBio's against eyefem's convergence tolerances: the classic laws agree to 1.2e-5, the
further ones to 1.3e-3 (ma61, Yeoh: FEBio's looser residual test) and 5e-5 or better
(the others)."""




@pytest.mark.skipif(not os.environ.get("EYEFEM_FEBIO_VERIFY"),
                    reason="EYEFEM_FEBIO_VERIFY (FEBio's TestSuite/Verify folder) not set")
@pytest.mark.parametrize("name", sorted(FEBIO_SOLUTION_NORMS))
def test_febio_regression_decks(name):
    deck = Path(os.environ["EYEFEM_FEBIO_VERIFY"]) / f"{name}.feb"
    mesh, mats, loads = read_feb(deck)
    model, stage = build_model(mesh, mats, loads)
    q = solve(model, [stage]).q
    assert solution_norm(mesh, stage, q, loads) == pytest.approx(
        FEBIO_SOLUTION_NORMS[name], rel=2e-3 if name == "ma61" else 1e-4)


def test_the_problems_that_take_a_bulk_modulus_are_the_verification_ones_and_user_mesh():
    """eyefem.io.casefile names them (io does not import the problems above it)."""
    from eyefem.io.casefile import BULK_MODULUS_PROBLEMS
    from eyefem.problems.user_mesh import PROBLEMS as user_mesh
    from eyefem.problems.verification import PROBLEMS as verification

    assert BULK_MODULUS_PROBLEMS == set(verification) | set(user_mesh)
