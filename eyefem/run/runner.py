"""Running a problem: solve its load path, write history CSV, VTU/XDMF series and plots.

A problem builder returns a :class:`eyefem.solve.problem.Setup`: the model, the stages, a ``probe`` giving
the scalar quantities recorded at every converged step, and a ``finish`` that
compares the recorded curve with theory, plots it and returns a summary.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from eyefem.io import checkpoint, manifest
from eyefem.io.output import Part, SeriesWriter, XdmfSeriesWriter, write_csv
from eyefem.io.progress import Progress
from eyefem.solve.model import Model
from eyefem.solve.problem import Setup
from eyefem.solve.loadpath import replay_hooks
from eyefem.solve.solver import ACCEPTED_FLAGS, NewtonOptions, Solution, Stage, solve

log = logging.getLogger(__name__)

_LOGGED = ("pressure_mmHg", "volume_mm3", "/active", "max_penetration_mm", "/force_N")
"""Report quantities echoed in the step log (cavities, contact); all go to the CSV."""


@dataclasses.dataclass
class RunResult:
    """Outcome of a run: summary, per-step rows, solution, output directory and the record
    of the files written (eyefem.io.manifest.FileRecord)."""

    summary: dict
    rows: list[dict]
    solution: Solution
    out_dir: Path
    record: Any = None


def cell_and_point_fields(model: Model, q, theta, active=None, prescribed=None,
                          residual=None):
    """VTU fields of the state q (n_dof,) for the design theta.

    Point fields (n_nodes, ...): 'displacement' (3) mm; every term's ``point_fields``
    (cavity and contact pressures, gaps...); with ``prescribed`` (dof indices)
    'reaction_force_N' (3): the residual of the active terms on the prescribed
    displacement dofs (the force the supports exert on the body), 0 elsewhere; ``residual``
    (n_dof,): that residual when the caller has it (the mirror half's, lifted).
    Cell fields (n_elem, ...): 'material' (id into ``mesh.materials``) and the solid
    terms' ``fields`` (stresses, strains; NaN outside a term's elements).
    Fields of terms not in ``active`` (a stage's active names; None: all) are NaN, so
    every frame of a series has the same arrays and ParaView's colour ranges skip them.
    """
    n, n_elem = model.mesh.n_nodes, model.mesh.n_elem
    point = {"displacement": np.asarray(q[: 3 * n], np.float64).reshape(n, 3)}
    cell = {"material": model.mesh.material_ids.astype(np.int32)}
    for t in model.terms:
        on = active is None or t.name in active
        for k, v in t.point_fields(q, theta[t.name], n).items():
            point[k] = np.asarray(v, np.float64) if on else np.full(np.shape(v), np.nan)
        if hasattr(t, "fields"):
            for k, v in t.fields(q, theta[t.name]).items():
                v = np.asarray(v, np.float64)
                full = cell.setdefault(k, np.full((n_elem,) + v.shape[1:], np.nan))
                full[t.elements] = v if on else np.nan
    if prescribed is not None:
        dofs = np.asarray(prescribed, np.int64)
        dofs = dofs[dofs < 3 * n]
        reaction = np.zeros(3 * n)
        if residual is None:
            residual = model.gradient(q, theta, active)
        reaction[dofs] = np.asarray(residual)[dofs]
        point["reaction_force_N"] = reaction.reshape(n, 3)
    return point, cell


def term_parts(model: Model, q, theta, active=None) -> dict[str, Part]:
    """Term name -> Part for every term with a ``geometry`` (rigid buckle surfaces,
    sutures and zonule as lines with 'force_N'), in the current configuration. Each has
    the cell field 'active' (1 when the term is in ``active``); the float cell fields of
    an inactive term (forces) are NaN, except its lengths ('..._mm', geometry)."""
    parts = {}
    for t in model.terms:
        geo = t.geometry(q, theta[t.name])
        if geo is None:
            continue
        points, cell_type, cells, cell_data = geo
        on = active is None or t.name in active
        cd = {k: (np.full(len(cells), np.nan) if not on and not k.endswith("_mm")
                  and np.issubdtype(np.asarray(v).dtype, np.floating) else np.asarray(v))
              for k, v in cell_data.items()}
        cd["active"] = np.full(len(cells), int(on), np.int32)
        parts[t.name] = Part(np.asarray(points, np.float64), cell_type, np.asarray(cells), {}, cd)
    return parts


class SeriesGroup:
    """Several series writers (VTU, XDMF) fed the same frames; ``entries`` are the first
    writer's."""

    def __init__(self, writers):
        self.writers = list(writers)

    @property
    def entries(self) -> list:
        return self.writers[0].entries

    def add(self, *args, **kwargs):
        for w in self.writers:
            w.add(*args, **kwargs)


def add_frame(writer: SeriesWriter, model: Model, q, theta, stages, index: int, t: float,
              residual=None):
    """Write the state q of stage ``stages[index]`` at load factor t in [0, 1] as one
    frame at time index + t: the mesh with :func:`cell_and_point_fields`, the terms'
    parts (:func:`term_parts`) and field data 'time', 'stage' (index), 'load_factor',
    'stage:<name>' -> index of every stage and 'material:<name>' -> material id.
    ``residual``: the model's residual at q when the caller has it (for the reactions)."""
    stage, t = stages[index], round(float(t), 12)  # t of the last step: 1 - 1e-16 -> 1
    point, cell = cell_and_point_fields(model, q, theta, stage.active, stage.prescribed[0],
                                        residual)
    field = {"time": index + t, "stage": index, "load_factor": t,
             **{f"stage:{s.name}": i for i, s in reversed(list(enumerate(stages)))},
             **{f"material:{m}": i for i, m in enumerate(model.mesh.materials)}}
    writer.add(index + t, model.mesh.nodes, model.mesh.hexes, point, cell, field,
               term_parts(model, q, theta, stage.active))


def write_step(writer: SeriesWriter, setup: Setup, stage_name: str, t: float, model: Model,
               q, theta):
    """Append a converged step (stage ``stage_name``, load factor t) to the series; a
    fresh series first gets the undeformed state (``setup.q0`` or zero, default design,
    the first stage's active terms) at time 0. A setup with a ``whole`` (the mirror half)
    writes the whole model at the lifted state (its mesh, fields and reactions: from the
    solved model's residual when the Whole lifts it, so the whole's kernels are not
    compiled)."""
    whole = setup.whole
    names = [s.name for s in setup.stages]

    def residual(model_s, q_s, theta_s, name):
        """The whole's residual from the solved model's (None: the whole computes it)."""
        if whole is None or whole.residual is None:
            return None
        active = setup.stages[names.index(name)].active
        return whole.residual(model_s.gradient(q_s, theta_s, active))

    if not writer.entries:
        q0 = np.zeros(setup.model.n_dof) if setup.q0 is None else np.asarray(setup.q0)
        g0 = residual(setup.model, q0, setup.model.theta0(), names[0])
        first, stages0 = setup.model, setup.stages
        if whole is not None:
            first, stages0 = whole.model, whole.stages
            q0 = np.zeros(first.n_dof) if whole.q0 is None else np.asarray(whole.q0)
        add_frame(writer, first, q0, first.theta0(), stages0, 0, 0.0, g0)
    g = residual(model, q, theta, stage_name)
    stages = setup.stages
    if whole is not None:
        model, q, theta = whole.lift(model, q, theta)
        stages = whole.stages
    last = writer.entries[-1][0]
    index = next((i for i, s in enumerate(names) if s == stage_name and i + t > last),
                 names.index(stage_name))
    add_frame(writer, model, q, theta, stages, index, t, g)


def checkpoint_key(setup: Setup, key: str = "") -> str:
    """The key a run of ``setup`` writes in its checkpoint (``key``: the case's)."""
    return checkpoint.fingerprint(key, setup.name, setup.model.n_dof, len(setup.stages))


def _checked(ck: dict, setup: Setup, out_dir: Path) -> dict:
    """The checkpoint ``ck`` of ``setup``'s run, its stage index and arrays checked against
    the model (CheckpointError naming the field and the fix, never a traceback later)."""
    path = Path(out_dir) / checkpoint.FILENAME
    again = "run without --resume (or use another --out)"
    n, last = setup.model.n_dof, len(setup.stages) - 1
    stage = ck["stage"]
    if not 0 <= stage <= last:
        raise checkpoint.CheckpointError(f"{path}: stage = {stage}, but the case has stages "
                                         f"0 to {last}; {again}")
    if np.shape(ck["q"]) != (n,) or len(ck["starts"]) != stage + 1 or any(
            np.shape(a) != (n,) for a, _ in ck["starts"]):
        raise checkpoint.CheckpointError(
            f"{path}: its state q has shape {np.shape(ck['q'])} and {len(ck['starts'])} stage "
            f"starts, the model has {n} dofs and completed stage {stage} needs {stage + 1}; "
            f"{again}")
    if not np.all(np.isfinite(ck["q"])):
        raise checkpoint.CheckpointError(f"{path}: its state q is not finite; {again}")
    return ck


def completed_state(setup: Setup, out_dir: Path, key: str = "", stage: int | None = None):
    """The model and state at the end of a completed stage of the run in ``out_dir``.

    Reads the run's checkpoint (``key`` as given to :func:`run_setup`; CheckpointError if
    it is missing or of another case) and replays the ``before`` hooks of the stages up to
    ``stage`` (default: the last completed one) on ``setup.model``. Returns (model, q
    (n_dof,), theta, stage index)."""
    ck = _checked(checkpoint.load(Path(out_dir), checkpoint_key(setup, key)), setup, out_dir)
    last = int(ck["stage"])
    i = last if stage is None else int(stage)
    if not 0 <= i <= last:
        done = ", ".join(f"{j} '{s.name}'" for j, s in enumerate(setup.stages[: last + 1]))
        raise checkpoint.CheckpointError(
            f"{Path(out_dir) / checkpoint.FILENAME}: stage {i} has not been completed in "
            f"this run; completed: {done}")
    model = replay_hooks(setup.model, setup.stages[: i + 1], ck["starts"])
    q, theta = (ck["q"], ck["theta"]) if i == last else ck["starts"][i + 1]
    return model, np.array(q, np.float64), theta, i


def whole_state(setup: Setup, model: Model, q, theta, index: int):
    """(model, q, theta, stage) of the whole model at a solved state of stage ``index``:
    the solved ones when ``setup.whole`` is None, else the whole model at the lifted
    state with the whole's stage (its prescribed dofs on the whole)."""
    if setup.whole is None:
        return model, q, theta, setup.stages[index]
    model, q, theta = setup.whole.lift(model, q, theta)
    return model, np.asarray(q, np.float64), theta, setup.whole.stages[index]


def solved_model(setup: Setup) -> dict | None:
    """What a reduced setup solves (run.json's and summary.json's "solved"): its kind and
    its mesh's nodes, elements and unknowns; None for a setup that solves its whole."""
    if setup.whole is None:
        return None
    m = setup.model
    return {"model": setup.whole.solved, "nodes": int(m.mesh.n_nodes),
            "elements": int(m.mesh.n_elem), "dofs": int(m.n_dof)}


def stage_stability(model, q, theta, stage: Stage, options: NewtonOptions, k: int = 3) -> dict:
    """Whether a stage's end state is a stable equilibrium (eyefem.solve.stability: the k
    eigenvalues of the tangent nearest zero); an unstable one is said (log warning).
    Returns the record for summary.json's "stability"."""
    from eyefem.solve.errors import LinearSolveError
    from eyefem.solve.stability import StabilityError, stage_end

    held = np.zeros(model.n_dof, bool)
    held[stage.prescribed[0]] = True
    try:
        rec = stage_end(model, q, theta, held, stage.active, k, beta=options.beta,
                        backend=options.backend)
    except (StabilityError, LinearSolveError) as exc:  # the run goes on; the record says
        log.warning("stage '%s': its stability was not checked: %s", stage.name, exc)
        return {"stable": None, "error": str(exc)}
    share = rec["lowest_mode_rigid_share"]
    what = "" if share is None else f" (its mode {100 * share:.0f}% a rigid motion of the mesh)"
    if not rec["stable"]:
        log.warning("stage '%s' ended in an unstable equilibrium: the tangent's lowest "
                    "eigenvalue is %.3g N/mm%s. Newton converged to a saddle of the energy, "
                    "a state the tissue would leave, so the outcomes at the end of that "
                    "stage are not physical (eyefem stability shows the mode; "
                    "docs/outputs.md)", stage.name, rec["lowest_eigenvalue_N_per_mm"], what)
    else:
        log.info("stage '%s' ends in a stable equilibrium (lowest eigenvalue %.3g N/mm%s)",
                 stage.name, rec["lowest_eigenvalue_N_per_mm"], what)
    return rec


def run_setup(setup: Setup, out_dir: Path, options: NewtonOptions = NewtonOptions(), *,
              vtu: bool = True, plots: bool = True, key: str = "", resume: bool = False,
              xdmf: bool = False, stability: int = 0, force: bool = False,
              inputs: tuple[str, ...] = (), locked: bool = False) -> RunResult:
    """Solve a setup, writing outputs after each converged step (atomically).

    ``vtu`` writes the ParaView series ``<name>.pvd`` (vtu/*.vtu); ``xdmf`` the same
    frames of the mesh as ``<name>.xdmf`` (eyefem.io.output.XdmfSeriesWriter).

    After every completed stage a checkpoint is written to ``out_dir``; with
    ``resume=True`` the run continues after the last completed stage of the checkpoint
    (``key`` identifies the case, so a checkpoint of another case is refused).

    With ``stability`` = k > 0 the end state of every stage solved is checked for
    stability (:func:`stage_stability`, k eigenvalues) and summary.json gets
    "stability": {stage name: record}.
    """
    if locked:  # the caller claimed out_dir and holds its lock (:func:`claimed_folder`)
        out_dir, release = Path(out_dir), (lambda: None)
    else:
        out_dir = manifest.claim(Path(out_dir), force=force, inputs=inputs)
        release = manifest.acquire(out_dir)  # a second run into out_dir is refused
    since_ns = time.time_ns()
    rows: list[dict] = []
    writer = SeriesWriter(out_dir, setup.name)
    xwriter = XdmfSeriesWriter(out_dir, setup.name) if xdmf else None
    frames = SeriesGroup(([writer] if vtu else []) + ([xwriter] if xdmf else []))
    tic = time.perf_counter()
    case_hash = manifest.case_hash(key)
    key = checkpoint_key(setup, key)
    q0, theta0, completed = setup.q0, None, ()
    try:
        previous = manifest.read(out_dir)
        if resume:
            listed = (previous or {}).get("files") or {}
            changed = manifest.changed_files(  # what the resume reads: the checkpoint
                out_dir, previous, names={n for n in listed if n.startswith("checkpoint")})
            if changed:
                raise checkpoint.CheckpointError(
                    f"{out_dir}: {len(changed)} files of the interrupted run changed since it "
                    f"wrote them ({', '.join(changed[:3])}: sha256 differs from run.json or "
                    "missing); run without --resume to compute the case again")
            ck = _checked(checkpoint.load(out_dir, key), setup, out_dir)
            rows[:] = ck["rows"]
            writer.entries = list(ck["vtu_entries"])
            q0, theta0, completed = ck["q"], ck["theta"], ck["starts"]
            if xwriter is not None:
                xwriter.resume(until=ck["stage"] + 1)  # frame times: stage index + t
            for old in ("summary.json", "stability.json", "stability.vtu"):
                (out_dir / old).unlink(missing_ok=True)  # of the state before resuming
            log.info("resuming %s after stage %d ('%s') from %s", setup.name, ck["stage"] + 1,
                     setup.stages[ck["stage"]].name, out_dir / checkpoint.FILENAME)
        else:
            manifest.clear_outputs(out_dir, previous if manifest.is_eyefem_run(previous)
                                   else None)
            for old in (f"{setup.name}.xdmf", f"{setup.name}.h5"):  # an older run's XDMF
                (out_dir / old).unlink(missing_ok=True)
        written = setup.model if setup.whole is None else setup.whole.model
        mesh = written.mesh
        record = manifest.FileRecord(out_dir, since_ns,
                                     kept=(previous or {}).get("files") if resume else None)
        solved = solved_model(setup)
        run = manifest.write(out_dir, {
            "program": manifest.PROGRAM,
            "format": manifest.FORMAT, "code_version": manifest.code_version(),
            "case_hash": case_hash, "name": setup.name, "resumed": bool(resume),
            "mesh": {"nodes": mesh.n_nodes, "elements": mesh.n_elem,
                     "dofs": written.n_dof},
            **({"solved": solved} if solved else {}),
            "stages": [s.name for s in setup.stages], "status": "running",
            "started": manifest.now()})
    except BaseException:
        release()
        raise

    active = {s.name: s.active for s in setup.stages}
    progress = Progress(setup.stages, len(completed))  # stage k/n, step k/n, time left

    def on_step(rec, model, q, theta):
        row = {"stage": rec.stage, "step": rec.step, "t": rec.t, "iterations": rec.iterations,
               "residual_N": rec.residual,
               **{flag: int(rec.info.get(flag, False)) for flag in ACCEPTED_FLAGS.values()},
               "unbalanced_N": float(rec.info.get("unbalanced_N", 0.0))}
        row.update(setup.probe(model, q, theta))
        report = model.report(q, theta, active.get(rec.stage))
        row.update(report)
        rows.append(row)
        logged = [f"{k} {v:.9g}" if k.endswith("volume_mm3") else f"{k} {v:.5g}"
                  for k, v in report.items() if k.endswith(_LOGGED)]
        if logged:
            log.info("    %s", ", ".join(logged))
        write_csv(out_dir / f"{setup.name}_history.csv", rows)
        if frames.writers:
            write_step(frames, setup, rec.stage, rec.t, model, q, theta)
        progress.step(rec.stage, rec.step, rec.t)

    checks: dict[str, dict] = {}

    def on_stage_end(i, model, q, theta, starts):
        record.files()  # hash the stage's frames first: the checkpoint's own listing follows
        checkpoint.save(out_dir, key=key, stage=i, q=q, theta=theta, starts=starts, rows=rows,
                        vtu_entries=writer.entries)  # its hashes are then listed at once
        nonlocal run
        run = manifest.updated(out_dir, run, files=record.files())
        if stability:  # on the whole model (a mirror half's symmetric state included)
            checks[setup.stages[i].name] = stage_stability(
                *whole_state(setup, model, q, theta, i), options, stability)

    progress.start()
    try:
        sol = solve(setup.model, setup.stages, q0=q0, theta=theta0, options=options,
                    on_step=on_step, on_stage_end=on_stage_end, completed=completed)
        if not sol.history:  # resumed after the last stage: nothing left to solve
            setup.probe(sol.model, sol.q, sol.theta)
        summary = setup.finish(rows, out_dir, plots)
        run = manifest.updated(out_dir, run, status="complete", finished=manifest.now(),
                               files=record.files())
    except BaseException as exc:
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        try:  # the folder may be what failed
            manifest.updated(out_dir, run, status=status, finished=manifest.now(),
                             files=record.files(),
                             reason=f"{type(exc).__name__}: {exc}"[:2000])
        except OSError:
            exc.add_note(f"{out_dir / manifest.FILENAME} could not be updated either")
        raise
    finally:
        progress.close()
        if xwriter is not None:
            xwriter.close()
        release()
    summary["wall_s"] = time.perf_counter() - tic
    summary["newton_iterations"] = int(sum(r.iterations for r in sol.history))
    for flag, key in (("stalled", "steps_accepted_on_a_stall"),
                      ("contact_cycle", "steps_accepted_on_a_contact_cycle")):
        summary[key] = int(sum(r.info.get(flag, False) for r in sol.history))
    summary["unbalanced_steps"] = unbalanced_steps(rows)
    if stability:
        summary["stability"] = checks
    if solved:
        summary["solved"] = solved
    return RunResult(summary, rows, sol, out_dir, record)


def write_summary(res: RunResult, summary: dict) -> Path:
    """Write ``summary.json`` of a finished run and list it (with its sha256) in the run's
    manifest, so that a reuse checks it too. Returns its path; raises OSError."""
    from eyefem.io.output import write_text

    path = res.out_dir / "summary.json"
    write_text(path, json.dumps(summary, indent=2) + "\n")
    m = manifest.read(res.out_dir)
    if m is not None and res.record is not None:
        manifest.updated(res.out_dir, m, files=res.record.files())
    return path


@contextlib.contextmanager
def claimed_folder(out_dir: Path, force: bool = False, inputs: tuple[str, ...] = ()):
    """Claim ``out_dir`` (eyefem.io.manifest.claim) and hold its lock while the block runs,
    before the model is built; pass ``locked=True`` to :func:`run_setup` inside it."""
    out_dir = manifest.claim(Path(out_dir), force=force, inputs=inputs)
    with manifest.locked(out_dir):
        yield out_dir


def unbalanced_steps(rows: list[dict]) -> dict:
    """The steps of a run accepted without converging (on a stall or a cycling contact
    pairing): their count, the largest force left out of balance (N) and where (at most
    ten "stage step k (t = ...)"). Every outcome is reported from a converged state only
    when the count is 0."""
    bad = [r for r in rows if any(r.get(f) for f in ACCEPTED_FLAGS.values())]
    return {"count": len(bad),
            "largest_unbalanced_N": max((r.get("unbalanced_N", 0.0) for r in bad), default=0.0),
            "steps": [f"{r['stage']} step {r['step']} (t = {r['t']:.4g})" for r in bad[:10]]}
