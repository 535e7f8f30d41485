"""Deformable-rigid penalty contact (seed 4.4): a node set against moving rigid triangle
surfaces (the definitions: eyefem.fem.contact)."""

from __future__ import annotations

import copy
import dataclasses

import jax.numpy as jnp
import numpy as np

from eyefem.fem.contact import PENALTY_FACTOR, _bucket, node_areas
from eyefem.fem.mesh import Mesh
from eyefem.fem.terms import Term


@dataclasses.dataclass(frozen=True, eq=False)
class RigidContact(Term):
    """Frictionless penalty contact of a node set with moving rigid bodies.

    Args:
      name: term name; params {"d": (n_bodies,) displacement of each body along its
        direction, mm; "s": (n_bodies,) along its direction2, mm}.
      mesh: the mesh holding the slave node set.
      node_set: contact (slave) nodes.
      bodies: RigidBody surfaces (normals pointing out of the rigid body).
      modulus: Young's modulus of the slave material, MPa (for the default penalty).
      penalty: alpha per node, N/mm (overrides the default).
      search_gap: nodes closer than this to a surface are paired, mm (default 2 h).
      max_initial_penetration: larger initial penetration is an error, mm (default h / 2).
    """

    name: str
    mesh: Mesh
    node_set: str
    bodies: tuple
    modulus: float = 1.0
    penalty: float | None = None
    search_gap: float | None = None
    max_initial_penetration: float | None = None
    dynamic = True
    contact = True

    def __post_init__(self):
        nodes = self.mesh.node_set(self.node_set)
        if not self.bodies:
            raise ValueError(f"contact '{self.name}': no rigid bodies given")
        names = [b.name for b in self.bodies]
        if len(set(names)) != len(names):
            raise ValueError(f"contact '{self.name}': rigid body names must be unique: {names}")
        area, h = node_areas(self.mesh, nodes)
        alpha = self.penalty if self.penalty is not None else PENALTY_FACTOR * self.modulus * h
        if not alpha > 0:
            raise ValueError(f"contact '{self.name}': penalty {alpha} N/mm; must be > 0")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "area", np.maximum(area, 1e-12))
        object.__setattr__(self, "alpha", float(alpha))
        object.__setattr__(self, "h", h)
        object.__setattr__(self, "params", {"d": np.zeros(len(self.bodies)),
                                            "s": np.zeros(len(self.bodies))})
        self._pair(np.zeros(3 * self.mesh.n_nodes), self.params, initial=True)

    def static_key(self):
        return ()

    def _pair(self, q, params, initial=False):
        X = self.mesh.nodes[self.nodes]
        x = X + q[: 3 * self.mesh.n_nodes].reshape(-1, 3)[self.nodes]
        sg = self.search_gap if self.search_gap is not None else 2.0 * self.h
        rows = []
        for k, body in enumerate(self.bodies):
            dk, sk = float(params["d"][k]), float(params["s"][k])
            t, c, g = body.closest(x, dk, s=sk)
            # a node whose closest point lies beyond an open edge of the body does not
            # face it: keep only nodes over the surface (tangential offset ~ 0)
            d1, d2 = body.motion_dirs(c)
            off = np.linalg.norm(x - dk * d1 - sk * d2 - c - g[:, None] * body.normals[t], axis=1)
            sel = np.nonzero((g < sg) & (off <= 0.1 * self.h + 0.5 * np.abs(g)))[0]
            rows.append((sel, np.full(len(sel), k), c[sel], body.normals[t[sel]], g[sel],
                         d1[sel], d2[sel]))
        sel, bid, c, n, g, d1, d2 = (np.concatenate([r[i] for r in rows]) for i in range(7))
        if initial and len(g):
            tol = (self.max_initial_penetration if self.max_initial_penetration is not None
                   else 0.5 * self.h)
            bad = np.nonzero(g < -tol)[0]
            if bad.size:
                j = bad[np.argmin(g[bad])]
                raise ValueError(
                    f"contact '{self.name}': {bad.size} nodes start inside rigid bodies beyond "
                    f"{tol:.3g} mm, e.g. node {self.nodes[sel[j]]} at depth {-g[j]:.3g} mm in "
                    f"'{self.bodies[bid[j]].name}'; move the body or the mesh apart")
        P = _bucket(len(sel))
        pad = P - len(sel)
        node = np.concatenate([self.nodes[sel], np.full(pad, self.nodes[0])])
        w = np.concatenate([np.ones(len(sel)), np.zeros(pad)])

        data = {"X": self.mesh.nodes[node],
                "c": np.concatenate([c, np.zeros((pad, 3))]),
                "n": np.concatenate([n, np.tile([0.0, 0.0, 1.0], (pad, 1))]),
                "dir": np.concatenate([d1, np.zeros((pad, 3))]),
                "dir2": np.concatenate([d2, np.zeros((pad, 3))]),
                "body": np.concatenate([bid, np.zeros(pad, np.int64)]),
                "w": w, "alpha": np.full(P, self.alpha),
                "area": np.concatenate([self.area[sel], np.ones(pad)])}
        object.__setattr__(self, "dofs", 3 * node[:, None] + np.arange(3))
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "n_pairs", len(sel))

    def update(self, q, params):
        new = copy.copy(self)
        new._pair(np.asarray(q), params)
        return new

    @staticmethod
    def gaps(q_loc, params, data):
        x = data["X"] + q_loc
        target = (data["c"] + params["d"][data["body"]][:, None] * data["dir"]
                  + params["s"][data["body"]][:, None] * data["dir2"])
        return jnp.einsum("pi,pi->p", x - target, data["n"])

    def local_energy(self, q_loc, params, data):
        g = jnp.minimum(self.gaps(q_loc, params, data), 0.0)
        return 0.5 * data["w"] * data["alpha"] * g * g

    def _state(self, q, params):
        g = np.asarray(self.gaps(np.asarray(q)[self.dofs], params, self.data))
        w = self.data["w"] > 0
        return g[w], self.dofs[w, 0] // 3, self.data["area"][w]

    def report(self, q, params):
        g, _, _ = self._state(q, params)
        pen = np.maximum(-g, 0.0)
        return {"active": int(np.sum(pen > 0)), "max_penetration_mm": float(pen.max(initial=0.0)),
                "force_N": float(self.alpha * pen.sum())}

    def point_fields(self, q, params, n_nodes):
        """'<name>_gap_mm' (NaN at unpaired nodes), '<name>_pressure_MPa' (0 off contact)."""
        g, node, area = self._state(q, params)
        gap = np.full(n_nodes, np.nan)
        pres = np.zeros(n_nodes)
        gap[node] = g
        pres[node] = self.alpha * np.maximum(-g, 0.0) / area
        return {f"{self.name}_gap_mm": gap, f"{self.name}_pressure_MPa": pres}

    def geometry(self, q, params):
        """The rigid bodies' triangles moved by their params d and s; cell data 'body'."""
        pts, tris, body, off = [], [], [], 0
        for k, b in enumerate(self.bodies):
            d1, d2 = b.motion_dirs(b.points)
            pts.append(b.points + float(params["d"][k]) * d1 + float(params["s"][k]) * d2)
            tris.append(b.triangles + off)
            body.append(np.full(len(b.triangles), k, np.int32))
            off += len(b.points)
        return (np.concatenate(pts), "triangle", np.concatenate(tris),
                {"body": np.concatenate(body)})
