"""Meshes for the seed's liquid-container examples (mm): a closed cylinder and a slit band.

- :func:`closed_cylinder`: a thick-walled cylinder with end caps around a closed
  cylindrical cavity (a liquid-filled pipe or container), axis along z;
- :func:`slit_band`: an annular band cut at one meridian (two free ends), to be wrapped
  around a cylinder and tightened by pulling its ends past each other.

The cross-section of the cylinder is an O-grid (square core blended into circles), so
the caps have no degenerate element on the axis.
"""

from __future__ import annotations

import numpy as np

from eyefem.fem.generators import extrude, grid_quads, hex_mesh, merge_nodes
from eyefem.fem.mesh import Mesh, boundary_faces


def _square_loop(a, nc):
    """Points (8 nc, 2) around the square [-a, a]^2, counterclockwise from (a, 0)."""
    s = np.linspace(-a, a, 2 * nc + 1)
    right = np.column_stack([np.full(nc, a), s[nc:-1]])  # (a, 0) .. below (a, a)
    top = np.column_stack([s[::-1][:-1], np.full(2 * nc, a)])  # (a, a) .. before (-a, a)
    left = np.column_stack([np.full(2 * nc, -a), s[::-1][:-1]])
    bottom = np.column_stack([s[:-1], np.full(2 * nc, -a)])
    up = np.column_stack([np.full(nc, a), s[:nc]])  # (a, -a) .. below (a, 0)
    return np.concatenate([right, top, left, bottom, up])


def disk_section(inner_radius, thickness, n_circ, n_blend, n_wall):
    """2-D O-grid of the disk r <= inner_radius + thickness.

    Returns nodes (n, 2), quads (m, 4) counterclockwise, and a mask (m,) of the wall
    quads (inner_radius <= r <= inner_radius + thickness)."""
    nc = n_circ // 8
    a = 0.5 * inner_radius / np.sqrt(2.0)  # core corners at half the inner radius
    g = np.linspace(-a, a, 2 * nc + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    core = np.stack([X.ravel(), Y.ravel()], 1)
    core_q = grid_quads(2 * nc, 2 * nc)
    th = 2 * np.pi * np.arange(n_circ) / n_circ
    e = np.column_stack([np.cos(th), np.sin(th)])
    loop = _square_loop(a, nc)
    t = np.linspace(0.0, 1.0, n_blend + 1)[None, :, None]
    blend = (1 - t) * loop[:, None] + t * inner_radius * e[:, None]
    blend[:, 0] = loop  # bitwise the core's edge, for exact merging
    r_wall = inner_radius + thickness * np.arange(1, n_wall + 1) / n_wall
    wall = r_wall[None, :, None] * e[:, None]
    ring = np.concatenate([blend, wall], axis=1)  # (n_circ, nr + 1, 2)
    nr = n_blend + n_wall
    idx = np.arange(n_circ * (nr + 1)).reshape(n_circ, nr + 1)
    nxt = np.roll(idx, -1, axis=0)
    # i counterclockwise, j outward: (i, j) (i, j+1) (i+1, j+1) (i+1, j) is counterclockwise
    ring_q = np.stack([idx[:, :-1], idx[:, 1:], nxt[:, 1:], nxt[:, :-1]], -1).reshape(-1, 4)
    is_wall = np.tile(np.arange(nr) >= n_blend, n_circ)
    nodes = np.concatenate([core, ring.reshape(-1, 2)])
    quads = np.concatenate([core_q, ring_q + len(core)])
    nodes, quads = merge_nodes(nodes, quads, (2 * nc + 1) ** 2 + n_circ * nr)
    return nodes, quads, np.concatenate([np.zeros(len(core_q), bool), is_wall])


def closed_cylinder(inner_radius, thickness, length, n_circ=16, n_wall=1, n_len=8, *,
                    n_blend=2, material="default") -> Mesh:
    """A closed thick-walled cylinder (tube with end caps), axis z, cavity 0 <= z <= length.

    Wall and caps have the same thickness; the solid spans -thickness <= z <= length +
    thickness and r <= inner_radius + thickness.

    Args:
      inner_radius, thickness, length: cavity radius and length, wall thickness, mm.
      n_circ: elements around (a multiple of 8); n_wall: through the wall and caps;
      n_len: along the cavity (even, so that there are nodes at mid-length);
      n_blend: rings blending the caps' square core into the inner circle.
    Node sets: "all", "outer" (outer surface), "mid" (z = length / 2), "x0" (x = 0),
    "y0" (y = 0), "rim_y0" (outer surface at y = 0, z = length / 2: the two nodes at
    x = +-(inner_radius + thickness)).
    Face sets: "cavity" (the inner surface, closed; normals into the cavity), "outer"
    (the whole outer surface), "mantle" (its cylindrical part).
    """
    if int(n_circ) != n_circ or n_circ < 8 or n_circ % 8:
        raise ValueError(f"closed_cylinder: n_circ = {n_circ}; must be a multiple of 8")
    if int(n_len) != n_len or n_len < 2 or n_len % 2:
        raise ValueError(f"closed_cylinder: n_len = {n_len}; must be even and >= 2")
    if n_wall < 1 or n_blend < 1:
        raise ValueError(f"closed_cylinder: n_wall = {n_wall}, n_blend = {n_blend}; need >= 1")
    for name, v in (("inner_radius", inner_radius), ("thickness", thickness), ("length", length)):
        if not v > 0:
            raise ValueError(f"closed_cylinder: {name} = {v} mm; must be > 0")
    nodes2d, quads, is_wall = disk_section(inner_radius, thickness, n_circ, n_blend, n_wall)
    h = thickness
    z = np.concatenate([np.linspace(-h, 0.0, n_wall + 1)[:-1], np.linspace(0.0, length, n_len + 1),
                        np.linspace(length, length + h, n_wall + 1)[1:]])
    nodes, hexes, layer = extrude(nodes2d, quads, z)
    in_cap = (layer < n_wall) | (layer >= n_wall + n_len)
    keep = np.tile(is_wall, len(z) - 1) | in_cap
    used, hexes = np.unique(hexes[keep], return_inverse=True)
    nodes, hexes = nodes[used], hexes.reshape(-1, 8)
    ro = inner_radius + thickness
    tol = 1e-9 * max(ro, length)
    r = np.hypot(nodes[:, 0], nodes[:, 1])
    outside = (np.abs(r - ro) < tol) | (nodes[:, 2] < -h + tol) | (nodes[:, 2] > length + h - tol)
    bf = boundary_faces(hexes)
    on_outer = np.all(outside[bf], axis=1)
    mantle = np.all(np.abs(r[bf] - ro) < tol, axis=1)
    mid = np.abs(nodes[:, 2] - 0.5 * length) < tol
    outer_nodes = np.unique(bf[on_outer])
    rim = np.nonzero(mid & (np.abs(r - ro) < tol) & (np.abs(nodes[:, 1]) < tol))[0]
    node_sets = {"all": np.arange(len(nodes)), "outer": outer_nodes,
                 "mid": np.nonzero(mid)[0],
                 "x0": np.nonzero(np.abs(nodes[:, 0]) < tol)[0],
                 "y0": np.nonzero(np.abs(nodes[:, 1]) < tol)[0], "rim_y0": rim}
    face_sets = {"cavity": bf[~on_outer], "outer": bf[on_outer], "mantle": bf[mantle]}
    return hex_mesh(nodes, hexes, material, node_sets, face_sets)


def slit_band(inner_radius, thickness, width, n_circ=32, n_thick=1, n_width=2, *,
              z_centre=0.0, slit_angle=90.0, material="default") -> Mesh:
    """An annular band around the z axis, cut at the meridian ``slit_angle`` (degrees).

    The two ends lie on the cut (coincident but distinct nodes): end "end0" starts the
    band counterclockwise, "end1" closes it. Pulling end0 along the cut's tangent
    (counterclockwise) and end1 against it, past each other, shortens the band.

    Args:
      inner_radius, thickness, width: mm; n_circ, n_thick, n_width: elements around,
      through the thickness, across the width (even: nodes on the mid-plane).
      z_centre: height of the band's mid-plane, mm.
    Node sets: "all", "end0", "end1", "mid" (z = z_centre), "inner" (r = inner_radius).
    Face sets: "inner" (r = inner_radius, normals toward the axis).
    """
    if int(n_width) != n_width or n_width < 2 or n_width % 2:
        raise ValueError(f"slit_band: n_width = {n_width}; must be even and >= 2")
    if n_circ < 3 or n_thick < 1:
        raise ValueError(f"slit_band: n_circ = {n_circ}, n_thick = {n_thick}; need >= 3 and >= 1")
    for name, v in (("inner_radius", inner_radius), ("thickness", thickness), ("width", width)):
        if not v > 0:
            raise ValueError(f"slit_band: {name} = {v} mm; must be > 0")
    th = np.deg2rad(slit_angle) + 2 * np.pi * np.arange(n_circ + 1) / n_circ
    rr = inner_radius + thickness * np.arange(n_thick + 1) / n_thick
    nodes2d = (rr[None, :, None] * np.stack([np.cos(th), np.sin(th)], -1)[:, None]).reshape(-1, 2)
    # i around (counterclockwise), j outward: reverse the grid order to turn counterclockwise
    quads = grid_quads(n_circ, n_thick)[:, [0, 3, 2, 1]]
    z = z_centre + np.linspace(-0.5 * width, 0.5 * width, n_width + 1)
    nodes, hexes, _ = extrude(nodes2d, quads, z)
    i = np.tile(np.repeat(np.arange(n_circ + 1), n_thick + 1), n_width + 1)
    j = np.tile(np.arange(n_thick + 1), (n_circ + 1) * (n_width + 1))
    bf = boundary_faces(hexes)
    inner = np.nonzero(j == 0)[0]
    node_sets = {"all": np.arange(len(nodes)), "end0": np.nonzero(i == 0)[0],
                 "end1": np.nonzero(i == n_circ)[0], "inner": inner,
                 "mid": np.nonzero(np.abs(nodes[:, 2] - z_centre) < 1e-9 * width)[0]}
    face_sets = {"inner": bf[np.all(j[bf] == 0, axis=1)]}
    return hex_mesh(nodes, hexes, material, node_sets, face_sets)
