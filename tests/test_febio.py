"""FEBio 4 decks: eyefem -> .feb -> eyefem gives the same model and the same solution.

FEBio itself is not installable here, so the check is the round trip: a block with a
follower pressure and prescribed displacements is written with write_feb, parsed as XML,
read back with read_feb and both models are solved by eyefem.
"""

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from eyefem.fem import generators
from eyefem.fem.materials import mooney_rivlin
from eyefem.fem.mesh import hex_geometry
from eyefem.fem.surface import PressureLoad
from eyefem.io.febio import FebError, write_feb
from eyefem.io.febio_read import build_model, read_feb
from eyefem.solve.problem import Setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage, solve

ROOT = Path(__file__).resolve().parents[1]


def _block_setup():
    """A 2 x 1 x 1 mm rubber block in 3 x 2 x 2 hexahedra: x0 clamped, z1 pulled up
    0.05 mm, a pressure of -0.05 MPa (a pull) on x1, 2 steps."""
    mat = mooney_rivlin("rubber", 0.25, 0.05)
    mesh = generators.box(2.0, 1.0, 1.0, 3, 2, 2, material=mat.name)
    model = solid_model(mesh, {mat.name: mat}, (PressureLoad("pressure", mesh, "x1", 0.0),))
    clamp = node_dofs(mesh.node_set("x0"), "xyz")
    lift = node_dofs(np.setdiff1d(mesh.node_set("z1"), mesh.node_set("x0")), "z")
    stage = Stage("load", 2, (np.r_[clamp, lift], np.r_[np.zeros(len(clamp)),
                                                         np.full(len(lift), 0.05)]),
                  params={"pressure": {"p": -0.05}})
    return Setup("block", model, [stage], lambda *a: {}, lambda *a: {})


@pytest.fixture(scope="module")
def round_trip(tmp_path_factory):
    setup = _block_setup()
    deck = tmp_path_factory.mktemp("feb") / "block.feb"
    warnings = write_feb(setup, deck)
    mesh, materials, loads = read_feb(deck)
    model, stage = build_model(mesh, materials, loads)
    native = solve(setup.model, setup.stages)
    imported = solve(model, [stage])
    return setup, deck, warnings, mesh, materials, loads, native, imported


def test_deck_is_febio_4_xml(round_trip):
    setup, deck, warnings, *_ = round_trip
    root = ET.parse(deck).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    assert warnings == []
    mat = root.find("Material/material")
    assert mat.get("type") == "Mooney-Rivlin"
    assert [float(mat.findtext(k)) for k in ("c1", "c2", "k")] == [0.25, 0.05, 300.0]
    assert len(root.findall("Mesh/Nodes/node")) == setup.model.mesh.n_nodes
    assert len(root.findall("Mesh/Elements[@type='hex8']/elem")) == setup.model.mesh.n_elem
    assert root.find("MeshDomains/SolidDomain").get("mat") == "rubber"
    assert root.find("Loads/surface_load").get("type") == "pressure"
    assert float(root.findtext("Loads/surface_load/pressure")) == -0.05
    assert root.findtext("Control/time_steps") == "2"
    kinds = sorted(bc.get("type") for bc in root.findall("Boundary/bc"))
    assert kinds == ["prescribed displacement", "zero displacement"]
    # FEBio numbers from 1: the first element is eyefem's element 0 plus one
    first = [int(v) for v in root.find("Mesh/Elements/elem").text.split(",")]
    assert first == (setup.model.mesh.hexes[0] + 1).tolist()


def test_round_trip_gives_the_same_model(round_trip):
    setup, _, _, mesh, materials, loads, *_ = round_trip
    m0 = setup.model.mesh
    np.testing.assert_array_equal(mesh.nodes, m0.nodes)
    np.testing.assert_array_equal(mesh.hexes, m0.hexes)
    np.testing.assert_array_equal(mesh.face_set("x1"), m0.face_set("x1"))
    np.testing.assert_array_equal(materials["rubber"].coeffs, setup.model.terms[0].coeffs[0])
    d0, v0 = setup.stages[0].prescribed
    order0, order1 = np.argsort(d0), np.argsort(loads.prescribed[0])
    np.testing.assert_array_equal(loads.prescribed[0][order1], d0[order0])
    np.testing.assert_array_equal(loads.prescribed[1][order1], v0[order0])
    assert loads.pressures == (("pressure", "x1", 0.0, -0.05),)
    assert loads.n_steps == 2 and loads.bulk_moduli == {"rubber": 300.0}
    # hex8 node order: every element keeps a positive volume after the round trip
    _, dv, det = hex_geometry(mesh.nodes, mesh.hexes)
    assert np.all(det > 0)
    assert np.sum(dv) == pytest.approx(2.0, rel=1e-12)


def test_round_trip_gives_the_same_solution(round_trip):
    *_, native, imported = round_trip
    n_u = 3 * round_trip[3].n_nodes
    u0, u1 = native.q[:n_u], imported.q[:n_u]
    # mm: a real deformation (0.0732 mm recorded; x1's open edges make its pressure a
    # FollowerPressure on both sides)
    assert np.max(np.abs(u0)) > 0.05
    assert np.max(np.abs(u1 - u0)) <= 1e-6


def test_uniaxial_case_exports(tmp_path):
    from eyefem.catalog import problems, schemas
    from eyefem.io.casefile import load_case

    case = load_case(ROOT / "cases/verification/uniaxial.toml", schemas())
    setup = problems()[case.problem][1](case.parameters, case.materials)
    write_feb(setup, tmp_path / "u.feb")
    _, materials, loads = read_feb(tmp_path / "u.feb")
    d0, v0 = setup.stages[0].prescribed
    got = dict(zip(loads.prescribed[0].tolist(), loads.prescribed[1].tolist()))
    assert got == dict(zip(d0.tolist(), v0.tolist()))  # the whole pull: x1 moves 2 mm
    assert loads.n_steps == setup.stages[0].n_steps and loads.pressures == ()
    assert materials["rubber"].coeffs[1, 0] == 25.0 and materials["rubber"].coeffs[0, 1] == 5.0


def test_skipped_terms_are_named(tmp_path):
    setup = _block_setup()
    x1 = setup.model.mesh.node_set("x1")
    orbit = __import__("eyefem.fem.terms", fromlist=["OrbitSpring"]).OrbitSpring(
        "orbit", x1, setup.model.mesh.nodes[x1])
    model = setup.model.with_terms((*setup.model.terms, orbit))
    warnings = write_feb(Setup("b", model, setup.stages, setup.probe, setup.finish),
                         tmp_path / "b.feb")
    assert any("'orbit'" in w for w in warnings)
    assert "not exported or approximated: term 'orbit'" in (tmp_path / "b.feb").read_text()


_DECK = """<?xml version="1.0"?>
<febio_spec version="{version}">
  <Module type="solid"/>
  <Control><time_steps>2</time_steps><step_size>0.5</step_size></Control>
  <Material>
    <material id="1" name="m" type="{mtype}"><c1>1</c1><c2>0</c2><k>1000</k></material>
  </Material>
  <Mesh>
    <Nodes name="all">
      <node id="1">0,0,0</node><node id="2">1,0,0</node><node id="3">1,1,0</node>
      <node id="4">0,1,0</node><node id="5">0,0,1</node><node id="6">1,0,1</node>
      <node id="7">1,1,1</node><node id="8">0,1,1</node>
    </Nodes>
    <Elements type="{etype}" name="part"><elem id="7">{conn}</elem></Elements>
    <NodeSet name="bottom">1,2,3,4</NodeSet>
    <NodeSet name="top">5:8</NodeSet>
  </Mesh>
  <MeshDomains><SolidDomain name="part" mat="m"/></MeshDomains>
  <Boundary>
    <bc name="fix" node_set="bottom" type="zero displacement">
      <x_dof>1</x_dof><y_dof>1</y_dof><z_dof>1</z_dof></bc>
    <bc name="pull" node_set="top" type="prescribed displacement">
      <dof>z</dof><value lc="1">0.2</value><relative>0</relative></bc>
  </Boundary>
  <LoadData>
    <load_controller id="1" type="loadcurve"><interpolate>LINEAR</interpolate>
      <points><pt>0,0</pt>{points}</points></load_controller>
  </LoadData>
</febio_spec>
"""


def _deck(tmp_path, version="4.0", mtype="Mooney-Rivlin", etype="hex8",
          conn="1,2,3,4,5,6,7,8", points="<pt>1,1</pt>"):
    f = tmp_path / "d.feb"
    f.write_text(_DECK.format(version=version, mtype=mtype, etype=etype, conn=conn,
                              points=points))
    return f


def test_reads_a_hand_written_deck(tmp_path):
    mesh, _, loads = read_feb(_deck(tmp_path))
    assert mesh.n_elem == 1 and mesh.materials == ("m",)
    top = node_dofs(np.arange(4, 8), "z")
    vals = dict(zip(loads.prescribed[0].tolist(), loads.prescribed[1].tolist()))
    assert all(vals[d] == 0.2 for d in top) and len(vals) == 12 + 4


@pytest.mark.parametrize("kw, message", [
    ({"version": "3.0"}, "version '3.0'"),
    ({"mtype": "Shenoy"}, "type 'Shenoy' is not supported"),
    ({"etype": "tet4", "conn": "1,2,3,5"}, "hexahedra are needed"),
    ({"conn": "1,4,3,2,5,8,7,6"}, "element 7: non-positive Jacobian"),
    ({"points": "<pt>1,1</pt></points><extend>SPIRAL</extend><points>"},
     "load curve 1: <extend>SPIRAL</extend> is not supported"),
])
def test_unsupported_decks_are_refused_clearly(tmp_path, kw, message):
    with pytest.raises(FebError, match=message) as exc:
        read_feb(_deck(tmp_path, **kw))
    assert "d.feb" in str(exc.value)


def test_missing_sections_are_named(tmp_path):
    f = _deck(tmp_path)
    text = f.read_text()
    start, end = text.index("<Material>"), text.index("</Material>") + len("</Material>")
    f.write_text(text[:start] + text[end:])
    with pytest.raises(FebError, match="no <Material> section"):
        read_feb(f)


def test_cli_export_and_import(tmp_path, capsys):
    from eyefem.cli.main import main

    deck = tmp_path / "u.feb"
    assert main(["-q", "export-feb", str(ROOT / "cases/verification/uniaxial.toml"),
                 "-o", str(deck)]) == 0
    assert ET.parse(deck).getroot().get("version") == "4.0"
    out = tmp_path / "run"
    assert main(["-q", "import-feb", str(deck), "-o", str(out), "--no-vtu"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    # the unit cube pulled to stretch 3: the far corner moves 2 mm along x and contracts
    # by 1 - 1/sqrt(3) along y and z (exact for Q1P0 under homogeneous stretch)
    far = np.sqrt(2.0**2 + 2 * (1 - 1 / np.sqrt(3.0)) ** 2)
    assert summary["max_displacement_mm"] == pytest.approx(far, rel=1e-9)
    bad = tmp_path / "bad.feb"
    bad.write_text("<febio_spec version='4.0'><Material/></febio_spec>")
    assert main(["-q", "import-feb", str(bad), "-o", str(tmp_path / "r2")]) == 2
    assert "bad.feb: no <Material> section" in capsys.readouterr().err
    assert main(["-q", "export-feb", str(tmp_path / "missing.toml"), "-o", str(deck)]) == 2
