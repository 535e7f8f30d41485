"""benchmarks/febio_surgery.py: FEBio's node log read back and eyefem's outcome measures on
FEBio's states. FEBio is not needed: a log is written here in FEBio's format with a known
homogeneous state, whose outcomes are known in closed form."""

import importlib.util
from pathlib import Path

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("febio_surgery",
                                               ROOT / "benchmarks" / "febio_surgery.py")
fs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fs)


def _log(path, blocks):
    """A <logfile> node_data file as FEBio 4 writes it (ids from 1, ',' delimited)."""
    lines = []
    for step, (t, u) in enumerate(blocks, start=1):
        lines += [f"*Step  = {step}", f"*Time  = {t:g}", "*Data  = ux;uy;uz"]
        lines += [f"{i + 1},{a:.12g},{b:.12g},{c:.12g}" for i, (a, b, c) in enumerate(u)]
    path.write_text("\n".join(lines) + "\n")


def test_node_log_is_read_by_time_in_node_order(tmp_path):
    u = np.arange(12.0).reshape(4, 3)
    path = tmp_path / "d.txt"
    _log(path, [(1, u), (2, 2 * u)])
    text = path.read_text().splitlines()
    path.write_text("\n".join(text[:3] + text[3:7][::-1] + text[7:]) + "\n")  # ids shuffled
    blocks = fs.read_node_log(path)
    assert sorted(blocks) == [1.0, 2.0]
    np.testing.assert_array_equal(blocks[1.0], u)
    np.testing.assert_array_equal(blocks[2.0], 2 * u)


def test_an_empty_log_is_refused_by_name(tmp_path):
    path = tmp_path / "empty.txt"
    path.write_text("FEBio log\n")
    with pytest.raises(ValueError, match="empty.txt: no node data blocks"):
        fs.read_node_log(path)


def test_outcomes_of_a_uniform_shrink_match_the_closed_form(tmp_path):
    """Step 1 at rest, step 2 every node at 0.99 x: the axial length and the anterior
    chamber depth shrink by 1 %, the volume by 1 - 0.99^3, the IOP rises by |eps| dV, the
    indentation (a difference of radii, zero at rest) stays zero."""
    from eyefem.catalog import problems, schemas
    from eyefem.eye.outcomes import eye_optics, indentation, outcome_nodes
    from eyefem.fem.units import MMHG
    from eyefem.io.casefile import load_case

    case = load_case(ROOT / "cases/surgery/case1.toml", schemas())
    case.parameters.update(mesh="coarse", symmetry="none")
    setup = problems()[case.problem][1](case.parameters, case.materials)
    X = setup.model.mesh.nodes
    path = tmp_path / "case1_displacement.txt"
    _log(path, [(1, np.zeros_like(X)), (2, -0.01 * X)])
    eps = -0.4331
    rows = fs.febio_outcomes(setup, fs.read_node_log(path), eps)
    assert [r["stage"] for r in rows] == ["pressurise", "tighten"]

    q0 = np.zeros(setup.model.n_dof)
    nodes = outcome_nodes(setup.parts)
    rest = eye_optics(X, q0, nodes)
    v0 = float(setup.model.term("cavity").pressures(q0, setup.model.theta0()["cavity"])[1][0])
    first, second = rows
    assert first["iop_mmhg"] == 15.0 and first["axial_length_change_mm"] == 0.0
    np.testing.assert_allclose(second["axial_length_change_mm"],
                               -0.01 * float(rest["axial_length_mm"]), rtol=1e-9)
    np.testing.assert_allclose(second["anterior_chamber_depth_change_mm"],
                               -0.01 * float(rest["anterior_chamber_depth_mm"]), rtol=1e-9)
    np.testing.assert_allclose(second["volume_change_mm3"], (0.99 ** 3 - 1) * v0, rtol=1e-9)
    np.testing.assert_allclose(second["iop_mmhg"],
                               15.0 + 0.4331 * (1 - 0.99 ** 3) * v0 / MMHG, rtol=1e-9)
    assert abs(float(indentation(X, q0, nodes))) < 1e-12  # the unloaded eye is round there
    assert abs(second["indentation_mm"]) < 1e-12  # and a uniform shrink keeps it round


def test_the_open_cavity_deck_drops_the_volume_constraints_and_later_steps(tmp_path):
    """The tighten step's comparison deck: every <Constraints> (the model's and each
    step's) removed, only the first two steps kept, its node log named after it; the rest
    of the deck as it was."""
    deck = tmp_path / "case.feb"
    deck.write_text(
        "<?xml version='1.0' encoding='ISO-8859-1'?>\n<febio_spec version=\"4.0\">"
        "<Constraints><constraint type=\"volume\"/></Constraints><Step>"
        "<step id=\"1\"><Control/></step>"
        "<step id=\"2\"><Contact><contact/></Contact><Constraints><constraint "
        "type=\"volume\"/></Constraints></step><step id=\"3\"><Contact/></step></Step>"
        "<Output><logfile><node_data data=\"ux;uy;uz\" file=\"case_displacement.txt\"/>"
        "</logfile></Output></febio_spec>\n")
    out = fs.open_cavity_deck(deck, tmp_path / "case_open.feb")
    root = fs.ET.parse(out).getroot()
    assert not list(root.iter("Constraints")) and not list(root.iter("constraint"))
    assert [s.get("id") for s in root.iter("step")] == ["1", "2"]
    assert root.find("Step/step[@id='2']/Contact/contact") is not None
    assert root.find("Output/logfile/node_data").get("file") == "case_open_displacement.txt"
    assert "<Constraints>" in deck.read_text()  # the deck itself is untouched


def test_the_given_iop_deck_ramps_the_pressure_over_step_2(tmp_path):
    """The closed deck's IOP given to FEBio: the pressure load's new curve holds its value
    at t = 1 and reaches ``iop_mmhg`` at t = 2 (read back by given_iop); the other
    curves are kept; the node log is named after the new deck."""
    from eyefem.fem.units import MMHG

    deck = tmp_path / "case_open.feb"
    deck.write_text(
        "<?xml version='1.0' encoding='ISO-8859-1'?>\n<febio_spec version=\"4.0\"><Loads>"
        "<surface_load name=\"iop\" type=\"pressure\" surface=\"wetted\"><pressure lc=\"2\">"
        f"{15 * MMHG!r}</pressure></surface_load></Loads><LoadData>"
        "<load_controller id=\"1\" type=\"loadcurve\"><points><pt>0,0</pt><pt>1,0</pt>"
        "<pt>2,0.8</pt></points></load_controller>"
        "<load_controller id=\"2\" type=\"loadcurve\"><points><pt>0,0</pt><pt>1,1</pt>"
        "</points></load_controller></LoadData><Output><logfile><node_data "
        "data=\"ux;uy;uz\" file=\"case_open_displacement.txt\"/></logfile></Output>"
        "</febio_spec>\n")
    assert fs.given_iop(deck) == pytest.approx(15.0)
    out = fs.given_iop_deck(deck, tmp_path / "case_iop.feb", 24.5)
    root = fs.ET.parse(out).getroot()
    assert root.find(".//surface_load/pressure").get("lc") == "3"
    pts = [pt.text for pt in root.find(".//load_controller[@id='3']").iter("pt")]
    assert [float(p.split(",")[0]) for p in pts] == [0.0, 1.0, 2.0]
    assert float(pts[1].split(",")[1]) == pytest.approx(1.0)
    assert fs.given_iop(out) == pytest.approx(24.5)
    assert len(root.findall(".//load_controller")) == 3
    assert root.find(".//node_data").get("file") == "case_iop_displacement.txt"


def test_the_closed_iop_meets_the_cavitys_own_volume_law():
    """FEBio's closed-cavity IOP from its open and given-IOP runs: on the line through
    them, where the volume change equals the closed cavity's -(p - p_open) MMHG / |eps|
    (a rigid liquid, eps -> -inf: where the line crosses dV = 0)."""
    from eyefem.fem.units import MMHG

    p = fs.closed_iop(15.0, -30.0, 25.0, 2.0, -0.4331)
    assert -30.0 + (p - 15.0) * 3.2 == pytest.approx(-(p - 15.0) * MMHG / 0.4331, abs=1e-12)
    assert fs.closed_iop(15.0, -30.0, 25.0, 2.0, -1e30) == pytest.approx(15.0 + 30.0 / 3.2)
