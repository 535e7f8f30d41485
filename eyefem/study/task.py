"""One run of a sweep, as executed on a Dask worker (or in this process).

:func:`run_case` writes the run's case file into its folder, runs it as ``eyefem run``
does (the problem's builder, :func:`eyefem.run.runner.run_setup`, ``summary.json``),
optionally differentiates the outcomes (:func:`gradients_of`: the adjoint of
:func:`eyefem.simulate` for a surgery case's design variables, central differences for
any other real-valued input), and writes ``row.json``: the record that the results table
and a restarted sweep read. Failures are
returned as data (status ``failed`` or ``did-not-converge`` with the message), never
raised, so Dask re-runs a task only when its worker died.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import tempfile
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


def case_with(case, overrides: dict, folder: Path, name: str):
    """The parsed case with ``overrides`` (dotted path -> value) applied to its TOML, written
    as ``folder/<name>.toml`` and read back (validated) with load_case. File paths of the
    case (a user's mesh) stay the resolved ones."""
    import tomli_w

    from eyefem.catalog import schemas, solver_defaults
    from eyefem.io.casefile import load_case
    from eyefem.study.spec import _set

    raw = copy.deepcopy(case.raw)
    for f in schemas()[case.problem]:
        if getattr(f, "path", False) and case.parameters.get(f.name):
            _set(raw, f"parameters.{f.name}", str(case.parameters[f.name]))
    for p, v in overrides.items():
        _set(raw, p, v)
    f = Path(folder) / f"{name}.toml"
    f.write_text(tomli_w.dumps(raw), encoding="utf-8")
    return load_case(f, schemas(), solver_defaults())


def solve_case(case, out: Path, setup=None):
    """Run a parsed case into ``out`` as ``eyefem run`` does (its problem's builder and
    run_setup); returns run_setup's result."""
    from eyefem.catalog import problems
    from eyefem.io import manifest
    from eyefem.io.casefile import check_material_names
    from eyefem.run.runner import run_setup

    if setup is None:
        setup = problems()[case.problem][1](case.parameters, case.materials)
    check_material_names(case, setup.model.mesh.materials)
    return run_setup(setup, out, case.solver, vtu=case.output["vtu"], plots=case.output["plots"],
                     key=manifest.case_key(case.problem, case.parameters, case.materials,
                                           case.solver),
                     inputs=(CASE_FILE, ROW_FILE))  # a sweep run's own inputs, kept


def outcomes_of(case, out: Path) -> dict:
    """The numbers of a run of a case (no VTU, no plots) in ``out``: those recorded at the
    last converged step, overridden by those of the summary (as the results table reads
    an outcome)."""
    Path(out).mkdir(parents=True, exist_ok=True)
    quiet = case_with(case, {"output": {"vtu": False, "plots": False}}, out, "case")
    res = solve_case(quiet, Path(out) / "run")
    return {**(_numbers(res.rows[-1]) if res.rows else {}), **_numbers(res.summary)}


def gradients_of(case, setup, names, *, outcomes=(), values=None,
                 fd_step: float | None = None) -> dict:
    """d outcome / d input at the case, keys 'd_<outcome>/d_<input>' (units: the
    outcome's per the input's).

    ``names``: design variables of a rigid-buckle surgery case (the adjoint: one
    eyefem.simulate forward solve and a jax.jacrev, three adjoint solves per outcome,
    every surgery outcome) and dotted paths (parameters.NAME, materials.NAME.cRS) of any
    case (central differences (y(x + h) - y(x - h)) / 2h, h = fd_step |x|: two more
    solves each; a surgery case's by eyefem.simulate, any other by a run of the case).
    ``outcomes``: the outcomes of a non-surgery case to differentiate (default: every
    number of ``values``, the run's summary at x, as the results table records)."""
    import jax

    from eyefem.study.spec import FD_STEP, value_of
    from eyefem.study.spec import fd_step as step_at

    adjoint = [n for n in names if "." not in n]
    central = [n for n in names if "." in n]
    out: dict[str, float] = {}
    surgery = case.problem == "surgery"
    if surgery:
        from eyefem.api import simulate
    if adjoint:
        x0 = design_point(case, setup, adjoint)
        jac = jax.jacrev(lambda d: simulate(case, d))(x0)
        out.update({f"d_{o}/d_{v}": float(jac[o][v]) for o in jac for v in adjoint})
    if not central:
        return out
    names_y = list(outcomes) or [k for k in (values or {}) if k != "wall_s"]
    with tempfile.TemporaryDirectory(prefix="eyefem-fd-") as tmp:
        for p in central:
            x = value_of(case, p)
            h = step_at(x, fd_step or FD_STEP)
            ys = []
            for sign, tag in ((1, "plus"), (-1, "minus")):
                shifted = case_with(case, {p: x + sign * h}, tmp, f"{p}_{tag}")
                if surgery:
                    ys.append(simulate(shifted, {}))
                else:
                    ys.append(outcomes_of(shifted, Path(tmp) / f"{p}_{tag}"))
            for o in (list(ys[0]) if surgery else names_y):
                if o in ys[0] and o in ys[1]:
                    out[f"d_{o}/d_{p}"] = (ys[0][o] - ys[1][o]) / (2 * h)
    return out


def run_case(case_text: str, run_dir: str, *, run_hash: str, index: int,
             gradients: tuple = (), outcomes: tuple = (), fd_step: float | None = None,
             jax_cache: str | None = None, device: str = "cpu") -> dict:
    """Run one case (TOML text) into ``run_dir``; returns (and writes as row.json) the
    record: index, run_hash, status ('ok', 'failed', 'did-not-converge'), error, wall_s,
    summary (the numbers of summary.json), last_step (the numbers recorded at the last
    converged step), gradients (:func:`gradients_of` by ``gradients`` of ``outcomes``,
    central differences with the relative step ``fd_step``), run_dir, worker (host:pid),
    device (where the element kernels ran: ``device`` "cpu" or "gpu",
    eyefem.solve.device; a worker without the GPU asked for fails the run, saying so)."""
    import os
    import socket

    import jax

    from eyefem.solve.device import keep_compiled
    from eyefem.solve.heap import configure_heap

    jax.config.update("jax_enable_x64", True)
    configure_heap()
    if jax_cache and not jax.config.jax_compilation_cache_dir:
        keep_compiled(jax_cache)
    from eyefem.catalog import problems, schemas, solver_defaults
    from eyefem.io import manifest
    from eyefem.io.casefile import load_case
    from eyefem.io.output import write_text
    from eyefem.run.runner import write_summary
    from eyefem.solve.solver import ConvergenceError

    out = Path(run_dir)
    rec = {"index": index, "run_hash": run_hash, "status": "ok", "error": "", "wall_s": math.nan,
           "summary": {}, "last_step": {}, "gradients": {}, "run_dir": str(out),
           "worker": f"{socket.gethostname()}:{os.getpid()}", "device": ""}
    tic = time.perf_counter()
    try:
        from eyefem.solve.device import select_device

        rec["device"] = select_device(device)
        manifest.check_writable(out)
        (out / ROW_FILE).unlink(missing_ok=True)
        write_text(out / CASE_FILE, case_text)
        case = load_case(out / CASE_FILE, schemas(), solver_defaults())
        setup = problems()[case.problem][1](case.parameters, case.materials)
        res = solve_case(case, out, setup)
        summary = {"case": str(case.path), "title": case.title, **res.summary}
        write_summary(res, summary)  # listed with its hash in run.json (reused_record)
        rec["summary"] = _numbers(res.summary)
        rec["last_step"] = _numbers(res.rows[-1]) if res.rows else {}
        if gradients:
            rec["gradients"] = gradients_of(
                case, setup, tuple(gradients), outcomes=tuple(outcomes), fd_step=fd_step,
                values=rec["summary"])
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


def reused_record(run_dir: Path, run_hash: str, statuses) -> dict | None:
    """The row.json of a run folder when a restarted sweep may keep it: of this run hash,
    with a status of ``statuses``, its run's record (run.json) finished with every listed
    file unchanged, and, for a run that completed, its numbers those of its summary.json
    (an accident to row.json or to the run's files means the run is computed again)."""
    from eyefem.io import manifest

    rec = read_record(run_dir)
    if not rec or rec.get("run_hash") != run_hash or rec.get("status") not in statuses:
        return None
    m = manifest.read(run_dir)
    if m is None or m.get("status") not in ("complete", "failed") \
            or manifest.changed_files(run_dir, m):
        return None
    if rec["status"] == "ok":
        try:
            summary = json.loads((Path(run_dir) / "summary.json").read_text())
        except (OSError, ValueError):
            return None
        if "summary.json" not in m.get("files", {}) or _numbers(summary) != rec.get("summary"):
            return None
    return rec


def read_record(run_dir: Path) -> dict | None:
    """The row.json of a run folder, or None."""
    try:
        rec = json.loads((Path(run_dir) / ROW_FILE).read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) else None
