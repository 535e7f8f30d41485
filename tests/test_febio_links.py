"""FEBio's trusses, discrete springs and rigid bodies as eyefem.io.febio_read reads them:
small decks written here after the TestSuite's (bt01: linear-truss BeamDomain; di01-di03:
<DiscreteSet> with "linear spring"; co10/cf*: "rigid body" with rigid_fixed /
rigid_displacement), each against a closed form; what is not mapped is refused by name.
FEBio's own numbers for the suite's decks are in benchmarks/febio_conformance.csv."""

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from eyefem.fem.bars import Bars
from eyefem.io.febio import FebError
from eyefem.io.febio_read import (LinearSpring, build_stages, read_feb, solution_norm)
from eyefem.solve.solver import solve

HEAD = """<?xml version="1.0" encoding="ISO-8859-1"?>
<febio_spec version="4.0">
  <Module type="solid"/>
  <Control><analysis>STATIC</analysis><time_steps>{steps}</time_steps>
    <step_size>{dt}</step_size></Control>
"""
CURVE = """  <LoadData><load_controller id="1" type="loadcurve"><interpolate>LINEAR</interpolate>
    <points><pt>0,0</pt><pt>1,1</pt></points></load_controller></LoadData>
"""


def _write(tmp_path, body, name="d.feb", steps=10):
    p = tmp_path / name
    p.write_text(HEAD.format(steps=steps, dt=1.0 / steps) + body + CURVE + "</febio_spec>\n")
    return p


def _solve(path):
    mesh, mats, loads = read_feb(path)
    model, stages = build_stages(mesh, mats, loads)
    return mesh, loads, model, stages, np.asarray(solve(model, stages).q)


def _truss_deck(tmp_path, E=200.0, area=0.5, force=15.0, extra=""):
    """One linear truss along x from node 1 (held) to node 2 (y, z held), pulled along x."""
    return _write(tmp_path, f"""  <Material><material id="1" name="wire" type="linear truss">
    <E>{E}</E><v>0.3</v></material></Material>
  <Mesh><Nodes name="n"><node id="1">0,0,0</node><node id="2">2,0,0</node></Nodes>
    <Elements type="line2" name="bar"><elem id="1">1,2</elem></Elements>
    <NodeSet name="fix">1</NodeSet><NodeSet name="tip">2</NodeSet></Mesh>
  <MeshDomains><BeamDomain name="bar" mat="wire" type="linear-truss">
    <cross_sectional_area>{area}</cross_sectional_area>{extra}</BeamDomain></MeshDomains>
  <Boundary><bc name="f" node_set="fix" type="zero displacement"><x_dof>1</x_dof><y_dof>1</y_dof>
    <z_dof>1</z_dof></bc><bc name="t" node_set="tip" type="zero displacement"><x_dof>0</x_dof>
    <y_dof>1</y_dof><z_dof>1</z_dof></bc></Boundary>
  <Loads><nodal_load name="pull" node_set="tip" type="nodal_load"><dof>x</dof>
    <scale lc="1">{force}</scale></nodal_load></Loads>
""")


def test_linear_truss_is_febio_hencky_law(tmp_path):
    """FEBio's linear truss carries T = E A ln(lam) / lam (FELinearTrussDomain): under an
    axial pull F the stretch solves E A ln(lam) / lam = F, here 14 % strain, where eyefem's
    Bars (EA (lam - 1)) would be 2 % off; the truss's solution_norm is the tip's motion."""
    E, A, F, L = 200.0, 0.5, 12.0, 2.0
    lam = brentq(lambda x: E * A * math.log(x) / x - F, 1.0, 2.0)
    mesh, loads, model, stages, q = _solve(_truss_deck(tmp_path, E, A, F))
    assert q[3] == pytest.approx(L * (lam - 1.0), rel=1e-9)
    assert solution_norm(mesh, stages[-1], q, loads) == pytest.approx(L * (lam - 1.0), rel=1e-9)
    assert abs(L * (lam - 1.0) - L * F / (E * A)) > 0.02 * L * (lam - 1.0)
    truss = model.term("linear_truss:bar")
    assert truss.forces(q, truss.params)[0] == pytest.approx(F, rel=1e-9)


def test_truss_refusals_name_the_feature(tmp_path):
    with pytest.raises(FebError, match="cross_sectional_area.*must be > 0"):
        read_feb(_truss_deck(tmp_path, area=0.0))
    deck = _truss_deck(tmp_path).read_text().replace('type="linear-truss"',
                                                      'type="elastic-truss"')
    (tmp_path / "e.feb").write_text(deck)
    with pytest.raises(FebError, match="elastic-truss.*not supported.*linear-truss"):
        read_feb(tmp_path / "e.feb")


def _spring_deck(tmp_path, kind="linear spring", E=3.0, force=1.5, rest=1.0):
    """Node 2 held in y, z, pulled along x by ``force``; a spring of length ``rest`` (0: two
    coincident nodes) ties it to node 1 (held)."""
    return _write(tmp_path, f"""  <Material><material id="1" name="m" type="neo-Hookean">
    <E>1</E><v>0.3</v></material></Material>
  <Mesh><Nodes name="n"><node id="1">0,0,0</node><node id="2">{rest},0,0</node></Nodes>
    <NodeSet name="fix">1</NodeSet><NodeSet name="tip">2</NodeSet>
    <DiscreteSet name="s"><delem>1,2</delem></DiscreteSet></Mesh>
  <MeshDomains/>
  <Boundary><bc name="f" node_set="fix" type="zero displacement"><x_dof>1</x_dof><y_dof>1</y_dof>
    <z_dof>1</z_dof></bc><bc name="t" node_set="tip" type="zero displacement"><x_dof>0</x_dof>
    <y_dof>1</y_dof><z_dof>1</z_dof></bc></Boundary>
  <Loads><nodal_load name="pull" node_set="tip" type="nodal_load"><dof>x</dof>
    <scale lc="1">{force}</scale></nodal_load></Loads>
  <Discrete><discrete_material id="1" name="k" type="{kind}"><E>{E}</E></discrete_material>
    <discrete dmat="1" discrete_set="s"/></Discrete>
""")


@pytest.mark.parametrize("rest", [1.0, 0.0])
def test_linear_spring_stretches_by_force_over_stiffness(tmp_path, rest):
    """FEBio's linear spring: F = E (l - L0), so the tip moves F / E, for a spring of
    length 1 and for one of zero length (di01's spring joins two coincident nodes)."""
    mesh, loads, model, stages, q = _solve(_spring_deck(tmp_path, rest=rest))
    assert q[3] == pytest.approx(1.5 / 3.0, rel=1e-10)
    assert solution_norm(mesh, stages[-1], q, loads) == pytest.approx(0.5, rel=1e-10)


def test_tension_only_spring_carries_no_push(tmp_path):
    """A tension-only linear spring pulled by 1.5 N stretches F / E like a linear one;
    shortened, it carries nothing (FEBio's E max(l - L0, 0))."""
    deck = _spring_deck(tmp_path, kind="tension-only linear spring", force=1.5)
    mesh, loads, model, stages, q = _solve(deck)
    assert q[3] == pytest.approx(0.5, rel=1e-10)
    term = model.term("tension-only_linear_spring:s")
    q2 = q.copy()
    q2[3] = -0.3
    assert term.forces(q2, term.params)[0] == 0.0


def test_linear_spring_is_bars_with_ea_e_l0():
    """The spring's energy equals eyefem.fem.bars.Bars with node ends and EA = E L0 at a
    random state (the mapping the docs state)."""
    rng = np.random.default_rng(3)
    X = rng.normal(size=(4, 3))
    conn = np.array([[0, 1], [2, 3]])
    E = np.array([2.0, 5.0])
    L0 = np.linalg.norm(X[conn[:, 1]] - X[conn[:, 0]], axis=1)
    spring = LinearSpring("s", conn, X, E)
    z = np.zeros((2, 2))
    bars = Bars("b", np.repeat(conn[:, :1], 4, 1), np.repeat(conn[:, 1:], 4, 1), z, z, X,
                EA=E * L0)
    u = 0.2 * rng.normal(size=12)
    e_s = float(spring.energy(u, spring.params, spring.data, spring.dofs))
    e_b = float(bars.energy(u, bars.params, bars.data, bars.dofs))
    assert e_s == pytest.approx(e_b, rel=1e-12)


def _rigid_deck(tmp_path, d=0.5, ks=2.0, rigid_bc=None):
    """A unit cube of FEBio's neo-Hookean (E = 1, v = 0.3) in uniaxial strain (bottom held
    in z, every side on rollers) under a rigid block (z in [2, 3]) lifted by ``d``: four
    linear springs (ks N/mm, length 1) tie the cube's top corners to the block's bottom."""
    nodes = [(x, y, z) for z in (0, 1, 2, 3) for y in (0, 1) for x in (0, 1)]
    text = "".join(f'<node id="{i + 1}">{x},{y},{z}</node>' for i, (x, y, z) in enumerate(nodes))
    hexa = lambda o: ",".join(str(o + i) for i in (1, 2, 4, 3, 5, 6, 8, 7))  # noqa: E731
    bc = rigid_bc if rigid_bc is not None else f"""<rigid_bc name="hold" type="rigid_fixed">
      <rb>plate</rb><Rx_dof>1</Rx_dof><Ry_dof>1</Ry_dof><Ru_dof>1</Ru_dof><Rv_dof>1</Rv_dof>
      <Rw_dof>1</Rw_dof></rigid_bc>
    <rigid_bc name="lift" type="rigid_displacement"><rb>plate</rb><dof>z</dof>
      <value lc="1">{d}</value><relative>0</relative></rigid_bc>"""
    return _write(tmp_path, f"""  <Material><material id="1" name="gel" type="neo-Hookean">
    <E>1</E><v>0.3</v></material>
    <material id="2" name="plate" type="rigid body"><density>1</density>
    <center_of_mass>0.5,0.5,2.5</center_of_mass></material></Material>
  <Mesh><Nodes name="n">{text}</Nodes>
    <Elements type="hex8" name="cube"><elem id="1">{hexa(0)}</elem></Elements>
    <Elements type="hex8" name="block"><elem id="2">{hexa(8)}</elem></Elements>
    <NodeSet name="bottom">1,2,3,4</NodeSet><NodeSet name="xs">1,2,3,4,5,6,7,8</NodeSet>
    <DiscreteSet name="ties"><delem>5,9</delem><delem>6,10</delem><delem>7,11</delem>
      <delem>8,12</delem></DiscreteSet></Mesh>
  <MeshDomains><SolidDomain name="cube" mat="gel"/><SolidDomain name="block" mat="plate"/>
  </MeshDomains>
  <Boundary><bc name="b" node_set="bottom" type="zero displacement"><x_dof>0</x_dof>
    <y_dof>0</y_dof><z_dof>1</z_dof></bc><bc name="r" node_set="xs" type="zero displacement">
    <x_dof>1</x_dof><y_dof>1</y_dof><z_dof>0</z_dof></bc></Boundary>
  <Rigid>{bc}</Rigid>
  <Discrete><discrete_material id="1" name="k" type="linear spring"><E>{ks}</E>
    </discrete_material><discrete dmat="1" discrete_set="ties"/></Discrete>
""")


def test_rigid_body_with_prescribed_motion_pulls_through_springs(tmp_path):
    """The block's nodes translate by the rigid_displacement; the cube's top rises by u
    where each spring's pull equals a quarter of the cube's uniaxial-strain force:
    ks (d - u) = [mu (lam^2 - 1) + lam_L ln lam] / (4 lam), lam = 1 + u (FEBio's neo-Hookean
    Cauchy stress on the unit current area); solved by brentq."""
    E, v, ks, d = 1.0, 0.3, 2.0, 0.5
    mu, lame = E / (2 * (1 + v)), E * v / ((1 + v) * (1 - 2 * v))
    u = brentq(lambda x: ks * (d - x) - (mu * ((1 + x) ** 2 - 1) + lame * math.log(1 + x))
               / (4 * (1 + x)), 0.0, d)
    mesh, loads, model, stages, q = _solve(_rigid_deck(tmp_path, d, ks))
    U = q[: 3 * mesh.n_nodes].reshape(-1, 3)
    assert np.allclose(U[8:], [0.0, 0.0, d], atol=1e-14)
    assert np.allclose(U[4:8, 2], u, rtol=1e-9)
    assert set(loads.rigid) == {"plate"} and mesh.n_elem == 1
    assert solution_norm(mesh, stages[-1], q, loads) == pytest.approx(2 * u, rel=1e-9)


@pytest.mark.parametrize("bc, match", [
    ("""<rigid_bc name="h" type="rigid_fixed"><rb>plate</rb><Rx_dof>1</Rx_dof>
        <Ry_dof>1</Ry_dof><Rz_dof>1</Rz_dof></rigid_bc>""",
     "rigid body 'plate': degrees of freedom Ru, Rv, Rw are free"),
    ("""<rigid_bc name="h" type="rigid_fixed"><rb>plate</rb><Rx_dof>1</Rx_dof><Ry_dof>1</Ry_dof>
        <Rz_dof>1</Rz_dof><Ru_dof>1</Ru_dof><Rv_dof>1</Rv_dof></rigid_bc>
        <rigid_bc name="turn" type="rigid_rotation"><rb>plate</rb><dof>Rw</dof>
        <value lc="1">0.1</value></rigid_bc>""", "a prescribed rotation .Rw = 0.1 rad"),
    ("""<rigid_load name="f" type="rigid_force"><rb>plate</rb></rigid_load>""",
     "rigid_load.*is not supported"),
])
def test_rigid_refusals_name_the_feature(tmp_path, bc, match):
    with pytest.raises(FebError, match=match):
        read_feb(_rigid_deck(tmp_path, rigid_bc=bc))


def _contact_deck(tmp_path, d=0.2, eps=5.0, extra=""):
    """A unit cube of FEBio's neo-Hookean with v = 0 (uniaxial stress is uniaxial strain:
    sigma_yy = mu (b_yy - 1) / J = 0 gives no lateral stretch) on rollers (z = 0, x = 0,
    y = 0), pressed by a rigid block (x, y in [-0.5, 1.5], z in [1, 2]) moved down by d,
    through FEBio's sliding-elastic contact of the cube's top (primary) against the
    block's bottom face (secondary), penalty eps MPa/mm."""
    cube = [(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1)]
    block = [(x, y, z) for z in (1, 2) for y in (-0.5, 1.5) for x in (-0.5, 1.5)]
    text = "".join(f'<node id="{i + 1}">{x},{y},{z}</node>'
                   for i, (x, y, z) in enumerate(cube + block))
    hexa = lambda o: ",".join(str(o + i) for i in (1, 2, 4, 3, 5, 6, 8, 7))  # noqa: E731
    return _write(tmp_path, f"""  <Material><material id="1" name="gel" type="neo-Hookean">
    <E>1</E><v>0</v></material>
    <material id="2" name="press" type="rigid body"><density>1</density></material></Material>
  <Mesh><Nodes name="n">{text}</Nodes>
    <Elements type="hex8" name="cube"><elem id="1">{hexa(0)}</elem></Elements>
    <Elements type="hex8" name="block"><elem id="2">{hexa(8)}</elem></Elements>
    <NodeSet name="z0">1,2,3,4</NodeSet><NodeSet name="x0">1,3,5,7</NodeSet>
    <NodeSet name="y0">1,2,5,6</NodeSet>
    <Surface name="top"><quad4 id="1">5,6,8,7</quad4></Surface>
    <Surface name="plate"><quad4 id="1">9,11,12,10</quad4></Surface>
    <SurfacePair name="touch"><primary>top</primary><secondary>plate</secondary></SurfacePair>
  </Mesh>
  <MeshDomains><SolidDomain name="cube" mat="gel"/><SolidDomain name="block" mat="press"/>
  </MeshDomains>
  <Boundary><bc name="b" node_set="z0" type="zero displacement"><z_dof>1</z_dof></bc>
    <bc name="sx" node_set="x0" type="zero displacement"><x_dof>1</x_dof></bc>
    <bc name="sy" node_set="y0" type="zero displacement"><y_dof>1</y_dof></bc></Boundary>
  <Rigid><rigid_bc name="hold" type="rigid_fixed"><rb>press</rb><Rx_dof>1</Rx_dof>
      <Ry_dof>1</Ry_dof><Ru_dof>1</Ru_dof><Rv_dof>1</Rv_dof><Rw_dof>1</Rw_dof></rigid_bc>
    <rigid_bc name="push" type="rigid_displacement"><rb>press</rb><dof>z</dof>
      <value lc="1">{-d}</value></rigid_bc></Rigid>
  <Contact><contact name="touch" surface_pair="touch" type="sliding-elastic">
    <laugon>PENALTY</laugon><penalty>{eps}</penalty><auto_penalty>0</auto_penalty>
    <two_pass>0</two_pass><tension>0</tension><fric_coeff>0</fric_coeff>{extra}</contact>
  </Contact>
""")


def test_sliding_contact_with_a_rigid_press_is_uniaxial_compression(tmp_path):
    """The block pushed down by d compresses the cube to lam = 1 + u with the penetration
    p = u + d carrying the cube's force: eps p A = mu (1 - lam^2) / lam (unit current area;
    FEBio's traction eps p integrated over the top face, eyefem's alpha = eps A / 4 at each
    of its four nodes: the same force for this uniform gap). Solved by brentq."""
    d, eps, mu = 0.2, 5.0, 0.5
    u = brentq(lambda x: eps * (x + d) - mu * (1 - (1 + x) ** 2) / (1 + x), -d, 0.0)
    mesh, loads, model, stages, q = _solve(_contact_deck(tmp_path, d, eps))
    U = q[: 3 * mesh.n_nodes].reshape(-1, 3)
    assert np.allclose(U[4:8, 2], u, rtol=1e-8)
    assert np.allclose(U[:8, :2], 0.0, atol=1e-10)  # no lateral stretch with v = 0
    assert loads.contacts[0].penalty == pytest.approx(eps * 0.25, rel=1e-12)
    assert abs(u) > 0.1  # a real compression, most of d


@pytest.mark.parametrize("extra, match", [
    ("<auto_penalty>1</auto_penalty>", "auto_penalty> 1 is not supported"),
    ("<fric_coeff>0.2</fric_coeff>", "fric_coeff> 0.2 is not supported"),
])
def test_contact_refusals_name_the_feature(tmp_path, extra, match):
    deck = _contact_deck(tmp_path).read_text()
    tag = extra.split(">")[0] + ">"
    deck = deck.replace(deck[deck.index(tag):deck.index(tag.replace("<", "</"))
                             + len(tag) + 1], extra)
    (tmp_path / "c.feb").write_text(deck)
    with pytest.raises(FebError, match=match):
        read_feb(tmp_path / "c.feb")


def _volume_deck(tmp_path, eps=-2.0, in_step=False):
    """A unit cube of FEBio's neo-Hookean with v = 0 on rollers (x, y, z = 0), its top
    pulled up 0.2 mm (two steps: 0.1, then 0.2); FEBio's volume constraint (penalty eps)
    on its six faces, from the start or from the second step."""
    cube = [(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1)]
    text = "".join(f'<node id="{i + 1}">{x},{y},{z}</node>' for i, (x, y, z) in enumerate(cube))
    faces = "".join(f'<quad4 id="{i + 1}">{f}</quad4>' for i, f in enumerate(
        ("1,3,4,2", "5,6,8,7", "1,2,6,5", "3,7,8,4", "1,5,7,3", "2,4,8,6")))
    cons = f"""<Constraints><constraint name="vol" surface="all" type="volume">
      <laugon>0</laugon><penalty>{eps}</penalty></constraint></Constraints>"""
    step = lambda name, body: f"""<step name="{name}"><Control><time_steps>5</time_steps>
      <step_size>0.2</step_size></Control>{body}</step>"""  # noqa: E731
    return _write(tmp_path, f"""  <Material><material id="1" name="gel" type="neo-Hookean">
    <E>1</E><v>0</v></material></Material>
  <Mesh><Nodes name="n">{text}</Nodes>
    <Elements type="hex8" name="cube"><elem id="1">1,2,4,3,5,6,8,7</elem></Elements>
    <NodeSet name="z0">1,2,3,4</NodeSet><NodeSet name="x0">1,3,5,7</NodeSet>
    <NodeSet name="y0">1,2,5,6</NodeSet><NodeSet name="top">5,6,7,8</NodeSet>
    <Surface name="all">{faces}</Surface></Mesh>
  <MeshDomains><SolidDomain name="cube" mat="gel"/></MeshDomains>
  <Boundary><bc name="b" node_set="z0" type="zero displacement"><z_dof>1</z_dof></bc>
    <bc name="sx" node_set="x0" type="zero displacement"><x_dof>1</x_dof></bc>
    <bc name="sy" node_set="y0" type="zero displacement"><y_dof>1</y_dof></bc>
    <bc name="up" node_set="top" type="prescribed displacement"><dof>z</dof>
      <value lc="1">0.1</value></bc></Boundary>
  {"" if in_step else cons}
  <Step>{step("first", "")}{step("second", cons if in_step else "")}</Step>
""").with_suffix(".feb")


@pytest.mark.parametrize("in_step", [False, True])
def test_volume_constraint_is_a_liquid_cavity(tmp_path, in_step):
    """FEBio's p = eps (V - V0) on the faces is a liquid of pressure P = eps (V - V0)
    (FEVolumeConstraint::LoadVector): in the cube, stretched to lam = 1.2 with lateral
    stretch a, the free faces carry sigma_xx = mu (a^2 - 1) / (a^2 lam) = P, V = a^2 lam
    (brentq). From the start V0 = 1; written in the second step, the constraint takes
    V0 = the volume at that step's start (1.1: v = 0, no lateral stretch before)."""
    eps, mu, lam = -2.0, 0.5, 1.2
    V0 = 1.1 if in_step else 1.0
    a = brentq(lambda a: mu * (a * a - 1) / (a * a * lam) - eps * (a * a * lam - V0), 0.5, 1.0)
    deck = _volume_deck(tmp_path, eps, in_step)
    text = deck.read_text().replace('<pt>0,0</pt><pt>1,1</pt>', '<pt>0,0</pt><pt>1,1</pt>'
                                    '<pt>2,2</pt>')
    deck.write_text(text)
    mesh, loads, model, stages, q = _solve(deck)
    U = q[: 3 * mesh.n_nodes].reshape(-1, 3)
    assert np.allclose(U[4:, 2], 0.2, rtol=1e-12)
    assert U[7, 0] == pytest.approx(a - 1.0, rel=1e-8)
    assert U[7, 1] == pytest.approx(a - 1.0, rel=1e-8)
    assert a < 0.99


def test_volume_constraint_refusals(tmp_path):
    deck = _volume_deck(tmp_path)
    deck.write_text(deck.read_text().replace("<laugon>0</laugon>", "<laugon>1</laugon>"))
    with pytest.raises(FebError, match="augmented Lagrangian holds the volume exactly"):
        read_feb(deck)
    deck = _volume_deck(tmp_path, eps=2.0)
    with pytest.raises(FebError, match="needs eps < 0"):
        read_feb(deck)


@pytest.mark.parametrize("make", ["truss", "spring", "tension_only"])
def test_link_terms_residual_tangent_and_rotation(make):
    """Each link's autodiff residual equals its hand-coded axial force along the link
    (forces(): EA ln(lam) / lam, E (l - L0)), its Hessian the central differences of that
    residual (step 1e-6 mm: truncation ~1e-12, roundoff ~1e-10 of forces of order 1 N), and
    its energy is unchanged by a rigid rotation."""
    import jax
    import jax.numpy as jnp

    from eyefem.io.febio_read import LinearSpring, LinearTruss

    xyz = np.array([[0.0, 0.0, 0.0], [1.0, 0.2, -0.1], [0.3, 1.1, 0.4]])
    nodes = np.array([[0, 1], [1, 2]])
    term = (LinearTruss("t", nodes, xyz, [40.0, 25.0]) if make == "truss"
            else LinearSpring("s", nodes, xyz, [40.0, 25.0], tension_only=make != "spring"))
    q = np.zeros(9)
    q[3:6] = [0.12, -0.03, 0.05]  # node 1 moves: link 0 stretched, link 1 changed too
    q[6:9] = [-0.02, 0.3, 0.01]
    q_loc = jnp.asarray(q[term.dofs])
    grad = jax.grad(lambda x: jnp.sum(term.local_energy(x, term.params, term.data)))
    g = np.asarray(grad(q_loc))
    x = (term.data["X"] + q[term.dofs]).reshape(-1, 2, 3)
    t = (x[:, 1] - x[:, 0]) / np.linalg.norm(x[:, 1] - x[:, 0], axis=1)[:, None]
    f = term.forces(q, term.params)
    assert np.abs(f).max() > 0.1
    np.testing.assert_allclose(g, np.concatenate([-f[:, None] * t, f[:, None] * t], axis=1),
                               atol=1e-12 * np.abs(f).max())
    hess = jax.jacfwd(grad)(q_loc)  # (m, 6, m, 6): each link's own block on the diagonal
    h = 1e-6
    for j in range(6):
        e = jnp.zeros_like(q_loc).at[:, j].set(h)
        fd = (np.asarray(grad(q_loc + e)) - np.asarray(grad(q_loc - e))) / (2 * h)
        exact = np.stack([np.asarray(hess)[k, :, k, j] for k in range(len(nodes))])
        np.testing.assert_allclose(exact, fd, atol=1e-6 * np.abs(np.asarray(hess)).max())
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = (xyz + q.reshape(-1, 3)) @ R.T - xyz
    e0 = float(jnp.sum(term.local_energy(q_loc, term.params, term.data)))
    e1 = float(jnp.sum(term.local_energy(jnp.asarray(moved.reshape(-1)[term.dofs]),
                                         term.params, term.data)))
    assert e0 > 0 and abs(e1 - e0) < 1e-12 * e0
