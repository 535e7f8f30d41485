"""Bending of the eye wall's Q1P0 hexahedra against beam theory, and the aspect the eye's
mesh levels give them.

A clamped plane-strain strip as thick as the sclera at the equator (0.4 mm), loaded at its
tip (eyefem.problems.verification.cantilever_bending_stiffness): the finite element
stiffness over Timoshenko's for element lengths 1.6 ... 0.1 mm and 2 or 4 layers through
the thickness; then, per eye mesh level, the meridional length of the outer scleral faces
at the equator (polar angle 90 deg) and behind it (150 deg), against the sclera's
thickness there (0.4 and about 0.8 mm; the sclera is the wall's outer 2 layers).

    python benchmarks/bending_locking.py
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from eyefem.eye.eyemodel import LEVELS, build_eye  # noqa: E402
from eyefem.problems.verification import cantilever_bending_stiffness  # noqa: E402


def meridional_length(eye, polar_deg: float) -> float:
    """Median meridional extent (mm) of the outer faces whose centre lies within 5 deg of
    the polar angle."""
    faces = eye.mesh.nodes[eye.mesh.face_set("eye/outer")]
    th = np.degrees(np.arccos(faces[..., 2] / np.linalg.norm(faces, axis=2)))
    centre = th.mean(1)
    extent = np.radians(th.max(1) - th.min(1)) * np.linalg.norm(faces, axis=2).mean(1)
    return float(np.median(extent[np.abs(centre - polar_deg) < 5]))


def main() -> None:
    print("| element length, mm | a / t | 2 layers: k / k_beam | 4 layers: k / k_beam |")
    print("|---:|---:|---:|---:|")
    for a in (1.6, 0.8, 0.4, 0.2, 0.1):
        two, four = (cantilever_bending_stiffness(a, n) for n in (2, 4))
        print(f"| {a} | {two['aspect']:.2f} | {two['ratio']:.3f} | {four['ratio']:.3f} |")
    print()
    print("| level | hexahedra | meridional length at 90 deg, mm | a / t there (t 0.4) "
          "| at 150 deg, mm | a / t there (t 0.8) |")
    print("|---|---:|---:|---:|---:|---:|")
    for level in LEVELS:
        eye = build_eye(level=level)
        a90, a150 = meridional_length(eye, 90.0), meridional_length(eye, 150.0)
        print(f"| {level} | {eye.mesh.n_elem} | {a90:.3f} | {a90 / 0.4:.2f} | {a150:.3f} "
              f"| {a150 / 0.8:.2f} |")


if __name__ == "__main__":
    main()
