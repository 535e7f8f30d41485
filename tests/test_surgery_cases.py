"""The seed's surgical cases 1-6 on the coarse eye mesh (slow: about 10 minutes).

Runs ``eyefem compare`` on cases/surgery/case*.toml with ``--mesh coarse`` into
results/compare-coarse (the docs/compare_cases notebook reuses these runs) and checks
the comparisons the seed reports.
"""

import json
from pathlib import Path

import pytest

from eyefem.cli.main import main as cli_main

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "results" / "compare-coarse"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def summaries():
    cases = sorted(str(p) for p in (ROOT / "cases" / "surgery").glob("case*.toml"))
    assert len(cases) == 6
    rc = cli_main(["-q", "compare", *cases, "--mesh", "coarse", "--out", str(OUT), "--reuse"])
    assert rc == 0
    return {p.parent.name: json.loads(p.read_text()) for p in OUT.glob("case*/summary.json")}


def test_every_case_writes_its_outputs(summaries):
    assert sorted(summaries) == [f"case{i}" for i in range(1, 7)]
    for name in summaries:
        d = OUT / name
        for f in ("stages.csv", "surgery_history.csv", "section_von_mises.png",
                  "outside_von_mises.png", "summary.json"):
            assert (d / f).exists(), (name, f)
    for f in ("comparison.csv", "comparison.md", "comparison.png"):
        assert (OUT / f).exists()


def test_encircling_tightening_raises_indentation_and_iop(summaries):
    weak, strong = summaries["case2"], summaries["case4"]
    assert strong["indentation_mm"] > weak["indentation_mm"]
    assert strong["iop_mmhg"] > weak["iop_mmhg"] > 15.0


def test_ridged_tire_indents_more_than_flat(summaries):
    assert summaries["case2"]["indentation_mm"] > summaries["case1"]["indentation_mm"]


def test_narrower_suture_width_indents_less(summaries):
    assert summaries["case3"]["indentation_mm"] < summaries["case2"]["indentation_mm"]


def test_segmental_sponge_indents_locally(summaries):
    for name in ("case5", "case6"):
        s = summaries[name]
        assert s["indentation_mm"] > 0.05, name
        assert s["iop_mmhg"] > 15.0, name  # the closed eye's IOP rises as the sponge indents
