"""Hexahedral meshes: nodes, 8-node bricks in VTK order, materials, named sets.

A :class:`Mesh` is immutable; functions that change a mesh return a copy. It is
validated at construction: every element has a positive Jacobian at every Gauss
point, ids are in range, and face sets are consistently oriented.

VTK / meshio hexahedron node order (reference coordinates xi, eta, zeta in [-1, 1])::

    0 (-,-,-)  1 (+,-,-)  2 (+,+,-)  3 (-,+,-)
    4 (-,-,+)  5 (+,-,+)  6 (+,+,+)  7 (-,+,+)

Quadrilateral faces are stored with their nodes ordered so that the right-hand rule
gives the normal pointing out of the element they bound (out of the solid).
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType
from typing import Mapping

import numpy as np

HEX_CORNERS = np.array(
    [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
     [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64)
"""Reference coordinates of the 8 hexahedron nodes, (8, 3)."""

HEX_FACES = np.array(
    [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4],
     [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]], dtype=np.int64)
"""Local node numbers of the 6 faces of a hexahedron, outward normal, (6, 4)."""

QUAD_CORNERS = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)

_G = 1.0 / np.sqrt(3.0)


def hex_gauss_points():
    """2x2x2 Gauss rule: points (8, 3) in reference coordinates and weights (8,)."""
    return HEX_CORNERS * _G, np.ones(8)


def quad_gauss_points():
    """2x2 Gauss rule on [-1, 1]^2: points (4, 2) and weights (4,)."""
    return QUAD_CORNERS * _G, np.ones(4)


def hex_shape(xi):
    """Trilinear shape functions N (..., 8) and reference gradients (..., 8, 3) at xi (..., 3)."""
    xi = np.asarray(xi, dtype=np.float64)
    c = HEX_CORNERS
    t = 1.0 + xi[..., None, :] * c  # (..., 8, 3)
    n = 0.125 * t[..., 0] * t[..., 1] * t[..., 2]
    dn = np.stack([0.125 * c[:, 0] * t[..., 1] * t[..., 2],
                   0.125 * c[:, 1] * t[..., 0] * t[..., 2],
                   0.125 * c[:, 2] * t[..., 0] * t[..., 1]], axis=-1)
    return n, dn


def quad_shape(xi):
    """Bilinear shape functions N (..., 4) and reference gradients (..., 4, 2) at xi (..., 2)."""
    xi = np.asarray(xi, dtype=np.float64)
    c = QUAD_CORNERS
    t = 1.0 + xi[..., None, :] * c
    n = 0.25 * t[..., 0] * t[..., 1]
    dn = np.stack([0.25 * c[:, 0] * t[..., 1], 0.25 * c[:, 1] * t[..., 0]], axis=-1)
    return n, dn


def hex_geometry(nodes, hexes):
    """Reference-configuration quantities of every element at the 2x2x2 Gauss points.

    Args:
      nodes: (n_nodes, 3) coordinates, mm.
      hexes: (n_elem, 8) node ids.
    Returns:
      grad_n: (n_elem, 8, 8, 3) shape-function gradients d N_a / d X at each Gauss point, 1/mm.
      dv: (n_elem, 8) Gauss weight times det(dX/dxi), mm^3 (the volume each point carries).
      det: (n_elem, 8) det(dX/dxi).
    """
    return element_geometry(np.asarray(nodes)[hexes], np)


def element_geometry(xe, xp=np):
    """:func:`hex_geometry` from element node coordinates xe (n_elem, 8, 3), mm, with the
    array module ``xp`` (numpy, or jax.numpy to differentiate with respect to xe)."""
    xg, wg = hex_gauss_points()
    _, dn = hex_shape(xg)  # (8g, 8a, 3)
    jac = xp.einsum("eai,gaj->egij", xe, dn)  # dX_i/dxi_j
    det = xp.linalg.det(jac)
    inv = xp.linalg.inv(xp.where(xp.abs(det)[..., None, None] > 0, jac, np.eye(3)))
    grad_n = xp.einsum("gaj,egji->egai", dn, inv)
    return grad_n, det * wg, det


def boundary_faces(hexes):
    """Faces that belong to exactly one element, outward oriented: (n_faces, 4) node ids."""
    faces = hexes[:, HEX_FACES].reshape(-1, 4)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.ravel()] == 1]


def face_edges(faces):
    """Directed edges (n_faces * 4, 2) of quadrilateral faces."""
    return np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)


def open_edges(faces):
    """Edges of a face set used by only one face: (n, 2) node ids (empty if closed)."""
    e = face_edges(faces)
    key = np.sort(e, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return e[counts[inv.ravel()] == 1]


def check_face_orientation(faces, name="face set"):
    """Raise if two faces of a set traverse a shared edge in the same direction."""
    e = face_edges(faces)
    _, counts = np.unique(e, axis=0, return_counts=True)
    if np.any(counts > 1):
        _, idx, counts = np.unique(e, axis=0, return_index=True, return_counts=True)
        bad = e[idx[counts > 1][0]]
        faces_bad = np.nonzero(np.any(faces == bad[0], axis=1) & np.any(faces == bad[1], axis=1))[0]
        raise ValueError(
            f"{name}: faces {faces_bad.tolist()} traverse edge ({bad[0]}, {bad[1]}) in the same "
            "direction: inconsistent orientation; reverse the node order of one of them")


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """An 8-node hexahedral mesh with materials and named node and face sets.

    Attributes:
      nodes: (n_nodes, 3) reference coordinates, mm.
      hexes: (n_elem, 8) node ids in VTK order.
      material_ids: (n_elem,) index into ``materials`` for every element.
      materials: names of the materials, referred to by name in case files.
      node_sets: name -> (n,) node ids.
      face_sets: name -> (n_faces, 4) node ids, outward (right-hand) ordered.
      element_sets: name -> (n,) element ids.
      material_fractions: None (every element wholly its material), or (n_elem,
        n_materials) the volume fraction of each material in each element (rows sum to
        1): an element cut by a material boundary stores the mixture of their energies
        (eyefem.fem.solid.element_coeffs); ``material_ids`` still names the one that
        labels it in the outputs.
    """

    nodes: np.ndarray
    hexes: np.ndarray
    material_ids: np.ndarray
    materials: tuple[str, ...] = ("default",)
    node_sets: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    face_sets: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    element_sets: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    material_fractions: np.ndarray | None = None

    def __post_init__(self):
        nodes = np.ascontiguousarray(self.nodes, dtype=np.float64)
        hexes = np.ascontiguousarray(self.hexes, dtype=np.int64)
        mids = np.ascontiguousarray(self.material_ids, dtype=np.int64)
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise ValueError(f"mesh nodes: shape {nodes.shape}; expected (n_nodes, 3)")
        if not np.all(np.isfinite(nodes)):
            bad = np.nonzero(~np.all(np.isfinite(nodes), axis=1))[0]
            raise ValueError(f"mesh nodes {bad[:10].tolist()}: non-finite coordinates")
        if hexes.ndim != 2 or hexes.shape[1] != 8:
            raise ValueError(f"mesh hexes: shape {hexes.shape}; expected (n_elem, 8)")
        n = len(nodes)
        bad = np.nonzero(np.any((hexes < 0) | (hexes >= n), axis=1))[0]
        if bad.size:
            raise ValueError(f"element {bad[0]}: node ids {hexes[bad[0]].tolist()} out of range "
                             f"[0, {n}); {bad.size} such elements")
        if mids.shape != (len(hexes),):
            raise ValueError(f"material_ids: shape {mids.shape}; expected ({len(hexes)},)")
        mats = tuple(self.materials)
        bad = np.nonzero((mids < 0) | (mids >= len(mats)))[0]
        if bad.size:
            raise ValueError(f"element {bad[0]}: material id {mids[bad[0]]} not in 0..{len(mats) - 1} "
                             f"(materials {mats})")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "hexes", hexes)
        object.__setattr__(self, "material_ids", mids)
        object.__setattr__(self, "materials", mats)
        if self.material_fractions is not None:
            object.__setattr__(self, "material_fractions",
                               _checked_fractions(self.material_fractions, len(hexes), mats))
        ns = {}
        for k, v in dict(self.node_sets).items():
            v = np.asarray(v, dtype=np.int64).ravel()
            badn = v[(v < 0) | (v >= n)]
            if badn.size:
                raise ValueError(f"node set '{k}': node ids {badn[:5].tolist()} do not exist "
                                 f"(mesh has {n} nodes)")
            ns[k] = v
        fs = {}
        for k, v in dict(self.face_sets).items():
            v = np.asarray(v, dtype=np.int64).reshape(-1, 4)
            badf = np.nonzero(np.any((v < 0) | (v >= n), axis=1))[0]
            if badf.size:
                raise ValueError(f"face set '{k}': face {badf[0]} names nodes "
                                 f"{v[badf[0]].tolist()} outside [0, {n})")
            check_face_orientation(v, f"face set '{k}'")
            fs[k] = v
        es = {}
        for k, v in dict(self.element_sets).items():
            v = np.asarray(v, dtype=np.int64).ravel()
            bade = v[(v < 0) | (v >= len(hexes))]
            if bade.size:
                raise ValueError(f"element set '{k}': element ids {bade[:5].tolist()} do not exist")
            es[k] = v
        object.__setattr__(self, "node_sets", MappingProxyType(ns))
        object.__setattr__(self, "face_sets", MappingProxyType(fs))
        object.__setattr__(self, "element_sets", MappingProxyType(es))
        if len(hexes):
            _, _, det = hex_geometry(nodes, hexes)
            bad = np.nonzero(np.min(det, axis=1) <= 0)[0]
            if bad.size:
                e = bad[0]
                raise ValueError(
                    f"element {e} (nodes {hexes[e].tolist()}): non-positive Jacobian "
                    f"{det[e].min():.3g} at a Gauss point; the element is inverted or degenerate "
                    f"({bad.size} such elements). Check the node order (VTK hexahedron) and geometry")

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_elem(self) -> int:
        return len(self.hexes)

    def node_set(self, name: str) -> np.ndarray:
        """Node ids of a named set; a clear error if it does not exist."""
        try:
            return self.node_sets[name]
        except KeyError:
            raise KeyError(f"no node set '{name}'; the mesh has {sorted(self.node_sets)}") from None

    def face_set(self, name: str) -> np.ndarray:
        """Faces (n, 4) of a named set; a clear error if it does not exist."""
        try:
            return self.face_sets[name]
        except KeyError:
            raise KeyError(f"no face set '{name}'; the mesh has {sorted(self.face_sets)}") from None

    def replace(self, **changes) -> "Mesh":
        """A validated copy with some attributes changed."""
        return dataclasses.replace(self, **changes)

    def jacobian_ratio(self) -> np.ndarray:
        """(n_elem,) min/max of det(dX/dxi) over the Gauss points: 1 for a parallelepiped."""
        _, _, det = hex_geometry(self.nodes, self.hexes)
        return det.min(axis=1) / det.max(axis=1)


def _checked_fractions(fractions, n_elem: int, materials: tuple) -> np.ndarray:
    """Material volume fractions (n_elem, n_materials), validated (Mesh)."""
    f = np.ascontiguousarray(fractions, dtype=np.float64)
    if f.shape != (n_elem, len(materials)):
        raise ValueError(f"material_fractions: shape {f.shape}; expected ({n_elem}, "
                         f"{len(materials)}) (elements, materials {materials})")
    bad = np.nonzero(~np.all(np.isfinite(f) & (f >= 0), axis=1)
                     | (np.abs(f.sum(axis=1) - 1.0) > 1e-9))[0]
    if bad.size:
        raise ValueError(f"element {bad[0]}: material fractions {f[bad[0]].tolist()}; they must "
                         f"be >= 0 and sum to 1 ({bad.size} such elements)")
    return f


def merge(*parts: tuple[str, Mesh]) -> Mesh:
    """Join meshes into one (disjoint bodies); set names get the prefix ``'<part>/'``.

    Materials with the same name are shared. Args: pairs (part name, mesh).
    """
    nodes, hexes, mids, ns, fs, es, remaps = [], [], [], {}, {}, {}, []
    mats: list[str] = []
    offn = offe = 0
    for pname, m in parts:
        remap = np.array([mats.index(x) if x in mats else (mats.append(x) or len(mats) - 1)
                          for x in m.materials], dtype=np.int64)
        nodes.append(m.nodes)
        hexes.append(m.hexes + offn)
        mids.append(remap[m.material_ids])
        remaps.append((remap, m))
        for k, v in m.node_sets.items():
            ns[f"{pname}/{k}"] = v + offn
        for k, v in m.face_sets.items():
            fs[f"{pname}/{k}"] = v + offn
        for k, v in m.element_sets.items():
            es[f"{pname}/{k}"] = v + offe
        ns[f"{pname}"] = np.arange(offn, offn + m.n_nodes)
        es[f"{pname}"] = np.arange(offe, offe + m.n_elem)
        offn += m.n_nodes
        offe += m.n_elem
    mixed = None
    if any(m.material_fractions is not None for _, m in parts):
        mixed = np.zeros((offe, len(mats)))
        row = 0
        for remap, m in remaps:  # a part without fractions is wholly its materials
            f = (m.material_fractions if m.material_fractions is not None
                 else np.eye(len(m.materials))[m.material_ids])
            mixed[row:row + len(f), remap] = f
            row += len(f)
    return Mesh(np.concatenate(nodes), np.concatenate(hexes), np.concatenate(mids),
                tuple(mats), ns, fs, es, mixed)
