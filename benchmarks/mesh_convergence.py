"""Mesh convergence study of the eye outcomes (issue 29 item 1; docs/convergence.md).

Runs surgical cases at several eye mesh levels (or reads the run folders already there),
collects the outcomes and applies the three-grid procedure of Celik et al. 2008
(eyefem.eye.convergence: observed order, Richardson extrapolation, GCI with Fs = 1.25) to
every outcome and every consecutive triple of levels. Grid size h = 1 / n, n the elements
per cubed-sphere patch edge (eyefem.eye.eyemodel.LEVELS); the wall keeps 4 element layers
at every level, so the refinement is in-plane only (a level with the suffix "x2", e.g.
``run-one CASE mediumx2 DIR``, has 8: the through-thickness check).

    python benchmarks/mesh_convergence.py --cases case1,case5 \
        --levels coarse,medium,default,fine --runs /tmp/conv --out /tmp/conv/report \
        --images docs/images
    python benchmarks/mesh_convergence.py ... --no-run     # tabulate existing runs only
    python benchmarks/mesh_convergence.py ... --compare OTHER_RUNS   # drawn beside, grey
    python benchmarks/mesh_convergence.py ... --no-run --fill   # runs made before the
              # peak scleral stress was recorded or the indentation weighted by area
    python benchmarks/mesh_convergence.py --record eyefem/eye/mesh_study.json \
        --cases case1,case4,case5 --levels half,default,fine,finer \
        --candidate fine --out /tmp/conv/report   # from the shipped record
    python benchmarks/mesh_convergence.py export --runs RUNS [--update]   # the record

Each run goes to RUNS/CASE/LEVEL (summary.json, stages.csv, surgery_history.csv, run.log),
one at a time in a subprocess (``run-one``), skipped when its summary.json exists. Besides
the case's own outcomes the runs record two suture forces that do not hang on one bar:
the mean bar force over all sutures and the largest per-suture mean bar force.
Writes OUT/convergence.json, OUT/convergence_table.md and IMAGES/convergence_<case>.png
(docs/convergence.md quotes them). ``export`` writes the outcome values of the runs (and
their iterations, times and memory) to the record runs quote their mesh error from;
``--update`` keeps the record's levels that the run folders lack, and ``--record``
tabulates and plots from the record alone, once the run folders are gone.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import resource
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

log = logging.getLogger("mesh_convergence")

OUTCOMES = {  # key -> (label, relative bound of the default level's GCI)
    "iop_rise_mmhg": ("IOP rise, mmHg", 0.05),
    "indentation_mm": ("indentation, mm", 0.05),
    "indentation_nodes_mm": ("indentation, bands at the nodes, mm", None),
    "axial_length_change_mm": ("axial length change, mm", 0.05),
    "refraction_change_D": ("refraction change, D", 0.05),
    "max_suture_force_N": ("largest suture bar force, N", 0.10),
    "mean_suture_force_N": ("mean suture bar force, N", 0.10),
    "max_suture_mean_force_N": ("largest per-suture mean force, N", 0.10),
    "corneal_power_change_D": ("corneal power change, D", None),
    "anterior_chamber_depth_change_mm": ("anterior chamber depth change, mm", None),
    "scleral_stress_kPa": ("peak scleral von Mises stress (1 mm patch), kPa", None),
}
"""Outcomes studied; the bound is issue 29's (5 % / 10 %), None: reported only."""

FORMAL_ORDER = 2.0
"""Formal order of the Q1P0 hexahedra's displacements: where a triple's observed order is
above it, the default level's GCI is also given with this order (Roache's conservative
choice), whose Richardson extrapolation lies further from the fine level."""

ABBREV = {"coarse": "c", "half": "h", "medium": "m", "default": "D", "fine": "f", "finer": "F",
          "graded_half": "gh", "graded": "G", "graded_fine": "gf", "gradedc18": "c18",
          "gradedc26": "c26", "gradedc36": "c36", "finest": "Ff", "ultrafine": "U"}


# --------------------------------------------------------------------------- running

def _study_probe(base_probe, parts, n_sutures: int):
    """Probe that adds suture forces that do not hang on one bar: the mean bar force over
    all sutures and the largest per-suture mean bar force, N (0 before the sutures are
    tightened, as max_suture_force_N), and the indentation with its bands sampled at the
    nodes (:func:`_indentation_at_nodes`)."""
    indent = _indentation_at_nodes(parts)

    def probe(model, q, theta):
        out = base_probe(model, q, theta)
        out["indentation_nodes_mm"] = indent(q)
        f = np.asarray(model.term("sutures").forces(q, theta["sutures"]), float)
        tight = np.any(np.asarray(theta["sutures"]["tightening"]))
        per_suture = f.reshape(n_sutures, -1).mean(axis=1)
        out["mean_suture_force_N"] = float(f.mean()) if tight else 0.0
        out["max_suture_mean_force_N"] = float(per_suture.max()) if tight else 0.0
        return out
    return probe


def _indentation_at_nodes(parts):
    """q -> the indentation (mm) with the plain mean radius of the outer scleral nodes in
    each band (the bands of eyefem.eye.outcomes.band_area_weights), the outcome's
    definition before the bands were weighted by area: kept to show what the weighting
    does to the convergence (docs/convergence.md)."""
    from eyefem.eye.parts import buckle_coords

    a, ok = buckle_coords(parts)
    a, w, nodes = np.abs(a), parts.buckle.width, parts.sclera_nodes
    under = nodes[ok & (a < w / 4)]
    beside = nodes[ok & (a > w / 2 + 1.5) & (a < w / 2 + 3.0)]
    X = parts.eye.mesh.nodes

    def indent(q):
        u = np.asarray(q)[: X.size].reshape(-1, 3)
        r = lambda ids: np.linalg.norm(X[ids] + u[ids], axis=1).mean()  # noqa: E731
        return float(r(beside) - r(under))
    return indent


def run_one(case_path: str, level: str, out_dir: Path) -> dict:
    """Run one case at one mesh level into out_dir (no VTU, no plots); returns the summary
    written to out_dir/summary.json (the case's summary + level, n_per_edge, the suture
    forces of :func:`_suture_probe` and the peak memory)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from eyefem.catalog import problems, schemas
    from eyefem.eye.eyemodel import level_spec
    from eyefem.io import manifest
    from eyefem.io.casefile import load_case, with_mesh
    from eyefem.run.runner import run_setup
    from eyefem.solve.heap import configure_heap

    configure_heap()  # EYEFEM_HEAP=lean: the finer levels are limited by memory

    case = load_case(case_path, schemas())
    case = with_mesh(case, level)
    setup = problems()[case.problem][1](case.parameters, case.materials)
    n_sutures = int(setup.parts.p["n_sutures"])
    setup = dataclasses.replace(setup, probe=_study_probe(setup.probe, setup.parts, n_sutures))
    res = run_setup(setup, out_dir, case.solver, vtu=False, plots=False,
                    key=manifest.case_key(case.problem, case.parameters, case.materials,
                                          case.solver))
    last = res.rows[-1]
    summary = {"case": str(case_path), "title": case.title, "level": level,
               "n_per_edge": level_spec(level)[0], "iop_param_mmhg": case.parameters["iop_mmhg"],
               **res.summary,
               "mean_suture_force_N": last["mean_suture_force_N"],
               "max_suture_mean_force_N": last["max_suture_mean_force_N"],
               "indentation_nodes_mm": last["indentation_nodes_mm"],
               "max_rss_GB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def run_missing(cases, levels, runs: Path, case_dir: Path) -> None:
    """Run every (case, level) whose RUNS/CASE/LEVEL/summary.json is missing, one at a
    time, each in its own process (memory is given back between runs)."""
    for level in levels:
        for case in cases:
            out = runs / case / level
            if (out / "summary.json").exists():
                continue
            out.mkdir(parents=True, exist_ok=True)
            log.info("running %s at %s -> %s", case, level, out)
            tic = time.perf_counter()
            with open(out / "run.log", "w") as fh:
                rc = subprocess.call([sys.executable, __file__, "run-one",
                                      str(case_dir / f"{case}.toml"), level, str(out)],
                                     stdout=fh, stderr=subprocess.STDOUT)
            log.info("  %s %s: exit %d after %.0f s", case, level, rc,
                     time.perf_counter() - tic)


FILLED = ("scleral_stress_kPa", "indentation_nodes_mm")
"""Outcomes :func:`fill_outcomes` adds to runs made before they were recorded."""


def fill_outcomes(case_path: Path, level: str, out_dir: Path) -> bool:
    """Add the outcomes of FILLED that a run's summary.json lacks (runs made before they
    were recorded: the peak scleral stress, eyefem.eye.outcomes.peak_scleral_stress; the
    indentation with its bands at the nodes, :func:`_indentation_at_nodes`, the run's
    ``indentation_mm`` then evaluated again, with its bands weighted by area, as the
    outcome is now defined), evaluated on the final state of its
    checkpoint (a numpy archive, checked against its checkpoint.json) with the case rebuilt
    at ``level``. Returns False (and says why) where the run has no final state."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from eyefem.catalog import problems, schemas
    from eyefem.eye.outcomes import peak_scleral_stress, stress_patches
    from eyefem.io import checkpoint
    from eyefem.io.casefile import load_case, with_mesh

    f = out_dir / "summary.json"
    summary = json.loads(f.read_text())
    meta = json.loads((out_dir / checkpoint.FILENAME).read_text())
    ck = checkpoint.load(out_dir, meta["key"])
    case = load_case(str(case_path), schemas())
    case = with_mesh(case, level)
    setup = problems()[case.problem][1](case.parameters, case.materials)
    if ck["stage"] != len(setup.stages) - 1:
        log.warning("%s: its checkpoint holds stage %d of %d, not the final state; nothing "
                    "filled", out_dir, ck["stage"] + 1, len(setup.stages))
        return False
    if ck["q"].shape != (setup.model.n_dof,):
        log.warning("%s: its state has %d unknowns, the case at %s %d; nothing filled",
                    out_dir, ck["q"].size, level, setup.model.n_dof)
        return False
    if "scleral_stress_kPa" not in summary:
        summary["scleral_stress_kPa"] = peak_scleral_stress(
            setup.model, ck["q"], ck["theta"], stress_patches(setup.model.mesh))
    if "indentation_nodes_mm" not in summary:
        from eyefem.eye.outcomes import indentation, outcome_nodes

        summary["indentation_nodes_mm"] = _indentation_at_nodes(setup.parts)(ck["q"])
        summary["indentation_mm"] = float(indentation(setup.parts.eye.mesh.nodes, ck["q"],
                                                      outcome_nodes(setup.parts)))
    filled = [k for k in FILLED if k not in json.loads(f.read_text())]
    if "indentation_nodes_mm" in filled:
        filled.append("indentation_mm")
    summary["filled_from_checkpoint"] = filled
    f.write_text(json.dumps(summary, indent=2) + "\n")
    return True


# --------------------------------------------------------------------------- the study

def outcome_values(summary: dict) -> dict:
    """The studied outcomes of one run's summary (IOP rise = iop_mmhg - the case's IOP), or
    of one level of the study record (its "values")."""
    if "values" in summary:
        return {k: float(v) for k, v in summary["values"].items() if k in OUTCOMES}
    out = {k: summary.get(k) for k in OUTCOMES if k in summary}
    iop0 = summary.get("iop_param_mmhg", 15.0)
    out["iop_rise_mmhg"] = summary["iop_mmhg"] - iop0
    return {k: float(v) for k, v in out.items() if v is not None}


def study_case(runs: dict, levels: list[str], candidate: str = "default",
               lsq_levels: list[str] | None = None) -> dict:
    """The study of one case. runs: level -> summary (levels fine to coarse not needed:
    sorted by h here). Returns {"levels", "h", "values": {outcome: [...]}, "triples":
    {outcome: [ThreeGridStudy dict per consecutive triple]}, "candidate": the level judged
    against the bounds, "default_gci": {outcome: GCI of the candidate level against the
    finest triple's extrapolation}} (the key keeps its name for the JSON's readers), and
    "least_squares": {outcome: LeastSquaresStudy dict} over ``lsq_levels`` (default: the
    uniform levels run), where four or more were run."""
    from eyefem.eye.convergence import least_squares_study, relative_gci, three_grid_study
    from eyefem.eye.eyemodel import is_graded

    levels = sorted([lv for lv in levels if lv in runs], key=lambda lv: -runs[lv]["n_per_edge"])
    h = [1.0 / runs[lv]["n_per_edge"] for lv in levels]  # fine -> coarse
    vals = {lv: outcome_values(runs[lv]) for lv in levels}
    keys = [k for k in OUTCOMES if all(k in vals[lv] for lv in levels)]
    out = {"levels": levels, "h": h,
           "elements": [runs[lv].get("elements") for lv in levels],
           "wall_s": [runs[lv].get("wall_s") for lv in levels],
           "newton_iterations": [runs[lv].get("newton_iterations") for lv in levels],
           "max_rss_GB": [runs[lv].get("max_rss_GB") for lv in levels],
           "values": {k: [vals[lv][k] for lv in levels] for k in keys},
           "triples": {}, "candidate": candidate, "default_gci": {}, "default_gci_p2": {},
           "least_squares": {}}
    # the least-squares procedure over the uniform levels (h = 1 / n means the same
    # element size there, not on the graded levels), from four of them
    uniform = [i for i, lv in enumerate(levels)
               if (lv in lsq_levels if lsq_levels else not is_graded(lv))]
    out["least_squares_levels"] = [levels[i] for i in uniform] if len(uniform) >= 4 else []
    for k in keys:
        if out["least_squares_levels"]:
            out["least_squares"][k] = least_squares_study(
                [h[i] for i in uniform], [out["values"][k][i] for i in uniform]).as_dict()
        trip = []
        for i in range(len(levels) - 2):
            s = three_grid_study(h[i:i + 3], out["values"][k][i:i + 3])
            trip.append({"levels": levels[i:i + 3], **s.as_dict()})
        out["triples"][k] = trip
        if trip and candidate in levels:
            finest = trip[0]
            ext = finest["extrapolated"]
            v = out["values"][k][levels.index(candidate)]
            out["default_gci"][k] = (relative_gci(v, ext) if ext is not None
                                     else None)
            if ext is not None:  # Roache's conservative choice: the order at most 2
                f1, f2 = out["values"][k][:2]
                p2 = min(finest["p"], FORMAL_ORDER)
                ext2 = f1 + (f1 - f2) / ((h[1] / h[0]) ** p2 - 1)
                out["default_gci_p2"][k] = relative_gci(v, ext2)
    return out


def _fmt(v, digits=4):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{digits}g}"


def _pct(v):
    return "-" if v is None else f"{100 * v:.2g} %" if v < 0.1 else f"{100 * v:.0f} %"


def markdown(study: dict) -> str:
    """Markdown tables of all cases: values per level, then per triple p, extrapolated
    value, GCI of the triple's finest level, and the default level's GCI."""
    lines = []
    for case, s in study.items():
        lv = s["levels"]
        cand = s.get("candidate", "default")
        lines += [f"### {case}", "",
                  "| outcome | " + " | ".join(f"{x} (n={round(1 / h)})" for x, h in
                                              zip(lv, s["h"])) + " |",
                  "|---|" + "---:|" * len(lv)]
        for k, v in s["values"].items():
            lines.append(f"| {OUTCOMES[k][0]} | " + " | ".join(_fmt(x, 5) for x in v) + " |")
        lines.append("| elements | " + " | ".join(str(e) for e in s["elements"]) + " |")
        lines.append("| Newton iterations | " + " | ".join("-" if e is None else str(e)
                                                          for e in s["newton_iterations"]) + " |")
        lines.append("| wall time, s | " + " | ".join(_fmt(e, 3) for e in s["wall_s"]) + " |")
        lines.append("")
        hdr = ["outcome"]
        for t in next(iter(s["triples"].values()), []):
            name = "/".join(ABBREV.get(x, x) for x in t["levels"])
            hdr += [f"{name}: behaviour", "p", "extrapolated", "GCI fine"]
        hdr += [f"GCI of {cand}", f"GCI of {cand}, p <= 2", f"{cand} - finest", "bound"]
        lines += ["| " + " | ".join(hdr) + " |", "|---|" + "---:|" * (len(hdr) - 1)]
        for k, trips in s["triples"].items():
            row = [OUTCOMES[k][0]]
            for t in trips:
                flag = " (!)" if t["behaviour"] == "monotone" and t["note"] else ""
                row += [t["behaviour"] + flag, _fmt(t["p"], 3), _fmt(t["extrapolated"], 5),
                        _pct(t["gci_fine"])]
            g, bound = s["default_gci"].get(k), OUTCOMES[k][1]
            g2 = s.get("default_gci_p2", {}).get(k)
            ok = "" if g is None or bound is None else (" ok" if g <= bound else " **over**")
            ok2 = "" if g2 is None or bound is None else (" ok" if g2 <= bound else " **over**")
            vals = s["values"][k]
            d = (None if cand not in lv or lv[0] == cand or vals[0] == 0
                 else (vals[lv.index(cand)] - vals[0]) / abs(vals[0]))
            diff = "-" if d is None else f"{100 * d:+.2g} %"
            row += [_pct(g) + ok, _pct(g2) + ok2, diff, _pct(bound) if bound else "-"]
            lines.append("| " + " | ".join(row) + " |")
        lsq = s.get("least_squares") or {}
        if lsq:
            names = s["least_squares_levels"]
            lines += ["", f"Least squares over {', '.join(names)} (Eca and Hoekstra 2014): "
                      "the fit the error comes from (p: the free order; 1, 2, 12: fixed "
                      "orders), the estimate of the exact value, and each level's "
                      "uncertainty U relative to its value:", "",
                      "| outcome | p | fit | Fs | extrapolated | " +
                      " | ".join(f"U {x}" for x in names) + " |",
                      "|---|" + "---:|" * (4 + len(names))]
            for k, t in lsq.items():
                rel = [u / abs(v) if v else None for u, v in zip(t["uncertainty"], t["values"])]
                lines.append(f"| {OUTCOMES[k][0]} | {_fmt(t['p'], 3)} | {t['fit']} | "
                             f"{t['safety_factor']:g} | {_fmt(t['extrapolated'], 5)} | " +
                             " | ".join(_pct(r) for r in rel) + " |")
        legend = ("(levels: c coarse, h half, m medium, D default, f fine, F finer, Ff finest, "
                  "U ultrafine, gh graded_half, G graded, gf graded_fine, c18 gradedc18 (c26, "
                  "c36); "
                  "behaviour of "
                  "each triple, observed order p, Richardson value and GCI_fine of its "
                  "finest level; (!): p outside 0.5..4 or the extrapolation changes sign; "
                  f"'GCI of {cand}': Fs |phi_ext - phi_{cand}| / |phi_{cand}| against "
                  "the finest triple's extrapolation; 'p <= 2': the same with that "
                  f"triple's order capped at the elements' formal order 2; '{cand} - "
                  f"finest': the {cand} level's value relative to the finest level's, a "
                  "lower bound of its error where no order can be given)")
        lines += ["", textwrap.fill(legend, 92), ""]
    return "\n".join(lines)


def plot(case: str, s: dict, path: Path, other: dict | None = None, other_label: str = "") -> None:
    """Outcome vs h per outcome (one panel each), with the finest triple's extrapolated
    value at h = 0 where the triple converges monotonically with a plausible order;
    ``other``: a study of the same case from other runs (``--compare``), drawn grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(s["values"])
    ncol = 3
    nrow = math.ceil(len(keys) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.2 * nrow), squeeze=False)
    for ax, k in zip(axes.flat, keys):
        ax.plot(s["h"], s["values"][k], "o-", label="runs")
        if other and k in other["values"]:
            ax.plot(other["h"], other["values"][k], "s--", color="0.6", ms=4, label=other_label)
        for x, y, lv in zip(s["h"], s["values"][k], s["levels"]):
            ax.annotate(lv, (x, y), textcoords="offset points", xytext=(3, 3), fontsize=7)
        ls = (s.get("least_squares") or {}).get(k)
        if ls:  # each level's least-squares uncertainty U_i as an error bar
            ax.errorbar(ls["h"], ls["values"], yerr=ls["uncertainty"], fmt="none",
                        ecolor="C1", elinewidth=0.8, capsize=2,
                        label=f"least squares U (fit {ls['fit']}, Fs {ls['safety_factor']:g})")
            ax.plot([0.0], [ls["extrapolated"]], "D", ms=5, color="C1")
        t = s["triples"][k][0] if s["triples"][k] else None
        if t and t["extrapolated"] is not None and not t["note"]:
            ax.plot([0.0], [t["extrapolated"]], "*", ms=10, color="C2",
                    label=f"Richardson (p = {t['p']:.2f})")
            ax.axhline(t["extrapolated"], color="C2", ls=":", lw=0.8)
        elif t:
            what = (f"p = {t['p']:.2f}: not credible" if t["behaviour"] == "monotone"
                    else t["behaviour"])
            ax.text(0.02, 0.05, what, transform=ax.transAxes, fontsize=8)
        if ls:  # the runs set the scale; wider error bars run off it
            v = list(s["values"][k]) + [ls["extrapolated"]]
            span = max(max(v) - min(v), 1e-12 * max(abs(x) for x in v))
            ax.set_ylim(min(v) - 0.4 * span, max(v) + 0.4 * span)
        ax.set_xlim(left=0.0)
        ax.set_xlabel("h = 1 / n")
        ax.set_title(OUTCOMES[k][0], fontsize=9)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    fig.suptitle(f"{case}: mesh convergence (in-plane refinement, 4 wall layers)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _studies(cases, levels, candidate: str, found_of, lsq_levels=None) -> dict:
    """case -> :func:`study_case` of ``found_of(case)`` (level -> summary or record level);
    cases with fewer than three levels are left out, with a warning."""
    study = {}
    for case in cases:
        found = found_of(case)
        if len(found) < 3:
            log.warning("%s: %d level(s) found; a study needs three", case, len(found))
            continue
        study[case] = study_case(found, levels, candidate, lsq_levels)
    return study


def collect(cases, levels, runs: Path, candidate: str = "default", lsq_levels=None) -> dict:
    """case -> :func:`study_case` of the runs RUNS/CASE/LEVEL/summary.json there (cases
    with fewer than three levels run are left out, with a warning)."""
    def found_of(case):
        found = {}
        for lv in levels:
            f = runs / case / lv / "summary.json"
            if f.exists():
                found[lv] = json.loads(f.read_text())
            else:
                log.warning("%s: no run at %s (%s missing); left out", case, lv, f)
        return found

    return _studies(cases, levels, candidate, found_of, lsq_levels)


def collect_record(record: dict, cases, levels, candidate: str = "default",
                   lsq_levels=None) -> dict:
    """As :func:`collect`, from the study record's levels instead of run folders (the
    shipped record keeps the values after the run folders are gone)."""
    def found_of(case):
        have = record["cases"].get(case, {}).get("levels", {})
        for lv in [lv for lv in levels if lv not in have]:
            log.warning("%s: the record has no level %s; left out", case, lv)
        return {lv: have[lv] for lv in levels if lv in have}

    return _studies(cases, levels, candidate, found_of, lsq_levels)


RUN_FIGURES = ("newton_iterations", "wall_s", "max_rss_GB")
"""What the record keeps of each run besides its outcomes (for the tables)."""


def export(runs: Path, cases: list[str], families: list[list[str]], case_dir: Path,
           out: Path, update: bool = False, extra_levels: list[str] = ()) -> dict:
    """Write the study record that runs quote their mesh error from
    (eyefem.eye.mesh_error.STUDY_FILE): the outcome values of RUNS/CASE/LEVEL/summary.json
    for the levels of ``families`` (each three levels, fine first) and the ``extra_levels``
    that were run (quoted against the families' extrapolations), and the model fields each
    case ran with. ``update``: keep the levels of the record already at ``out`` that RUNS
    does not hold (the runs found there replace theirs), and its cases ``cases`` does not
    name."""
    from eyefem.catalog import schemas
    from eyefem.eye.buckles import Buckle
    from eyefem.eye.surgery import STUDY_MODEL
    from eyefem.io.casefile import load_case

    old = json.loads(out.read_text()) if update and out.exists() else {"cases": {}}
    recorded = sorted(set(cases) | set(old["cases"]))
    record = {"source": "docs/convergence.md; python benchmarks/mesh_convergence.py export "
              f"--cases {','.join(recorded)} --families "
              f"'{';'.join(','.join(f) for f in families)}'",
              "materials": "seed", "families": families, "cases": {}}
    fresh = {}
    for case in cases:
        params = load_case(case_dir / f"{case}.toml", schemas()).parameters
        levels = {}
        kept = old["cases"].get(case, {}).get("levels", {})
        in_families = {lv for f in families for lv in f}
        for lv in sorted(in_families | set(extra_levels)):
            f = runs / case / lv / "summary.json"
            if not f.exists():
                if lv in kept:
                    levels[lv] = kept[lv]
                    log.info("%s: %s kept from %s", case, lv, out)
                elif lv in in_families:  # (an extra level the case did not run: silent)
                    log.warning("%s: no run at %s (%s missing); left out", case, lv, f)
                continue
            summary = json.loads(f.read_text())
            if summary.get("unbalanced_steps", {}).get("count", 0):
                raise SystemExit(f"{f}: the run accepted unbalanced steps; its outcomes are "
                                 "not equilibrium values: run it again")
            levels[lv] = {"n_per_edge": summary["n_per_edge"],
                          "elements": summary.get("elements"),
                          **{k: summary.get(k) for k in RUN_FIGURES},
                          "values": outcome_values(summary)}
        fresh[case] = {"buckle": params["buckle"],
                       "encircling": Buckle(params["buckle"]).encircling,
                       "tightening_mm": params.get("tightening"),
                       "model": {k: params.get(k, v) for k, v in STUDY_MODEL.items()},
                       "levels": levels}
    for c in recorded:
        if c not in fresh:
            log.info("%s kept from %s", c, out)
        record["cases"][c] = fresh.get(c, old["cases"].get(c))
    out.write_text(json.dumps(record, indent=1) + "\n")
    log.info("wrote %s", out)
    return record


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s",
                        datefmt="%H:%M:%S")
    if argv and argv[0] == "export":
        ap = argparse.ArgumentParser(prog="mesh_convergence.py export",
                                     description="write the study record runs quote their "
                                     "mesh error from (eyefem/eye/mesh_study.json)")
        ap.add_argument("--cases", default="case1,case4,case5")
        ap.add_argument("--families",
                        default="finer,default,half;finer,fine,default;finest,finer,fine",
                        help="level triples, fine first, separated by ';' (default: those of "
                        "the shipped record)")
        ap.add_argument("--case-dir", default="cases/surgery")
        ap.add_argument("--runs", required=True, help="run folders RUNS/CASE/LEVEL")
        ap.add_argument("--out", default="eyefem/eye/mesh_study.json")
        ap.add_argument("--update", action="store_true",
                        help="keep the levels of the record at --out that --runs lacks")
        ap.add_argument("--levels", default="gradedc26,ultrafine",
                        help="levels recorded outside the families, where run (default: "
                        "gradedc26, the surgical cases' mesh before fine, and ultrafine, the "
                        "sixth uniform level; '' for none)")
        a = ap.parse_args(argv[1:])
        export(Path(a.runs), a.cases.split(","), [f.split(",") for f in a.families.split(";")],
               Path(a.case_dir), Path(a.out), update=a.update,
               extra_levels=[lv for lv in a.levels.split(",") if lv])
        return 0
    if argv and argv[0] in ("run-one", "fill"):
        if len(argv) != 4 or any(a.startswith("-") for a in argv[1:]):
            print(f"usage: python benchmarks/mesh_convergence.py {argv[0]} CASE.toml LEVEL "
                  "RUN_DIR\n  e.g. run-one cases/surgery/case1.toml fine /tmp/conv/case1/fine"
                  + ("" if argv[0] == "run-one" else
                     "\n  (fill: the outcomes of a finished run from its final checkpoint)"),
                  file=sys.stderr)
            return 0 if argv[1:] in (["-h"], ["--help"]) else 2
        case_path, level, out = argv[1:4]
        if argv[0] == "run-one":
            run_one(case_path, level, Path(out))
            return 0
        return 0 if fill_outcomes(Path(case_path), level, Path(out)) else 1
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="case1,case5", help="case names in --case-dir")
    ap.add_argument("--levels", default="coarse,medium,default,fine",
                    help="mesh levels (eyefem.eye.eyemodel.LEVELS), at least three")
    ap.add_argument("--candidate", default="default",
                    help="the level judged against the bounds (its GCI against the finest "
                    "triple's extrapolation; default: default)")
    ap.add_argument("--least-squares", help="the levels of the least-squares procedure, four "
                    "or more (default: the uniform levels of --levels)")
    ap.add_argument("--case-dir", default="cases/surgery")
    ap.add_argument("--runs", default="/tmp/conv", help="run folders RUNS/CASE/LEVEL")
    ap.add_argument("--out", default="/tmp/conv/report", help="where the table and JSON go")
    ap.add_argument("--images", help="where the plots go (default OUT/images)")
    ap.add_argument("--no-run", action="store_true", help="only tabulate the runs there")
    ap.add_argument("--record", help="tabulate the values of this study record (e.g. "
                    "eyefem/eye/mesh_study.json) instead of run folders; implies --no-run")
    ap.add_argument("--compare", help="other run folders (RUNS/CASE/LEVEL, e.g. of an earlier "
                    "model) drawn beside these in the plots")
    ap.add_argument("--compare-levels", help="with --record: levels of the record drawn "
                    "beside, grey (e.g. another family: finer,default,half)")
    ap.add_argument("--compare-label", default="compared runs", help="their legend entry")
    ap.add_argument("--fill", action="store_true",
                    help="add the peak scleral stress to runs made before it was recorded, "
                    "and evaluate the indentation with its bands weighted by area (from their "
                    "final checkpoints; one process per run)")
    args = ap.parse_args(argv)
    cases, levels = args.cases.split(","), args.levels.split(",")
    lsq = args.least_squares.split(",") if args.least_squares else None
    runs = Path(args.runs)
    if args.record:
        record = json.loads(Path(args.record).read_text())
        study = collect_record(record, cases, levels, args.candidate, lsq)
        other = (collect_record(record, cases, args.compare_levels.split(","), args.candidate)
                 if args.compare_levels else {})
    elif not args.no_run:
        run_missing(cases, levels, runs, Path(args.case_dir))
    if args.fill and not args.record:
        for case in cases:
            for lv in levels:
                d = runs / case / lv
                if (d / "summary.json").exists() and not set(FILLED) <= set(json.loads(
                        (d / "summary.json").read_text())):
                    log.info("outcomes of %s at %s from its checkpoint", case, lv)
                    subprocess.call([sys.executable, __file__, "fill",
                                     str(Path(args.case_dir) / f"{case}.toml"), lv, str(d)])
    if not args.record:
        study = collect(cases, levels, runs, args.candidate, lsq)
        other = (collect(cases, levels, Path(args.compare), args.candidate) if args.compare
                 else {})
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    images = Path(args.images) if args.images else out / "images"
    (out / "convergence.json").write_text(json.dumps(study, indent=1) + "\n")
    (out / "convergence_table.md").write_text(markdown(study) + "\n")
    for case, s in study.items():
        plot(case, s, images / f"convergence_{case}.png", other.get(case), args.compare_label)
    log.info("wrote %s, %s and the plots in %s", out / "convergence.json",
             out / "convergence_table.md", images)
    return 0


if __name__ == "__main__":
    sys.exit(main())
