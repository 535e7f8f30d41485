"""Output folders are owned (issue 76): a run writes only into a new, empty or eyefem run
folder, clears only the files its predecessor listed in run.json, never through a
symbolic link, never inside eyefem's code; the listed files' hashes guard a reuse and a
resume; SIGTERM ends a run as Ctrl-C does.

Every test snapshots a decoy folder and a decoy file outside the output folder and checks
that they did not change. The runs are the tiny uniaxial verification problem.
"""

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import eyefem
from eyefem.cli.main import main as cli_main
from eyefem.io import manifest
from test_bad_inputs import UNIAXIAL


def _run(capsys, *args) -> tuple[int, str]:
    rc = cli_main(["-q", *map(str, args)])
    return rc, capsys.readouterr().err


def _snapshot(root: Path) -> dict:
    """rel path -> sha256 of every file below ``root`` (links not followed)."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.is_symlink():
            out[p.relative_to(root).as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture
def world(tmp_path):
    """A case file, a decoy folder (a photo, a summary.json, a PNG) and a decoy file outside
    the output folder; returns (case, decoys folder, its snapshot, decoy file)."""
    case = tmp_path / "u.toml"
    case.write_text(UNIAXIAL)
    decoys = tmp_path / "decoys"
    decoys.mkdir()
    (decoys / "photo.jpg").write_bytes(b"\xff\xd8 a photo")
    (decoys / "summary.json").write_text('{"mine": true}\n')
    (decoys / "figure.png").write_bytes(b"\x89PNG not eyefem's")
    lone = tmp_path / "decoy.txt"
    lone.write_text("keep me\n")
    return case, decoys, _snapshot(decoys), lone


def _untouched(world_):
    _, decoys, snap, lone = world_
    assert _snapshot(decoys) == snap
    assert lone.read_text() == "keep me\n"


def test_a_folder_no_run_wrote_is_refused_and_left_as_it_was(tmp_path, capsys, world):
    case, decoys, snap, _ = world
    rc, err = _run(capsys, "run", case, "--out", decoys)
    assert rc == 4
    assert err.count("\n") == 1 and "Traceback" not in err
    assert str(decoys) in err and "no eyefem run wrote it" in err
    assert "--out NEW_DIR" in err and "--force" in err
    _untouched(world)
    assert not (decoys / manifest.LOCK).exists() and not (decoys / "run.json").exists()


def test_a_link_to_such_a_folder_is_refused_too(tmp_path, capsys, world):
    case, decoys, _, _ = world
    link = tmp_path / "link"
    link.symlink_to(decoys)
    rc, err = _run(capsys, "run", case, "--out", link)
    assert rc == 4 and "no eyefem run wrote it" in err
    _untouched(world)


def test_a_folder_inside_the_package_is_refused(tmp_path, capsys, world):
    case = world[0]
    inside = Path(eyefem.__file__).parent / "eye"
    before = _snapshot(inside)
    rc, err = _run(capsys, "run", case, "--out", inside / "results")
    assert rc == 4 and "inside eyefem's own code" in err and "--out" in err
    assert _snapshot(inside) == before and not (inside / "results").exists()


def test_new_and_empty_folders_are_used(tmp_path, capsys, world):
    case = world[0]
    empty = tmp_path / "empty"
    empty.mkdir()
    for out in (tmp_path / "new" / "deeper", empty):
        rc, _ = _run(capsys, "run", case, "--out", out)
        assert rc == 0
        run = json.loads((out / "run.json").read_text())
        assert run["program"] == "eyefem" and run["status"] == "complete"
    _untouched(world)


def test_the_manifest_lists_and_hashes_every_file_the_run_wrote(tmp_path, capsys, world):
    out = tmp_path / "out"
    assert _run(capsys, "run", world[0], "--out", out)[0] == 0
    files = json.loads((out / "run.json").read_text())["files"]
    on_disk = {k: v for k, v in _snapshot(out).items() if k != "run.json"}
    assert files == on_disk  # summary.json, checkpoint, history, pvd, vtu frames, PNG
    assert {"summary.json", "checkpoint.json", "uniaxial_history.csv"} <= files.keys()
    assert any(k.startswith("vtu/") for k in files)


def test_a_new_run_removes_only_what_the_old_one_listed(tmp_path, capsys, world):
    """A photo and notes put into a run's folder afterwards are not the run's: kept (the
    file names and patterns of eyefem's outputs no longer decide)."""
    out = tmp_path / "out"
    case = world[0]
    assert _run(capsys, "run", case, "--out", out)[0] == 0
    (out / "my_photo.png").write_bytes(b"\x89PNG mine")
    (out / "notes.txt").write_text("mine\n")
    stale = out / "vtu" / "uniaxial_9999.vtu"  # not listed: a frame of no run of this record
    stale.write_text("x")
    rc, _ = _run(capsys, "run", case.with_name("u.toml"), "--out", out)
    assert rc == 0
    assert (out / "my_photo.png").read_bytes() == b"\x89PNG mine"
    assert (out / "notes.txt").read_text() == "mine\n"
    assert stale.exists()
    _untouched(world)


def test_clearing_never_follows_a_link(tmp_path, capsys, world):
    """summary.json as a link to a file outside, and a listed name that climbs out of the
    folder: neither the link's target nor the outside file is removed or written."""
    case, decoys, _, lone = world
    out = tmp_path / "out"
    assert _run(capsys, "run", case, "--out", out)[0] == 0
    (out / "summary.json").unlink()
    (out / "summary.json").symlink_to(decoys / "summary.json")
    m = manifest.read(out)
    manifest.write(out, {**m, "files": {**m["files"], "../decoy.txt": "0" * 64,
                                        "/etc/hostname": "0" * 64}})
    assert _run(capsys, "run", case, "--out", out)[0] == 0
    assert not (out / "summary.json").is_symlink()  # the link was replaced, not written through
    _untouched(world)


def test_a_vtu_folder_that_is_a_link_is_refused(tmp_path, capsys, world):
    case, decoys, _, _ = world
    out = tmp_path / "out"
    assert _run(capsys, "run", case, "--out", out, "--no-vtu")[0] == 0
    (out / "vtu").symlink_to(decoys)
    rc, err = _run(capsys, "run", case, "--out", out)
    assert rc == 4 and "'vtu'" in err and "symbolic link" in err
    _untouched(world)


def test_force_adopts_a_folder_after_listing_what_it_removes(tmp_path, capsys, caplog, world):
    case = world[0]
    out = tmp_path / "adopted"
    out.mkdir()
    (out / "summary.json").write_text("{}\n")  # an eyefem name: listed, then removed
    (out / "notes.txt").write_text("mine\n")  # not an eyefem name: kept
    with caplog.at_level("WARNING", logger="eyefem.io.manifest"):
        rc = cli_main(["run", str(case), "--out", str(out), "--force"])
    assert rc == 0
    assert "adopted with --force" in caplog.text and "summary.json" in caplog.text
    assert (out / "notes.txt").read_text() == "mine\n"
    assert json.loads((out / "summary.json").read_text())["case"] == str(case)
    _untouched(world)


def test_reuse_recomputes_when_a_listed_file_changed(tmp_path, capsys, world):
    out = tmp_path / "out"
    assert _run(capsys, "run", world[0], "--out", out)[0] == 0
    m = manifest.read(out)
    key = "k"
    manifest.write(out, {**m, "case_hash": manifest.case_hash(key)})
    assert manifest.reusable_summary(out, key) is not None
    (out / "summary.json").write_text('{"iop_mmHg": 234.0}\n')  # an accident, or an edit
    assert manifest.reusable_summary(out, key) is None
    manifest.write(out, {k: v for k, v in manifest.read(out).items() if k != "files"})
    assert manifest.reusable_summary(out, key) is None  # nothing to check it against


def test_resume_refuses_a_checkpoint_that_changed(tmp_path, capsys, world):
    out = tmp_path / "out"
    case = world[0]
    assert _run(capsys, "run", case, "--out", out)[0] == 0
    ck = json.loads((out / "checkpoint.json").read_text())
    ck["rows"][0]["residual_N"] = 1.0  # rows are covered by run.json's hash of the file
    (out / "checkpoint.json").write_text(json.dumps(ck))
    rc, err = _run(capsys, "run", case, "--out", out, "--resume")
    assert rc == 2 and "checkpoint.json" in err and "without --resume" in err


def test_sigterm_ends_a_run_as_ctrl_c_does(tmp_path):
    """SIGTERM during the solve: exit 130, run.json 'interrupted', the lock released."""
    long = UNIAXIAL.replace("steps = 2", "steps = 20000")  # minutes: it is stopped early
    case = tmp_path / "long.toml"
    case.write_text(long)
    out = tmp_path / "out"
    env = {**os.environ, "EYEFEM_JAX_CACHE": "off"}
    cli = "import sys; from eyefem.cli.main import main; sys.exit(main())"
    proc = subprocess.Popen([sys.executable, "-c", cli, "-q", "run", str(case), "--out",
                             str(out), "--no-vtu"], stderr=subprocess.PIPE, text=True, env=env)
    for _ in range(6000):  # up to 5 min on a loaded machine
        if (out / "uniaxial_history.csv").exists() or proc.poll() is not None:
            break  # the solve has begun
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be signalled"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err
    assert manifest.read(out)["status"] == "interrupted"
    assert not (out / manifest.LOCK).exists()


@pytest.mark.parametrize("edit,words", [
    (lambda ck: ck.update(stage=99), "stage = 99, but the case has stages 0 to 0"),
    (lambda ck: ck["tree"].update(q=ck["tree"]["starts"][0][1]), "its state q has shape"),
], ids=["stage 99", "q of the wrong shape"])
def test_a_checkpoint_that_does_not_fit_the_case_is_one_line(tmp_path, capsys, world, edit,
                                                             words):
    """A checkpoint edited together with its hash in run.json (the hashes do not stop its
    owner): refused by what it holds, exit 2, no traceback."""
    out = tmp_path / "out"
    case = world[0]
    assert _run(capsys, "run", case, "--out", out)[0] == 0
    ck = json.loads((out / "checkpoint.json").read_text())
    edit(ck)
    (out / "checkpoint.json").write_text(json.dumps(ck))
    m = manifest.read(out)
    digest = hashlib.sha256((out / "checkpoint.json").read_bytes()).hexdigest()
    manifest.write(out, {**m, "files": {**m["files"], "checkpoint.json": digest}})
    rc, err = _run(capsys, "run", case, "--out", out, "--resume")
    assert rc == 2 and words in err and "without --resume" in err and "Traceback" not in err
