"""The sweep file: a base case, what to vary, what to record; and the planned runs.

A sweep file is TOML (docs/sweep.md)::

    [sweep]
    case = "../surgery/case1.toml"        # base case, relative to this file
    outcomes = ["iop_mmhg", "refraction_change_D"]
    gradients = ["tightening"]            # optional: adjoint (surgery design variables)
                                          # or central differences (dotted paths)

    [set]                                 # the same override in every run
    parameters.mesh = "coarse"

    [grid]                                # cartesian product of the values
    parameters.tightening = [4.0, 6.0, 8.0]

    [samples]                             # random or Latin-hypercube samples
    n = 16
    seed = 1
    method = "lhs"
    materials.sclera.c10 = { dist = "normal", mean = 0.0833, std = 0.0125 }

An override is a dotted path into the case: ``parameters.NAME``, ``materials.NAME.cRS``
or ``solver.NAME``. The runs are the cartesian product of the blocks present (grid,
list, samples). Every run's case is the base case's TOML with the overrides, parsed and
validated by :func:`eyefem.io.casefile.load_case` like any case file.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import itertools
import json
import math
import os
import re
import tempfile
import tomllib
from pathlib import Path

import numpy as np

from eyefem.catalog import schemas, solver_defaults
from eyefem.eye.presets import SEED_MATERIALS
from eyefem.eye.variables import DESIGN_VARIABLES, OUTCOMES
from eyefem.io import manifest
from eyefem.io.casefile import SOLVER_FIELDS, Case, CaseError, load_case

SECTIONS = ("sweep", "set", "grid", "list", "samples", "best")
SWEEP_FIELDS = {
    "case": "base case file, relative to the sweep file (required)",
    "title": "title of the sweep",
    "outcomes": "names of the summary (or last recorded step) to record; default: every number",
    "gradients": "inputs to differentiate the outcomes by: design variables "
                 "(eyefem.eye.variables.DESIGN_VARIABLES) of a surgery case, by the adjoint "
                 "(eyefem.simulate), or dotted paths (parameters.NAME, materials.NAME.cRS) "
                 "of any case, by central differences (two more solves each); default none",
    "fd_step": "relative step of the central differences: h = fd_step |x| (fd_step if x = 0); "
               "default 1e-3",
    "output": "output folder, relative to the current folder; default results/sweeps/<stem>",
    "vtu": "write each run's VTU series (default false: saves disk)",
    "plots": "write each run's own plots (default false); the sweep's plots are always made",
}
DISTRIBUTIONS = {
    "normal": ("mean", "std"),
    "uniform": ("low", "high"),
    "lognormal": ("median", "sigma"),
}
"""Distribution -> its parameters: normal (mean, std > 0); uniform on [low, high);
lognormal: x = median * exp(sigma * z), z standard normal (sigma > 0: std of log x)."""
METHODS = ("lhs", "random")
BEST_GOALS = ("min", "max", "target")
RUNNING_STATUSES = ("ok", "failed", "did-not-converge")
FD_STEP = 1e-3
"""Default relative step of the central differences (h = FD_STEP |x|): small enough for a
truncation error of order 1e-6 relative on smooth outcomes, large enough that Newton's
tolerance (rtol 1e-8) costs about 1e-5 relative."""
ADJOINT, CENTRAL = "adjoint", "central differences"


class SweepError(ValueError):
    """A sweep file is invalid; the message names the file, section, field and the fix."""


@dataclasses.dataclass(frozen=True)
class Distribution:
    """A stated distribution of one parameter (see :data:`DISTRIBUTIONS`)."""

    kind: str
    a: float
    b: float

    def ppf(self, u: np.ndarray) -> np.ndarray:
        """The quantiles at u in (0, 1) (inverse CDF)."""
        from scipy.special import ndtri

        u = np.asarray(u, np.float64)
        if self.kind == "normal":
            return self.a + self.b * ndtri(u)
        if self.kind == "uniform":
            return self.a + (self.b - self.a) * u
        return self.a * np.exp(self.b * ndtri(u))

    @property
    def centre(self) -> float:
        """Where a first-order expansion is taken: the mean (normal, uniform) or the
        median (lognormal)."""
        return self.a if self.kind != "uniform" else 0.5 * (self.a + self.b)

    def linear_std(self) -> float:
        """The std of x (normal, uniform) or of log x (lognormal)."""
        if self.kind == "uniform":
            return (self.b - self.a) / math.sqrt(12.0)
        return self.b

    def describe(self) -> str:
        names = DISTRIBUTIONS[self.kind]
        return f"{self.kind}({names[0]}={self.a:g}, {names[1]}={self.b:g})"


@dataclasses.dataclass(frozen=True)
class Sweep:
    """A validated sweep file.

    Attributes: path; case_path (the base case); base (its parsed Case); title;
    outcomes (names; () = every number of the summary); gradients (design variables);
    output (folder); vtu, plots (each run's own outputs); fixed (path -> value, every
    run); rows (one dict path -> value per run, before ``fixed``); varied (the paths
    that vary, in order); distributions (path -> Distribution, for sampled paths);
    best (outcome, goal, target, show) for the table of best designs; fd_step (relative
    step of the central-difference gradients).
    """

    path: Path
    case_path: Path
    base: Case
    title: str
    outcomes: tuple[str, ...]
    gradients: tuple[str, ...]
    output: Path
    vtu: bool
    plots: bool
    fixed: dict
    rows: list[dict]
    varied: tuple[str, ...]
    distributions: dict
    best: dict
    fd_step: float = FD_STEP


@dataclasses.dataclass(frozen=True)
class PlannedRun:
    """One run of a sweep: its index, overrides, case text (TOML) and run hash.

    ``run_hash`` is the sha256 of the parsed case with the overrides (eyefem.io.manifest
    case_key), the code version and the gradients asked for: equal hash <=> the same
    computation, so a completed run of that hash is not repeated."""

    index: int
    overrides: dict
    case_text: str
    run_hash: str
    folder: str


def _suggest(name: str, choices) -> str:
    m = difflib.get_close_matches(str(name), [str(c) for c in choices], n=1)
    return f" (did you mean '{m[0]}'?)" if m else ""


def _flatten(d: dict, prefix: str, leaf) -> dict:
    """Nested tables -> dotted path -> value; ``leaf(v)`` says where a path ends."""
    out = {}
    for k, v in d.items():
        p = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict) and not leaf(v):
            out.update(_flatten(v, p, leaf))
        else:
            out[p] = v
    return out


def check_path(path: str, base: Case, where: str) -> None:
    """SweepError unless ``path`` names a field of the base case's problem, a material
    coefficient or a solver option."""
    fields = [f.name for f in schemas()[base.problem]]
    parts = path.split(".")
    head = parts[0]
    if head == "parameters" and len(parts) == 2:
        if parts[1] not in fields:
            raise SweepError(f"{where}: '{path}': problem '{base.problem}' has no parameter "
                             f"'{parts[1]}'{_suggest(parts[1], fields)}; its parameters: "
                             f"{', '.join(fields)}")
        return
    if head == "materials" and len(parts) == 3:
        names = set(base.materials) | (set(SEED_MATERIALS) if base.problem == "surgery" else set())
        if parts[1] not in names:
            raise SweepError(f"{where}: '{path}': unknown material '{parts[1]}'"
                             f"{_suggest(parts[1], names)}; the case's materials: "
                             f"{', '.join(sorted(names))}")
        if not re.fullmatch(r"c[0-3][0-3]", parts[2]):
            raise SweepError(f"{where}: '{path}': unknown coefficient '{parts[2]}'; give a "
                             "Mooney-Rivlin coefficient c10, c01, c20, ... (MPa)")
        return
    if head == "solver" and len(parts) == 2:
        names = [f.name for f in SOLVER_FIELDS]
        if parts[1] not in names:
            raise SweepError(f"{where}: '{path}': unknown solver option '{parts[1]}'"
                             f"{_suggest(parts[1], names)}; options: {', '.join(names)}")
        return
    hint = ""
    if path in fields:
        hint = f" (did you mean 'parameters.{path}'?)"
    elif path.startswith("c10_") and path[4:] in SEED_MATERIALS:
        hint = f" (did you mean 'materials.{path[4:]}.c10'?)"
    else:
        cands = [f"parameters.{f}" for f in fields] + [f"solver.{f.name}" for f in SOLVER_FIELDS]
        cands += [f"materials.{m}.c10" for m in base.materials]
        hint = _suggest(path, cands)
    raise SweepError(f"{where}: unknown parameter '{path}'{hint}; give parameters.NAME, "
                     "materials.NAME.c10 (or another coefficient) or solver.NAME")


def design_variable(path: str) -> str | None:
    """The design variable (eyefem.eye.variables) a sweep path sets, or None:
    materials.<m>.c10 -> c10_<m>; parameters.<name> -> <name> for a design variable."""
    parts = path.split(".")
    if len(parts) == 3 and parts[0] == "materials" and parts[2] == "c10":
        name = f"c10_{parts[1]}"
    elif len(parts) == 2 and parts[0] == "parameters":
        name = parts[1]
    else:
        return None
    return name if name in DESIGN_VARIABLES else None


def differentiable_input(name: str, base: Case, body: str, where: str) -> tuple[str, str]:
    """How the outcomes are differentiated by the input ``name``: (key, method).

    A design variable (``tightening`` or its path ``parameters.tightening``,
    ``materials.sclera.c10`` -> ``c10_sclera``) of a rigid-buckle surgery case: (design
    variable, ADJOINT). Any other real-valued input given by its dotted path
    (``parameters.axial_length``, ``materials.rubber.c01``): (path, CENTRAL), two more
    solves at x +- h. SweepError (naming the input, the reason and the fix) otherwise.
    ``body`` is the runs' buckle body (surgery cases)."""
    surgery = base.problem == "surgery"
    fields = {f.name: f for f in schemas()[base.problem]}
    if "." not in name:
        if name in DESIGN_VARIABLES:
            if not surgery:
                raise SweepError(f"{where}: '{name}' is a design variable of the surgery cases: "
                                 "gradients need a surgery case (eyefem.simulate) for the "
                                 f"adjoint; the base case's problem is '{base.problem}'; give "
                                 "a dotted path (parameters.NAME, materials.NAME.cRS) for "
                                 "central differences, or remove it")
            key = name
        elif name in fields:
            raise SweepError(f"{where}: '{name}' is not a design variable (no adjoint "
                             f"gradient); give its path 'parameters.{name}' for central "
                             "differences (two more solves)")
        else:
            raise SweepError(f"{where}: unknown input '{name}'"
                             f"{_suggest(name, list(DESIGN_VARIABLES) + list(fields))}; give a "
                             f"design variable ({', '.join(DESIGN_VARIABLES)}) of a surgery "
                             "case or a dotted path (parameters.NAME, materials.NAME.cRS)")
    else:
        check_path(name, base, where)
        parts = name.split(".")
        if parts[0] == "solver":
            raise SweepError(f"{where}: '{name}' is a solver option, not an input of the model; "
                             "it has no derivative: remove it")
        kind = fields[parts[1]].type if parts[0] == "parameters" else float
        if kind is not float:
            what = {int: "an integer", str: "a text", bool: "a true/false"}.get(kind, "a list")
            raise SweepError(f"{where}: '{name}' is {what} parameter; a derivative needs a "
                             "real-valued (float) parameter: remove it")
        key = (design_variable(name) if surgery else None) or name
    if surgery and body != "rigid":
        raise SweepError(f"{where}: '{name}': gradients need a rigid buckle (eyefem.simulate); "
                         f"the case has buckle_body = '{body}'; set buckle_body = \"rigid\" "
                         "or remove it")
    return key, (ADJOINT if "." not in key else CENTRAL)


def value_of(case: Case, path: str) -> float:
    """The value of a dotted path (parameters.NAME, materials.NAME.cRS) in a parsed case;
    ValueError naming the path when the case does not hold it."""
    parts = path.split(".")
    if parts[0] == "parameters" and parts[1] in case.parameters:
        return float(case.parameters[parts[1]])
    if parts[0] == "materials" and len(parts) == 3 and parts[1] in case.materials:
        return float(np.asarray(case.materials[parts[1]].coeffs)[int(parts[2][1]),
                                                                  int(parts[2][2])])
    raise ValueError(f"{case.path}: '{path}' has no value in the case; give it in the case "
                     "file (its own table for a material) to differentiate by it")


def fd_step(x0: float, rel: float = FD_STEP) -> float:
    """The step h of a central difference at x0: rel |x0|, or rel when x0 = 0."""
    return rel * abs(x0) if x0 != 0 else rel


def _distribution(spec, where: str) -> Distribution:
    if not isinstance(spec, dict):
        raise SweepError(f"{where} = {spec!r}: give a distribution table, e.g. "
                         "{ dist = \"normal\", mean = 0.0833, std = 0.0125 }")
    kind = spec.get("dist")
    if kind not in DISTRIBUTIONS:
        raise SweepError(f"{where}: dist = {kind!r} is not a known distribution"
                         f"{_suggest(kind, DISTRIBUTIONS) if kind else ''}; give one of "
                         f"{', '.join(DISTRIBUTIONS)}")
    names = DISTRIBUTIONS[kind]
    extra = set(spec) - {"dist", *names}
    if extra:
        raise SweepError(f"{where}: {kind} distribution has no parameter "
                         f"'{min(extra)}'; it takes {' and '.join(names)}")
    vals = []
    for n in names:
        v = spec.get(n)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise SweepError(f"{where}: {kind} distribution needs a finite number '{n}' "
                             f"(got {v!r}); it takes {' and '.join(names)}")
        vals.append(float(v))
    a, b = vals
    if kind == "normal" and b <= 0:
        raise SweepError(f"{where}: normal std = {b:g}; must be > 0")
    if kind == "uniform" and not a < b:
        raise SweepError(f"{where}: uniform low = {a:g}, high = {b:g}; need low < high")
    if kind == "lognormal" and (a <= 0 or b <= 0):
        raise SweepError(f"{where}: lognormal median = {a:g}, sigma = {b:g}; both must be > 0")
    return Distribution(kind, a, b)


def sample_rows(dists: dict[str, Distribution], n: int, seed: int, method: str) -> list[dict]:
    """n rows path -> value drawn from independent distributions: 'random' (i.i.d.) or
    'lhs' (Latin hypercube: one draw in each of n equal-probability strata per path, the
    strata paired at random). Reproducible from ``seed``."""
    rng = np.random.default_rng(seed)
    cols = {}
    for path, d in dists.items():
        if method == "lhs":
            u = (rng.permutation(n) + rng.random(n)) / n
        else:
            u = rng.random(n)
        cols[path] = d.ppf(np.clip(u, 1e-12, 1 - 1e-12))
    return [{p: float(cols[p][i]) for p in dists} for i in range(n)]


def load_sweep(path: str | Path) -> Sweep:
    """Read and validate a sweep file; SweepError (with the fix) when it is wrong."""
    path = Path(path)
    if not path.is_file():
        raise SweepError(f"sweep file '{path}' does not exist" if not path.exists() else
                         f"sweep file '{path}' is not a file; give a .toml sweep file")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise SweepError(f"{path}: not a text file; a sweep file is TOML text") from None
    except tomllib.TOMLDecodeError as exc:
        raise SweepError(f"{path}: not valid TOML: {exc}") from None
    for k in raw:
        if k not in SECTIONS:
            raise SweepError(f"{path}: unknown section [{k}]{_suggest(k, SECTIONS)}; "
                             f"valid sections: {', '.join(SECTIONS)}")
    head = raw.get("sweep", {})
    for k in head:
        if k not in SWEEP_FIELDS:
            raise SweepError(f"{path} [sweep]: unknown field '{k}'{_suggest(k, SWEEP_FIELDS)}; "
                             f"valid fields: {', '.join(SWEEP_FIELDS)}")
    if "case" not in head or not isinstance(head["case"], str):
        raise SweepError(f"{path} [sweep]: missing 'case' (the base case file, relative to the "
                         "sweep file), e.g. case = \"../surgery/case1.toml\"")
    case_path = (path.parent / head["case"])
    if not case_path.is_file():
        raise SweepError(f"{path} [sweep]: base case '{head['case']}' not found (looked for "
                         f"{case_path}); the path is relative to the sweep file's folder")
    try:
        base = load_case(case_path, schemas(), solver_defaults())
    except CaseError as exc:
        raise SweepError(f"{path} [sweep] case: {exc}") from None

    def strings(name):
        v = head.get(name, [])
        if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
            raise SweepError(f"{path} [sweep]: {name} = {v!r}; give a list of names, "
                             "e.g. [\"iop_mmhg\"]")
        if len(set(v)) != len(v):
            raise SweepError(f"{path} [sweep]: {name} lists a name twice: {v}")
        return tuple(v)

    outcomes, given = strings("outcomes"), strings("gradients")
    body = head_fixed_body(raw, base)
    gradients = tuple(dict.fromkeys(differentiable_input(g, base, body, f"{path} [sweep] "
                                                         "gradients")[0] for g in given))
    if len(gradients) != len(given):
        raise SweepError(f"{path} [sweep]: gradients name one input twice (a design variable "
                         f"and its path): {list(given)}")
    step = head.get("fd_step", FD_STEP)
    if isinstance(step, bool) or not isinstance(step, (int, float)) or not 0 < step <= 0.1:
        raise SweepError(f"{path} [sweep]: fd_step = {step!r}; give the relative step of the "
                         "central differences, a number in (0, 0.1], e.g. 1e-3")
    if gradients and base.problem == "surgery":
        for o in outcomes:
            if o not in OUTCOMES:
                raise SweepError(f"{path} [sweep]: gradients are of the surgery outcomes "
                                 f"({', '.join(OUTCOMES)}); '{o}' is not one"
                                 f"{_suggest(o, OUTCOMES)}")
    for flag in ("vtu", "plots"):
        if not isinstance(head.get(flag, False), bool):
            raise SweepError(f"{path} [sweep]: {flag} = {head[flag]!r}; give true or false")
    output = head.get("output", str(Path("results") / "sweeps" / path.stem))
    if not isinstance(output, str) or not output:
        raise SweepError(f"{path} [sweep]: output = {output!r}; give a folder name")

    def is_value(v):
        return not isinstance(v, dict)

    fixed = _flatten(raw.get("set", {}), "", lambda v: False)
    for p, v in fixed.items():
        check_path(p, base, f"{path} [set]")
    blocks: list[list[dict]] = []
    grid = _flatten(raw.get("grid", {}), "", is_value)
    for p, v in grid.items():
        check_path(p, base, f"{path} [grid]")
        if not isinstance(v, list) or not v:
            raise SweepError(f"{path} [grid]: '{p}' = {v!r}; give a non-empty list of values")
    if grid:
        _check_count(math.prod(len(v) for v in grid.values()), f"{path} [grid]")
        blocks.append([dict(zip(grid, combo)) for combo in itertools.product(*grid.values())])
    rows_in = raw.get("list", [])
    if rows_in:
        if not isinstance(rows_in, list) or not all(isinstance(r, dict) for r in rows_in):
            raise SweepError(f"{path} [list]: write each run as a [[list]] table of "
                             "path = value")
        rows = [_flatten(r, "", lambda v: False) for r in rows_in]
        for i, r in enumerate(rows):
            for p in r:
                check_path(p, base, f"{path} [[list]] row {i + 1}")
        blocks.append(rows)
    dists: dict[str, Distribution] = {}
    samples = raw.get("samples")
    if samples is not None:
        ctl = {k: samples[k] for k in ("n", "seed", "method") if k in samples}
        n, seed = ctl.get("n"), ctl.get("seed")
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise SweepError(f"{path} [samples]: n = {n!r}; give the number of samples "
                             "(an integer >= 1)")
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise SweepError(f"{path} [samples]: seed = {seed!r}; give an integer seed so "
                             "that the samples can be drawn again")
        _check_count(n, f"{path} [samples]")
        method = ctl.get("method", "lhs")
        if method not in METHODS:
            raise SweepError(f"{path} [samples]: method = {method!r}{_suggest(method, METHODS)}; "
                             f"give one of {', '.join(METHODS)}")
        rest = _flatten({k: v for k, v in samples.items() if k not in ctl}, "",
                        lambda v: "dist" in v)
        if not rest:
            raise SweepError(f"{path} [samples]: no parameter to sample; add e.g. "
                             "materials.sclera.c10 = { dist = \"normal\", mean = 0.0833, "
                             "std = 0.0125 }")
        for p, spec in rest.items():
            check_path(p, base, f"{path} [samples]")
            dists[p] = _distribution(spec, f"{path} [samples] {p}")
        blocks.append(sample_rows(dists, n, seed, method))
    if not blocks:
        raise SweepError(f"{path}: nothing to vary; add a [grid], [[list]] or [samples] "
                         "section (docs/sweep.md)")
    varied: list[str] = []
    for b in blocks:
        keys = [p for r in b for p in r]
        twice = [p for p in dict.fromkeys(keys) if p in varied]
        if twice:
            raise SweepError(f"{path}: '{twice[0]}' is varied in two sections ([grid], "
                             "[[list]], [samples]); vary each parameter in one")
        varied += [p for p in dict.fromkeys(keys)]
    for p in varied:
        if p in fixed:
            raise SweepError(f"{path}: '{p}' is both fixed in [set] and varied; keep one")
    _check_count(math.prod(len(b) for b in blocks), str(path))
    rows = [dict(itertools.chain.from_iterable(r.items() for r in combo))
            for combo in itertools.product(*blocks)]
    best = _best(raw.get("best", {}), outcomes, f"{path} [best]")
    return Sweep(path, case_path, base, head.get("title", path.stem), outcomes, gradients,
                 Path(output), head.get("vtu", False), head.get("plots", False), fixed, rows,
                 tuple(varied), dists, best, float(step))


MAX_RUNS = 10_000
"""The most runs a sweep file may make (``EYEFEM_MAX_RUNS`` raises it): a sweep's runs are
listed before any starts, and 10,000 coarse surgeries already take days on a workstation."""


def _check_count(n: int, where: str):
    """SweepError when a sweep would make more than MAX_RUNS (or EYEFEM_MAX_RUNS) runs."""
    try:
        bound = int(os.environ.get("EYEFEM_MAX_RUNS", MAX_RUNS))
    except ValueError:
        bound = MAX_RUNS
    if n > bound:
        raise SweepError(f"{where}: {n:,} runs, more than the {bound:,} a sweep may make; "
                         "vary fewer values (a coarse grid first, then a finer one where it "
                         "matters), or raise the bound with EYEFEM_MAX_RUNS=N")


def head_fixed_body(raw: dict, base: Case) -> str:
    """The buckle body of a surgery sweep's runs: [set] parameters.buckle_body, else the
    base case's."""
    fixed = _flatten(raw.get("set", {}), "", lambda v: False)
    return str(fixed.get("parameters.buckle_body", base.parameters.get("buckle_body", "rigid")))


def _best(b: dict, outcomes, where: str) -> dict:
    allowed = ("outcome", "goal", "target", "show")
    for k in b:
        if k not in allowed:
            raise SweepError(f"{where}: unknown field '{k}'{_suggest(k, allowed)}; valid "
                             f"fields: {', '.join(allowed)}")
    out = {"outcome": b.get("outcome", outcomes[0] if outcomes else None),
           "goal": b.get("goal", "min"), "target": b.get("target"), "show": b.get("show", 5)}
    if out["goal"] not in BEST_GOALS:
        raise SweepError(f"{where}: goal = {out['goal']!r}; give one of {', '.join(BEST_GOALS)}")
    if out["goal"] == "target" and not isinstance(out["target"], (int, float)):
        raise SweepError(f"{where}: goal = \"target\" needs a number 'target' (the wanted "
                         "value of the outcome)")
    if outcomes and out["outcome"] not in outcomes:
        raise SweepError(f"{where}: outcome '{out['outcome']}' is not recorded"
                         f"{_suggest(out['outcome'], outcomes)}; record it in [sweep] outcomes")
    return out


def _set(raw: dict, path: str, value) -> None:
    parts = path.split(".")
    node = raw
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value


def case_raw(sweep: Sweep, overrides: dict) -> dict:
    """The base case's TOML data with the fixed and the run's overrides (a material not in
    the base case gets a table with the overridden coefficient only). File paths (a
    user's mesh) are made absolute: the base case's relative to the base case, an
    override's relative to the sweep file."""
    raw = copy.deepcopy(sweep.base.raw)
    raw.pop("output", None)
    changes = {**sweep.fixed, **overrides}
    for f in schemas()[sweep.base.problem]:  # file paths: absolute, the run's case lives elsewhere
        p = f"parameters.{f.name}"
        if not getattr(f, "path", False):
            continue
        if isinstance(changes.get(p), str) and changes[p]:
            changes[p] = str((sweep.path.parent / Path(changes[p]).expanduser()).resolve())
        elif sweep.base.parameters.get(f.name):
            changes.setdefault(p, str(sweep.base.parameters[f.name]))
    for p, v in changes.items():
        _set(raw, p, v)
    raw["output"] = {"vtu": sweep.vtu, "plots": sweep.plots}
    return raw


def run_hash(case: Case, gradients=(), rel_step: float = FD_STEP) -> str:
    """The hash naming a run: the parsed case (manifest.case_key), the code version and
    the gradients asked for (with the step, when some are central differences)."""
    key = manifest.case_key(case.problem, case.parameters, case.materials, case.solver)
    what = {"case": key, "code_version": manifest.code_version(), "gradients": sorted(gradients)}
    if any("." in g for g in gradients):
        what["fd_step"] = rel_step
    return manifest.case_hash(json.dumps(what, sort_keys=True))


def plan(sweep: Sweep) -> tuple[list[PlannedRun], list[tuple[int, dict, str]]]:
    """The runs of a sweep: (planned runs, invalid rows as (index, overrides, message)).

    Each row's case is written as TOML and read back with load_case (so a run is
    validated exactly as a case file); a row that load_case refuses is not run and is
    reported with the message."""
    import tomli_w

    runs, invalid = [], []
    with tempfile.TemporaryDirectory(prefix="eyefem-sweep-") as tmp:
        for i, row in enumerate(sweep.rows):
            text = f"# run {i} of sweep {sweep.path} (base case {sweep.case_path})\n"
            text += tomli_w.dumps(case_raw(sweep, row))
            f = Path(tmp) / f"run{i}.toml"
            f.write_text(text, encoding="utf-8")
            try:
                case = load_case(f, schemas(), solver_defaults())
            except CaseError as exc:
                invalid.append((i, row, str(exc).replace(str(f), f"run {i}")))
                continue
            h = run_hash(case, sweep.gradients, sweep.fd_step)
            runs.append(PlannedRun(i, row, text, h, f"{i:04d}_{h[:8]}"))
    return runs, invalid
