"""Rigid bodies as triangle meshes, and closest-point queries against them.

A rigid body is a triangle surface (points (n, 3) mm, triangles (m, 3) with the
right-hand-rule normal pointing out of the body) that translates by ``d * direction``
(d in mm, a param ramped by load stages; seed 4.4: "each rigid body moves along an
arbitrary direction vector").
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree


@dataclasses.dataclass(frozen=True, eq=False)
class RigidBody:
    """A translating rigid triangle surface.

    Attributes: name; points (n, 3) mm; triangles (m, 3); direction (3,) unit vector of
    the motion d * direction; direction2 (3,) a second motion s * direction2 (unit or
    zero; e.g. a buckle's shift along the meridian). With ``radial`` the body instead
    shrinks toward the z axis: every point moves by d along -(its horizontal radial
    unit vector), and by s along direction2 turned about z to the point's meridian
    (direction2 given at the +x meridian): an encircling band tightened uniformly.
    """

    name: str
    points: np.ndarray
    triangles: np.ndarray
    direction: tuple = (0.0, 0.0, 1.0)
    direction2: tuple = (0.0, 0.0, 0.0)
    radial: bool = False

    def __post_init__(self):
        P = np.asarray(self.points, float)
        T = np.asarray(self.triangles, np.int64)
        if P.ndim != 2 or P.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 3:
            raise ValueError(f"rigid body '{self.name}': points must be (n, 3) and triangles (m, 3)")
        if T.min() < 0 or T.max() >= len(P):
            raise ValueError(f"rigid body '{self.name}': triangle node ids outside [0, {len(P)})")
        n = np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]])
        area = 0.5 * np.linalg.norm(n, axis=1)
        scale = np.ptp(P, axis=0).max() ** 2
        bad = np.nonzero(area <= 1e-12 * scale)[0]
        if bad.size:
            raise ValueError(f"rigid body '{self.name}': triangles {bad[:10].tolist()} have zero "
                             "area; remove or fix them")
        e = np.stack([T, np.roll(T, -1, axis=1)], -1).reshape(-1, 2)
        _, cnt = np.unique(e, axis=0, return_counts=True)
        if np.any(cnt > 1):
            u, idx, cnt = np.unique(e, axis=0, return_index=True, return_counts=True)
            edge = u[cnt > 1][0]
            tris = np.nonzero(np.any(T == edge[0], 1) & np.any(T == edge[1], 1))[0]
            raise ValueError(f"rigid body '{self.name}': triangles {tris.tolist()} traverse edge "
                             f"{edge.tolist()} in the same direction: inconsistent orientation")
        d = np.asarray(self.direction, float)
        if np.linalg.norm(d) == 0:
            raise ValueError(f"rigid body '{self.name}': direction is the zero vector")
        object.__setattr__(self, "points", P)
        object.__setattr__(self, "triangles", T)
        object.__setattr__(self, "direction", d / np.linalg.norm(d))
        d2 = np.asarray(self.direction2, float)
        object.__setattr__(self, "direction2", d2 / np.linalg.norm(d2) if d2.any() else d2)
        object.__setattr__(self, "normals", n / (2 * area)[:, None])
        object.__setattr__(self, "_tree", cKDTree(P[T].mean(axis=1)))
        object.__setattr__(self, "_radius", float(np.sqrt(np.max(np.sum(
            (P[T] - P[T].mean(1, keepdims=True)) ** 2, axis=2)))))

    @classmethod
    def from_file(cls, name, path, direction=(0.0, 0.0, 1.0)) -> "RigidBody":
        """Read a triangle surface with meshio (STL, OBJ, VTU, ...)."""
        import meshio

        m = meshio.read(path)
        tris = [c.data for c in m.cells if c.type == "triangle"]
        if not tris:
            raise ValueError(f"rigid body '{name}': {path} holds no triangles")
        return cls(name, m.points[:, :3], np.concatenate(tris), direction)

    def motion_dirs(self, c):
        """Unit directions (n, 3) of the d and s motions at surface points c (n, 3)."""
        c = np.atleast_2d(c)
        if not self.radial:
            return (np.broadcast_to(self.direction, c.shape).copy(),
                    np.broadcast_to(self.direction2, c.shape).copy())
        phi = np.arctan2(c[:, 1], c[:, 0])
        cs, sn = np.cos(phi), np.sin(phi)
        d1 = np.stack([-cs, -sn, np.zeros_like(cs)], 1)
        a = self.direction2
        d2 = np.stack([cs * a[0] - sn * a[1], sn * a[0] + cs * a[1], np.full_like(cs, a[2])], 1)
        return d1, d2

    def closest(self, x, d=0.0, k=8, s=0.0):
        """Closest points on the surface moved by d * direction + s * direction2 to x (n, 3).

        Returns: triangle ids (n,), closest points (n, 3) in the reference (unmoved)
        frame, signed gaps (n,) along the triangle normal (negative: penetration).
        """
        x = np.asarray(x, float)
        d1, d2 = self.motion_dirs(x)  # for a radial body: exact on surfaces of revolution
        x = x - d * d1 - s * d2
        k = min(k, len(self.triangles))
        _, cand = self._tree.query(x, k=k)
        cand = cand.reshape(len(x), k)
        best_d = np.full(len(x), np.inf)
        best_t = np.zeros(len(x), np.int64)
        best_c = np.zeros_like(x)
        for j in range(k):
            t = cand[:, j]
            c = closest_point_triangle(x, *(self.points[self.triangles[t, i]] for i in range(3)))
            dist = np.linalg.norm(x - c, axis=1)
            better = dist < best_d - 1e-14
            best_d[better], best_t[better], best_c[better] = dist[better], t[better], c[better]
        gap = np.einsum("ni,ni->n", x - best_c, self.normals[best_t])
        return best_t, best_c, gap


def closest_point_triangle(p, a, b, c):
    """Closest points on triangles (a, b, c) to points p, all (n, 3) (Ericson's regions)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ni,ni->n", ab, ap), np.einsum("ni,ni->n", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ni,ni->n", ab, bp), np.einsum("ni,ni->n", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ni,ni->n", ab, cp), np.einsum("ni,ni->n", ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        out = a + ab * v[:, None] + ac * w[:, None]  # interior
        # edge ab
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        t = d1 / (d1 - d3)
        out[m] = (a + ab * t[:, None])[m]
        # edge ac
        m2 = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        t = d2 / (d2 - d6)
        out[m2] = (a + ac * t[:, None])[m2]
        # edge bc
        m3 = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        out[m3] = (b + (c - b) * t[:, None])[m3]
    # vertices
    out[(d1 <= 0) & (d2 <= 0)] = a[(d1 <= 0) & (d2 <= 0)]
    out[(d3 >= 0) & (d4 <= d3)] = b[(d3 >= 0) & (d4 <= d3)]
    out[(d6 >= 0) & (d5 <= d6)] = c[(d6 >= 0) & (d5 <= d6)]
    return out


# --- generators ----------------------------------------------------------------------------

def grid_triangles(nu, nv, closed_u=False):
    """Triangles of a (nu + 1) x (nv + 1) grid (u-major), optionally periodic in u."""
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    if closed_u:
        idx[-1] = idx[0]
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                           np.stack([a, c, d], -1).reshape(-1, 3)])


def plane(name, centre, normal, size, n=4, direction=None) -> RigidBody:
    """A square plate of side ``size`` (mm) centred at ``centre``, normal ``normal`` (outward)."""
    nrm = np.asarray(normal, float)
    nrm /= np.linalg.norm(nrm)
    t1 = np.cross(nrm, [1.0, 0, 0] if abs(nrm[0]) < 0.9 else [0, 1.0, 0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(nrm, t1)
    s = np.linspace(-size / 2, size / 2, n + 1)
    U, V = np.meshgrid(s, s, indexing="ij")
    pts = np.asarray(centre, float) + U.ravel()[:, None] * t1 + V.ravel()[:, None] * t2
    return RigidBody(name, pts, grid_triangles(n, n), nrm if direction is None else direction)


def cylinder(name, centre, axis, radius, length, n_circ=48, n_len=8, inward=False,
             direction=(0.0, 0.0, 1.0)) -> RigidBody:
    """Lateral surface of a cylinder; normals outward (or inward: a tube's inside)."""
    ax = np.asarray(axis, float)
    ax /= np.linalg.norm(ax)
    e1 = np.cross(ax, [1.0, 0, 0] if abs(ax[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ax, e1)
    th = np.linspace(0, 2 * np.pi, n_circ + 1)
    z = np.linspace(-length / 2, length / 2, n_len + 1)
    T, Z = np.meshgrid(th, z, indexing="ij")
    pts = (np.asarray(centre, float) + radius * (np.cos(T).ravel()[:, None] * e1
                                                 + np.sin(T).ravel()[:, None] * e2)
           + Z.ravel()[:, None] * ax)
    tris = grid_triangles(n_circ, n_len, closed_u=True)
    tris = tris[:, ::-1] if inward else tris  # grid order gives outward normals
    return RigidBody(name, pts, tris, direction)


def ring_segment(name, centre, axis, radius, width, phi0, phi1, n_circ=8, n_width=2,
                 direction=None) -> RigidBody:
    """A band of a cylinder (radius, width along the axis) between angles phi0, phi1 (rad),
    normals pointing toward the axis (it presses inward, like an encircling band piece).
    Default direction: radially inward at the segment's middle."""
    ax = np.asarray(axis, float)
    ax /= np.linalg.norm(ax)
    e1 = np.cross(ax, [1.0, 0, 0] if abs(ax[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ax, e1)
    th = np.linspace(phi0, phi1, n_circ + 1)
    z = np.linspace(-width / 2, width / 2, n_width + 1)
    T, Z = np.meshgrid(th, z, indexing="ij")
    pts = (np.asarray(centre, float) + radius * (np.cos(T).ravel()[:, None] * e1
                                                 + np.sin(T).ravel()[:, None] * e2)
           + Z.ravel()[:, None] * ax)
    pm = 0.5 * (phi0 + phi1)
    inward = -(np.cos(pm) * e1 + np.sin(pm) * e2)
    return RigidBody(name, pts, grid_triangles(n_circ, n_width)[:, ::-1],  # toward the axis
                     inward if direction is None else direction)


def sphere(name, centre, radius, n=12, direction=(0.0, 0.0, 1.0)) -> RigidBody:
    """A sphere (cubed-sphere triangulation), normals outward."""
    a = np.tan(np.linspace(-np.pi / 4, np.pi / 4, n + 1))
    u, v = np.meshgrid(a, a, indexing="ij")
    one = np.ones_like(u)
    pts, tris = [], []
    for k, f in enumerate(((one, u, v), (-one, v, u), (v, one, u), (u, -one, v),
                           (u, v, one), (v, u, -one))):
        d = np.stack(f, -1).reshape(-1, 3)
        pts.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        t = grid_triangles(n, n) + k * (n + 1) ** 2
        x = pts[-1]
        nn = np.cross(x[t[0, 1] - k * (n + 1) ** 2] - x[t[0, 0] - k * (n + 1) ** 2],
                      x[t[0, 2] - k * (n + 1) ** 2] - x[t[0, 0] - k * (n + 1) ** 2])
        if nn @ x[t[0, 0] - k * (n + 1) ** 2] < 0:
            t = t[:, ::-1]
        tris.append(t)
    P = np.concatenate(pts)
    key = np.round(P, 12)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return RigidBody(name, np.asarray(centre, float) + radius * P[first],
                     inv.ravel()[np.concatenate(tris)], direction)
