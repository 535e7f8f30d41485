"""Structured hexahedral meshes for the verification and benchmark problems.

- :func:`box`: a brick, with node and face sets on its six planes;
- :func:`quarter_disk`: 1/4 of a thin disk (O-grid: square core + ring, no degenerate
  element at the centre) for the seed's inflation problem;
- :func:`spherical_shell`: a thin spherical shell as a cubed sphere (6 equiangular
  patches, no pole singularity) for the benchmark and cavity tests.
"""

from __future__ import annotations

import numpy as np

from .mesh import HEX_FACES, Mesh

# local face of a hexahedron on each side of a structured block (see mesh.HEX_FACES)
_SIDE_FACE = {"z0": 0, "z1": 1, "y0": 2, "x1": 3, "y1": 4, "x0": 5}


def _merge_nodes(nodes, cells, decimals=9):
    """Merge coincident nodes; returns (unique nodes, renumbered cells)."""
    scale = max(np.abs(nodes).max(), 1.0)
    key = np.round(nodes / scale, decimals)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return nodes[first], inv.ravel()[cells]


def _extrude(nodes2d, quads, z):
    """Stack 2-D quads (ccw seen from +z) into hexes over the levels z (nz + 1,)."""
    n2 = len(nodes2d)
    nz = len(z) - 1
    nodes = np.concatenate([np.column_stack([nodes2d, np.full(n2, zk)]) for zk in z])
    layers = [np.concatenate([quads + k * n2, quads + (k + 1) * n2], axis=1) for k in range(nz)]
    return nodes, np.concatenate(layers), np.repeat(np.arange(nz), len(quads))


def _grid_quads(ni, nj):
    """Quads (ni * nj, 4) of an (ni + 1) x (nj + 1) node grid numbered i * (nj + 1) + j, ccw."""
    idx = np.arange((ni + 1) * (nj + 1)).reshape(ni + 1, nj + 1)
    return np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)


def box(lx, ly, lz, nx, ny, nz, *, origin=(0.0, 0.0, 0.0), material="default") -> Mesh:
    """Brick [ox, ox + lx] x [oy, oy + ly] x [oz, oz + lz] with nx * ny * nz hexahedra (mm).

    Node and face sets: "x0", "x1", "y0", "y1", "z0", "z1" (the six planes),
    "all" (nodes), "boundary" (all boundary faces).
    """
    for name, n in (("nx", nx), ("ny", ny), ("nz", nz)):
        if n < 1:
            raise ValueError(f"box: {name} = {n}; need at least 1 element")
    o = np.asarray(origin, float)
    g = [np.linspace(0.0, l, n + 1) for l, n in ((lx, nx), (ly, ny), (lz, nz))]
    X, Y, Z = np.meshgrid(*g, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1) + o
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    c = idx[:-1, :-1, :-1], idx[1:, :-1, :-1], idx[1:, 1:, :-1], idx[:-1, 1:, :-1]
    t = idx[:-1, :-1, 1:], idx[1:, :-1, 1:], idx[1:, 1:, 1:], idx[:-1, 1:, 1:]
    hexes = np.stack([a.ravel() for a in c + t], 1)
    eidx = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    sides = {"x0": eidx[0], "x1": eidx[-1], "y0": eidx[:, 0], "y1": eidx[:, -1],
             "z0": eidx[:, :, 0], "z1": eidx[:, :, -1]}
    node_sets, face_sets = {"all": np.arange(len(nodes))}, {}
    for name, els in sides.items():
        a = "xyz".index(name[0])
        val = o[a] + (0.0 if name[1] == "0" else (lx, ly, lz)[a])
        node_sets[name] = np.nonzero(np.isclose(nodes[:, a], val))[0]
        face_sets[name] = hexes[els.ravel()][:, HEX_FACES[_SIDE_FACE[name]]]
    face_sets["boundary"] = np.concatenate([face_sets[k] for k in sides])
    return Mesh(nodes, hexes, np.zeros(len(hexes), np.int64), (material,), node_sets, face_sets)


def quarter_disk(radius, thickness, n_radial, n_circ, n_thick, *, core=0.5,
                 material="default") -> Mesh:
    """1/4 of a disk (x, y >= 0, 0 <= z <= thickness) meshed as an O-grid (mm).

    A square core [0, core * radius]^2 with (n_circ / 2)^2 elements and a ring of
    n_radial x n_circ elements up to the arc; n_thick layers. About 3250 hexahedra for
    n_circ = 50, n_radial = 52, n_thick = 1.

    Node sets: "sym_x" (x = 0), "sym_y" (y = 0), "rim" (r = radius), "pole" (axis),
    "pole_bottom", "pole_top", "all". Face sets: "bottom" (z = 0), "top", "rim".
    """
    if n_circ < 2 or n_circ % 2:
        raise ValueError(f"quarter_disk: n_circ = {n_circ}; must be even and >= 2")
    if n_radial < 1 or n_thick < 1:
        raise ValueError("quarter_disk: n_radial and n_thick must be >= 1")
    nc = n_circ // 2
    a = core * radius
    # core grid (nc + 1)^2
    g = np.linspace(0.0, a, nc + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    core_nodes = np.stack([X.ravel(), Y.ravel()], 1)
    core_quads = _grid_quads(nc, nc)
    # ring: s along the core boundary (x = a then y = a), t from the core to the arc
    s = np.linspace(0.0, 1.0, n_circ + 1)
    cb = np.where(s[:, None] <= 0.5, np.column_stack([np.full_like(s, a), 2 * s * a]),
                  np.column_stack([a * (2 - 2 * s), np.full_like(s, a)]))
    th = 0.5 * np.pi * s
    arc = radius * np.column_stack([np.cos(th), np.sin(th)])
    t = np.linspace(0.0, 1.0, n_radial + 1)
    ring = (1 - t[None, :, None]) * cb[:, None] + t[None, :, None] * arc[:, None]  # (s, t, 2)
    ring_nodes = ring.reshape(-1, 2)
    # quads with i along s, j along t: (i, j) -> i * (n_radial + 1) + j; ccw seen from +z
    rq = _grid_quads(n_circ, n_radial)[:, [0, 3, 2, 1]]
    nodes2d = np.concatenate([core_nodes, ring_nodes])
    quads = np.concatenate([core_quads, rq + len(core_nodes)])
    nodes2d, quads = _merge_nodes(nodes2d, quads)
    nodes, hexes, layer = _extrude(nodes2d, quads, np.linspace(0.0, thickness, n_thick + 1))
    r = np.hypot(nodes[:, 0], nodes[:, 1])
    tol = 1e-9 * radius
    axis = np.nonzero(r < tol)[0]
    node_sets = {
        "all": np.arange(len(nodes)),
        "sym_x": np.nonzero(np.abs(nodes[:, 0]) < tol)[0],
        "sym_y": np.nonzero(np.abs(nodes[:, 1]) < tol)[0],
        "rim": np.nonzero(np.abs(r - radius) < 1e-7 * radius)[0],
        "pole": axis,
        "pole_bottom": axis[np.argmin(nodes[axis, 2])][None],
        "pole_top": axis[np.argmax(nodes[axis, 2])][None],
    }
    bottom = hexes[layer == 0][:, HEX_FACES[0]]
    top = hexes[layer == n_thick - 1][:, HEX_FACES[1]]
    ring_e = np.nonzero(layer >= 0)[0]
    rim_faces = hexes[ring_e][:, HEX_FACES].reshape(-1, 4)
    on_rim = np.all(np.abs(np.hypot(*nodes[rim_faces][..., :2].transpose(2, 0, 1)) - radius)
                    < 1e-7 * radius, axis=1)
    return Mesh(nodes, hexes, np.zeros(len(hexes), np.int64), (material,), node_sets,
                {"bottom": bottom, "top": top, "rim": rim_faces[on_rim]})


def _cube_patches(n):
    """Unit directions of the 6 equiangular cubed-sphere patches: (6, n + 1, n + 1, 3)."""
    a = np.tan(np.linspace(-np.pi / 4, np.pi / 4, n + 1))
    u, v = np.meshgrid(a, a, indexing="ij")
    one = np.ones_like(u)
    faces = [np.stack(f, -1) for f in (
        (one, u, v), (-one, v, u), (v, one, u), (u, -one, v), (u, v, one), (v, u, -one))]
    d = np.stack(faces)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def spherical_shell(inner_radius, thickness, n_per_edge, n_thick, *, material="default") -> Mesh:
    """Thin spherical shell centred at the origin as a conforming cubed sphere (mm).

    6 * n_per_edge^2 * n_thick hexahedra (e.g. 11, 2 -> 1452; 32, 2 -> 12288).
    Face sets: "inner" (normals toward the centre, i.e. out of the solid), "outer".
    Node sets: "inner", "outer", "all".
    """
    if n_per_edge < 1 or n_thick < 1:
        raise ValueError("spherical_shell: n_per_edge and n_thick must be >= 1")
    if not 0 < thickness:
        raise ValueError(f"spherical_shell: thickness = {thickness} mm; must be > 0")
    n = n_per_edge
    d = _cube_patches(n).reshape(6, -1, 3)
    radii = inner_radius + thickness * np.linspace(0.0, 1.0, n_thick + 1)
    q = _grid_quads(n, n)
    nodes, hexes = [], []
    npatch = (n + 1) ** 2
    for p in range(6):
        base = p * npatch * (n_thick + 1)
        pts = np.concatenate([r * d[p] for r in radii])
        qq = q.copy()
        # orient the quads counterclockwise seen from outside
        x = d[p][qq[0]]
        if np.dot(np.cross(x[1] - x[0], x[3] - x[0]), x.mean(0)) < 0:
            qq = qq[:, [0, 3, 2, 1]]
        for k in range(n_thick):
            hexes.append(np.concatenate([qq + base + k * npatch, qq + base + (k + 1) * npatch], 1))
        nodes.append(pts)
    nodes, hexes = _merge_nodes(np.concatenate(nodes), np.concatenate(hexes))
    layer = np.tile(np.repeat(np.arange(n_thick), n * n), 6)
    r = np.linalg.norm(nodes, axis=1)
    tol = 1e-7 * inner_radius
    return Mesh(nodes, hexes, np.zeros(len(hexes), np.int64), (material,),
                {"inner": np.nonzero(np.abs(r - radii[0]) < tol)[0],
                 "outer": np.nonzero(np.abs(r - radii[-1]) < tol)[0],
                 "all": np.arange(len(nodes))},
                {"inner": hexes[layer == 0][:, HEX_FACES[0]],
                 "outer": hexes[layer == n_thick - 1][:, HEX_FACES[1]]})
