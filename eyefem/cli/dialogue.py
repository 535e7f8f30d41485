"""Interactive (or scripted) creation of a case file from a problem's schema.

``eyefem new-case`` asks for each parameter of the chosen problem that applies to what
was chosen so far (a surgery's sponge is not asked about band tension; advanced fields
keep their defaults unless ``--all``), showing its unit, default and valid range, validates every answer with the same checks as the case
reader and asks again with the reason when an answer is invalid, then writes a case
file that runs. The same is available without questions: ``--set name=value`` and
``--yes`` (accept defaults).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, Iterable

from eyefem.io.casefile import REQUIRED, CaseError, Field, parse_section
from eyefem.io.output import write_case


def _convert(field: Field, text: str):
    text = text.strip()
    if field.type is bool:
        low = text.lower()
        if low in ("y", "yes", "true", "1"):
            return True
        if low in ("n", "no", "false", "0"):
            return False
        raise CaseError(f"'{text}' is not yes/no")
    try:
        return field.type(text)
    except ValueError:
        raise CaseError(f"'{text}' is not a {field.type.__name__}") from None


def ask_parameters(fields: list[Field], ask: Callable[[str], str], say: Callable[[str], None],
                   preset: dict | None = None, accept_defaults: bool = False,
                   max_tries: int = 5, questions: Callable | None = None,
                   ask_all: bool = False) -> dict:
    """Collect validated parameter values.

    Args:
      fields: the problem's schema.
      ask: prompt -> answer (``input`` interactively, an iterator in tests).
      say: prints a message.
      preset: values given up front (``--set``), validated too.
      accept_defaults: take the default of every field not preset without asking.
      questions: the problem's ``questions(values) -> (names not to ask, defaults)`` given
        the answers so far (every default filled in): fields that do not apply to what was
        chosen, and defaults that depend on it (a sponge's sutures); None: ask every field.
      ask_all: ask the fields ``questions`` leaves out too (they keep their defaults
        otherwise); its defaults still apply.
    """
    values = {}
    preset = dict(preset or {})
    for f in fields:
        skip, own = (questions({**{g.name: g.default for g in fields}, **values})
                     if questions is not None else ((), {}))
        f = dataclasses.replace(f, default=own[f.name]) if f.name in own else f
        if f.name in preset:
            raw = preset.pop(f.name)
            val = _convert(f, raw) if isinstance(raw, str) else raw
            parse_section({f.name: val}, [f], "parameter")
            values[f.name] = val
            continue
        if (accept_defaults or (f.name in skip and not ask_all)) and f.default is not REQUIRED:
            if f.name in own:
                values[f.name] = f.default
            continue
        default = "" if f.default is REQUIRED else f" [{f.default}]"
        rng = f" ({f.check_doc})" if f.check_doc else ""
        for _ in range(max_tries):
            ans = ask(f"{f.name}: {f.doc}{rng}{default}? ")
            if not ans.strip() and f.default is not REQUIRED:
                if f.name in own:
                    values[f.name] = f.default
                break
            try:
                val = _convert(f, ans)
                parse_section({f.name: val}, [f], "answer")
            except CaseError as exc:
                say(f"  invalid: {exc}")
                continue
            if val != f.default or f.name in own:
                values[f.name] = val
            break
        else:
            raise CaseError(f"no valid answer for '{f.name}' after {max_tries} tries")
    if preset:
        raise CaseError(f"unknown parameters {sorted(preset)}; valid: {[f.name for f in fields]}")
    return values


def check_target(path: Path, force: bool = False) -> Path:
    """CaseError unless ``path`` can take a new case file: not a folder, its folder
    exists, and not an existing file unless ``force``."""
    path = Path(path)
    if path.is_dir():
        raise CaseError(f"-o {path}: is a folder; give the case file to write, e.g. "
                        f"-o {path / 'my_case.toml'}")
    if path.exists() and not force:
        raise CaseError(f"-o {path}: the file exists; nothing written (--force overwrites it)")
    if not path.parent.is_dir():
        raise CaseError(f"-o {path}: its folder '{path.parent}' does not exist; create it "
                        "first")
    return path


def new_case(problem: str, fields: list[Field], path: Path, *, ask=input, say=print,
             preset=None, accept_defaults=False, title="", materials=None,
             check=None, force=False, questions=None, ask_all=False,
             solver_settings=None) -> Path:
    """Ask for the parameters of ``problem`` and write the case file; returns its path.

    ``check(params)``: the problem's checks across fields (params with the defaults
    filled in); its ValueError becomes a CaseError and nothing is written.
    ``solver_settings(params)``: the ``[solver]`` section to write (a dict). An existing
    file at ``path`` is refused (CaseError) unless ``force``; a folder always.
    ``questions``, ``ask_all``: see :func:`ask_parameters`."""
    check_target(path, force)
    say(f"New '{problem}' case -> {path}  (Enter keeps the default)")
    params = ask_parameters(fields, ask, say, preset, accept_defaults,
                            questions=questions, ask_all=ask_all)
    filled = {**{f.name: f.default for f in fields}, **params}
    if check is not None:
        try:
            check(filled)
        except ValueError as exc:
            raise CaseError(f"{problem}: {exc}; nothing written to {path}") from None
    solver = solver_settings(filled) if solver_settings is not None else None
    write_case(path, problem, title, params, materials, solver=solver)
    say(f"wrote {path}; run it with: eyefem run {path}")
    return Path(path)


def scripted(answers: Iterable[str]) -> Callable[[str], str]:
    """An ``ask`` function that replays answers (for tests and batch use)."""
    it = iter(answers)
    return lambda prompt: next(it)
