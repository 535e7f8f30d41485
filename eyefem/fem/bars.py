"""Linear elastic bars with axial stiffness only (sutures, Zinn's zonule).

Each bar joins two *embedded points*: a point x = sum_a N_a(xi) x_a inside a
bilinear quadrilateral face (4 nodes, parametric coordinates xi in [-1, 1]^2), or a
mesh node (the same node four times). Suture anchors therefore need not be mesh
nodes, and they move smoothly with the suture geometry (xi is a differentiable param).

Energy of one bar (seed 4.6: "linear elastic bar element with axial stiffness only"):

    e = EA / (2 L0) (l - L_rest)^2          [N mm],   L_rest = L0 (1 - s)

with l the current length, L0 the initial length, EA the axial stiffness (N) and s the
relative shortening (tightening) of the bar, a param ramped by load stages. With
``tension_only`` a slack bar (l < L_rest) carries nothing.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.terms import Term

_C = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)


def bilinear(xi):
    """Bilinear shape functions (..., 4) at parametric points xi (..., 2) (numpy or jax)."""
    return 0.25 * (1 + xi[..., None, 0] * _C[:, 0]) * (1 + xi[..., None, 1] * _C[:, 1])


def embedded_positions(X4, u4, xi):
    """Positions (n, 3) of embedded points: X4, u4 (n, 4, 3) face nodes; xi (n, 2)."""
    N = bilinear(xi)
    return jnp.einsum("na,nai->ni", N, X4 + u4)


@dataclasses.dataclass(frozen=True, eq=False)
class Bars(Term):
    """Bars between embedded points.

    Args:
      name: term name. params: {"EA": (n,) N, "shortening": (n,) relative, "xi": (n, 2, 2)}.
      nodes_a, nodes_b: (n, 4) node ids of the face holding each end (a node repeated 4
        times for a node end).
      xi_a, xi_b: (n, 2) parametric coordinates of the ends in their faces.
      node_xyz: (n_nodes, 3) reference coordinates of the mesh.
      EA: axial stiffness E * A per bar, N (scalar or (n,)).
      tension_only: slack bars carry no force.
    """

    name: str
    nodes_a: np.ndarray
    nodes_b: np.ndarray
    xi_a: np.ndarray
    xi_b: np.ndarray
    node_xyz: np.ndarray
    EA: float | np.ndarray = 1.0
    tension_only: bool = False

    def __post_init__(self):
        na = np.asarray(self.nodes_a, np.int64).reshape(-1, 4)
        nb = np.asarray(self.nodes_b, np.int64).reshape(-1, 4)
        n = len(na)
        xi = np.stack([np.asarray(self.xi_a, float).reshape(n, 2),
                       np.asarray(self.xi_b, float).reshape(n, 2)], axis=1)
        if np.any(np.abs(xi) > 1 + 1e-9):
            i = int(np.nonzero(np.any(np.abs(xi) > 1 + 1e-9, axis=(1, 2)))[0][0])
            raise ValueError(f"bars '{self.name}': bar {i} has an end outside its face "
                             f"(xi = {xi[i].tolist()}); parametric coordinates must be in [-1, 1]")
        EA = np.broadcast_to(np.asarray(self.EA, float), (n,)).copy()
        if np.any(EA <= 0):
            raise ValueError(f"bars '{self.name}': axial stiffness EA must be > 0 N "
                             f"(bar {int(np.argmin(EA))}: {EA.min()})")
        X = self.node_xyz
        nodes8 = np.concatenate([na, nb], axis=1)
        L0 = np.linalg.norm(np.asarray(embedded_positions(X[nb], 0 * X[nb], xi[:, 1]))
                            - np.asarray(embedded_positions(X[na], 0 * X[na], xi[:, 0])), axis=1)
        if np.any(L0 <= 1e-12):
            i = int(np.argmin(L0))
            raise ValueError(f"bars '{self.name}': bar {i} has zero initial length; its ends "
                             "coincide")
        object.__setattr__(self, "dofs", (3 * nodes8[:, :, None] + np.arange(3)).reshape(n, 24))
        object.__setattr__(self, "params", {"EA": EA, "shortening": np.zeros(n), "xi": xi})
        object.__setattr__(self, "data", {"X": X[nodes8], "L0": L0})

    def static_key(self):
        return (self.tension_only,)

    def endpoints(self, q_loc, params, data):
        """Current end positions xa, xb (n, 3), mm."""
        u = q_loc.reshape(-1, 8, 3)
        xa = embedded_positions(data["X"][:, :4], u[:, :4], params["xi"][:, 0])
        xb = embedded_positions(data["X"][:, 4:], u[:, 4:], params["xi"][:, 1])
        return xa, xb

    def lengths(self, q_loc, params, data):
        xa, xb = self.endpoints(q_loc, params, data)
        return jnp.sqrt(jnp.sum((xb - xa) ** 2, axis=1))

    def geometry(self, q, params):
        """The bars as lines (2 points each) with their axial force 'force_N' (n,)."""
        return bar_lines(self, q, params)

    def local_energy(self, q_loc, params, data):
        l = self.lengths(q_loc, params, data)
        L0 = data["L0"]
        stretch = l - L0 * (1.0 - params["shortening"])
        if self.tension_only:
            stretch = jnp.maximum(stretch, 0.0)
        return 0.5 * params["EA"] / L0 * stretch**2

    def forces(self, q, params):
        """Axial force per bar (n,), N (positive in tension)."""
        ql = jnp.asarray(q)[self.dofs]
        l = self.lengths(ql, params, self.data)
        L0 = self.data["L0"]
        s = l - L0 * (1.0 - params["shortening"])
        if self.tension_only:
            s = jnp.maximum(s, 0.0)
        return np.asarray(params["EA"] / L0 * s)

    def report(self, q, params):
        f = self.forces(q, params)
        return {"max_force_N": float(f.max()) if len(f) else 0.0}


def bar_lines(term, q, params):
    """(points (2n, 3) mm, "line", cells (n, 2), {"force_N": (n,), "length_mm": (n,)}) of a
    bar term with ``endpoints`` and ``forces``."""
    xa, xb = (np.asarray(a) for a in term.endpoints(jnp.asarray(q)[term.dofs], params,
                                                     term.data))
    n = len(xa)
    points = np.stack([xa, xb], axis=1).reshape(2 * n, 3)
    return (points, "line", np.arange(2 * n).reshape(n, 2),
            {"force_N": np.asarray(term.forces(q, params), np.float64),
             "length_mm": np.linalg.norm(xb - xa, axis=1)})


def rotate_z(x, angle):
    """Points x (n, 3) turned by ``angle`` (rad; scalar or (n,)) about the z axis."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1], x[:, 2]], axis=1)


@dataclasses.dataclass(frozen=True, eq=False)
class AnchoredBars(Term):
    """Bars from embedded points to anchors that move with rigid bodies (sutures over a
    rigid buckle).

    End a: a point in a face (nodes_a (n, 4), params xi (n, 2)); end b: an anchor at
    anchor_xyz (n, 3) moved by d[body] * dir + s[body] * dir2 + dr[body] * dir3 (the
    buckle's motion, params "d", "s", "dr" (n_bodies,); dir, dir2, dir3 (n, 3) per anchor)
    and then turned by rot[body] (rad) about the z axis. Energy EA / (2 L0) (l - (L0 - tightening))^2 with the
    tied length L0 (n,) and the tightening (n,) (mm) params: the suture is tied snug at
    the state where it is made, then shortened.

    Args:
      name; nodes_a; xi_a (n, 2); anchor_xyz (n, 3); body (n,) body index of each anchor;
      dirs, dirs2: (n, 3) motion directions of the anchors; n_bodies: number of bodies;
      dirs3: (n, 3) anchor motion per unit change of the fitted buckle radius (default 0);
      node_xyz (n_nodes, 3) reference nodes;
      L0 (n,) tied lengths, mm; EA: N; tension_only (sutures: True).
      extra_dof: global dof of a free radial motion of the (single) body added to d, or
        -1 (see buckle_contact).
      smoothing: a tension-only bar's stretch is eps softplus(stretch / eps) (eps in mm):
        C-infinity, so Newton does not cycle on sutures that are just taut (as every
        suture is when it is tied); the force of a bar at zero stretch is EA/L0 eps ln 2.
    """

    name: str
    nodes_a: np.ndarray
    xi_a: np.ndarray
    anchor_xyz: np.ndarray
    body: np.ndarray
    dirs: np.ndarray
    dirs2: np.ndarray
    n_bodies: int
    node_xyz: np.ndarray
    L0: np.ndarray
    EA: float | np.ndarray = 1.0
    tension_only: bool = True
    extra_dof: int = -1
    smoothing: float = 2e-4
    dirs3: np.ndarray | None = None

    def __post_init__(self):
        na = np.asarray(self.nodes_a, np.int64).reshape(-1, 4)
        n = len(na)
        L0 = np.broadcast_to(np.asarray(self.L0, float), (n,)).copy()
        if np.any(L0 <= 0):
            raise ValueError(f"bars '{self.name}': bar {int(np.argmin(L0))} has tied length "
                             f"{L0.min():.3g} mm; must be > 0")
        EA = np.broadcast_to(np.asarray(self.EA, float), (n,)).copy()
        if np.any(EA <= 0):
            raise ValueError(f"bars '{self.name}': axial stiffness EA must be > 0 N")
        nb = self.n_bodies
        dofs = (3 * na[:, :, None] + np.arange(3)).reshape(n, 12)
        if self.extra_dof >= 0:
            if nb != 1:
                raise ValueError(f"bars '{self.name}': a free body motion needs n_bodies = 1")
            dofs = np.concatenate([dofs, np.full((n, 1), self.extra_dof)], axis=1)
        object.__setattr__(self, "dofs", dofs)
        object.__setattr__(self, "params", {"EA": EA, "tightening": np.zeros(n), "L0": L0,
                                            "xi": np.asarray(self.xi_a, float).reshape(n, 2),
                                            "d": np.zeros(nb), "s": np.zeros(nb),
                                            "dr": np.zeros(nb), "rot": np.zeros(nb)})
        dir3 = np.zeros((n, 3)) if self.dirs3 is None else np.asarray(self.dirs3, float)
        object.__setattr__(self, "data", {"X": self.node_xyz[na], "anchor": np.asarray(
            self.anchor_xyz, float), "body": np.asarray(self.body, np.int64),
            "dir": np.asarray(self.dirs, float), "dir2": np.asarray(self.dirs2, float),
            "dir3": dir3})

    def static_key(self):
        return (self.tension_only, self.extra_dof >= 0)

    def endpoints(self, q_loc, params, data):
        """Current positions (n, 3), mm, of the bites xa and the moved anchors xb."""
        xa = embedded_positions(data["X"], q_loc[:, :12].reshape(-1, 4, 3), params["xi"])
        d = params["d"][data["body"]]
        if self.extra_dof >= 0:
            d = d + q_loc[:, 12]
        b = data["body"]
        xb = (data["anchor"] + d[:, None] * data["dir"] + params["s"][b][:, None] * data["dir2"]
              + params["dr"][b][:, None] * data["dir3"])
        return xa, rotate_z(xb, params["rot"][b])

    def lengths(self, q_loc, params, data):
        xa, xb = self.endpoints(q_loc, params, data)
        return jnp.sqrt(jnp.sum((xb - xa) ** 2, axis=1))

    def geometry(self, q, params):
        """The bars as lines (bite to anchor) with their axial force 'force_N' (n,)."""
        return bar_lines(self, q, params)

    def _stretch(self, q_loc, params, data):
        s = self.lengths(q_loc, params, data) - (params["L0"] - params["tightening"])
        if not self.tension_only:
            return s
        e = self.smoothing
        return e * jnp.logaddexp(s / e, 0.0)  # overflow-safe softplus, exact slope at 0

    def local_energy(self, q_loc, params, data):
        return 0.5 * params["EA"] / params["L0"] * self._stretch(q_loc, params, data) ** 2

    def axial_forces(self, q_loc, params, data):
        """Axial force per bar (n,), N: dE/dl (JAX-traceable)."""
        s = self.lengths(q_loc, params, data) - (params["L0"] - params["tightening"])
        k = params["EA"] / params["L0"]
        if not self.tension_only:
            return k * s
        return k * self._stretch(q_loc, params, data) * jax.nn.sigmoid(s / self.smoothing)

    def forces(self, q, params):
        """Axial force per bar (n,), N (positive in tension)."""
        return np.asarray(self.axial_forces(jnp.asarray(q)[self.dofs], params, self.data))

    def report(self, q, params):
        f = self.forces(q, params)
        return {"max_force_N": float(f.max()) if len(f) else 0.0}


@dataclasses.dataclass(frozen=True, eq=False)
class TiedBars(Bars):
    """Tension-only bars between two embedded points, tied at a length and shortened
    (sutures over a deformable buckle: from a bite in a scleral face to a point in the
    buckle's outer faces).

    Energy EA / (2 L0) p^2 with the smoothed stretch p = eps softplus((l - (L0 - tightening))
    / eps) (as :class:`AnchoredBars`), l the current length between the two embedded points.

    Args: as :class:`Bars` (name; nodes_a, nodes_b (n, 4); xi_a, xi_b (n, 2); node_xyz
      (n_nodes, 3), mm; EA, N); smoothing: eps, mm.
    Params: {"EA" (n,) N, "xi" (n, 2, 2), "tightening" (n,) mm, "L0" (n,) tied lengths, mm
    (default: the reference lengths)}.
    """

    smoothing: float = 2e-4

    def __post_init__(self):
        super().__post_init__()
        p = self.params
        object.__setattr__(self, "params", {"EA": p["EA"], "xi": p["xi"], "L0": self.data["L0"].copy(),
                                            "tightening": np.zeros(len(p["EA"]))})

    def static_key(self):
        return (self.smoothing,)

    def _raw(self, q_loc, params, data):
        return self.lengths(q_loc, params, data) - (params["L0"] - params["tightening"])

    def local_energy(self, q_loc, params, data):
        e = self.smoothing
        p = e * jnp.logaddexp(self._raw(q_loc, params, data) / e, 0.0)
        return 0.5 * params["EA"] / params["L0"] * p**2

    def forces(self, q, params):
        """Axial force per bar (n,), N (positive in tension)."""
        s = self._raw(jnp.asarray(q)[self.dofs], params, self.data)
        e = self.smoothing
        p = e * jnp.logaddexp(s / e, 0.0)
        return np.asarray(params["EA"] / params["L0"] * p * jax.nn.sigmoid(s / e))
