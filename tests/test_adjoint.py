"""Adjoint gradients of converged solutions against finite differences of full solves."""

import jax.numpy as jnp
import numpy as np
import pytest

from eyefem.fem import generators
from eyefem.fem.materials import mooney_rivlin
from eyefem.fem.terms import NodalForce
from eyefem.solve.adjoint import value_and_grad
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage, solve


@pytest.fixture(scope="module")
def loaded_cube():
    m = generators.box(1.0, 1.0, 1.0, 2, 2, 2, material="r")
    x1 = node_dofs(m.node_set("x1"), "x")
    load = NodalForce("load", x1, {"f": np.zeros(len(x1))})
    model = solid_model(m, {"r": mooney_rivlin("r", 1.0, 0.3)}, (load,))
    d = np.concatenate([node_dofs(m.node_set("x0"), "x"), node_dofs(m.node_set("y0"), "y"),
                        node_dofs(m.node_set("z0"), "z")])

    def run(theta, f=2.0):
        st = [Stage("load", 4, (d, np.zeros(len(d))),
                    params={"load": {"f": np.full(len(x1), f)}})]
        return solve(model, st, theta=theta)

    return model, x1, run


def _perturb(theta, path, h):
    out = {k: dict(v) for k, v in theta.items()}
    term, key, idx = path
    a = np.array(out[term][key], dtype=float)
    a[idx] += h
    out[term][key] = a
    return out


def test_adjoint_matches_finite_differences(loaded_cube):
    model, x1, run = loaded_cube
    th0 = model.theta0()
    sol = run(th0)

    def objective(q, theta):
        return jnp.mean(q[x1]) + 0.1 * jnp.sum(q[x1] ** 2)

    val, grad = value_and_grad(objective, sol)
    assert val == pytest.approx(float(objective(sol.q, None)))
    h = 1e-6
    for path in [("solid", "coeffs", (0, 1, 0)), ("solid", "coeffs", (0, 0, 1))]:
        fp = float(objective(run(_perturb(th0, path, h)).q, None))
        fm = float(objective(run(_perturb(th0, path, -h)).q, None))
        fd = (fp - fm) / (2 * h)
        ad = grad[path[0]][path[1]][path[2]]
        assert ad == pytest.approx(fd, rel=1e-6)
    # gradient with respect to the load magnitude (the stage target): d/df of a uniform load
    fp = float(objective(run(th0, 2.0 + h).q, None))
    fm = float(objective(run(th0, 2.0 - h).q, None))
    assert np.sum(grad["load"]["f"]) == pytest.approx((fp - fm) / (2 * h), rel=1e-6)
