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
