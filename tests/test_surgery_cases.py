"""The seed's surgical cases 1-6 on the coarse eye mesh (slow: about 10 minutes).

``eyefem compare`` runs them into a temporary directory (the session fixture
``coarse_comparison``); the tests check the files, pin the outcomes against recorded
values, and check the comparisons the seed reports.
"""

import json
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]

RECORDED = {
    "case1": {
        "iop_mmhg": 26.407250088504007,
        "iop_after_tightening_mmhg": 24.928963287818476,
        "indentation_mm": 0.9870993209140053,
        "axial_length_change_mm": 0.8925945696285957,
        "volume_change_mm3": -0.0038182496828085277,
        "max_suture_force_N": 0.19823446818587737,
        "scleral_stress_kPa": 66.52919005828568,
    },
    "case2": {
        "iop_mmhg": 30.986500736267033,
        "iop_after_tightening_mmhg": 29.792039360446456,
        "indentation_mm": 1.4924607190266972,
        "axial_length_change_mm": 1.2199237718209162,
        "volume_change_mm3": -0.005351022454306076,
        "max_suture_force_N": 0.18958118481330152,
        "scleral_stress_kPa": 81.66421753897487,
    },
    "case3": {
        "iop_mmhg": 28.32964004571081,
        "iop_after_tightening_mmhg": 29.79203936316362,
        "indentation_mm": 1.5611486961932322,
        "axial_length_change_mm": 0.9561246640636334,
        "volume_change_mm3": -0.004461714565877628,
        "max_suture_force_N": 0.5453343131256801,
        "scleral_stress_kPa": 88.31337546084904,
    },
    "case4": {
        "iop_mmhg": 46.060603192283615,
        "iop_after_tightening_mmhg": 43.01553938215386,
        "indentation_mm": 2.2188320813311986,
        "axial_length_change_mm": 2.689324866465814,
        "volume_change_mm3": -0.010396645761829859,
        "max_suture_force_N": 0.23740631357825737,
        "scleral_stress_kPa": 118.28189312420263,
    },
    "case5": {
        "iop_mmhg": 15.090793249450565,
        "iop_after_tightening_mmhg": 15.001188729272014,
        "indentation_mm": 0.2487987433518999,
        "axial_length_change_mm": 0.011235699711800606,
        "volume_change_mm3": -3.0390435313165653e-05,
        "max_suture_force_N": 0.017011435580850803,
        "scleral_stress_kPa": 30.26990819577932,
    },
    "case6": {
        "iop_mmhg": 15.091722728097876,
        "iop_after_tightening_mmhg": 15.001188734706355,
        "indentation_mm": 0.2500197525831531,
        "axial_length_change_mm": 0.008963137439110369,
        "volume_change_mm3": -3.070155162276933e-05,
        "max_suture_force_N": 0.014311324635260737,
        "scleral_stress_kPa": 29.454119569326235,
    },
}
"""case -> outcome -> value (coarse mesh), recorded with the case files' tire edges lifting
over 1 mm (`buckle_edge`; 8 tightening steps, case 1's 2), the lens held by 0.343 N/mm in all
(`lens_support`), the ridged tires' flanks 1.5 mm wide (`ridge_flank`), the suture bites
spread over patches of 1.5 mm radius, the limbus a 1.5 mm ring, the indentation's bands
weighted by area, a segmental buckle's bands and snug fit on its side of the globe and the
sponge's ends rounded over 1 mm (`sponge_end`; case 6's coarse outcomes moved by under 1e-8
relative with it) (docs/surgery.md, "Buckles", "Supports",
"Suture bites", "Definitions")."""

RTOL = 1e-6
"""Relative tolerance of the pinned outcomes: the cases converge to a force residual of
1e-8 of their reference force, and the same code gives the same numbers to about 1e-9 on
one machine; 1e-6 leaves room for BLAS and compiler differences between machines, and is
far below any change of the model (which moves outcomes by 1e-4 or more); 1 to 8
tightening steps moved case 1's by under 3e-9."""


@pytest.fixture(scope="module")
def summaries(coarse_comparison):
    return {p.parent.name: json.loads(p.read_text())
            for p in coarse_comparison.glob("case*/summary.json")}


def test_every_case_writes_its_outputs(summaries, coarse_comparison):
    assert sorted(summaries) == [f"case{i}" for i in range(1, 7)]
    for name in summaries:
        d = coarse_comparison / name
        for f in ("stages.csv", "surgery_history.csv", "section_von_mises.png",
                  "outside_von_mises.png", "summary.json"):
            assert (d / f).exists(), (name, f)
    for f in ("comparison.csv", "comparison.md", "comparison.png"):
        assert (coarse_comparison / f).exists()


@pytest.mark.parametrize("case", [f"case{i}" for i in range(1, 7)])
def test_outcomes_are_the_recorded_ones(summaries, case):
    got = summaries[case]
    for key, want in RECORDED[case].items():
        assert got[key] == pytest.approx(want, rel=RTOL, abs=1e-9), (case, key)


def test_encircling_tightening_raises_indentation_and_iop(summaries):
    weak, strong = summaries["case2"], summaries["case4"]
    assert strong["indentation_mm"] > weak["indentation_mm"]
    assert strong["iop_mmhg"] > weak["iop_mmhg"] > 15.0


def test_ridged_tire_indents_more_than_flat(summaries):
    assert summaries["case2"]["indentation_mm"] > summaries["case1"]["indentation_mm"]


def test_narrower_suture_width_pulls_the_globe_in_less(summaries):
    """The seed's comparison of suture widths: at 7.8 mm (case 3) the sutures tighten the
    globe less than at 9.0 mm (case 2), so the IOP after suturing is lower. The seed's
    "indents less" is not what the model gives (on every mesh since the bites are spread,
    docs/surgery_results.md, "Case 3 against case 2"): at 7.8 mm the bites reach under
    the tire's lifted edge and pull the sclera it presses, so the indentation is within a
    few per cent of case 2's, on either side."""
    narrow, wide = summaries["case3"], summaries["case2"]
    assert narrow["iop_mmhg"] < wide["iop_mmhg"] - 1.0
    assert narrow["indentation_mm"] == pytest.approx(wide["indentation_mm"], rel=0.06)


def test_segmental_sponge_indents_locally(summaries):
    for name in ("case5", "case6"):
        s = summaries[name]
        assert s["indentation_mm"] > 0.05, name
        assert s["iop_mmhg"] > 15.0, name  # the closed eye's IOP rises as the sponge indents


def test_encircled_globe_does_not_hang_on_its_axial_hold(summaries, tmp_path):
    """Coarse case 2 with the axial hold on the globe at 3 N/mm against the default 10 N/mm.

    Measured (docs/surgery.md, "Procedure"): 3 against 10 N/mm moves the IOP by 0.02%,
    the indentation and the axial length change by 0.05%, the largest suture force by
    2.3%; on the nerve stub alone (no hold) the globe slides almost freely through the
    band, the suture force is 52% above the default's and the axial length change 1.8%
    above it. The bounds (0.1%, 0.5%, 1%, 10%) sit between the two."""
    from eyefem.cli.main import main

    text = (ROOT / "cases" / "surgery" / "case2.toml").read_text()
    assert "globe_axial" not in text  # the case runs with the default hold
    case = tmp_path / "case2_axial.toml"
    case.write_text(text.replace("[parameters]\n", "[parameters]\nglobe_axial = 3.0\n", 1))
    out = tmp_path / "run"
    assert main(["-q", "run", str(case), "--mesh", "coarse", "--out", str(out), "--no-vtu"]) == 0
    got, ref = json.loads((out / "summary.json").read_text()), summaries["case2"]
    for key, rel in (("iop_mmhg", 1e-3), ("indentation_mm", 5e-3),
                     ("axial_length_change_mm", 1e-2), ("max_suture_force_N", 0.1)):
        assert got[key] == pytest.approx(ref[key], rel=rel), key
