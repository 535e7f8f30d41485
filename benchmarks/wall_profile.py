"""Where a buckled globe's volume and axial length change sit, level by level (issue 29;
docs/convergence.md, "Where case 4's volume goes").

Reads run folders of the mesh study (``benchmarks/mesh_convergence.py run-one CASE LEVEL
RUNS/LEVEL``: their checkpoints hold the state at the start of every stage and at the
end) and compares, along the polar angle from the corneal apex, what the surgery did to
the pressurised eye (from the start of the second stage, where the cavity is closed, to
the end of the run):

- the radial displacement of the outer surface (face set "eye/outer"), mean over the
  faces of each polar-angle bin weighted by their area, mm (null for a bin no face
  centre falls in); the same of the inner surface;
- the cavity's volume change accumulated from the apex: the cone volumes (from the
  globe's centre) of the wall's inner faces ("eye/inner") whose centres lie within the
  polar angle, mm^3. With the cavity closed its total is the lens's change (nearly 0):
  the volume the buckle pushes in under the band equals what the anterior and posterior
  segments take up, and the split between them says which part of the wall sets the IOP
  rise and the axial length change;
- the axial displacements of the corneal apex, the limbus (the outer faces within 1
  degree of it) and the posterior pole (the apex's and the pole's make up the axial
  length change from the pressurised eye; the apex's less the limbus's is the cornea's
  own bulge); the zonule's total tension at the end (the sum of its bar forces, N); and
  the backward displacement of the outer sclera along the posterior
  meridian through the optic nerve: the stub, its end held, holds the wall about the
  pole back.

    python benchmarks/wall_profile.py --case cases/studies/case4_7mm.toml \
        --runs RUNS/case4_7mm --levels default,fine,finer --out OUT --images docs/images

Writes OUT/wall_profile_<case>.json and, with --images, IMAGES/wall_profile_<case>.png.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger("wall_profile")

BIN_DEG = 2.5
"""Width of the polar-angle bins, degrees."""

MERIDIAN_MM = 0.3
"""Half-width of the strip about the plane y = 0 (through the optic nerve, which leaves
15 degrees nasally, toward +x) whose outer scleral nodes make the posterior meridian."""


def _polar_deg(points):
    """Polar angle (degrees from +z, the optical axis through the corneal apex) of points
    (..., 3) about the globe's centre (the origin)."""
    r = np.linalg.norm(points, axis=-1)
    return np.degrees(np.arccos(np.clip(points[..., 2] / r, -1.0, 1.0)))


def _face_areas(x, faces):
    """Areas (n,) of bilinear faces (n, 4) at node positions x, from the cross product of
    their diagonals, mm^2."""
    p = x[faces]
    return 0.5 * np.linalg.norm(np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1]), axis=1)


def _bin_mean(angle, area, values, edges):
    """Area-weighted mean (n_bins,) of per-face values over polar-angle bins of the faces'
    centres; nan for a bin no face centre falls in (coarse levels)."""
    weight = np.histogram(angle, edges, weights=area)[0]
    total = np.histogram(angle, edges, weights=area * values)[0]
    return np.where(weight > 0, total / np.where(weight > 0, weight, 1.0), np.nan)


def _binned_radial(X, du, faces, edges):
    """Radial displacement du (n_nodes, 3) of faces (n, 4) at reference positions X, along
    the reference direction from the globe's centre: (face areas (n,), face polar angles
    (n,) deg, face values (n,), bin means (n_bins,))."""
    centre = X[faces].mean(axis=1)
    radial = centre / np.linalg.norm(centre, axis=1, keepdims=True)
    ur = np.einsum("ij,ij->i", du[faces].mean(axis=1), radial)
    area = _face_areas(X, faces)
    th = _polar_deg(centre)
    return area, th, ur, _bin_mean(th, area, ur, edges)


def _listed(values) -> list:
    """A profile as a JSON list, None for the bins no face falls in."""
    return [None if np.isnan(v) else float(v) for v in values]


def profile(case_path: str, level: str, run_dir: Path) -> dict:
    """The profiles of one run (module docstring): dict of arrays as lists and scalars."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from eyefem.catalog import problems, schemas
    from eyefem.eye.outcomes import axis_point
    from eyefem.fem.cavity import face_cone_volume
    from eyefem.io import checkpoint, manifest
    from eyefem.io.casefile import load_case, with_mesh
    from eyefem.run.runner import checkpoint_key, completed_state

    case = load_case(case_path, schemas())
    if case.problem != "surgery":
        raise checkpoint.CheckpointError(f"{case_path} is a '{case.problem}' case; the profile "
                                         "reads surgical runs (problem = \"surgery\")")
    case = with_mesh(case, level)
    setup = problems()[case.problem][1](case.parameters, case.materials)
    key = manifest.case_key(case.problem, case.parameters, case.materials, case.solver)
    ck = checkpoint.load(run_dir, checkpoint_key(setup, key))
    if int(ck["stage"]) != len(setup.stages) - 1:
        raise checkpoint.CheckpointError(
            f"{run_dir} ended after stage {ck['stage'] + 1} of {len(setup.stages)}; run it "
            "to the end")
    mesh = setup.model.mesh
    X, n = mesh.nodes, mesh.n_nodes
    u1 = np.asarray(ck["starts"][1][0])[: 3 * n].reshape(n, 3)  # the closed, pressurised eye
    u2 = np.asarray(ck["q"])[: 3 * n].reshape(n, 3)
    edges = np.arange(0.0, 180.0 + 1e-9, BIN_DEG)

    du = u2 - u1
    outer, inner = mesh.face_set("eye/outer"), mesh.face_set("eye/inner")
    area, th, ur, ur_bin = _binned_radial(X, du, outer, edges)
    _, _, _, ur_in_bin = _binned_radial(X, du, inner, edges)
    uz = du[outer].mean(axis=1)[:, 2]
    uz_bin = _bin_mean(th, area, uz, edges)
    limbus_deg = float(np.degrees(setup.parts.eye.geometry.limbus_angle))
    ring = np.abs(th - limbus_deg) < 1.0
    limbus_dz = float(area[ring] @ uz[ring] / area[ring].sum())

    def cone(u, faces):
        return -np.asarray(face_cone_volume(jnp.asarray((X + u)[faces]), jnp.zeros(3)))

    dv = cone(u2, inner) - cone(u1, inner)  # per inner face, mm^3
    dv_cum = np.cumsum(np.histogram(_polar_deg(X[inner].mean(axis=1)), edges, weights=dv)[0])
    lens = mesh.face_set("lens/surface")
    dv_lens = float(np.sum(cone(u2, lens) - cone(u1, lens)))
    top = int(np.argmax(dv_cum[: len(dv_cum) // 2 + 8]))  # anterior gain: the maximum before 110 deg
    low = top + int(np.argmin(dv_cum[top:]))
    apex, pole = axis_point(mesh, True), axis_point(mesh, False)
    apex_dz = float(apex.weights @ (u2 - u1)[apex.ids, 2])
    pole_dz = float(pole.weights @ (u2 - u1)[pole.ids, 2])
    # the posterior meridian through the nerve (the x-z plane): the outer scleral nodes
    # within MERIDIAN_MM of it, behind the equator
    sclera = np.unique(mesh.face_set("eye/sclera_outer"))
    P = X[sclera]
    on = (P[:, 2] < -0.5 * np.linalg.norm(P, axis=1)) & (np.abs(P[:, 1]) < MERIDIAN_MM)
    order = np.argsort(P[on, 0])
    meridian_x = P[on, 0][order]
    meridian_back = -(u2 - u1)[sclera[on], 2][order]
    model, q, theta, _ = completed_state(setup, run_dir, key)
    zonule = float(np.sum(model.term("zonule").forces(q, theta["zonule"])))
    summary = json.loads((run_dir / "summary.json").read_text())
    return {"level": level, "hexahedra": int(len(mesh.hexes)), "edges_deg": edges.tolist(),
            "radial_displacement_mm": _listed(ur_bin),
            "axial_displacement_mm": _listed(uz_bin),
            "inner_radial_displacement_mm": _listed(ur_in_bin),
            "meridian_x_mm": meridian_x.tolist(), "meridian_backward_mm": meridian_back.tolist(),
            "limbus_deg": limbus_deg, "limbus_forward_mm": limbus_dz,
            "cumulative_volume_change_mm3": dv_cum.tolist(),
            "anterior_gain_mm3": float(dv_cum[top]), "anterior_gain_to_deg": float(edges[top + 1]),
            "band_loss_mm3": float(dv_cum[top] - dv_cum[low]),
            "band_loss_to_deg": float(edges[low + 1]),
            "posterior_gain_mm3": float(dv_cum[-1] - dv_cum[low]),
            "lens_volume_change_mm3": dv_lens,
            "zonule_tension_N": zonule, "apex_forward_mm": apex_dz, "pole_backward_mm": -pole_dz,
            "axial_length_change_mm": apex_dz - pole_dz,
            "iop_rise_mmhg": summary["iop_mmhg"] - setup.parts.p["iop_mmhg"]}


def plot(rows: list[dict], title: str, path: Path) -> None:
    """Radial displacement and accumulated volume change against the polar angle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(16, 4.4))
    for row in rows:
        e = np.asarray(row["edges_deg"])
        mid = 0.5 * (e[1:] + e[:-1])
        ur = np.asarray(row["radial_displacement_mm"], float)  # None -> nan: an empty bin
        ok = np.isfinite(ur)
        label = f"{row['level']} ({row['hexahedra']:,} hex)"
        ax1.plot(mid[ok], ur[ok], label=label)
        ax2.plot(e[1:], row["cumulative_volume_change_mm3"], label=label)
        ax3.plot(row["meridian_x_mm"], row["meridian_backward_mm"], ".-", ms=3, label=label)
    ax1.axhline(0.0, color="0.6", lw=0.8)
    ax2.axhline(0.0, color="0.6", lw=0.8)
    ax1.set(xlabel="polar angle from the corneal apex, deg",
            ylabel="radial displacement of the outer surface, mm",
            title="what the surgery did to the pressurised eye")
    ax2.set(xlabel="polar angle from the corneal apex, deg",
            ylabel="cavity volume change from the apex to here, mm$^3$",
            title="where the volume goes")
    ax3.set(xlabel="x, mm (the optic nerve leaves toward +x; the pole at 0)",
            ylabel="backward (-z) displacement, mm",
            title="posterior meridian through the nerve (y = 0)")
    ax1.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", required=True, help="the case file the runs were made of")
    ap.add_argument("--runs", required=True, help="folder of the run folders RUNS/LEVEL")
    ap.add_argument("--levels", required=True, help="mesh levels, comma-separated")
    ap.add_argument("--out", required=True, help="where the JSON goes")
    ap.add_argument("--images", help="where the plot goes (none without it)")
    a = ap.parse_args(argv)
    from eyefem.io.checkpoint import CheckpointError

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    name = Path(a.case).stem
    rows = []
    for level in a.levels.split(","):
        run_dir = Path(a.runs) / level
        if not (run_dir / "checkpoint.json").exists():
            print(f"wall_profile: {run_dir} holds no run (no checkpoint.json): run "
                  f"python benchmarks/mesh_convergence.py run-one {a.case} {level} {run_dir}",
                  file=sys.stderr)
            return 2
        log.info("reading %s", run_dir)
        try:
            rows.append(profile(a.case, level, run_dir))
        except CheckpointError as exc:
            print(f"wall_profile: {exc} (the run must be of {a.case} at level {level})",
                  file=sys.stderr)
            return 2
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"wall_profile_{name}.json").write_text(json.dumps(rows, indent=1) + "\n")
    keys = [("iop_rise_mmhg", "IOP rise, mmHg", "%.2f"),
            ("axial_length_change_mm", "axial length change from the closed eye, mm", "%.3f"),
            ("apex_forward_mm", "corneal apex forward, mm", "%.3f"),
            ("limbus_forward_mm", "limbus forward (outer surface, 1 deg either side), mm",
             "%.3f"),
            ("pole_backward_mm", "posterior pole backward, mm", "%.3f"),
            ("band_loss_mm3", "volume pushed in under the band, mm^3", "%.1f"),
            ("anterior_gain_mm3", "taken up in front of it, mm^3", "%.1f"),
            ("posterior_gain_mm3", "taken up behind it, mm^3", "%.1f"),
            ("lens_volume_change_mm3", "lens volume change, mm^3", "%.3f"),
            ("zonule_tension_N", "zonule's total tension at the end, N", "%.3f")]
    print("| | " + " | ".join(r["level"] for r in rows) + " |")
    print("|---|" + "---:|" * len(rows))
    for k, label, fmt in keys:
        print(f"| {label} | " + " | ".join(fmt % r[k] for r in rows) + " |")
    if a.images:
        Path(a.images).mkdir(parents=True, exist_ok=True)
        png = Path(a.images) / f"wall_profile_{name}.png"
        plot(rows, f"{name}: levels {a.levels}", png)
        print(f"plot: {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
