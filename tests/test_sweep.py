"""Parameter sweeps on dask.distributed (eyefem.study): the table equals serial runs, a
killed worker's run is re-run, a restart skips completed runs, failures are rows, a
wrong sweep file gets a message naming the fix, the progress lines, and the gradient
columns and first-order uncertainty (--uncertainty) against the closed form of the
uniaxial test and central differences.

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


def write_sweep(folder: Path, body: str, c01: float = 5.0,
                outcomes: str = '["force_N", "newton_iterations"]') -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "base.toml").write_text(UNIAXIAL.format(c01=c01))
    f = folder / "sweep.toml"
    f.write_text(f'[sweep]\ncase = "base.toml"\noutcomes = {outcomes}\n'
                 f'output = "{(folder / "out").as_posix()}"\n' + body)
    return f


def force(stretch, c10=25.0, c01=5.0):
    """The uniaxial test's closed form (unit cube, incompressible Mooney-Rivlin), N: the
    FE force equals it to roundoff (max_rel_error_force ~ 2e-14)."""
    return 2 * (stretch - stretch**-2) * (c10 + c01 / stretch)


def dforce(stretch, c10=25.0, c01=5.0):
    """d force / d (stretch, c10, c01) of the closed form."""
    return (2 * (1 + 2 * stretch**-3) * (c10 + c01 / stretch)
            - 2 * (stretch - stretch**-2) * c01 / stretch**2,
            2 * (stretch - stretch**-2), 2 * (stretch - stretch**-2) / stretch)


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
    from eyefem.run.runner import run_setup

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
    # an edited row.json (its numbers no longer its run's summary) is computed again
    row = json.loads(rows_files[0].read_text())
    row["summary"]["force_N"] = 1e6
    rows_files[0].write_text(json.dumps(row))
    edited = run_sweep(load_sweep(f), client=client)
    assert (edited.computed, edited.skipped) == (1, 1)
    assert edited.rows[0]["force_N"] == pytest.approx(first.rows[0]["force_N"], rel=1e-6)
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


def test_runs_go_to_the_device_asked_for(client, tmp_path):
    """``device`` reaches the workers: "cpu" is recorded in each run's row.json, and "gpu"
    on workers without one fails every run with what to install (a restart on the CPU
    then runs them)."""
    import jax

    sweep = load_sweep(write_sweep(tmp_path / "s", "[[list]]\nparameters.stretch = 1.3\n"))
    res = run_sweep(sweep, client=client, device="cpu")
    row = json.loads(next((tmp_path / "s" / "out" / "runs").glob("*/row.json")).read_text())
    assert res.rows[0]["status"] == "ok" and row["device"].startswith("cpu")
    try:
        jax.devices("gpu")
        pytest.skip("the CPU half passed; this machine has a GPU, so the refusal cannot "
                    "be provoked")
    except RuntimeError:
        pass
    sweep = load_sweep(write_sweep(tmp_path / "g", "[[list]]\nparameters.stretch = 1.4\n"))
    res = run_sweep(sweep, client=client, device="gpu")
    assert res.rows[0]["status"] == "failed" and "JAX finds no GPU" in res.rows[0]["error"]
    assert run_sweep(sweep, client=client).rows[0]["status"] == "ok"


def test_cli_on_an_existing_scheduler(client, tmp_path, capsys):
    """`eyefem sweep FILE --scheduler ADDRESS`: the table, the plots, the best designs,
    the progress lines on stderr (none with -q)."""
    from eyefem.cli.main import main

    f = write_sweep(tmp_path / "s", "[grid]\nparameters.stretch = [1.3, 1.5]\n"
                    "[best]\noutcome = \"force_N\"\ngoal = \"target\"\ntarget = 60.0\n")
    assert main(["-q", "sweep", str(f), "--scheduler", client.scheduler.address,
                 "--out", str(tmp_path / "quiet")]) == 0
    assert "runs done" not in capsys.readouterr().err  # -q: no progress
    assert main(["sweep", str(f), "--scheduler", client.scheduler.address,
                 "--out", str(tmp_path / "cli")]) == 0
    out, err = capsys.readouterr()
    progress = [ln for ln in err.splitlines() if ln.startswith("sweep: ") and "runs done" in ln]
    assert progress[0].startswith("sweep: 0/2 runs done (0 failed), ") and "~? left" in progress[0]
    assert progress[-1].startswith("sweep: 2/2 runs done (0 failed), 0 running, 0 queued; ")
    assert progress[-1].endswith("~0s left")
    printed = out
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
    ('gradients = ["stretch"]\n[grid]\nparameters.stretch = [1.2]\n',
     "give its path 'parameters.stretch' for central differences"),
    ('gradients = ["parameters.steps"]\n[grid]\nparameters.stretch = [1.2]\n',
     "'parameters.steps' is an integer parameter"),
    ('gradients = ["solver.rtol"]\n[grid]\nparameters.stretch = [1.2]\n',
     "'solver.rtol' is a solver option"),
    ('fd_step = 0.5\n[grid]\nparameters.stretch = [1.2]\n', "fd_step = 0.5; give the relative"),
    ("", "nothing to vary"),
    ("[grid]\nparameters.stretch = [" + ", ".join(["1.2"] * 1000) + "]\n"
     "materials.rubber.c10 = [" + ", ".join(["1.0"] * 1000) + "]\n",
     "1,000,000 runs, more than the 10,000 a sweep may make"),
    ("[samples]\nn = 100000\nseed = 1\nparameters.stretch = { dist = \"uniform\", low = 1.2, "
     "high = 1.5 }\n", "100,000 runs, more than the 10,000"),
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
    surgery runs: 18 minutes on a shared 2-core machine). A worker and a serial run solve
    on different thread counts, so their sums round differently and their states agree to
    the force tolerance, not bit for bit (measured up to 1.4e-9 relative in an outcome):
    they are compared at 1e-6, the tolerance of the recorded coarse outcomes
    (tests/test_surgery_cases.py)."""
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
            assert math.isclose(r[o], ref[o], rel_tol=1e-6, abs_tol=1e-12), (o, r[o], ref[o])


def test_progress_lines_at_most_every_interval():
    """SweepProgress: a line at most every `interval` s (or forced), the counts and the
    time left from the pace so far."""
    from eyefem.study.sweep import SweepProgress

    now = [100.0]
    lines = []
    meter = SweepProgress(10, lines.append, interval=5.0, clock=lambda: now[0])
    assert meter.update(0, 0, 2, force=True)
    now[0] += 2.0
    assert not meter.update(1, 0, 2)  # 2 s after the last line: quiet
    now[0] += 4.0
    assert meter.update(3, 1, 2)  # 6 s: 3 runs in 6 s, 7 left -> 14 s
    assert lines == ["sweep: 0/10 runs done (0 failed), 2 running, 8 queued; 0s elapsed, ~? left",
                     "sweep: 3/10 runs done (1 failed), 2 running, 5 queued; 6s elapsed, ~14s left"]
    assert meter.update(3, 1, 2, force=True) and len(lines) == 3


def test_gradient_columns_match_the_closed_form_and_the_outcome_column(client, tmp_path):
    """gradients by dotted paths of a non-surgery case: central differences of whole runs
    (h = 1e-3 |x|). d force / d stretch against the closed form and against the central
    difference of the table's force column over the grid's neighbours (+-1e-3): their
    truncation errors are 9e-7 and 4e-7 relative (the force's roundoff, 1e-15, adds 1e-11),
    so rtol 1e-5 holds with a margin of 10 and fails for a wrong step or factor. The force
    is linear in c01: that column is exact to roundoff."""
    d = 1e-3
    stretches = [1.5 - d, 1.5, 1.5 + d]
    body = ('gradients = ["parameters.stretch", "materials.rubber.c01"]\n'
            f"[grid]\nparameters.stretch = {stretches}\n")
    res = run_sweep(load_sweep(write_sweep(tmp_path / "s", body, outcomes='["force_N"]')),
                    client=client)
    assert [r["status"] for r in res.rows] == ["ok"] * 3, res.rows
    rows = table.read(res.out_dir)
    col, col_c01 = "d_force_N/d_parameters.stretch", "d_force_N/d_materials.rubber.c01"
    assert {col, col_c01} <= set(rows[0])
    f = [r["force_N"] for r in rows]
    assert f[1] == pytest.approx(force(1.5), rel=1e-12)
    from_column = (f[2] - f[0]) / (2 * d)
    assert rows[1][col] == pytest.approx(from_column, rel=1e-5)
    for r, lam in zip(rows, stretches):
        dl, _, dc01 = dforce(lam)
        assert r[col] == pytest.approx(dl, rel=2e-6), lam
        assert r[col_c01] == pytest.approx(dc01, rel=1e-9), lam


def test_uncertainty_first_order_against_the_closed_form(client, tmp_path, capsys):
    """`eyefem sweep FILE --uncertainty` on the uniaxial test: the first-order mean and std
    it writes (uncertainty.json) against the closed form's gradient (the force is linear in
    c10 and c01: exact; the stretch by central differences, 1e-6 relative truncation), and
    the sampled statistics against the closed form at the table's sampled parameters."""
    import numpy as np

    from eyefem.cli.main import main

    body = ("[samples]\nn = 6\nseed = 2\n"
            "parameters.stretch = { dist = \"uniform\", low = 1.4, high = 1.6 }\n"
            "materials.rubber.c10 = { dist = \"normal\", mean = 25.0, std = 2.0 }\n"
            "materials.rubber.c01 = { dist = \"lognormal\", median = 5.0, sigma = 0.2 }\n")
    f = write_sweep(tmp_path / "s", body, outcomes='["force_N"]')
    out = tmp_path / "uq"
    assert main(["-q", "sweep", str(f), "--scheduler", client.scheduler.address,
                 "--out", str(out), "--uncertainty"]) == 0
    printed = capsys.readouterr().out
    assert "| force_N |" in printed and "7 forward solves" in printed
    assert "parameters.stretch (central differences, h = 0.0015)" in printed
    uq = json.loads((out / "uncertainty.json").read_text())
    fo, sa = uq["first_order"], uq["sampled"]
    dl, dc10, dc01 = dforce(1.5)
    terms = {"parameters.stretch": dl * 0.2 / math.sqrt(12), "materials.rubber.c10": dc10 * 2.0,
             "materials.rubber.c01": dc01 * 5.0 * 0.2}  # lognormal: dy/dx x0 sigma
    assert fo["mean"]["force_N"] == pytest.approx(force(1.5), rel=1e-12)
    for k, t in terms.items():
        assert fo["terms"]["force_N"][k] == pytest.approx(t, rel=2e-6), k
    std = math.sqrt(sum(t * t for t in terms.values()))
    assert fo["std"]["force_N"] == pytest.approx(std, rel=2e-6)
    rows = table.read(out)
    exact = np.array([force(r["parameters.stretch"], r["materials.rubber.c10"],
                            r["materials.rubber.c01"]) for r in rows])
    assert sa["n"]["force_N"] == 6
    assert sa["mean"]["force_N"] == pytest.approx(exact.mean(), rel=1e-12)
    assert sa["std"]["force_N"] == pytest.approx(exact.std(ddof=1), rel=1e-9)
    assert (out / "uncertainty_hist.png").is_file() and (out / "uncertainty_tornado.png").is_file()


@pytest.mark.parametrize("sampled, message", [
    ("parameters.steps = { dist = \"uniform\", low = 2.0, high = 4.0 }",
     "'parameters.steps' is an integer parameter; a derivative needs a real-valued"),
    ("solver.rtol = { dist = \"uniform\", low = 1e-9, high = 1e-8 }",
     "'solver.rtol' is a solver option, not an input of the model"),
])
def test_uncertainty_refuses_an_input_without_a_derivative_before_the_runs(
        tmp_path, capsys, sampled, message):
    from eyefem.cli.main import main

    f = write_sweep(tmp_path / "s", f"[samples]\nn = 2\nseed = 1\n{sampled}\n")
    assert main(["-q", "sweep", str(f), "--out", str(tmp_path / "out"), "--uncertainty"]) == 2
    err = capsys.readouterr().err
    assert message in err and str(f) in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()  # refused before any run


def test_biometry_is_propagated_by_central_differences(monkeypatch, tmp_path):
    """parameters.axial_length of a surgery case changes the mesh: no adjoint; first_order
    takes central differences of eyefem.simulate (two more solves) next to the adjoint of a
    design variable. A stand-in simulate with a closed form (quadratic in the axial length
    L, linear in c10) checks the propagation without a surgery solve."""
    import jax.numpy as jnp

    import eyefem.api
    from eyefem.eye.variables import OUTCOMES
    from eyefem.study.spec import Distribution
    from eyefem.study.uncertainty import first_order, sweep_distributions

    f = tmp_path / "sweep.toml"
    f.write_text(f'[sweep]\ncase = "{(ROOT / "cases/surgery/case1.toml").as_posix()}"\n'
                 '[set]\nparameters.mesh = "coarse"\n[samples]\nn = 4\nseed = 1\n'
                 'parameters.axial_length = { dist = "normal", mean = 25.0, std = 1.0 }\n'
                 'materials.sclera.c10 = { dist = "normal", mean = 0.0833, std = 0.0125 }\n')
    dists = sweep_distributions(load_sweep(f))
    assert dists == {"parameters.axial_length": Distribution("normal", 25.0, 1.0),
                     "c10_sclera": Distribution("normal", 0.0833, 0.0125)}
    lengths = []

    def fake_simulate(case, design=None, *, mesh=None):
        L = case.parameters["axial_length"]
        lengths.append(L)
        c = jnp.asarray(design.get("c10_sclera", 0.07))
        return {o: 0.3 * (i + 1) * L**2 - 40.0 * c for i, o in enumerate(OUTCOMES)}

    monkeypatch.setattr(eyefem.api, "simulate", fake_simulate)
    fo = first_order(ROOT / "cases/surgery/case1.toml", dists)
    h = 25.0e-3
    assert sorted(lengths) == [25.0 - h, 25.0, 25.0, 25.0 + h]  # y0, the adjoint, +-h
    assert fo["solves"] == 3 and fo["step"] == {"parameters.axial_length": h}
    assert fo["method"] == {"parameters.axial_length": "central differences",
                            "c10_sclera": "adjoint"}
    for i, o in enumerate(OUTCOMES):
        a = 0.3 * (i + 1)
        assert fo["mean"][o] == pytest.approx(a * 625.0 - 40.0 * 0.0833, rel=1e-12)
        dl = 2 * a * 25.0  # central differences of a quadratic: exact to roundoff
        assert fo["gradient"][o]["parameters.axial_length"] == pytest.approx(dl, rel=1e-9)
        assert fo["gradient"][o]["c10_sclera"] == pytest.approx(-40.0, rel=1e-12)
        assert fo["std"][o] == pytest.approx(math.hypot(dl * 1.0, 40.0 * 0.0125), rel=1e-9)


@pytest.mark.parametrize("address", ["garbage://x", "results.csv", "tcp://localhost"])
def test_a_scheduler_address_dask_cannot_dial_is_one_line(tmp_path, capsys, address):
    from eyefem.cli.main import main

    f = write_sweep(tmp_path, "[grid]\nparameters.stretch = [1.2]\n")
    assert main(["-q", "sweep", str(f), "--scheduler", address]) == 2
    err = capsys.readouterr().err
    assert f"--scheduler '{address}' is not a Dask scheduler address" in err
    assert "tcp://HOST:8786" in err and "Traceback" not in err
