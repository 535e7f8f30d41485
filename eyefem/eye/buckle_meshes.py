"""Deformable buckles as hexahedral meshes: encircling bands and tires, radial sponges.

An encircling buckle (kind "band", "tire_flat" or "tire_ridged") is its cross-section
(:func:`ring_profile`) swept once around the optical axis and cut at the +y meridian, so
that its two ends can be pulled past each other (the seed's displacement condition at
the band ends, 6.1 stage 2), or closed (a loop tightened by shortening its rest length,
:mod:`eyefem.fem.loop_solid`). The tires are modelled with their band as one silicone
body (the band runs in the tire's groove; both neo-Hookean c10 = 1.0 MPa in the seed).
A radial sponge (:func:`deformable_sponge`) is a solid cylinder curved along the sclera.
"""

from __future__ import annotations

import numpy as np

from eyefem.eye.buckles import KINDS, SPONGE_LENGTH, Buckle
from eyefem.eye.eyemodel import EyeGeometry
from eyefem.fem.generators import extrude, grid_quads
from eyefem.fem.mesh import Mesh, boundary_faces
from eyefem.fem.vessels import disk_section

BAND_C10 = 1.0
"""Silicone of a deformable band: neo-Hookean c10, MPa (material name "band")."""
TIRE_C10 = 1.0
"""Silicone of a deformable tire (with its band): neo-Hookean c10, MPa (material "tire")."""
RING_KINDS = ("band", "tire_flat", "tire_ridged")
"""Buckle kinds with a deformable encircling body."""


def ring_profile(buckle: Buckle, n_thick: int = 1):
    """Cross-section of an encircling buckle in (v, u): v across (mm, 0 on the centre
    line, toward the limbus negative), u up from its lowest point (mm, away from the eye).

    The band is 2 elements across; a tire 8 (a ridged tire's ridge, 3 mm wide and 0.75 mm
    high under the middle of its base, gets 4 of them and one element of its own height).
    Returns nodes (n2, 2), quads (nq, 4) counterclockwise in (v, u), column (n2,) (index
    of the node's v), inner (n2,) bool (on the eye-facing side: the base's lower face and
    the ridge's bottom and flanks), outer (n2,) bool (on the upper face).
    """
    w, t, ridge, rw = KINDS[buckle.kind]
    if buckle.kind == "band":
        v = np.linspace(-w / 2, w / 2, 3)
    elif ridge == 0:
        v = np.linspace(-w / 2, w / 2, 9)
    else:
        side = np.linspace(-w / 2, -rw / 2, 3)
        v = np.concatenate([side, np.linspace(-rw / 2, rw / 2, 5)[1:], -side[::-1][1:]])
    nv, tol = len(v), 1e-9 * w
    V, U = np.meshgrid(v, ridge + t * np.arange(n_thick + 1) / n_thick, indexing="ij")
    nodes = np.column_stack([V.ravel(), U.ravel()])
    quads = grid_quads(nv - 1, n_thick)
    column = np.repeat(np.arange(nv), n_thick + 1)
    j = np.tile(np.arange(n_thick + 1), nv)
    inner, outer = j == 0, j == n_thick
    if ridge > 0:
        ri = np.nonzero(np.abs(v) <= rw / 2 + tol)[0]
        bottom = len(nodes) + np.arange(len(ri))
        top = ri * (n_thick + 1)
        quads = np.concatenate([quads, np.column_stack([bottom[:-1], bottom[1:], top[1:],
                                                        top[:-1]])])
        inner[top[1:-1]] = False  # the base's lower face above the ridge is inside
        nodes = np.concatenate([nodes, np.column_stack([v[ri], np.zeros(len(ri))])])
        column = np.concatenate([column, ri])
        inner = np.concatenate([inner, np.ones(len(ri), bool)])
        outer = np.concatenate([outer, np.zeros(len(ri), bool)])
    return nodes, quads, column, inner, outer


def deformable_band(buckle: Buckle, g: EyeGeometry, inner_radius: float, n_circ: int,
                    n_thick: int = 1, material: str | None = None, closed: bool = False) -> Mesh:
    """Hexahedral encircling band or tire (with its band) on the eye, cut at +y (or closed).

    The cross-section :func:`ring_profile` swept around the optical axis in ``n_circ``
    elements from the +y meridian counterclockwise (seen from +z): a node at (v, u) of
    the profile lies at radius inner_radius + u (mm) about the globe centre and polar
    angle theta_b - v / inner_radius (theta_b: the buckle centre line), so the lowest
    face follows the sphere of radius ``inner_radius`` across the buckle's width (like the
    rigid ring's profile) and the thickness runs radially.

    Args: n_circ, n_thick: elements around and through the base; material: default
      "band" for a band, "tire" for a tire; closed: no cut, the last cross-section of
      nodes is the first (a closed loop, tightened by shortening its rest length:
      :class:`eyefem.fem.loop_solid.ShortenedLoopSolid`).
    Node sets: "all", "end0", "end1" (the two ends on the cut: coincident, distinct
    nodes; the same nodes, the cross-section at +y, on a closed ring), "mid" (on the centre line theta_b), "inner" (eye-facing: the contact's slave
    nodes); face sets: "inner" (eye-facing), "outer" (the upper face, normals away from
    the globe: the sutures' points over the buckle are embedded there).
    Pulling end0 along +x (clockwise at the cut) and end1 along -x shortens the loop.
    """
    if buckle.kind not in RING_KINDS:
        raise ValueError(f"deformable_band: buckle kind '{buckle.kind}'; the deformable "
                         f"encircling bodies are {list(RING_KINDS)}")
    if int(n_circ) != n_circ or n_circ < 12:
        raise ValueError(f"deformable_band: n_circ = {n_circ}; must be an integer >= 12")
    if int(n_thick) != n_thick or n_thick < 1:
        raise ValueError(f"deformable_band: n_thick = {n_thick}; must be an integer >= 1")
    material = material or ("band" if buckle.kind == "band" else "tire")
    uv, quads, _, inner2, outer2 = ring_profile(buckle, n_thick)
    X, hexes, _ = extrude(uv, quads, np.arange(n_circ + 1, dtype=float))
    v, u, k = X[:, 0], X[:, 1], X[:, 2]
    phi = np.pi / 2 + 2 * np.pi * k / n_circ
    r, tau = inner_radius + u, buckle.centre_angle(g) - v / inner_radius
    nodes = np.column_stack([r * np.sin(tau) * np.cos(phi), r * np.sin(tau) * np.sin(phi),
                             r * np.cos(tau)])
    e = nodes[hexes]
    det = np.einsum("ei,ei->e", np.cross(e[:, 1] - e[:, 0], e[:, 3] - e[:, 0]), e[:, 4] - e[:, 0])
    hexes = np.where((det < 0)[:, None], hexes[:, [4, 5, 6, 7, 0, 1, 2, 3]], hexes)
    level = np.repeat(np.arange(n_circ + 1), len(uv))
    inner, outer = np.tile(inner2, n_circ + 1), np.tile(outer2, n_circ + 1)
    if closed:  # the nodes are level-major: the last level's become the first's
        last = n_circ * len(uv)
        hexes = np.where(hexes >= last, hexes - last, hexes)
        nodes, v, level, inner, outer = (a[:last] for a in (nodes, v, level, inner, outer))
    bf = boundary_faces(hexes)
    node_sets = {"all": np.arange(len(nodes)), "end0": np.nonzero(level == 0)[0],
                 "end1": np.nonzero(level == (0 if closed else n_circ))[0], "inner": np.nonzero(inner)[0],
                 "mid": np.nonzero(np.abs(v) < 1e-9 * buckle.width)[0]}
    face_sets = {"inner": bf[np.all(inner[bf], axis=1)], "outer": bf[np.all(outer[bf], axis=1)]}
    return Mesh(nodes, hexes, np.zeros(len(hexes), np.int64), (material,), node_sets, face_sets)


def ring_fit_groups(buckle: Buckle, n_circ: int, n_thick: int = 1,
                    closed: bool = False) -> np.ndarray:
    """Group of every node of :func:`deformable_band` (n,) moved together when it is
    fitted snug on the eye: a band's or flat tire's radial columns (each settles on the
    sclera under it), a ridged tire's cross-sections (so that its ridge keeps its height)."""
    uv, _, column, _, _ = ring_profile(buckle, n_thick)
    n_levels = n_circ if closed else n_circ + 1
    level = np.repeat(np.arange(n_levels), len(uv))
    if KINDS[buckle.kind][2] > 0:
        return level
    return level * (column.max() + 1) + np.tile(column, n_levels)


def band_n_circ(mesh: Mesh, sclera_nodes: np.ndarray, buckle: Buckle, g: EyeGeometry) -> int:
    """Elements around a deformable band: twice the number of outer scleral nodes on the
    mesh ring nearest the buckle centre line (two band elements per scleral face)."""
    X = mesh.nodes[sclera_nodes]
    tau = np.arccos(np.clip(X[:, 2] / np.linalg.norm(X, axis=1), -1, 1))
    a = g.scleral_radius * (tau - buckle.centre_angle(g))
    ring = np.abs(a - a[np.argmin(np.abs(a))]) < 1e-3
    return int(2 * max(ring.sum(), 12))


SPONGE_C10 = 0.1
"""Silicone sponge of a deformable sponge: neo-Hookean c10, MPa (seed 6.2; material
"sponge")."""


def deformable_sponge(buckle: Buckle, g: EyeGeometry, axis_radius: float, n_len: int = 10,
                      n_circ: int = 8, material: str = "sponge") -> Mesh:
    """Hexahedral radial silicone sponge (kind "sponge_radial": 5 mm across, 10 mm long).

    A solid cylinder of radius w / 2 whose axis is the arc of radius ``axis_radius`` (mm)
    about the globe centre in the sponge's meridian plane, centred on the polar angle of
    the buckle centre line and spanning SPONGE_LENGTH of arc (as the rigid radial
    sponge, which is curved along the sclera). Cross-section: an O-grid (square core
    blended into the circle, :func:`eyefem.fem.vessels.disk_section`) with ``n_circ``
    elements around (a multiple of 8); ``n_len`` elements along (even).

    Node sets: "all", "inner" (the mantle's nodes on the eye-facing side, up to 0.3 w / 2
    above the axis: the contact's slave nodes), "mid" (the cross-section at the centre);
    face sets: "outer" (mantle faces of the half away from the eye, normals outward: the
    sutures' points over the sponge are embedded there), "mantle".
    """
    if buckle.kind != "sponge_radial":
        raise ValueError(f"deformable_sponge: buckle kind '{buckle.kind}'; only "
                         "'sponge_radial' has a deformable (hexahedral) sponge")
    if int(n_len) != n_len or n_len < 2 or n_len % 2:
        raise ValueError(f"deformable_sponge: n_len = {n_len}; must be even and >= 2")
    if int(n_circ) != n_circ or n_circ < 8 or n_circ % 8:
        raise ValueError(f"deformable_sponge: n_circ = {n_circ}; must be a multiple of 8")
    rho = buckle.width / 2
    nodes2d, quads, _ = disk_section(0.75 * rho, 0.25 * rho, n_circ, 1, 1)
    s = np.linspace(-0.5, 0.5, n_len + 1) * SPONGE_LENGTH
    X, hexes, _ = extrude(nodes2d, quads, s)
    u, v, t = X[:, 0], X[:, 1], X[:, 2]  # u: radial (out of the eye), v: across, t: arc
    th, ph = buckle.centre_angle(g) + t / axis_radius, np.radians(buckle.meridian_deg)
    n = np.column_stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    e = np.array([-np.sin(ph), np.cos(ph), 0.0])
    nodes = (axis_radius + u)[:, None] * n + v[:, None] * e
    # (u, v, t) -> (n, e, m) is left-handed (n x e = -m): mirror across to keep the
    # elements' orientation
    nodes -= 2 * v[:, None] * e
    tol = 1e-9 * rho
    r2 = np.hypot(u, v)
    bf = boundary_faces(hexes)
    on_mantle = np.all(np.abs(r2[bf] - rho) < tol, axis=1)
    outer = on_mantle & np.all(u[bf] > -tol, axis=1)
    node_sets = {"all": np.arange(len(nodes)),
                 "inner": np.nonzero((np.abs(r2 - rho) < tol) & (u < 0.3 * rho))[0],
                 "mid": np.nonzero(np.abs(t) < tol)[0]}
    face_sets = {"outer": bf[outer], "mantle": bf[on_mantle]}
    return Mesh(nodes, hexes, np.zeros(len(hexes), np.int64), (material,), node_sets, face_sets)
