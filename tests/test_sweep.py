"""Parameter sweeps on dask.distributed (eyefem.study): the table equals serial runs, a
killed worker's run is re-run, a restart skips completed runs, failures are rows, and a
wrong sweep file gets a message naming the fix.

The fast tests sweep the uniaxial verification problem (seconds per run) on one
LocalCluster of 2 worker processes shared by the module.
"""

import dataclasses
import json
import math
import os
import sys
from pathlib import Path

import pytest

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from distributed import WorkerPlugin

from eyefem.study import table
from eyefem.study.spec import SweepError, load_sweep
from eyefem.study.sweep import run_sweep

ROOT = Path(__file__).resolve().parents[1]
UNIAXIAL = """[case]
problem = "uniaxial"
[parameters]
stretch = 1.5
steps = 2
[materials.rubber]
c10 = 25.0
c01 = {c01}
"""
STRETCHES = [1.2, 1.4, 1.6, 1.8]


def write_sweep(folder: Path, body: str, c01: float = 5.0) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "base.toml").write_text(UNIAXIAL.format(c01=c01))
    f = folder / "sweep.toml"
    f.write_text('[sweep]\ncase = "base.toml"\noutcomes = ["force_N", "newton_iterations"]\n'
                 f'output = "{(folder / "out").as_posix()}"\n' + body)
    return f


GRID = f"[grid]\nparameters.stretch = {STRETCHES}\n"


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                           dashboard_address=":0")
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def serial_uniaxial(folder: Path, stretch: float, c01: float = 5.0) -> dict:
    """The same case run in this process, as `eyefem run` does: last step and summary."""
    from eyefem.catalog import problems, schemas
    from eyefem.io import manifest
    from eyefem.io.casefile import load_case
    from eyefem.io.runner import run_setup

    folder.mkdir(parents=True)
    f = folder / "case.toml"
    f.write_text(UNIAXIAL.format(c01=c01).replace("stretch = 1.5", f"stretch = {stretch!r}"))
    case = load_case(f, schemas())
    setup = problems()[case.problem][1](case.parameters, case.materials)
    res = run_setup(setup, folder / "out", case.solver, vtu=False, plots=False,
                    key=manifest.case_key(case.problem, case.parameters, case.materials,
                                          case.solver))
    return {**res.summary, **res.rows[-1]}


def test_sweep_table_equals_serial_runs(client, tmp_path):
    sweep = load_sweep(write_sweep(tmp_path / "s", GRID))
    res = run_sweep(sweep, client=client)
    assert (res.computed, res.skipped, res.failed) == (4, 0, 0)
    rows = table.read(res.out_dir)
    assert [r["parameters.stretch"] for r in rows] == STRETCHES
    assert [r["status"] for r in rows] == ["ok"] * 4
    for r in rows:
        ref = serial_uniaxial(tmp_path / f"serial{r['index']}", r["parameters.stretch"])
        assert math.isclose(r["force_N"], ref["force_N"], rel_tol=1e-12), (r, ref)
        assert r["newton_iterations"] == ref["newton_iterations"]
        run = res.out_dir / "runs" / Path(r["run_dir"]).name
        assert (run / "summary.json").is_file() and (run / "run.json").is_file()
        assert not (run / "vtu").exists()  # VTU off by default in sweeps
    forces = [r["force_N"] for r in rows]
    assert forces == sorted(forces) and forces[0] > 0  # a stiffer pull at a larger stretch
    # the CSV holds the same numbers, exactly
    import csv

    with open(res.out_dir / "results.csv") as fh:
        csv_rows = list(csv.DictReader(fh))
    assert [float(c["force_N"]) for c in csv_rows] == forces


class KillOnce(WorkerPlugin):
    """A worker plugin: the first run to start executing on any worker kills that
    worker's process at once (once per marker file)."""

    name = "eyefem-test-kill-once"

    def __init__(self, marker: str):
        self.marker = marker

    def setup(self, worker):
        pass

    def teardown(self, worker):
        pass

    def transition(self, key, start, finish, **kwargs):
        if finish == "executing" and "eyefem-run" in str(key) and not os.path.exists(self.marker):
            with open(self.marker, "w") as fh:
                fh.write(f"{os.getpid()} {key}\n")
            os._exit(1)  # the task is executing: die before it can finish


def test_a_killed_worker_has_its_run_rerun(client, tmp_path):
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import tests/
    marker = tmp_path / "killed.txt"
    client.register_plugin(KillOnce(str(marker)))
    try:
        sweep = load_sweep(write_sweep(tmp_path / "s", GRID))
        res = run_sweep(sweep, client=client)
    finally:
        client.unregister_worker_plugin(KillOnce.name)
    assert marker.is_file(), "no worker was killed: the test tested nothing"
    killed_pid = marker.read_text().split()[0]
    assert [r["status"] for r in res.rows] == ["ok"] * 4
    workers = [json.loads((res.out_dir / "runs" / Path(r["run_dir"]).name / "row.json")
                          .read_text())["worker"] for r in res.rows]
    assert all(not w.endswith(f":{killed_pid}") for w in workers), workers
    client.wait_for_workers(2, timeout=120)  # the nanny restarted it, for the next tests


def test_restart_skips_completed_runs_and_redoes_changed_ones(client, tmp_path):
    body = "[grid]\nparameters.stretch = [1.2, 1.4]\n"
    f = write_sweep(tmp_path / "s", body)
    first = run_sweep(load_sweep(f), client=client)
    assert first.computed == 2
    rows_files = sorted(first.out_dir.glob("runs/*/row.json"))
    stamps = [p.stat().st_mtime_ns for p in rows_files]
    again = run_sweep(load_sweep(f), client=client)
    assert (again.computed, again.skipped) == (0, 2)
    assert [p.stat().st_mtime_ns for p in rows_files] == stamps  # nothing recomputed
    assert [r["force_N"] for r in again.rows] == [r["force_N"] for r in first.rows]
    # an interrupted run (no record) is redone, the other kept
    rows_files[1].unlink()
    part = run_sweep(load_sweep(f), client=client)
    assert (part.computed, part.skipped) == (1, 1)
    assert rows_files[0].stat().st_mtime_ns == stamps[0]
    # a changed base case changes every run's hash: all recomputed, with new numbers
    f = write_sweep(tmp_path / "s", body, c01=6.0)
    changed = run_sweep(load_sweep(f), client=client)
    assert (changed.computed, changed.skipped) == (2, 0)
    assert all(c["force_N"] > o["force_N"] for c, o in zip(changed.rows, first.rows))
    assert all(c["run_hash"] != o["run_hash"] for c, o in zip(changed.rows, first.rows))


def test_failed_runs_are_rows_and_the_others_complete(client, tmp_path):
    body = ('[[list]]\nparameters.stretch = 1.3\n'
            '[[list]]\nparameters.stretch = 2.5\nsolver.max_iter = 1\nsolver.max_cuts = 0\n'
            '[[list]]\nparameters.stretch = -1.0\n'
            '[[list]]\nparameters.stretch = 1.5\n')
    res = run_sweep(load_sweep(write_sweep(tmp_path / "s", body)), client=client)
    status = [r["status"] for r in res.rows]
    assert status == ["ok", "did-not-converge", "failed", "ok"], res.rows
    assert "ConvergenceError" in res.rows[1]["error"]
    assert "stretch" in res.rows[2]["error"] and "invalid case" in res.rows[2]["error"]
    assert all(r["force_N"] > 0 for r in (res.rows[0], res.rows[3]))
    assert math.isnan(res.rows[1]["force_N"])
    assert res.failed == 2
    # a restart keeps the non-converged run (same answer) and retries nothing else
    again = run_sweep(load_sweep(write_sweep(tmp_path / "s", body)), client=client)
    assert again.computed == 0


def test_cli_on_an_existing_scheduler(client, tmp_path, capsys):
    """`eyefem sweep FILE --scheduler ADDRESS`: the table, the plots, the best designs."""
    from eyefem.cli.main import main

    f = write_sweep(tmp_path / "s", "[grid]\nparameters.stretch = [1.3, 1.5]\n"
                    "[best]\noutcome = \"force_N\"\ngoal = \"target\"\ntarget = 60.0\n")
    assert main(["-q", "sweep", str(f), "--scheduler", client.scheduler.address,
                 "--out", str(tmp_path / "cli")]) == 0
    printed = capsys.readouterr().out
    assert "best designs by force_N (closest to 60)" in printed
    best = printed.split("best designs by")[1].splitlines()[2].split()
    assert best[:2] == ["1", "1.5"]  # stretch 1.5 pulls with ~60 N, 1.3 with ~40 N
    assert (tmp_path / "cli" / "sweep_parameters_stretch.png").stat().st_size > 1000
    assert len(table.read(tmp_path / "cli")) == 2


@pytest.mark.parametrize("body, message", [
    ("[grid]\nparameters.strech = [1.2]\n", "did you mean 'stretch'"),
    ("[grid]\nstretch = [1.2]\n", "did you mean 'parameters.stretch'"),
    ("[grid]\nmaterials.rubbr.c10 = [1.0]\n", "did you mean 'rubber'"),
    ("[grid]\nparameters.stretch = 1.2\n", "non-empty list"),
    (("[samples]\nn = 4\nseed = 1\nparameters.stretch = { dist = \"norml\", mean = 1.2, "
     "std = 0.1 }\n"), "did you mean 'normal'"),
    (("[samples]\nn = 4\nseed = 1\nparameters.stretch = { dist = \"gaussian\", mean = 1.2, "
     "std = 0.1 }\n"), "give one of normal, uniform, lognormal"),
    (("[samples]\nn = 4\nseed = 1\nparameters.stretch = { dist = \"normal\", mean = 1.2, "
     "std = -0.1 }\n"), "std = -0.1; must be > 0"),
    ("[samples]\nn = 4\nparameters.stretch = { dist = \"uniform\", low = 1.2, high = 1.5 }\n",
     "give an integer seed"),
    ("[sampels]\nn = 4\n", "did you mean 'samples'"),
    ('gradients = ["tightening"]\n[grid]\nparameters.stretch = [1.2]\n',
     "gradients need a surgery case"),
    ("", "nothing to vary"),
])
def test_sweep_file_errors_name_the_fix(tmp_path, body, message):
    f = write_sweep(tmp_path, body)
    with pytest.raises(SweepError, match=message.replace("(", r"\(")) as err:
        load_sweep(f)
    assert str(f) in str(err.value)


def test_missing_base_case_and_cli_exit_code(tmp_path, capsys):
    from eyefem.cli.main import main

    f = tmp_path / "sweep.toml"
    f.write_text('[sweep]\ncase = "nowhere.toml"\n[grid]\nparameters.stretch = [1.2]\n')
    assert main(["sweep", str(f)]) == 2
    err = capsys.readouterr().err
    assert "base case 'nowhere.toml' not found" in err and "Traceback" not in err


def test_samples_are_reproducible_and_stratified(tmp_path):
    body = ("[samples]\nn = 8\nseed = 3\nmethod = \"lhs\"\n"
            "parameters.stretch = { dist = \"uniform\", low = 1.2, high = 2.0 }\n"
            "materials.rubber.c10 = { dist = \"lognormal\", median = 25.0, sigma = 0.1 }\n")
    a, b = load_sweep(write_sweep(tmp_path, body)), load_sweep(write_sweep(tmp_path, body))
    assert a.rows == b.rows and len(a.rows) == 8
    strata = sorted(int((r["parameters.stretch"] - 1.2) / 0.1) for r in a.rows)
    assert strata == list(range(8))  # Latin hypercube: one sample per stratum


def test_file_paths_of_the_base_case_stay_valid_in_the_runs(tmp_path):
    """A user_mesh case names its mesh file relative to the case file: each run's case
    (written elsewhere) names it by its absolute path, and the file's content is in the
    run hash."""
    meshio = pytest.importorskip("meshio")
    import numpy as np

    from eyefem.study.spec import plan

    pts = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
    mesh_dir = tmp_path / "meshes"
    mesh_dir.mkdir()
    meshio.write(mesh_dir / "cube.vtu", meshio.Mesh(pts, [("hexahedron", [[0, 1, 3, 2, 4, 5, 7, 6]])]))
    (tmp_path / "base.toml").write_text('[case]\nproblem = "user_mesh"\n[parameters]\n'
                                        'mesh_file = "meshes/cube.vtu"\n')
    f = tmp_path / "sweep.toml"
    f.write_text('[sweep]\ncase = "base.toml"\n[grid]\nparameters.steps = [1, 2]\n')
    runs, invalid = plan(load_sweep(f))
    assert invalid == [] and len(runs) == 2
    assert str((mesh_dir / "cube.vtu").resolve()) in runs[0].case_text
    before = runs[0].run_hash
    meshio.write(mesh_dir / "cube.vtu", meshio.Mesh(pts * 2, [("hexahedron", [[0, 1, 3, 2, 4, 5, 7, 6]])]))
    assert plan(load_sweep(f))[0][0].run_hash != before  # a changed mesh file: a new run


@pytest.mark.slow
def test_coarse_surgery_sweep_equals_serial_runs(client, tmp_path):
    """A 2 x 2 coarse surgery sweep (case 1: tightening x suture width) on 2 workers
    against the same cases run one after the other with `eyefem run`: slow (8 coarse
    surgery runs: 18 minutes on a shared 2-core machine)."""
    from eyefem.cli.main import main

    sweep = load_sweep(ROOT / "cases/sweeps/case1_coarse.toml")
    sweep = dataclasses.replace(sweep, gradients=())
    res = run_sweep(sweep, out=tmp_path / "sweep", client=client)
    assert [r["status"] for r in res.rows] == ["ok"] * 4
    for r in res.rows:
        run = res.out_dir / "runs" / Path(r["run_dir"]).name
        assert main(["-q", "run", str(run / "case.toml"), "--out", str(tmp_path / f"serial{r['index']}"),
                     "--no-vtu"]) == 0
        ref = json.loads((tmp_path / f"serial{r['index']}" / "summary.json").read_text())
        for o in sweep.outcomes:
            assert math.isclose(r[o], ref[o], rel_tol=1e-9, abs_tol=1e-12), (o, r[o], ref[o])
