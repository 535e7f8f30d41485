"""Automatic suture generation (seed 4.7).

From the number of sutures, the suture width (the bite span across the buckle) and
the suture angle:

1. each suture k sits at a point P_k of the buckle's centre line, where the buckle has
   its generatrix direction g_k (along the buckle), its across direction a_k
   (perpendicular to g_k, tangent to the buckle surface) and outward normal n_k;
2. the two bites are the intersections with the outer scleral surface of the rays
   from the globe centre through P_k -/+ (w/2) a'_k, a'_k being a_k turned by the
   suture angle about n_k. The bites lie inside scleral faces (not only at nodes) and
   are stored as (face, parametric coordinates), so they move smoothly with w;
3. the suture runs from bite A over the buckle's outer surface to bite B: its interior
   points are the intersections of rays through the buckle top with the buckle's
   outer surface; n_bars bars per suture (n_bars - 1 points over the buckle). The
   suture lengths follow from the geometry.
4. a bite of physical size (``bite_radius`` R > 0) spreads the suture's pull over the
   outer scleral faces within R of the bite point (eyefem.fem.bars.EndPatches: the
   bite is the weighted mean of that patch, weight (1 - r^2/R^2)^2); R = 0 keeps the
   point bite, whose force sits on one face's four nodes.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.bars import (
    TiedBars,
    bilinear,
    dbilinear,
    end_patches,
    reference_end_positions,
)


@dataclasses.dataclass(frozen=True)
class EmbeddedPoint:
    """Points inside quadrilateral faces: node ids (n, 4) and parametric coords (n, 2)."""

    nodes: np.ndarray
    xi: np.ndarray

    def positions(self, xyz):
        """Positions (n, 3) for node coordinates xyz (n_nodes, 3)."""
        return np.einsum("na,nai->ni", bilinear(self.xi), xyz[self.nodes])


def ray_face_intersection(xyz, faces, origin, direction, n_candidates=12, tol=1e-9):
    """First intersection (t > 0) of the ray origin + t d with bilinear faces.

    Args: xyz (n_nodes, 3); faces (m, 4); origin, direction (3,).
    Returns: (face index, xi (2,), t) or None when the ray misses every face.
    """
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    o = np.asarray(origin, float)
    cen = xyz[faces].mean(1)
    rel = cen - o
    t_c = rel @ d
    dist = np.linalg.norm(rel - t_c[:, None] * d, axis=1)
    dist[t_c <= 0] = np.inf
    best = None
    for f in np.argsort(dist)[:n_candidates]:
        if not np.isfinite(dist[f]):
            break
        xf = xyz[faces[f]]
        z = np.array([0.0, 0.0, t_c[f]])
        for _ in range(30):
            xi = z[:2]
            r = bilinear(xi) @ xf - (o + z[2] * d)
            J = np.column_stack([(dbilinear(xi).T @ xf).T, -d])
            try:
                dz = np.linalg.solve(J, -r)
            except np.linalg.LinAlgError:
                break
            z = z + dz
            if np.linalg.norm(dz) < tol:
                break
        if np.all(np.abs(z[:2]) <= 1 + 1e-7) and z[2] > 0 and np.linalg.norm(r) < 1e-6:
            if best is None or z[2] < best[2]:
                best = (int(f), np.clip(z[:2], -1, 1), float(z[2]))
    return best


@dataclasses.dataclass(frozen=True)
class SutureLayout:
    """Generated sutures: bites on the sclera and points over the buckle.

    Attributes:
      bite_a, bite_b: EmbeddedPoint (n_sutures) in the scleral faces.
      over: EmbeddedPoint (n_sutures * (n_bars - 1)) in the buckle's outer faces, or None
        for a rigid buckle given as points only (``over_xyz``).
      over_xyz: (n_sutures, n_bars - 1, 3) initial positions of the points over the buckle.
      width: suture width, mm; angle_deg: suture angle, degrees.
    """

    bite_a: EmbeddedPoint
    bite_b: EmbeddedPoint
    over: EmbeddedPoint | None
    over_xyz: np.ndarray
    width: float
    angle_deg: float

    @property
    def n_sutures(self) -> int:
        return len(self.bite_a.nodes)

    @property
    def n_bars(self) -> int:
        return self.over_xyz.shape[1] + 1

    def lengths(self, xyz_sclera):
        """Initial suture lengths (n_sutures,), mm (bite A -> over the buckle -> bite B)."""
        pts = np.concatenate([self.bite_a.positions(xyz_sclera)[:, None], self.over_xyz,
                              self.bite_b.positions(xyz_sclera)[:, None]], axis=1)
        return np.linalg.norm(np.diff(pts, axis=1), axis=2).sum(1)


def generate_sutures(xyz, sclera_faces, centres, across, normals, *, width, angle_deg=0.0,
                     n_bars=2, globe_centre=(0.0, 0.0, 0.0), buckle_faces=None,
                     buckle_half_width=None):
    """Place sutures across a buckle (seed 4.7).

    Args:
      xyz: (n_nodes, 3) node coordinates (sclera and buckle in one mesh), mm.
      sclera_faces: (m, 4) outer scleral faces.
      centres: (k, 3) points of the buckle's centre line on its outer (top) surface.
      across: (k, 3) unit across directions (perpendicular to the generatrix, tangent).
      normals: (k, 3) unit outward normals of the buckle surface at the centres.
      width: bite span across the buckle, mm (> buckle width).
      angle_deg: rotation of the suture about the normal, degrees (0: perpendicular to the
        generatrix).
      n_bars: bars per suture (>= 2): n_bars - 1 points over the buckle.
      globe_centre: centre of the eye, mm.
      buckle_faces: (p, 4) outer faces of a deformable buckle: the points over it are
        embedded there; None for a rigid buckle (points only).
      buckle_half_width: half width of the buckle top, mm, spanned by the points over it
        (default: 0.6 * width / 2).
    Returns: SutureLayout.
    """
    if width <= 0:
        raise ValueError(f"suture width = {width} mm; must be > 0")
    if n_bars < 2:
        raise ValueError(f"n_bars = {n_bars}; a suture needs at least 2 bars (over the buckle)")
    c = np.asarray(centres, float).reshape(-1, 3)
    a = np.asarray(across, float).reshape(-1, 3)
    nrm = np.asarray(normals, float).reshape(-1, 3)
    g0 = np.asarray(globe_centre, float)
    ang = np.deg2rad(angle_deg)
    gen = np.cross(nrm, a)
    a_rot = np.cos(ang) * a + np.sin(ang) * gen
    hw = 0.3 * width if buckle_half_width is None else buckle_half_width
    bites = {"a": ([], []), "b": ([], [])}
    over_nodes, over_xi, over_xyz = [], [], []
    for k in range(len(c)):
        for side, sgn in (("a", -1.0), ("b", 1.0)):
            p = c[k] + sgn * 0.5 * width * a_rot[k]
            hit = ray_face_intersection(xyz, sclera_faces, g0 + 2.0 * (p - g0), g0 - p)
            if hit is None:
                raise ValueError(f"suture {k}: the bite ray through {np.round(p, 3).tolist()} "
                                 "misses the scleral surface; check width and placement")
            bites[side][0].append(sclera_faces[hit[0]])
            bites[side][1].append(hit[1])
        s = np.linspace(-hw, hw, n_bars - 1) if n_bars > 2 else np.zeros(1)
        pts = []
        for sk in s:
            p = c[k] + sk * a_rot[k]
            if buckle_faces is not None:
                hit = ray_face_intersection(xyz, buckle_faces, g0 + 3.0 * (p - g0), g0 - p)
                if hit is None:
                    raise ValueError(f"suture {k}: no buckle surface under the point "
                                     f"{np.round(p, 3).tolist()}")
                over_nodes.append(buckle_faces[hit[0]])
                over_xi.append(hit[1])
                pts.append(bilinear(hit[1]) @ xyz[buckle_faces[hit[0]]])
            else:
                pts.append(p)
        over_xyz.append(pts)
    ba = EmbeddedPoint(np.array(bites["a"][0]), np.array(bites["a"][1]))
    bb = EmbeddedPoint(np.array(bites["b"][0]), np.array(bites["b"][1]))
    over = (EmbeddedPoint(np.array(over_nodes), np.array(over_xi))
            if buckle_faces is not None else None)
    return SutureLayout(ba, bb, over, np.array(over_xyz), float(width), float(angle_deg))


def suture_bar_ends(layout: SutureLayout, over_node_ids=None):
    """End definitions of all suture bars for :class:`eyefem.fem.bars.Bars`.

    Args:
      layout: the sutures.
      over_node_ids: (n_sutures, n_bars - 1) node ids of the points over a rigid buckle
        (extra nodes that follow it); None when ``layout.over`` embeds them in faces.
    Returns: nodes_a (n, 4), xi_a (n, 2), nodes_b (n, 4), xi_b (n, 2), suture index (n,).
    """
    k, m = layout.n_sutures, layout.n_bars - 1
    if layout.over is not None:
        on = layout.over.nodes.reshape(k, m, 4)
        ox = layout.over.xi.reshape(k, m, 2)
    else:
        on = np.repeat(np.asarray(over_node_ids).reshape(k, m, 1), 4, axis=2)
        ox = np.zeros((k, m, 2))
    chain_n = np.concatenate([layout.bite_a.nodes[:, None], on, layout.bite_b.nodes[:, None]], 1)
    chain_x = np.concatenate([layout.bite_a.xi[:, None], ox, layout.bite_b.xi[:, None]], 1)
    na, nb = chain_n[:, :-1].reshape(-1, 4), chain_n[:, 1:].reshape(-1, 4)
    xa, xb = chain_x[:, :-1].reshape(-1, 2), chain_x[:, 1:].reshape(-1, 2)
    return na, xa, nb, xb, np.repeat(np.arange(k), m + 1)


def suture_bars(name, layout: SutureLayout, xyz, sclera_faces, *, EA, bite_radius,
                bite_length=0.0):
    """Tension-only tied bars (:class:`eyefem.fem.bars.TiedBars`) of sutures over a
    deformable buckle, their bites spread over patches of radius ``bite_radius`` (mm; 0:
    point bites), or over ellipses ``bite_length`` long along the buckle's edge (mm; 0: a
    disc). The first bar of each suture starts at bite A, the last ends at bite B; the
    ends over the buckle stay points.

    Args: name; layout; xyz (n_nodes, 3) mm; sclera_faces (m, 4); EA, N; bite_radius,
    bite_length, mm.
    """
    na, xa, nb, xb, _ = suture_bar_ends(layout)
    if bite_radius == 0:
        return TiedBars(name, na, nb, xa, xb, xyz, EA=EA)
    first = np.arange(len(na)) % layout.n_bars == 0
    last = np.arange(len(na)) % layout.n_bars == layout.n_bars - 1
    half = bite_length / 2 if bite_length else None
    pos_a, pos_b = reference_end_positions(xyz, na, xa), reference_end_positions(xyz, nb, xb)
    pa = end_patches(xyz, sclera_faces, na, xa, first, bite_radius, half_length=half,
                     toward=pos_b)
    pb = end_patches(xyz, sclera_faces, nb, xb, last, bite_radius, half_length=half,
                     toward=pos_a)
    return TiedBars(name, na, nb, xa, xb, xyz, EA=EA, patch_a=pa, patch_b=pb)


BITE_NEWTON = 8
"""Newton iterations of :func:`radial_bites` from its start (quadratic: from a bite of the
nearby design, 3-4 reach round-off)."""


def _ray_residual(z, p, xf):
    """x(xi) - t u (3,): zero where the bilinear face xf (4, 3) at z = (xi (2,), t) lies on
    the ray t u from the globe centre (the origin) through p (3,), u = p / |p|."""
    return bilinear(z[:2]) @ xf - z[2] * p / jnp.linalg.norm(p)


def _ray_hit(p, xf, xi0):
    """(xi (2,), t) of the ray through p on the face xf, by Newton from xi0 (2,)."""
    z = jnp.concatenate([xi0, jnp.linalg.norm(bilinear(xi0) @ xf)[None]])
    for _ in range(BITE_NEWTON):
        z = z - jnp.linalg.solve(jax.jacfwd(_ray_residual)(z, p, xf), _ray_residual(z, p, xf))
    return z


@jax.custom_jvp
def radial_bites(points, faces_xyz, xi0):
    """Parametric coordinates xi (n, 2) of the suture bites: where the rays from the globe
    centre (the origin) through ``points`` (n, 3), mm, meet the faces ``faces_xyz``
    (n, 4, 3) (reference node positions of the face holding each bite, mm), by Newton
    from ``xi0`` (n, 2) (the bites of a nearby design, :func:`generate_sutures`).

    Differentiable in ``points`` (the faces and xi0 are constants of the design's layout):
    its JVP is the implicit derivative of the ray's hit within each face, d(xi, t) =
    -[dr/d(xi, t)]^-1 dr/dp dp for the residual r of :func:`_ray_residual`, so a bite moves
    with the design inside its face; where a design moves a bite across a face boundary
    its layout (the face, xi0) is made anew, the bite staying continuous and its
    derivative jumping."""
    return jax.vmap(_ray_hit)(points, faces_xyz, xi0)[:, :2]


@radial_bites.defjvp
def _radial_bites_jvp(primals, tangents):
    points, faces_xyz, xi0 = primals
    dpoints = tangents[0]
    z = jax.vmap(_ray_hit)(points, faces_xyz, xi0)

    def dz(z, p, xf, dp):
        _, rp = jax.jvp(lambda p: _ray_residual(z, p, xf), (p,), (dp,))
        return -jnp.linalg.solve(jax.jacfwd(_ray_residual)(z, p, xf), rp)

    return z[:, :2], jax.vmap(dz)(z, points, faces_xyz, dpoints)[:, :2]


radial_bites = jax.jit(radial_bites)
"""Compiled: a design's bites are one XLA program (eager JAX compiles one per operation of
the Newton iterations); still differentiable by its custom JVP."""
