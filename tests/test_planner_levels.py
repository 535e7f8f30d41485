"""Multi-fidelity planning (optimize.plan.plan_levels, --search-mesh): the search on a cheap
level hands its best design to the trusted level, whose outcomes the plan reports, and the
two levels' difference at that design is measured. The fast tests use a stand-in simulator
whose outcomes are linear in the tightening, with a level-dependent slope (the mesh's
effect); the slow one plans coarse case 1 on coarse and finishes on medium."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from optimize import objectives as obj
from optimize.plan import main as plan_main
from optimize.plan import plan_levels, study_errors

ROOT = Path(__file__).resolve().parents[1]
SLOPE = {"cheap": 0.10, "trusted": 0.12}
"""Indentation per mm of tightening on each stand-in level: the cheap level is stiffer."""


class StandIn:
    """The SurgerySimulator interface plan() uses: indentation = s t, IOP = 15 + 2 t mmHg."""

    def __init__(self, level, start):
        self.level, self.t0, self.runs = level, start.get("tightening", 2.0), []
        self.results, self.starts = [], []

    def design0(self):
        return {"tightening": self.t0}

    def run(self, design, start=None):
        t = design["tightening"]
        self.runs.append(t)
        self.starts.append(start)
        self.results.append(SimpleNamespace(
            outcomes={"indentation_mm": SLOPE[self.level] * t, "iop_mmhg": 15.0 + 2.0 * t},
            newton_iterations=1))
        return self.results[-1]

    def gradients(self, res, used):
        d = {"indentation_mm": SLOPE[self.level], "iop_mmhg": 2.0}
        return {k: {"tightening": d[k]} for k in used}


def test_the_search_hands_its_design_to_the_trusted_level():
    """The search reaches the target on the cheap level (t = 4.5 mm), the trusted level
    starts there and moves to its own answer (t = 3.75 mm, |indentation - 0.45| < 0.005 mm
    by the default tol); the level difference is measured at the search's design."""
    sims, rows = {}, []

    def make(level, start):
        sims[level] = StandIn(level, start)
        return sims[level]

    r = plan_levels(make, ("cheap", "trusted"), [obj.target_indentation(0.45)], ["tightening"],
                    constraints=[obj.iop_at_most(25.0)], iterations=10, finish_iterations=6,
                    on_iteration=rows.append)
    t_search = r.search.best["design"]["tightening"]
    assert t_search == pytest.approx(4.5, abs=0.05)
    assert sims["trusted"].runs[0] == t_search  # the finish starts at the search's design
    assert r.trusted.converged
    # the correction makes the linear cheap model the trusted one: one corrected search,
    # then the trusted level at its answer
    assert len(r.trusted.history) == 2 and len(r.corrections) == 1
    assert r.trusted.best["design"]["tightening"] == pytest.approx(3.75, abs=0.05)
    assert r.trusted.best["outcomes"]["indentation_mm"] == pytest.approx(0.45, abs=0.005)
    d = r.level_difference["indentation_mm"]
    assert d["search"] == pytest.approx(0.10 * t_search, rel=1e-12)
    assert d["trusted"] == pytest.approx(0.12 * t_search, rel=1e-12)
    assert d["relative"] == pytest.approx(1.0 / 6.0, rel=1e-12)  # (0.12 - 0.10) / 0.12
    assert [row["simulation"] for row in rows] == list(range(len(rows)))
    n_s, n_c = len(r.search.history), len(r.corrections[0].history)
    assert [row["mesh"] for row in rows] == (["cheap"] * n_s + ["trusted"]
                                            + ["cheap+correction"] * n_c + ["trusted"])
    assert sims["trusted"].runs == [t_search, r.trusted.best["design"]["tightening"]]
    # each level's simulations are warm started from that level's one before (explicitly:
    # run(design, start=result)), the first of each from nothing
    for sim in sims.values():
        assert sim.starts[0] is None
        assert all(a is b for a, b in zip(sim.starts[1:], sim.results[:-1]))


def test_the_correction_matches_the_trusted_level_where_it_was_taken():
    """_Corrected's outcomes and gradients equal the trusted level's at x_k and differ
    from it by the levels' curvature elsewhere (zero for the linear stand-in)."""
    from optimize.plan import _correction, _Corrected, _uncorrected

    cheap, trusted = StandIn("cheap", {}), StandIn("trusted", {})
    used = ["indentation_mm", "iop_mmhg"]

    def entry(sim, t):
        res = sim.run({"tightening": t})
        return {"design": {"tightening": t}, "outcomes": res.outcomes,
                "gradients": sim.gradients(res, used)}
    delta, slope = _correction(entry(trusted, 4.0), entry(cheap, 4.0), ["tightening"])
    model = _Corrected(cheap, {"tightening": 4.0}, delta, slope)
    for t in (4.0, 2.5):
        got, want = model.run({"tightening": t}), trusted.run({"tightening": t})
        assert got.outcomes == pytest.approx(want.outcomes, rel=1e-13)
        g_got, g_want = model.gradients(got, used), trusted.gradients(want, used)
        for k in used:
            assert g_got[k]["tightening"] == pytest.approx(g_want[k]["tightening"], rel=1e-13)
    best = {**entry(trusted, 2.5), "gradients": trusted.gradients(None, used)}
    back = _uncorrected(best, delta, slope, {"tightening": 4.0})
    assert back["outcomes"]["indentation_mm"] == pytest.approx(0.25, rel=1e-13)
    assert back["gradients"]["indentation_mm"]["tightening"] == pytest.approx(0.10)


def test_the_same_level_twice_is_refused():
    with pytest.raises(ValueError, match="search level is the trusted level"):
        plan_levels(StandIn, ("trusted", "trusted"), [obj.target_indentation(0.45)],
                    ["tightening"])


@pytest.mark.parametrize("args, message", [
    (["--search-mesh", "bogus"], "eye mesh level 'bogus'"),
    (["--search-mesh", "coarse", "--mesh", "coarse"], "already plans on 'coarse'"),
    (["--search-mesh", "coarse", "--finish-iterations", "0"], "--finish-iterations 0"),
])
def test_bad_levels_are_refused_by_name(tmp_path, capsys, args, message):
    rc = plan_main([str(ROOT / "cases/surgery/case1.toml"), "--target-indentation", "0.8",
                    "--vars", "tightening", "--out", str(tmp_path), *args])
    assert rc == 2 and message in capsys.readouterr().err


def test_study_errors_quote_the_recorded_levels():
    """The mesh study's estimates: none on coarse (not studied), a number on fine."""
    err = study_errors(("coarse", "fine"), encircling=True)
    assert err["indentation_mm"]["coarse"] is None
    assert 0.0 < err["indentation_mm"]["fine"] < 0.2


@pytest.mark.slow
def test_plan_on_coarse_finishes_on_medium(tmp_path):
    """Case 1: search on coarse, finish on medium; the plan reports medium's outcomes at
    the target (tol 0.25: |indentation - 0.8| < 0.025 mm) and the levels' difference."""
    rc = plan_main([str(ROOT / "cases/surgery/case1.toml"), "--mesh", "medium",
                    "--search-mesh", "coarse", "--target-indentation", "0.8", "--iop-max", "25",
                    "--vars", "tightening", "--iterations", "8", "--finish-iterations", "4",
                    "--tol", "0.25", "--out", str(tmp_path)])
    s = json.loads((tmp_path / "plan_summary.json").read_text())
    assert rc == 0 and s["converged"] and s["trusted_mesh"] == "medium"
    assert s["search"]["mesh"] == "coarse" and s["search"]["converged"]
    assert s["outcomes"]["indentation_mm"] == pytest.approx(0.8, abs=0.026)
    d = s["level_difference"]["indentation_mm"]
    assert d["search"] == pytest.approx(s["search"]["outcomes"]["indentation_mm"], rel=1e-12)
    assert d["difference"] == pytest.approx(d["trusted"] - d["search"], rel=1e-12)
    assert s["simulations"] == (s["search"]["simulations"] + s["trusted_simulations"]
                                + s["corrected_search_simulations"])
    assert (tmp_path / "plan.png").exists() and (tmp_path / "planned_case.toml").exists()
