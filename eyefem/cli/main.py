"""Command line: ``eyefem run CASE``, ``eyefem compare CASES``, ``eyefem verify-tangents``,
``eyefem cases``, ``eyefem describe PROBLEM``, ``eyefem new-case PROBLEM``,
``eyefem export-feb CASE -o model.feb``, ``eyefem import-feb model.feb``,
``eyefem sweep SWEEP.toml``, ``eyefem stability CASE``.

The entry point switches JAX to float64, keeps compiled kernels in a persistent cache
(``EYEFEM_JAX_CACHE``, default ``~/.cache/eyefem/jax``; ``off`` disables it) and sets up
logging (one line per load step); the library itself never prints.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import logging
import os
import sys
from pathlib import Path


def _setup(verbose: int, device: str = "cpu"):
    import jax

    from eyefem.solve.device import keep_compiled_by_default, select_device
    from eyefem.solve.heap import configure_heap

    jax.config.update("jax_enable_x64", True)
    keep_compiled_by_default()
    level = logging.WARNING if verbose < 0 else logging.DEBUG if verbose > 1 else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)-7s %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)
    logging.getLogger("jax").setLevel(logging.WARNING)
    configure_heap()  # after the logging: it may warn
    where = select_device(device)
    if device != "cpu":
        from eyefem.solve.linsolve import default_backend

        backend = default_backend()
        logging.getLogger("eyefem").info(
            "element kernels on %s; the factorisation: %s", where,
            "cuDSS on the GPU" if backend == "cudss" else f"{backend} on the host (cuDSS: "
            "pip install cupy-cuda13x nvidia-cudss-cu13)")


def _load_run_case(args, claim: bool = False):
    """(case, setup, output folder, release) of the arguments of ``eyefem run`` or ``eyefem
    stability`` (case, --out, --mesh, --materials), or an exit code after saying why.

    With ``claim`` the output folder is claimed (eyefem.io.manifest.claim: new, empty or an
    eyefem run's; ``--force`` adopts another) and locked before the model is built;
    ``release`` frees the lock (a no-op without ``claim``)."""
    from eyefem.api import with_material_preset
    from eyefem.catalog import problems, schemas, solver_defaults
    from eyefem.io import manifest
    from eyefem.io.casefile import CaseError, check_material_names, load_case, with_mesh

    try:
        case = load_case(args.case, schemas(), solver_defaults())
        out = Path(args.out or case.output["directory"])
        if args.mesh:
            case = with_mesh(case, args.mesh)
        if args.materials:  # a material preset (eyefem.eye.presets) instead of the case's
            case = with_material_preset(case, args.materials)
    except (CaseError, ValueError, KeyError) as exc:
        print(f"eyefem: {exc}", file=sys.stderr)
        return 2
    if getattr(args, "allow_include", None):  # read by eyefem.io.meshfile (and sweep workers)
        from eyefem.io.meshfile import ENV_ALLOW_INCLUDE

        os.environ[ENV_ALLOW_INCLUDE] = os.pathsep.join(
            [str(Path(d).resolve()) for d in args.allow_include]
            + [d for d in os.environ.get(ENV_ALLOW_INCLUDE, "").split(os.pathsep) if d])
    release = lambda: None  # noqa: E731
    try:
        if claim:  # before the model is built: a refused folder costs nothing
            release = _claim_and_lock(out, getattr(args, "force", False))
        setup = problems()[case.problem][1](case.parameters, case.materials)
        check_material_names(case, setup.model.mesh.materials)
        manifest.check_writable(out)  # before solving; a rejected case leaves no folder
        _say_where(case.path, out)
    except manifest.OutputError as exc:
        release()
        print(f"eyefem: {exc}", file=sys.stderr)
        return 4
    except CaseError as exc:
        release()
        print(f"eyefem: {exc}", file=sys.stderr)
        return 2
    except (ValueError, KeyError) as exc:  # the builder rejected a parameter or material
        release()
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"eyefem: {case.path} [parameters]/[materials]: {msg}", file=sys.stderr)
        return 2
    except BaseException:
        release()
        raise
    return case, setup, out, release


def _claim_and_lock(out: Path, force: bool):
    """Claim ``out`` (eyefem.io.manifest.claim) and take its lock; returns the function that
    releases it, and removes the folder again if the claim created it and nothing was
    written there (a case rejected afterwards leaves no folder behind)."""
    from eyefem.io import manifest

    created = not os.path.lexists(out)
    manifest.claim(out, force=force)
    unlock = manifest.acquire(out)

    def release():
        unlock()
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()  # only if empty

    return release


def _failed_record(out: Path) -> str:
    """What the run's record says after a failure, as the messages quote it: its status,
    or that no run.json could be written."""
    from eyefem.io import manifest

    m = manifest.read(out)
    if m is None or m.get("status") in (None, "running"):
        return f"no run record could be written in {out}"
    return f"run.json says '{m.get('status')}'"


def cmd_run(args) -> int:
    from eyefem.io import manifest
    from eyefem.io.checkpoint import CheckpointError
    from eyefem.run.runner import run_setup, write_summary
    from eyefem.solve.solver import ConvergenceError

    loaded = _load_run_case(args, claim=True)
    if isinstance(loaded, int):
        return loaded
    case, setup, out, release = loaded
    logging.getLogger(__name__).info("case %s (%s): %d elements, %d dofs -> %s", case.path,
                                     case.problem, setup.model.mesh.n_elem, setup.model.n_dof, out)
    try:
        res = run_setup(setup, out, case.solver, vtu=case.output["vtu"] and not args.no_vtu,
                        xdmf=case.output["xdmf"] or args.xdmf,
                        plots=case.output["plots"], resume=args.resume,
                        stability=3 if args.stability else 0, locked=True,
                        key=manifest.case_key(case.problem, case.parameters, case.materials,
                                              case.solver))
        summary = {"case": str(case.path), "title": case.title, **res.summary}
        write_summary(res, summary)
    except ConvergenceError as exc:
        print(f"eyefem: {exc}\nOutputs of the converged steps are in {out}; after fixing the "
              "cause, --resume continues after the last completed stage", file=sys.stderr)
        return 3
    except CheckpointError as exc:
        print(f"eyefem: {exc}", file=sys.stderr)
        return 2
    except manifest.OutputError as exc:
        print(f"eyefem: {exc}", file=sys.stderr)
        return 4
    except KeyboardInterrupt:
        print(f"eyefem: interrupted; {out} holds the converged steps ({_failed_record(out)}); "
              "--resume continues after the last completed stage", file=sys.stderr)
        return 130
    except OSError as exc:
        print(f"eyefem: cannot write the results in {out}: {exc}; the run stopped "
              f"({_failed_record(out)}); free space or fix the folder, then run again (or "
              "--resume)", file=sys.stderr)
        return 4
    finally:
        release()
    print(f"\n{case.title}")
    for k, v in summary.items():
        if k not in ("case", "title", "mesh_error"):
            print(f"  {k:<32} {v:.6g}" if isinstance(v, float) else f"  {k:<32} {v}")
    if isinstance(summary.get("mesh_error"), dict):
        from eyefem.eye.mesh_error import quote_lines

        for line in quote_lines(summary["mesh_error"]):
            print(f"  {line}")
    print(f"  results in {out}/")
    return 0


def cmd_stability(args) -> int:
    """The eigenvalues of the constrained tangent nearest zero at the end of a completed
    stage of a run (eyefem.solve.stability): stability.json and stability.vtu."""
    import numpy as np

    from eyefem.io import manifest
    from eyefem.io.checkpoint import CheckpointError
    from eyefem.io.output import write_text, write_vtu
    from eyefem.run.runner import completed_state, whole_state
    from eyefem.solve.errors import LinearSolveError
    from eyefem.solve.stability import (
        StabilityError,
        lowest_modes,
        rigid_motions,
        rigid_shares,
    )

    loaded = _load_run_case(args)
    if isinstance(loaded, int):
        return loaded
    case, setup, out, _ = loaded
    names = [s.name for s in setup.stages]
    index = None
    if args.stage is not None:
        if args.stage not in names:
            print(f"eyefem stability: {case.path} has no stage '{args.stage}'; its stages: "
                  f"{', '.join(names)}", file=sys.stderr)
            return 2
        index = names.index(args.stage)
    key = manifest.case_key(case.problem, case.parameters, case.materials, case.solver)
    again = (f"eyefem run {case.path} --out {out}, with the same --mesh and --materials")
    if not (out / "checkpoint.json").exists():
        print(f"eyefem stability: {out} holds no run of this case (no checkpoint.json): run "
              f"the case first ({again})", file=sys.stderr)
        return 2
    try:
        model, q, theta, i = completed_state(setup, out, key, index)
    except CheckpointError as exc:
        print(f"eyefem stability: {exc}; it reads the run of this case ({again})",
              file=sys.stderr)
        return 2
    # the whole model at the lifted state of a mirror half (modes that break the symmetry)
    model, q, theta, stage = whole_state(setup, model, q, theta, i)
    held = np.zeros(model.n_dof, bool)
    held[stage.prescribed[0]] = True
    logging.getLogger(__name__).info(
        "the %d eigenvalues nearest zero of the tangent at the end of stage %d '%s' (%d free "
        "dofs)", args.modes, i + 1, stage.name, int((~held).sum() - len(model.multiplier_dofs)))
    n = model.mesh.n_nodes
    rigid = rigid_motions(model, q)
    try:
        modes = lowest_modes(model, q, theta, held, stage.active, k=args.modes,
                             beta=case.solver.beta, backend=case.solver.backend,
                             exclude=rigid.T if args.deformation else None)
    except (StabilityError, LinearSolveError) as exc:
        print(f"eyefem stability: {exc}", file=sys.stderr)
        return 3
    shapes = modes.shapes[:, : 3 * n].reshape(len(modes.values), n, 3)
    rows = [{"mode": j + 1, "eigenvalue_N_per_mm": float(mu), "relative_residual": float(res),
             "rigid_share": float(share)}
            for j, (mu, res, share) in enumerate(zip(modes.values, modes.residuals,
                                                     rigid_shares(modes, rigid, held)))]
    if "eye/outer" in model.mesh.node_sets:  # the surgical eye: the modes' wave numbers
        from eyefem.eye.outcomes import azimuthal_shares

        for row, u in zip(rows, shapes):
            shares = azimuthal_shares(model.mesh, u)
            row["azimuthal_wave_number"] = int(np.argmax(shares[:-1]))
            row["azimuthal_shares"] = [round(float(v), 4) for v in shares]
    result = {"case": str(case.path), "title": case.title, "stage": stage.name,
              "stage_index": i, "stable": modes.stable, "modes": rows,
              "rigid_motions_excluded": bool(args.deformation),
              "metric": "Euclidean norm of the free nodal displacements (N/mm)"}
    peak = np.maximum(np.linalg.norm(shapes, axis=2).max(axis=1), 1e-300)
    point = {"displacement": np.asarray(q[: 3 * n]).reshape(n, 3),
             **{f"mode_{j + 1}": u / p for j, (u, p) in enumerate(zip(shapes, peak))}}
    write_vtu(out / "stability.vtu", model.mesh.nodes, model.mesh.hexes, point,
              {"material": model.mesh.material_ids.astype(np.int32)},
              {"eigenvalue_N_per_mm": modes.values, "stage": i})
    write_text(out / "stability.json", json.dumps(result, indent=2) + "\n")
    print(f"\n{case.title}: end of stage '{stage.name}', "
          f"{'stable' if modes.stable else 'UNSTABLE (a negative eigenvalue)'}")
    for row in rows:
        wave = (f"  azimuthal wave number {row['azimuthal_wave_number']} "
                f"({100 * max(row['azimuthal_shares'][:-1]):.0f}%)"
                if "azimuthal_wave_number" in row else "")
        print(f"  mode {row['mode']:2d}  {row['eigenvalue_N_per_mm']:+.6e} N/mm  residual "
              f"{row['relative_residual']:.1e}  rigid {100 * row['rigid_share']:3.0f}%{wave}")
    print(f"  modes in {out / 'stability.vtu'} (mode_k, largest nodal value 1), "
          f"table in {out / 'stability.json'}")
    return 0


def _say_where(case_path: Path, out: Path):
    """Log the output folder, with a warning when it lies outside the current folder and
    the case's folder (an --out with '..')."""
    where = out.resolve()
    homes = (Path.cwd().resolve(), Path(case_path).resolve().parent)
    if not any(where.is_relative_to(h) for h in homes):
        logging.getLogger(__name__).warning("writing results outside the current and the "
                                            "case's folder: %s", where)


def cmd_compare(args) -> int:
    from eyefem.cli.compare import compare
    from eyefem.io.casefile import CaseError
    from eyefem.io.checkpoint import CheckpointError
    from eyefem.solve.solver import ConvergenceError

    try:
        summaries = compare(args.cases, Path(args.out), mesh=args.mesh, reuse=args.reuse)
    except (CaseError, ValueError, CheckpointError, ConvergenceError) as exc:
        print(f"eyefem: {exc}", file=sys.stderr)
        return 2 if not isinstance(exc, ConvergenceError) else 3
    print(Path(args.out, "comparison.md").read_text())
    print(f"results in {args.out}/")
    return 0 if summaries else 2


def cmd_verify(args) -> int:
    from eyefem.verify.tangents import format_table, verify_tangents

    checks = verify_tangents(seed=args.seed)
    print(format_table(checks))
    return 0 if all(c.passed for c in checks) else 1


def cmd_cases(args) -> int:
    from eyefem.catalog import problems

    PROBLEMS = problems()  # noqa: N806

    root = Path(args.dir)
    for f in sorted(root.rglob("*.toml")):
        print(f)
    print("\nproblems:", ", ".join(sorted(PROBLEMS)))
    return 0


def _known_problem(name: str):
    """(fields, builder) of the problem ``name``, or None after printing the known ones."""
    from eyefem.catalog import problems

    known = problems()
    if name not in known:
        print(f"eyefem: unknown problem '{name}'; known: {', '.join(sorted(known))}",
              file=sys.stderr)
        return None
    return known[name]


def cmd_describe(args) -> int:
    from eyefem.io.casefile import describe

    found = _known_problem(args.problem)
    if found is None:
        return 2
    fields, builder = found
    print(f"{args.problem}: {(builder.__doc__ or '').strip().splitlines()[0]}\n[parameters]")
    print(describe(fields, first=getattr(builder, "first", ()),
                   advanced=getattr(builder, "advanced", ())))
    return 0


def cmd_new_case(args) -> int:
    from eyefem.cli.dialogue import new_case
    from eyefem.io.casefile import CaseError

    found = _known_problem(args.problem)
    if found is None:
        return 2
    preset = {}
    for item in args.set or []:
        if "=" not in item:
            print(f"eyefem: --set '{item}': expected name=value", file=sys.stderr)
            return 2
        k, v = item.split("=", 1)
        preset[k.strip()] = v
    try:
        fields, build = found
        new_case(args.problem, fields, Path(args.output), preset=preset,
                 accept_defaults=args.yes, title=args.title or "",
                 check=getattr(build, "check", None), force=args.force,
                 questions=getattr(build, "questions", None), ask_all=args.all,
                 solver_settings=getattr(build, "solver_settings", None))
    except CaseError as exc:
        print(f"eyefem: {exc}", file=sys.stderr)
        return 2
    except EOFError:
        print(f"eyefem new-case: no answer (end of input); nothing written to {args.output}; "
              "give the values with --set NAME=VALUE and --yes", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"eyefem new-case: interrupted; nothing written to {args.output}",
              file=sys.stderr)
        return 130
    return 0


def cmd_export_feb(args) -> int:
    from eyefem.catalog import problems, schemas, solver_defaults
    from eyefem.io.casefile import CaseError, check_material_names, load_case, with_mesh
    from eyefem.io.febio import write_feb

    try:
        case = load_case(args.case, schemas(), solver_defaults())
        if args.mesh:
            case = with_mesh(case, args.mesh)
        setup = problems()[case.problem][1](case.parameters, case.materials)
        check_material_names(case, setup.model.mesh.materials)
        skipped = write_feb(setup, Path(args.output))
    except OSError as exc:
        print(f"eyefem export-feb: cannot write {args.output}: {exc}", file=sys.stderr)
        return 4
    except (CaseError, ValueError, KeyError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"eyefem export-feb: {msg}", file=sys.stderr)
        return 2
    mesh = (setup.whole or setup).model.mesh  # a mirror half is exported whole
    print(f"wrote {args.output}: FEBio 4 deck of '{setup.name}', {len(setup.stages)} stage(s) "
          f"as steps ({mesh.n_nodes} mesh nodes, {mesh.n_elem} elements); what FEBio 4.11 "
          "gives for it: docs/febio.md")
    for w in skipped:
        print(f"  not exported or approximated: {w}")
    return 0


def cmd_import_feb(args) -> int:
    from eyefem.io import manifest
    from eyefem.io.febio_read import feb_setup
    from eyefem.run.runner import run_setup, write_summary
    from eyefem.solve.solver import ConvergenceError

    try:
        setup = feb_setup(args.deck)
    except OSError as exc:
        print(f"eyefem import-feb: cannot read {args.deck}: {exc}", file=sys.stderr)
        return 4
    except ValueError as exc:
        print(f"eyefem import-feb: {exc}", file=sys.stderr)
        return 2
    out = Path(args.output or Path("results") / Path(args.deck).stem)
    try:  # the case hash of a deck: its bytes (an edited deck is another case)
        key = json.dumps({"feb_sha256": hashlib.sha256(Path(args.deck).read_bytes()).hexdigest()})
        res = run_setup(setup, out, vtu=not args.no_vtu, plots=False, key=key,
                        force=args.force)
        summary = {"deck": str(args.deck), **res.summary}
        write_summary(res, summary)
    except ConvergenceError as exc:
        print(f"eyefem import-feb: {exc}\nOutputs of the converged steps are in {out}",
              file=sys.stderr)
        return 3
    except (manifest.OutputError, OSError) as exc:
        print(f"eyefem import-feb: cannot write the results in {out}: {exc}", file=sys.stderr)
        return 4
    print(f"\n{args.deck} (FEBio 4 deck, solved by eyefem)")
    for k, v in summary.items():
        if k != "deck":
            print(f"  {k:<32} {v:.6g}" if isinstance(v, float) else f"  {k:<32} {v}")
    print(f"  results in {out}/")
    return 0


def cmd_sweep(args) -> int:
    """``eyefem sweep SWEEP.toml``: every run of a sweep file as a Dask task (eyefem.study)."""
    from eyefem.study.spec import SweepError, load_sweep

    try:
        sweep = load_sweep(args.sweep)
    except SweepError as exc:
        print(f"eyefem: {exc}", file=sys.stderr)
        return 2
    from eyefem.study.sweep import (
        check_dependencies,
        format_best,
        quiet_dask_logs,
        run_sweep,
    )

    try:
        check_dependencies()
    except ImportError as exc:
        print(f"eyefem: {exc}", file=sys.stderr)
        return 2
    quiet_dask_logs()
    if args.scheduler:  # an address Dask can dial, before any run is planned
        from distributed.comm.addressing import parse_address, parse_host_port
        from distributed.comm.registry import get_backend

        try:
            scheme, where = parse_address(args.scheduler)
            get_backend(scheme)
            if scheme in ("tcp", "tls", "ws", "wss"):
                parse_host_port(where)
        except ValueError as exc:
            print(f"eyefem sweep: --scheduler '{args.scheduler}' is not a Dask scheduler "
                  f"address ({exc}); give one like tcp://HOST:8786 (the address "
                  "'dask scheduler' prints), or leave --scheduler out for a local cluster",
                  file=sys.stderr)
            return 2
    if args.workers is not None and args.workers < 1:
        print(f"eyefem sweep: --workers {args.workers}; give at least 1", file=sys.stderr)
        return 2
    if args.uncertainty:  # refuse an input without a derivative before the runs, not after
        from eyefem.study.uncertainty import sweep_distributions

        try:
            sweep_distributions(sweep)
        except ValueError as exc:
            print(f"eyefem sweep --uncertainty: {exc}", file=sys.stderr)
            return 2
    from eyefem.io import manifest

    def progress(line: str) -> None:  # -q: silent; else a line at most every few seconds
        if args.verbose >= 0:
            print(line, file=sys.stderr, flush=True)

    try:
        res = run_sweep(sweep, out=args.out, scheduler=args.scheduler, workers=args.workers,
                        progress=progress, device=args.device)
    except manifest.OutputError as exc:
        print(f"eyefem: {exc}", file=sys.stderr)
        return 4
    except OSError as exc:
        where = f"the Dask scheduler {args.scheduler}" if args.scheduler else "the output folder"
        print(f"eyefem sweep: {exc}; check {where}", file=sys.stderr)
        return 4
    except KeyboardInterrupt:
        out = args.out or sweep.output
        print(f"eyefem sweep: interrupted; {out}/results.csv holds the runs that finished; "
              "the same command continues (completed runs are skipped)", file=sys.stderr)
        return 130
    from eyefem.study.plots import plot_sweep

    pngs = plot_sweep(res.rows, sweep.varied, res.out_dir)
    if args.uncertainty:
        from eyefem.solve.solver import ConvergenceError
        from eyefem.study.uncertainty import report

        try:
            print(report(sweep, res.rows, res.out_dir))
        except ValueError as exc:
            print(f"eyefem sweep --uncertainty: {exc}", file=sys.stderr)
            return 2
        except ConvergenceError as exc:
            print(f"eyefem sweep --uncertainty: the first-order solves did not converge: "
                  f"{str(exc).splitlines()[0]}; the sweep's table is complete in "
                  f"{res.out_dir}", file=sys.stderr)
            return 3
    print(f"\n{sweep.title}: {len(res.rows)} runs ({res.computed} computed now, {res.skipped} "
          f"complete before), {res.failed} failed, {res.wall_s:.1f} s")
    print(format_best(sweep, res.rows))
    print(f"  table: {res.out_dir}/results.parquet, results.csv; runs in {res.out_dir}/runs/"
          + (f"; plots: {', '.join(p.name for p in pngs)}" if pngs else ""))
    if res.failed:
        print(f"eyefem sweep: {res.failed} of {len(res.rows)} runs failed or did not converge; "
              f"their messages are in {res.out_dir}/results.csv (column 'error')", file=sys.stderr)
        return 3
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="eyefem", description=__doc__.splitlines()[0])
    ap.add_argument("-v", "--verbose", action="count", default=1)
    ap.add_argument("-q", "--quiet", action="store_const", const=-1, dest="verbose")
    ap.add_argument("--device", choices=("cpu", "gpu"), default="cpu",
                    help="where the element kernels run (default cpu; gpu needs a CUDA "
                    "jaxlib); with gpu the factorisation runs there too where cuDSS is "
                    "installed (CuPy and nvidia-cudss-cu13), else on the host")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("run", help="run a case file")
    p.add_argument("case")
    p.add_argument("--out", help="output directory (default from the case file)")
    p.add_argument("--no-vtu", action="store_true", help="skip the VTU series")
    p.add_argument("--xdmf", action="store_true", help="also write the series as XDMF "
                   "(<name>.xdmf; HDF5 arrays when h5py is installed)")
    p.add_argument("--resume", action="store_true",
                   help="continue after the last completed stage (checkpoint in the output dir)")
    p.add_argument("--allow-include", metavar="DIR", action="append", default=[],
                   help="a folder an Abaqus *INCLUDE of the case's mesh may read besides the "
                   "including file's own (repeatable; also EYEFEM_ALLOW_INCLUDE)")
    p.add_argument("--force", action="store_true",
                   help="adopt an output folder that no eyefem run wrote (its files of "
                   "eyefem's names are listed, then removed); without it such a folder is "
                   "refused")
    p.add_argument("--stability", action="store_true",
                   help="check that every stage ends in a stable equilibrium (the tangent's "
                   "3 eigenvalues nearest zero; summary.json 'stability'): each check costs "
                   "about 5-20 Newton iterations (coarse to medium eye)")
    p.add_argument("--mesh", help="override the case's eye mesh level (coarse, half, medium, "
                   "default, fine, finer, finest, ultrafine; graded_half, graded, graded_fine, or "
                   "graded<N> with N elements per patch edge, 12-64: finer toward the band "
                   "zone; gradedc<N>: also finer in the cornea; the suffix x2: 8 wall layers)")
    p.add_argument("--materials", metavar="PRESET", choices=("seed", "physiological"),
                   help="tissue constants preset (eyefem.eye.presets): replaces the case's "
                   "materials_preset and its own [materials] tables of the eye's tissues")
    p.set_defaults(fn=cmd_run)
    p = sub.add_parser("stability", help="the eigenvalues of the tangent nearest zero at "
                       "the end of a completed stage of a run (is the state stable?)")
    p.add_argument("case")
    p.add_argument("--out", help="the run's output directory (default from the case file)")
    p.add_argument("--mesh", help="the --mesh the run was given")
    p.add_argument("--materials", metavar="PRESET", choices=("seed", "physiological"),
                   help="the --materials the run was given")
    p.add_argument("--stage", help="stage name (default: the last completed stage)")
    p.add_argument("--modes", type=int, default=6, help="how many eigenvalues (default 6)")
    p.add_argument("--deformation", action="store_true", help="modes orthogonal to the rigid "
                   "motions of the whole mesh (a body held only softly, such as the globe in "
                   "its orbit, otherwise fills the lowest modes with its rigid motions)")
    p.set_defaults(fn=cmd_stability)
    p = sub.add_parser("compare", help="run several cases and tabulate/plot their outcomes")
    p.add_argument("cases", nargs="+", help="case files")
    p.add_argument("--mesh", help="override the mesh level of every case")
    p.add_argument("--out", default="results/compare", help="output root (one folder per case)")
    p.add_argument("--reuse", action="store_true",
                   help="skip cases whose folder holds a complete run of the same case (run.json)")
    p.set_defaults(fn=cmd_compare)
    p = sub.add_parser("verify-tangents", help="autodiff vs hand-coded vs finite-difference tangents")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(fn=cmd_verify)
    p = sub.add_parser("cases", help="list case files and problems")
    p.add_argument("dir", nargs="?", default="cases")
    p.set_defaults(fn=cmd_cases)
    p = sub.add_parser("describe", help="document a problem's parameters")
    p.add_argument("problem")
    p.set_defaults(fn=cmd_describe)
    p = sub.add_parser("new-case", help="write a case file by answering questions (or --set)")
    p.add_argument("problem", help="problem name (see 'eyefem cases')")
    p.add_argument("-o", "--output", required=True, help="case file to write")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help="answer without asking")
    p.add_argument("--yes", action="store_true", help="accept the defaults of the rest")
    p.add_argument("--title", help="case title")
    p.add_argument("--force", action="store_true", help="overwrite an existing case file")
    p.add_argument("--all", action="store_true", help="ask every field, the advanced ones and "
                   "those that do not apply to the chosen buckle too")
    p.set_defaults(fn=cmd_new_case)
    p = sub.add_parser("export-feb", help="write a case's stages as an FEBio 4 deck")
    p.add_argument("case", help="case file")
    p.add_argument("-o", "--output", required=True, help="the .feb file to write")
    p.add_argument("--mesh", help="override the case's mesh level (surgery: coarse, medium, "
                   "default)")
    p.set_defaults(fn=cmd_export_feb)
    p = sub.add_parser("import-feb", help="solve an FEBio 4 deck (hex8 Mooney-Rivlin, "
                       "displacements and pressures) with eyefem")
    p.add_argument("deck", help="the .feb file")
    p.add_argument("-o", "--output", help="output directory (default results/<deck name>)")
    p.add_argument("--no-vtu", action="store_true", help="skip the VTU series")
    p.add_argument("--force", action="store_true",
                   help="adopt an output folder that no eyefem run wrote (as eyefem run)")
    p.set_defaults(fn=cmd_import_feb)
    p = sub.add_parser("sweep", help="run a parameter sweep (sweep file) on a Dask cluster")
    p.add_argument("sweep", help="sweep file (docs/sweep.md)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="an existing Dask scheduler "
                   "(tcp://host:8786); default: a local cluster")
    p.add_argument("--workers", type=int, help="worker processes of the local cluster "
                   "(default: the cores)")
    p.add_argument("--out", help="output folder (default from the sweep file)")
    p.add_argument("--uncertainty", action="store_true", help="also propagate the sampled "
                   "distributions to first order (adjoint gradients; central differences, "
                   "two more solves each, for inputs without one, such as biometry) and "
                   "compare")
    p.set_defaults(fn=cmd_sweep)
    args = ap.parse_args(argv)
    from eyefem.solve.device import DeviceError

    try:
        _setup(args.verbose, args.device)
    except DeviceError as exc:
        print(f"eyefem {args.cmd}: {exc}", file=sys.stderr)
        return 2
    import signal

    def terminated(signum, frame):  # SIGTERM as Ctrl-C: status 'interrupted', lock freed
        raise KeyboardInterrupt(f"signal {signum}")

    try:
        previous = signal.signal(signal.SIGTERM, terminated)
    except ValueError:  # not the main thread (a caller's worker): its own handling stays
        previous = None
    try:
        return args.fn(args)
    except KeyboardInterrupt:
        print(f"eyefem {args.cmd}: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        print(f"eyefem {args.cmd}: {exc}", file=sys.stderr)
        return 4
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
