"""The results table of a sweep: one row per run, written as Parquet and CSV.

Columns: ``index``, ``status`` (ok, failed, did-not-converge, pending), ``error``,
``wall_s``, ``run_hash``, ``run_dir`` (relative to the sweep folder), then the varied parameters (their dotted paths),
the outcomes and the gradients (``d_<outcome>/d_<variable>``). Both files are written
atomically (a temporary file renamed over the old one), so a reader never sees half a
table, even when the sweep is interrupted while writing.
"""

from __future__ import annotations

import csv
import difflib
import io
import math
from pathlib import Path

from eyefem.io.output import atomic_path, write_text

FIXED_COLUMNS = ("index", "status", "error", "wall_s", "run_hash", "run_dir")


def outcome_value(rec: dict, name: str) -> float | None:
    """An outcome of a run record: from its summary, else from its last recorded step."""
    for part in ("summary", "last_step"):
        if name in rec.get(part, {}):
            return float(rec[part][name])
    return None


def rows(records: dict[int, dict], overrides: dict[int, dict], varied, outcomes) -> list[dict]:
    """Table rows (index order) from run records (index -> record; absent: pending).

    ``outcomes`` () records every number of the summaries. A successful run that lacks a
    named outcome gets status 'failed' and a message naming the known ones."""
    if not outcomes:
        names: list[str] = []
        for rec in records.values():
            names += [k for k in rec.get("summary", {}) if k not in names and k != "wall_s"]
        outcomes = tuple(names)
    grads: list[str] = []
    for rec in records.values():
        grads += [k for k in rec.get("gradients", {}) if k not in grads]
    out = []
    for i in sorted(overrides):
        rec = records.get(i, {"status": "pending", "error": "", "wall_s": math.nan,
                              "run_hash": "", "run_dir": ""})
        row = {k: rec.get(k, "") for k in FIXED_COLUMNS}
        row["index"] = i
        if row["run_dir"]:
            row["run_dir"] = f"runs/{Path(row['run_dir']).name}"
        row.update({p: overrides[i].get(p) for p in varied})
        missing = []
        for o in outcomes:
            v = outcome_value(rec, o)
            if v is None and rec.get("status") == "ok":
                missing.append(o)
            row[o] = math.nan if v is None else v
        for g in grads:
            row[g] = float(rec.get("gradients", {}).get(g, math.nan))
        if missing:
            known = sorted(set(rec.get("summary", {})) | set(rec.get("last_step", {})))
            m = difflib.get_close_matches(missing[0], known, n=1)
            hint = f" (did you mean '{m[0]}'?)" if m else ""
            row["status"] = "failed"
            row["error"] = (f"outcome '{missing[0]}' is not in the run's summary or last "
                            f"step{hint}; known: {', '.join(known)}")
        out.append(row)
    return out


def _column_type(values):
    vals = [v for v in values if v is not None]
    if vals and all(isinstance(v, bool) for v in vals):
        return "bool"
    if all(isinstance(v, int) and not isinstance(v, bool) for v in vals) and vals:
        return "int"
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
        return "float"
    return "str"


def write(table: list[dict], out_dir: Path, *, parquet: bool = True) -> None:
    """Write ``results.csv`` and (with pyarrow) ``results.parquet`` in ``out_dir``."""
    out_dir = Path(out_dir)
    cols = list(table[0]) if table else list(FIXED_COLUMNS)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in table:
        w.writerow(["" if r.get(c) is None else repr(r[c]) if isinstance(r.get(c), float)
                    else r[c] for c in cols])
    write_text(out_dir / "results.csv", buf.getvalue())
    if not parquet:
        return
    import pyarrow as pa
    import pyarrow.parquet as pq

    types = {"bool": pa.bool_(), "int": pa.int64(), "float": pa.float64(), "str": pa.string()}
    arrays = {}
    for c in cols:
        vals = [r.get(c) for r in table]
        t = _column_type(vals)
        if t == "str":
            vals = [None if v is None else str(v) for v in vals]
        elif t == "float":
            vals = [None if v is None else float(v) for v in vals]
        arrays[c] = pa.array(vals, type=types[t])
    with atomic_path(out_dir / "results.parquet") as tmp:
        pq.write_table(pa.table(arrays), tmp)


def read(out_dir: Path) -> list[dict]:
    """The rows of ``results.parquet`` in ``out_dir`` (pyarrow)."""
    import pyarrow.parquet as pq

    return pq.read_table(Path(out_dir) / "results.parquet").to_pylist()
