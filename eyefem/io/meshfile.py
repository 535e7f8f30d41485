"""A user's hexahedral mesh from a file meshio reads (gmsh .msh, Abaqus .inp, VTU...).

Named sets become eyefem's:
- gmsh physical groups (``field_data`` name -> (tag, dimension), ``gmsh:physical`` cell
  data): volumes name the materials of their hexahedra; surfaces become face sets (the
  mesh's boundary faces whose four nodes they cover, oriented outward whatever the file's
  quad orientation) and node sets; curves and points become node sets;
- Abaqus element sets (meshio ``cell_sets``) name materials, node sets (``point_sets``)
  node sets;
- always: the node set "all", and the face set "boundary" (every boundary face).
Hexahedra are needed: other volume cells (tetrahedra, wedges) are refused by name.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eyefem.fem.mesh import Mesh, boundary_faces

VOLUME_CELLS = {"tetra", "tetra10", "wedge", "wedge15", "pyramid", "pyramid13",
                "hexahedron20", "hexahedron27"}
"""meshio volume cell types eyefem cannot use (its elements are 8-node hexahedra)."""


class MeshFileError(ValueError):
    """A mesh file eyefem cannot use; the message names the file and what is wrong."""


def read_hex_mesh(path: str | Path) -> Mesh:
    """The Mesh of a hexahedral mesh file, with materials and named sets (module doc)."""
    import meshio

    path = Path(path)
    try:
        m = meshio.read(path)
    except Exception as exc:  # noqa: BLE001 - meshio raises many types for a bad file
        raise MeshFileError(f"{path}: meshio cannot read it ({type(exc).__name__}: {exc}); "
                            "give a gmsh .msh, Abaqus .inp or VTU hexahedral mesh") from None
    kinds = [c.type for c in m.cells]
    other = sorted({k for k in kinds if k in VOLUME_CELLS})
    if "hexahedron" not in kinds:
        raise MeshFileError(f"{path}: no hexahedra (cells: {', '.join(sorted(set(kinds))) or 'none'})"
                            "; eyefem needs 8-node hexahedra: mesh the volume with hexahedra "
                            "(gmsh: Mesh.RecombineAll = 1 and Mesh.Recombine3DAll = 1, or a "
                            "transfinite volume)")
    if other:
        raise MeshFileError(f"{path}: {', '.join(other)} cells; eyefem needs 8-node hexahedra "
                            "only (remesh the volume with hexahedra)")
    hex_blocks = [i for i, k in enumerate(kinds) if k == "hexahedron"]
    hexes = np.concatenate([m.cells[i].data for i in hex_blocks]).astype(np.int64)
    used = np.unique(hexes)
    renumber = np.full(len(m.points), -1, np.int64)
    renumber[used] = np.arange(len(used))
    nodes = np.asarray(m.points, float)[used]
    if nodes.shape[1] == 2:
        raise MeshFileError(f"{path}: 2-D points; eyefem needs a 3-D hexahedral mesh")
    groups = _groups(m, hex_blocks)
    mat_names = [name for name, (dim, _) in groups.items() if dim == 3] or ["default"]
    material_ids = np.full(len(hexes), -1, np.int64)
    for j, name in enumerate(mat_names):
        if name in groups:
            material_ids[groups[name][1]] = j
    if np.any(material_ids < 0):
        if groups and any(dim == 3 for dim, _ in groups.values()):
            first = int(np.nonzero(material_ids < 0)[0][0])
            raise MeshFileError(f"{path}: hexahedron {first} (and {int(np.sum(material_ids < 0)) - 1} "
                                "more) is in no volume group; put every hexahedron in a named "
                                "physical volume / element set (its material)")
        material_ids[:] = 0
    hexes = renumber[hexes]
    bfaces = boundary_faces(hexes)
    node_sets = {"all": np.arange(len(nodes))}
    face_sets = {"boundary": bfaces}
    for name, (dim, ids) in groups.items():
        if dim == "points":
            node_sets[name] = np.unique(renumber[ids][renumber[ids] >= 0])
        elif dim in (0, 1, 2):
            node_sets[name] = np.unique(renumber[ids][renumber[ids] >= 0])
            if dim == 2:
                inside = np.zeros(len(nodes), bool)
                inside[node_sets[name]] = True
                face_sets[name] = bfaces[inside[bfaces].all(axis=1)]
    return Mesh(nodes, hexes, material_ids, tuple(mat_names), node_sets=node_sets,
                face_sets=face_sets)


def _groups(m, hex_blocks) -> dict:
    """name -> (dimension, ids): dimension 3 with hexahedron indices (counted over the hex
    blocks in order), 0-2 with point ids of the group's cells, "points" with point ids."""
    out = {}
    offsets = np.cumsum([0] + [len(m.cells[i].data) for i in hex_blocks])
    phys = m.cell_data.get("gmsh:physical")
    for name, (tag, dim) in ((k, (int(v[0]), int(v[1]))) for k, v in (m.field_data or {}).items()
                             if len(v) >= 2 and phys is not None):
        if dim == 3:
            ids = [offsets[j] + np.nonzero(phys[i] == tag)[0] for j, i in enumerate(hex_blocks)]
            out[name] = (3, np.concatenate(ids))
        else:
            pts = [m.cells[i].data[phys[i] == tag].ravel() for i in range(len(m.cells))
                   if i not in hex_blocks]
            out[name] = (dim, np.unique(np.concatenate(pts)) if pts else np.zeros(0, np.int64))
    for name, per_block in (m.cell_sets or {}).items():
        if name in out or name.startswith("gmsh:"):
            continue
        ids = [offsets[j] + np.asarray(per_block[i], np.int64)
               for j, i in enumerate(hex_blocks) if i < len(per_block) and per_block[i] is not None]
        if ids and sum(len(x) for x in ids):
            out[name] = (3, np.concatenate(ids))
    for name, ids in (m.point_sets or {}).items():
        out.setdefault(name, ("points", np.asarray(ids, np.int64)))
    return out
