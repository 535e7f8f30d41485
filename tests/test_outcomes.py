"""The peak scleral stress over a patch: the averaging matrix (closed form, rotation
invariance) and the whole outcome on a homogeneous deformation (closed-form stress); the
azimuthal wave numbers of a displacement of the outer surface."""

import numpy as np
import pytest

from eyefem.eye.eyemodel import build_eye
from eyefem.eye.outcomes import (
    STRESS_PATCH_MM,
    azimuthal_shares,
    peak_scleral_stress,
    stress_patches,
)
from eyefem.eye.presets import SEED_MATERIALS
from eyefem.fem.materials import MooneyRivlin
from eyefem.fem.mesh import hex_geometry
from eyefem.fem.units import KPA
from eyefem.solve.model import solid_model


@pytest.fixture(scope="module")
def eye_mesh():
    return build_eye(level="coarse").mesh


@pytest.fixture(scope="module")
def patches(eye_mesh):
    return stress_patches(eye_mesh)


def _sclera(mesh):
    return np.nonzero(mesh.material_ids == list(mesh.materials).index("sclera"))[0]


def test_patches_average_the_sclera_within_the_radius(eye_mesh, patches):
    sid = _sclera(eye_mesh)
    assert patches.shape == (len(sid), eye_mesh.n_elem)
    np.testing.assert_allclose(np.asarray(patches.sum(axis=1)).ravel(), 1.0, rtol=1e-13)
    others = np.setdiff1d(np.arange(eye_mesh.n_elem), sid)
    assert patches[:, others].nnz == 0  # only scleral elements are averaged
    centroids = eye_mesh.nodes[eye_mesh.hexes].mean(axis=1)
    vol = hex_geometry(eye_mesh.nodes, eye_mesh.hexes)[1].sum(axis=1)
    for i in (0, len(sid) // 2, len(sid) - 1):  # brute force: the volume-weighted mean
        near = sid[np.linalg.norm(centroids[sid] - centroids[sid[i]], axis=1) <= STRESS_PATCH_MM]
        want = np.zeros(eye_mesh.n_elem)
        want[near] = vol[near] / vol[near].sum()
        np.testing.assert_allclose(patches[i].toarray().ravel(), want, rtol=1e-12, atol=1e-15)
    # a spike in one element is diluted by its patch's volume; a uniform field is kept
    spike = np.zeros(eye_mesh.n_elem)
    spike[sid[5]] = 1.0
    assert (patches @ spike).max() == pytest.approx(patches[5, sid[5]], rel=1e-12)
    assert (patches @ spike).max() < 1.0
    np.testing.assert_allclose(patches @ np.full(eye_mesh.n_elem, 7.0), 7.0, rtol=1e-13)


def test_patches_are_invariant_under_a_rotation_of_the_mesh(eye_mesh, patches):
    a, b = 0.4, 1.1
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    Rx = np.array([[1.0, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    turned = stress_patches(eye_mesh.replace(nodes=eye_mesh.nodes @ (Rx @ Rz).T))
    assert abs(turned - patches).max() < 1e-12


def test_peak_scleral_stress_of_a_homogeneous_stretch_is_the_closed_form(eye_mesh, patches):
    """An isochoric stretch lam along z of neo-Hookean tissue (W = c10 (I1bar - 3)):
    von Mises stress 2 c10 (lam^2 - 1 / lam) in every element, so in every patch."""
    mats = {m: MooneyRivlin.from_terms(m, {"c10": SEED_MATERIALS[m]}) for m in eye_mesh.materials}
    model = solid_model(eye_mesh, mats)
    lam = 1.05
    F = np.diag([lam ** -0.5, lam ** -0.5, lam])
    q = np.zeros(model.n_dof)
    q[: 3 * eye_mesh.n_nodes] = (eye_mesh.nodes @ (F - np.eye(3)).T).ravel()
    theta = {"solid": model.terms[0].params}
    want = 2 * SEED_MATERIALS["sclera"] * (lam**2 - 1 / lam) / KPA
    assert peak_scleral_stress(model, q, theta, patches) == pytest.approx(want, rel=1e-10)


@pytest.mark.parametrize("wave", [0, 2, 3])
def test_azimuthal_shares_of_a_pure_harmonic(eye_mesh, wave):
    """A radial displacement sin^2(polar) cos(m phi) of the outer surface is wave number m:
    the other shares are what its change across a band's 15 degrees of polar angle leaks
    through the uneven azimuths of the nodes (below 0.1%), and the rest is what the bands
    next to the apex and the pole (too few nodes to fit) hold (below 2%)."""
    X = eye_mesh.nodes
    radial = X / np.linalg.norm(X, axis=1, keepdims=True)
    sin2 = 1.0 - radial[:, 2] ** 2
    u = radial * (sin2 * np.cos(wave * np.arctan2(X[:, 1], X[:, 0])))[:, None]
    shares = azimuthal_shares(eye_mesh, u)
    assert shares[wave] > 0.98 and shares[-1] < 0.02
    assert np.delete(shares[:-1], wave).max() < 1e-3
    assert shares.sum() == pytest.approx(1.0)


# --------------------------------------------------------------------------- indentation

def _parts(buckle, level="coarse"):
    from eyefem.eye.surgery import surgery
    from eyefem.eye.variables import default_parameters

    return surgery(default_parameters(mesh=level, buckle=buckle), None).parts


@pytest.fixture(scope="module", params=["coarse", "half"])
def tire_parts(request):
    return _parts("tire_flat", request.param)


@pytest.fixture(scope="module")
def sponge_parts():
    return _parts("sponge_radial")


def _zone(parts, a0, a1, f=lambda a: 1.0, n=20001):
    """Closed form on the sphere of the sclera: integral of f(a) dA over the zone a0 < a <
    a1 about an encircling buckle's centre line (a = R (theta - theta_b), mm), mm^2."""
    g, b = parts.eye.geometry, parts.buckle
    R, thb = g.scleral_radius, b.centre_angle(g)
    a = np.linspace(a0, a1, n)
    return np.trapezoid(f(a) * 2 * np.pi * R * np.sin(thb + a / R), a)


def test_encircling_band_areas_are_the_sphere_zones(tire_parts):
    """The bands' areas against the zones of the scleral sphere: the faces are flat
    (chordal) and the band's edges are sampled at 6 x 6 Gauss points per face, so they
    agree to the square of the element size over the radius (1.3 mm / 11.5 mm: 1.3 %)."""
    from eyefem.eye.outcomes import band_area_weights

    w = tire_parts.buckle.width
    under, beside = band_area_weights(tire_parts, False), band_area_weights(tire_parts, True)
    exact_under = _zone(tire_parts, -w / 4, w / 4)
    exact_beside = _zone(tire_parts, w / 2 + 1.5, w / 2 + 3) * 2
    assert under.area_mm2 == pytest.approx(exact_under, rel=0.025)
    assert beside.area_mm2 == pytest.approx(exact_beside, rel=0.01)
    for bw in (under, beside):
        assert np.all(bw.weights > 0) and bw.weights.sum() == pytest.approx(1.0, abs=1e-14)
        assert np.isin(bw.ids, tire_parts.sclera_nodes).all()


def test_indentation_of_a_radial_field_is_its_area_mean(tire_parts):
    """A radial displacement eps a^2 of the wall: the indentation is the area mean of eps
    a^2 beside the buckle minus under it (closed form on the sphere), to 0.5 % on both
    levels; the bands' plain node means missed it by -9 % (coarse) and -3 % (half), with
    the sign and size changing from level to level."""
    from eyefem.eye.outcomes import indentation, outcome_nodes

    parts, eps = tire_parts, 0.01
    g, b = parts.eye.geometry, parts.buckle
    X = parts.eye.mesh.nodes
    R = np.linalg.norm(X, axis=1)
    a = g.scleral_radius * (np.arccos(X[:, 2] / R) - b.centre_angle(g))
    q = np.zeros(3 * len(X) + 8)
    q[: 3 * len(X)] = (X / R[:, None] * (eps * a**2)[:, None]).ravel()
    w, sq = b.width, lambda a: a**2
    lo, hi = w / 2 + 1.5, w / 2 + 3
    mean_beside = 2 * _zone(parts, lo, hi, sq) / (2 * _zone(parts, lo, hi))
    mean_under = _zone(parts, -w / 4, w / 4, sq) / _zone(parts, -w / 4, w / 4)
    exact = eps * (mean_beside - mean_under)
    assert float(indentation(X, q, outcome_nodes(parts))) == pytest.approx(exact, rel=5e-3)


def test_segmental_bands_lie_on_the_buckles_side_of_the_globe(sponge_parts):
    """A segmental buckle's bands: a 2.5 x 4 mm patch under its central half and two 1.5 x
    4 mm strips beside it, their areas on the sphere the closed form
    integral R / sqrt(R^2 - x^2 - y^2) dx dy over their projections onto the buckle's
    tangent plane, to 6 % (coarse mesh: elements of 1.8 mm against strips 1.5 mm wide,
    whose edges cut the faces between their 6 x 6 Gauss points; measured 1.5 % and 5.3 %);
    every node within 8 mm of the buckle's centre (the antipodal sclera, 23 mm away, has
    small across and along coordinates too)."""
    from scipy import integrate

    from eyefem.eye.buckles import suture_anchor_frame
    from eyefem.eye.outcomes import band_area_weights

    parts = sponge_parts
    R, w = parts.eye.geometry.scleral_radius, parts.buckle.width
    cen = suture_anchor_frame(parts.buckle, parts.eye.geometry, 1)[0][0]
    dA = lambda y, x: R / np.sqrt(R**2 - x**2 - y**2)  # noqa: E731
    exact_under = integrate.dblquad(dA, -w / 4, w / 4, -2, 2)[0]
    exact_beside = 2 * integrate.dblquad(dA, w / 2 + 1.5, w / 2 + 3, -2, 2)[0]
    under, beside = band_area_weights(parts, False), band_area_weights(parts, True)
    assert under.area_mm2 == pytest.approx(exact_under, rel=0.06)
    assert beside.area_mm2 == pytest.approx(exact_beside, rel=0.06)
    X = parts.eye.mesh.nodes
    for bw in (under, beside):
        assert np.linalg.norm(X[bw.ids] - cen, axis=1).max() < 8.0



# --------------------------------------------------------------------------- plausibility

def test_plausibility_ratios_of_a_made_up_state():
    """The peak scleral stress over the sclera's strength and the largest suture force over
    a tied suture's breaking load: 4.7 MPa is half of 9.4 MPa, 0.75 N a quarter of 3 N."""
    from eyefem.eye.outcomes import SCLERA_STRENGTH_MPA, SUTURE_BREAK_N, plausibility

    out = plausibility(4700.0, 0.75)
    assert out == {"scleral_stress_fraction_of_strength": pytest.approx(0.5, rel=1e-14),
                   "suture_force_fraction_of_break": pytest.approx(0.25, rel=1e-14)}
    assert (SCLERA_STRENGTH_MPA, SUTURE_BREAK_N) == (9.4, 3.0)


def test_the_strength_constants_name_their_sources():
    """The constants' docstrings (the string literals that follow them) cite the paper and
    the figure each value is read from."""
    import inspect

    from eyefem.eye import outcomes as oc

    src = inspect.getsource(oc)
    i = src.index("SCLERA_STRENGTH_MPA = 9.4")
    assert "Stapp Car Crash Journal 46" in src[i:i + 800] and "9.4 MPa" in src[i:i + 800]
    j = src.index("SUTURE_BREAK_N = 3.0")
    assert "307.6 g" in src[j:j + 900] and "28989101" in src[j:j + 900]


def test_outcomes_report_the_ratios_of_their_own_stress_and_force():
    """outcomes() at a made-up displacement of the coarse eye (seed case 1's model): the
    two fractions are the reported peak stress and suture force over the constants."""
    from eyefem.eye.outcomes import outcomes, plausibility
    from eyefem.eye.surgery import surgery
    from eyefem.eye.variables import default_parameters

    setup = surgery(default_parameters(mesh="coarse", buckle="tire_flat"), None)
    model, theta = setup.model, setup.model.theta0()
    rng = np.random.default_rng(0)
    q = np.zeros(model.n_dof)
    q[:model.n_u] = 1e-3 * rng.standard_normal(model.n_u)
    out = outcomes(setup.parts, model, q, theta)
    assert out["scleral_stress_kPa"] > 1.0  # a random field strains the sclera
    want = plausibility(out["scleral_stress_kPa"], out["max_suture_force_N"])
    for k, v in want.items():
        assert out[k] == pytest.approx(v, rel=1e-14), k
