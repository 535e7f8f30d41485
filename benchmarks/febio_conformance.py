"""Conformance of eyefem's FEBio reader against FEBio's own regression suite (issue 77).

    python benchmarks/febio_conformance.py --suite TestSuite/Verify \
        [--gold TestSuite/code/linuxGoldStandards.py] [--out results.csv] \
        [--time-cap 120] [--max-nodes 3000] [--only mi03,mi26]

For every deck of the suite (``*.feb``; FEBio's runner skips the optimisation inputs
``oi*``, and so does this script) it reads the deck with eyefem.io.febio_read (no solve if
refused), solves the decks in scope (at most ``--max-nodes`` nodes, ``--time-cap``
seconds each) and computes what the suite's gold standard records: FEBio's test task
(``-task=test``, FEBioTestSuiteTask) logs the model data record ``solution_norm`` when the
deck defines no data record of its own, and code/runTests.py takes the value from the
last "Data Record #1" block of the log, i.e. at the end of the last step:
FELogSolutionNorm = the l2 norm of the solver's total solution vector (FENewtonSolver::
m_Ut), the displacements of every dof with an equation in the last step: nodes in
elements (solids, trusses, springs), neither fixed nor prescribed by the conditions active
in that step (a rigid body's nodes are prescribed). A deck
whose <Output><logfile> defines records of its own has another gold value and is marked
so.

The table: deck, status (agree / differ / refused / error / ...), the one-line reason,
eyefem's value, FEBio's, the relative difference, agree (<= 0.5 %). The counts go to
stdout. A deck that raises anything unexpected is an "error" row, never a traceback.
"""

from __future__ import annotations

import argparse
import ast
import collections
import csv
import dataclasses
import logging
import re
import signal
import sys
import time
from pathlib import Path

import numpy as np

TOLERANCE = 0.005
"""Relative difference within which eyefem agrees with FEBio's gold value (0.5 %)."""

ZERO = 1e-12
"""A solution norm below this (mm) is zero to roundoff: two such values agree (decks whose
free dofs do not move, e.g. ma62: FEBio records 2.9e-16)."""

FIELDS = ("deck", "status", "reason", "nodes", "elements", "steps", "eyefem", "febio",
          "rel_diff", "agree", "seconds")


@dataclasses.dataclass
class Row:
    deck: str
    status: str
    reason: str = ""
    nodes: int | None = None
    elements: int | None = None
    steps: int | None = None
    eyefem: float | None = None
    febio: float | None = None
    rel_diff: float | None = None
    agree: bool = False
    seconds: float = 0.0

    def as_dict(self):
        d = dataclasses.asdict(self)
        for k in ("eyefem", "febio"):
            d[k] = "" if d[k] is None else f"{d[k]:.10g}"
        d["rel_diff"] = "" if self.rel_diff is None else f"{self.rel_diff:.2e}"
        d["agree"] = "yes" if self.agree else "no"
        d["seconds"] = f"{self.seconds:.1f}"
        return {k: ("" if d[k] is None else d[k]) for k in FIELDS}


def load_gold(path) -> dict:
    """deck -> FEBio's recorded value (code/linuxGoldStandards.py: stdResults[deck][6],
    the last entry of each row), read with ast (never executed)."""
    tree = ast.parse(Path(path).read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(
                getattr(t, "id", None) == "stdResults" for t in node.targets):
            table = ast.literal_eval(node.value)
            out = {}
            for name, row in table.items():
                try:
                    out[name] = float(row[-1])
                except (TypeError, ValueError, IndexError):
                    out[name] = None
            return out
    raise ValueError(f"{path}: no stdResults table")



def own_log_records(path) -> str | None:
    """The first data record a deck's <Output><logfile> defines (its gold value is then
    that record's, not the solution norm), or None."""
    import xml.etree.ElementTree as ET
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError:
        return None
    for rec in root.iterfind("Output/logfile/*"):
        if isinstance(rec.tag, str):
            return f"{rec.tag} '{rec.get('data')}'"
    return None


class _Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise _Timeout()


def reason_of(exc) -> str:
    """One line: the message without the deck's path."""
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return re.sub(r"^\S+\.feb: ", "", msg)


def run_deck(path, gold: float | None, *, time_cap: float = 120.0,
             max_nodes: int = 3000) -> Row:
    """Read (and, in scope, solve) one deck; a Row whatever happens."""
    from eyefem.io.febio import FebError
    from eyefem.io.febio_read import build_stages, read_feb, solution_norm
    from eyefem.solve.solver import ConvergenceError, solve

    path = Path(path)
    row = Row(path.stem, "error")
    t0 = time.perf_counter()
    try:
        try:
            mesh, materials, loads = read_feb(path)
        except FebError as exc:
            row.status, row.reason = "refused", reason_of(exc)
            return row
        row.nodes, row.elements = mesh.n_nodes, mesh.n_elem
        row.steps = len(loads.steps)
        row.febio = gold
        own = own_log_records(path)
        if gold is None:
            row.status, row.reason = "no gold", "no gold standard for this deck"
            return row
        if own:
            row.status = "other measure"
            row.reason = f"the gold value is the deck's own log record {own}"
            return row
        if mesh.n_nodes > max_nodes:
            row.status = "too large"
            row.reason = f"{mesh.n_nodes} nodes > {max_nodes} (--max-nodes)"
            return row
        try:
            model, stages = build_stages(mesh, materials, loads)
        except FebError as exc:
            row.status, row.reason = "refused", reason_of(exc)
            return row
        old = signal.signal(signal.SIGALRM, _alarm)
        signal.setitimer(signal.ITIMER_REAL, time_cap)
        try:
            q = solve(model, stages).q
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
        row.eyefem = solution_norm(mesh, stages[-1], q, loads)
        row.rel_diff = (row.eyefem - gold) / abs(gold) if gold else (
            0.0 if row.eyefem == 0 else float("inf"))
        row.agree = abs(row.rel_diff) <= TOLERANCE or (abs(gold) < ZERO and row.eyefem < ZERO)
        row.status = "agree" if row.agree else "differ"
    except _Timeout:
        row.status, row.reason = "timeout", f"solve longer than {time_cap:g} s (--time-cap)"
    except ConvergenceError as exc:
        row.status, row.reason = "no convergence", reason_of(exc)
    except Exception as exc:  # noqa: BLE001 - the table records it, never a traceback
        row.status, row.reason = "error", f"error: {type(exc).__name__}: {reason_of(exc)}"
    finally:
        row.seconds = time.perf_counter() - t0
    return row


def group_of(reason: str) -> str:
    """A refusal's group: the message with names, ids and numbers taken out."""
    g = re.sub(r"\bname=\"[^\"]*\"", "", reason)
    g = re.sub(r"(material|surface|node set|element block|SolidDomain|rigid body|discrete "
               r"set|surface pair|volume constraint|contact) '[^']*'( \(id [^)]*\))?", r"\1", g)
    g = re.sub(r"(load curve|load controller|element|node) \d+", r"\1 N", g)
    g = re.sub(r"-?\d+(\.\d+)?(e[-+]?\d+)?", "N", g)
    g = g.split(";")[0]
    return g[:120]


def run_suite(suite, gold_path=None, *, time_cap=120.0, max_nodes=3000, only=None,
              log=print) -> list[Row]:
    """Rows of every deck of ``suite`` (a Verify folder), in name order."""
    suite = Path(suite)
    gold = load_gold(gold_path) if gold_path else {}
    rows = []
    for f in sorted(suite.glob("*.feb")):
        if f.stem.startswith("oi") or (only and f.stem not in only):
            continue
        row = run_deck(f, gold.get(f.stem), time_cap=time_cap, max_nodes=max_nodes)
        rows.append(row)
        if row.status not in ("refused",):
            log(f"{row.deck}: {row.status} {row.reason} eyefem {row.eyefem} febio {row.febio} "
                f"rel {row.rel_diff} ({row.seconds:.1f} s)")
    return rows


def summary(rows) -> str:
    counts = collections.Counter(r.status for r in rows)
    refused = collections.Counter(group_of(r.reason) for r in rows if r.status == "refused")
    solved = [r for r in rows if r.eyefem is not None]
    lines = [f"decks: {len(rows)}",
             f"in scope (read and solved): {len(solved)}",
             f"agreeing to {TOLERANCE:.1%}: {sum(r.agree for r in rows)}",
             "by status: " + ", ".join(f"{k} {v}" for k, v in counts.most_common()),
             "refused, by reason:"]
    lines += [f"  {n:4d}  {g}" for g, n in refused.most_common()]
    return "\n".join(lines)


def write_csv(rows, out) -> None:
    with open(out, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow(r.as_dict())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", required=True, help="the TestSuite's Verify folder")
    ap.add_argument("--gold", help="code/linuxGoldStandards.py (default: ../code/ of --suite)")
    ap.add_argument("--out", default="febio_conformance.csv")
    ap.add_argument("--time-cap", type=float, default=120.0, help="seconds per deck's solve")
    ap.add_argument("--max-nodes", type=int, default=3000)
    ap.add_argument("--only", help="comma-separated deck names")
    args = ap.parse_args(argv)
    import jax
    jax.config.update("jax_enable_x64", True)
    logging.basicConfig(level=logging.ERROR)
    gold = args.gold or Path(args.suite).resolve().parent / "code" / "linuxGoldStandards.py"
    if not Path(gold).exists():
        print(f"no gold standards at {gold}; give --gold", file=sys.stderr)
        return 2
    rows = run_suite(args.suite, gold, time_cap=args.time_cap, max_nodes=args.max_nodes,
                     only=set(args.only.split(",")) if args.only else None)
    write_csv(rows, args.out)
    print(summary(rows))
    print(f"table: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
