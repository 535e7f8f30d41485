"""Deformable encircling band on the eye (surgery buckle_body = 'deformable')."""

import json

import numpy as np
import pytest

from eyefem.eye.band import BAND_CLEARANCE, band_contact_term, fit_band
from eyefem.eye.buckle_meshes import deformable_band, ring_fit_groups
from eyefem.eye.buckles import Buckle
from eyefem.eye.eyemodel import EyeGeometry
from eyefem.eye.surgery import SEED_MATERIALS, SURGERY_FIELDS, surgery
from eyefem.fem.mesh import hex_geometry


def _params(**kw):
    p = {f.name: f.default for f in SURGERY_FIELDS}
    p.update(mesh="coarse", buckle="band", buckle_body="deformable", tightening=5.0)
    p.update(kw)
    return p


def test_band_mesh_dimensions_and_sets():
    g, b = EyeGeometry(), Buckle("band", 12.0)
    m = deformable_band(b, g, 11.6, 40)
    assert m.n_elem == 40 * 2 * 1
    r = np.linalg.norm(m.nodes, axis=1)
    inner, outer = m.node_set("inner"), np.unique(m.face_set("outer"))
    np.testing.assert_allclose(r[inner], 11.6, atol=1e-12)
    np.testing.assert_allclose(r[outer], 11.6 + 0.6, atol=1e-12)  # 0.6 mm thick
    tau = np.arccos(m.nodes[inner, 2] / r[inner])
    assert np.ptp(tau) * 11.6 == pytest.approx(2.5, abs=1e-9)  # 2.5 mm wide on the inner face
    assert np.mean(tau) == pytest.approx(b.centre_angle(g), abs=1e-12)
    # the two ends coincide on the cut (+y) but are distinct nodes
    e0, e1 = m.node_set("end0"), m.node_set("end1")
    assert len(e0) == len(e1) == 6 and not np.intersect1d(e0, e1).size
    np.testing.assert_allclose(m.nodes[e0], m.nodes[e1], atol=1e-12)
    assert np.all(np.abs(m.nodes[e0, 0]) < 1e-12) and np.all(m.nodes[e0, 1] > 0)
    assert m.jacobian_ratio().min() > 0.9


def _zone_volume(a, b, t1, t2):
    """Volume between the spheres of radii a < b and the polar angles t1 < t2, mm^3."""
    return 2 * np.pi / 3 * (b**3 - a**3) * (np.cos(t1) - np.cos(t2))


@pytest.mark.parametrize("kind", ["tire_flat", "tire_ridged"])
def test_tire_mesh_dimensions_sets_and_volume(kind):
    g, Ri = EyeGeometry(), 11.6
    b = Buckle(kind, 12.0)
    m = deformable_band(b, g, Ri, 80)
    ridged = kind == "tire_ridged"
    assert m.materials == ("tire",)
    assert m.n_elem == 80 * (12 if ridged else 8)  # 8 across (+ 4 in the ridge)
    assert m.jacobian_ratio().min() > 0.85
    _, dv, det = hex_geometry(m.nodes, m.hexes)
    assert det.min() > 0
    # closed form: the tire's base (7 mm wide, 1.25 mm thick) on the ridge (3 x 0.75 mm)
    th, h = b.centre_angle(g), 0.75 if ridged else 0.0
    exact = _zone_volume(Ri + h, Ri + h + 1.25, th - 3.5 / Ri, th + 3.5 / Ri)
    if ridged:
        exact += _zone_volume(Ri, Ri + h, th - 1.5 / Ri, th + 1.5 / Ri)
    assert dv.sum() == pytest.approx(exact, rel=3e-3)  # facets around: 80 chords
    r = np.linalg.norm(m.nodes, axis=1)
    tau = np.arccos(m.nodes[:, 2] / r)
    inner = m.node_set("inner")
    bottom = inner[np.abs(r[inner] - Ri) < 1e-9]
    assert np.ptp(tau[bottom]) * Ri == pytest.approx(3.0 if ridged else 7.0, abs=1e-9)
    seat = np.setdiff1d(inner, bottom)  # a ridged tire's base beside the ridge and flank tops
    assert len(seat) == (80 + 1) * (6 if ridged else 0)
    np.testing.assert_allclose(r[seat], Ri + h, atol=1e-12)
    outer = np.unique(m.face_set("outer"))
    np.testing.assert_allclose(r[outer], Ri + h + 1.25, atol=1e-12)
    assert np.ptp(tau[outer]) * Ri == pytest.approx(7.0, abs=1e-9)
    # inner faces face the globe centre, outer faces away from it
    for name, sign in (("inner", -1), ("outer", 1)):
        P = m.nodes[m.face_set(name)]
        nrm = np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 1])
        c = P.mean(1)
        flank = np.abs(np.einsum("ij,ij->i", nrm, c)) < 0.5 * np.linalg.norm(nrm, axis=1) * np.linalg.norm(c, axis=1)
        assert np.all(sign * np.einsum("ij,ij->i", nrm, c)[~flank] > 0)
        assert flank.sum() == (2 * 80 if ridged and name == "inner" else 0)  # ridge flanks
    with pytest.raises(ValueError, match="kind 'sponge_radial'; the deformable encircling"):
        deformable_band(Buckle("sponge_radial"), g, Ri, 80)
    with pytest.raises(ValueError, match="n_circ = 8; must be an integer >= 12"):
        deformable_band(b, g, Ri, 8)
    with pytest.raises(ValueError, match="n_thick = 0"):
        deformable_band(b, g, Ri, 80, n_thick=0)
    # fitted as columns (band, flat tire) or rigid cross-sections (ridged tire)
    groups = ring_fit_groups(b, 80)
    assert len(groups) == m.n_nodes
    assert len(np.unique(groups)) == (81 if ridged else 81 * 9)


def test_a_deformable_tire_off_the_coarse_mesh_is_flagged(caplog):
    surgery(_params(mesh="medium", buckle="tire_flat"), None)
    assert "deformable tire_flat on the medium eye mesh" in caplog.text
    assert "run to the end on the coarse and default eyes only" in caplog.text


def test_deformable_band_refuses_a_pulling_force():
    with pytest.raises(ValueError, match="band_tension"):
        surgery(_params(band_tension=0.2, tightening=0.0), None)


def test_band_fitted_on_the_sclera_all_around():
    setup = surgery(_params(), None)
    parts = setup.parts
    band = parts.band
    assert setup.model.mesh.n_elem == 2470 + 2 * band.n_circ  # coarse eye + band
    # parked 0.3 mm off the sclera during stage 1
    q = np.zeros(setup.model.n_dof)
    g0, _, _ = band_contact_term(parts, SEED_MATERIALS["sclera"])._gaps(q)
    assert g0.min() > 0.2
    # fitted on an eye inflated by 1 %: every inner band node BAND_CLEARANCE off the sclera
    u = 0.01 * parts.eye.mesh.nodes
    u[band.nodes] = 0.0
    q[: u.size] = u.ravel()
    parts = parts.refitted(fit_band(parts, 1.01, q), 1.01)
    g, nodes, _ = band_contact_term(parts, SEED_MATERIALS["sclera"]).update(q, None)._gaps(q)
    assert len(nodes) == len(parts.eye.mesh.node_set("band/inner"))
    np.testing.assert_allclose(g, BAND_CLEARANCE, atol=2e-4)


def test_ridged_tire_fitted_with_its_ridge_on_the_sclera():
    setup = surgery(_params(buckle="tire_ridged", tightening=10.0), None)
    parts = setup.parts
    assert setup.model.mesh.n_elem == 2470 + 12 * parts.band.n_circ  # coarse eye + tire
    assert "tire" in setup.model.mesh.materials
    q = np.zeros(setup.model.n_dof)
    u = 0.01 * parts.eye.mesh.nodes
    u[parts.band.nodes] = 0.0
    q[: u.size] = u.ravel()
    parts = parts.refitted(fit_band(parts, 1.01, q), 1.01)
    mesh = parts.eye.mesh
    g, nodes, _ = band_contact_term(parts, SEED_MATERIALS["sclera"]).update(q, None)._gaps(q)
    assert len(nodes) == len(mesh.node_set("band/inner"))
    # each cross-section moved as a whole: its closest node BAND_CLEARANCE off the sclera
    station = (nodes - parts.band.nodes[0]) // 23  # 23 nodes in a ridged cross-section
    closest = np.full(station.max() + 1, np.inf)
    np.minimum.at(closest, station, g)
    np.testing.assert_allclose(closest, BAND_CLEARANCE, atol=1e-9)
    # the ridge's bottom touches (within the facets' sag), its base stands 0.75 mm off
    r = np.linalg.norm(mesh.nodes[nodes], axis=1)
    bottom = r < r.min() + 0.1
    assert g[bottom].max() < 0.05
    np.testing.assert_allclose(g[r > r.min() + 0.7], 0.75, atol=0.05)


@pytest.mark.slow
def test_deformable_band_case_coarse(tmp_path):
    from eyefem.cli.main import main

    main(["run", "cases/surgery/deformable_band.toml", "--mesh", "coarse", "--out",
          str(tmp_path)])
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["buckle_body"] == "deformable"
    # the band indents the sclera and raises the IOP (the closed cavity is squeezed)
    assert s["indentation_mm"] > 0.2
    assert s["iop_after_tightening_mmhg"] > 18.0
    assert s["iop_mmhg"] > s["iop_after_tightening_mmhg"]  # the sutures add to it
    assert s["band_tension_N"] > 0.05 and s["max_suture_force_N"] > 0.0
    # the loop shortens by the tightening (its rest length taken up) less the band's stretch
    assert s["band_shortening_mm"] == pytest.approx(5.0)
    assert 0.0 < s["band_stretch_mm"] < 5.0
    assert s["band_loop_shortening_mm"] + s["band_stretch_mm"] == pytest.approx(5.0, abs=0.3)
    # stand-off springs on the band's rigid motion carry next to nothing
    import csv
    rows = list(csv.DictReader(open(tmp_path / "surgery_history.csv")))
    assert max(float(r["band_springs/force_N"]) for r in rows if r["band_springs/force_N"]) < 0.002


@pytest.mark.slow
@pytest.mark.parametrize("kind, hexes, tightening, indent, iop, how", [
    ("ridged", 12, 10.0, 1.0, 30.0, "shortened_loop"),  # case 4: strong
    ("flat", 8, 5.0, 0.4, 22.0, "shortened_loop"),  # case 1: weak
    ("flat", 8, 5.0, 0.4, 22.0, "pulled_ends")])  # the tire cut, its ends pulled
def test_deformable_tire_cases_coarse(tmp_path, kind, hexes, tightening, indent, iop, how):
    from eyefem.cli.main import main

    text = open(f"cases/surgery/deformable_{kind}_tire.toml").read()
    assert 'deformable_tightening = "shortened_loop"' in text
    case = tmp_path / "case.toml"
    case.write_text(text.replace('"shortened_loop"', f'"{how}"'))
    out = tmp_path / "out"  # a folder of its own: the run refuses one holding other files
    assert main(["run", str(case), "--no-vtu", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["buckle_body"] == "deformable" and s["elements"] == 2470 + hexes * 80
    # the tire is pressed in and the closed cavity squeezed
    assert s["indentation_mm"] > indent
    assert s["iop_after_tightening_mmhg"] > iop
    assert s["iop_mmhg"] > s["iop_after_tightening_mmhg"]  # the sutures add to it
    assert s["band_shortening_mm"] == pytest.approx(tightening)
    # the tightening shortens the loop and stretches the tire; neither takes all of it
    assert 0.0 < s["band_stretch_mm"] < s["band_loop_shortening_mm"] < tightening
    assert s["band_tension_N"] > 0.1 and s["max_suture_force_N"] > 0.0
    assert (out / "section_von_mises.png").stat().st_size > 10_000


def test_design_gradients_refuse_the_deformable_band():
    from eyefem.eye.design import SurgerySimulator

    with pytest.raises(ValueError, match="buckle_body = 'deformable'.*set buckle_body = 'rigid'"):
        SurgerySimulator(_params())


def test_a_shortened_loop_tire_is_closed_and_tightened_by_its_rest_length():
    from eyefem.fem.loop_solid import ShortenedLoopSolid

    setup = surgery(_params(buckle="tire_ridged", tightening=10.0,
                            deformable_tightening="shortened_loop"), None)
    parts, model = setup.parts, setup.model
    n_circ = parts.band.n_circ
    # closed: one cross-section of nodes fewer than the cut tire, the same elements
    assert len(parts.band.nodes) == 23 * n_circ and model.mesh.n_elem == 2470 + 12 * n_circ
    assert parts.band.closed and np.array_equal(parts.band.end0, parts.band.end1)
    solid = model.term("solid")
    assert isinstance(solid, ShortenedLoopSolid) and len(solid.data["loop_el"]) == 12 * n_circ
    tighten = next(s for s in setup.stages if s.name == "tighten")
    assert tighten.params["solid"] == {"shortening": 10.0}
    # held: the centre line across the globe, the +y cross-section along the loop (x = 0)
    dofs, values = tighten.prescribed
    assert set(3 * parts.band.end0) <= set(dofs.tolist()) and not values.any()
    suture = next(s for s in setup.stages if s.name == "suture")
    assert np.array_equal(suture.prescribed[0], dofs) and "solid" not in suture.params


def test_a_tire_with_pulled_ends_is_cut_and_its_ends_pulled_past_each_other():
    setup = surgery(_params(buckle="tire_ridged", tightening=10.0,
                            deformable_tightening="pulled_ends"), None)
    band = setup.parts.band
    assert not band.closed and len(band.nodes) == 23 * (band.n_circ + 1)
    assert not np.intersect1d(band.end0, band.end1).size
    assert type(setup.model.term("solid")).__name__ == "SolidQ1P0"
    tighten = next(s for s in setup.stages if s.name == "tighten")
    assert "solid" not in tighten.params
    target = dict(zip(*tighten.prescribed))
    assert {target[3 * n] for n in band.end0} == {5.0} and {target[3 * n] for n in band.end1} == {-5.0}
