"""Clinical optics of the model eye: corneal power and astigmatism, anterior chamber depth,
and the refraction change they and the axial length make in a reduced schematic eye.

Every function takes the node positions x (n_nodes, 3) as a numpy or JAX array and is
written with jax.numpy, so the same definition gives the reported value and, through
the adjoint, its gradient (eyefem.eye.design).

Definitions (the optical axis is z, the cornea faces +z):

- The anterior corneal surface is fitted, by least squares, with the quadric
  z = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2 over its nodes within a central zone
  (CORNEA_ZONE_MM across; widened to hold at least CORNEA_MIN_NODES nodes on a coarse
  mesh: :func:`cornea_zone`). Its principal curvatures are the eigenvalues k1, k2 of
  -[[2 c3, c4], [c4, 2 c5]] (1/mm); keratometric powers P = (n_k - 1) k with the
  keratometric index n_k = 1.3375 (dioptres with k in 1/m). Corneal power: their mean;
  astigmatism: |P1 - P2|.
- Anterior chamber depth: the anterior corneal apex to the anterior pole of the lens, mm.
- Refraction change in the reduced eye (Emsley: one refracting surface of 60 D, image
  space index n' = 4/3, focal length f' = n'/P = 22.22 mm; Atchison and Smith, Optics of
  the Human Eye, 2000, ch. 5): a longer eye by dL and a cornea stronger by dK make the
  eye more myopic; to first order the refraction (at the corneal plane) changes by
  dR = -n' dL / f'^2 - dK  (about -2.7 D per mm of axial elongation).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

KERATOMETRIC_INDEX = 1.3375
"""Keratometric index n_k: corneal power (n_k - 1) / R of the anterior radius R."""
REDUCED_EYE_INDEX = 4.0 / 3.0
"""Image-space refractive index n' of the reduced eye (Emsley)."""
REDUCED_EYE_POWER_D = 60.0
"""Power of the reduced eye's single refracting surface, dioptres (Emsley)."""
CORNEA_ZONE_MM = 3.0
"""Diameter of the central corneal zone the surface is fitted over, mm (keratometry)."""
CORNEA_MIN_NODES = 9
"""The fit zone is widened until it holds this many nodes (a coarse mesh has few)."""


def cornea_zone(mesh, x0=None) -> tuple[np.ndarray, float]:
    """Node ids (k,) of the anterior corneal surface within the central fit zone of the
    undeformed mesh, and the zone's diameter, mm (CORNEA_ZONE_MM, or wider on a coarse
    mesh so that it holds CORNEA_MIN_NODES nodes)."""
    x0 = mesh.nodes if x0 is None else x0
    apex = mesh.node_set("eye/apex")[0]
    outer = mesh.node_set("eye/outer")
    front = outer[x0[outer, 2] > x0[apex, 2] - 3.0]  # the cornea's front, within 3 mm of the apex
    rho = np.hypot(x0[front, 0], x0[front, 1])
    order = np.argsort(rho)
    zone = max(CORNEA_ZONE_MM, 2 * rho[order[CORNEA_MIN_NODES - 1]] * (1 + 1e-9))
    return np.sort(front[rho <= zone / 2]), float(zone)


def cornea_curvatures(x, nodes):
    """Principal curvatures (k1 >= k2, 1/mm) of the quadric fitted to the nodes' positions
    x[nodes] (k, 3) of the anterior cornea (positive: convex toward +z)."""
    p = x[nodes]
    X, Y, Z = p[:, 0], p[:, 1], p[:, 2]
    A = jnp.stack([jnp.ones_like(X), X, Y, X * X, X * Y, Y * Y], axis=1)
    c = jnp.linalg.solve(A.T @ A, A.T @ Z)
    a, b, d = -2 * c[3], -c[4], -2 * c[5]
    mean, half = 0.5 * (a + d), jnp.sqrt(0.25 * (a - d) ** 2 + b ** 2 + 1e-30)
    return mean + half, mean - half


def corneal_power_d(x, nodes):
    """Mean keratometric power of the anterior cornea, dioptres."""
    k1, k2 = cornea_curvatures(x, nodes)
    return 1e3 * (KERATOMETRIC_INDEX - 1.0) * 0.5 * (k1 + k2)


def corneal_astigmatism_d(x, nodes):
    """Corneal astigmatism: the difference of the principal keratometric powers, dioptres."""
    k1, k2 = cornea_curvatures(x, nodes)
    return 1e3 * (KERATOMETRIC_INDEX - 1.0) * (k1 - k2)


def anterior_chamber_depth(apex, lens_pole):
    """Anterior corneal apex to the lens's anterior pole along the axis (z), mm, from their
    positions (3,)."""
    return apex[2] - lens_pole[2]


def lens_anterior_pole(mesh) -> int:
    """The lens node on the optical axis nearest the cornea (largest z)."""
    lens = mesh.node_set("lens")
    return int(lens[np.argmax(mesh.nodes[lens, 2])])


def refraction_change_d(axial_change_mm, power_change_d):
    """Refraction change at the corneal plane, dioptres (negative: myopic), of an axial
    length change (mm) and a corneal power change (D), in the reduced eye."""
    f = REDUCED_EYE_INDEX / REDUCED_EYE_POWER_D  # m
    return -REDUCED_EYE_INDEX * 1e-3 * axial_change_mm / f ** 2 - power_change_d
