"""The augmented Lagrangian on the Q1P0 volume constraint (eyefem.solve.augmented,
NewtonOptions.incompressibility): its element against finite differences and under
rotation, the load path's convergence to the exact Q1P0 state as the Uzawa tolerance
tightens, the multipliers it leaves, the positive definite factorisation and its
fallback, and the option's validation."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

from eyefem.catalog import problems
from eyefem.fem import generators
from eyefem.fem.materials import MooneyRivlin
from eyefem.fem.solid import SolidQ1P0
from eyefem.solve import augmented, linsolve
from eyefem.solve.augmented import AugmentedQ1P0, augmented_model
from eyefem.solve.model import solid_model
from eyefem.solve.solver import NewtonOptions, solve


@pytest.fixture(scope="module")
def element():
    """Two distorted, deformed hexahedra of a generalised Mooney-Rivlin material, with
    multiplier estimates and penalties: (term, q_loc (2, 24))."""
    rng = np.random.default_rng(3)
    m = generators.box(1.0, 0.8, 0.6, 2, 1, 1, material="m")
    m = dataclasses.replace(m, nodes=m.nodes + 0.05 * rng.standard_normal(m.nodes.shape))
    mat = MooneyRivlin.from_terms("m", {"c10": 0.5, "c01": 0.2, "c20": 0.1})
    exact = SolidQ1P0("solid", m, mat.coeffs[None], multiplier_offset=3 * m.n_nodes)
    term = AugmentedQ1P0(exact, np.array([0.3, -0.2]), np.array([7.0, 4.0]))
    F = np.eye(3) + 0.15 * rng.standard_normal((3, 3))
    u = m.nodes @ F.T - m.nodes + 0.03 * rng.standard_normal(m.nodes.shape)
    return term, jnp.asarray(u.ravel()[term.dofs])


def _energy(term, q_loc):
    return jnp.sum(term.local_energy(q_loc, term.params, term.data))


@pytest.fixture(scope="module")
def energy_grad(element):
    """The element's energy and its gradient, compiled once (q_loc (2, 24) ->)."""
    term, _ = element
    return (jax.jit(lambda x: _energy(term, x)), jax.jit(jax.grad(lambda x: _energy(term, x))))


def test_residual_and_tangent_against_finite_differences(element):
    """The element's gradient and Hessian (the Q1P0 blocks at lambda_eff plus the penalty's
    rank one) against central differences of its energy and of its gradient (step 1e-6 mm:
    truncation ~1e-12, roundoff ~1e-10 of gradients of order 0.1 N)."""
    term, q = element
    energy = jax.jit(lambda x: term.local_energy(x, term.params, term.data))
    grad_hess = jax.jit(lambda x: term.local_grad_hess(x, term.params, term.data))
    g, H = (np.asarray(a) for a in grad_hess(q))
    h = 1e-6
    g_fd, H_fd = np.zeros_like(g), np.zeros_like(H)
    for j in range(24):
        e = jnp.zeros_like(q).at[:, j].set(h)
        g_fd[:, j] = (energy(q + e) - energy(q - e)) / (2 * h)
        H_fd[:, :, j] = (np.asarray(grad_hess(q + e)[0])
                         - np.asarray(grad_hess(q - e)[0])) / (2 * h)
    assert np.max(np.abs(g - g_fd)) < 1e-8 * np.max(np.abs(g))
    assert np.max(np.abs(H - H_fd)) < 1e-6 * np.max(np.abs(H))
    assert np.allclose(H, np.swapaxes(H, 1, 2), atol=1e-12 * np.max(np.abs(H)))


def test_gradient_is_the_q1p0_gradient_at_the_effective_multiplier(element, energy_grad):
    """dPi/du = the Q1P0 element's displacement gradient at lambda_eff = lambda +
    kappa g / (2 V), and lambda_eff is what multipliers() returns."""
    term, q = element
    full = np.zeros(term.exact.dofs.max() + 1)
    full[term.dofs] = np.asarray(q)
    lam_eff = term.multipliers(full)
    assert not np.allclose(lam_eff, term.lam)  # the penalty is in play
    q25 = jnp.concatenate([q, jnp.asarray(lam_eff)[:, None]], axis=1)
    g_exact = jax.jit(jax.grad(lambda x: jnp.sum(term.exact.local_energy(
        x, term.params, term.exact.data))))(q25)
    g = energy_grad[1](q)
    assert np.allclose(g, g_exact[:, :24], rtol=1e-12, atol=1e-14)


def test_rotation_invariance(element, energy_grad):
    """Rotating the deformed elements leaves the energy unchanged and rotates the
    gradient: r'_a = Q r_a."""
    term, q = element
    X = np.asarray(term.exact.mesh.nodes)[term.exact.mesh.hexes].reshape(-1, 24)
    rng = np.random.default_rng(8)
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))
    x = (X + np.asarray(q)).reshape(-1, 8, 3)
    q_rot = jnp.asarray((x @ Q.T).reshape(-1, 24) - X)
    energy, grad = energy_grad
    e0, e1 = energy(q), energy(q_rot)
    assert abs(float(e1 - e0)) < 1e-12 * abs(float(e0))
    g0 = np.asarray(grad(q)).reshape(-1, 8, 3)
    g1 = np.asarray(grad(q_rot)).reshape(-1, 8, 3)
    assert np.allclose(g1, g0 @ Q.T, atol=1e-12 * np.abs(g0).max())


def _bar():
    fields = problems()["uniaxial"][0]
    p = {f.name: f.default for f in fields}
    p.update(stretch=1.6, steps=2, n=2)
    setup = problems()["uniaxial"][1](p, {})
    return setup.model, setup.stages


def _shell():
    from eyefem.problems.verification import SHELL_FIELDS, inflated_shell

    p = {f.name: f.default for f in SHELL_FIELDS}
    p.update(n_per_edge=3, n_thick=1, steps=2)
    setup = inflated_shell(p, {})
    return setup.model, setup.stages


@pytest.fixture(scope="module", params=["bar", "shell"])
def paths(request):
    """The exact Q1P0 solution and augmented ones at loosening Uzawa tolerances."""
    model, stages = {"bar": _bar, "shell": _shell}[request.param]()
    tight = dict(rtol=1e-11, atol=1e-13)
    exact = solve(model, stages, options=NewtonOptions(**tight, vtol=1e-13))
    out = {}
    for tol in (1e-4, 1e-7, 1e-11):
        before = augmented.UZAWA_UPDATES["updates"]
        sol = solve(model, stages, options=NewtonOptions(
            **tight, incompressibility="augmented_lagrangian", uzawa_tol=tol))
        out[tol] = (sol, augmented.UZAWA_UPDATES["updates"] - before)
    return request.param, model, exact, out


def test_augmented_state_converges_to_the_exact_q1p0_state(paths):
    """As the Uzawa tolerance tightens, the displacements approach the exact Q1P0 ones, to
    1e-8 relative at 1e-11 (measured, penalty 100 x mu: bar 5.5e-13 in 9 updates, shell
    6.7e-11 in 6; at 1e-4: 3.0e-5 and 3.9e-7 in 2), the multipliers (lambda_eff) the Q1P0
    pressures likewise (1.3e-12, 9.4e-11), the volume error stays below its tolerance,
    and the updates grow."""
    name, model, exact, out = paths
    n_u = model.n_u
    u0, l0 = exact.q[:n_u], exact.q[n_u:]
    du = {tol: np.linalg.norm(s.q[:n_u] - u0) / np.linalg.norm(u0) for tol, (s, _) in out.items()}
    dl = {tol: np.linalg.norm(s.q[n_u:] - l0) / np.linalg.norm(l0) for tol, (s, _) in out.items()}
    assert du[1e-11] < 1e-8 and dl[1e-11] < 1e-8, (du, dl)
    assert du[1e-11] < du[1e-4] and dl[1e-11] < dl[1e-4], (du, dl)
    assert du[1e-4] < 1e-3, du  # the error is of the order of the volume error left
    for tol, (sol, n) in out.items():
        assert isinstance(sol.model.term("solid"), SolidQ1P0) and n >= 1
        r = sol.model.gradient(sol.q, sol.theta)
        t = sol.model.term("solid")
        g = np.abs(r[t.dofs[:, 24]]) / (2.0 * t.data["dv"].sum(axis=1))  # |Jbar - 1|
        assert g.max() <= tol * (1 + 1e-6), (tol, g.max())
    assert out[1e-11][1] > out[1e-4][1]


def test_bar_multiplier_is_uniform_and_the_q1p0_pressure(paths):
    """On the bar (a uniform uniaxial stretch) the multiplier the augmented solve leaves
    (lambda_eff) is uniform and equals the exact Q1P0 one to 1e-8 relative (the exact
    one against the closed form: the uniaxial verification problem)."""
    name, model, exact, out = paths
    if name != "bar":
        pytest.skip("a uniform state only on the bar")
    n_u = model.n_u
    lam, lam0 = out[1e-11][0].q[n_u:], exact.q[n_u:]
    assert np.allclose(lam, lam[0], rtol=1e-8)
    assert abs(lam[0] - lam0[0]) < 1e-8 * abs(lam0[0])


def test_adjoint_of_the_augmented_solution_is_the_exact_one(paths):
    """The Solution of an augmented run is the exact model at (u, lambda_eff): its adjoint
    gradient (here of the multipliers' sum, which depends on the material constants) is
    the exact run's to 1e-8 relative at uzawa_tol 1e-11 (measured on the bar with
    uzawa_tol 1e-6: 1e-6)."""
    from eyefem.solve.adjoint import value_and_grad

    name, model, exact, out = paths
    if name != "bar":
        pytest.skip("one problem suffices")

    def objective(q, theta):
        return jnp.sum(q[model.n_u:])

    v0, g0 = value_and_grad(objective, exact)
    v1, g1 = value_and_grad(objective, out[1e-11][0])
    c0, c1 = np.asarray(g0["solid"]["coeffs"]), np.asarray(g1["solid"]["coeffs"])
    assert abs(v1 - v0) < 1e-8 * abs(v0)
    assert np.max(np.abs(c1 - c0)) < 1e-8 * np.max(np.abs(c0))


def test_positive_definite_factorisation_and_its_fallback():
    """'+spd' factorises a positive definite matrix by Cholesky and an indefinite one,
    after the Cholesky fails, as symmetric indefinite; both solve to roundoff; asked to,
    the indefinite one raises NegativeCurvature."""
    if "pardiso" not in linsolve.available_backends():
        pytest.skip("Pardiso is not installed")
    rng = np.random.default_rng(0)
    n = 60
    A = sp.random(n, n, 0.1, random_state=1)
    A = (A + A.T + 6.0 * sp.eye(n)).tocsr()
    b = rng.standard_normal(n)
    for M, kind in ((A, 2), (A - 9.0 * sp.eye(n), -2)):
        before = dict(linsolve.FACTORISATIONS)
        f = linsolve.factorize(M, linsolve.positive_definite("pardiso"))
        assert f.mtype == kind
        assert np.linalg.norm(M @ f.solve(b) - b) < 1e-10 * np.linalg.norm(b)
        failed = linsolve.FACTORISATIONS["cholesky_failed"] - before["cholesky_failed"]
        assert failed == (kind == -2)
    with pytest.raises(linsolve.NegativeCurvature, match="not positive definite"):
        linsolve.factorize(A - 9.0 * sp.eye(n), "pardiso+spd", on_indefinite="raise")


def test_the_option_and_its_bad_values():
    with pytest.raises(ValueError, match="incompressibility = 'penalty'"):
        NewtonOptions(incompressibility="penalty")
    with pytest.raises(ValueError, match="penalty_factor = 0"):
        NewtonOptions(penalty_factor=0.0)
    with pytest.raises(ValueError, match="uzawa_max = 0"):
        NewtonOptions(uzawa_max=0)
    m = generators.box(1.0, 1.0, 1.0, 1, 1, 1, material="m")
    model = solid_model(m, {"m": MooneyRivlin.from_terms("m", {"c10": 0.5})})
    aug = augmented_model(model, 10.0)
    assert aug is not model and type(model.term("solid")) is SolidQ1P0  # a new model
    assert np.allclose(aug.term("solid").kappa, 10.0 * 1.0)  # 10 x 2 c10
    with pytest.raises(ValueError, match="penalty_factor = -1"):
        augmented_model(model, -1.0)
