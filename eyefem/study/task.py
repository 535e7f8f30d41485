"""One run of a sweep, as executed on a Dask worker (or in this process).

:func:`run_case` writes the run's case file into its folder, runs it as ``eyefem run``
does (the problem's builder, :func:`eyefem.io.runner.run_setup`, ``summary.json``),
optionally differentiates the surgery outcomes with :func:`eyefem.simulate`, and writes
``row.json``: the record that the results table and a restarted sweep read. Failures are
returned as data (status ``failed`` or ``did-not-converge`` with the message), never
raised, so Dask re-runs a task only when its worker died.
"""

from __future__ import annotations

import json
import logging
import math
import time
import traceback
from pathlib import Path

log = logging.getLogger(__name__)

ROW_FILE = "row.json"
CASE_FILE = "case.toml"


def _numbers(d: dict) -> dict:
    """The finite-or-not float/int entries of a dict (bools and nested data dropped)."""
    return {k: float(v) for k, v in d.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool)}


def design_point(case, setup, names) -> dict:
    """The values of the design variables ``names`` in a surgery case: its parameters, and
    c10_<material> from the built model's coefficients (which include presets)."""
    theta0 = None
    out = {}
    for n in names:
        if n.startswith("c10_"):
            if theta0 is None:
                theta0 = setup.model.theta0()
            i = setup.model.mesh.materials.index(n[4:])
            out[n] = float(theta0["solid"]["coeffs"][i, 1, 0])
        else:
            out[n] = float(case.parameters[n])
    return out


def gradients_of(case, setup, names) -> dict:
    """d outcome / d variable for every surgery outcome and each design variable in
    ``names``, at the case's design: one eyefem.simulate forward solve and a jax.jacrev
    (three adjoint solves per outcome). Keys 'd_<outcome>/d_<variable>'."""
    import jax

    from eyefem.api import simulate

    x0 = design_point(case, setup, names)
    jac = jax.jacrev(lambda d: simulate(case, d))(x0)
    return {f"d_{o}/d_{v}": float(jac[o][v]) for o in jac for v in names}


def run_case(case_text: str, run_dir: str, *, run_hash: str, index: int,
             gradients: tuple = (), jax_cache: str | None = None) -> dict:
    """Run one case (TOML text) into ``run_dir``; returns (and writes as row.json) the
    record: index, run_hash, status ('ok', 'failed', 'did-not-converge'), error, wall_s,
    summary (the numbers of summary.json), last_step (the numbers recorded at the last
    converged step), gradients, run_dir, worker (host:pid)."""
    import os
    import socket

    import jax

    jax.config.update("jax_enable_x64", True)
    if jax_cache and not jax.config.jax_compilation_cache_dir:
        jax.config.update("jax_compilation_cache_dir", jax_cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)
    from eyefem.catalog import problems, schemas
    from eyefem.io import manifest
    from eyefem.io.casefile import check_material_names, load_case
    from eyefem.io.output import write_text
    from eyefem.io.runner import run_setup
    from eyefem.solve.solver import ConvergenceError

    out = Path(run_dir)
    rec = {"index": index, "run_hash": run_hash, "status": "ok", "error": "", "wall_s": math.nan,
           "summary": {}, "last_step": {}, "gradients": {}, "run_dir": str(out),
           "worker": f"{socket.gethostname()}:{os.getpid()}"}
    tic = time.perf_counter()
    try:
        manifest.check_writable(out)
        (out / ROW_FILE).unlink(missing_ok=True)
        write_text(out / CASE_FILE, case_text)
        case = load_case(out / CASE_FILE, schemas())
        setup = problems()[case.problem][1](case.parameters, case.materials)
        check_material_names(case, setup.model.mesh.materials)
        res = run_setup(setup, out, case.solver, vtu=case.output["vtu"],
                        plots=case.output["plots"],
                        key=manifest.case_key(case.problem, case.parameters, case.materials,
                                              case.solver))
        summary = {"case": str(case.path), "title": case.title, **res.summary}
        write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
        rec["summary"] = _numbers(res.summary)
        rec["last_step"] = _numbers(res.rows[-1]) if res.rows else {}
        if gradients:
            rec["gradients"] = gradients_of(case, setup, tuple(gradients))
    except ConvergenceError as exc:
        rec.update(status="did-not-converge", error=f"ConvergenceError: {exc}")
    except Exception as exc:  # noqa: BLE001 - a failed run is data; the sweep goes on
        rec.update(status="failed", error=f"{type(exc).__name__}: {exc}")
        log.debug("run %d failed:\n%s", index, traceback.format_exc())
    rec["wall_s"] = time.perf_counter() - tic
    try:
        write_text(out / ROW_FILE, json.dumps(rec, indent=1) + "\n")
    except OSError as exc:
        rec.update(status="failed", error=f"cannot write {out / ROW_FILE}: {exc}")
    return rec


def read_record(run_dir: Path) -> dict | None:
    """The row.json of a run folder, or None."""
    try:
        rec = json.loads((Path(run_dir) / ROW_FILE).read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) else None
