"""The FEBio conformance script (issue 77, benchmarks/febio_conformance.py) on decks the
project writes itself after the suite's cases, the reader's several steps, load curves,
nodal and body loads, and (when EYEFEM_FEBIO_VERIFY names a checkout of FEBio's
TestSuite/Verify folder) the agreement recorded in benchmarks/febio_conformance.csv."""

import csv
import importlib.util
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from eyefem.io.febio_read import LoadCurve, build_stages, read_feb, solution_norm
from eyefem.solve.solver import solve
from test_febio import _DECK

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location(
    "febio_conformance", ROOT / "benchmarks" / "febio_conformance.py")
conf = importlib.util.module_from_spec(_spec)
sys.modules["febio_conformance"] = conf
_spec.loader.exec_module(conf)


def _one(points="<pt>1,1</pt>", mtype="Mooney-Rivlin"):
    return _DECK.format(version="4.0", mtype=mtype, etype="hex8", conn="1,2,3,4,5,6,7,8",
                        points=points)


def _two_steps():
    """_DECK's cube in two steps: the pull 0.2 (linear curve) in step 1 only, then 0.1
    on a SMOOTH curve in step 2 (FEBio: step components act in their step)."""
    deck = _one()
    head, tail = deck.split("  <Boundary>")
    boundary = tail.split("</Boundary>")[0]
    fix = boundary.split("<bc name=\"pull\"")[0]
    pull = "<bc name=\"pull\"" + boundary.split("<bc name=\"pull\"")[1]
    steps = f"""  <Boundary>{fix}</Boundary>
  <Step>
    <step id="1" name="first"><Control><time_steps>2</time_steps><step_size>0.5</step_size>
      </Control><Boundary>{pull}</Boundary></step>
    <step id="2" name="second"><Control><time_steps>2</time_steps><step_size>0.5</step_size>
      </Control><Boundary>{pull.replace('lc="1">0.2', 'lc="2">0.1')}</Boundary></step>
  </Step>
  <LoadData>
    <load_controller id="1" type="loadcurve"><interpolate>LINEAR</interpolate>
      <points><pt>0,0</pt><pt>1,1</pt></points></load_controller>
    <load_controller id="2" type="loadcurve"><interpolate>SMOOTH</interpolate>
      <points><pt>1,0</pt><pt>1.5,3</pt><pt>2,1</pt></points></load_controller>
  </LoadData>
</febio_spec>
"""
    head = head.replace("<Control>", "<Control><!-- top -->")
    return head + steps


def _norm(path):
    mesh, mats, loads = read_feb(path)
    model, stages = build_stages(mesh, mats, loads)
    return solution_norm(mesh, stages[-1], solve(model, stages).q)


def test_load_curves_as_febio_evaluates_them():
    pts = ((0.0, 1.0, 2.0, 3.0), (0.0, 2.0, 1.0, 4.0))
    lin, step = LoadCurve("1", *pts), LoadCurve("1", *pts, interpolate="STEP")
    smooth = LoadCurve("1", *pts, interpolate="SMOOTH")
    assert lin(0.5) == 1.0 and lin(2.5) == 2.5 and lin(9.0) == 4.0  # CONSTANT beyond
    assert step(0.5) == 2.0 and step(1.0) == 1.0 and step(3.0) == 4.0  # the next point's
    # SMOOTH: the quadratics through (0,1,2) and (1,2,3) blended linearly on [1, 2]
    q1 = lambda t: 2 * t * (2 - t) + 0.5 * t * (t - 1)  # noqa: E731 (through 0,2,1)
    q2 = lambda t: (2 * (t - 2) * (t - 3) / 2 - (t - 1) * (t - 3) + 4 * (t - 1) * (t - 2) / 2)  # noqa
    assert smooth(1.5) == pytest.approx(q1(1.5) * 0.5 + q2(1.5) * 0.5, rel=1e-14)
    assert smooth(2.0) == 1.0 and smooth(0.5) == pytest.approx(q1(0.5), rel=1e-14)
    ext = LoadCurve("1", *pts, extend="EXTRAPOLATE")
    assert ext(4.0) == pytest.approx(7.0)
    rep = LoadCurve("1", *pts, extend="REPEAT OFFSET")
    assert rep(4.0) == pytest.approx(lin(1.0) + 4.0)
    sstep = LoadCurve("1", (0.0, 1.0), (0.0, 1.0), interpolate="SMOOTH STEP")
    assert sstep(0.5) == pytest.approx(0.5)


def test_several_steps_end_where_the_last_step_puts_them(tmp_path):
    two = tmp_path / "two.feb"
    two.write_text(_two_steps())
    mesh, _, loads = read_feb(two)
    assert [s.name for s in loads.steps] == ["first", "second"]
    assert [s.t_end for s in loads.steps] == [1.0, 2.0]
    top = set(loads.steps[0].prescribed[0].tolist())
    targets = [dict(zip(*map(np.ndarray.tolist, s.prescribed))) for s in loads.steps]
    assert max(targets[0].values()) == pytest.approx(0.2)
    assert max(targets[1].values()) == pytest.approx(0.1)  # 0.1 x smooth(2) = 0.1 x 1
    assert top == set(loads.steps[1].prescribed[0].tolist())
    one = tmp_path / "one.feb"
    one.write_text(_one(points="<pt>1,0.5</pt>"))  # the same cube pulled 0.1 in one step
    assert _norm(two) == pytest.approx(_norm(one), rel=1e-9, abs=1e-12)


def test_body_load_is_the_nodal_forces_of_the_element_volume(tmp_path):
    """One unit hex, bottom fixed: FEBio's const body load z = -8 (density 1) puts
    -rho b V / 8 = +1 N on each top node, as a nodal_force of (0, 0, 1) does."""
    base = _one().replace("<bc name=\"pull\"", "<!-- <bc name=\"pull\"").replace(
        "<relative>0</relative></bc>", "<relative>0</relative></bc> -->")
    body = base.replace("</Boundary>", """</Boundary>
  <Loads><body_load type="const"><x>0</x><y>0</y><z lc="1">-8</z></body_load></Loads>""")
    nodal = base.replace("</Boundary>", """</Boundary>
  <Loads><nodal_load name="push" type="nodal_force" node_set="top">
    <relative>0</relative><value lc="1">0,0,1</value></nodal_load></Loads>""")
    (tmp_path / "b.feb").write_text(body)
    (tmp_path / "n.feb").write_text(nodal)
    mesh, _, loads = read_feb(tmp_path / "b.feb")
    (name, dofs, f0), = loads.forces
    f1 = loads.steps[0].params[name]["f"]
    top = set(np.asarray(mesh.node_sets["top"]) * 3 + 2)
    assert sum(f for d, f in zip(dofs, f1) if d in top) == pytest.approx(4.0)
    assert np.sum(f1) == pytest.approx(8.0) and np.allclose(f0, 0.0)
    nb, nn = _norm(tmp_path / "b.feb"), _norm(tmp_path / "n.feb")
    assert nb > 1e-3 and nb == pytest.approx(nn, rel=1e-9)


def test_script_core_on_decks_the_project_writes(tmp_path):
    suite = tmp_path / "Verify"
    suite.mkdir()
    (suite / "ab01.feb").write_text(_one())
    (suite / "ab02.feb").write_text(_two_steps())
    (suite / "ab03.feb").write_text(_one(mtype="Shenoy"))
    (suite / "oi01.feb").write_text(_one())  # FEBio's runner skips optimisation inputs
    ref = _norm(suite / "ab01.feb")
    gold = tmp_path / "linuxGoldStandards.py"
    gold.write_text("stdResults = {'ab01': ['Normal', 2, 4, 5, 2, 100, '%.12g'],\n"
                    "    'ab02': ['Normal', 4, 8, 9, 4, 100, '%.12g'],\n"
                    "    'ab03': ['Normal', 1, 1, 1, 1, 1, '1.0']}\n"
                    % (ref, 1.01 * _norm(suite / "ab02.feb")))
    rows = conf.run_suite(suite, gold, time_cap=120, max_nodes=100, log=lambda *a: None)
    by = {r.deck: r for r in rows}
    assert sorted(by) == ["ab01", "ab02", "ab03"]
    assert by["ab01"].status == "agree" and abs(by["ab01"].rel_diff) < 1e-9
    assert by["ab02"].status == "differ" and by["ab02"].rel_diff == pytest.approx(-1 / 101)
    assert by["ab03"].status == "refused" and "type 'Shenoy' is not supported" in by[
        "ab03"].reason
    text = conf.summary(rows)
    assert "decks: 3" in text and "agreeing to 0.5%: 1" in text
    assert "1  material: type 'Shenoy' is not supported" in text
    out = tmp_path / "t.csv"
    conf.write_csv(rows, out)
    assert [r["status"] for r in csv.DictReader(open(out))] == ["agree", "differ", "refused"]


def test_a_deck_that_breaks_the_reader_is_a_row_not_a_traceback(tmp_path):
    (tmp_path / "zz01.feb").write_text("<febio_spec version=\"4.0\"><Mesh>")
    row = conf.run_deck(tmp_path / "zz01.feb", 1.0)
    assert row.status == "refused" and "not valid XML" in row.reason


RECORDED = ROOT / "benchmarks" / "febio_conformance.csv"


@pytest.mark.skipif(not os.environ.get("EYEFEM_FEBIO_VERIFY"),
                    reason="EYEFEM_FEBIO_VERIFY (a checkout's TestSuite/Verify folder) not set: "
                    "FEBio's decks are not part of eyefem")
def test_recorded_agreement_holds():
    verify = Path(os.environ["EYEFEM_FEBIO_VERIFY"])
    gold = conf.load_gold(verify.parent / "code" / "linuxGoldStandards.py")
    agreed = [r["deck"] for r in csv.DictReader(open(RECORDED)) if r["agree"] == "yes"]
    assert len(agreed) >= 40
    for name in agreed:
        row = conf.run_deck(verify / f"{name}.feb", gold[name])
        assert row.agree, (name, row.status, row.reason, row.rel_diff)
