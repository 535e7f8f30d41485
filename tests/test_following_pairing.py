"""The adjoint's tangent of node-to-segment contact: the pairing's target points follow the
state (SurfaceContact.following_pairing, eyefem.fem.contact.followed_xi), as re-pairing
every Newton iterate makes them, where the pairing's own energy holds them fixed."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from eyefem.fem import generators
from eyefem.fem.contact import SurfaceContact
from eyefem.fem.mesh import merge
from eyefem.solve.adjoint import following
from eyefem.solve.model import solid_model
from eyefem.fem.materials import mooney_rivlin

PARAMS = {"scale": 1.0}


def _pressed(smoothing):
    """A 4x4 block (0.6 mm square) sunk into the top of a 3x3 one (1 mm square) and
    displaced at random: every slave node's closest point lies inside a master face (none
    clamped to an edge), on faces that are not flat."""
    lo = generators.box(1, 1, 0.5, 3, 3, 1, material="r")
    hi = generators.box(0.6, 0.6, 0.5, 4, 4, 1, origin=(0.2, 0.2, 0.5), material="r")
    m = merge(("lo", lo), ("hi", hi))
    rng = np.random.default_rng(4)
    q = 0.03 * rng.standard_normal(3 * m.n_nodes)
    q[2::3][m.node_set("hi")] -= 0.02
    t = SurfaceContact("c", m, "hi/z0", "lo/z1", penalty=1e3, smoothing=smoothing).update(q, None)
    return m, t, q, rng.standard_normal(len(q))


def _grad(term, q):
    return np.asarray(jax.grad(lambda y: term.energy(y, PARAMS, term.data, term.dofs))(
        jnp.asarray(q)))


def _hvp(term, q, v):
    g = jax.grad(lambda y: term.energy(y, PARAMS, term.data, term.dofs))
    return np.asarray(jax.jvp(g, (jnp.asarray(q),), (jnp.asarray(v),))[1])


@pytest.mark.parametrize("smoothing", [None, 0.01])
def test_following_pairing_tangent_is_the_repaired_residuals_derivative(smoothing):
    """At a state paired at itself the following term's residual is the pairing's (to
    roundoff); its tangent-vector product is the central difference of the residual
    re-paired at q +- h v (step 1e-6 mm: the differences' error is O(h^2), measured
    8e-11 relative), where the held pairing's tangent misses it by about 6 %."""
    _, t, q, v = _pressed(smoothing)
    f = t.following_pairing()
    assert t.n_pairs >= 20 and not np.any(np.abs(t.data["xi"][t.data["w"] > 0]) >= 1 - 1e-9)
    g = _grad(t, q)
    np.testing.assert_allclose(_grad(f, q), g, rtol=0, atol=1e-12 * np.abs(g).max())
    h = 1e-6
    tp, tm = t.update(q + h * v, None), t.update(q - h * v, None)
    assert np.array_equal(tp.dofs, tm.dofs)  # the same faces: a smooth response
    fd = (_grad(tp, q + h * v) - _grad(tm, q - h * v)) / (2 * h)
    scale = np.abs(fd).max()
    assert np.abs(_hvp(f, q, v) - fd).max() < 1e-7 * scale
    assert np.abs(_hvp(t, q, v) - fd).max() > 1e-2 * scale  # what the held pairing misses


def test_the_adjoint_takes_the_following_pairing():
    """eyefem.solve.adjoint.following swaps the re-paired facet contact for its following
    term and leaves a model without one as it is."""
    m, t, _, _ = _pressed(None)
    mat = {"r": mooney_rivlin("r", 0.1, 0.0)}
    model = solid_model(m, mat, (t,))
    adj = following(model)
    assert adj is not model and adj.term("c").following and not getattr(t, "following", False)
    plain = solid_model(m, mat, ())
    assert following(plain) is plain
    nodal = SurfaceContact("c", m, "hi/z0", "lo/z1", penalty=1e3, normals="nodal")
    assert nodal.following_pairing() is nodal  # held normals: not followed
