"""Plots of a sweep: each outcome against each varied parameter (PNG in the sweep folder)."""

from __future__ import annotations

import math
from pathlib import Path

from eyefem.study import table

MAX_PANELS = 8


def numeric(values) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def outcome_columns(rows: list[dict], varied) -> list[str]:
    """The outcome columns of a table (not fixed, varied or gradient columns)."""
    return [c for c in (rows[0] if rows else {}) if c not in table.FIXED_COLUMNS
            and c not in varied and not c.startswith("d_")]


def plot_sweep(rows: list[dict], varied, out_dir: Path) -> list[Path]:
    """One figure per numeric varied parameter, ``sweep_<parameter>.png``: a panel per
    outcome (up to MAX_PANELS), the successful runs as points, failed runs as red ticks
    on the axis. Returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    outs = outcome_columns(rows, varied)[:MAX_PANELS]
    ok = [r for r in rows if r["status"] == "ok"]
    bad = [r for r in rows if r["status"] not in ("ok", "pending")]
    written = []
    for p in varied:
        xs = [r[p] for r in rows if r.get(p) is not None]
        if not outs or not xs or not numeric(xs):
            continue
        n = len(outs)
        ncol = min(n, 3)
        nrow = math.ceil(n / ncol)
        fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.2 * nrow), squeeze=False)
        for ax, o in zip(axes.flat, outs):
            pts = sorted((r[p], r[o]) for r in ok if r.get(p) is not None
                         and isinstance(r.get(o), float) and math.isfinite(r[o]))
            if pts:
                ax.plot([a for a, _ in pts], [b for _, b in pts], "o", ms=4, alpha=0.8)
            for r in bad:
                if r.get(p) is not None:
                    ax.axvline(r[p], color="tab:red", lw=0.8, alpha=0.5)
            ax.set_xlabel(p)
            ax.set_ylabel(o)
            ax.grid(alpha=0.3)
        for ax in list(axes.flat)[n:]:
            ax.set_visible(False)
        fig.suptitle(f"outcomes against {p} ({len(ok)} runs ok, {len(bad)} failed: red)")
        fig.tight_layout()
        path = Path(out_dir) / f"sweep_{p.replace('.', '_')}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written.append(path)
    return written
