"""Deformable encircling band on the eye (surgery buckle_body = 'deformable')."""

import json

import numpy as np
import pytest

from eyefem.buckles import Buckle, deformable_band
from eyefem.eyemodel import EyeGeometry
from eyefem.problems.surgery import (BAND_CLEARANCE, SURGERY_FIELDS, band_contact_term, fit_band,
                                     surgery)


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


def test_deformable_needs_a_band():
    with pytest.raises(ValueError, match="buckle = 'band' and 'sponge_radial'; got 'tire_ridged'"):
        surgery(_params(buckle="tire_ridged"), None)
    with pytest.raises(ValueError, match="band_tension"):
        surgery(_params(band_tension=0.2, tightening=0.0), None)


def test_band_fitted_on_the_sclera_all_around():
    setup = surgery(_params(), None)
    parts = setup.parts
    band = parts.band
    assert setup.model.mesh.n_elem == 2470 + 2 * band.n_circ  # coarse eye + band
    # parked 0.3 mm off the sclera during stage 1
    q = np.zeros(setup.model.n_dof)
    g0, _, _ = band_contact_term(parts)._gaps(q)
    assert g0.min() > 0.2
    # fitted on an eye inflated by 1 %: every inner band node BAND_CLEARANCE off the sclera
    u = 0.01 * parts.eye.mesh.nodes
    u[band.nodes] = 0.0
    q[: u.size] = u.ravel()
    parts.eye = parts.eye.__class__(**{**parts.eye.__dict__, "mesh": fit_band(parts, 1.01, q)})
    g, nodes, _ = band_contact_term(parts).update(q, None)._gaps(q)
    assert len(nodes) == len(parts.eye.mesh.node_set("band/inner"))
    np.testing.assert_allclose(g, BAND_CLEARANCE, atol=2e-4)


@pytest.mark.slow
def test_deformable_band_case_coarse(tmp_path):
    from eyefem.cli import main

    main(["run", "cases/surgery/deformable_band.toml", "--mesh", "coarse", "--out",
          str(tmp_path)])
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["buckle_body"] == "deformable"
    # the band indents the sclera and raises the IOP (the closed cavity is squeezed)
    assert s["indentation_mm"] > 0.2
    assert s["iop_after_tightening_mmhg"] > 18.0
    assert s["iop_mmhg"] > s["iop_after_tightening_mmhg"]  # the sutures add to it
    assert s["band_tension_N"] > 0.05 and s["max_suture_force_N"] > 0.0
    # the loop shortens by the end overlap minus the band's own stretch
    assert s["band_shortening_mm"] == pytest.approx(5.0)
    assert 0.0 < s["band_stretch_mm"] < 5.0
    assert s["band_loop_shortening_mm"] + s["band_stretch_mm"] == pytest.approx(5.0, abs=0.3)
    # stand-off springs on the band's rigid motion carry next to nothing
    import csv
    rows = list(csv.DictReader(open(tmp_path / "surgery_history.csv")))
    assert max(float(r["band_springs/force_N"]) for r in rows if r["band_springs/force_N"]) < 0.002


def test_design_gradients_refuse_the_deformable_band():
    from eyefem.design import SurgerySimulator

    with pytest.raises(ValueError, match="buckle_body = 'deformable'.*set buckle_body = 'rigid'"):
        SurgerySimulator(_params())
