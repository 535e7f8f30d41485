"""Run several surgery cases and compare them: table (CSV, Markdown) and bar chart (PNG).

``eyefem compare cases/surgery/case*.toml --mesh coarse --out results/compare`` runs each
case into ``out/<case stem>/`` and writes ``comparison.csv``, ``comparison.md`` and
``comparison.png``. With ``reuse`` a case whose folder holds a complete run of the same
parsed case (``run.json``: case hash, code version) is not run again (the notebooks use
this); an edited case is computed again.
"""

from __future__ import annotations

import logging
from pathlib import Path

from eyefem.io.output import atomic_path, write_text

log = logging.getLogger(__name__)

COLUMNS = {  # summary key -> label
    "iop_after_tightening_mmhg": "IOP after stage 2, mmHg",
    "iop_mmhg": "IOP after surgery, mmHg",
    "indentation_mm": "indentation, mm",
    "axial_length_change_mm": "axial length change, mm",
    "volume_change_mm3": "cavity volume change, mm^3",
    "max_suture_force_N": "max suture force, N",
}


def run_case(path, out_dir, *, mesh=None, reuse=False, vtu=False) -> dict:
    """Run one case file (mesh level override for surgery cases); returns its summary.

    With ``reuse`` the summary in ``out_dir`` is taken only from a complete run of the
    same parsed case (hash of problem, parameters, mesh, materials, solver) by this
    eyefem version (``run.json``); otherwise the case is computed again."""
    from eyefem.catalog import problems, schemas, solver_defaults
    from eyefem.io import manifest
    from eyefem.io.casefile import check_material_names, load_case
    from eyefem.run.runner import claimed_folder, run_setup, write_summary

    case = load_case(path, schemas(), solver_defaults())
    params = dict(case.parameters)
    if mesh is not None:
        params["mesh"] = mesh
    out_dir = Path(out_dir)
    key = manifest.case_key(case.problem, params, case.materials, case.solver)
    if reuse:
        s = manifest.reusable_summary(out_dir, key)
        if s is not None:
            log.info("%s: reusing %s", case.path, out_dir / "summary.json")
            return s
    with claimed_folder(out_dir) as out_dir:  # claimed and locked before the model is built
        setup = problems()[case.problem][1](params, case.materials)
        check_material_names(case, setup.model.mesh.materials)
        res = run_setup(setup, out_dir, case.solver, vtu=vtu, plots=case.output["plots"],
                        key=key, locked=True)
        summary = {"case": str(case.path), "title": case.title, "mesh": params.get("mesh"),
                   **res.summary}
        write_summary(res, summary)
    return summary


def write_table(summaries: dict[str, dict], stem: Path):
    """comparison table as stem.csv and stem.md (one row per case)."""
    from eyefem.io.output import write_csv

    rows = [{"case": k, "title": s.get("title", ""), **{c: s.get(c) for c in COLUMNS}}
            for k, s in summaries.items()]
    write_csv(Path(f"{stem}.csv"), rows)
    head = "| case | " + " | ".join(COLUMNS.values()) + " |\n|---|" + "---:|" * len(COLUMNS) + "\n"
    body = "".join("| " + r["case"] + " | " + " | ".join(
        "" if r[c] is None else f"{r[c]:.3f}" for c in COLUMNS) + " |\n" for r in rows)
    titles = "".join(f"- **{r['case']}**: {r['title']}\n" for r in rows)
    write_text(Path(f"{stem}.md"), head + body + "\n" + titles)


def plot_comparison(summaries: dict[str, dict], path: Path):
    """Bar charts of IOP, indentation and axial length change per case (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summaries)
    keys = ["iop_mmhg", "indentation_mm", "axial_length_change_mm", "max_suture_force_N"]
    fig, axes = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 3.2))
    for ax, k in zip(axes, keys):
        ax.bar(names, [summaries[n].get(k) or 0.0 for n in names], color="C0")
        ax.set_title(COLUMNS[k], fontsize=9)
        ax.tick_params(axis="x", rotation=45, labelsize=8)
        ax.grid(axis="y", alpha=0.3)
    if "iop_mmhg" in keys:
        axes[0].axhline(15.0, ls="--", color="k", lw=0.8, label="pre-op")
        axes[0].legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def compare(paths, out_root, *, mesh=None, reuse=False) -> dict[str, dict]:
    """Run the cases (in order) and write the comparison files into out_root."""
    out_root = Path(out_root)
    summaries = {}
    for p in paths:
        stem = Path(p).stem
        log.info("case %s (%d of %d)", p, len(summaries) + 1, len(paths))
        summaries[stem] = run_case(p, out_root / stem, mesh=mesh, reuse=reuse)
    write_table(summaries, out_root / "comparison")
    plot_comparison(summaries, out_root / "comparison.png")
    return summaries
