"""Test configuration: float64 everywhere, as the entry points switch it on; the CLI's
persistent compilation cache off (``EYEFEM_JAX_CACHE``), so that the tests that call the
CLI write nothing outside their temporary directories; and the coarse comparison of the
surgical cases 1-6, computed once per session into a temporary directory and shared by
tests/test_surgery_cases.py and the compare_cases notebook (tests/test_notebooks.py).
"""

import os
from pathlib import Path

import jax
import pytest

os.environ.setdefault("EYEFEM_JAX_CACHE", "off")
jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]


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
