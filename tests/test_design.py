"""Adjoint gradients of surgical outcomes against finite differences of full simulations.

One coarse encircling case (flat tire, 2 mm tightening) is solved once; every finite
difference is a complete simulation of stages 2 and 3 at the perturbed design (warm
started from the base design's converged states; the equilibria are path independent).
"""

import numpy as np
import pytest

from eyefem.design import DESIGN_VARIABLES, OUTCOMES, SurgerySimulator, default_parameters

H = {"tightening": 1e-3, "buckle_shift": 1e-3, "suture_width": 1e-3, "suture_tightening": 1e-3}
"""Central-difference steps, mm. The IOP is stiff in the cavity volume (K / V_ini =
0.35 MPa/mm^3), so its roundoff (about 1e-8 mmHg) caps how small a step can be: at
h = 1e-4 it alone makes 1e-4 relative error. Steps of 1e-3 with Richardson
extrapolation (h and 2h) leave truncation and roundoff both near 1e-5."""


@pytest.fixture(scope="module")
def base():
    p = default_parameters(mesh="coarse", tightening=2.0, steps_tighten=4, steps_suture=2)
    sim = SurgerySimulator(p)
    res = sim.run()
    return sim, res, sim.gradients(res)


def _central(sim, res, var, h):
    vals = []
    for e in (h, -h):
        sim.last = res
        vals.append(sim.run({**res.design, var: res.design[var] + e}).outcomes)
    sim.last = res
    return {k: (vals[0][k] - vals[1][k]) / (2 * h) for k in OUTCOMES}


def _fd(sim, res, var, h):
    """Central differences with one Richardson extrapolation: error O(h^4)."""
    d1, d2 = _central(sim, res, var, h), _central(sim, res, var, 2 * h)
    return {k: (4 * d1[k] - d2[k]) / 3 for k in OUTCOMES}


def test_base_outcomes_are_plausible(base):
    sim, res, _ = base
    o = res.outcomes
    assert 15.0 < o["iop_mmhg"] < 40.0  # tightening raises the IOP of the closed eye
    assert o["indentation_mm"] > 0.1
    assert o["max_suture_force_N"] > 0.0


@pytest.mark.parametrize("var", ["tightening", "buckle_shift", "suture_width", "suture_tightening"])
def test_adjoint_gradient_matches_central_differences(base, var):
    sim, res, grads = base
    fd = _fd(sim, res, var, H[var])
    for out in OUTCOMES:
        ad = grads[out][var]
        assert ad == pytest.approx(fd[out], rel=1e-4, abs=1e-7), (out, var)


def test_drained_volume_lowers_the_iop_at_the_liquid_bulk_modulus_rate(base):
    """d IOP / d drained volume: adjoint against finite differences, and the sign."""
    sim, res, grads = base
    fd = _central(sim, res, "drain_volume", h=0.1)  # mm^3: the IOP change must dwarf the solve tolerance
    g = grads["iop_mmhg"]["drain_volume"]
    assert g < 0
    assert g == pytest.approx(fd["iop_mmhg"], rel=1e-4)


def test_every_design_variable_has_a_gradient(base):
    _, _, grads = base
    for out in OUTCOMES:
        assert set(grads[out]) == set(DESIGN_VARIABLES)
        assert all(np.isfinite(v) for v in grads[out].values())


def test_band_pull_term_is_the_work_of_the_tension():
    """DofForce: energy -f gain q, gradient -f gain, zero tangent (hand-coded values)."""
    import jax.numpy as jnp

    from eyefem.terms import DofForce

    t = DofForce("pull", 4, gain=2.5)
    q = jnp.arange(6.0)
    p = {"f": 0.3}
    assert float(t.energy(q, p, t.data, t.dofs)) == pytest.approx(-0.3 * 2.5 * 4.0)
    g, H = t.grad_hess(q, p, t.data, t.dofs)
    assert np.allclose(g, -0.75) and np.allclose(H, 0.0)
    assert t.report(np.asarray(q), p) == {"force_N": 0.3, "motion_mm": 10.0}
    with pytest.raises(ValueError, match="dof -1"):
        DofForce("pull", -1)


@pytest.mark.slow
def test_pulled_band_tension_gradient_matches_central_differences():
    """A band pulled by 0.25 N (force control: its shortening is an unknown) shortens by
    about 5 mm, like case 1's prescribed 5 mm; d outcomes / d tension by the adjoint
    against Richardson-extrapolated central differences of full simulations."""
    p = default_parameters(mesh="coarse", tightening=0.0, band_tension=0.25, steps_tighten=4,
                           steps_suture=2)
    sim = SurgerySimulator(p)
    res = sim.run()
    assert res.sol2.model.term("band_pull").report(res.sol2.q, res.sol2.theta["band_pull"])[
        "motion_mm"] == pytest.approx(5.0, abs=0.2)
    grads = sim.gradients(res)
    fd = _fd(sim, res, "band_tension", 1e-3)
    for out in OUTCOMES:
        assert grads[out]["band_tension"] == pytest.approx(fd[out], rel=1e-4), out
    assert grads["iop_mmhg"]["band_tension"] > 0  # pulling harder raises the IOP
    with pytest.raises(ValueError, match="'tightening' = 1.0 cannot vary"):
        sim.run({"tightening": 1.0})


def test_band_tension_cannot_vary_in_a_displacement_controlled_case(base):
    sim, res, grads = base
    assert all(grads[o]["band_tension"] == 0.0 for o in OUTCOMES)
    with pytest.raises(ValueError, match="'band_tension' = 0.1 cannot vary"):
        sim.run({**res.design, "band_tension": 0.1})
