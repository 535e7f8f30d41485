"""The mesh error a surgical run quotes (eyefem.eye.mesh_error) and its study record."""

import json

import pytest

from eyefem.eye.convergence import SAFETY_FACTOR
from eyefem.eye.eyemodel import is_level
from eyefem.eye.mesh_error import (FROM_EXTRAPOLATION, FROM_FINEST, GCI, NOT_ESTIMATED, QUOTED,
                                   load_study, mesh_error, quote_lines)
from eyefem.eye.surgery import run_mesh_error

FAMILY = ["finer", "default", "half"]
N = {"finer": 44, "default": 22, "half": 11}


def _study(values_by_level, encircling=True):
    """A one-case study record with the outcome values given per level."""
    return {"materials": "seed", "families": [FAMILY],
            "cases": {"caseX": {"encircling": encircling, "levels": {
                lv: {"n_per_edge": N[lv], "values": vals}
                for lv, vals in values_by_level.items()}}}}


def test_monotone_family_gives_the_gci_against_the_exact_extrapolation():
    # phi = f0 + C h^p, h = 1/n: Richardson recovers f0 exactly, so the GCI of each level
    # is Fs |f0 - phi| / |phi|
    f0, c, p = 12.0, -40.0, 1.5
    vals = {lv: {"iop_rise_mmhg": f0 + c * (1.0 / N[lv]) ** p} for lv in FAMILY}
    study = _study(vals)
    for lv in FAMILY:
        e = mesh_error(lv, True, {"iop_rise_mmhg": 11.0}, study)["outcomes"]["iop_rise_mmhg"]
        phi = vals[lv]["iop_rise_mmhg"]
        assert e["caseX"]["kind"] == GCI
        assert e["caseX"]["p"] == pytest.approx(p, rel=1e-9)
        assert e["caseX"]["relative"] == pytest.approx(SAFETY_FACTOR * abs(f0 - phi) / abs(phi),
                                                       rel=1e-9)
        assert e["caseX"]["absolute"] == pytest.approx(11.0 * e["caseX"]["relative"])


def test_oscillating_family_gives_the_difference_from_the_finest_level_only():
    vals = {"finer": {"indentation_mm": 1.00}, "default": {"indentation_mm": 0.95},
            "half": {"indentation_mm": 0.99}}
    study = _study(vals)
    e = mesh_error("default", True, None, study)["outcomes"]["indentation_mm"]["caseX"]
    assert (e["kind"], e["behaviour"]) == (FROM_FINEST, "oscillatory")
    assert e["relative"] == pytest.approx(0.05)
    assert e["absolute"] is None  # no run values given
    finest = mesh_error("finer", True, None, study)["outcomes"]["indentation_mm"]["caseX"]
    assert finest["kind"] == NOT_ESTIMATED and finest["relative"] is None
    # an outcome the study did not record is not estimated, not zero
    assert mesh_error("default", True, None, study)["outcomes"]["scleral_stress_kPa"][
        "caseX"]["kind"] == NOT_ESTIMATED


def test_a_level_quotes_another_familys_extrapolation_when_its_own_does_not_converge():
    # two families of one case: "a" (finer, mid, coarse) converges to f0 at order p; the
    # level "odd" sits in family "b" (finer, odd, other) whose values oscillate
    f0, c, p = 12.0, -40.0, 1.5
    n = {"finer": 44, "mid": 22, "coarse": 11, "odd": 30, "other": 15}
    vals = {lv: f0 + c * (1.0 / n[lv]) ** p for lv in ("finer", "mid", "coarse")}
    vals.update(odd=11.5, other=12.5)  # finer 11.86 > odd < other: oscillatory
    study = {"materials": "seed", "families": [["finer", "mid", "coarse"],
                                               ["finer", "odd", "other"]],
             "cases": {"caseX": {"encircling": True, "levels": {
                 lv: {"n_per_edge": n[lv], "values": {"iop_rise_mmhg": v}}
                 for lv, v in vals.items()}}}}
    err = mesh_error("odd", True, {"iop_rise_mmhg": 10.0}, study)
    e = err["outcomes"]["iop_rise_mmhg"]["caseX"]
    assert err["family"] == ["finer", "odd", "other"]
    assert (e["kind"], e["behaviour"]) == (FROM_EXTRAPOLATION, "oscillatory")
    assert e["family"] == ["finer", "mid", "coarse"]
    assert e["extrapolated"] == pytest.approx(f0, rel=1e-9)
    assert e["relative"] == pytest.approx(SAFETY_FACTOR * 0.5 / 11.5, rel=1e-9)
    assert e["absolute"] == pytest.approx(10.0 * e["relative"])
    assert "against finer/mid/coarse's extrapolation, p = 1.5" in quote_lines(err)[1]
    # without the converging family it is the difference from its own finest level
    alone = {**study, "families": [["finer", "odd", "other"]]}
    e = mesh_error("odd", True, None, alone)["outcomes"]["iop_rise_mmhg"]["caseX"]
    assert e["kind"] == FROM_FINEST
    assert e["relative"] == pytest.approx(abs(11.5 - vals["finer"]) / vals["finer"], rel=1e-9)
    # a level in the converging family keeps its own GCI
    e = mesh_error("mid", True, None, study)["outcomes"]["iop_rise_mmhg"]["caseX"]
    assert e["kind"] == GCI and e["family"] == ["finer", "mid", "coarse"]
    # a level run outside every family (the surgical cases' gradedc26) quotes the same way
    outside = {**study, "families": [["finer", "mid", "coarse"]]}
    err = mesh_error("odd", True, {"iop_rise_mmhg": 10.0}, outside)
    e = err["outcomes"]["iop_rise_mmhg"]["caseX"]
    assert err["family"] is None and e["behaviour"] == "not in a family"
    assert e["kind"] == FROM_EXTRAPOLATION
    assert e["relative"] == pytest.approx(SAFETY_FACTOR * 0.5 / 11.5, rel=1e-9)
    assert "outside its families of three" in quote_lines(err)[0]
    # ... else from the finest level the case ran; with no family at all, not estimated
    e = mesh_error("mid", True, None, alone)["outcomes"]["iop_rise_mmhg"]["caseX"]
    assert (e["kind"], e["family"]) == (FROM_FINEST, ["finer", "odd", "other"])
    assert e["relative"] == pytest.approx(abs(vals["mid"] - vals["finer"]) / vals["finer"],
                                          rel=1e-9)
    e = mesh_error("odd", True, None, {**alone, "families": []})["outcomes"][
        "iop_rise_mmhg"]["caseX"]
    assert e["kind"] == NOT_ESTIMATED and e["relative"] is None


def test_a_family_the_case_did_not_run_does_not_hide_one_it_ran():
    # the finest level ran for one case only: for the others, the family holding it is
    # "not run", and the level's estimate comes from the family the case did run
    n = {"finest": 54, "finer": 44, "fine": 32, "default": 22}
    vals = {"finer": 1.00, "fine": 0.95, "default": 0.99}  # oscillatory
    study = {"materials": "seed", "families": [["finest", "finer", "fine"],
                                               ["finer", "fine", "default"]],
             "cases": {"caseX": {"encircling": True, "levels": {
                 lv: {"n_per_edge": n[lv], "values": {"indentation_mm": v}}
                 for lv, v in vals.items()}}}}
    e = mesh_error("fine", True, None, study)["outcomes"]["indentation_mm"]["caseX"]
    assert (e["kind"], e["family"]) == (FROM_FINEST, ["finer", "fine", "default"])
    assert e["relative"] == pytest.approx(0.05)
    # with the finest level run, its family comes first: fine against the finer levels
    # of that family, the larger difference (the values oscillate)
    levels = study["cases"]["caseX"]["levels"]
    for finest, rel in ((0.97, 0.05), (0.90, 0.05 / 0.90)):
        levels["finest"] = {"n_per_edge": 54, "values": {"indentation_mm": finest}}
        e = mesh_error("fine", True, None, study)["outcomes"]["indentation_mm"]["caseX"]
        assert (e["kind"], e["family"]) == (FROM_FINEST, ["finest", "finer", "fine"])
        assert e["relative"] == pytest.approx(rel) and e["compared"] == ["finest", "finer"]


def test_levels_and_buckles_outside_the_study_are_not_estimated():
    study = _study({lv: {"iop_rise_mmhg": 1.0 + N[lv]} for lv in FAMILY}, encircling=True)
    for level, encircling in (("coarse", True), ("default", False)):
        err = mesh_error(level, encircling, None, study)
        assert err["outcomes"] == {} and "not estimated" in err["note"]
        assert quote_lines(err) == [f"mesh error: {err['note']}"]


def test_shipped_record_matches_the_convergence_page():
    study = load_study()
    for family in study["families"]:
        assert len(family) == 3 and all(is_level(lv) for lv in family)
    assert study["families"] == [["finer", "default", "half"], ["finer", "fine", "default"],
                                 ["finest", "finer", "fine"]]
    assert set(study["cases"]) == {"case1", "case4", "case5"}
    assert [c for c, r in study["cases"].items() if not r["encircling"]] == ["case5"]
    for case, rec in study["cases"].items():  # the case files' model, on every level
        assert rec["model"]["lens_support"] == 0.343, case
        assert set(rec["levels"]) - {"finest", "ultrafine"} == {"half", "default", "fine",
                                                                 "finer", "gradedc26"}, case
    assert "finest" in study["cases"]["case1"]["levels"]
    # the sixth level (outside the families: recorded, not quoted against): cases 1 and 5
    # (docs/convergence.md, "The sixth level"); case 5's fine IOP rise within 0.3 % of it,
    # case 1's axial length change on finest within 0.1 % of it and on fine within 1 %
    assert [c for c, r in study["cases"].items() if "ultrafine" in r["levels"]] == [
        "case1", "case5"]
    c5 = study["cases"]["case5"]["levels"]
    assert c5["ultrafine"]["elements"] == 123762
    assert c5["fine"]["values"]["iop_rise_mmhg"] == pytest.approx(
        c5["ultrafine"]["values"]["iop_rise_mmhg"], rel=3e-3)
    c1 = {lv: r["values"] for lv, r in study["cases"]["case1"]["levels"].items()}
    assert study["cases"]["case1"]["levels"]["ultrafine"]["elements"] == 123762
    axial = {lv: v["axial_length_change_mm"] for lv, v in c1.items()}
    assert axial["finest"] == pytest.approx(axial["ultrafine"], rel=1e-3)
    assert axial["fine"] == pytest.approx(axial["ultrafine"], rel=1e-2)
    assert study["cases"]["case4"]["model"]["ridge_flank"] == 1.5
    # docs/convergence.md, "Honest statement": the surgical cases' level, fine, is within
    # the bounds: case 4's axial length change (GCI 3.2 %, p 2.0) and refraction change
    # (1.8 %, p 1.4), case 1's largest suture force (9.2 %, p 2.8); case 4's IOP rise
    # against the nested triple's extrapolation (2.1 %); case 1's IOP rise, indentation,
    # axial length and refraction changes oscillate over fine / finer / finest: the larger
    # difference from those two levels (0.6, 0.4, 1.6, 1.7 %)
    fine = mesh_error("fine", True)
    assert fine["family"] == ["finer", "fine", "default"]
    enc = fine["outcomes"]
    for k, case, kind, rel in (
            ("axial_length_change_mm", "case4", GCI, 0.032),
            ("refraction_change_D", "case4", GCI, 0.018),
            ("max_suture_force_N", "case1", GCI, 0.092),
            ("iop_rise_mmhg", "case4", FROM_EXTRAPOLATION, 0.021),
            ("iop_rise_mmhg", "case1", FROM_FINEST, 0.0064),
            ("indentation_mm", "case1", FROM_FINEST, 0.0043),
            ("axial_length_change_mm", "case1", FROM_FINEST, 0.0164),
            ("refraction_change_D", "case1", FROM_FINEST, 0.0168)):
        assert enc[k][case]["kind"] == kind, (k, case)
        assert enc[k][case]["relative"] == pytest.approx(rel, abs=5e-4), (k, case)
    assert enc["axial_length_change_mm"]["case4"]["p"] == pytest.approx(1.99, abs=0.01)
    axial = next(line for line in quote_lines(fine) if "axial length change" in line)
    assert "case1 1.6 % (from finest/finer, oscillatory)" in axial
    assert enc["iop_rise_mmhg"]["case4"]["family"] == ["finer", "default", "half"]
    assert set(enc) == set(QUOTED)
    # the default level: case 4's IOP rise GCI 5.2 % on the nested triple, its axial length
    # change 6.9 % on finer / fine / default; case 1's largest suture force 23 %
    enc = mesh_error("default", True)["outcomes"]
    assert enc["iop_rise_mmhg"]["case4"]["relative"] == pytest.approx(0.052, abs=5e-4)
    assert enc["axial_length_change_mm"]["case4"]["relative"] == pytest.approx(0.0695, abs=5e-4)
    assert enc["max_suture_force_N"]["case1"]["relative"] == pytest.approx(0.235, abs=5e-4)
    # gradedc26, in no family: against an extrapolation where one converges, else from the
    # finest level the case ran (case 1's IOP rise 2.6 % from finest, case 4's axial length
    # change 5.9 %)
    c26 = mesh_error("gradedc26", True)
    assert c26["family"] is None
    e = c26["outcomes"]["iop_rise_mmhg"]["case1"]
    assert (e["kind"], e["behaviour"]) == (FROM_FINEST, "not in a family")
    assert e["family"][0] == "finest" and e["relative"] == pytest.approx(0.0255, abs=5e-4)
    e = c26["outcomes"]["axial_length_change_mm"]["case4"]
    assert e["kind"] == FROM_EXTRAPOLATION and e["relative"] == pytest.approx(0.0595, abs=5e-4)
    assert e["extrapolated"] == pytest.approx(3.109, abs=5e-4)
    # case 5 (the sponge's ends rounded over 1 mm): the default level's IOP rise and
    # indentation from the nested triple's finest level (oscillatory, monotone without an
    # order in range), and the case file's level fine's IOP rise from finest / finer
    seg = mesh_error("default", False)["outcomes"]
    e = seg["iop_rise_mmhg"]["case5"]
    assert (e["kind"], e["behaviour"]) == (FROM_FINEST, "oscillatory")
    assert e["relative"] == pytest.approx(0.0406, abs=5e-4)
    assert seg["indentation_mm"]["case5"]["relative"] == pytest.approx(0.0058, abs=5e-4)
    fine = mesh_error("fine", False)["outcomes"]
    assert fine["iop_rise_mmhg"]["case5"]["relative"] == pytest.approx(0.0057, abs=5e-4)
    assert fine["axial_length_change_mm"]["case5"]["relative"] == pytest.approx(0.0538, abs=5e-4)
    assert mesh_error("graded24", True)["outcomes"] == {}


def test_run_record_says_when_the_run_is_not_like_the_study():
    out = {"iop_mmhg": 27.0, "indentation_mm": 0.95, "axial_length_change_mm": 1.1,
           "refraction_change_D": -2.5, "max_suture_force_N": 0.09, "scleral_stress_kPa": 56.0}
    p = {"mesh": "default", "iop_mmhg": 15.0, "materials_preset": "seed"}
    err = run_mesh_error(p, True, out)
    assert err["note"] == ""
    rise = err["outcomes"]["iop_rise_mmhg"]["case4"]
    assert rise["absolute"] == pytest.approx(12.0 * rise["relative"])
    lines = quote_lines(err)
    assert lines[0].startswith("mesh error of level 'default' (study of case1, case4")
    assert any(line.lstrip().startswith("IOP rise") and "case4 5.2 %, 0.63 mmHg (GCI)" in line
               for line in lines)
    json.dumps(err)  # summary.json takes it as it is
    other = run_mesh_error({**p, "materials_preset": "physiological", "buckle_body": "ring",
                            "buckle_edge": 0.5}, True, out)
    assert "physiological" in other["note"] and "deformable" in other["note"]
    assert "buckle_edge" not in other["note"]  # the rigid ring's shape; a deformable has none
    assert quote_lines(other)[-1] == f"  {other['note']}"
    # the model fields of a studied case say nothing (case 1's flat tire keeps the default
    # ridge_flank 1.0, case 4's ridged tire 1.5); a value no studied case ran is named
    assert {c: m["buckle_edge"] for c, m in err["model"].items()} == {"case1": 1.0,
                                                                      "case4": 1.0}
    for same in ({"buckle_edge": 1.0, "lens_support": 0.343}, {"ridge_flank": 1.0},
                 {"ridge_flank": 1.5}):
        assert run_mesh_error({**p, **same}, True, out)["note"] == "", same
    other = run_mesh_error({**p, "buckle_edge": 0.5, "lens_support": 0.0, "ridge_flank": 2.0},
                           True, out)
    assert "ridge_flank = 2.0, buckle_edge = 0.5, lens_support = 0.0" in other["note"]
    # the studied cases' contact sat at the nodes: a run integrating it over the faces is
    # told, a deformable buckle (whose contact the field does not shape) is not
    faces = run_mesh_error({**p, "contact_quadrature": 2}, False, out)
    assert "contact_quadrature = 2" in faces["note"]
    deformable = run_mesh_error({**p, "contact_quadrature": 2, "buckle_body": "sponge"}, False,
                                out)
    assert "contact_quadrature" not in deformable["note"]


def test_unreadable_record_names_the_file(tmp_path):
    bad = tmp_path / "study.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="study.json: cannot read it"):
        load_study(str(bad))
    bad.write_text(json.dumps({"cases": {}}))
    with pytest.raises(ValueError, match="no 'families'"):
        load_study(str(bad))
