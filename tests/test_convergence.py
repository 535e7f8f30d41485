"""Three-grid procedure (eyefem.eye.convergence) and the mesh convergence study.

Fast: manufactured sequences f(h) = f0 + C h^p on the eye's non-constant refinement
ratios recover p and f0 to round-off; Celik et al. 2008 Table 1 (first column) is
reproduced to its printed digits; oscillatory, divergent and flat sequences give no
order, no extrapolation and no GCI. Slow: case 5 at coarse and half against the values
recorded by benchmarks/mesh_convergence.py (docs/convergence.md).
"""

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from eyefem.eye.convergence import (
    DIVERGENT,
    INDETERMINATE,
    MONOTONE,
    OSCILLATORY,
    least_squares_study,
    observed_order,
    relative_gci,
    three_grid_study,
)
from eyefem.eye.eyemodel import LEVELS

ROOT = Path(__file__).resolve().parents[1]
EYE_H = [1.0 / LEVELS[lv][0] for lv in ("fine", "default", "medium", "coarse")]


@pytest.mark.parametrize("p", [0.8, 1.0, 1.7, 2.0, 3.0])
@pytest.mark.parametrize("C", [2.5, -0.4])
@pytest.mark.parametrize("start", [0, 1])
def test_manufactured_power_law_recovers_order_and_limit(p, C, start):
    f0 = 1.3
    h = np.array(EYE_H[start:start + 3])  # r21, r32 differ (e.g. 1.375, 1.4545)
    s = three_grid_study(h, f0 + C * h**p)
    assert s.behaviour == MONOTONE and s.note == ""
    assert s.p == pytest.approx(p, rel=1e-9)
    assert s.extrapolated == pytest.approx(f0, rel=1e-12)
    err = abs(C) * h[0] ** p / abs(f0 + C * h[0] ** p)  # the exact error of grid 1
    assert s.gci_fine == pytest.approx(1.25 * err, rel=1e-9)
    f = f0 + C * h**p  # GCI32 / (r21^p GCI21) = phi1 / phi2 for an exact power law
    assert s.asymptotic_ratio == pytest.approx(f[0] / f[1], rel=1e-9)
    assert relative_gci(f0 + C * h[1] ** p, s.extrapolated) == pytest.approx(s.gci_medium)


def test_order_of_shuffled_grids_does_not_matter():
    h = np.array(EYE_H[:3])
    f = 4.0 - 2.0 * h**2
    a, b = three_grid_study(h, f), three_grid_study(h[::-1], f[::-1])
    assert a == b


def test_celik_2008_table_1_first_column():
    """Celik et al. 2008, Table 1, phi column 1: N = 18000, 8000, 4500 cells in 2-D
    (h = N^-1/2), phi = 6.063, 5.972, 5.863; printed p = 1.53, phi_ext = 6.1685,
    e_a = 1.5 %, e_ext = 1.7 %, GCI_fine = 2.2 %."""
    h = np.array([18000.0, 8000.0, 4500.0]) ** -0.5
    s = three_grid_study(h, [6.063, 5.972, 5.863])
    assert (s.r21, s.r32) == pytest.approx((1.5, 4 / 3))
    assert round(s.p, 2) == 1.53
    assert round(s.extrapolated, 4) == 6.1685
    assert round(100 * s.e_a21, 1) == 1.5
    assert round(100 * s.e_ext21, 1) == 1.7
    assert round(100 * s.gci_fine, 1) == 2.2


def test_oscillatory_sequence_gives_no_numbers():
    h = np.array(EYE_H[:3])
    s = three_grid_study(h, [1.00, 1.02, 0.99])
    assert s.behaviour == OSCILLATORY
    assert all(math.isnan(x) for x in (s.p, s.extrapolated, s.gci_fine, s.e_ext21))
    assert s.spread == pytest.approx(0.03)
    d = s.as_dict()
    assert d["p"] is None and d["gci_fine"] is None and d["behaviour"] == "oscillatory"
    json.dumps(d)  # JSON-ready


def test_divergent_sequence_is_not_given_an_order():
    """Differences that grow as h shrinks: Celik's |.| would give p > 0; here p < 0 and
    no extrapolation."""
    h = np.array(EYE_H[:3])
    s = three_grid_study(h, 1.0 + 0.01 * h**-1.0)
    assert s.behaviour == DIVERGENT
    assert s.p == pytest.approx(-1.0, rel=1e-9)
    assert math.isnan(s.extrapolated) and math.isnan(s.gci_fine)


def test_flat_sequence_is_indeterminate():
    s = three_grid_study(EYE_H[:3], [2.0, 2.0, 2.1])
    assert s.behaviour == INDETERMINATE and math.isnan(s.p)


def test_far_order_is_flagged():
    h = np.array(EYE_H[:3])
    s = three_grid_study(h, 1.0 + h**6)
    assert s.behaviour == MONOTONE and s.p == pytest.approx(6.0) and "asymptotic" in s.note


def test_extrapolation_across_zero_is_flagged():
    h = np.array(EYE_H[:3])
    s = three_grid_study(h, -0.01 + 0.5 * h)  # values > 0, limit < 0
    assert s.behaviour == MONOTONE and s.extrapolated == pytest.approx(-0.01)
    assert "other sign" in s.note


def test_constant_ratio_order_is_the_closed_form():
    p, ok = observed_order(2.0, 2.0, 0.25, 1.0)
    assert ok and p == pytest.approx(2.0, rel=1e-14)


@pytest.mark.parametrize("h, f", [([0.1, 0.2], [1, 2]), ([0.1, 0.1, 0.2], [1, 2, 3]),
                                  ([0.1, 0.2, 0.3], [1, float("nan"), 3])])
def test_bad_input_names_the_problem(h, f):
    with pytest.raises(ValueError, match="three_grid_study"):
        three_grid_study(h, f)


STUDY_H = [1.0 / LEVELS[lv][0] for lv in ("finest", "finer", "fine", "default", "half")]


@pytest.mark.parametrize("p", [0.8, 1.5, 2.0])
@pytest.mark.parametrize("C", [3.0, -40.0])
def test_least_squares_recovers_an_exact_power_law(p, C):
    # phi = 12 + C h^p on the study's five uniform levels: the free-order fit is exact,
    # so U_i = 1.25 |C| h_i^p (no scatter)
    h = np.array(STUDY_H)
    s = least_squares_study(h[::-1], 12.0 + C * h[::-1] ** p)  # any order in
    assert (s.fit, s.safety_factor, s.note) == ("p", 1.25, "")
    assert s.p == pytest.approx(p, rel=1e-6)
    assert s.extrapolated == pytest.approx(12.0, abs=1e-8 * abs(C))
    assert s.sigma < 1e-9 * abs(C)
    np.testing.assert_allclose(s.uncertainty, 1.25 * abs(C) * h ** p, rtol=1e-6)
    assert s.relative(0) == pytest.approx(s.uncertainty[0] / abs(12.0 + C * h[0] ** p))


def test_least_squares_is_affine_invariant():
    h = np.array(STUDY_H)
    f = np.array([1.1633, 1.1442, 1.12, 1.0923, 1.05])
    a, b = least_squares_study(h, f), least_squares_study(h, -3.0 * f + 7.0)
    assert (a.fit, a.safety_factor) == (b.fit, b.safety_factor)
    assert b.extrapolated == pytest.approx(-3.0 * a.extrapolated + 7.0, rel=1e-9)
    np.testing.assert_allclose(b.uncertainty, 3.0 * np.array(a.uncertainty), rtol=1e-7)


def test_least_squares_falls_back_on_fixed_orders_with_the_larger_factor():
    h = np.array(STUDY_H)
    high = least_squares_study(h, 12.0 - 500.0 * h ** 3)  # p 3: orders 2 or 1 and 2
    assert high.fit in ("2", "12") and high.safety_factor == 3.0
    assert "outside 0.5..2.1" in high.note
    # the finest level's uncertainty covers its true error
    assert high.uncertainty[0] > 500.0 * h[0] ** 3
    slow = least_squares_study(h, 12.0 - h ** 0.3)  # p 0.3: orders 1, 2 or both
    assert slow.fit in ("1", "2", "12") and slow.p == pytest.approx(0.3, rel=1e-4)
    # the finest level's uncertainty covers its true error 12 - phi
    assert slow.uncertainty[0] > 0.1 * h[0] ** 0.3


def test_least_squares_of_scatter_widens_the_uncertainty():
    # values that scatter by more than they move: sigma >= the data range, and
    # U = 3 sigma / range (error + sigma + |phi - fit|) >= the scatter itself
    h = np.array(STUDY_H)
    f = np.array([1.0, 1.1, 0.9, 1.1, 0.92])
    s = least_squares_study(h, f)
    assert s.sigma >= s.data_range == pytest.approx(0.2 / 4)
    assert s.uncertainty[0] >= 3.0 * (s.error[0] + s.sigma) - 1e-12
    assert "scatter exceeds the data range" in s.note and s.safety_factor == 3.0
    assert s.uncertainty[0] > 0.1  # the scatter's size (0.1 about the mean)
    # four levels (case 1's scleral stress, kPa, finest to default): no two-term fit,
    # which would follow the scatter and extrapolate to 51 kPa, outside the data
    four = least_squares_study(h[:4], [56.7094, 56.7266, 57.7721, 56.4049])
    assert four.fit in ("1", "2") and 56.4 < four.extrapolated < 57.8
    flat = least_squares_study(h, np.ones(5))
    assert flat.uncertainty == (0.0,) * 5 and "same on every grid" in flat.note


@pytest.mark.parametrize("h, f", [(STUDY_H[:3], [1, 2, 3]), (STUDY_H[:3] + STUDY_H[:1], [1, 2, 3, 4]),
                                  (STUDY_H[:4], [1, 2, float("nan"), 3])])
def test_least_squares_bad_input_names_the_problem(h, f):
    with pytest.raises(ValueError, match="least_squares_study"):
        least_squares_study(h, f)


def test_fine_level_keeps_four_wall_layers_and_sound_elements():
    """The "fine" level refines in-plane only: 6 patches x 32^2 x 4 layers of wall
    hexahedra; worst Jacobian ratio recorded 0.4752 (default 0.4423, finer 0.5035)."""
    from eyefem.eye.eyemodel import build_eye

    eye = build_eye(level="fine")
    q = eye.quality()
    n, n_lens = LEVELS["fine"]
    assert q["elements_lens"] == n_lens**3
    stub = q["elements"] - n_lens**3 - 6 * n * n * 4  # the nerve stub: 3 extruded layers
    assert stub > 0 and stub % 3 == 0 and stub < 0.01 * q["elements"]
    assert q["elements"] == 25166
    assert q["worst_jacobian_ratio"] == pytest.approx(0.4752, abs=1e-4)


def _benchmark(name: str = "mesh_convergence"):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_wall_profile_names_a_missing_run_and_how_to_make_it(tmp_path, capsys):
    rc = _benchmark("wall_profile").main(
        ["--case", str(ROOT / "cases" / "studies" / "case4_7mm.toml"), "--runs",
         str(tmp_path), "--levels", "coarse", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2
    assert str(tmp_path / "coarse") in err and "no checkpoint.json" in err
    assert "mesh_convergence.py run-one" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, rc", [(["run-one", "--help"], 0),
                                      (["run-one", "cases/surgery/case1.toml"], 2),
                                      (["fill", "a.toml", "fine"], 2)])
def test_mesh_study_run_one_without_its_three_arguments_prints_its_usage(argv, rc, capsys):
    """`run-one` / `fill` take CASE LEVEL RUN_DIR: a missing one is a usage line, not a
    traceback, and nothing runs."""
    assert _benchmark().main(argv) == rc
    err = capsys.readouterr().err
    assert f"usage: python benchmarks/mesh_convergence.py {argv[0]} CASE.toml LEVEL RUN_DIR" in err


@pytest.mark.slow
def test_wall_profile_of_case4_at_7mm_balances_the_volume(tmp_path):
    """benchmarks/wall_profile.py on case 4 at 7 mm, coarse (docs/convergence.md, "Where
    case 4's volume goes"). The cavity is closed with a liquid of bulk modulus 2083 MPa,
    so the volume pushed in under the band is taken up in front of it and behind it to
    V dP / K (0.006 mm^3 here); the apex's and the pole's axial displacements make up the
    run's axial length change (its 3-D distance, 1e-4 mm apart through the globe's
    tilt); the band's centre moves inward. Pinned: the coarse run's volumes (recorded
    2026-11-28), 1e-4 relative: every step converged to ~1e-10 N, while a change of the
    model or of the profile's bins moves them by per cents."""
    from eyefem.cli.main import main

    case = ROOT / "cases" / "studies" / "case4_7mm.toml"
    run = tmp_path / "runs" / "coarse"
    assert main(["-q", "run", str(case), "--mesh", "coarse", "--out", str(run),
                 "--no-vtu"]) == 0
    assert _benchmark("wall_profile").main(
        ["--case", str(case), "--runs", str(tmp_path / "runs"), "--levels", "coarse",
         "--out", str(tmp_path / "out")]) == 0
    row, = json.loads((tmp_path / "out" / "wall_profile_case4_7mm.json").read_text())
    summary = json.loads((run / "summary.json").read_text())
    taken = row["anterior_gain_mm3"] + row["posterior_gain_mm3"]
    assert abs(row["band_loss_mm3"] - taken) < 0.02
    assert abs(row["cumulative_volume_change_mm3"][-1]) < 0.02
    assert row["axial_length_change_mm"] == pytest.approx(
        summary["axial_length_change_mm"], abs=1e-3)
    assert row["iop_rise_mmhg"] == pytest.approx(summary["iop_mmhg"] - 15.0, rel=1e-12)
    centre = np.asarray(row["edges_deg"][:-1]) + 1.25
    ur = np.asarray(row["radial_displacement_mm"], float)
    band = np.abs(centre - 90.0) < 5.0
    assert np.nanmin(ur[band]) < -1.0 < 1.0 < np.nanmax(ur[centre < 10.0])
    assert row["band_loss_mm3"] == pytest.approx(343.546, rel=1e-4)
    assert row["anterior_gain_mm3"] == pytest.approx(229.327, rel=1e-4)


def test_study_of_synthetic_runs():
    """benchmarks/mesh_convergence.py: IOP rise from the case's IOP, triples in order fine
    to coarse, the default level's GCI against the finest triple's extrapolation."""
    bench = _benchmark()
    runs = {}
    for lv in ("coarse", "medium", "default", "fine"):
        h = 1.0 / LEVELS[lv][0]
        runs[lv] = {"n_per_edge": LEVELS[lv][0], "iop_param_mmhg": 15.0,
                    "iop_mmhg": 25.0 - 40 * h**2, "indentation_mm": 1.0 + 3 * h,
                    "axial_length_change_mm": 1.2 + 0.1 * (-1) ** LEVELS[lv][0] * h,
                    "elements": 1, "wall_s": 1.0, "newton_iterations": 1}
    s = bench.study_case(runs, ["coarse", "medium", "default", "fine"])
    assert s["levels"] == ["fine", "default", "medium", "coarse"]
    t = s["triples"]["iop_rise_mmhg"]
    assert [x["levels"] for x in t] == [["fine", "default", "medium"],
                                        ["default", "medium", "coarse"]]
    assert t[0]["p"] == pytest.approx(2.0) and t[0]["extrapolated"] == pytest.approx(10.0)
    v = s["values"]["iop_rise_mmhg"][1]
    assert s["default_gci"]["iop_rise_mmhg"] == pytest.approx(1.25 * abs(10.0 - v) / v)
    assert s["triples"]["indentation_mm"][0]["p"] == pytest.approx(1.0)
    table = bench.markdown({"caseX": s})
    assert "IOP rise" in table and "GCI of default" in table
    # another level judged against the bounds (--candidate): its own value, the same
    # extrapolation
    m = bench.study_case(runs, ["coarse", "medium", "default", "fine"], candidate="medium")
    vm = m["values"]["iop_rise_mmhg"][2]
    assert m["candidate"] == "medium" and vm != v
    assert m["default_gci"]["iop_rise_mmhg"] == pytest.approx(1.25 * abs(10.0 - vm) / vm)
    assert "GCI of medium" in bench.markdown({"caseX": m})
    # four uniform levels: the least-squares procedure over them (the IOP rise's
    # h^2 exactly: its free order and limit)
    ls = s["least_squares"]["iop_rise_mmhg"]
    assert s["least_squares_levels"] == ["fine", "default", "medium", "coarse"]
    assert (ls["fit"], ls["p"]) == ("p", pytest.approx(2.0, rel=1e-6))
    assert ls["extrapolated"] == pytest.approx(10.0, rel=1e-8)
    assert "Least squares over fine, default, medium, coarse" in table


def test_record_update_keeps_levels_and_tabulates_like_the_runs(tmp_path):
    """export --update keeps the record's levels the run folders lack; --record tabulates
    the record as the run folders were tabulated (the IOP rise stored, not recomputed)."""
    bench = _benchmark()
    runs = {}
    for lv in ("medium", "default", "fine"):
        h = 1.0 / LEVELS[lv][0]
        runs[lv] = {"n_per_edge": LEVELS[lv][0], "iop_param_mmhg": 15.0,
                    "iop_mmhg": 25.0 - 40 * h**2, "indentation_mm": 1.0 + 3 * h,
                    "elements": 7, "wall_s": 2.0, "newton_iterations": 9,
                    "unbalanced_steps": {"count": 0}}
    for lv in ("default", "fine"):  # medium's run folder is gone: only the record has it
        d = tmp_path / "runs" / "case1" / lv
        d.mkdir(parents=True)
        (d / "summary.json").write_text(json.dumps(runs[lv]))
    rec = tmp_path / "record.json"
    medium = {"n_per_edge": LEVELS["medium"][0], "elements": 7,
              "values": bench.outcome_values(runs["medium"])}
    other = {"buckle": "tire_ridged", "encircling": True, "levels": {"medium": medium}}
    rec.write_text(json.dumps({"cases": {"case4": other,
                                         "case1": {"levels": {"medium": medium}}}}))
    family = [["fine", "default", "medium"]]
    out = bench.export(tmp_path / "runs", ["case1"], family, ROOT / "cases" / "surgery", rec,
                       update=True)
    levels = out["cases"]["case1"]["levels"]
    assert set(levels) == {"fine", "default", "medium"} and levels["medium"] == medium
    # a case --cases does not name stays as recorded (updating one case keeps the others)
    assert list(out["cases"]) == ["case1", "case4"] and out["cases"]["case4"] == other
    assert "--cases case1,case4 " in out["source"]
    assert levels["fine"]["newton_iterations"] == 9 and levels["fine"]["wall_s"] == 2.0
    from_record = bench.collect_record(json.loads(rec.read_text()), ["case1"], family[0])
    direct = bench.study_case(runs, family[0])
    assert set(from_record["case1"]["values"]) == set(direct["values"])
    for k, v in direct["values"].items():
        assert from_record["case1"]["values"][k] == pytest.approx(v, rel=1e-14)
    assert from_record["case1"]["default_gci"] == pytest.approx(direct["default_gci"])
    assert from_record["case1"]["values"]["iop_rise_mmhg"][0] == pytest.approx(
        10.0 - 40 / LEVELS["fine"][0] ** 2)
    # without --update the level whose run folder is gone is left out
    out = bench.export(tmp_path / "runs", ["case1"], family, ROOT / "cases" / "surgery", rec)
    assert set(out["cases"]["case1"]["levels"]) == {"fine", "default"}
    assert bench.collect_record(out, ["case1"], family[0]) == {}
    # a level outside the families is recorded where it was run, left out where not; the
    # record holds the model fields the case file sets (the quoted runs compare theirs)
    d = tmp_path / "runs" / "case1" / "gradedc26"
    d.mkdir()
    (d / "summary.json").write_text(json.dumps({**runs["fine"], "n_per_edge": 26}))
    out = bench.export(tmp_path / "runs", ["case1"], family, ROOT / "cases" / "surgery", rec,
                       extra_levels=["gradedc26", "finer"])
    assert set(out["cases"]["case1"]["levels"]) == {"fine", "default", "gradedc26"}
    model = out["cases"]["case1"]["model"]
    assert model["buckle_edge"] == 1.0 and model["lens_support"] == 0.343
    assert model["wall_element"] == "q1p0"  # not in the case file: the field's default
    # --update keeps an extra level of the record whose run folder is gone
    import shutil
    shutil.rmtree(d)
    out = bench.export(tmp_path / "runs", ["case1"], family, ROOT / "cases" / "surgery", rec,
                       update=True, extra_levels=["gradedc26"])
    assert out["cases"]["case1"]["levels"]["gradedc26"]["n_per_edge"] == 26


# case 5 (seed materials, the lens held by 0.343 N/mm in all, bites spread over 1.5 mm
# patches, the 1.5 mm limbus ring, the indentation weighted by area, the sponge's ends
# rounded over 1 mm), recorded by `eyefem
# compare` (coarse) and benchmarks/mesh_convergence.py (half; docs/convergence.md)
CASE5_RECORDED = {
    "coarse": {
        "iop_mmhg": 15.090793249450565,
        "indentation_mm": 0.2487987433518999,
        "axial_length_change_mm": 0.011235699711800606,
        "refraction_change_D": -0.024328624792676484,
        "max_suture_force_N": 0.017011435580850803,
    },
    "half": {  # with the orbit's springs on the whole equatorial ring (44 nodes, not 4)
        "iop_mmhg": 15.041404932560686,
        "indentation_mm": 0.14515509731655207,
        "axial_length_change_mm": 0.00533472557497916,
        "refraction_change_D": -0.011876828296580657,
        "max_suture_force_N": 0.00895630302327066,
    },
}


@pytest.mark.slow
def test_case5_coarse_and_half_reproduce_the_study(tmp_path):
    """Case 5 (radial sponge) at coarse and half through the CLI, against the values of
    the convergence study (half) and of the coarse comparison (docs/surgery_results.md).
    Tolerance 1e-5 relative: every step is converged to the solver's tolerance (residual
    ~1e-10 N), so runs differ by round-off and by the order of floating-point sums only;
    a change of the model moves these outcomes by far more (coarse -> half: tens of per
    cent)."""
    from eyefem.cli.main import main

    for level, want in CASE5_RECORDED.items():
        out = tmp_path / level
        rc = main(["-q", "run", str(ROOT / "cases" / "surgery" / "case5.toml"), "--mesh", level,
                   "--out", str(out), "--no-vtu"])
        assert rc == 0
        got = json.loads((out / "summary.json").read_text())
        for key, value in want.items():
            assert got[key] == pytest.approx(value, rel=1e-5, abs=1e-9), (level, key)


def test_through_thickness_split_keeps_the_tissues():
    """A level with the suffix 'x2' splits each of the 4 wall layers in two at the
    midpoints of its radial edges: each trilinear hexahedron is cut into two exactly, so
    every tissue keeps its volume to round-off, the wall gets twice its elements, and the
    outer scleral surface (where the buckle and the bites sit) is unchanged."""
    from eyefem.eye.eyemodel import build_eye, is_level, level_spec
    from eyefem.fem.mesh import hex_geometry

    assert level_spec("coarsex2") == LEVELS["coarse"] + (2,)
    assert is_level("defaultx2") and not is_level("coarsex3") and not is_level("x2")
    with pytest.raises(ValueError, match="suffix 'x2'"):
        level_spec("coarse2")
    a, b = build_eye(level="coarse"), build_eye(level="coarsex2")
    va, vb = (np.bincount(m.mesh.material_ids, hex_geometry(m.mesh.nodes, m.mesh.hexes)[1].sum(1))
              for m in (a, b))
    np.testing.assert_allclose(vb, va, rtol=1e-12)
    qa, qb = a.quality(), b.quality()
    for tissue in ("sclera", "choroid", "retina", "cornea", "limbus", "ciliary_body"):
        assert qb[f"elements_{tissue}"] == 2 * qa[f"elements_{tissue}"], tissue
    fa, fb = (m.mesh.nodes[m.mesh.face_set("eye/sclera_outer")] for m in (a, b))
    np.testing.assert_allclose(np.sort(fb.reshape(-1, 3), 0), np.sort(fa.reshape(-1, 3), 0),
                               atol=1e-12)


def test_limbus_of_fixed_width_keeps_its_volume_across_levels():
    """With ``limbus_width = None`` the limbus is the ring of elements the corneoscleral
    junction passes through: one element wide, so its volume falls with the element size
    (a different model on each level). With a width (mm of arc; the default 1.5) it is the
    elements whose centroid lies within that ring, and its volume stays within 15 % across
    the levels (the nested ones too); the other tissues are assigned as before and the
    wall's volume is unchanged."""
    import dataclasses

    from eyefem.eye.eyemodel import TISSUES, EyeGeometry, build_eye
    from eyefem.fem.mesh import hex_geometry

    def volumes(level, width):
        m = build_eye(dataclasses.replace(EyeGeometry(), limbus_width=width), level).mesh
        return np.bincount(m.material_ids, hex_geometry(m.nodes, m.hexes)[1].sum(1),
                           minlength=len(TISSUES))

    limbus, sclera = TISSUES.index("limbus"), TISSUES.index("sclera")
    ring = {lv: volumes(lv, None) for lv in ("coarse", "medium", "default")}
    fixed = {lv: volumes(lv, 1.5) for lv in ("coarse", "half", "medium", "default")}
    assert EyeGeometry().limbus_width == 1.5
    assert ring["coarse"][limbus] > 2 * ring["default"][limbus]  # 55 against 23 mm^3
    v = [fixed[lv][limbus] for lv in fixed]
    assert max(v) < 1.15 * min(v), v
    for lv in ring:
        np.testing.assert_allclose(fixed[lv].sum(), ring[lv].sum(), rtol=1e-12)
        assert fixed[lv][sclera] == pytest.approx(ring[lv][sclera], rel=0.02)
    with pytest.raises(ValueError, match="limbus_width = -1"):
        EyeGeometry(limbus_width=-1.0)


def test_graded_polar_angle_refines_the_band_zone_and_keeps_the_levels_nested():
    """The graded levels' polar-angle map takes [0, pi] onto itself, monotone, with
    elements BAND_REFINEMENT times shorter along the meridians inside the band zone than
    outside (the derivative of the map, by differences); graded_half's wall nodes are
    nodes of graded (ratio 2, so the study's q(p) = 0); the wall's volume differs from the
    uniform level's by the faceting only (the same surfaces, sampled elsewhere); and the
    tissues keep their volumes within the faceting error."""
    from eyefem.eye.eyemodel import (BAND_REFINEMENT, BAND_ZONE_DEG, TISSUES, build_eye,
                                     graded_polar_angle)
    from eyefem.fem.mesh import hex_geometry

    ref = np.linspace(0.0, np.pi, 100001)
    th = graded_polar_angle(ref)
    assert th[0] == 0.0 and th[-1] == pytest.approx(np.pi, abs=1e-12)
    assert np.all(np.diff(th) > 0)
    slope = np.gradient(th, ref)
    deg = np.degrees(th)
    mid = slope[np.abs(deg - np.mean(BAND_ZONE_DEG)) < 10].mean()
    cornea = slope[deg < 30].mean()
    pole = slope[deg > 160].mean()
    assert cornea / mid == pytest.approx(BAND_REFINEMENT, rel=1e-3)
    assert pole / mid == pytest.approx(BAND_REFINEMENT, rel=1e-3)

    coarse, fine = build_eye(level="graded_half"), build_eye(level="graded")
    nodes_fine = {tuple(np.round(x, 9)) for x in fine.mesh.nodes}
    outer = coarse.mesh.nodes[coarse.mesh.face_set("eye/sclera_outer")].reshape(-1, 3)
    assert all(tuple(np.round(x, 9)) in nodes_fine for x in outer)

    def volumes(m):
        return np.bincount(m.mesh.material_ids, hex_geometry(m.mesh.nodes, m.mesh.hexes)[1].sum(1),
                           minlength=len(TISSUES))
    graded, uniform = volumes(fine), volumes(build_eye(level="default"))
    for tissue in ("sclera", "choroid", "retina", "cornea", "ciliary_body"):
        i = TISSUES.index(tissue)
        assert graded[i] == pytest.approx(uniform[i], rel=0.05), tissue


def test_q1p0_strip_in_bending_against_beam_theory():
    """The wall's element in bending (eyefem.problems.verification.cantilever_bending_stiffness:
    a clamped plane-strain strip 8 x 0.4 mm, the sclera's thickness at the equator). With
    elements a quarter of the thickness long and 4 layers it is within 2 % of Timoshenko's
    beam (0.985). At the eye's aspect it locks: with the default eye's 0.8 mm elements and
    the sclera's 2 layers the strip is 1.90 times too stiff, with the half level's 1.6 mm
    5.07 times (recorded; docs/convergence.md, "Bending of the wall's elements"). Pinned to
    0.5 %, so that a change of the element shows here."""
    import jax

    from eyefem.problems.verification import cantilever_bending_stiffness

    jax.config.update("jax_enable_x64", True)
    fine = cantilever_bending_stiffness(0.1, 4)
    assert fine["aspect"] == pytest.approx(0.25) and fine["ratio"] == pytest.approx(1.0, abs=0.02)
    default = cantilever_bending_stiffness(0.8, 2)
    assert default["ratio"] == pytest.approx(1.8963, rel=5e-3)
    half = cantilever_bending_stiffness(1.6, 2)
    assert half["ratio"] == pytest.approx(5.0656, rel=5e-3)


def test_graded_family_levels_name_their_elements_per_edge():
    """'graded<N>' levels: N elements per patch edge graded like the named graded levels
    (graded30 is the level 'graded', node for node), an even lens count, the suffix 'x2',
    and a clear error outside 12..64."""
    from eyefem.eye.eyemodel import build_eye, is_graded, is_level, level_spec

    assert level_spec("graded30") == level_spec("graded") == (30, 8, 1)
    assert level_spec("graded36x2") == (36, 10, 2)
    assert all(level_spec(f"graded{n}")[1] % 2 == 0 for n in range(12, 65))
    assert is_graded("graded18") and is_graded("graded_half") and not is_graded("default")
    assert is_level("graded") and not is_level("graded7") and not is_level("gradedx")
    with pytest.raises(ValueError, match="'graded99': 99 elements per patch edge; choose 12 to 64"):
        level_spec("graded99")
    a, b = build_eye(level="graded15"), build_eye(level="graded_half")
    np.testing.assert_array_equal(a.mesh.nodes, b.mesh.nodes)
    np.testing.assert_array_equal(a.mesh.hexes, b.mesh.hexes)


def test_gradedc_levels_refine_the_cornea_too():
    """'gradedc<N>' levels: graded like 'graded<N>' and, below CORNEA_ZONE_DEG, with
    meridional elements CORNEA_REFINEMENT times shorter than outside both zones (the map's
    derivative, by differences); the band zone keeps BAND_REFINEMENT. Same element counts
    as 'graded<N>' (the same topology, nodes placed elsewhere), more of them in the cornea;
    gradedc18's wall nodes are nodes of gradedc36 (nested, ratio 2)."""
    from eyefem.eye.eyemodel import (BAND_REFINEMENT, BAND_ZONE_DEG, CORNEA_REFINEMENT,
                                     CORNEA_ZONE_DEG, build_eye, cornea_refinement,
                                     graded_polar_angle, is_graded, level_spec)

    assert cornea_refinement("gradedc26") == CORNEA_REFINEMENT
    assert cornea_refinement("gradedc26x2") == CORNEA_REFINEMENT
    assert cornea_refinement("graded26") == 1.0 and cornea_refinement("default") == 1.0
    assert level_spec("gradedc26") == level_spec("graded26") == (26, 6, 1)
    assert is_graded("gradedc26")
    with pytest.raises(ValueError, match="'gradedc8': 8 elements per patch edge"):
        level_spec("gradedc8")

    ref = np.linspace(0.0, np.pi, 100001)
    slope = np.gradient(graded_polar_angle(ref, cornea_refinement=CORNEA_REFINEMENT), ref)
    deg = np.degrees(graded_polar_angle(ref, cornea_refinement=CORNEA_REFINEMENT))
    mid = slope[np.abs(deg - np.mean(BAND_ZONE_DEG)) < 10].mean()
    cornea = slope[deg < CORNEA_ZONE_DEG - 10].mean()
    pole = slope[deg > 160].mean()
    assert cornea / mid == pytest.approx(BAND_REFINEMENT / CORNEA_REFINEMENT, rel=1e-3)
    assert pole / mid == pytest.approx(BAND_REFINEMENT, rel=1e-3)

    plain, refined = build_eye(level="graded18"), build_eye(level="gradedc18")
    assert refined.quality()["elements"] == plain.quality()["elements"]
    assert refined.quality()["elements_cornea"] > 1.5 * plain.quality()["elements_cornea"]
    fine = build_eye(level="gradedc36")
    nodes_fine = {tuple(np.round(x, 9)) for x in fine.mesh.nodes}
    outer = refined.mesh.nodes[refined.mesh.face_set("eye/sclera_outer")].reshape(-1, 3)
    assert all(tuple(np.round(x, 9)) in nodes_fine for x in outer)


@pytest.mark.parametrize("level,n_row", [("default", 22), ("half", 11), ("graded_half", 15),
                                         ("graded24", 24), ("gradedc26", 26),
                                         ("graded27", 27)])
def test_orbit_ring_goes_round_the_globe_on_every_level(level, n_row):
    """The orbit's springs hold the equatorial ring (eyefem.eye.surgery.equatorial_ring):
    on every level a full row of the outer sclera, about 4 N nodes (N per patch edge) with
    no gap wider than two elements, within an element of the equator; on the uniform
    levels with an even count the plane row z = 0 (the default's 88 nodes). Before, the
    ring was the nodes at the widest node's z to 1e-6 mm, 4 or 8 nodes on the graded and
    odd levels: the orbit's forces fell on 4 points there, a mesh-dependent load."""
    from eyefem.eye.eyemodel import build_eye
    from eyefem.eye.surgery import equatorial_ring, orbit_spring

    mesh = build_eye(level=level).mesh
    ring = equatorial_ring(mesh.nodes, mesh.face_set("eye/sclera_outer"))
    X = mesh.nodes[ring]
    assert len(set(ring.tolist())) == len(ring)
    assert 4 * n_row <= len(ring) <= 4 * n_row + 8
    phi = np.sort(np.arctan2(X[:, 1], X[:, 0]))
    assert np.max(np.diff(np.r_[phi, phi[0] + 2 * np.pi])) < 2 * (2 * np.pi / (4 * n_row))
    element = np.pi * 11.5 / (2 * n_row)  # the mean meridional element length, mm
    assert np.max(np.abs(X[:, 2])) < element
    if level == "default":
        assert len(ring) == 88 and np.all(X[:, 2] == 0.0)
    p = {"globe_rotation": 70.0, "globe_torsion": 7.0, "globe_translation": 1.0,
         "globe_axial": 10.0}
    assert orbit_spring(mesh, p).nodes.tolist() == ring.tolist()


def test_spread_zonule_has_the_same_cross_section_on_every_level():
    """With point insertions (the default, zonule_insertion_radius None) every zonule bar
    has 0.01 mm^2, so the zonule's total stiffness follows the lens mesh's bar count (16
    bars on the coarse level, 24 on the default); with spread insertions the bars share
    zonule_total_area, and each pulls on a disc of the ciliary body's inner surface: its
    weights sum to 1, reach beyond the hit face on the default level and are smooth
    (no node carries more than half of the pull)."""
    import dataclasses

    from eyefem.eye.eyemodel import EyeGeometry, build_eye
    from eyefem.fem.bars import patch_weights

    E = 100.0
    point = {lv: build_eye(level=lv) for lv in ("coarse", "default")}
    spread_geometry = dataclasses.replace(EyeGeometry(), zonule_insertion_radius=1.5)
    spread = {lv: build_eye(spread_geometry, lv) for lv in ("coarse", "default")}
    n = {lv: len(e.zonule[0]) for lv, e in point.items()}
    assert n == {"coarse": 16, "default": 24}
    for lv, e in point.items():
        assert e.zonule_bar_EA(E) == pytest.approx(E * 0.01)
        assert e.zonule_bars(E).patch_b is None
    for lv, e in spread.items():
        assert n[lv] * e.zonule_bar_EA(E) == pytest.approx(E * 0.24, rel=1e-12)
        bars = e.zonule_bars(E)
        assert bars.params["EA"] == pytest.approx(np.full(n[lv], E * 0.24 / n[lv]))
        pb = bars.patch_b.data()
        X = e.mesh.nodes[bars.patch_b.nodes]
        w = np.asarray(patch_weights(X, np.asarray(e.zonule[2]), pb))
        np.testing.assert_allclose(w.sum(1), 1.0, rtol=1e-12)
        assert w.max() < 0.5, (lv, w.max())
        if lv == "default":
            assert np.all(np.count_nonzero(w > 1e-6, axis=1) > 8)
    with pytest.raises(ValueError, match="zonule_insertion_radius = -1"):
        EyeGeometry(zonule_insertion_radius=-1.0)


def test_lens_support_is_the_same_on_every_level():
    """The lens's springs (EyeModel.lens_springs): 1e-3 N/mm on each lens node by default,
    so their sum follows the lens mesh (0.125 N/mm on the coarse level, 0.343 on the
    default); with ``lens_support`` the sum is that stiffness on every level, and on the
    default level it is the per-node model exactly (the recorded results unchanged)."""
    import dataclasses

    from eyefem.eye.eyemodel import LENS_SPRING_PER_NODE, EyeGeometry, build_eye

    per_node = {lv: build_eye(level=lv).lens_springs() for lv in ("coarse", "default")}
    assert {lv: len(s.nodes) for lv, s in per_node.items()} == {"coarse": 125, "default": 343}
    assert all(s.params["k"] == LENS_SPRING_PER_NODE for s in per_node.values())
    shared = dataclasses.replace(EyeGeometry(), lens_support=0.343)
    for lv in ("coarse", "default"):
        s = build_eye(shared, lv).lens_springs()
        assert s.params["k"] * len(s.nodes) == pytest.approx(0.343, rel=1e-14)
        assert s.nodes.tolist() == per_node[lv].nodes.tolist()
    assert build_eye(shared, "default").lens_springs().params["k"] == per_node["default"].params["k"]
    with pytest.raises(ValueError, match="lens_support = -0.1 N/mm; must be a positive"):
        EyeGeometry(lens_support=-0.1)


def test_lens_support_field_reaches_both_eye_problems(tmp_path):
    """The case field sets the springs of the surgery and pressure_volume problems' lens,
    and a value outside its range is refused by the schema with the range."""
    from eyefem.catalog import schemas
    from eyefem.eye.surgery import SURGERY_FIELDS, surgery
    from eyefem.eye.validation import PV_FIELDS, pv_parts
    from eyefem.io.casefile import CaseError, load_case

    p = {**{f.name: f.default for f in SURGERY_FIELDS}, "mesh": "coarse", "lens_support": 0.5}
    springs = surgery(p, {}).model.term("lens_springs")
    assert springs.params["k"] * len(springs.nodes) == pytest.approx(0.5, rel=1e-14)
    p = {**{f.name: f.default for f in PV_FIELDS}, "mesh": "coarse", "lens_support": 0.5}
    springs = pv_parts(p)[0].term("lens_springs")
    assert springs.params["k"] * len(springs.nodes) == pytest.approx(0.5, rel=1e-14)
    path = tmp_path / "c.toml"
    path.write_text('[case]\nproblem = "surgery"\n[parameters]\nlens_support = -1.0\n')
    with pytest.raises(CaseError, match=r"lens_support.*-1.*1e-4 to 100 N/mm"):
        load_case(path, schemas())
