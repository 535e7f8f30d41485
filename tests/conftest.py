"""Test configuration: float64 everywhere, as the entry points switch it on; the CLI's
persistent compilation cache off (``EYEFEM_JAX_CACHE``), so that the tests that call the
CLI write nothing outside their temporary directories; the coarse comparison of the
surgical cases 1-6, computed once per session into a temporary directory and shared by
tests/test_surgery_cases.py and the compare_cases notebook (tests/test_notebooks.py); and
the run of a timeline case with its gradients (``timeline_gradients``), which the slow
checks of tests/test_timeline_gradients.py and test_relaxation_gradients.py share.
The test session keeps XLA's compiled programs in a persistent cache of its own (a
temporary folder, removed at the end; :func:`pytest_configure`).
"""

import os
import shutil
import tempfile
from pathlib import Path

import jax
import pytest

os.environ.setdefault("EYEFEM_JAX_CACHE", "off")
jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]

SESSION_CACHE = "EYEFEM_TEST_SESSION_JAX_CACHE"
"""The environment variable that hands the session's compilation cache to pytest-xdist's
workers (they start after the controller's :func:`pytest_configure` and inherit it)."""
_OWNED_CACHE = pytest.StashKey[str]()


def pytest_configure(config):
    """Keep the compiled programs that took over 0.1 s in one persistent cache shared by
    every test process of the session: many tests build their own jitted function or model
    of a shape another test compiled already (a term's kernel, a coarse eye's), and then
    load its executable instead of compiling it again. The folder is a temporary one,
    made by the controller and removed by it at the end; nothing is written elsewhere, and
    a test of the cache itself runs in a subprocess with its own folder."""
    folder = os.environ.get(SESSION_CACHE)
    if folder is None:
        folder = tempfile.mkdtemp(prefix="eyefem-tests-jax-")
        os.environ[SESSION_CACHE] = folder
        config.stash[_OWNED_CACHE] = folder
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)


def pytest_unconfigure(config):
    folder = config.stash.get(_OWNED_CACHE, None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(SESSION_CACHE, None)



@pytest.fixture(scope="session")
def results_root(tmp_path_factory) -> Path:
    """A session's results directory (what ``results/`` is to a user): the notebooks read
    it from EYEFEM_RESULTS."""
    return tmp_path_factory.mktemp("results")


@pytest.fixture(scope="session")
def coarse_comparison(results_root) -> Path:
    """``eyefem compare cases/surgery/case*.toml --mesh coarse`` into
    ``<results_root>/compare-coarse`` (about 10 minutes on 2 cores); returns that folder."""
    from eyefem.cli.main import main as cli_main

    out = results_root / "compare-coarse"
    cases = sorted(str(p) for p in (ROOT / "cases" / "surgery").glob("case*.toml"))
    assert len(cases) == 6
    assert cli_main(["-q", "compare", *cases, "--mesh", "coarse", "--out", str(out)]) == 0
    return out


def _timeline_gradients(case: str, names) -> tuple:
    """(simulator, result, gradients of ``names``) of the timeline case file ``case`` on
    the coarse eye, followed to a week (1h, 48h, 1w) with a paracentesis of 30 uL two
    minutes after the tightening (eyefem.eye.simulators.SurgerySimulator: a
    TimelineSimulator)."""
    from eyefem.api import load_case
    from eyefem.eye.simulators import SurgerySimulator

    c = load_case(case)
    p = {**c.parameters, "mesh": "coarse", "followup": "1h, 48h, 1w",
         "paracentesis_volume": 30.0, "paracentesis_delay_minutes": 2.0}
    sim = SurgerySimulator(p, c.materials, c.solver)
    res = sim.run()
    return sim, res, sim.gradients(res, names)


@pytest.fixture(scope="session")
def timeline_gradients():
    """The function (case file, outcome names) -> (simulator, result, gradients) that runs
    a timeline case on the coarse eye (:func:`_timeline_gradients`); a test module keeps
    its result in a module fixture."""
    return _timeline_gradients
