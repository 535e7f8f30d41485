"""Seed problem 2 (inflated disk): agreement with thin-membrane theory vs mesh and thickness.

Runs the inflated-disk problem for several meshes and thicknesses and prints, for each,
the largest relative error of the applied pressure and of the pole stress against the
membrane formulas over the second half of the load path.

    python benchmarks/disk_convergence.py
"""

from __future__ import annotations

import tempfile

import jax

jax.config.update("jax_enable_x64", True)

from eyefem.problems.verification import (DISK_FIELDS, disk_solver_settings,  # noqa: E402
                                          inflated_disk)
from eyefem.run.runner import run_setup  # noqa: E402
from eyefem.solve.solver import NewtonOptions  # noqa: E402

RUNS = [
    # (label, thickness mm, n_radial, n_circ, n_thick)
    ("coarse", 0.1, 12, 12, 1),
    ("medium", 0.1, 26, 26, 1),
    ("seed (3225 hex)", 0.1, 52, 50, 1),
    ("seed mesh, 2 layers", 0.1, 26, 50, 2),
    ("thicker h = 0.2", 0.2, 52, 50, 1),
    ("thinner h = 0.05", 0.05, 52, 50, 1),
]


def main():
    base = {f.name: f.default for f in DISK_FIELDS}
    print("| mesh | h, mm | hexes | pole stretch | max err pressure | max err pole stress |")
    print("|---|---|---|---|---|---|")
    for label, h, nr, nc, nt in RUNS:
        p = dict(base, thickness=h, n_radial=nr, n_circ=nc, n_thick=nt)
        with tempfile.TemporaryDirectory() as d:
            s = run_setup(inflated_disk(p, {}), d, NewtonOptions(**disk_solver_settings(p)),
                          vtu=False, plots=False).summary
        print(f"| {label} | {h} | {s['n_elem']} | {s['final_pole_stretch']:.3f} | "
              f"{100 * s['max_rel_error_pressure']:.2f}% | {100 * s['max_rel_error_stress']:.2f}% |",
              flush=True)


if __name__ == "__main__":
    main()
