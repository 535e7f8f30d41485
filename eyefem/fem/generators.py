"""Structured hexahedral meshes for the verification and benchmark problems (mm).

- :func:`box`: a brick, with node and face sets on its six planes;
- :func:`quarter_disk`: 1/4 of a thin disk (O-grid: square core + ring, no degenerate
  element at the centre) for the seed's inflation problem;
- :func:`spherical_shell`: a thin spherical shell as a cubed sphere (6 equiangular
  patches, no pole singularity), or its octant, for the benchmark and cavity tests.

Nodes shared between blocks are built from bitwise-identical coordinates, so merging
them is exact; each builder checks the merged node count against the expected one.
"""

from __future__ import annotations

import numpy as np

from eyefem.fem.mesh import HEX_FACES, Mesh, boundary_faces

# local face of a hexahedron on each side of a structured block (see mesh.HEX_FACES)
_SIDE_FACE = {"z0": 0, "z1": 1, "y0": 2, "x1": 3, "y1": 4, "x0": 5}


def merge_nodes(nodes, cells, expected=None):
    """Merge coincident nodes: (unique nodes, renumbered cells); ``expected`` node count."""
    nodes = nodes + 0.0  # -0.0 -> 0.0
    scale = max(np.abs(nodes).max(), 1e-300)
    _, first, inv = np.unique(np.round(nodes / scale, 9), axis=0, return_index=True,
                              return_inverse=True)
    if expected is not None and len(first) != expected:
        raise RuntimeError(f"node merging gave {len(first)} nodes, expected {expected}")
    return nodes[first], inv.ravel()[cells]


def extrude(nodes2d, quads, z):
    """Stack 2-D quads (ccw seen from +z) into hexes over the levels z (nz + 1,).

    Returns nodes (n2 * (nz + 1), 3), hexes (nq * nz, 8) and the layer of each hex.
    """
    n2 = len(nodes2d)
    nz = len(z) - 1
    nodes = np.concatenate([np.column_stack([nodes2d, np.full(n2, zk)]) for zk in z])
    layers = [np.concatenate([quads + k * n2, quads + (k + 1) * n2], axis=1) for k in range(nz)]
    return nodes, np.concatenate(layers), np.repeat(np.arange(nz), len(quads))


def grid_quads(ni, nj):
    """Quads (ni * nj, 4) of an (ni + 1) x (nj + 1) node grid numbered i * (nj + 1) + j.

    Counterclockwise when i runs along +x and j along +y.
    """
    idx = np.arange((ni + 1) * (nj + 1)).reshape(ni + 1, nj + 1)
    return np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)


def hex_mesh(nodes, hexes, material, node_sets, face_sets):
    return Mesh(nodes, hexes, np.zeros(len(hexes), np.int64), (material,), node_sets, face_sets)


def box(lx, ly, lz, nx, ny, nz, *, origin=(0.0, 0.0, 0.0), material="default") -> Mesh:
    """Brick [ox, ox + lx] x [oy, oy + ly] x [oz, oz + lz] with nx * ny * nz hexahedra.

    Args:
      lx, ly, lz: edge lengths, mm (> 0).
      nx, ny, nz: elements along each edge (>= 1).
      origin: (3,) lowest corner, mm.
    Node and face sets: "x0", "x1", "y0", "y1", "z0", "z1" (the six planes; faces
    outward), "all" (nodes), "boundary" (all boundary faces).
    """
    for name, n in (("nx", nx), ("ny", ny), ("nz", nz)):
        if int(n) != n or n < 1:
            raise ValueError(f"box: {name} = {n}; need an integer >= 1")
    for name, v in (("lx", lx), ("ly", ly), ("lz", lz)):
        if not v > 0:
            raise ValueError(f"box: {name} = {v} mm; must be > 0")
    o = np.asarray(origin, float).reshape(3)
    g = [np.linspace(0.0, l, n + 1) + oa for l, n, oa in ((lx, nx, o[0]), (ly, ny, o[1]),
                                                          (lz, nz, o[2]))]
    X, Y, Z = np.meshgrid(*g, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    c = idx[:-1, :-1, :-1], idx[1:, :-1, :-1], idx[1:, 1:, :-1], idx[:-1, 1:, :-1]
    t = idx[:-1, :-1, 1:], idx[1:, :-1, 1:], idx[1:, 1:, 1:], idx[:-1, 1:, 1:]
    hexes = np.stack([a.ravel() for a in c + t], 1)
    eidx = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    sel = {"x0": np.s_[0], "x1": np.s_[-1], "y0": np.s_[:, 0], "y1": np.s_[:, -1],
           "z0": np.s_[:, :, 0], "z1": np.s_[:, :, -1]}
    node_sets, face_sets = {"all": np.arange(len(nodes))}, {}
    for name, s in sel.items():
        node_sets[name] = idx[s].ravel()
        face_sets[name] = hexes[eidx[s].ravel()][:, HEX_FACES[_SIDE_FACE[name]]]
    face_sets["boundary"] = np.concatenate([face_sets[k] for k in sel])
    return hex_mesh(nodes, hexes, material, node_sets, face_sets)


def quarter_disk(radius, thickness, n_radial, n_circ, n_thick, *, core=0.5,
                 material="default") -> Mesh:
    """1/4 of a disk (x, y >= 0, 0 <= z <= thickness) meshed as an O-grid.

    A square core [0, core * radius]^2 of (n_circ / 2)^2 elements and a ring of
    n_circ (around) x n_radial (outward) elements blending the core's edge into the arc
    r = radius; n_thick layers. Hexahedra: ((n_circ / 2)^2 + n_circ * n_radial) * n_thick,
    e.g. (n_radial, n_circ, n_thick) = (52, 50, 1) -> 3225, (20, 50, 2) -> 3250,
    (56, 26, 2) -> 3250.

    Args:
      radius, thickness: mm (> 0).
      n_radial, n_circ, n_thick: element counts (n_circ even).
      core: half-width of the square core as a fraction of the radius, in (0, 1).
    Node sets: "sym_x" (x = 0), "sym_y" (y = 0), "rim" (r = radius, all z), "pole"
    (x = y = 0, all z), "pole_bottom", "pole_top" (one node each), "all".
    Face sets: "bottom" (z = 0, normal -z), "top" (z = thickness, +z), "rim" (+r).
    """
    if int(n_circ) != n_circ or n_circ < 2 or n_circ % 2:
        raise ValueError(f"quarter_disk: n_circ = {n_circ}; must be even and >= 2")
    if n_radial < 1 or n_thick < 1:
        raise ValueError(f"quarter_disk: n_radial = {n_radial}, n_thick = {n_thick}; "
                         "both must be >= 1")
    if not (radius > 0 and thickness > 0):
        raise ValueError(f"quarter_disk: radius = {radius}, thickness = {thickness} mm; "
                         "both must be > 0")
    if not 0 < core < 1:
        raise ValueError(f"quarter_disk: core = {core}; must be in (0, 1)")
    nc = n_circ // 2
    a = core * radius
    g = np.linspace(0.0, a, nc + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    core_nodes = np.stack([X.ravel(), Y.ravel()], 1)
    core_quads = grid_quads(nc, nc)
    # core edge, from (a, 0) up to (a, a) then left to (0, a): the very same coordinates
    cb = np.concatenate([np.column_stack([np.full(nc + 1, a), g]),
                         np.column_stack([g[::-1][1:], np.full(nc, a)])])
    th = np.linspace(0.0, 0.5 * np.pi, n_circ + 1)
    arc = radius * np.column_stack([np.cos(th), np.sin(th)])
    arc[0] = radius, 0.0
    arc[-1] = 0.0, radius
    t = np.linspace(0.0, 1.0, n_radial + 1)[None, :, None]
    ring = (1 - t) * cb[:, None] + t * arc[:, None]  # (n_circ + 1, n_radial + 1, 2)
    # ring grid: i around (ccw), j outward -> quads (i, j) clockwise, so reverse
    rq = grid_quads(n_circ, n_radial)[:, [0, 3, 2, 1]]
    nodes2d = np.concatenate([core_nodes, ring.reshape(-1, 2)])
    quads = np.concatenate([core_quads, rq + len(core_nodes)])
    nodes2d, quads = merge_nodes(nodes2d, quads, (nc + 1) ** 2 + (n_circ + 1) * n_radial)
    nodes, hexes, layer = extrude(nodes2d, quads, np.linspace(0.0, thickness, n_thick + 1))
    r = np.hypot(nodes[:, 0], nodes[:, 1])
    tol = 1e-9 * radius
    on_rim = np.abs(r - radius) < tol
    axis = np.nonzero(r < tol)[0]
    node_sets = {
        "all": np.arange(len(nodes)),
        "sym_x": np.nonzero(np.abs(nodes[:, 0]) < tol)[0],
        "sym_y": np.nonzero(np.abs(nodes[:, 1]) < tol)[0],
        "rim": np.nonzero(on_rim)[0],
        "pole": axis,
        "pole_bottom": axis[np.argmin(nodes[axis, 2])][None],
        "pole_top": axis[np.argmax(nodes[axis, 2])][None],
    }
    bf = boundary_faces(hexes)
    face_sets = {"bottom": hexes[layer == 0][:, HEX_FACES[0]],
                 "top": hexes[layer == n_thick - 1][:, HEX_FACES[1]],
                 "rim": bf[np.all(on_rim[bf], axis=1)]}
    return hex_mesh(nodes, hexes, material, node_sets, face_sets)


def _cube_patches(n):
    """Unit directions of the 6 equiangular cubed-sphere patches: (6, n + 1, n + 1, 3).

    Built so that points shared by two patches have bitwise-identical coordinates.
    """
    a = np.tan(np.linspace(-np.pi / 4, np.pi / 4, n + 1))
    a = 0.5 * (a - a[::-1])  # exactly odd
    a[0], a[-1] = -1.0, 1.0
    u, v = np.meshgrid(a, a, indexing="ij")
    one = np.ones_like(u)
    d = np.stack([np.stack(f, -1) for f in (
        (one, u, v), (-one, v, u), (v, one, u), (u, -one, v), (u, v, one), (v, u, -one))])
    norm = np.sqrt(np.sort(d * d, axis=-1).sum(-1, keepdims=True))  # permutation invariant
    return d / norm + 0.0


def spherical_shell(inner_radius, thickness, n_per_edge, n_thick, *, octant=False,
                    material="default") -> Mesh:
    """Thin spherical shell about the origin as a conforming cubed sphere.

    Each of the 6 cube faces is an equiangular n_per_edge x n_per_edge patch projected
    onto the sphere, with n_thick layers through the wall: 6 * n_per_edge^2 * n_thick
    hexahedra (e.g. (11, 2) -> 1452, (32, 2) -> 12288, (25, 3) -> 11250).

    Args:
      inner_radius, thickness: mm (> 0).
      n_per_edge, n_thick: element counts.
      octant: keep only the part x, y, z >= 0 (3 quarter patches meeting at the (1, 1, 1)
        direction, the same nodes as the full shell): n_per_edge must be even, and there
        are 3/4 * n_per_edge^2 * n_thick hexahedra.
    Face sets: "inner" (normals toward the centre, i.e. out of the solid), "outer"; with
    octant also "sym_x", "sym_y", "sym_z" (on the planes, normals -x, -y, -z).
    Node sets: "inner", "outer", "all"; with octant also "sym_x", "sym_y", "sym_z".
    """
    if n_per_edge < 1 or n_thick < 1:
        raise ValueError(f"spherical_shell: n_per_edge = {n_per_edge}, n_thick = {n_thick}; "
                         "both must be >= 1")
    if not (inner_radius > 0 and thickness > 0):
        raise ValueError(f"spherical_shell: inner_radius = {inner_radius}, thickness = "
                         f"{thickness} mm; both must be > 0")
    if octant and n_per_edge % 2:
        raise ValueError(f"spherical_shell: n_per_edge = {n_per_edge}; must be even with "
                         "octant=True (the symmetry planes cut the patches in half)")
    n = n_per_edge
    npatch = (n + 1) ** 2
    d = _cube_patches(n).reshape(6, npatch, 3)
    radii = inner_radius + thickness * np.linspace(0.0, 1.0, n_thick + 1)
    q = grid_quads(n, n)
    nodes, hexes = [], []
    for p in range(6):
        base = p * npatch * (n_thick + 1)
        qq = q
        x = d[p][q[0]]  # orient the quads counterclockwise seen from outside
        if np.dot(np.cross(x[1] - x[0], x[3] - x[0]), x.mean(0)) < 0:
            qq = q[:, [0, 3, 2, 1]]
        nodes.append((radii[:, None, None] * d[p]).reshape(-1, 3))
        hexes += [np.concatenate([qq + base + k * npatch, qq + base + (k + 1) * npatch], 1)
                  for k in range(n_thick)]
    nodes, hexes = merge_nodes(np.concatenate(nodes), np.concatenate(hexes),
                                (6 * n * n + 2) * (n_thick + 1))
    layer = np.tile(np.repeat(np.arange(n_thick), n * n), 6)
    if octant:
        keep = np.all(nodes[hexes].mean(axis=1) > 0, axis=1)
        used, hexes = np.unique(hexes[keep], return_inverse=True)
        hexes = hexes.reshape(-1, 8)
        nodes, layer = nodes[used], layer[keep]
    r = np.linalg.norm(nodes, axis=1)
    tol = 1e-9 * radii[-1]
    node_sets = {"inner": np.nonzero(np.abs(r - radii[0]) < tol)[0],
                 "outer": np.nonzero(np.abs(r - radii[-1]) < tol)[0],
                 "all": np.arange(len(nodes))}
    face_sets = {"inner": hexes[layer == 0][:, HEX_FACES[0]],
                 "outer": hexes[layer == n_thick - 1][:, HEX_FACES[1]]}
    if octant:
        bf = boundary_faces(hexes)
        for k, name in enumerate(("sym_x", "sym_y", "sym_z")):
            on = np.abs(nodes[:, k]) < tol
            node_sets[name] = np.nonzero(on)[0]
            face_sets[name] = bf[np.all(on[bf], axis=1)]
    return hex_mesh(nodes, hexes, material, node_sets, face_sets)
