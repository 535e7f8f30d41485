"""A patient's eye from biometry (eyefem.eye.biometry): the geometry it gives, the
errors for measurements that make no eye, and (slow) a long eye's changed outcomes."""

import json
from pathlib import Path

import numpy as np
import pytest

from eyefem.catalog import schemas
from eyefem.eye.biometry import BIOMETRY_FIELDS, eye_geometry
from eyefem.eye.eyemodel import EyeGeometry, build_eye
from eyefem.io.casefile import CaseError, load_case

ROOT = Path(__file__).resolve().parents[1]


def test_defaults_are_the_reference_eye():
    assert eye_geometry({}) == EyeGeometry()


@pytest.mark.parametrize("axial_length", [22.0, 26.0])
def test_the_mesh_has_the_measured_axial_length(axial_length):
    g = eye_geometry({"axial_length": axial_length, "anterior_chamber_depth": 3.2})
    eye = build_eye(g, "coarse")
    apex = eye.mesh.nodes[eye.mesh.node_set("eye/apex")][0]
    pole = eye.mesh.nodes[eye.mesh.node_set("eye/pole")][0]
    assert apex[2] - pole[2] == pytest.approx(axial_length, rel=1e-12)
    assert g.scleral_radius == pytest.approx(11.5 * axial_length / 24.0)
    assert g.lens_centre_depth - g.lens_thickness / 2 == pytest.approx(3.2)
    assert eye.quality()["worst_jacobian_ratio"] > 0.3


def test_measurements_that_make_no_eye_are_named():
    with pytest.raises(ValueError, match="anterior_chamber_depth = 0.4 mm is not beyond"):
        eye_geometry({"anterior_chamber_depth": 0.4})
    with pytest.raises(ValueError, match="axial_length = 24.0 mm with corneal_radius = 12.0 mm"
                       ".*do not intersect"):
        eye_geometry({"corneal_radius": 12.0})


@pytest.mark.parametrize("line, words", [
    ("axial_length = 2.6", "did you give cm?"),
    ("central_corneal_thickness = 540.0", "did you give um?"),
])
def test_unit_slips_in_biometry_are_refused(tmp_path, line, words):
    case = tmp_path / "c.toml"
    case.write_text(f'[case]\nproblem = "surgery"\n[parameters]\nmesh = "coarse"\n{line}\n')
    with pytest.raises(CaseError, match=words):
        load_case(case, schemas())


def test_every_biometry_field_is_in_both_eye_problems():
    names = {f.name for f in BIOMETRY_FIELDS}
    for problem in ("surgery", "pressure_volume"):
        assert names <= {f.name for f in schemas()[problem]}


@pytest.mark.slow
def test_a_long_eye_changes_the_outcomes(tmp_path, coarse_comparison):
    """cases/patients/long_eye.toml (case 1 on a 26 mm eye) on the coarse mesh against
    case 1 on the 24 mm reference eye (the session's coarse comparison). A larger globe
    under the same band shortening: the IOP rise falls and the axial length and
    refraction changes move, each by more than 1 % (measured 2026-11-27: -4.6 %, +4.1 %,
    -21 %), while the buckle height stays set by the shortening (about 5 mm / 2 pi on any
    globe): the indentation moves by less than 5 % (measured -0.85 %)."""
    from eyefem.cli.main import main

    out = tmp_path / "long"
    assert main(["-q", "run", str(ROOT / "cases/patients/long_eye.toml"), "--mesh", "coarse",
                 "--no-vtu", "--out", str(out)]) == 0
    long_eye = json.loads((out / "summary.json").read_text())
    ref = json.loads((coarse_comparison / "case1" / "summary.json").read_text())
    assert long_eye["unbalanced_steps"]["count"] == 0
    for key in ("iop_mmhg", "axial_length_change_mm", "refraction_change_D"):
        assert np.isfinite(long_eye[key])
        assert abs(long_eye[key] / ref[key] - 1) > 0.01, key
    assert long_eye["iop_mmhg"] < ref["iop_mmhg"]
    assert abs(long_eye["indentation_mm"] / ref["indentation_mm"] - 1) < 0.05
