"""The benchmark scripts run and still measure what they say (docs/performance.md quotes
them). They wrap the solver's internals to count and weigh (Pardiso's factorisations, the
assembler's blocks), so a changed signature there breaks them without failing anything
else; these runs are the smallest each script takes, into tmp_path."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(script: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args],
                         cwd=cwd, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, f"{script} {' '.join(args)} failed:\n{out.stderr[-3000:]}"
    return out


def test_the_core_benchmark_counts_the_factorisations_of_full_newton_and_bfgs(tmp_path):
    """bench_core.py on a 432-hexahedron shell, full Newton then BFGS in one process: every
    full Newton iteration factorises once (21 of them, recorded), BFGS reaches the same
    state (to 1e-8) with fewer factorisations than iterations."""
    _run("bench_core.py", "--sizes", "6:2", "--repeats", "1", "--quasi-newton", "off,bfgs",
         "--json", str(tmp_path / "core.json"), cwd=tmp_path)
    rows = json.loads((tmp_path / "core.json").read_text())
    full, bfgs = (next(r for r in rows if r["quasi_newton"] == k) for k in ("off", "bfgs"))
    assert full["n_elem"] == 432
    assert full["factorisations"] == full["newton_iterations"] == 21
    assert 1 <= bfgs["factorisations"] < bfgs["newton_iterations"]
    assert bfgs["state_rel_diff"] < 1e-8


@pytest.mark.slow
def test_the_memory_benchmark_reports_each_phase_and_pardisos_factors(tmp_path):
    """bench_memory.py on coarse case 1 (pressurise and one tightening step, with the case
    file's solver options): every phase has a peak, the factorisations are counted, and
    Pardiso's report of its factors is read."""
    _run("bench_memory.py", "--json", str(tmp_path / "memory.json"), cwd=ROOT)
    out = json.loads((tmp_path / "memory.json").read_text())
    phases = [r["phase"] for r in out["phases"]]
    assert phases[:2] == ["import jax, eyefem", "build the case (mesh, model)"]
    assert phases[-1] == "one VTU frame" and len(phases) == 5
    solved = out["phases"][2:4]
    assert all(r["factorisations"] >= r["newton_iterations"] > 0 for r in solved)
    assert out["pardiso_largest"]["factors_KB"] > 0 and out["pardiso_largest"]["nnz_L"] > 0
    assert all(r["peak_rss_MB"] >= r["end_rss_MB"] > 0 for r in out["phases"])
