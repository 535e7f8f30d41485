"""Case files (TOML): reading and validation against self-documenting schemas.

A case file names a problem and gives its parameters, materials, solver settings
and outputs::

    [case]
    problem = "equibiaxial_sheet"      # which builder (see ``eyefem cases``)
    title = "Seed verification 1"

    [parameters]                       # the problem's own fields (``eyefem describe PROBLEM``)
    stretch = 5.8

    [materials.rubber]                 # generalised Mooney-Rivlin c_rs, MPa
    c10 = 25.0
    c01 = 5.0

    [solver]                           # NewtonOptions fields
    rtol = 1e-8

    [output]
    directory = "results/seed1_sheet"  # relative to the current directory
    vtu = true

Every unknown or mistyped field is an error naming the file, the section, the field
and the valid choices.
"""

from __future__ import annotations

import dataclasses
import difflib
import tomllib
from pathlib import Path
from typing import Any, Callable

from eyefem.fem.materials import MooneyRivlin
from eyefem.solve.solver import NewtonOptions


class CaseError(ValueError):
    """A case file is invalid; the message names the file, section and field."""


@dataclasses.dataclass(frozen=True)
class Field:
    """One documented field of a case-file section.

    Attributes: name; type (float, int, str, bool, list); default (``REQUIRED`` if
    none); doc (with units); check: optional predicate on the value with ``check_doc``
    describing the valid range.
    """

    name: str
    type: type
    default: Any
    doc: str
    check: Callable[[Any], bool] | None = None
    check_doc: str = ""


REQUIRED = object()


def _suggest(name, choices):
    m = difflib.get_close_matches(name, list(choices), n=1)
    return f" (did you mean '{m[0]}'?)" if m else ""


def parse_section(values: dict, fields: list[Field], where: str) -> dict:
    """Validate a section: known names, types, ranges; fill defaults."""
    known = {f.name: f for f in fields}
    for k in values:
        if k not in known:
            raise CaseError(f"{where}: unknown field '{k}'{_suggest(k, known)}; "
                            f"valid fields: {', '.join(sorted(known))}")
    out = {}
    for f in fields:
        if f.name not in values:
            if f.default is REQUIRED:
                raise CaseError(f"{where}: missing required field '{f.name}' ({f.doc})")
            out[f.name] = f.default
            continue
        v = values[f.name]
        if f.type is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if not isinstance(v, f.type) or (f.type in (int, float) and isinstance(v, bool)):
            raise CaseError(f"{where}: field '{f.name}' = {v!r} has type {type(v).__name__}; "
                            f"expected {f.type.__name__} ({f.doc})")
        if f.check is not None and not f.check(v):
            raise CaseError(f"{where}: field '{f.name}' = {v!r} is out of range: {f.check_doc} "
                            f"({f.doc})")
        out[f.name] = v
    return out


OUTPUT_FIELDS = [
    Field("directory", str, "", "output directory; default results/<case file stem>"),
    Field("vtu", bool, True, "write a VTU time series (ParaView .pvd)"),
    Field("plots", bool, True, "write PNG plots"),
]

SOLVER_FIELDS = [
    Field(f.name, type(f.default) if not isinstance(f.default, bool) else bool, f.default,
          f"NewtonOptions.{f.name}")
    for f in dataclasses.fields(NewtonOptions) if f.name != "backend"
] + [Field("backend", str, "", "linear solver backend: '' (default), 'pardiso' or 'superlu'")]


@dataclasses.dataclass(frozen=True)
class Case:
    """A validated case file."""

    path: Path
    problem: str
    title: str
    parameters: dict
    materials: dict[str, MooneyRivlin]
    solver: NewtonOptions
    output: dict
    raw: dict


def load_case(path: str | Path, schemas: dict[str, list[Field]]) -> Case:
    """Read and validate a case file against the problem schemas (problem -> fields)."""
    path = Path(path)
    if not path.is_file():
        raise CaseError(f"case file '{path}' does not exist")
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise CaseError(f"{path}: not valid TOML: {exc}") from None
    top = {"case", "parameters", "materials", "solver", "output"}
    for k in raw:
        if k not in top:
            raise CaseError(f"{path}: unknown section [{k}]{_suggest(k, top)}; "
                            f"valid sections: {', '.join(sorted(top))}")
    case = parse_section(raw.get("case", {}), [
        Field("problem", str, REQUIRED, "problem builder name"),
        Field("title", str, "", "human-readable title"),
        Field("description", str, "", "free text: what the case is and how its terms are defined"),
    ], f"{path} [case]")
    problem = case["problem"]
    if problem not in schemas:
        raise CaseError(f"{path} [case]: problem '{problem}' is unknown{_suggest(problem, schemas)}; "
                        f"known problems: {', '.join(sorted(schemas))}")
    params = parse_section(raw.get("parameters", {}), schemas[problem], f"{path} [parameters]")
    mats = {}
    for name, terms in raw.get("materials", {}).items():
        if not isinstance(terms, dict):
            raise CaseError(f"{path} [materials]: '{name}' must be a table of coefficients")
        try:
            mats[name] = MooneyRivlin.from_terms(name, terms)
        except ValueError as exc:
            raise CaseError(f"{path} [materials.{name}]: {exc}") from None
    solver = parse_section(raw.get("solver", {}), SOLVER_FIELDS, f"{path} [solver]")
    solver["backend"] = solver["backend"] or None
    try:
        opts = NewtonOptions(**solver)
    except ValueError as exc:
        raise CaseError(f"{path} [solver]: {exc}") from None
    out = parse_section(raw.get("output", {}), OUTPUT_FIELDS, f"{path} [output]")
    if not out["directory"]:
        out["directory"] = str(Path("results") / path.stem)
    return Case(path, problem, case["title"] or path.stem, params, mats, opts, out, raw)


def positive(x) -> bool:
    return x > 0


def describe(fields: list[Field]) -> str:
    """Human-readable table of a schema (for ``eyefem describe``)."""
    lines = []
    for f in fields:
        d = "required" if f.default is REQUIRED else repr(f.default)
        lines.append(f"  {f.name:<24} {f.type.__name__:<6} default {d:<12} {f.doc}"
                     + (f" [{f.check_doc}]" if f.check_doc else ""))
    return "\n".join(lines)
