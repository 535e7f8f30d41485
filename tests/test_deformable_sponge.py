"""Deformable radial sponge sewn onto the eye (surgery buckle_body = 'deformable')."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from eyefem.eye.buckle_meshes import deformable_sponge
from eyefem.eye.buckles import SPONGE_LENGTH, Buckle
from eyefem.eye.eyemodel import EyeGeometry
from eyefem.eye.sponge import (
    SPONGE_CLEARANCE,
    SPONGE_SPRING,
    fit_sponge,
    sponge_contact_term,
    sponge_divisions,
    sponge_spring_term,
)
from eyefem.eye.surgery import SURGERY_FIELDS, surgery
from eyefem.fem.mesh import hex_geometry

ROOT = Path(__file__).resolve().parents[1]


def _params(**kw):
    p = {f.name: f.default for f in SURGERY_FIELDS}
    p.update(mesh="coarse", buckle="sponge_radial", buckle_body="deformable", tightening=0.0,
             n_sutures=2, suture_width=8.5)
    p.update(kw)
    return p


def test_sponge_divisions_on_every_eye_level():
    """The levels with their own divisions keep them; any other level takes those of the
    finest listed level it is at least as fine as (half was a KeyError)."""
    assert sponge_divisions("coarse") == (8, 10) and sponge_divisions("default") == (16, 20)
    assert sponge_divisions("half") == (8, 10)  # 11 per patch edge: coarse's (10)
    assert sponge_divisions("medium") == (16, 16) and sponge_divisions("fine") == (16, 20)
    assert sponge_divisions("gradedc26") == (16, 20) and sponge_divisions("defaultx2") == (16, 20)
    with pytest.raises(ValueError, match="eye mesh level 'nonsense'"):
        sponge_divisions("nonsense")


def test_sponge_mesh_dimensions_and_sets():
    g, b = EyeGeometry(), Buckle("sponge_radial", 12.0, 30.0)
    Rc = 14.0  # axis radius
    m = deformable_sponge(b, g, Rc, n_len=10, n_circ=16)
    assert m.n_elem == 10 * (16 + 16 + 16)  # O-grid: 4 x 4 core, blend ring, outer ring
    _, dv, _ = hex_geometry(m.nodes, m.hexes)
    assert dv.min() > 0 and m.jacobian_ratio().min() > 0.4
    # a solid of revolution about the axis arc: the 16-gon's area times the axis length
    area = 0.5 * 16 * 2.5 ** 2 * np.sin(2 * np.pi / 16)
    assert dv.sum() == pytest.approx(area * SPONGE_LENGTH, rel=1e-2)
    # the axis arc lies in the meridian plane at 30 degrees, centred on the buckle's angle
    ph = np.radians(30.0)
    e = np.array([-np.sin(ph), np.cos(ph), 0.0])
    X = m.nodes
    v = X @ e  # across
    inplane = X - v[:, None] * e
    r = np.linalg.norm(inplane, axis=1)
    dist = np.hypot(r - Rc, v)  # distance from the axis arc
    mantle = np.unique(m.face_set("mantle"))
    np.testing.assert_allclose(dist[mantle], 2.5, atol=1e-9)
    mid = m.node_set("mid")
    tau = np.arccos(X[mid, 2] / r[mid])
    np.testing.assert_allclose(tau, b.centre_angle(g), atol=1e-12)
    # contact nodes face the eye, suture faces the far half, with outward normals
    inner = m.node_set("inner")
    assert np.all(r[inner] - Rc < 0.3 * 2.5 + 1e-9) and r[inner].min() == pytest.approx(Rc - 2.5)
    P = X[m.face_set("outer")]
    assert np.all(np.linalg.norm(P, axis=2) >= Rc - 1e-9)
    nrm = np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 1])
    c = P.mean(1)
    away = c - Rc * (c - (c @ e)[:, None] * e) / np.linalg.norm(
        c - (c @ e)[:, None] * e, axis=1, keepdims=True)  # from the axis to the face centre
    assert np.all(np.einsum("ij,ij->i", nrm, away) > 0)
    with pytest.raises(ValueError, match="only 'sponge_radial'"):
        deformable_sponge(Buckle("tire_flat"), g, Rc)
    with pytest.raises(ValueError, match="n_len = 5"):
        deformable_sponge(b, g, Rc, n_len=5)
    with pytest.raises(ValueError, match="n_circ = 12; must be a multiple of 8"):
        deformable_sponge(b, g, Rc, n_circ=12)


def test_deformable_buckles_are_a_band_a_tire_or_a_radial_sponge():
    with pytest.raises(ValueError, match="'band', 'tire_flat', 'tire_ridged', 'sponge_radial'; "
                       "got 'sponge_circumferential'.*set buckle to one of those"):
        surgery(_params(buckle="sponge_circumferential"), None)
    with pytest.raises(ValueError, match="tightening = 1.0 mm.*set tightening = 0"):
        surgery(_params(tightening=1.0), None)


def test_a_deformable_sponge_off_the_coarse_mesh_is_flagged(caplog):
    surgery(_params(mesh="medium"), None)
    assert "its suture steps were cut until they stopped" in caplog.text and "medium" in caplog.text
    assert "deformable_sponge_default.toml" in caplog.text


def test_the_default_eye_sponge_case_is_the_coarse_one_off_the_symmetry_plane(caplog):
    """deformable_sponge_default.toml: the coarse case with the default mesh and the three
    settings its header gives, and none else; with them no warning."""
    from eyefem.catalog import schemas
    from eyefem.io.casefile import load_case

    coarse = load_case(ROOT / "cases/surgery/deformable_sponge.toml", schemas())
    default = load_case(ROOT / "cases/surgery/deformable_sponge_default.toml", schemas())
    changed = {k: v for k, v in default.parameters.items() if coarse.parameters[k] != v}
    assert changed == {"mesh": "default", "buckle_meridian_deg": 3.0,
                       "contact_normals": "nodal", "globe_axial": 1.0}
    assert default.raw["materials"] == coarse.raw["materials"] and default.solver == coarse.solver
    with caplog.at_level("WARNING"):
        surgery({**default.parameters, "mesh": "medium"}, None)
    assert "deformable sponge" not in caplog.text and "sponge_radial on" not in caplog.text


def test_sponge_parked_then_fitted_snug():
    setup = surgery(_params(), None)
    parts = setup.parts
    mesh = parts.eye.mesh
    sponge = mesh.node_set("sponge")
    assert setup.model.mesh.n_elem == 2470 + 200  # coarse eye + sponge
    q = np.zeros(setup.model.n_dof)
    g0, _, _ = sponge_contact_term(mesh, 0.0833).update(q, None)._gaps(q)
    assert g0.min() == pytest.approx(0.3, abs=0.05)  # parked during stage 1
    # fitted on an eye inflated by 1 %: its closest node SPONGE_CLEARANCE off the sclera
    u = 0.01 * mesh.nodes
    u[sponge] = 0.0
    q[: u.size] = u.ravel()
    fitted = fit_sponge(mesh, parts.buckle, parts.eye.geometry, "coarse", 1.01, q)
    g, nodes, _ = sponge_contact_term(fitted, 0.0833).update(q, None)._gaps(q)
    assert g.min() == pytest.approx(SPONGE_CLEARANCE, abs=1e-6)
    assert np.all(g > 0)
    # only the sponge moved
    moved = np.any(fitted.nodes != mesh.nodes, axis=1)
    assert set(np.nonzero(moved)[0]) <= set(sponge)


@pytest.mark.slow
def test_deformable_sponge_case_coarse(tmp_path):
    from eyefem.cli.main import main

    assert main(["run", "cases/surgery/deformable_sponge.toml", "--out", str(tmp_path)]) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["buckle_body"] == "deformable"
    # the sutures press the sponge in: a local indentation, a small rise of the IOP
    assert 0.05 < s["indentation_mm"] < 0.5
    assert 15.0 < s["iop_mmhg"] < 16.0
    assert s["max_suture_force_N"] > 0.005
    rows = list(csv.DictReader(open(tmp_path / "surgery_history.csv")))
    springs = max(float(r["sponge_springs/force_N"]) for r in rows if r["sponge_springs/force_N"])
    assert springs < 0.1 * s["max_suture_force_N"]  # the springs on its drift carry little
    assert float(rows[-1]["buckle/force_N"]) > s["max_suture_force_N"]  # the sclera holds it


def test_sponge_springs_hold_its_drift_not_its_motion_into_the_sclera():
    g, b = EyeGeometry(), Buckle("sponge_radial", 12.0, 40.0)
    setup = surgery(_params(buckle_meridian_deg=40.0), None)
    mesh = setup.parts.eye.mesh
    t = sponge_spring_term(mesh, b, g)
    ids = mesh.node_set("sponge")
    th, ph = b.centre_angle(g), np.radians(40.0)
    n0 = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    across = np.array([-np.sin(ph), np.cos(ph), 0.0])
    k_rot, k_trans = SPONGE_SPRING

    def energy(u_nodes):
        q = np.zeros(setup.model.n_dof)
        q[3 * ids[:, None] + np.arange(3)] = u_nodes
        return float(setup.model.energy(q, setup.model.theta0(), ("sponge_springs",)))

    assert energy(np.tile(0.2 * n0, (len(ids), 1))) == pytest.approx(0.0, abs=1e-15)
    assert energy(np.tile(0.2 * across, (len(ids), 1))) == pytest.approx(0.5 * k_trans * 0.04)
    # a small rotation about the sponge's own axis (rolling) through its centroid
    X = mesh.nodes[ids]
    c = X.mean(axis=0)
    axis = np.cross(n0, across)
    a = 1e-3
    assert energy(a * np.cross(axis, X - c)) == pytest.approx(0.5 * k_rot * a * a, rel=1e-9)
    assert t.name == "sponge_springs"
