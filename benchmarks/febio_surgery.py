"""A surgical case exported to FEBio, run in FEBio, and compared with eyefem on the same mesh.

    python benchmarks/febio_surgery.py --febio PATH/TO/febio4 \
        [--case cases/surgery/case1.toml] [--mesh coarse] [--out results/febio_case1] \
        [--record benchmarks/febio_surgery.json] [--reuse]

It writes the case's deck (`eyefem export-feb`, the whole eye), runs FEBio on it (2 OpenMP
threads unless OMP_NUM_THREADS is set), reads the nodes' displacements that the deck's
<logfile> asks for at the end of each step, and measures on FEBio's states the outcomes
eyefem measures on its own (eyefem.eye.outcomes: the axial length and the anterior chamber
depth from the pressurised eye, the buckle's indentation, the IOP from the cavity's volume
with the deck's volume constraint: p = p_iop + |eps| (V_0 - V), V_0 the volume at the step's
start). FEBio 4.11's volume constraint cannot converge where the sclera is pressed in
(:func:`open_cavity_deck` says why), so the tighten step is also run in FEBio on the deck
with the cavity open (the IOP held): that run is compared with eyefem's solve of the same
open deck read back, and eyefem's solve of the deck itself (closed) with eyefem's own case.
eyefem's own figures are those of `eyefem run` of the same case on the same mesh
(stages.csv); the first step is also compared with eyefem's solve of the deck read back
(the same model as FEBio's, the export's omissions included). The tables go to stdout;
``--record`` writes both sides, FEBio's version, command and wall time as JSON
(docs/febio.md quotes it); ``--reuse`` takes the deck and FEBio's logs a run left in OUT.

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


def eyefem_on_the_deck(setup, deck: Path, steps: int = 1) -> np.ndarray:
    """eyefem's solve of the deck's first ``steps`` steps as eyefem reads it back (FEBio's
    model: the same springs, segments and omissions): the mesh nodes' displacements
    (n, 3) at the last one's end (measure them with :func:`febio_outcomes`)."""
    from eyefem.io.febio_read import build_stages, read_feb
    from eyefem.solve.solver import solve

    mesh, materials, loads = read_feb(deck)
    model, stages = build_stages(mesh, materials, loads)
    n = setup.model.mesh.n_nodes
    return np.asarray(solve(model, stages[:steps]).q)[: 3 * mesh.n_nodes].reshape(-1, 3)[:n]


def open_cavity_deck(deck: Path, dst: Path, steps: int = 2) -> Path:
    """A copy of the deck with its volume constraints removed (the cavity open: the IOP
    load held as it is) and only its first ``steps`` steps, logging to
    DST-STEM_displacement.txt. FEBio 4.11's volume constraint (FEVolumeConstraint) adds
    to the stiffness only each face's own eps^2 (n da)(n da)^T, not the liquid's global
    rank-one eps (dV/du)(dV/du)^T, so no Newton step sees that pressing the sclera in
    raises the pressure everywhere: with the liquid's penalty (|eps| = K / V ~ 0.43
    MPa/mm^3) the tighten step inverts elements. Without the cavity FEBio and eyefem
    solve the same tightening (contact, structure) at the held IOP."""
    tree = ET.parse(deck)
    root = tree.getroot()
    for parent in [root, *root.iter("step")]:
        for c in parent.findall("Constraints"):
            parent.remove(c)
    for sec in root.findall("Step"):
        for st in sec.findall("step")[steps:]:
            sec.remove(st)
    for nd in root.iter("node_data"):
        nd.set("file", f"{dst.stem}_displacement.txt")
    tree.write(dst, encoding="ISO-8859-1", xml_declaration=True)
    return dst


def given_iop_deck(open_deck: Path, dst: Path, iop_mmhg: float) -> Path:
    """A copy of the open-cavity deck (:func:`open_cavity_deck`) whose pressure loads rise
    linearly over its step 2 from their value at t = 1 to ``iop_mmhg`` (the IOP that
    eyefem's solve of the closed deck ends the step with; a new load curve), logging to
    DST-STEM_displacement.txt: FEBio then solves the closed cavity's end state with its
    pressure given (hyperelastic, frictionless: the end state does not depend on the
    path), so the volume FEBio ends with checks the pressure."""
    from eyefem.fem.units import MMHG

    tree = ET.parse(open_deck)
    root = tree.getroot()
    data = root.find("LoadData")
    lcs = {lc.get("id"): lc for lc in data.findall("load_controller")}
    for load in root.iter("surface_load"):
        if load.get("type") != "pressure":
            continue
        pr = load.find("pressure")
        value, pts = float(pr.text), lcs[pr.get("lc")].find("points")
        at1 = np.interp(1.0, *np.array([[float(v) for v in pt.text.split(",")]
                                         for pt in pts]).T)
        new = ET.SubElement(data, "load_controller", id=str(len(lcs) + 1), type="loadcurve")
        lcs[new.get("id")] = new
        ET.SubElement(new, "interpolate").text = "LINEAR"
        ET.SubElement(new, "extend").text = "CONSTANT"
        xp = ET.SubElement(new, "points")
        for t, v in ((0.0, 0.0), (1.0, at1), (2.0, iop_mmhg * MMHG / value)):
            ET.SubElement(xp, "pt").text = f"{t!r},{float(v)!r}"
        pr.set("lc", new.get("id"))
    for nd in root.iter("node_data"):
        nd.set("file", f"{dst.stem}_displacement.txt")
    tree.write(dst, encoding="ISO-8859-1", xml_declaration=True)
    return dst


def given_iop(deck: Path) -> float:
    """The IOP (mmHg) a deck's pressure load reaches at its end (the largest time on its
    load curve): :func:`given_iop_deck`'s ``iop_mmhg``."""
    from eyefem.fem.units import MMHG

    root = ET.parse(deck).getroot()
    pr = next(ld.find("pressure") for ld in root.iter("surface_load")
              if ld.get("type") == "pressure")
    lc = next(c for c in root.iter("load_controller") if c.get("id") == pr.get("lc"))
    t, v = np.array([[float(x) for x in pt.text.split(",")] for pt in lc.iter("pt")]).T
    return float(pr.text) * float(v[np.argmax(t)]) / MMHG


def closed_iop(p_open: float, dv_open: float, p_given: float, dv_given: float,
               eps: float) -> float:
    """FEBio's IOP (mmHg) of the closed cavity, interpolated between its two tighten runs
    with the cavity open (IOP p_open, volume change dv_open mm^3) and with the closed
    deck's IOP given (p_given, dv_given): the volume change linear in the IOP between
    them, dV(p) = dv_open + (p - p_open) s, meets the closed cavity's own, dV = -(p -
    p_open) MMHG / |eps| (FEBio's penalty, MPa/mm^3)."""
    from eyefem.fem.units import MMHG

    s = (dv_given - dv_open) / (p_given - p_open)
    return p_open - dv_open / (s + MMHG / abs(eps))


def run_febio(febio: str, deck: Path, env, reuse: bool = False) -> tuple:
    """FEBio on a deck in its folder: (exit code, wall s, normal termination, the log's
    text); ``reuse``: read the log a run left there instead (the wall time from FEBio's
    "Total elapsed time")."""
    log = deck.parent / f"{deck.stem}.log"
    if reuse and log.exists():
        text = log.read_text(errors="replace")
        normal = "N O R M A L   T E R M I N A T I O N" in text
        wall = next((float(line.split("(")[1].split()[0]) for line in text.splitlines()
                     if line.strip().startswith("Total elapsed time")), float("nan"))
        return (0 if normal else 1), wall, normal, text
    cmd = [febio, "-i", deck.name, "-silent"]
    t0 = time.perf_counter()
    run = subprocess.run(cmd, cwd=deck.parent, env=env, capture_output=True, text=True,
                         stdin=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    (deck.parent / f"{deck.stem}_stdout.txt").write_text(run.stdout + run.stderr)
    text = log.read_text(errors="replace") if log.exists() else ""
    return run.returncode, wall, "N O R M A L   T E R M I N A T I O N" in text, text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--febio", default=os.environ.get("FEBIO", "febio4"),
                    help="FEBio 4's executable (default: $FEBIO or febio4 on PATH)")
    ap.add_argument("--case", default=str(ROOT / "cases/surgery/case1.toml"))
    ap.add_argument("--mesh", default="coarse")
    ap.add_argument("--out", default="results/febio_surgery")
    ap.add_argument("--record", help="write both sides' outcomes as JSON to this file")
    ap.add_argument("--reuse", action="store_true", help="take the deck and FEBio's logs "
                    "already in OUT (a finished run of this script) instead of exporting "
                    "and running FEBio again")
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
    if args.reuse:
        from eyefem.io.febio_read import deck_pieces
        omissions = deck_pieces(deck)["omissions"]
    else:
        omissions = write_feb(setup, deck)
    pen = ET.parse(deck).getroot().find(".//constraint[@type='volume']/penalty")
    if pen is None:
        print(f"{deck}: no volume constraint (a case without a closed cavity)", file=sys.stderr)
        return 2
    eps = float(pen.text)

    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "2")}
    cmd = [args.febio, "-i", deck.name, "-silent"]
    try:
        rc, wall, normal, log_text = run_febio(args.febio, deck, env, args.reuse)
    except OSError as exc:
        print(f"cannot run FEBio '{args.febio}': {exc}; give --febio PATH", file=sys.stderr)
        return 4
    log_file = out / f"{deck.stem}_displacement.txt"
    if not log_file.exists():
        print(f"FEBio wrote no {log_file.name} (exit {rc}); its output: "
              f"{out / (deck.stem + '_stdout.txt')}", file=sys.stderr)
        return 3
    febio = febio_outcomes(setup, read_node_log(log_file), eps)
    # the tighten step with the cavity open (FEBio's volume constraint cannot converge)
    open_deck = out / f"{deck.stem}_open.feb"
    if not (args.reuse and open_deck.exists()):
        open_cavity_deck(deck, open_deck)
    rc_o, wall_o, normal_o, _ = run_febio(args.febio, open_deck, env, args.reuse)
    open_log = out / f"{open_deck.stem}_displacement.txt"
    febio_open = febio_outcomes(setup, read_node_log(open_log), 0.0) if open_log.exists() \
        else []
    # the pressurised eye (step 1) against eyefem's, measured alike, changes from unloaded
    ours1 = eyefem_pressurised(setup)
    base = ours1["unloaded"]
    n = setup.model.mesh.n_nodes
    u1 = eyefem_on_the_deck(setup, deck)
    same = febio_outcomes(setup, {1.0: u1, 2.0: np.zeros((n, 3))}, -1.0)[0]
    first = []
    for key in ("axial_length_mm", "anterior_chamber_depth_mm", "volume_mm3"):
        f_d, e_d = febio[0][key] - base[key], ours1["pressurised"][key] - base[key]
        first.append({"stage": febio[0]["stage"], "outcome": f"{key} change from unloaded",
                      "febio": f_d, "eyefem": e_d})
        first.append({"stage": febio[0]["stage"], "outcome": f"{key} (the deck in eyefem)",
                      "febio": f_d, "eyefem": same[key] - base[key]})
    try:  # eyefem's solve of the deck itself (the cavity closed) through the tighten step
        u2c = eyefem_on_the_deck(setup, deck, steps=2)
        same_closed = febio_outcomes(setup, {1.0: u1, 2.0: u2c}, eps)[1]
    except Exception as exc:  # noqa: BLE001 (recorded: eyefem's solver stopped)
        print(f"eyefem's solve of {deck.name} stopped: {exc}", file=sys.stderr)
        same_closed = None
    febio_iop, wall_i, normal_i, p_given = [], float("nan"), False, float("nan")
    if same_closed is not None:  # FEBio given the IOP eyefem's closed deck ends with
        iop_deck = out / f"{deck.stem}_iop.feb"
        if not (args.reuse and iop_deck.exists()):
            given_iop_deck(open_deck, iop_deck, same_closed["iop_mmhg"])
        p_given = given_iop(iop_deck)
        _, wall_i, normal_i, _ = run_febio(args.febio, iop_deck, env, args.reuse)
        iop_log = out / f"{iop_deck.stem}_displacement.txt"
        if iop_log.exists():
            febio_iop = febio_outcomes(setup, read_node_log(iop_log), 0.0)
    try:  # eyefem's solve of the open deck through the tighten step
        u2 = eyefem_on_the_deck(setup, open_deck, steps=2)
        same_open = febio_outcomes(setup, {1.0: u1, 2.0: u2}, 0.0)[1]
    except Exception as exc:  # noqa: BLE001 (recorded: eyefem's solver stopped)
        print(f"eyefem's solve of {open_deck.name} stopped: {exc}", file=sys.stderr)
        same_open = None

    run_dir = Path(args.eyefem_run) if args.eyefem_run else out / "eyefem"
    if not args.eyefem_run:
        subprocess.run([sys.executable, "-m", "eyefem.cli.main", "-q", "run", args.case,
                        "--mesh", args.mesh, "--no-vtu", "--out", str(run_dir)], check=True)
    with open(run_dir / "stages.csv") as fh:
        ours = list(csv.DictReader(fh))
    keys = ("iop_mmhg", "indentation_mm", "axial_length_change_mm",
            "anterior_chamber_depth_change_mm")
    print(f"FEBio: {'normal termination' if normal else 'NOT normal termination'} "
          f"(exit {rc}), {wall:.1f} s, {len(febio)} step(s) with results; "
          f"the open cavity: {'normal' if normal_o else 'NOT normal'} termination "
          f"(exit {rc_o}), {wall_o:.1f} s, {len(febio_open)} step(s)")
    print(f"FEBio given the closed deck's IOP: {'normal' if normal_i else 'NOT normal'} "
          f"termination, {wall_i:.1f} s, {len(febio_iop)} step(s)")
    print(f"{'stage':<11} {'outcome':<44} {'FEBio':>10} {'eyefem':>10} {'diff':>9}")
    table = first[:]
    for f_row in febio[1:]:
        e_row = next((r for r in ours if r["stage"] == f_row["stage"]), None)
        for key in keys:
            table.append({"stage": f_row["stage"], "outcome": key, "febio": f_row[key],
                          "eyefem": float(e_row[key]) if e_row else float("nan")})
    for f_row in febio_open[1:]:
        e_row = next((r for r in ours if r["stage"] == f_row["stage"]), None)
        for key in keys + ("volume_change_mm3",):
            if same_open is not None:
                table.append({"stage": f_row["stage"], "outcome": f"{key} (open, the deck in "
                              "eyefem)", "febio": f_row[key], "eyefem": same_open[key]})
    for f_row in febio_iop[1:2]:
        f_row["iop_mmhg"] = p_given  # given, not measured
        e_row = next((r for r in ours if r["stage"] == f_row["stage"]), None)
        o_row = next((r for r in febio_open if r["stage"] == f_row["stage"]), None)
        if o_row is not None:  # FEBio's closed-cavity IOP, from its two runs
            p = closed_iop(o_row["iop_mmhg"], o_row["volume_change_mm3"], p_given,
                           f_row["volume_change_mm3"], eps)
            table.append({"stage": f_row["stage"], "outcome": "iop_mmhg (FEBio: closed, "
                          "interpolated; the deck in eyefem)", "febio": p,
                          "eyefem": same_closed["iop_mmhg"]})
            if e_row:
                table.append({"stage": f_row["stage"], "outcome": "iop_mmhg (FEBio: closed, "
                              "interpolated; eyefem's case)", "febio": p,
                              "eyefem": float(e_row["iop_mmhg"])})
        for key in keys + ("volume_change_mm3",):
            if key != "iop_mmhg":
                table.append({"stage": f_row["stage"], "outcome": f"{key} (IOP given; the "
                              "deck in eyefem, closed)", "febio": f_row[key],
                              "eyefem": same_closed[key]})
            if e_row and key in e_row:
                table.append({"stage": f_row["stage"], "outcome": f"{key} (IOP given; "
                              "eyefem's case)", "febio": f_row[key], "eyefem": float(e_row[key])})
    for row in table:
        print(f"{row['stage']:<11} {row['outcome']:<44} {row['febio']:>10.4f} "
              f"{row['eyefem']:>10.4f} {row['febio'] - row['eyefem']:>+9.4f}")
    closed = []  # the deck's model (cavity closed) in eyefem against eyefem's own case
    if same_closed is not None:
        e_row = next((r for r in ours if r["stage"] == same_closed["stage"]), None)
        print(f"{'stage':<11} {'outcome (cavity closed)':<44} {'deck':>10} {'case':>10}")
        for key in keys + ("volume_change_mm3",):
            e = float(e_row[key]) if e_row and key in e_row else float("nan")
            closed.append({"stage": same_closed["stage"], "outcome": key,
                           "deck_in_eyefem": same_closed[key], "eyefem_case": e})
            print(f"{same_closed['stage']:<11} {key:<44} {same_closed[key]:>10.4f} {e:>10.4f}")
    if args.record:
        Path(args.record).write_text(json.dumps({
            "case": str(Path(args.case).relative_to(ROOT)) if Path(args.case).is_absolute()
            else args.case, "mesh": args.mesh, "febio_version": febio_version(log_text),
            "febio_command": " ".join(cmd), "febio_threads": env["OMP_NUM_THREADS"],
            "febio_normal_termination": normal, "febio_wall_s": round(wall, 1),
            "open_cavity_normal_termination": normal_o, "open_cavity_wall_s": round(wall_o, 1),
            "given_iop_normal_termination": normal_i, "given_iop_wall_s": round(wall_i, 1),
            "given_iop_mmhg": p_given,
            "febio_given_iop_steps": febio_iop,
            "volume_penalty_MPa_per_mm3": eps, "omissions": omissions,
            "febio_steps": febio, "febio_open_cavity_steps": febio_open,
            "eyefem_deck_closed_tighten": same_closed, "eyefem_deck_open_tighten": same_open,
            "comparison": table, "closed_deck_in_eyefem_vs_case": closed}, indent=1) + "\n")
    return 0 if normal_o and normal_i and same_open is not None else 3


if __name__ == "__main__":
    sys.exit(main())
