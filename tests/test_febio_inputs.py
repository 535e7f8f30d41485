"""FEBio decks checked like case files (issue 76): every bad deck is refused by
`eyefem import-feb` with exit 2 and one line naming the file, the tag and the value, and
the fix, before any output folder is made; the run records the deck's sha256."""

import hashlib
import json

import pytest

from eyefem.cli.main import main as cli_main
from eyefem.io.febio import FebError
from eyefem.io.febio_read import MAX_TIME_STEPS, read_feb
from test_febio import _DECK

BASE = _DECK.format(version="4.0", mtype="Mooney-Rivlin", etype="hex8", conn="1,2,3,4,5,6,7,8",
                    points="<pt>1,1</pt>")


def _edit(old, new, count=1):
    assert BASE.count(old) >= 1, old
    return BASE.replace(old, new, count)


BAD_DECKS = [
    # (id, deck text, words of the message)
    ("reversed range", _edit("<NodeSet name=\"top\">5:8</NodeSet>",
                             "<NodeSet name=\"top\">27:1</NodeSet>"),
     "node set 'top': range '27:1' is reversed (it names no id); write it first:last, e.g. "
     "'1:27'"),
    ("huge range", _edit("<NodeSet name=\"top\">5:8</NodeSet>",
                         "<NodeSet name=\"top\">1:300000000</NodeSet>"),
     "node set 'top': range '1:300000000' makes 300000000 ids, more than the 8 nodes in "
     "<Nodes> (the bound of a set)"),
    ("range step 0", _edit("<NodeSet name=\"top\">5:8</NodeSet>",
                           "<NodeSet name=\"top\">5:8:0</NodeSet>"),
     "range '5:8:0' has step 0"),
    ("node without id", _edit('<node id="3">', "<node>"),
     "<Nodes name=\"all\">: a <node> has no id attribute; give each <node id=\"N\"> a whole "
     "number"),
    ("node id abc", _edit('<node id="3">', '<node id="abc">'),
     "<Nodes name=\"all\">: <node id=\"abc\">: the id is not a whole number"),
    ("duplicate node id", _edit('<node id="3">', '<node id="2">'),
     "node id 2 appears twice in <Nodes>"),
    ("nan coordinate", _edit('<node id="3">1,1,0', '<node id="3">1,nan,0'),
     "<Nodes name=\"all\"> node 3: 'nan' is not a finite number (give three finite "
     "coordinates, mm)"),
    ("c1 in Pa", _edit("<c1>1</c1>", "<c1>2.5e7</c1>"),
     "material 'm' (id 1) <c1> = 2.5e+07 MPa is impossible (0 to 10000 MPa): did you give "
     "Pa? 25 MPa = 2.5e+07 Pa; give <c1> in MPa"),
    ("c1 tiny", _edit("<c1>1</c1>", "<c1>1e-300</c1>"),
     "material 'm' (id 1): c1 = 1e-300 MPa, c2 = 0 MPa: the shear modulus 2 (c1 + c2) = "
     "2e-300 MPa is below 1e-06 MPa"),
    ("c1 negative", _edit("<c1>1</c1>", "<c1>-1</c1>"),
     "<c1> = -1 MPa is impossible (0 to 10000 MPa)"),
    ("k nan", _edit("<k>1000</k>", "<k>nan</k>"),
     "material 'm' (id 1) <k>: 'nan' is not a finite number (give the bulk modulus in MPa, "
     "e.g. <k>1000</k>)"),
    ("k negative", _edit("<k>1000</k>", "<k>-5</k>"), "<k> = -5 MPa: a bulk modulus must be >= 0"),
    ("time_steps inf", _edit("<time_steps>2</time_steps>", "<time_steps>inf</time_steps>"),
     "<Control> <time_steps>: 'inf' is not a finite number (give the number of load steps"),
    ("time_steps 1e8", _edit("<time_steps>2</time_steps>", "<time_steps>1e8</time_steps>"),
     f"<Control> time_steps = 1e+08: more than {MAX_TIME_STEPS} load steps (each is a Newton "
     "solve; eyefem ramps the loads linearly, so tens suffice); lower time_steps, or raise "
     "the bound with EYEFEM_MAX_STEPS"),
    ("time_steps 2.5", _edit("<time_steps>2</time_steps>", "<time_steps>2.5</time_steps>"),
     "time_steps must be a whole number >= 1"),
    ("dynamic analysis", _edit("<Control>", "<Control><analysis>DYNAMIC</analysis>"),
     "<Control><analysis> is 'DYNAMIC': eyefem solves static equilibrium only"),
    ("dynamic analysis, FEBio 2.5 form",
     _edit("<Control>", '<Control><analysis type="dynamic"/>'),
     "<Control><analysis> is 'dynamic': eyefem solves static equilibrium only"),
    ("dynamic analysis in the step", _edit(
        "  <LoadData>", "  <Step><step id=\"1\"><Control><analysis>DYNAMIC</analysis>"
        "</Control></step></Step>\n  <LoadData>"),
     "<Control><analysis> is 'DYNAMIC'"),
    ("element id range past the nodes", _edit("1,2,3,4,5,6,7,8", "1:9"),
     "element 7: range '1:9' makes 9 ids, more than the 8 nodes"),
    ("text for a pressure", BASE.replace(
        "  <LoadData>", '  <Loads><surface_load surface="s" type="pressure"><pressure>high'
        "</pressure></surface_load></Loads>\n  <LoadData>").replace(
        "</Mesh>", '<Surface name="s"><quad4 id="1">5,6,7,8</quad4></Surface></Mesh>'),
     "'high' is not a number"),
]


@pytest.mark.parametrize("text, words", [c[1:] for c in BAD_DECKS], ids=[c[0] for c in BAD_DECKS])
def test_bad_decks_are_refused_in_one_line(tmp_path, capsys, text, words):
    deck = tmp_path / "d.feb"
    deck.write_text(text)
    out = tmp_path / "out"
    rc = cli_main(["-q", "import-feb", str(deck), "-o", str(out), "--no-vtu"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith(f"eyefem import-feb: {deck}: ") and words in err, err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()  # refused before any output folder is made


def test_the_step_bound_can_be_raised(tmp_path, monkeypatch):
    deck = tmp_path / "d.feb"
    deck.write_text(_edit("<time_steps>2</time_steps><step_size>0.5</step_size>",
                          "<time_steps>20000</time_steps><step_size>5e-5</step_size>"))
    with pytest.raises(FebError, match="more than 10000 load steps"):
        read_feb(deck)
    monkeypatch.setenv("EYEFEM_MAX_STEPS", "20000")
    assert read_feb(deck)[2].n_steps == 20000
    monkeypatch.setenv("EYEFEM_MAX_STEPS", "lots")
    with pytest.raises(FebError, match="EYEFEM_MAX_STEPS = 'lots' is not a whole number"):
        read_feb(deck)


def test_ranges_with_a_step_and_plausible_constants_are_read(tmp_path, caplog):
    deck = tmp_path / "d.feb"
    deck.write_text(_edit("<NodeSet name=\"top\">5:8</NodeSet>",
                          "<NodeSet name=\"top\">5:7:2,6,8</NodeSet>")
                    .replace("<c1>1</c1>", "<c1>2000</c1>"))  # impossible above 1e4 only
    mesh, materials, _ = read_feb(deck)
    assert sorted(mesh.node_sets["top"].tolist()) == [4, 5, 6, 7]
    assert materials["m"].coeffs[1, 0] == 2000.0
    assert "<c1> = 2000 MPa is outside the plausible range (0 to 1000 MPa)" in caplog.text


def test_import_feb_records_the_deck_sha256(tmp_path, capsys):
    deck = tmp_path / "d.feb"
    deck.write_text(BASE)
    out = tmp_path / "out"
    assert cli_main(["-q", "import-feb", str(deck), "-o", str(out), "--no-vtu"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["deck_sha256"] == hashlib.sha256(deck.read_bytes()).hexdigest()
    assert summary["deck_sha256"] != hashlib.sha256(b"").hexdigest()
