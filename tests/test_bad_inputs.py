"""Bad inputs and faults: each gives a one-line message and a documented exit code (0 ok,
2 bad input, 3 did not converge, 4 output/OS error, 130 interrupted), and leaves no stale
or partial output that looks complete (docs/errors.md lists them with their messages).

The runs use the tiny uniaxial verification problem (a few elements, 2 load steps).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from eyefem.catalog import schemas
from eyefem.cli.main import main as cli_main
from eyefem.io import checkpoint, manifest
from eyefem.io.casefile import CaseError, load_case

UNIAXIAL = """\
[case]
problem = "uniaxial"
[parameters]
stretch = 1.5
steps = 2
[materials.rubber]
c10 = 25.0
c01 = 5.0
"""

SURGERY = """\
[case]
problem = "surgery"
[parameters]
mesh = "coarse"
iop_mmhg = 15.0
"""


def _edit(text: str, old: str, new: str) -> str:
    assert old in text, old
    return text.replace(old, new, 1)


U = UNIAXIAL
CASE_FILE_ERRORS = [  # (id, case text, words of the message); exit code 2, nothing written
    ("nan parameter", _edit(U, "stretch = 1.5", "stretch = nan"),
     "'stretch' = nan is not a finite number"),
    ("inf parameter", _edit(U, "stretch = 1.5", "stretch = inf"),
     "'stretch' = inf is not a finite number"),
    ("-inf parameter", _edit(U, "stretch = 1.5", "stretch = -inf"), "not a finite number"),
    ("nan solver option", U + "[solver]\nrtol = nan\n", "'rtol' = nan is not a finite"),
    ("inf solver option", U + "[solver]\natol = inf\n", "'atol' = inf is not a finite"),
    ("nan material coefficient", _edit(U, "c10 = 25.0", "c10 = nan"), "non-finite"),
    ("inf material coefficient", _edit(U, "c01 = 5.0", "c01 = inf"), "non-finite"),
    ("impossible c10 (kPa slip)", _edit(U, "c10 = 25.0", "c10 = 25000.0"),
     "did you give kPa? 25 MPa = 25000 kPa"),
    ("vanishing c10", _edit(_edit(U, "c10 = 25.0", "c10 = 1e-300"), "c01 = 5.0", "c01 = 0.0"),
     "initial shear modulus 2 (c10 + c01) = 2e-300 MPa is below 1e-06 MPa"),
    ("c10 given as text", _edit(U, "c10 = 25.0", 'c10 = "stiff"'),
     "coefficient 'c10' = 'stiff' is not a number"),
    ("unknown coefficient", _edit(U, "c01 = 5.0", "c99 = 5.0"), "[materials.rubber]"),
    ("material not a table", _edit(U, "[materials.rubber]\nc10 = 25.0\nc01 = 5.0\n",
                                   "[materials]\nrubber = 3\n"), "must be a table"),
    ("two materials, one-material problem", U + "[materials.steel]\nc10 = 80.0\n",
     "uses one material"),
    ("unknown section", U + "[solvr]\nrtol = 1e-8\n", "did you mean 'solver'"),
    ("misspelt parameter", _edit(U, "stretch = 1.5", "strech = 1.5"),
     "did you mean 'stretch'"),
    ("unknown problem", _edit(U, '"uniaxial"', '"uniaxal"'), "did you mean 'uniaxial'"),
    ("missing problem", _edit(U, 'problem = "uniaxial"', 'title = "x"'),
     "missing required field 'problem'"),
    ("text for a number", _edit(U, "stretch = 1.5", 'stretch = "1.5"'),
     "has type str; expected float"),
    ("float for an integer", _edit(U, "steps = 2", "steps = 2.5"), "expected int"),
    ("boolean for a number", _edit(U, "stretch = 1.5", "stretch = true"), "expected float"),
    ("not TOML", _edit(U, "stretch = 1.5", "stretch = "), "not valid TOML"),
    ("unknown solver option", U + "[solver]\nbogus = 1\n", "unknown field 'bogus'"),
    ("output flag as text", U + '[output]\nvtu = "yes"\n', "expected bool"),
    ("surgery IOP in MPa", _edit(SURGERY, "iop_mmhg = 15.0", "iop_mmhg = 0.002"),
     "did you give MPa? 15 mmHg = 0.002 MPa"),
    ("surgery IOP nan", _edit(SURGERY, "iop_mmhg = 15.0", "iop_mmhg = nan"),
     "'iop_mmhg' = nan is not a finite number"),
    ("surgery IOP inf", _edit(SURGERY, "iop_mmhg = 15.0", "iop_mmhg = inf"),
     "'iop_mmhg' = inf is not a finite number"),
    ("surgery IOP impossible", _edit(SURGERY, "iop_mmhg = 15.0", "iop_mmhg = 750.0"),
     "is impossible (0.1 to 200 mmHg)"),
    ("sclera c10 in kPa", SURGERY + "[materials.sclera]\nc10 = 83.3\n",
     "did you give kPa? 0.0833 MPa = 83.3 kPa"),
    ("buckle shift nan", SURGERY + "buckle_shift = nan\n", "'buckle_shift' = nan"),
    ("bite length with point bites", SURGERY + "bite_radius = 0.0\nbite_length = 4.0\n",
     "bite_length = 4.0 mm needs a bite of physical size"),
    ("bite length shorter than its width", SURGERY + "bite_length = 2.0\n",
     "shorter than the patch's width 2 x bite_radius = 3.0 mm"),
    ("bite length out of range", SURGERY + "bite_length = 0.2\n", "0 (a disc) or 0.4 to 12 mm"),
    ("contact quadrature out of range", SURGERY + "contact_quadrature = 5\n",
     "'contact_quadrature' = 5 is out of range: 0 (nodes) or 1 to 4"),
    ("sponge end on a ring", SURGERY + "sponge_end = 0.5\n",
     "sponge_end = 0.5 mm rounds a sponge's ends; the tire_flat is a ring"),
    ("sponge end out of range", SURGERY + "sponge_end = 0.1\n", "0 or 0.2 to 2 mm"),
    ("sponge end on a deformable sponge",
     SURGERY + 'buckle = "sponge_radial"\nbuckle_body = "deformable"\ntightening = 0.0\n'
     "sponge_end = 0.5\n", "a deformable sponge has its own mesh"),
]


def _write(tmp_path, text, name="c.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _run(capsys, *args) -> tuple[int, str]:
    rc = cli_main(["-q", *map(str, args)])
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("text,words", [c[1:] for c in CASE_FILE_ERRORS],
                         ids=[c[0] for c in CASE_FILE_ERRORS])
def test_case_file_errors_are_refused_before_running(tmp_path, capsys, text, words):
    out = tmp_path / "out"
    rc, err = _run(capsys, "run", _write(tmp_path, text), "--out", out)
    assert rc == 2
    assert words in err and err.startswith("eyefem: ") and "Traceback" not in err
    assert not out.exists() or not any(out.iterdir())  # at most the empty folder


def test_a_mesh_level_for_a_problem_without_one_is_refused(tmp_path, capsys):
    """``--mesh`` on a problem that has no eye mesh: exit 2 naming the file, nothing run."""
    out = tmp_path / "out"
    for cmd in (["run", _write(tmp_path, U), "--out", out, "--mesh", "coarse"],
                ["export-feb", _write(tmp_path, U), "-o", tmp_path / "u.feb", "--mesh", "coarse"]):
        rc, err = _run(capsys, *cmd)
        assert rc == 2 and "has no mesh level; drop --mesh" in err and "c.toml" in err
        assert "Traceback" not in err
    assert not (tmp_path / "u.feb").exists() and (not out.exists() or not any(out.iterdir()))


@pytest.mark.parametrize("text,field,words", [
    (_edit(SURGERY, "iop_mmhg = 15.0", "iop_mmhg = 2.0"), "iop_mmhg",
     "did you give kPa? 15 mmHg = 2 kPa"),
    (SURGERY + "liquid_bulk = 2.2\n", "liquid_bulk", "did you give GPa? 2.2e+03 MPa = 2.2 GPa"),
    (SURGERY + "[materials.sclera]\nc10 = 3.0\n", "c10", "outside the plausible range"),
], ids=["IOP in kPa", "bulk modulus in GPa", "stiff sclera"])
def test_implausible_values_warn_with_the_likely_unit_slip(tmp_path, caplog, text, field, words):
    case = load_case(_write(tmp_path, text), schemas())
    assert case.problem == "surgery"
    msgs = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(field in m and words in m for m in msgs), msgs


def test_unknown_material_name_is_an_error_with_did_you_mean(tmp_path, capsys):
    """[materials.scelra] was silently ignored: the built model's material names decide."""
    out = tmp_path / "out"
    rc, err = _run(capsys, "run", _write(tmp_path, SURGERY + "[materials.scelra]\nc10 = 0.09\n"),
                   "--out", out)
    assert rc == 2
    assert "unknown material 'scelra' (did you mean 'sclera'?)" in err
    assert not (out / "run.json").exists()


@pytest.mark.parametrize("kind", ["directory", "binary", "missing"])
def test_case_path_that_is_not_a_case_file(tmp_path, capsys, kind):
    path = {"directory": tmp_path, "binary": tmp_path / "r.vtu",
            "missing": tmp_path / "none.toml"}[kind]
    if kind == "binary":
        path.write_bytes(bytes(range(256)) * 4)
    rc, err = _run(capsys, "run", path, "--out", tmp_path / "o")
    assert rc == 2
    assert {"directory": "is a directory", "binary": "not a text file",
            "missing": "does not exist"}[kind] in err


# --- new-case ------------------------------------------------------------------------------

@pytest.mark.parametrize("sets,words", [
    (["stretch=nan"], "'stretch' = nan is not a finite number"),
    (["stretch=inf"], "'stretch' = inf is not a finite number"),
    (["stretch=big"], "'big' is not a float"),
    (["stretch"], "expected name=value"),
], ids=["nan", "inf", "text", "no value"])
def test_new_case_refuses_bad_values_and_writes_nothing(tmp_path, capsys, sets, words):
    out = tmp_path / "c.toml"
    args = ["new-case", "uniaxial", "-o", out, "--yes"]
    for s in sets:
        args += ["--set", s]
    rc, err = _run(capsys, *args)
    assert rc == 2 and words in err
    assert not out.exists()


def test_new_case_surgery_nan_shift_refused(tmp_path, capsys):
    out = tmp_path / "s.toml"
    rc, err = _run(capsys, "new-case", "surgery", "-o", out, "--set", "buckle_shift=nan", "--yes")
    assert rc == 2 and "'buckle_shift' = nan is not a finite number" in err
    assert not out.exists()


def test_new_case_output_targets(tmp_path, capsys):
    rc, err = _run(capsys, "new-case", "uniaxial", "-o", tmp_path, "--yes")
    assert rc == 2 and "is a folder" in err
    rc, err = _run(capsys, "new-case", "uniaxial", "-o", tmp_path / "no" / "c.toml", "--yes")
    assert rc == 2 and "does not exist" in err
    existing = _write(tmp_path, "# mine\n", "mine.toml")
    rc, err = _run(capsys, "new-case", "uniaxial", "-o", existing, "--yes")
    assert rc == 2 and "the file exists" in err and "--force" in err
    assert existing.read_text() == "# mine\n"
    rc, _ = _run(capsys, "new-case", "uniaxial", "-o", existing, "--yes", "--force")
    assert rc == 0 and 'problem = "uniaxial"' in existing.read_text()


@pytest.mark.parametrize("exc,rc_words", [(KeyboardInterrupt, (130, "interrupted")),
                                          (EOFError, (2, "end of input"))],
                         ids=["ctrl-c", "end of input"])
def test_new_case_interrupted_writes_nothing(tmp_path, capsys, monkeypatch, exc, rc_words):
    class Keyboard:  # input() reads a line from sys.stdin
        def readline(self, *args):
            if exc is EOFError:
                return ""
            raise exc

    monkeypatch.setattr("sys.stdin", Keyboard())
    out = tmp_path / "c.toml"
    rc, err = _run(capsys, "new-case", "uniaxial", "-o", out)
    assert (rc, rc_words[1] in err) == (rc_words[0], True)
    assert "Traceback" not in err and not out.exists()


# --- output folder, lock, faults while writing -------------------------------------------

def test_out_pointing_at_a_file_is_refused_before_solving(tmp_path, capsys):
    target = _write(tmp_path, "keep\n", "results.txt")
    rc, err = _run(capsys, "run", _write(tmp_path, U), "--out", target)
    assert rc == 4 and "is an existing file" in err
    assert target.read_text() == "keep\n"
    rc, err = _run(capsys, "run", _write(tmp_path, U), "--out", target / "sub")
    assert rc == 4 and "cannot write in the output folder" in err


def test_second_run_into_a_locked_folder_is_refused(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    holder = os.getppid()  # a live process
    (out / manifest.LOCK).write_text(f"{holder}\n")
    rc, err = _run(capsys, "run", _write(tmp_path, U), "--out", out)
    assert rc == 4 and f"in use by another eyefem run (pid {holder}" in err and str(out) in err
    assert (out / manifest.LOCK).read_text() == f"{holder}\n"  # the holder's lock stays


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path, capsys, caplog):
    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    (out / manifest.LOCK).write_text(f"{dead}\n")
    rc, _ = _run(capsys, "run", _write(tmp_path, U), "--out", out, "--no-vtu")
    assert rc == 0 and (out / "summary.json").exists()
    assert not (out / manifest.LOCK).exists()
    assert any("stale lock" in r.getMessage() for r in caplog.records)


@pytest.fixture(scope="module")
def old_results(tmp_path_factory):
    """A complete uniaxial run (VTU, history, summary, manifest) to overwrite."""
    root = tmp_path_factory.mktemp("old")
    case = root / "u.toml"
    case.write_text(U)
    assert cli_main(["-q", "run", str(case), "--out", str(root / "out")]) == 0
    return root / "out"


def _copy_of(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_failed_run_clears_old_results_and_says_failed(tmp_path, capsys, old_results):
    out = _copy_of(old_results, tmp_path / "out")
    keep = _write(out, "mine\n", "notes.txt")  # not eyefem's: kept
    assert (out / "summary.json").exists() and list((out / "vtu").glob("*.vtu"))
    bad = U.replace("stretch = 1.5", "stretch = 60.0") + "[solver]\nmax_iter = 2\nmax_cuts = 2\n"
    rc, err = _run(capsys, "run", _write(tmp_path, bad), "--out", out)
    assert rc == 3 and "--resume" in err
    assert not (out / "summary.json").exists() and not (out / "uniaxial.pvd").exists()
    assert not list(out.glob("vtu/*.vtu")) and not list(out.glob("*.png"))
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "failed" and "ConvergenceError" in run["reason"]
    assert keep.read_text() == "mine\n"


SHELL_PAST_ITS_LIMIT = """\
[case]
problem = "inflated_shell"
[parameters]
n_per_edge = 2
n_thick = 1
pressure_mmHg = 300.0
steps = 5
"""


def test_load_past_a_limit_point_says_so_and_suggests_volume_control(tmp_path, capsys):
    # a neo-Hookean shell (c10 = 0.0833 MPa, R/H = 11) carries at most about 140 mmHg
    out = tmp_path / "out"
    rc, err = _run(capsys, "run", _write(tmp_path, SHELL_PAST_ITS_LIMIT), "--out", out, "--no-vtu")
    assert rc == 3
    assert "limit point" in err and "pressure.p" in err and "volume control" in err
    assert json.loads((out / "run.json").read_text())["status"] == "failed"
    assert not (out / "summary.json").exists()


def _floating_deck(tmp_path) -> Path:
    """An FEBio deck of one brick whose base is held in z only, pushed sideways by a
    pressure: it can slide along x and y and turn about z."""
    from test_febio import _DECK

    text = _DECK.format(version="4.0", mtype="Mooney-Rivlin", etype="hex8",
                        conn="1,2,3,4,5,6,7,8", points="<pt>1,1</pt>")
    text = text.replace("<x_dof>1</x_dof><y_dof>1</y_dof>", "<x_dof>0</x_dof><y_dof>0</y_dof>")
    text = text[:text.index('    <bc name="pull"')] + "  " + text[text.index("</Boundary>"):]
    text = text.replace('<NodeSet name="top">5:8</NodeSet>', '<NodeSet name="top">5:8</NodeSet>\n'
                        '    <Surface name="side"><quad4 id="1">2,3,7,6</quad4></Surface>')
    text = text.replace("  <LoadData>", '  <Loads><surface_load name="push" surface="side" '
                        'type="pressure"><pressure lc="1">0.1</pressure></surface_load></Loads>\n'
                        "  <LoadData>")
    deck = tmp_path / "floating.feb"
    deck.write_text(text)
    return deck


def test_singular_tangent_names_the_free_body_and_its_motions(tmp_path, capsys):
    rc, err = _run(capsys, "import-feb", _floating_deck(tmp_path), "-o", tmp_path / "out",
                   "--no-vtu")
    assert rc == 3 and "singular" in err
    assert "the body of 8 nodes (materials 'm'; terms 'solid', 'push')" in err.lower()
    assert "translate along x, translate along y and rotate about z freely" in err
    assert "rotate about x" not in err  # the base held in z stops it


def test_materials_many_orders_apart_are_named():
    from eyefem.fem.materials import mooney_rivlin
    from eyefem.fem.mesh import Mesh
    from eyefem.solve.diagnosis import stiffness_spread
    from eyefem.solve.model import solid_model

    nodes = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1, 2)], float)
    hexes = np.array([[0, 1, 4, 3, 6, 7, 10, 9], [1, 2, 5, 4, 7, 8, 11, 10]])
    mesh = Mesh(nodes, hexes, np.array([0, 1]), ("soft", "hard"))
    model = solid_model(mesh, {"soft": mooney_rivlin("soft", 1e-4, 0.0),
                               "hard": mooney_rivlin("hard", 1e3, 0.0)})
    said = stiffness_spread(model, model.theta0())
    assert "'soft' 0.0002 MPa against 'hard' 2e+03 MPa" in said and "1.0e+07" in said
    even = solid_model(mesh, {"soft": mooney_rivlin("soft", 0.1, 0.0),
                              "hard": mooney_rivlin("hard", 1.0, 0.0)})
    assert stiffness_spread(even, even.theta0()) == ""


def test_disk_full_while_writing_is_a_message(tmp_path, capsys, monkeypatch):
    import errno

    from eyefem.run import runner

    real = runner.write_csv
    calls = []

    def full(path, rows):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, rows)

    monkeypatch.setattr(runner, "write_csv", full)
    out = tmp_path / "out"
    rc, err = _run(capsys, "run", _write(tmp_path, U), "--out", out, "--no-vtu")
    assert rc == 4 and "No space left on device" in err and "Traceback" not in err
    assert json.loads((out / "run.json").read_text())["status"] == "failed"
    assert not (out / "summary.json").exists() and not (out / manifest.LOCK).exists()


def test_ctrl_c_in_run_is_a_message_and_marks_the_folder(tmp_path, capsys, monkeypatch):
    from eyefem.run import runner

    def interrupt(path, rows):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "write_csv", interrupt)
    out = tmp_path / "out"
    rc, err = _run(capsys, "run", _write(tmp_path, U), "--out", out, "--no-vtu")
    assert rc == 130 and "interrupted" in err and "--resume" in err
    assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    assert not (out / "summary.json").exists()


def test_output_outside_the_case_tree_is_allowed_but_said(tmp_path, capsys, caplog,
                                                          monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    case = _write(work, U)
    rc, _ = _run(capsys, "run", case, "--out", "../elsewhere", "--no-vtu")
    assert rc == 0 and (tmp_path / "elsewhere" / "summary.json").exists()
    assert any("outside the current and the case's folder" in r.getMessage()
               and str(tmp_path / "elsewhere") in r.getMessage() for r in caplog.records)


# --- checkpoints: data only, of this case and version --------------------------------------

def test_crafted_pickle_checkpoint_is_never_loaded(tmp_path, capsys):
    """A checkpoint.pkl whose unpickling runs a command: --resume must not open it."""
    import pickle

    out = tmp_path / "out"
    out.mkdir()
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    (out / "checkpoint.pkl").write_bytes(pickle.dumps(Payload()))
    case = _write(tmp_path, U)
    rc, err = _run(capsys, "run", case, "--out", out, "--resume")
    assert rc == 4 and "no eyefem run wrote it" in err  # no run.json: not eyefem's folder
    manifest.write(out, {"program": "eyefem", "format": 1, "status": "interrupted"})
    rc, err = _run(capsys, "run", case, "--out", out, "--resume")
    assert rc == 2 and "no checkpoint" in err and "never read" in err
    assert not marker.exists()


@pytest.fixture(scope="module")
def checkpointed(old_results):
    """The key under which old_results' checkpoint was written (uniaxial has one stage)."""
    meta = json.loads((old_results / checkpoint.FILENAME).read_text())
    return meta["key"]


def _tamper(out: Path, **changes):
    path = out / checkpoint.FILENAME
    meta = json.loads(path.read_text())
    meta.update(changes)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize("change,words", [
    ({"key": "0123456789abcdef"}, "belongs to another case"),
    ({"code_version": "0.0.1"}, "written by eyefem '0.0.1'"),
    ({"format": 1}, "checkpoint format 1"),
    ({"npz": "../../etc/passwd"}, "is missing"),
    ({"npz_sha256": "0" * 64}, "sha256 differs"),
], ids=["other case", "other version", "other format", "path escape", "tampered arrays"])
def test_foreign_checkpoint_is_refused(tmp_path, old_results, checkpointed, change, words):
    out = _copy_of(old_results, tmp_path / "out")
    _tamper(out, **change)
    with pytest.raises(checkpoint.CheckpointError, match="run without --resume") as exc:
        checkpoint.load(out, checkpointed)
    assert words in str(exc.value)


def test_checkpoint_of_another_case_refused_by_the_cli(tmp_path, capsys, old_results):
    out = _copy_of(old_results, tmp_path / "out")
    other = _write(tmp_path, U.replace("c10 = 25.0", "c10 = 20.0"))
    rc, err = _run(capsys, "run", other, "--out", out, "--resume")
    assert rc == 2 and "belongs to another case" in err


def test_object_arrays_in_the_npz_are_not_unpickled(tmp_path, old_results, checkpointed):
    import hashlib
    import io

    out = _copy_of(old_results, tmp_path / "out")
    buf = io.BytesIO()
    np.savez(buf, q=np.array([{"a": 1}], dtype=object))
    blob = buf.getvalue()
    (out / "evil.npz").write_bytes(blob)
    _tamper(out, npz="evil.npz", npz_sha256=hashlib.sha256(blob).hexdigest())
    with pytest.raises(checkpoint.CheckpointError, match="unreadable checkpoint"):
        checkpoint.load(out, checkpointed)


def test_theta_trees_round_trip_through_npz_and_json():
    tree = {"iop": {"p": np.float64(0.002)}, "sutures": {"t": np.arange(3.0)},
            "none": None, "pair": (np.ones(2), [np.zeros((2, 2))])}
    arrays = {}
    desc = checkpoint.flatten(tree, "theta", arrays)
    back = checkpoint.unflatten(json.loads(json.dumps(desc)), arrays)
    assert back["none"] is None and isinstance(back["pair"], tuple)
    np.testing.assert_array_equal(back["pair"][1][0], np.zeros((2, 2)))
    assert float(back["iop"]["p"]) == 0.002
    with pytest.raises(TypeError, match="theta/bad"):
        checkpoint.flatten({"bad": object()}, "theta", {})


# --- compare --reuse ----------------------------------------------------------------------

def test_compare_reuse_recomputes_an_edited_case(tmp_path, capsys):
    case = _write(tmp_path, U, "u.toml")
    out = tmp_path / "cmp"

    def stretch_result():
        return json.loads((out / "u" / "summary.json").read_text())

    assert cli_main(["-q", "compare", str(case), "--out", str(out), "--reuse"]) == 0
    first = stretch_result()
    run = json.loads((out / "u" / "run.json").read_text())
    assert run["status"] == "complete" and run["code_version"] == manifest.code_version()
    assert cli_main(["-q", "compare", str(case), "--out", str(out), "--reuse"]) == 0
    assert stretch_result() == first  # same case: reused (wall time identical)
    case.write_text(U.replace("stretch = 1.5", "stretch = 2.0"))
    assert cli_main(["-q", "compare", str(case), "--out", str(out), "--reuse"]) == 0
    second = stretch_result()
    assert second["wall_s"] != first["wall_s"]
    assert json.loads((out / "u" / "run.json").read_text())["case_hash"] != run["case_hash"]
    capsys.readouterr()


def test_reuse_needs_a_complete_manifest(tmp_path, old_results):
    out = _copy_of(old_results, tmp_path / "out")
    m = manifest.read(out)
    key_ok = None
    for status in ("running", "failed"):
        manifest.write(out, {**m, "status": status})
        assert manifest.reusable_summary(out, "anything") is None
    (out / manifest.FILENAME).unlink()
    assert manifest.reusable_summary(out, "anything") is key_ok


# --- planner arguments --------------------------------------------------------------------

@pytest.mark.parametrize("args,words", [
    (["--iterations", "0"], "--iterations 0: need at least 1"),
    (["--tol", "nan"], "--tol nan: need a finite value >= 0"),
    (["--bounds", "tightening=5"], "expected NAME=LOW:HIGH"),
    (["--bounds", "tightening=9:2"], "LOW must be below HIGH"),
    (["--bounds", "tightness=1:2"], "unknown design variable(s) ['tightness']"),
    (["--iop-max", "nan"], "--iop-max nan: need a finite number of mmHg"),
    (["--target-indentation", "50"], "--target-indentation 50 mm cannot be reached"),
    (["--iop-max", "21", "--iop-min", "25"], "--iop-min 25 must be below --iop-max 21"),
    (["--vars", "tightening,tightening"], "tightening given twice"),
    (["--vars", ","], "give design variables separated by commas"),
], ids=["zero iterations", "nan tolerance", "bounds syntax", "empty bounds", "unknown variable",
        "nan limit", "unreachable target", "crossed limits", "duplicate variable", "no variable"])
def test_planner_argument_errors(tmp_path, capsys, args, words):
    from optimize.plan import main as plan_main

    case = _write(tmp_path, SURGERY)
    rc = plan_main([str(case), "--target-indentation", "1.0", "--out", str(tmp_path / "p"),
                    *args])
    err = capsys.readouterr().err
    assert rc == 2 and words in err
    assert not (tmp_path / "p").exists()


IMPOSSIBLE_SURGERIES = [  # (id, parameter line, words): refused before the first step, exit 2
    ("drained more than a quarter of the cavity", "drain_volume = 10000.0",
     "drain_volume = 10000 mm^3 (uL) is more than 25% of the vitreous cavity"),
    ("sutures shortened beyond their span", "suture_tightening = 50.0",
     "a suture loop cannot shorten by its whole span"),
    ("more sutures than fit round the buckle", "n_sutures = 1000",
     "n_sutures = 1000: at most 24 sutures fit round the globe's circumference"),
]


@pytest.mark.parametrize("line,words", [c[1:] for c in IMPOSSIBLE_SURGERIES],
                         ids=[c[0] for c in IMPOSSIBLE_SURGERIES])
def test_impossible_surgeries_are_refused_before_the_first_step(tmp_path, capsys, line, words):
    out = tmp_path / "out"
    rc, err = _run(capsys, "run", _write(tmp_path, SURGERY + line + "\n"), "--out", out)
    assert rc == 2 and words in err and err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()


def test_planner_start_outside_its_bounds_is_refused(tmp_path, capsys):
    from optimize.plan import main as plan_main

    case = _write(tmp_path, SURGERY + "tightening = 5.0\n")
    rc = plan_main([str(case), "--target-indentation", "1.0", "--vars", "tightening",
                    "--bounds", "tightening=6:12", "--out", str(tmp_path / "p")])
    err = capsys.readouterr().err
    assert rc == 2 and "the start tightening = 5" in err and "[6, 12]" in err


def test_errors_doc_lists_the_case_file_errors():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "errors.md").read_text()
    missing = [c[0] for c in CASE_FILE_ERRORS if c[0] not in doc]
    assert not missing, missing


def test_case_error_is_a_value_error():  # the CLI's catch-all for bad input relies on it
    assert issubclass(CaseError, ValueError) and issubclass(manifest.OutputError, OSError)



def test_device_gpu_without_a_gpu_is_a_message(tmp_path, capsys):
    """``--device gpu`` on a machine where JAX has no GPU: exit 2 with what to install,
    before any case is read (a missing case file is not reported first)."""
    import jax

    try:
        jax.devices("gpu")
        pytest.skip("this machine has a GPU: the refusal cannot be provoked")
    except RuntimeError:
        pass
    rc = cli_main(["--device", "gpu", "run", str(tmp_path / "none.toml")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "JAX finds no GPU" in err and "jax[cuda12]" in err and "--device cpu" in err
    assert "Traceback" not in err


def test_planned_case_that_does_not_converge_exits_3(tmp_path, capsys, monkeypatch):
    """A case whose own solve fails before the plan starts: exit 3 (did not converge) with
    one line, not a traceback."""
    import eyefem.eye.simulators as simulators
    import optimize.plan as plan_mod
    from eyefem.solve.solver import ConvergenceError

    def failing(*a, **kw):
        raise ConvergenceError("stage 'pressurise': step to t = 1 failed after 8 cuts", None,
                               None, [])

    monkeypatch.setattr(simulators, "SurgerySimulator", failing)
    case = _write(tmp_path, SURGERY)
    rc = plan_mod.main([str(case), "--target-indentation", "1.0", "--vars", "tightening",
                        "--out", str(tmp_path / "p")])
    err = capsys.readouterr().err
    assert rc == 3 and "does not converge before planning starts" in err
    assert "Traceback" not in err
