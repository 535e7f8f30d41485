"""The mesh error a surgical run quotes beside its outcomes, from the mesh study.

The mesh study (docs/convergence.md) ran cases 1, 4 and 5 on families of three nested or
graded levels; its outcome values are in ``mesh_study.json`` beside this module (written by
``python benchmarks/mesh_convergence.py export``). For a run on one of those levels, each
outcome's error is estimated from the studied cases of the same kind of buckle (encircling:
cases 1 and 4; segmental: case 5), case by case:

- ``gci``: the three levels of a family that holds the level converge monotonically with
  an observed order in 0.5..4; the level's GCI against their Richardson extrapolation
  (Fs = 1.25, relative);
- ``from_extrapolation``: no family that holds the level converges, but another family of
  the same case does (the levels are meshes of one problem, so its extrapolation estimates
  the same exact value): Fs |phi_ext - phi| / |phi| against that family's extrapolation,
  from the converging family with the smallest GCI of its finest level;
- ``from_finest``: no family of the case converges (oscillatory, divergent or an order
  outside 0.5..4); the largest relative difference from the finer levels of the level's
  own family (for a level in no family, from the finest level the case ran), which the
  error is not known to be below (a lower estimate, not a bound);
- ``not_estimated``: the level is the finest of its family and nothing converges, or the
  studied case did not run the level (coarse, medium, graded<N> not studied).

A level the study ran outside its families of three (``gradedc26``, the surgical cases'
mesh before ``fine``) is estimated the same way: against a converging family's
extrapolation, else from the finest level the case ran.

Each estimate names the family it comes from (``family``).

The study used the seed's tissue constants and the case files' other parameters: for other
materials, tightenings or positions the figures say what the mesh did on the studied cases,
not on this run. Pure numpy; the file is read once per call (it is small).
"""

from __future__ import annotations

import json
import math
from functools import lru_cache
from pathlib import Path

from eyefem.eye.convergence import MONOTONE, relative_gci, three_grid_study

STUDY_FILE = Path(__file__).with_name("mesh_study.json")
"""The mesh study's outcome values per case and level (JSON, no code)."""

QUOTED = {  # summary key -> (label, unit)
    "iop_rise_mmhg": ("IOP rise", "mmHg"),
    "indentation_mm": ("indentation", "mm"),
    "axial_length_change_mm": ("axial length change", "mm"),
    "refraction_change_D": ("refraction change", "D"),
    "max_suture_force_N": ("largest suture force", "N"),
    "scleral_stress_kPa": ("scleral stress", "kPa"),
}
"""The outcomes a run quotes a mesh error for (the bounded ones of issue 29 and the stress)."""

GCI, FROM_EXTRAPOLATION, FROM_FINEST, NOT_ESTIMATED = (
    "gci", "from_extrapolation", "from_finest", "not_estimated")


@lru_cache(maxsize=4)
def load_study(path: str | None = None) -> dict:
    """The study record: {"materials", "families": [[fine, mid, coarse], ...], "cases":
    {case: {"encircling": bool, "model": {field: value}, "levels": {level: {"n_per_edge",
    "elements", "values": {outcome: value}}}}}}."""
    p = Path(path) if path else STUDY_FILE
    try:
        study = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"mesh study record {p}: cannot read it ({exc}); reinstall eyefem, "
                         "or write it with 'python benchmarks/mesh_convergence.py export'") \
            from exc
    for key in ("families", "cases"):
        if key not in study:
            raise ValueError(f"mesh study record {p}: no '{key}'; write it with "
                             "'python benchmarks/mesh_convergence.py export'")
    return study


def _triple(levels: dict, family: list[str], outcome: str):
    """The three-grid study of one outcome over one family of one case's runs, or None
    when a level of the family was not run or did not record the outcome."""
    if not all(lv in levels for lv in family):
        return None
    vals = [levels[lv]["values"].get(outcome) for lv in family]
    if not all(_finite(v) for v in vals):
        return None
    return three_grid_study([1.0 / levels[lv]["n_per_edge"] for lv in family], vals)


def _converges(s) -> bool:
    return s is not None and s.behaviour == MONOTONE and not s.note


def case_estimate(levels: dict, family: list[str], level: str, outcome: str) -> dict:
    """The error estimate of one outcome at ``level`` from one case's runs of one family
    that holds the level.

    Args: levels: level -> {"n_per_edge", "values"}; family: three level names, fine first.
    Returns: {"kind", "relative" (or None), "behaviour", "p" (or None), "family"};
    ``from_finest`` adds "compared" (the finer levels the difference is taken from)."""
    s = _triple(levels, family, outcome)
    if s is None:
        return {"kind": NOT_ESTIMATED, "relative": None, "behaviour": "not run", "p": None,
                "family": family}
    phi = levels[level]["values"][outcome]
    p = s.p if math.isfinite(s.p) else None
    if _converges(s):
        return {"kind": GCI, "relative": relative_gci(phi, s.extrapolated),
                "behaviour": s.behaviour, "p": p, "family": family}
    # the largest difference from the family's levels finer than this one (the values
    # oscillate: the finest level alone can lie closer than the one between)
    above = family[:family.index(level)]
    finer = [levels[lv]["values"][outcome] for lv in above]
    if finer and all(v != 0 for v in finer):
        return {"kind": FROM_FINEST, "relative": max(abs(phi - v) / abs(v) for v in finer),
                "behaviour": s.behaviour, "p": p, "family": family, "compared": above}
    return {"kind": NOT_ESTIMATED, "relative": None, "behaviour": s.behaviour, "p": p,
            "family": family}


def best_estimate(levels: dict, families: list[list[str]], level: str, outcome: str) -> dict:
    """The error estimate of one outcome at ``level`` from all of one case's families, in
    the module's order of preference: the GCI in a family that holds the level; else the
    GCI-like figure against the extrapolation of another, converging family (the one
    whose finest level's GCI is smallest); else the first holding family's
    ``from_finest`` or ``not_estimated``: of the families the case ran, the one whose top
    level is finest first (a level in no family: ``from_finest`` against the finest level
    the case ran).

    Returns: case_estimate's dict; ``from_extrapolation`` adds "extrapolated" (the
    family's Richardson value)."""
    own = [f for f in families if level in f]
    # the families the case ran, the one with the finest top level first (the finest
    # level ran for one case only: a family the case did not run comes last)
    estimates = sorted((case_estimate(levels, f, level, outcome) for f in own),
                       key=lambda e: (e["behaviour"] == "not run",
                                      -levels.get(e["family"][0], {}).get("n_per_edge", 0)))
    for e in estimates:
        if e["kind"] == GCI:
            return e
    phi = levels.get(level, {}).get("values", {}).get(outcome)
    if _finite(phi) and phi != 0:
        studies = [(s, f) for f in families if f not in own
                   for s in (_triple(levels, f, outcome),) if _converges(s)]
        if studies:
            s, f = min(studies, key=lambda sf: sf[0].gci_fine)
            return {"kind": FROM_EXTRAPOLATION, "relative": relative_gci(phi, s.extrapolated),
                    "behaviour": estimates[0]["behaviour"] if estimates else "not in a family",
                    "p": s.p, "family": f, "extrapolated": s.extrapolated}
    if estimates:
        return estimates[0]
    # a level outside every family: its difference from the finest level the case ran
    ran = [f for f in families if f[0] in levels
           and _finite(levels[f[0]]["values"].get(outcome))]
    if ran and _finite(phi):
        f = max(ran, key=lambda f: levels[f[0]]["n_per_edge"])
        finest = levels[f[0]]["values"][outcome]
        if f[0] != level and finest != 0:
            return {"kind": FROM_FINEST, "relative": abs(phi - finest) / abs(finest),
                    "behaviour": "not in a family", "p": None, "family": f,
                    "compared": f[:1]}
    return {"kind": NOT_ESTIMATED, "relative": None, "behaviour": "not in a family", "p": None,
            "family": None}


def _finite(v) -> bool:
    """A recorded outcome value that is a finite number (not None, NaN or missing)."""
    return isinstance(v, (int, float)) and math.isfinite(v)


def mesh_error(level: str, encircling: bool, values: dict | None = None,
               study: dict | None = None) -> dict:
    """The mesh error of a run's outcomes at ``level`` (for summary.json's "mesh_error").

    Args: level: the run's eye mesh level; encircling: its buckle encircles the globe;
      values: the run's outcomes (keys of QUOTED), for the errors in their units.
    Returns: {"level", "materials", "cases": [studied cases used], "family": [levels] (the
    first family that holds the level) or None, "model": {case: {field: value}} (the model
    fields each studied case ran with, where the record has them), "outcomes": {outcome:
    {case: best_estimate + "absolute" (the run's value times the relative error, in the
    outcome's unit; None without it)}}, "note"}."""
    study = study or load_study()
    kind = "encircling" if encircling else "segmental"
    cases = {c: rec for c, rec in sorted(study["cases"].items())
             if bool(rec.get("encircling")) == bool(encircling)}
    out = {"level": level, "materials": study.get("materials", "seed"), "cases": list(cases),
           "family": None, "outcomes": {}, "note": ""}
    families = [f for f in study["families"] if level in f]
    usable = {c: rec for c, rec in cases.items()
              if level in rec["levels"]
              or (families and all(lv in rec["levels"] for lv in families[0]))}
    if not usable:
        out["note"] = (f"no studied {kind} case ran level '{level}'; its mesh error is not "
                       "estimated (docs/convergence.md)")
        return out
    out["family"] = families[0] if families else None
    out["cases"] = list(usable)
    out["model"] = {c: rec.get("model", {}) for c, rec in usable.items()}
    values = values or {}
    for k in QUOTED:
        out["outcomes"][k] = {}
        for c, rec in usable.items():
            e = best_estimate(rec["levels"], study["families"], level, k)
            v = values.get(k)
            e["absolute"] = (abs(v) * e["relative"] if e["relative"] is not None
                             and isinstance(v, (int, float)) else None)
            out["outcomes"][k][c] = e
    return out


def quote_lines(err: dict) -> list[str]:
    """Lines that quote the mesh error of :func:`mesh_error` (for the terminal), its note
    last."""
    if not err.get("outcomes"):
        return [f"mesh error: {err.get('note', 'not estimated')}"]
    where = (f"on {'/'.join(err['family'])}" if err.get("family")
             else "outside its families of three")
    head = (f"mesh error of level '{err['level']}' (study of {', '.join(err['cases'])} "
            f"{where}, {err['materials']} materials; docs/convergence.md):")
    lines = [head]
    for k, per_case in err["outcomes"].items():
        label, unit = QUOTED[k]
        parts = []
        for case, e in per_case.items():
            how = e["behaviour"]
            if how == MONOTONE and e["p"] is not None and e["kind"] != GCI:
                how = f"monotone, p = {e['p']:.1f} outside 0.5..4"
            if e["relative"] is None:
                parts.append(f"{case} not estimated ({how})")
                continue
            pct = 100 * e["relative"]
            absolute = f", {e['absolute']:.2g} {unit}" if e["absolute"] is not None else ""
            fam = e.get("family") or err["family"]
            if e["kind"] == GCI:
                what = "GCI" if fam == err["family"] else f"GCI on {'/'.join(fam)}"
            elif e["kind"] == FROM_EXTRAPOLATION:
                what = f"against {'/'.join(fam)}'s extrapolation, p = {e['p']:.1f}"
            else:  # the largest difference from the levels compared with
                what = f"from {'/'.join(e['compared'])}, {how}"
            parts.append(f"{case} {pct:.1f} %{absolute} ({what})")
        lines.append(f"  {label:<22} " + "; ".join(parts))
    if err.get("note"):
        lines.append(f"  {err['note']}")
    return lines
