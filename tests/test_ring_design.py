"""Adjoint gradients of a deformable band's outcomes (RingSimulator: the stages its body
declares, differentiated by the generic staged sweep) against central differences of full
simulations, and through eyefem.simulate."""

import jax
import numpy as np
import pytest

import eyefem
from eyefem.eye.simulators import RingSimulator
from eyefem.eye.variables import OUTCOMES
from eyefem.solve.solver import NewtonOptions

CASE = "cases/surgery/deformable_band.toml"

H = {"tightening": 1e-3, "suture_tightening": 1e-3}
"""Central-difference steps, mm."""

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def ring():
    case = eyefem.load_case(CASE)
    sim = RingSimulator({**case.parameters, "mesh": "coarse", "steps_tighten": 4,
                         "steps_suture": 2}, case.materials, NewtonOptions(rtol=1e-10))
    res = sim.run()
    return sim, res, sim.gradients(res)


def _central(sim, res, var, h):
    vals = [sim.run({var: res.design[var] + e}).outcomes for e in (h, -h)]
    return {k: (vals[0][k] - vals[1][k]) / (2 * h) for k in OUTCOMES}


@pytest.mark.parametrize("var", ["tightening", "suture_tightening"])
def test_deformable_band_gradient_matches_central_differences(ring, var):
    """The closed loop's tightening (its rest length, stage 2) and the suture tightening
    (stage 3): every outcome's adjoint gradient against Richardson-extrapolated central
    differences (h, 2h) of full simulations of stages 2 and 3, to 1e-4 (abs 1e-7).

    The adjoint's tangent has the band's contact points following the state over the
    sclera's faces (eyefem.solve.adjoint.following). Measured (coarse eye, Newton to
    1e-10), the largest misses: 3.2e-6 (IOP, astigmatism, suture force 2.5e-6) in the
    tightening, 5.8e-6 (astigmatism) in the suture tightening; with the pairing's target
    points held in the tangent the astigmatism missed by 1.6e-4 and 3.5e-4, the suture
    force in the tightening by 3.0e-4 (2.0e-7 N/mm), so the test tells the two apart."""
    sim, res, grads = ring
    h = H[var]
    d1, d2 = _central(sim, res, var, h), _central(sim, res, var, 2 * h)
    missed = []
    for out in OUTCOMES:
        fd = (4 * d1[out] - d2[out]) / 3
        if grads[out][var] != pytest.approx(fd, rel=1e-4, abs=1e-7):
            missed.append((out, grads[out][var], fd))
    assert not missed, missed
    assert grads["iop_mmhg"][var] > 0  # tighter: more pressure


def test_simulate_differentiates_the_deformable_band():
    """jax.grad of eyefem.simulate on the deformable band case: the RingSimulator's
    adjoint (the same backward sweep), refused for a variable the ring cannot vary."""
    jax.config.update("jax_enable_x64", True)
    g = jax.grad(lambda d: eyefem.simulate(CASE, d, mesh="coarse")["iop_mmhg"])(
        {"drain_volume": 0.0})
    assert np.isfinite(g["drain_volume"]) and g["drain_volume"] < 0  # draining lowers it
    with pytest.raises(ValueError, match="'buckle_shift' cannot vary for a deformable band"):
        eyefem.simulate(CASE, {"buckle_shift": 0.5}, mesh="coarse")
