"""Adjoint gradients of surgical outcomes against finite differences of full simulations.

One coarse encircling case (flat tire, 2 mm tightening) is solved once; every finite
difference is a complete simulation of stages 2 and 3 at the perturbed design (warm
started from the base design's converged states; the equilibria are path independent).
"""

import numpy as np
import pytest

from eyefem.eye.simulators import SurgerySimulator
from eyefem.eye.variables import DESIGN_VARIABLES, OUTCOMES, default_parameters
from eyefem.solve.solver import NewtonOptions

H = {"tightening": 1e-3, "buckle_shift": 1e-3, "suture_width": 1e-3, "suture_tightening": 1e-3,
     "c10_sclera": 1e-4, "liquid_bulk": 100.0, "suture_EA": 1.0, "zonule_E": 1.0,
     "c10_cornea": 1e-4, "buckle_meridian_deg": 2e-3}
"""Central-difference steps (mm, MPa, N, degrees). The IOP is stiff in the cavity volume
(K / V_ini = 0.35 MPa/mm^3), so its roundoff (about 1e-8 mmHg) caps how small a step can
be: at h = 1e-4 mm it alone makes 1e-4 relative error. Steps of 1e-3 mm with Richardson
extrapolation (h and 2h) leave truncation and roundoff both near 1e-5. Material steps
change the outcome by 1e-5 or more; the meridian step is 0.4 um at the sclera, below
the 2 um contact smoothing length over which the response bends."""


TIGHT = NewtonOptions(rtol=1e-10)
"""Newton held to 1e-10 in these tests: at the default 1e-8 the IOP's central differences
scatter by about 1e-4 (measured for suture_tightening: 1.2e-4), the size of the check."""


@pytest.fixture(scope="module")
def base():
    p = default_parameters(mesh="coarse", tightening=2.0, steps_tighten=4, steps_suture=2)
    sim = SurgerySimulator(p, options=TIGHT)
    res = sim.run()
    return sim, res, sim.gradients(res)


def _central(sim, res, var, h):
    vals = []
    for e in (h, -h):
        vals.append(sim.run({**res.design, var: res.design[var] + e}, start=res).outcomes)
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


def _check_against_fd(sim, res, grads, var, outcomes=OUTCOMES):
    fd = _fd(sim, res, var, H[var])
    for out in outcomes:
        assert grads[out][var] == pytest.approx(fd[out], rel=1e-4, abs=1e-7), (out, var)


@pytest.mark.parametrize("var", ["tightening", "buckle_shift", "suture_width", "suture_tightening",
                                 "suture_EA"])
def test_adjoint_gradient_matches_central_differences(base, var):
    _check_against_fd(*base, var)


def test_material_gradient_through_the_preoperative_stage_matches_central_differences(base):
    """c10 of the sclera changes the pressurised eye (stage 1) and so the closed cavity's
    volume, the buckle's snug fit and the pre-operative axial length: the adjoint chains
    through stage 1 (three adjoint solves) and matches full re-simulations."""
    sim, res, grads = base
    _check_against_fd(sim, res, grads, "c10_sclera")
    assert grads["iop_mmhg"]["c10_sclera"] > 0  # a stiffer wall: the same squeeze, more pressure


def test_liquid_bulk_modulus_gradient_matches_central_differences(base):
    """The IOP's response to K is small (the cavity volume hardly changes after
    closing), so only the other outcomes are above the IOP's roundoff at any usable
    step; the IOP's is checked for sign (a stiffer liquid: more pressure per squeeze)."""
    sim, res, grads = base
    _check_against_fd(sim, res, grads, "liquid_bulk",
                      [o for o in OUTCOMES if o != "iop_mmhg"])
    assert grads["iop_mmhg"]["liquid_bulk"] > 0


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


def test_every_outcome_at_once_equals_one_outcome_at_a_time(base):
    """SurgerySimulator.gradients solves each stage's adjoints of all outcomes together
    (one right-hand side per outcome); asked for one outcome, or for a weighted sum
    (weighted_gradient, the planner's backward pass), it gives the same numbers to within
    what the adjoints' refinement tolerance (1e-10 relative residual) leaves: each column
    stops somewhere below it (stage 1's at 3e-11..7e-11), and a material entry through
    stage 1 (c10_retina of the IOP, c10_sclera of the refraction change) is a small sum of
    large element contributions, so the two agree there to 1.0e-8 and 1.5e-8 (measured;
    the other entries to 1e-9 or better). 1e-7 is 7x that; a wrong pairing of columns or
    stages is off by O(1)."""
    sim, res, grads = base
    for name in ("iop_mmhg", "refraction_change_D"):  # one without, one with a stage-1 route
        one = sim.gradients(res, [name])[name]
        for var in DESIGN_VARIABLES:
            assert one[var] == pytest.approx(grads[name][var], rel=1e-7, abs=1e-12), (name, var)
    w = sim.weighted_gradient(res, {"iop_mmhg": 2.0, "axial_length_change_mm": -1.0})
    for var in DESIGN_VARIABLES:
        want = 2.0 * grads["iop_mmhg"][var] - grads["axial_length_change_mm"][var]
        assert w[var] == pytest.approx(want, rel=1e-7, abs=1e-10), var


def test_a_new_design_reuses_the_compiled_outcome_jacobians(base):
    """The outcome functions and the stages' carry functions take a design's data as
    arguments (SurgerySimulator.outcome_vector, maps), so the gradients of a second
    design compile nothing new: the same functions, each compiled Jacobian's cache as
    large after as before."""
    from eyefem.solve import adjoint
    from eyefem.solve.adjoint import jacobians_of
    from eyefem.solve.staged import contracted, holding_carry

    sim, res, _ = base

    def compiled():  # function -> (itself, its compiled Jacobian's cache size)
        fns = []
        for key, f in sim._compiled.items():
            if key[0] == "outcomes":
                fns.append(holding_carry(f))
            else:
                fns += [contracted(m.carry) for m in f if m.carry is not None]
        return {f: (f, jacobians_of(f)._cache_size()) for f in fns
                if "jacobians" in adjoint._KEPT.get(f, {})}

    sim.gradients(res)
    sim.weighted_gradient(res, {"iop_mmhg": 1.0})
    before = compiled()
    assert len(before) >= 4 and all(n >= 1 for _, n in before.values())
    other = sim.run({**res.design, "tightening": res.design["tightening"] + 0.05}, start=res)
    assert other.outcomes["iop_mmhg"] != res.outcomes["iop_mmhg"]
    sim.gradients(other)
    sim.weighted_gradient(other, {"iop_mmhg": 1.0})
    assert compiled() == before


def test_a_result_holds_no_factorisation_and_its_gradients_survive_later_designs(base):
    """A design's result and the simulator's warm-start state hold states, not
    factorisations (each stage is factorised again at its converged state for the
    gradients), so a held result costs no factorisation's memory; after another design
    has been solved (refactorising the solver's shared Pardiso instances) the held result's
    gradients are the ones the fast tests check against central differences."""
    sim, res, grads = base
    other = sim.run({**res.design, "tightening": res.design["tightening"] + 1e-3}, start=res)
    assert all(r.solution.solver is None for r in other.stages + res.stages)
    assert sim.preop.sol1.solver is None
    again = sim.gradients(res, ["iop_mmhg"])["iop_mmhg"]
    assert again == pytest.approx(grads["iop_mmhg"], rel=1e-9, abs=1e-12)
    assert again != pytest.approx(sim.gradients(other, ["iop_mmhg"])["iop_mmhg"],
                                  rel=1e-12, abs=0.0)


def test_a_run_does_not_depend_on_the_designs_solved_before(base):
    """The simulator keeps no state between runs: a design of other material constants
    (its own pre-operative eye) leaves the case's pre-operative eye in place, and the
    case's design solved after it gives the same outcomes, to the last digit, as before,
    from the start result's states alone (states_only: a planner's start); such a result's
    gradients are refused."""
    from eyefem.eye.simulators import states_only

    sim, res, _ = base
    pre = sim.preop
    design = {**res.design, "tightening": res.design["tightening"] + 0.1}
    first = sim.run(design, start=res)
    stiffer = sim.run({**design, "c10_sclera": 1.05 * design["c10_sclera"]}, start=first)
    assert stiffer.preop is not pre and stiffer.outcomes["iop_mmhg"] > first.outcomes["iop_mmhg"]
    assert sim.preop is pre
    lean = states_only(res)
    assert lean.outcomes == res.outcomes and res.sol2.assembler is not None
    assert lean.sol2.assembler is None and lean.sol3.assembler is None
    again = sim.run(design, start=lean)
    assert again.preop is pre
    assert again.outcomes == first.outcomes
    with pytest.raises(ValueError, match="keeps its state only"):
        sim.gradients(lean, ["iop_mmhg"])


def test_a_start_that_is_not_this_simulators_result_is_refused(base):
    import dataclasses

    sim, res, _ = base
    with pytest.raises(ValueError, match="not a result of this simulator"):
        sim.run(res.design, start=res.outcomes)
    other = dataclasses.replace(res.stages[1].solution, q=res.stages[1].solution.q[:-3])
    bad = dataclasses.replace(res, stages=(res.stages[0], dataclasses.replace(
        res.stages[1], solution=other), res.stages[2]))
    with pytest.raises(ValueError, match=f"{sim.model1.n_dof} unknowns"):
        sim.run(res.design, start=bad)


def test_a_warm_start_past_its_limits_falls_back_to_the_full_load_path(base, monkeypatch,
                                                                       caplog):
    """A warm start runs within WARM_START_LIMITS (the case's limits capped); one that cannot
    converge within them (here: one Newton iteration, no halving) is abandoned, with a
    warning, for the load path from the pre-operative eye: the run a design without a
    start makes (its outcomes equal the warm starts' to the Newton tolerance: the
    central differences above run warm)."""
    import logging

    import eyefem.eye.simulators as simulators

    sim, res, _ = base
    warm = sim._warm_options()
    assert (warm.max_iter, warm.max_cuts, warm.stall_cut) == (20, 2, True)
    assert warm.rtol == sim.options.rtol
    design = {**res.design, "tightening": res.design["tightening"] - 0.5}
    monkeypatch.setattr(simulators, "WARM_START_LIMITS",
                        {"max_iter": 1, "max_cuts": 0, "stall_cut": True})
    starts, run = [], sim._run

    def spy(design, *, start=None):
        starts.append(start)
        return run(design, start=start)

    monkeypatch.setattr(sim, "_run", spy)
    with caplog.at_level(logging.WARNING, logger="eyefem.eye.simulators"):
        fallen = sim.run(design, start=res)
    assert any("warm start failed" in r.getMessage() for r in caplog.records)
    assert len(starts) == 2 and starts[0] is res and starts[1] is None
    assert fallen.newton_iterations > 1
    assert fallen.outcomes["indentation_mm"] < res.outcomes["indentation_mm"]  # less tightening


def test_the_run_reports_the_suture_force_the_simulator_differentiates(base, tmp_path):
    """One rule for the largest suture force (eyefem.eye.outcomes.suture_force): 0 until the
    sutures are tied, then the most loaded bar's force, in ``eyefem run``'s rows and in the
    design simulator's outcome alike; checked where the two once differed, a design with
    suture_tightening = 0 (the tied, slack sutures' smoothed force, about 1e-4 N). The two
    routes solve along different load paths to rtol 1e-10, so their states differ by
    roundoff: 1e-6 relative."""
    from eyefem.eye.surgery import surgery
    from eyefem.run.runner import run_setup

    sim, res, _ = base
    got = sim.run({**res.design, "suture_tightening": 0.0},
                  start=res).outcomes["max_suture_force_N"]
    run = run_setup(surgery({**sim.params, "suture_tightening": 0.0}, None), tmp_path, TIGHT,
                    vtu=False, plots=False)
    assert 1e-6 < got < 1e-3
    assert run.summary["max_suture_force_N"] == pytest.approx(got, rel=1e-6)
    untied = [r["max_suture_force_N"] for r in run.rows if r["stage"] != "suture"]
    assert untied and all(f == 0.0 for f in untied)


def test_band_pull_term_is_the_work_of_the_tension():
    """DofForce: energy -f gain q, gradient -f gain, zero tangent (hand-coded values)."""
    import jax.numpy as jnp

    from eyefem.fem.terms import DofForce

    t = DofForce("pull", 4, gain=2.5)
    q = jnp.arange(6.0)
    p = {"f": 0.3}
    assert float(t.energy(q, p, t.data, t.dofs)) == pytest.approx(-0.3 * 2.5 * 4.0)
    g, H = t.grad_hess(q, p, t.data, t.dofs)
    assert np.allclose(g, -0.75) and np.allclose(H, 0.0)
    assert t.report(np.asarray(q), p) == {"force_N": 0.3, "motion_mm": 10.0}
    with pytest.raises(ValueError, match="dof -1"):
        DofForce("pull", -1)


def test_orbit_spring_holds_rotations_and_shifts_with_the_given_stiffnesses():
    """The orbit's hold: a small rigid rotation delta about the x, y or z axis through the
    equatorial ring's centre stores 1/2 K delta^2 (K the case's globe_rotation or
    globe_torsion, N mm/rad), a lateral shift s stores 1/2 K_t s^2 (globe_translation,
    N/mm), an axial one 1/2 K_z s^2 (globe_axial; nothing with 0); a
    deformation symmetric about x = 0 and y = 0 (radial, axial) stores nothing. The
    gradient against the planar ring's hand-coded modes: twist (-y, x, 0) / sum rho^2,
    tilt about x (0, 0, y) / sum y^2, shifts 1/n."""
    import jax
    import numpy as np

    from eyefem.eye.eyemodel import EyeGeometry, build_eye
    from eyefem.eye.surgery import orbit_spring

    mesh = build_eye(EyeGeometry(), "coarse").mesh
    p = {"globe_rotation": 5.0, "globe_torsion": 7.0, "globe_translation": 0.8, "globe_axial": 0.0}
    t = orbit_spring(mesh, p)
    X = mesh.nodes
    c = X[t.nodes].mean(axis=0)
    assert abs(c[0]) < 1e-9 and abs(c[1]) < 1e-9
    delta = 1e-3

    def energy(u):
        return float(t.energy(np.asarray(u).ravel(), t.params, t.data, t.dofs))

    for axis, k in ((0, 5.0), (1, 5.0), (2, 7.0)):
        u_rot = delta * np.cross(np.eye(3)[axis], X - c)
        assert energy(u_rot) == pytest.approx(0.5 * k * delta**2, rel=1e-12)
    report = t.report((delta * np.cross(np.eye(3)[2], X - c)).ravel(), t.params)
    assert report["twist_deg"] == pytest.approx(np.degrees(delta))
    assert report["tilt_deg"] == pytest.approx(0.0, abs=1e-12)
    for axis in (0, 1):
        assert energy(np.tile(0.01 * np.eye(3)[axis], (len(X), 1))) == pytest.approx(
            0.5 * 0.8 * 0.01**2, rel=1e-12)
    u_axial = np.tile([0.0, 0.0, 0.3], (len(X), 1))
    assert energy(u_axial) == pytest.approx(0.0, abs=1e-20)
    rho = np.hypot(X[:, 0], X[:, 1])
    u_sym = np.stack([0.1 * X[:, 0], 0.1 * X[:, 1], 0.05 * np.cos(rho)], axis=1)
    assert energy(u_sym) == pytest.approx(0.0, abs=1e-20)
    t = orbit_spring(mesh, {**p, "globe_axial": 0.6})
    assert energy(u_axial) == pytest.approx(0.5 * 0.6 * 0.3**2, rel=1e-12)
    assert t.report(u_axial.ravel(), t.params)["axial_shift_mm"] == pytest.approx(0.3, rel=1e-12)
    rng = np.random.default_rng(0)
    q_loc = rng.standard_normal(t.dofs.shape)
    Xr = X[t.nodes]
    zero = np.zeros(len(Xr))
    modes = [np.stack([zero, zero, Xr[:, 1]], 1) / np.sum(Xr[:, 1] ** 2),
             np.stack([zero, zero, -Xr[:, 0]], 1) / np.sum(Xr[:, 0] ** 2),
             np.stack([-Xr[:, 1], Xr[:, 0], zero], 1) / np.sum(Xr[:, :2] ** 2),
             np.stack([zero + 1, zero, zero], 1) / len(Xr),
             np.stack([zero, zero + 1, zero], 1) / len(Xr),
             np.stack([zero, zero, zero + 1], 1) / len(Xr)]
    g_hand = sum(k * (q_loc[0] @ w.ravel()) * w.ravel()
                 for k, w in zip((5.0, 5.0, 7.0, 0.8, 0.8, 0.6), modes))
    g_ad = jax.grad(lambda q: t.local_energy(q, t.params, t.data).sum())(q_loc)
    np.testing.assert_allclose(np.asarray(g_ad)[0], g_hand, rtol=1e-10, atol=1e-14)
    with pytest.raises(ValueError, match="k_trans = -1.0 N/mm"):
        orbit_spring(mesh, {**p, "globe_translation": -1.0})


@pytest.mark.slow
def test_pulled_band_tension_gradient_matches_central_differences():
    """A band pulled by 0.25 N (force control: its shortening is an unknown) shortens by
    about 5 mm, like case 1's prescribed 5 mm; d outcomes / d tension by the adjoint
    against Richardson-extrapolated central differences of full simulations."""
    p = default_parameters(mesh="coarse", tightening=0.0, band_tension=0.25, steps_tighten=4,
                           steps_suture=2)
    sim = SurgerySimulator(p, options=TIGHT)
    res = sim.run()
    assert res.sol2.model.term("band_pull").report(res.sol2.q, res.sol2.theta["band_pull"])[
        "motion_mm"] == pytest.approx(5.0, abs=0.2)
    grads = sim.gradients(res)
    # the suture force is strongly curved in the tension: central differences with
    # h = 0.5, 1, 2, 4 mN give -0.4040, -0.4056, -0.4124, -0.4613 N/N (10 um contact
    # smoothing), so the Richardson pair needs h = 0.5 mN to reach 1e-4
    fd = _fd(sim, res, "band_tension", 5e-4)
    for out in OUTCOMES:
        assert grads[out]["band_tension"] == pytest.approx(fd[out], rel=1e-4), out
    assert grads["iop_mmhg"]["band_tension"] > 0  # pulling harder raises the IOP
    with pytest.raises(ValueError, match="'tightening' = 1.0 cannot vary"):
        sim.run({"tightening": 1.0})


@pytest.mark.slow
def test_segmental_meridian_and_stage1_material_gradients_match_central_differences():
    """A radial sponge (fitted at meridian 0) turned to 3 degrees, off the mesh's
    symmetry plane (there every meridian derivative vanishes): d outcomes / d meridian
    (buckle and sutures turned, bites moved over the scleral faces), and two constants
    of the pre-operative eye (cornea c10, zonule E), against central differences.

    Newton is held to 1e-10 here: the IOP's derivatives are small remainders of the
    cavity volume (the meridian's: 5e-7 mm^3 per degree) times K / V = 2600 mmHg/mm^3.
    That factor also turns the volume's round-off into steps of the IOP of about 1e-9
    mmHg, so the IOP's central differences scatter: for the meridian by 1e-6 mmHg/degree
    at h = 0.0005 to 0.004 degrees (1e-3 of the derivative; the axial length's converge
    to the adjoint's as h^2 there), for the two constants (changes of 1e-5..1e-4 mmHg) by
    4e-4 and 1.3e-3 (measured). The IOP is held to 2e-3 for all three, the other
    outcomes to 1e-4."""
    p = default_parameters(mesh="coarse", buckle="sponge_radial", tightening=2.0,
                           steps_tighten=4, steps_suture=2)
    sim = SurgerySimulator(p, options=TIGHT)
    res = sim.run({"buckle_meridian_deg": 3.0})
    grads = sim.gradients(res)
    for var in ("buckle_meridian_deg", "c10_cornea", "zonule_E"):
        fd = _fd(sim, res, var, H[var])
        for out in OUTCOMES:
            rel = 2e-3 if out == "iop_mmhg" else 1e-4
            assert grads[out][var] == pytest.approx(fd[out], rel=rel, abs=1e-7), (out, var)
    # the indentation is measured at the case's buckle position (the break): turning the
    # buckle away from it lowers it
    assert grads["indentation_mm"]["buckle_meridian_deg"] < 0


def test_meridian_cannot_vary_for_an_encircling_buckle(base):
    sim, res, grads = base
    assert all(grads[o]["buckle_meridian_deg"] == 0.0 for o in OUTCOMES)
    with pytest.raises(ValueError, match="'buckle_meridian_deg' = 10.0 cannot vary.*no meridian"):
        sim.run({**res.design, "buckle_meridian_deg": 10.0})
    with pytest.raises(ValueError, match="'c10_sclera' = -1.0; a material constant must be > 0"):
        sim.run({**res.design, "c10_sclera": -1.0})


def test_band_tension_cannot_vary_in_a_displacement_controlled_case(base):
    sim, res, grads = base
    assert all(grads[o]["band_tension"] == 0.0 for o in OUTCOMES)
    with pytest.raises(ValueError, match="'band_tension' = 0.1 cannot vary"):
        sim.run({**res.design, "band_tension": 0.1})


@pytest.mark.parametrize("buckle, given, expected", [
    ("tire_ridged", 0.0, 0.01), ("sponge_radial", 0.0, 0.002), ("band", 0.005, 0.005)])
def test_buckle_contact_smoothing_automatic_by_buckle_kind_or_as_given(buckle, given, expected):
    from eyefem.eye.surgery import surgery

    setup = surgery(default_parameters(mesh="coarse", buckle=buckle, contact_smoothing=given),
                    None)
    assert setup.model.term("buckle").smoothing == expected


@pytest.mark.parametrize("given", [None, 0.5])
def test_ring_edge_default_or_as_given(given):
    from eyefem.eye.surgery import surgery

    kw = {} if given is None else {"buckle_edge": given}
    setup = surgery(default_parameters(mesh="coarse", buckle="tire_flat", **kw), None)
    term = setup.model.term("buckle")
    assert term.edge_width == (1.0 if given is None else given) == term.data["geo"][8]


def test_ring_edge_wider_than_half_the_ring_or_on_a_deformable_band_is_refused():
    from eyefem.eye.surgery import check_parameters

    with pytest.raises(ValueError, match=r"buckle_edge = 1.5 mm.*band \(2.5 mm wide\).*"
                                         r"below 1.25 mm"):
        check_parameters(default_parameters(buckle="band", buckle_edge=1.5))
    with pytest.raises(ValueError, match="buckle_edge = 0.5 mm shapes the rigid ring"):
        check_parameters(default_parameters(buckle="band", buckle_body="deformable",
                                            buckle_edge=0.5))
    check_parameters(default_parameters(buckle="band", buckle_edge=1.0))


def test_contact_quadrature_integrates_the_rigid_buckle_over_the_scleral_faces():
    """contact_quadrature = n: one contact point per Gauss point of the outer scleral faces
    (their 12 dofs and the sponge's free radial dof), refused on a deformable buckle."""
    from eyefem.eye.surgery import check_parameters, surgery

    nodes = surgery(default_parameters(mesh="coarse", buckle="sponge_radial"), None)
    faces = surgery(default_parameters(mesh="coarse", buckle="sponge_radial",
                                       contact_quadrature=2), None)
    t0, t2 = nodes.model.term("buckle"), faces.model.term("buckle")
    n_faces = len(faces.model.mesh.face_set("eye/sclera_outer"))
    assert t0.dofs.shape == (len(t0.nodes), 4) and t2.dofs.shape == (4 * n_faces, 13)
    # the same stiffness per unit area (N/mm^3) as the nodes' penalty over their mean area
    np.testing.assert_allclose(t2.data["alpha"] / t2.data["area"],
                               t0.alpha / np.mean(t0.node_area), rtol=1e-12)
    # the points' area weights add up to the faces' area (half the diagonals' cross product)
    x = faces.model.mesh.nodes[faces.model.mesh.face_set("eye/sclera_outer")]
    area = 0.5 * np.linalg.norm(np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1]), axis=1).sum()
    assert t2.data["area"].sum() == pytest.approx(area, rel=1e-3)
    with pytest.raises(ValueError, match="contact_quadrature = 2 integrates the rigid"):
        check_parameters(default_parameters(buckle="band", buckle_body="deformable",
                                            contact_quadrature=2))


@pytest.mark.parametrize("given", [None, 0.5])
def test_ridged_tire_flank_default_or_as_given(given):
    from eyefem.eye.surgery import surgery

    kw = {} if given is None else {"ridge_flank": given}
    setup = surgery(default_parameters(mesh="coarse", buckle="tire_ridged", **kw), None)
    assert setup.model.term("buckle").ridge_flank == (1.5 if given is None else given)
