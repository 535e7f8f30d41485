"""The time-dependent sclera and cornea wired into the model (eyefem.eye.relaxation,
eyefem.solve.model.with_viscoelastic; issue 74, item 3): the case parameters, the Prony
tables per tissue, and on a two-tissue bar and on the coarse eye the instantaneous
response (the elastic law) and the long-time response (the relaxed modulus)."""

from __future__ import annotations

import numpy as np
import pytest

from eyefem.eye.relaxation import (RELAXATION_FIELDS, WALL_TISSUES, Relaxation, relaxation,
                                   with_relaxation)
from eyefem.fem import generators
from eyefem.fem.materials import MooneyRivlin
from eyefem.fem.solid import SolidQ1P0
from eyefem.fem.terms import NodalForce
from eyefem.fem.viscoelastic import ViscoelasticQ1P0
from eyefem.solve.loadpath import Stage, solve
from eyefem.solve.model import node_dofs, prony_tables, solid_model, with_viscoelastic
from eyefem.solve.options import NewtonOptions

G, TAU = [0.3, 0.2], [1.0, 20.0]  # fractions, minutes
CUSTOM = {"tissue_relaxation": "custom", "relaxation_g": G, "relaxation_tau_min": TAU}
DEFAULTS = {f.name: f.default for f in RELAXATION_FIELDS}


def test_none_is_the_default_and_leaves_the_model_elastic():
    assert DEFAULTS["tissue_relaxation"] == "none"
    assert relaxation(DEFAULTS) is None and relaxation({}) is None
    mesh = generators.box(1.0, 1.0, 1.0, 1, 1, 1, material="sclera")
    model = solid_model(mesh, {"sclera": MooneyRivlin.from_terms("sclera", {"c10": 0.1})})
    assert with_relaxation(model, DEFAULTS) is model


def test_custom_constants_name_the_wall_tissues():
    rel = relaxation({**DEFAULTS, **CUSTOM})
    assert rel == Relaxation((0.3, 0.2), (1.0, 20.0), WALL_TISSUES, "user (case file)")
    assert rel.g_inf == pytest.approx(0.5, abs=1e-15)
    assert rel.prony() == {t: ((0.3, 0.2), (1.0, 20.0)) for t in WALL_TISSUES}
    names = {f.name for f in RELAXATION_FIELDS}
    assert names == {"tissue_relaxation", "relaxation_g", "relaxation_tau_min",
                     "relaxation_tissues"}
    for f in RELAXATION_FIELDS:
        assert f.check is None or f.check(f.default), f.name


@pytest.mark.parametrize("change, match", [
    ({"relaxation_g": []}, "needs relaxation_g"),
    ({"relaxation_g": [0.6, 0.5]}, "sum below 1"),
    ({"relaxation_g": [0.2, -0.1]}, "must be >= 0"),
    ({"relaxation_tau_min": [1.0]}, "2 fractions and 1 time constants"),
    ({"relaxation_tau_min": [1.0, 0.0]}, "above 0 minutes"),
    ({"relaxation_tissues": []}, "relaxation_tissues is empty"),
    ({"tissue_relaxation": "song2023"}, "choose one of"),
])
def test_bad_constants_are_refused_by_name(change, match):
    with pytest.raises(ValueError, match=match):
        relaxation({**DEFAULTS, **CUSTOM, **change})


def test_a_tissue_the_mesh_lacks_is_refused():
    mesh = generators.box(1.0, 1.0, 1.0, 1, 1, 1, material="sclera")
    model = solid_model(mesh, {"sclera": MooneyRivlin.from_terms("sclera", {"c10": 0.1})})
    with pytest.raises(ValueError, match=r"relaxation_tissues: \['limbus', 'cornea'\]"):
        with_relaxation(model, {**DEFAULTS, **CUSTOM})
    out = with_relaxation(model, {**DEFAULTS, **CUSTOM, "relaxation_tissues": ["sclera"]})
    assert type(out.term("solid")) is ViscoelasticQ1P0


def test_prony_tables_pad_short_series_and_keep_elastic_rows():
    """Rows follow the mesh's materials; an elastic tissue gets g = 0 and the first relaxing
    tissue's time constants (so a mixed element keeps them); a shorter series is padded."""
    g, tau = prony_tables(("choroid", "sclera", "cornea"),
                          {"sclera": ([0.3, 0.2], [1.0, 20.0]), "cornea": ([0.1], [5.0])})
    assert np.array_equal(g, [[0, 0], [0.3, 0.2], [0.1, 0]])
    assert np.array_equal(tau, [[1.0, 20.0], [1.0, 20.0], [5.0, 20.0]])
    with pytest.raises(ValueError, match=r"materials \['lens'\] are not in the mesh"):
        prony_tables(("sclera",), {"lens": ([0.1], [1.0])})
    with pytest.raises(ValueError, match="sum g_i < 1"):
        prony_tables(("sclera",), {"sclera": ([0.7, 0.4], [1.0, 2.0])})


OPTIONS = NewtonOptions(rtol=1e-12, atol=1e-14)
SCLERA = MooneyRivlin.from_terms("sclera", {"c10": 0.2, "c30": 50.0})
CHOROID = MooneyRivlin.from_terms("choroid", {"c10": 0.05})


def _bar(materials, prony=None):
    """Two 1 mm hexahedra in series along x (sclera, then choroid), pulled at x = 2 mm by
    a held force of 0.02 N, symmetry planes held."""
    mesh = generators.box(2.0, 1.0, 1.0, 2, 1, 1, material="sclera")
    mesh = mesh.replace(materials=("sclera", "choroid"), material_ids=np.array([0, 1]))
    pull = node_dofs(mesh.node_set("x1"), "x")
    force = NodalForce("load", pull, {"f": np.zeros(len(pull))})
    model = solid_model(mesh, materials, (force,), prony=prony)
    held = np.concatenate([node_dofs(mesh.node_set(s), c)
                           for s, c in (("x0", "x"), ("y0", "y"), ("z0", "z"))])
    load = {"load": {"f": np.full(len(pull), 0.02 / len(pull))}}
    return model, (held, np.zeros(len(held))), load, pull


def test_two_tissue_bar_instantaneous_elastic_and_relaxed_modulus():
    """A force applied in a stage without duration, then held 100 tau_2: the first state is
    the elastic solid's (roundoff), the last the elastic solid's with the relaxing tissue's
    coefficients scaled by g_inf = 0.5 (the elastic tissue untouched), to 1e-10."""
    mats = {"sclera": SCLERA, "choroid": CHOROID}
    model, bc, load, pull = _bar(mats, prony={"sclera": (G, TAU)})
    solid = model.term("solid")
    assert type(solid) is ViscoelasticQ1P0
    assert np.array_equal(solid.g, [[0.3, 0.2], [0.0, 0.0]])
    times = tuple(np.geomspace(0.05, 2000.0, 30))
    stages = [Stage("load", 2, bc, params=load),
              Stage("hold", len(times), bc, params=load, duration=times[-1], times=times)]
    states = []
    solve(model, stages, options=OPTIONS,
          on_step=lambda rec, m, q, th: states.append((rec.stage, q[pull].mean())))
    u0 = [u for s, u in states if s == "load"][-1]
    u_end = states[-1][1]
    elastic, bc, load, _ = _bar(mats)
    u_el = solve(elastic, [Stage("load", 2, bc, params=load)], options=OPTIONS).q[pull].mean()
    scaled = MooneyRivlin("sclera", SCLERA.coeffs * 0.5)
    relaxed, bc, load, _ = _bar({"sclera": scaled, "choroid": CHOROID})
    u_rel = solve(relaxed, [Stage("load", 2, bc, params=load)], options=OPTIONS).q[pull].mean()
    assert abs(u0 - u_el) < 1e-12 * abs(u_el)
    assert abs(u_end - u_rel) < 1e-10 * abs(u_rel)
    assert u_rel > 1.1 * u_el  # the test can fail: the sclera crept
    hold = [u for s, u in states if s == "hold"]
    assert np.all(np.diff(hold) > 0)  # creep under a held load


def test_only_the_q1p0_brick_takes_the_relaxation():
    mesh = generators.box(1.0, 1.0, 1.0, 1, 1, 1, material="sclera")
    model = solid_model(mesh, {"sclera": SCLERA}, prony={"sclera": (G, TAU)})
    with pytest.raises(ValueError, match="is a ViscoelasticQ1P0"):
        with_viscoelastic(model, {"sclera": (G, TAU)})
    elastic = solid_model(mesh, {"sclera": SCLERA})
    assert type(elastic.term("solid")) is SolidQ1P0


@pytest.fixture(scope="module")
def eye_runs():
    """The coarse eye of the pressure_volume problem (physiological preset), its wall
    relaxing with G, TAU: the IOP applied in a stage without duration, then held to 20,000
    minutes (1000 tau_2) on the timeline; and the elastic eye and the eye with the wall's
    coefficients scaled by g_inf under the same IOP."""
    import dataclasses

    from eyefem.eye.presets import WALL_RATIOS, preset_terms
    from eyefem.eye.validation import PV_FIELDS, pv_parts

    p = {**{f.name: f.default for f in PV_FIELDS}, "mesh": "coarse"}
    model, pressurise, held, _ = pv_parts(p)
    opts = NewtonOptions(rtol=1e-11)
    visco = with_relaxation(model, {**DEFAULTS, **CUSTOM})
    times = (0.5, 2.0, 8.0, 30.0, 100.0, 400.0, 2000.0, 20000.0)
    hold = Stage("hold", len(times), held, active=pressurise.active, duration=times[-1],
                 times=times)
    rows = []
    solve(visco, [pressurise, hold], options=opts,
          on_step=lambda rec, m, q, th: rows.append((rec.stage, q.copy(), dict(th["solid"]))))
    elastic = solve(model, [pressurise], options=opts).q
    g_inf = 1.0 - sum(G)
    terms = preset_terms("physiological")
    scaled = {t: MooneyRivlin.from_terms(t, {k: g_inf * v for k, v in terms[t].items()})
              for t in WALL_RATIOS}
    relaxed_model, *_ = pv_parts(p, scaled)
    relaxed = solve(relaxed_model, [dataclasses.replace(pressurise, n_steps=3)],
                    options=opts).q
    return model, rows, elastic, relaxed


@pytest.mark.slow
def test_eye_wall_is_elastic_at_once_and_relaxed_after_1000_tau(eye_runs):
    """Coarse eye (2470 hexahedra), physiological wall relaxing as G(t) = 0.5 + 0.3
    e^(-t/1 min) + 0.2 e^(-t/20 min) under a held IOP of 15 mmHg: the displacements after
    the instantaneous pressurising equal the elastic eye's (1e-9 of the largest), those at
    20,000 minutes the eye's with the wall's c_rs scaled by g_inf = 0.5 (1e-8); between,
    the wall creeps outward at every step and the clock reaches 20,000 minutes. (At 2000
    minutes, after a 1600-minute step, the last state was still 6e-7 from the relaxed one:
    the step's update takes S0 linear over the step, and the creep left over from the
    step before carries an internal stress g_2 tau_2 / dt of its change.)"""
    model, rows, elastic, relaxed = eye_runs
    n_u = model.n_u
    q0 = [q for s, q, _ in rows if s == "pressurise"][-1]
    scale = np.max(np.abs(elastic[:n_u]))
    assert np.max(np.abs(q0[:n_u] - elastic[:n_u])) < 1e-9 * scale
    q_end, th_end = rows[-1][1], rows[-1][2]
    assert float(th_end["time"]) + float(th_end["dt"]) == pytest.approx(20000.0, rel=1e-12)
    assert np.max(np.abs(q_end[:n_u] - relaxed[:n_u])) < 1e-8 * np.max(np.abs(relaxed[:n_u]))
    assert np.max(np.abs(relaxed[:n_u] - elastic[:n_u])) > 0.1 * scale  # the wall crept
    norms = [np.linalg.norm(q[:n_u]) for s, q, _ in rows if s == "hold"]
    assert np.all(np.diff(norms) > 0)


def _surgery_params(**over):
    from eyefem.eye.surgery import SURGERY_FIELDS

    return {**{f.name: f.default for f in SURGERY_FIELDS}, "mesh": "coarse", **over}


def test_the_surgery_refuses_relaxation_without_the_timeline():
    from eyefem.eye.surgery import check_parameters

    p = _surgery_params(tissue_relaxation="custom", relaxation_g=[0.25],
                        relaxation_tau_min=[10.0])
    with pytest.raises(ValueError, match="volume_regulation = true"):
        check_parameters(p)
    check_parameters({**p, "volume_regulation": True})  # the timeline: accepted


def test_the_surgery_builds_its_wall_relaxing_on_the_timeline():
    """The surgery's schema carries the relaxation's fields, and a case with them builds
    the wall tissues as ViscoelasticQ1P0 (the other tissues elastic rows)."""
    from eyefem.eye.surgery import SURGERY_FIELDS, surgery

    names = {f.name for f in SURGERY_FIELDS}
    assert {f.name for f in RELAXATION_FIELDS} <= names
    p = _surgery_params(tissue_relaxation="custom", relaxation_g=[0.25, 0.25],
                        relaxation_tau_min=[10.0, 1440.0], volume_regulation=True,
                        materials_preset="physiological")
    setup = surgery(p, {})
    solid = next(t for t in setup.model.terms if t.name == "solid")
    assert isinstance(solid, ViscoelasticQ1P0)
    elastic = surgery({**p, "tissue_relaxation": "none"}, {})
    assert not isinstance(next(t for t in elastic.model.terms if t.name == "solid"),
                          ViscoelasticQ1P0)
