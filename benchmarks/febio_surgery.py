"""A surgical case exported to FEBio, run in FEBio, and compared with eyefem on the same mesh.

    python benchmarks/febio_surgery.py --febio PATH/TO/febio4 \
        [--case cases/surgery/case1.toml] [--mesh coarse] [--out results/febio_case1] \
        [--record benchmarks/febio_surgery.json]

It writes the case's deck (`eyefem export-feb`, the whole eye), runs FEBio on it (2 OpenMP
threads unless OMP_NUM_THREADS is set), reads the nodes' displacements that the deck's
<logfile> asks for at the end of each step, and measures on FEBio's states the outcomes
eyefem measures on its own (eyefem.eye.outcomes: the axial length and the anterior chamber
depth from the pressurised eye, the buckle's indentation, the IOP from the cavity's volume
with the deck's volume constraint: p = p_iop + |eps| (V_0 - V), V_0 the volume at the step's
start). eyefem's figures are those of `eyefem run` of the same case on the same mesh
(stages.csv), and for the first step also eyefem's solve of the deck itself read back (the
same model as FEBio's, the export's omissions included). The table goes to stdout;
``--record`` writes both sides, FEBio's version, command and wall time as JSON
(docs/febio.md quotes it).

The deck is not eyefem's model exactly: what it leaves out or approximates is printed
(the sutures and the orbit's springs are not written, so only the stages before the
sutures are tied are compared; see docs/febio.md, "What is exported").
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def read_node_log(path: Path) -> dict[float, np.ndarray]:
    """FEBio's <logfile> node_data blocks: {time: (n_nodes, k) values by node id order}.

    The blocks read ``*Step = ..``, ``*Time = t``, ``*Data = ux;uy;uz`` and one line per
    node, ``id<delim>v1<delim>v2...`` (delimiter ',' or blanks)."""
    blocks: dict[float, np.ndarray] = {}
    t, rows = None, []

    def flush():
        if t is not None and rows:
            a = np.array(rows)
            blocks[t] = a[np.argsort(a[:, 0]), 1:]
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        s = line.strip()
        if s.startswith("*Time"):
            flush()
            t, rows = float(s.split("=")[1]), []
        elif s and not s.startswith("*") and t is not None:  # a header before the blocks
            try:
                rows.append([float(v) for v in s.replace(",", " ").split()])
            except ValueError:
                raise ValueError(f"{path}:{number}: '{s[:60]}' is not a node's values "
                                 "(id, ux, uy, uz)") from None
    flush()
    if not blocks:
        raise ValueError(f"{path}: no node data blocks (*Time = ...) in FEBio's log")
    return blocks


def febio_outcomes(setup, blocks: dict[float, np.ndarray], eps: float) -> list[dict]:
    """eyefem's outcome measures on FEBio's states at the end of each step (t = 1, 2, ...):
    IOP (mmHg), indentation (mm), axial length change and anterior chamber depth change
    from the end of step 1 (mm). ``eps``: the deck's volume-constraint penalty (MPa/mm^3,
    < 0), active from step 2 on; the cavity's volume from eyefem's FluidCavity."""
    from eyefem.eye.outcomes import eye_optics, indentation, outcome_nodes
    from eyefem.fem.units import MMHG

    model, parts = setup.model, setup.parts
    X = model.mesh.nodes
    n = len(X)
    nodes = outcome_nodes(parts)
    cav = model.term("cavity")
    theta = model.theta0()
    p_iop = float(parts.p["iop_mmhg"])
    rows, preop, v0 = [], None, None
    for k, name in enumerate(s.name for s in setup.stages):
        t = float(k + 1)
        if t not in blocks:
            break
        q = np.zeros(model.n_dof)
        q[: 3 * n] = blocks[t][:n, :3].ravel()
        optics = {key: float(v) for key, v in eye_optics(X, q, nodes).items()}
        volume = float(cav.pressures(q, theta["cavity"])[1][0])
        if preop is None:
            preop, v0 = optics, volume
        rows.append({"stage": name,
                     "axial_length_mm": optics["axial_length_mm"],
                     "anterior_chamber_depth_mm": optics["anterior_chamber_depth_mm"],
                     "volume_mm3": volume,
                     "iop_mmhg": p_iop + abs(eps) * (v0 - volume) / MMHG,
                     "indentation_mm": float(indentation(X, q, nodes)),
                     "axial_length_change_mm": optics["axial_length_mm"]
                     - preop["axial_length_mm"],
                     "anterior_chamber_depth_change_mm": optics["anterior_chamber_depth_mm"]
                     - preop["anterior_chamber_depth_mm"],
                     "volume_change_mm3": volume - v0})
    return rows


def febio_version(log_text: str) -> str:
    """FEBio's version from its log's banner ("version 4.11.0"), or 'unknown'."""
    for line in log_text.splitlines():
        if line.strip().lower().startswith("version"):
            return "FEBio " + line.split()[-1]
    return "unknown"


def eyefem_pressurised(setup) -> dict:
    """eyefem's own first stage (the pressurised eye) solved on the whole model, measured
    as :func:`febio_outcomes` measures FEBio's (its row, with the unloaded eye's under
    "unloaded")."""
    from eyefem.solve.solver import solve

    sol = solve(setup.model, setup.stages[:1], q0=setup.q0)
    n = setup.model.mesh.n_nodes
    rows = febio_outcomes(setup, {1.0: sol.q[: 3 * n].reshape(-1, 3),
                                  2.0: np.zeros((n, 3))}, -1.0)
    return {"pressurised": rows[0], "unloaded": rows[1]}


def eyefem_on_the_deck(setup, deck: Path) -> dict:
    """eyefem's solve of the deck's first step as eyefem reads it back (FEBio's model: the
    same springs, segments and omissions), measured as :func:`febio_outcomes` measures."""
    from eyefem.io.febio_read import build_stages, read_feb
    from eyefem.solve.solver import solve

    mesh, materials, loads = read_feb(deck)
    model, stages = build_stages(mesh, materials, loads)
    n = setup.model.mesh.n_nodes
    u = np.asarray(solve(model, stages[:1]).q)[: 3 * mesh.n_nodes].reshape(-1, 3)[:n]
    return febio_outcomes(setup, {1.0: u, 2.0: np.zeros((n, 3))}, -1.0)[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--febio", default=os.environ.get("FEBIO", "febio4"),
                    help="FEBio 4's executable (default: $FEBIO or febio4 on PATH)")
    ap.add_argument("--case", default=str(ROOT / "cases/surgery/case1.toml"))
    ap.add_argument("--mesh", default="coarse")
    ap.add_argument("--out", default="results/febio_surgery")
    ap.add_argument("--record", help="write both sides' outcomes as JSON to this file")
    ap.add_argument("--eyefem-run", help="an `eyefem run` folder of the same case and mesh "
                    "(default: run it into OUT/eyefem)")
    args = ap.parse_args(argv)

    import jax
    jax.config.update("jax_enable_x64", True)
    from eyefem.catalog import problems, schemas
    from eyefem.io.casefile import load_case
    from eyefem.io.febio import write_feb

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    case = load_case(Path(args.case), schemas())
    case.parameters.update(mesh=args.mesh, symmetry="none")
    setup = problems()[case.problem][1](case.parameters, case.materials)
    deck = out / f"{Path(args.case).stem}.feb"
    omissions = write_feb(setup, deck)
    pen = ET.parse(deck).getroot().find(".//constraint[@type='volume']/penalty")
    if pen is None:
        print(f"{deck}: no volume constraint (a case without a closed cavity)", file=sys.stderr)
        return 2
    eps = float(pen.text)

    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "2")}
    cmd = [args.febio, "-i", deck.name, "-silent"]
    t0 = time.perf_counter()
    try:
        run = subprocess.run(cmd, cwd=out, env=env, capture_output=True, text=True,
                             stdin=subprocess.DEVNULL)
    except OSError as exc:
        print(f"cannot run FEBio '{args.febio}': {exc}; give --febio PATH", file=sys.stderr)
        return 4
    wall = time.perf_counter() - t0
    (out / "febio_stdout.txt").write_text(run.stdout + run.stderr)
    log_file = out / f"{deck.stem}_displacement.txt"
    if not log_file.exists():
        print(f"FEBio wrote no {log_file.name} (exit {run.returncode}); its output: "
              f"{out / 'febio_stdout.txt'}", file=sys.stderr)
        return 3
    febio_log = out / f"{deck.stem}.log"
    log_text = febio_log.read_text(errors="replace") if febio_log.exists() else ""
    normal = "N O R M A L   T E R M I N A T I O N" in log_text
    febio = febio_outcomes(setup, read_node_log(log_file), eps)
    # the pressurised eye (step 1) against eyefem's, measured alike, changes from unloaded
    ours1 = eyefem_pressurised(setup)
    base = ours1["unloaded"]
    first = []
    same = eyefem_on_the_deck(setup, deck)
    for key in ("axial_length_mm", "anterior_chamber_depth_mm", "volume_mm3"):
        f_d, e_d = febio[0][key] - base[key], ours1["pressurised"][key] - base[key]
        first.append({"stage": febio[0]["stage"], "outcome": f"{key} change from unloaded",
                      "febio": f_d, "eyefem": e_d})
        first.append({"stage": febio[0]["stage"], "outcome": f"{key} (the deck in eyefem)",
                      "febio": f_d, "eyefem": same[key] - base[key]})

    run_dir = Path(args.eyefem_run) if args.eyefem_run else out / "eyefem"
    if not args.eyefem_run:
        subprocess.run([sys.executable, "-m", "eyefem.cli.main", "-q", "run", args.case,
                        "--mesh", args.mesh, "--no-vtu", "--out", str(run_dir)], check=True)
    with open(run_dir / "stages.csv") as fh:
        ours = list(csv.DictReader(fh))
    keys = ("iop_mmhg", "indentation_mm", "axial_length_change_mm",
            "anterior_chamber_depth_change_mm")
    print(f"FEBio: {'normal termination' if normal else 'NOT normal termination'} "
          f"(exit {run.returncode}), {wall:.1f} s, {len(febio)} step(s) with results")
    print(f"{'stage':<11} {'outcome':<34} {'FEBio':>10} {'eyefem':>10} {'diff':>9}")
    table = []
    for row in first:
        print(f"{row['stage']:<11} {row['outcome']:<34} {row['febio']:>10.4f} "
              f"{row['eyefem']:>10.4f} {row['febio'] - row['eyefem']:>+9.4f}")
        table.append(row)
    for f_row in febio[1:]:
        e_row = next((r for r in ours if r["stage"] == f_row["stage"]), None)
        for key in keys:
            e = float(e_row[key]) if e_row else float("nan")
            print(f"{f_row['stage']:<11} {key:<34} {f_row[key]:>10.4f} {e:>10.4f} "
                  f"{f_row[key] - e:>+9.4f}")
            table.append({"stage": f_row["stage"], "outcome": key, "febio": f_row[key],
                          "eyefem": e})
    if args.record:
        Path(args.record).write_text(json.dumps({
            "case": str(Path(args.case).relative_to(ROOT)) if Path(args.case).is_absolute()
            else args.case, "mesh": args.mesh, "febio_version": febio_version(log_text),
            "febio_command": " ".join(cmd), "febio_threads": env["OMP_NUM_THREADS"],
            "febio_normal_termination": normal, "febio_wall_s": round(wall, 1),
            "volume_penalty_MPa_per_mm3": eps, "omissions": omissions,
            "febio_steps": febio, "comparison": table}, indent=1) + "\n")
    return 0 if normal else 3


if __name__ == "__main__":
    sys.exit(main())
