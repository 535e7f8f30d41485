"""Running a problem: solve its load path, write history CSV, VTU series and plots.

A problem builder returns a :class:`Setup`: the model, the stages, a ``probe`` giving
the scalar quantities recorded at every converged step, and a ``finish`` that
compares the recorded curve with theory, plots it and returns a summary.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from eyefem.io import checkpoint
from eyefem.io.output import SeriesWriter, write_csv
from eyefem.solve.model import Model
from eyefem.solve.solver import ACCEPTED_FLAGS, NewtonOptions, Solution, Stage, solve

log = logging.getLogger(__name__)

_LOGGED = ("pressure_mmHg", "volume_mm3", "/active", "max_penetration_mm", "/force_N")
"""Report quantities echoed in the step log (cavities, contact); all go to the CSV."""


@dataclasses.dataclass
class Setup:
    """What a problem builder returns.

    Attributes:
      name: base name of the output files.
      model: the model.
      stages: the load path.
      probe: ``f(model, q, theta) -> dict`` of scalars recorded at every step.
      finish: ``f(rows, out_dir, plots) -> dict`` summary (theory comparison, plots).
      q0: optional initial state.
    """

    name: str
    model: Model
    stages: list[Stage]
    probe: Callable[[Model, np.ndarray, Any], dict]
    finish: Callable[[list[dict], Path, bool], dict]
    q0: np.ndarray | None = None


@dataclasses.dataclass
class RunResult:
    """Outcome of a run: summary, per-step rows, solution and output directory."""

    summary: dict
    rows: list[dict]
    solution: Solution
    out_dir: Path


def cell_and_point_fields(model: Model, q, theta):
    """VTU fields: displacement and term point fields; solid stresses and materials per cell."""
    n = model.mesh.n_nodes
    point = {"displacement": q[: 3 * n].reshape(n, 3)}
    cell = {"material": model.mesh.material_ids.astype(np.int32)}
    for t in model.terms:
        point.update(t.point_fields(q, theta[t.name], n))
        if hasattr(t, "fields"):
            f = t.fields(q, theta[t.name])
            idx = t.elements
            for k, v in f.items():
                full = np.zeros((model.mesh.n_elem,) + v.shape[1:])
                full[idx] = v
                cell[k] = full
    return point, cell


def run_setup(setup: Setup, out_dir: Path, options: NewtonOptions = NewtonOptions(), *,
              vtu: bool = True, plots: bool = True, key: str = "", resume: bool = False
              ) -> RunResult:
    """Solve a setup, writing outputs after each converged step (atomically).

    After every completed stage a checkpoint is written to ``out_dir``; with
    ``resume=True`` the run continues after the last completed stage of the checkpoint
    (``key`` identifies the case, so a checkpoint of another case is refused).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    writer = SeriesWriter(out_dir, setup.name)
    tic = time.perf_counter()
    key = checkpoint.fingerprint(key, setup.name, setup.model.n_dof, len(setup.stages))
    q0, theta0, completed = setup.q0, None, ()
    if resume:
        ck = checkpoint.load(out_dir, key)
        rows[:] = ck["rows"]
        writer.entries = list(ck["vtu_entries"])
        q0, theta0, completed = ck["q"], ck["theta"], ck["starts"]
        log.info("resuming %s after stage %d ('%s') from %s", setup.name, ck["stage"] + 1,
                 setup.stages[ck["stage"]].name, out_dir / checkpoint.FILENAME)

    active = {s.name: s.active for s in setup.stages}

    def on_step(rec, model, q, theta):
        row = {"stage": rec.stage, "step": rec.step, "t": rec.t, "iterations": rec.iterations,
               "residual_N": rec.residual,
               **{flag: int(rec.info.get(flag, False)) for flag in ACCEPTED_FLAGS.values()}}
        row.update(setup.probe(model, q, theta))
        report = model.report(q, theta, active.get(rec.stage))
        row.update(report)
        rows.append(row)
        logged = [f"{k} {v:.9g}" if k.endswith("volume_mm3") else f"{k} {v:.5g}"
                  for k, v in report.items() if k.endswith(_LOGGED)]
        if logged:
            log.info("    %s", ", ".join(logged))
        write_csv(out_dir / f"{setup.name}_history.csv", rows)
        if vtu:
            point, cell = cell_and_point_fields(model, q, theta)
            writer.add(float(len(rows)), model.mesh.nodes, model.mesh.hexes, point, cell)

    def on_stage_end(i, model, q, theta, starts):
        checkpoint.save(out_dir, key=key, stage=i, q=q, theta=theta, starts=starts, rows=rows,
                        vtu_entries=writer.entries)

    sol = solve(setup.model, setup.stages, q0=q0, theta=theta0, options=options,
                on_step=on_step, on_stage_end=on_stage_end, completed=completed)
    if not sol.history:  # resumed after the last stage: nothing left to solve
        setup.probe(sol.model, sol.q, sol.theta)
    summary = setup.finish(rows, out_dir, plots)
    summary["wall_s"] = time.perf_counter() - tic
    summary["newton_iterations"] = int(sum(r.iterations for r in sol.history))
    for flag, key in (("stalled", "steps_accepted_on_a_stall"),
                      ("contact_cycle", "steps_accepted_on_a_contact_cycle")):
        summary[key] = int(sum(r.info.get(flag, False) for r in sol.history))
    return RunResult(summary, rows, sol, out_dir)
