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


def test_block_adjoints_equal_one_at_a_time(loaded_cube):
    """values_and_grads of k objectives (one block adjoint solve, the residual's design
    derivative contracted with all k adjoints by one compiled kernel) gives each
    objective's value and gradient as value_and_grad alone, to the adjoint's refinement
    tolerance (1e-10 relative)."""
    from eyefem.solve.adjoint import values_and_grads

    model, x1, run = loaded_cube
    sol = run(model.theta0())
    objectives = [lambda q, th: jnp.mean(q[x1]),
                  lambda q, th: jnp.sum(q[x1] ** 2) * th["solid"]["coeffs"][0, 1, 0],
                  lambda q, th: jnp.sum(q ** 3)]
    vals, grads = values_and_grads(lambda q, th: jnp.stack([f(q, th) for f in objectives]), sol)
    assert len(grads) == 3
    for f, v, g in zip(objectives, vals, grads):
        v1, g1 = value_and_grad(f, sol)
        assert v == pytest.approx(v1, rel=1e-14)
        for term in g1:
            for key in g1[term]:
                a, b = np.asarray(g[term][key]), np.asarray(g1[term][key])
                np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.abs(b).max() + 1e-300)
    # the three gradients differ from one another (the test is not comparing a result with itself)
    assert not np.allclose(grads[0]["solid"]["coeffs"], grads[2]["solid"]["coeffs"])


def test_objectives_of_data_are_compiled_once_and_released_with_the_function(loaded_cube):
    """values_and_grads(f, sol, data=...) calls f(q, theta, data): the same values and
    gradients as a closure over the data, its Jacobian compiled once for new data of the
    same shapes, and kept on f alone (once f is dropped, nothing keeps it, nor what it
    closes over)."""
    import gc
    import weakref

    from eyefem.solve.adjoint import jacobians_of, values_and_grads

    model, x1, run = loaded_cube
    sol = run(model.theta0())

    class Held:  # something an objective closes over (a simulator's mesh, say)
        pass

    traces = []  # f runs in Python only while it is traced (compiled)

    def make():
        held = Held()

        def f(q, theta, data):
            held.touched = True
            traces.append(1)
            return data["w"] * jnp.stack([jnp.mean(q[x1]), jnp.sum(q[x1] ** 2)])

        return f, weakref.ref(held)

    f, held = make()
    for w in (1.0, 3.0):
        vals, grads = values_and_grads(f, sol, data={"w": jnp.asarray(w)})
        ref_vals, ref_grads = values_and_grads(
            lambda q, th, w=w: w * jnp.stack([jnp.mean(q[x1]), jnp.sum(q[x1] ** 2)]), sol)
        np.testing.assert_allclose(vals, ref_vals, rtol=1e-14)
        for g, r in zip(grads, ref_grads):
            np.testing.assert_allclose(g["solid"]["coeffs"], r["solid"]["coeffs"],
                                       rtol=1e-9, atol=1e-12 * np.abs(r["solid"]["coeffs"]).max())
    assert len(traces) == 1  # the second weight reused the first compile (f not traced again)
    assert jacobians_of(f)._cache_size() <= 1
    assert abs(vals[0]) > 0 and not np.allclose(grads[0]["solid"]["coeffs"], 0)
    del f
    gc.collect()
    assert held() is None


def test_the_staged_wrappers_release_their_function(loaded_cube):
    """eyefem.solve.staged keeps one wrapper per carry or objective function (contracted,
    holding_carry, the carry pullback; their compiled Jacobians reused) and computes with
    it; the wrappers hold the function weakly, so once it is dropped nothing keeps it, nor
    what it closes over (a simulator's model and mesh)."""
    import gc
    import weakref

    from eyefem.solve import adjoint, staged
    from eyefem.solve.adjoint import values_and_grads

    model, x1, run = loaded_cube
    sol = run(model.theta0())

    class Held:  # something a carry closes over
        pass

    def make():
        held = Held()

        def carry(q, theta, data):
            held.touched = True
            return {"mean": jnp.mean(q[x1]), "sq": jnp.sum(q[x1] ** 2)}

        return carry, weakref.ref(held)

    carry, held = make()
    cbar = {"mean": jnp.ones((1,)), "sq": jnp.full((1,), 2.0)}
    vals, grads = values_and_grads(staged.contracted(carry), sol,
                                   data={"cbar": cbar, "data": None})
    q = np.asarray(sol.q)
    assert vals[0] == pytest.approx(np.mean(q[x1]) + 2 * np.sum(q[x1] ** 2), rel=1e-12)
    assert abs(vals[0]) > 0 and not np.allclose(grads[0]["solid"]["coeffs"], 0)
    assert staged.contracted(carry) is staged.contracted(carry)  # one wrapper per function
    staged.holding_carry(carry), staged._carry_pullback(carry)
    kept = len(adjoint._KEPT)
    del carry
    gc.collect()
    assert held() is None
    assert len(adjoint._KEPT) == kept - 2  # its entry, and its contraction's Jacobians


def test_params_vjp_many_is_the_residual_vjp(loaded_cube):
    """Model.params_vjp_many (compiled, k columns at once) against jax.vjp of the residual
    with respect to the design, column by column."""
    import jax

    model, x1, run = loaded_cube
    sol = run(model.theta0())
    theta = jax.tree_util.tree_map(jnp.asarray, sol.theta)
    rng = np.random.default_rng(0)
    L = rng.normal(size=(model.n_dof, 2))

    def residual(th):
        return sum(jax.grad(t.energy)(jnp.asarray(sol.q), th[t.name], t.data, t.dofs)
                   for t in model.terms)

    _, vjp = jax.vjp(residual, theta)
    got = model.params_vjp_many(jnp.asarray(sol.q), jnp.asarray(L), theta)
    for j in range(2):
        (want,) = vjp(jnp.asarray(L[:, j]))
        for term in want:
            for key in want[term]:
                b = np.asarray(want[term][key])
                np.testing.assert_allclose(got[j][term][key], b, rtol=1e-12,
                                           atol=1e-12 * np.abs(b).max() + 1e-300)


def test_assembled_tangent_is_the_autodiff_tangent(loaded_cube):
    """The adjoints' refinement from ASSEMBLED_FROM right-hand sides on multiplies by the
    tangent assembled without the augmentation (adjoint.assembled_tangent); on the free
    primal and multiplier rows it equals the autodiff tangent-vector products."""
    from eyefem.solve.adjoint import _apply, assembled_tangent

    model, x1, run = loaded_cube
    sol = run(model.theta0())
    asm = sol.assembler
    V = np.zeros((model.n_dof, 3))
    keep = np.concatenate([asm.free_primal, asm.mult])
    V[keep] = np.random.default_rng(2).normal(size=(len(keep), 3))
    want = _apply(model, sol.q, V, sol.theta, sol.active, asm)
    got = assembled_tangent(model, asm, sol.q, sol.theta, sol.active)(V)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
    assert np.abs(want[asm.mult]).max() > 0  # the multiplier rows are compared too


def _exact_residual(model, sol, lam, rhs):
    """Relative residual of K lam = rhs (columns) on the free primal and multiplier rows,
    K the exact tangent assembled at the solution."""
    from eyefem.solve.adjoint import assembled_tangent

    asm = sol.assembler
    keep = np.concatenate([asm.free_primal, asm.mult])
    res = assembled_tangent(model, asm, sol.q, sol.theta, sol.active)(lam)[keep] - rhs[keep]
    return np.linalg.norm(res, axis=0) / np.linalg.norm(rhs[keep], axis=0)


def test_adjoint_sweeps_are_checked_against_the_exact_tangent_alone(loaded_cube, monkeypatch):
    """Each refinement sweep of adjoint_solve is one pass of the saddle-point solve without
    the solve's own residual check (SaddlePointSolver.approximate_solve): the sweep's
    residual against the exact tangent is the check. The k adjoints still meet the
    refinement tolerance (1e-10) against the exact tangent."""
    from eyefem.solve.adjoint import ASSEMBLED_FROM, adjoint_solve
    from eyefem.solve.linsolve import SaddlePointSolver

    model, x1, run = loaded_cube
    sol = run(model.theta0()).factorised()
    rhs = np.random.default_rng(3).normal(size=(model.n_dof, ASSEMBLED_FROM + 1))

    def checked_solve(self, f, g=None):
        raise AssertionError("an adjoint sweep called the checked solve")

    passes = []
    approximate = SaddlePointSolver.approximate_solve

    def counted(self, f, g=None, rtol=None):
        passes.append(f.shape)
        return approximate(self, f, g, rtol)

    monkeypatch.setattr(SaddlePointSolver, "solve", checked_solve)
    monkeypatch.setattr(SaddlePointSolver, "approximate_solve", counted)
    lam = adjoint_solve(model, sol.solver, sol.assembler, sol.q, sol.theta, rhs,
                        active=sol.active)
    assert 1 <= len(passes) <= 3  # the last Newton factorisation is nearly exact
    assert _exact_residual(model, sol, lam, rhs).max() <= 1e-10


class _Damped:
    """A preconditioner that returns ``factor`` times the solver's answer."""

    def __init__(self, solver, factor):
        self.solver, self.factor, self.passes = solver, factor, 0

    def approximate_solve(self, f, g=None, rtol=None):
        self.passes += 1
        x, y = self.solver.approximate_solve(f, g, rtol)
        return self.factor * x, self.factor * y


def test_an_adjoint_refinement_that_stalls_stops_and_says_so(loaded_cube, caplog):
    """A sweep that lowers no column's residual (here a preconditioner that gives three
    times the solve, so that the residual doubles) ends the refinement with a warning
    after that one sweep, not after max_refine; a non-finite residual raises
    LinearSolveError naming the sweep."""
    from eyefem.solve.adjoint import adjoint_solve
    from eyefem.solve.errors import LinearSolveError

    model, x1, run = loaded_cube
    sol = run(model.theta0()).factorised()
    rhs = np.random.default_rng(4).normal(size=model.n_dof)
    damped = _Damped(sol.solver, 3.0)
    with caplog.at_level("WARNING", logger="eyefem.solve.adjoint"):
        lam = adjoint_solve(model, damped, sol.assembler, sol.q, sol.theta, rhs,
                            active=sol.active)
    assert damped.passes == 1
    assert "adjoint refinement stalled at relative residual 2.00e+00 after 1 sweeps" in caplog.text
    assert lam.shape == rhs.shape
    with pytest.raises(LinearSolveError, match="sweep 1 is not finite"):
        adjoint_solve(model, _Damped(sol.solver, np.nan), sol.assembler, sol.q, sol.theta,
                      rhs, active=sol.active)
