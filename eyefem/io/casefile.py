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
    c01 = 5.0                          # k = 1000: bulk modulus, MPa (absent or 0: exactly
                                       # incompressible; verification problems, user_mesh)

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
import errno
import logging
import math
import os
import re
import stat
import tomllib
from pathlib import Path
from typing import Any, Callable

from eyefem.fem.materials import MooneyRivlin
from eyefem.solve.solver import NewtonOptions

log = logging.getLogger(__name__)


class CaseError(ValueError):
    """A case file is invalid; the message names the file, section and field."""


@dataclasses.dataclass(frozen=True)
class Field:
    """One documented field of a case-file section.

    Attributes: name; type (float, int, str, bool, list); default (``REQUIRED`` if
    none); doc (with units); check: optional predicate on the value with ``check_doc``
    describing the valid range. Numbers must be finite. Plausibility of a number:
    ``warn`` (lo, hi) logs a warning outside it (outside the physiological range),
    ``refuse`` (lo, hi) is an error outside it (impossible); ``unit`` is the field's unit
    and ``slips`` ((unit, factor), ...) the units a user may have typed by mistake, where
    ``factor`` converts a value in that unit into ``unit`` (MPa -> mmHg: 7500.6); the
    message suggests the one that brings the value into ``warn``.
    """

    name: str
    type: type
    default: Any
    doc: str
    check: Callable[[Any], bool] | None = None
    check_doc: str = ""
    warn: tuple[float, float] | None = None
    refuse: tuple[float, float] | None = None
    unit: str = ""
    slips: tuple[tuple[str, float], ...] = ()
    path: bool = False
    """A file path (str), relative to the case file: resolved and checked at reading."""


REQUIRED = object()


def _suggest(name, choices):
    m = difflib.get_close_matches(name, list(choices), n=1)
    return f" (did you mean '{m[0]}'?)" if m else ""


def unit_slip(value: float, plausible: tuple[float, float], unit: str,
              slips: tuple[tuple[str, float], ...]) -> str:
    """The likely unit mistake behind an implausible value, e.g. "did you give MPa?
    15 mmHg = 0.002 MPa", or ""."""
    for other, factor in slips:
        v = value * factor
        if plausible[0] <= v <= plausible[1]:
            return f"did you give {other}? {v:.3g} {unit} = {value:g} {other}"
    return ""


def plausibility(value: float, f: Field, where: str) -> None:
    """Refuse (CaseError) or warn (logged) when a number is outside ``f``'s ranges."""
    unit = f" {f.unit}" if f.unit else ""
    for rng, refuse in ((f.refuse, True), (f.warn, False)):
        if rng is None or rng[0] <= value <= rng[1]:
            continue
        slip = unit_slip(value, f.warn or rng, f.unit, f.slips)
        what = "impossible" if refuse else "outside the plausible range"
        msg = (f"{where}: field '{f.name}' = {value:g}{unit} is {what} "
               f"({rng[0]:g} to {rng[1]:g}{unit})" + (f": {slip}" if slip else ""))
        if refuse:
            raise CaseError(msg + f" ({f.doc})")
        log.warning("%s; check the value and its unit", msg)
        return


def check_finite(value, name: str, where: str) -> None:
    """CaseError naming the field when a number (or a number in a list) is nan or inf."""
    items = value if isinstance(value, list) else [value]
    for v in items:
        if isinstance(v, float) and not math.isfinite(v):
            raise CaseError(f"{where}: field '{name}' = {value!r} is not a finite number; "
                            "give a finite value")


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
        check_finite(v, f.name, where)
        if f.check is not None and not f.check(v):
            hint = _suggest(v, re.findall(r"'([^']+)'", f.check_doc)) if isinstance(v, str) else ""
            raise CaseError(f"{where}: field '{f.name}' = {v!r} is out of range: {f.check_doc} "
                            f"({f.doc}){hint}")
        if f.type in (int, float):
            plausibility(v, f, where)
        out[f.name] = v
    return out


OUTPUT_FIELDS = [
    Field("directory", str, "", "output directory; default results/<case file stem>"),
    Field("vtu", bool, True, "write a VTU time series (ParaView .pvd)"),
    Field("xdmf", bool, False, "also write the mesh's frames as one XDMF time series "
          "(<name>.xdmf, arrays in <name>.h5 when h5py is installed)"),
    Field("plots", bool, True, "write PNG plots"),
]

SOLVER_FIELDS = [
    Field(f.name, type(f.default) if not isinstance(f.default, bool) else bool, f.default,
          f"NewtonOptions.{f.name}")
    for f in dataclasses.fields(NewtonOptions) if f.name != "backend"
] + [Field("backend", str, "", "linear solver backend: '' (default), 'pardiso', 'cudss' (a GPU) or 'superlu'")]


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


def with_parameters(case: Case, **values) -> Case:
    """A new Case with the given ``[parameters]`` replaced (``case`` is left as it was);
    CaseError naming a parameter the case's problem does not have."""
    for name in values:
        if name not in case.parameters:
            raise CaseError(f"{case.path}: problem '{case.problem}' has no parameter "
                            f"'{name}'{_suggest(name, case.parameters)}")
    return dataclasses.replace(case, parameters={**case.parameters, **values})


def with_mesh(case: Case, level: str) -> Case:
    """A new Case on the eye mesh level ``level`` (its ``[parameters] mesh``: "coarse",
    "fine", ...); CaseError for a problem without a mesh level (``--mesh`` does not
    apply)."""
    if "mesh" not in case.parameters:
        raise CaseError(f"{case.path}: problem '{case.problem}' has no mesh level; drop --mesh")
    return with_parameters(case, mesh=level)


def load_case(path: str | Path, schemas: dict[str, list[Field]],
              solver_defaults: dict | None = None) -> Case:
    """Read and validate a case file against the problem schemas (problem -> fields).

    ``solver_defaults``: problem -> ``f(parameters) -> dict`` of ``[solver]`` settings the
    problem wants for these parameters (the surgery's contact tangent for a rigid ridged
    tire or rounded sponge: eyefem.eye.surgery.solver_settings); a setting the case file's
    own ``[solver]`` gives wins."""
    path = Path(path)
    if path.is_dir():
        raise CaseError(f"case file '{path}' is a directory; give a .toml case file "
                        f"(list them with: eyefem cases {path})")
    if not path.is_file():
        raise CaseError(f"case file '{path}' does not exist")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise CaseError(f"{path}: not a text file (a case file is TOML text, UTF-8); "
                        "did you give a result or mesh file?") from None
    except OSError as exc:
        raise CaseError(f"{path}: cannot read the case file: {exc.strerror or exc}") from None
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
    for f in schemas[problem]:
        if f.path and params.get(f.name):
            given = Path(params[f.name]).expanduser()
            found = given if given.is_absolute() else (path.parent / given)
            where = f"{path} [parameters]: field '{f.name}' = '{params[f.name]}'"
            try:
                st = os.stat(found)
            except OSError as exc:
                what = ("a loop of symbolic links" if exc.errno == errno.ELOOP
                        else "no such file")
                raise CaseError(f"{where}: {what} ({os.path.abspath(found)}); paths are "
                                "relative to the case file") from None
            if stat.S_ISDIR(st.st_mode):
                raise CaseError(f"{where}: is a folder ({os.path.abspath(found)}); give the "
                                "mesh file in it (paths are relative to the case file)")
            if not stat.S_ISREG(st.st_mode):
                raise CaseError(f"{where}: not a regular file ({os.path.abspath(found)}); "
                                "give a mesh file")
            params[f.name] = os.path.realpath(found)
    mats = {}
    for name, terms in raw.get("materials", {}).items():
        if not isinstance(terms, dict):
            raise CaseError(f"{path} [materials]: '{name}' must be a table of coefficients")
        for k, v in terms.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise CaseError(f"{path} [materials.{name}]: coefficient '{k}' = {v!r} is not a "
                                "number; give it in MPa, e.g. c10 = 0.0833")
        try:
            mats[name] = MooneyRivlin.from_terms(name, terms)
        except ValueError as exc:
            raise CaseError(f"{path} [materials.{name}]: {exc}") from None
        c10 = terms.get("c10")
        if isinstance(c10, (int, float)) and not isinstance(c10, bool):
            plausibility(float(c10), material_c10_field(name), f"{path} [materials.{name}]")
        mu = 2.0 * (float(terms.get("c10", 0.0)) + float(terms.get("c01", 0.0)))
        if 0.0 < mu < MIN_SHEAR_MODULUS:
            raise CaseError(f"{path} [materials.{name}]: initial shear modulus 2 (c10 + c01) = "
                            f"{mu:.3g} MPa is below {MIN_SHEAR_MODULUS:g} MPa (1 Pa: no tissue "
                            "eyefem models is that soft); give the coefficients in MPa")
    bulk = [n for n, m in mats.items() if getattr(m, "k", 0.0)]
    if bulk and problem not in BULK_MODULUS_PROBLEMS:
        raise CaseError(f"{path} [materials.{bulk[0]}]: k = {mats[bulk[0]].k:g} MPa; problem "
                        f"'{problem}' keeps its materials exactly incompressible (the bulk "
                        "modulus k is read for the verification problems and user_mesh); "
                        "remove k")
    solver = parse_section(raw.get("solver", {}), SOLVER_FIELDS, f"{path} [solver]")
    wanted = (solver_defaults or {}).get(problem)
    if wanted is not None:
        try:
            solver.update({k: v for k, v in wanted(params).items()
                           if k not in raw.get("solver", {})})
        except ValueError as exc:
            raise CaseError(f"{path} [parameters]: {exc}") from None
    solver["backend"] = solver["backend"] or None
    try:
        opts = NewtonOptions(**solver)
    except ValueError as exc:
        raise CaseError(f"{path} [solver]: {exc}") from None
    out = parse_section(raw.get("output", {}), OUTPUT_FIELDS, f"{path} [output]")
    if not out["directory"]:
        out["directory"] = str(Path("results") / path.stem)
    return Case(path, problem, case["title"] or path.stem, params, mats, opts, out, raw)


_SOFT_TISSUE = ((1e-4, 1.0), (0.0, 20.0))
MATERIAL_C10_MPA = {  # name -> (warn, refuse) ranges of c10, MPa
    **{t: _SOFT_TISSUE for t in ("sclera", "cornea", "limbus", "ciliary_body", "choroid",
                                 "retina", "optic_nerve")},
    "lens": ((1e-4, 20.0), (0.0, 1000.0)),
}
"""Plausible Mooney-Rivlin c10 of the eye's tissues (sclera ~0.08 MPa); any other
material is refused above 1e4 MPa only (no rubber-like solid is that stiff)."""


MIN_SHEAR_MODULUS = 1e-6
"""MPa (1 Pa): a material whose initial shear modulus is below it is refused."""


BULK_MODULUS_PROBLEMS = frozenset({"equibiaxial_sheet", "inflated_disk", "inflated_shell",
                                   "patch_test", "uniaxial", "user_mesh"})
"""The problems whose case files may give a material a bulk modulus ``k`` > 0 (MPa:
FEBio's nearly incompressible uncoupled form, eyefem.fem.materials.UncoupledMooneyRivlin):
the verification problems and user_mesh, whose models are eyefem.solve.model.solid_model
of one solid (tests/test_febio_materials.py checks the list against their catalogues).
The eye's and the examples' keep exact incompressibility (their outcomes read the Q1P0
solid)."""


def material_c10_field(name: str) -> Field:
    """The plausibility Field of the c10 coefficient of material ``name`` (MPa)."""
    warn, refuse = MATERIAL_C10_MPA.get(name, ((0.0, 1e3), (0.0, 1e4)))
    return Field("c10", float, 0.0, f"Mooney-Rivlin c10 of '{name}', MPa", warn=warn,
                 refuse=refuse, unit="MPa", slips=(("kPa", 1e-3), ("Pa", 1e-6)))


def check_material_names(case: Case, used) -> None:
    """CaseError for a ``[materials.NAME]`` of ``case`` that the built model does not use
    (``used``: the model's material names), with a did-you-mean."""
    used = sorted(set(used))
    for name in case.materials:
        if name not in used:
            raise CaseError(f"{case.path} [materials.{name}]: unknown material '{name}'"
                            f"{_suggest(name, used)}; the materials of this "
                            f"'{case.problem}' model are: {', '.join(used)}")


def positive(x) -> bool:
    return x > 0


def describe(fields: list[Field], *, first=(), advanced=()) -> str:
    """Human-readable table of a schema (for ``eyefem describe``): one line per field.

    ``first``: names listed first, in that order (what a user changes first); the other
    fields follow in schema order, those named in ``advanced`` (numerical settings and
    model details) last, under the heading ADVANCED_HEADING."""
    def line(f):
        d = ("required" if f.default is REQUIRED else format(f.default, ".12g")
             if isinstance(f.default, float) else repr(f.default))
        return (f"  {f.name:<24} {f.type.__name__:<6} default {d:<12} {f.doc}"
                + (f" [{f.check_doc}]" if f.check_doc else ""))

    by_name = {f.name: f for f in fields}
    head = [by_name[n] for n in first if n in by_name]
    rest = [f for f in fields if f.name not in first]
    lines = [line(f) for f in head + [f for f in rest if f.name not in advanced]]
    more = [line(f) for f in rest if f.name in advanced]
    if more:
        lines += ["", ADVANCED_HEADING, *more]
    return "\n".join(lines)


ADVANCED_HEADING = "Advanced: numerical settings and model details (rarely changed)"
"""The heading :func:`describe` puts above a schema's advanced fields."""
