"""benchmarks/tissue_tests.py: the closed-form equibiaxial response of the wall's law
(docs/validation.md, "Tissue tests (compared, not fitted)") against one Q1P0 hexahedron of
the project's solid term, its small-strain stiffness 12 c10, and a wrong law caught."""

import importlib.util
from pathlib import Path

import jax
import numpy as np
import pytest

from eyefem.fem.generators import box
from eyefem.fem.solid import SolidQ1P0

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("tissue_tests",
                                                  ROOT / "benchmarks" / "tissue_tests.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def hexahedron_S(coeffs, E):
    """In-plane S11 (MPa) of a unit Q1P0 cube under F = diag(l, l, l^-2), l^2 = 1 + 2E, from
    the element's nodal forces (jax.grad of SolidQ1P0.local_energy): the multiplier
    is set so the z1 face carries no force (plane stress), then P11 = the x1 face's force /
    its reference area (1 mm^2), S11 = P11 / l."""
    mesh = box(1.0, 1.0, 1.0, 1, 1, 1)
    term = SolidQ1P0("solid", mesh, np.asarray(coeffs)[None], multiplier_offset=3 * mesh.n_nodes)
    lam = np.sqrt(1.0 + 2.0 * E)
    F = np.diag([lam, lam, lam ** -2])
    u = mesh.nodes @ (F - np.eye(3)).T

    def forces(mult):
        q = np.concatenate([u.ravel(), [mult]])
        g = jax.grad(lambda ql: term.local_energy(ql[None], term.params, term.data)[0])
        f = np.zeros((mesh.n_nodes, 3))
        np.add.at(f, mesh.hexes[0], np.asarray(g(q[term.dofs[0]]))[:24].reshape(8, 3))
        return f[mesh.node_sets["x1"], 0].sum(), f[mesh.node_sets["z1"], 2].sum()

    fx0, fz0 = forces(0.0)
    fx1, fz1 = forces(1.0)  # the forces are affine in the multiplier
    mult = -fz0 / (fz1 - fz0)
    fx = fx0 + mult * (fx1 - fx0)
    assert abs(fz0 + mult * (fz1 - fz0)) < 1e-12 * max(abs(fz0), 1.0)
    return fx / lam


@pytest.mark.parametrize("preset", ["seed", "physiological"])
def test_closed_form_equals_one_hexahedron(bench, preset):
    for tissue in ("sclera", "cornea"):
        c = bench.preset_coeffs(preset, tissue)
        strains = np.array([0.002, 0.01, 0.02, 0.04, 0.08])
        closed = np.asarray(bench.second_piola(strains, c))
        element = np.array([hexahedron_S(c, e) for e in strains])
        np.testing.assert_allclose(element, closed, rtol=1e-8)
        sigma = np.asarray(bench.cauchy(strains, c))
        np.testing.assert_allclose(sigma, (1 + 2 * strains) * element, rtol=1e-8)


@pytest.mark.parametrize("preset", ["seed", "physiological"])
def test_small_strain_stiffness_is_twelve_c10(bench, preset):
    c = bench.preset_coeffs(preset, "sclera")
    h = 1e-6
    s_minus, s_plus = np.asarray(bench.second_piola([-h, h], c))
    fd = (s_plus - s_minus) / (2 * h)  # central: the -48 c10 E^2 term cancels
    assert fd == pytest.approx(12 * c[1, 0], rel=1e-6)
    assert float(bench.tangent([0.0], c)[0]) == pytest.approx(12 * c[1, 0], rel=1e-12)


def test_a_law_without_its_cubic_term_is_caught(bench):
    """The physiological 4 % tangent is far above 12 c10 (the cubic term); a law that lost
    c30 would give about 12 c10 there and fail."""
    c = bench.preset_coeffs("physiological", "sclera")
    k4 = float(bench.tangent([0.04], c)[0])
    assert abs(k4 / (12 * c[1, 0]) - 1) > 0.5
    dropped = c.copy()
    dropped[3, 0] = 0.0
    assert abs(float(bench.tangent([0.04], dropped)[0]) / (12 * c[1, 0]) - 1) < 0.5
    rec = bench.law_record("physiological", "sclera")
    assert rec["small_strain_stiffness_MPa"] == pytest.approx(12 * 0.4132, rel=1e-12)
    assert rec["ratio_to_eilaghi"] == pytest.approx(12 * 0.4132 / 5.8, rel=1e-12)


def test_equibiaxial_equivalent_strain_inverts_the_invariant(bench):
    for E in (0.0, 0.005, 0.02, 0.05):
        a = float(bench.equibiaxial_invariants(E)[0]) - 3.0
        assert bench.equivalent_strain(a) == pytest.approx(E, abs=1e-12)
