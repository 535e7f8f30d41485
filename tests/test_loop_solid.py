"""A closed encircling loop tightened by shortening its rest length (eyefem.fem.loop_solid)."""

import numpy as np
import pytest

from eyefem.eye.buckle_meshes import deformable_band, ring_fit_groups
from eyefem.eye.buckles import Buckle
from eyefem.eye.eyemodel import EyeGeometry
from eyefem.fem.loop_solid import ShortenedLoopSolid
from eyefem.fem.materials import neo_hookean
from eyefem.fem.mesh import hex_geometry
from eyefem.solve.model import Model, node_dofs
from eyefem.solve.solver import Stage, solve

SHORTENING = 6.0  # mm


@pytest.fixture(scope="module")
def ring():
    """A closed ridged tire (24 elements around, radius 12 mm) alone, as one model."""
    mesh = deformable_band(Buckle("tire_ridged", 12.0), EyeGeometry(), 12.0, 24, closed=True)
    c = neo_hookean("tire", 1.0).coeffs[None]
    term = ShortenedLoopSolid("solid", mesh, c, 3 * mesh.n_nodes, loop_nodes=np.arange(mesh.n_nodes))
    return mesh, Model(mesh, (term,), 3 * mesh.n_nodes + mesh.n_elem)


def _radial_shift(X, s):
    rho = np.hypot(X[:, 0], X[:, 1])
    return -s / (2 * np.pi) * np.column_stack([X[:, 0] / rho, X[:, 1] / rho, np.zeros(len(X))])


def _theta(model, s):
    th = model.theta0()
    return {**th, "solid": {**th["solid"], "shortening": s}}


def test_closed_ring_mesh_has_no_cut():
    g, b = EyeGeometry(), Buckle("tire_ridged", 12.0)
    open_, closed = (deformable_band(b, g, 12.0, 24, closed=c) for c in (False, True))
    per_level = open_.n_nodes // 25
    assert closed.n_nodes == open_.n_nodes - per_level and closed.n_elem == open_.n_elem
    np.testing.assert_array_equal(closed.node_set("end0"), closed.node_set("end1"))
    assert hex_geometry(closed.nodes, closed.hexes)[2].min() > 0
    # every face inside the loop is shared by two elements: no face on the +y meridian
    faces = closed.face_set("inner")
    assert not np.any(np.all(np.isclose(closed.nodes[faces][..., 0], 0.0), axis=1))
    assert len(ring_fit_groups(b, 24, closed=True)) == closed.n_nodes


def test_shortened_ring_moved_to_its_rest_shape_is_stress_free(ring):
    mesh, model = ring
    q = np.zeros(model.n_dof)
    q[: 3 * mesh.n_nodes] = _radial_shift(mesh.nodes, SHORTENING).ravel()
    th = _theta(model, SHORTENING)
    assert abs(model.energy(q, th)) < 1e-12
    assert np.abs(model.gradient(q, th)).max() < 1e-12
    # at the original radius the shortened ring is stretched: energy and hoop tension
    assert model.energy(np.zeros(model.n_dof), th) > 1e-2


def test_free_ring_contracts_by_shortening_over_two_pi(ring):
    """Newton from the original radius: the free ring (held against its rigid motion
    only) settles on the radius reduced by shortening / (2 pi), stress-free."""
    mesh, model = ring
    X = mesh.nodes  # held along the loop where it crosses the x and y axes, z on its centre line
    held = np.r_[node_dofs(mesh.node_set("mid"), "z"), node_dofs(np.nonzero(np.abs(X[:, 0]) < 1e-9)[0], "x"),
                 node_dofs(np.nonzero(np.abs(X[:, 1]) < 1e-9)[0], "y")]
    sol = solve(model, [Stage("shorten", 2, (held, 0.0), params={"solid": {"shortening": SHORTENING}})])
    u = sol.q[: 3 * mesh.n_nodes].reshape(-1, 3)
    np.testing.assert_allclose(u, _radial_shift(mesh.nodes, SHORTENING), atol=1e-8)
    assert model.term("solid").tension(sol.q, sol.theta["solid"]) == pytest.approx(0.0, abs=1e-8)


def test_energy_is_invariant_to_rotation_about_the_axis(ring):
    mesh, model = ring
    rng = np.random.default_rng(3)
    th = _theta(model, SHORTENING)
    u = 0.05 * rng.standard_normal((mesh.n_nodes, 3)) + _radial_shift(mesh.nodes, 2.0)
    a = 0.4
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    q1, q2 = np.zeros(model.n_dof), np.zeros(model.n_dof)
    q1[: 3 * mesh.n_nodes] = u.ravel()
    q2[: 3 * mesh.n_nodes] = ((mesh.nodes + u) @ R.T - mesh.nodes).ravel()
    e1, e2 = model.energy(q1, th), model.energy(q2, th)
    assert e1 > 1e-3
    assert e2 == pytest.approx(e1, rel=1e-12)


def test_tension_is_the_energy_rate_and_positive_when_stretched(ring):
    mesh, model = ring
    term = model.term("solid")
    q = np.zeros(model.n_dof)
    q[: 3 * mesh.n_nodes] = _radial_shift(mesh.nodes, 2.0).ravel()
    h, th = 1e-5, _theta(model, SHORTENING)
    fd = (model.energy(q, _theta(model, SHORTENING + h))
          - model.energy(q, _theta(model, SHORTENING - h))) / (2 * h)
    T = term.tension(q, th["solid"])
    assert T > 0.1  # N: 4 mm of the 6 mm left to take up by stretching
    assert T == pytest.approx(fd, rel=1e-6)
    # loop element fields come from the shortened reference: hoop tension in the tire
    f = term.fields(q, th["solid"])
    assert np.all(f["von_mises"] > 0) and np.all(np.isfinite(f["cauchy"]))
