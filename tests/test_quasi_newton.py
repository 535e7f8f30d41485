"""Quasi-Newton iterations on a reused factorisation (NewtonOptions.quasi_newton,
eyefem.solve.quasi_newton): the same states as full Newton with fewer factorisations, the
reformation rule, stages with contact left to full Newton, the options."""

import copy
import logging

import jax
import numpy as np
import pytest

from eyefem.catalog import problems
from eyefem.fem import generators
from eyefem.fem.cavity import FluidCavity
from eyefem.fem.materials import neo_hookean
from eyefem.io.casefile import CaseError, load_case
from eyefem.solve import quasi_newton
from eyefem.solve.assembly import Assembler
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import NewtonOptions, Stage, solve

PROBLEMS = problems()


def _shell(steps=4):
    from eyefem.problems.verification import SHELL_FIELDS, inflated_shell

    p = {f.name: f.default for f in SHELL_FIELDS}
    p.update(n_per_edge=4, n_thick=1, steps=steps)
    setup = inflated_shell(p, {})
    return setup.model, setup.stages


def _bar():
    fields = PROBLEMS["uniaxial"][0]
    p = {f.name: f.default for f in fields}
    p.update(stretch=2.0, steps=4)
    setup = PROBLEMS["uniaxial"][1](p, {})
    return setup.model, setup.stages


def _cavity():
    """An octant of a thick sphere filled with a stiff liquid, inflated by injecting 60%
    of its volume in 6 steps (tests/test_cavity.py): the rank-one cavity terms."""
    m = generators.spherical_shell(5.0, 5.0, 6, 2, octant=True, material="wall")
    cav = FluidCavity("cav", m, "inner", bulk=2083.3, symmetry_planes=("x", "y", "z"))
    model = solid_model(m, {"wall": neo_hookean("wall", 0.5)}, (cav,))
    d = np.concatenate([node_dofs(m.node_set(f"sym_{a}"), a) for a in "xyz"])
    v0 = cav.params["v_ini"]
    return model, [Stage("inject", 6, (d, np.zeros(len(d))), params={"cav": {"dv": 0.6 * v0}})]


CASES = {"shell": _shell, "bar": _bar, "cavity": _cavity}


@pytest.fixture
def factorisations(monkeypatch):
    """The number of tangents factorised (Assembler.solver calls) since the last clear."""
    counted, original = [], Assembler.solver

    def counting(self, *a, **kw):
        counted.append(1)
        return original(self, *a, **kw)

    monkeypatch.setattr(Assembler, "solver", counting)
    return counted


def _run(model, stages, counted, **kw):
    counted.clear()
    sol = solve(model, stages, options=NewtonOptions(**kw))
    return sol, len(counted), sum(r.iterations for r in sol.history)


@pytest.mark.parametrize("case", list(CASES))
def test_quasi_newton_reaches_the_full_newton_state_with_fewer_factorisations(
        case, factorisations):
    """The pressure-driven shell, the displacement-driven bar and the volume-driven cavity
    reach the full Newton state to the force tolerance's order (the same convergence
    test) with at most half the factorisations (measured: shell 1 against 9, bar 4
    against 13, cavity 5-6 against 17), every step converged."""
    model, stages = CASES[case]()
    full, f_full, _ = _run(model, stages, factorisations)
    qn, f_qn, it_qn = _run(model, stages, factorisations, quasi_newton="bfgs")
    assert f_qn <= f_full // 2
    assert all(not r.info for r in qn.history)  # every step in equilibrium, none accepted
    scale = np.abs(full.q).max()
    np.testing.assert_allclose(qn.q, full.q, rtol=0, atol=1e-7 * scale)
    assert it_qn <= 40 * len(qn.history)


def _directions_scaled(monkeypatch, factor):
    original = quasi_newton.QuasiNewton.direction

    def scaled(self, h0, r_red):
        return factor * original(self, h0, r_red)

    monkeypatch.setattr(quasi_newton.QuasiNewton, "direction", scaled)


def test_the_tangent_is_reformed_when_the_updates_stop_lowering_the_residual(
        factorisations, monkeypatch, caplog):
    """Quasi-Newton steps cut to a fifth lower the merit by less than the factor
    quasi_newton_ratio (0.5): none is taken, each attempt reforms the tangent, and the
    shell converges to the state of the undisturbed run with more factorisations."""
    model, stages = _shell(steps=2)
    good, f_good, _ = _run(model, stages, factorisations, quasi_newton="bfgs")
    _directions_scaled(monkeypatch, 0.2)
    with caplog.at_level(logging.DEBUG, logger="eyefem.solve.quasi_newton"):
        slow, f_slow, _ = _run(model, stages, factorisations, quasi_newton="bfgs")
    assert "no trial lowers the merit 2-fold; tangent reformed" in caplog.text
    assert f_slow > f_good
    scale = np.abs(good.q).max()
    np.testing.assert_allclose(slow.q, good.q, rtol=0, atol=1e-7 * scale)


def test_the_tangent_is_reformed_when_no_line_search_trial_lowers_the_residual(
        factorisations, monkeypatch, caplog):
    """Quasi-Newton directions reversed (uphill): no trial lowers the residual, every
    attempt reforms the tangent, and the path is full Newton's: as many factorisations as
    without quasi-Newton, the same state."""
    model, stages = _shell(steps=2)
    full, f_full, it_full = _run(model, stages, factorisations)
    _directions_scaled(monkeypatch, -1.0)
    with caplog.at_level(logging.DEBUG, logger="eyefem.solve.quasi_newton"):
        qn, f_qn, it_qn = _run(model, stages, factorisations, quasi_newton="bfgs")
    assert "no trial lowers the merit" in caplog.text
    assert it_qn == it_full
    scale = np.abs(full.q).max()
    np.testing.assert_allclose(qn.q, full.q, rtol=0, atol=1e-7 * scale)


def test_the_tangent_is_reformed_after_the_allowed_number_of_updates(factorisations, caplog):
    """With one update allowed per factorisation the bar reforms more often than with the
    default ten, and reaches the same state."""
    model, stages = _bar()
    many, f_many, _ = _run(model, stages, factorisations, quasi_newton="bfgs")
    with caplog.at_level(logging.DEBUG, logger="eyefem.solve.quasi_newton"):
        one, f_one, _ = _run(model, stages, factorisations, quasi_newton="bfgs",
                             quasi_newton_updates=1)
    assert "1 updates; tangent reformed" in caplog.text
    assert f_one > f_many
    scale = np.abs(many.q).max()
    np.testing.assert_allclose(one.q, many.q, rtol=0, atol=1e-7 * scale)


def test_stages_with_contact_are_left_to_full_newton(factorisations):
    """A stage with an active contact term (its force switches with the state; the
    look-ahead and the frozen pairing act on each Newton step) takes no quasi-Newton
    iteration: the bar with its solid flagged as contact factorises as full Newton does."""
    model, stages = _bar()
    flagged = []
    for t in model.terms:
        t = copy.copy(t)
        object.__setattr__(t, "contact", True)  # a frozen dataclass
        flagged.append(t)
    contact = model.with_terms(flagged)
    assert not quasi_newton.quasi_newton_stage(contact, None)
    assert quasi_newton.quasi_newton_stage(model, None)
    _, f_full, it_full = _run(contact, stages, factorisations)
    _, f_qn, it_qn = _run(contact, stages, factorisations, quasi_newton="bfgs")
    assert (f_qn, it_qn) == (f_full, it_full)


def test_the_adjoint_of_a_quasi_newton_solution_is_the_full_newton_one():
    """The adjoint refines against the exact tangent at the converged state, whatever
    factorisation the solution holds: the pressure gradient of the shell's radial
    displacement is the same after full Newton and after quasi-Newton."""
    import jax.numpy as jnp

    from eyefem.solve.adjoint import value_and_grad

    model, stages = _shell(steps=2)
    grads = []
    for qn in ("off", "bfgs"):
        sol = solve(model, stages, options=NewtonOptions(quasi_newton=qn))
        val, g = value_and_grad(lambda q, theta: jnp.sum(q[:model.n_u] ** 2), sol)
        grads.append((val, g))
    (v0, g0), (v1, g1) = grads
    assert v1 == pytest.approx(v0, rel=1e-7)
    a, b = (np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(g)]) for g in (g0, g1))
    np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-9 * np.abs(a).max())


def test_quasi_newton_options_are_checked_and_read_from_case_files(tmp_path):
    with pytest.raises(ValueError, match="quasi_newton"):
        NewtonOptions(quasi_newton="broyden")
    with pytest.raises(ValueError, match="quasi_newton_ratio"):
        NewtonOptions(quasi_newton="bfgs", quasi_newton_ratio=1.0)
    schemas = {name: fields for name, (fields, _) in PROBLEMS.items()}
    path = tmp_path / "bar.toml"
    path.write_text('[case]\nproblem = "uniaxial"\n[solver]\nquasi_newton = "bfgs"\n'
                    'quasi_newton_updates = 5\n')
    case = load_case(path, schemas)
    assert case.solver.quasi_newton == "bfgs" and case.solver.quasi_newton_updates == 5
    path.write_text('[case]\nproblem = "uniaxial"\n[solver]\nquasi_newton = "sr1"\n')
    with pytest.raises(CaseError, match="quasi_newton"):
        load_case(path, schemas)
