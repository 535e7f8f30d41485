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

from eyefem.fem.terms import Term, host_kernel

_C = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)


def bilinear(xi):
    """Bilinear shape functions (..., 4) at parametric points xi (..., 2) (numpy or jax)."""
    return 0.25 * (1 + xi[..., None, 0] * _C[:, 0]) * (1 + xi[..., None, 1] * _C[:, 1])


def dbilinear(xi):
    """Derivatives (..., 4, 2) of the bilinear shape functions with respect to xi (..., 2)."""
    return np.stack([0.25 * _C[:, 0] * (1 + xi[..., None, 1] * _C[:, 1]),
                     0.25 * _C[:, 1] * (1 + xi[..., None, 0] * _C[:, 0])], -1)


def embedded_positions(X4, u4, xi):
    """Positions (n, 3) of embedded points: X4, u4 (n, 4, 3) face nodes; xi (n, 2)."""
    N = bilinear(xi)
    return jnp.einsum("na,nai->ni", N, X4 + u4)


_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(6)
_GAUSS_XI = np.stack(np.meshgrid(_GAUSS_X, _GAUSS_X, indexing="ij"), -1).reshape(-1, 2)
_GAUSS_WT = np.outer(_GAUSS_W, _GAUSS_W).ravel()

PATCH_PADDING = 8
"""A patch's node and face counts are padded up to a multiple of this (:func:`end_patches`):
bites that cover a few more or fewer faces for another design (a suture width, a meridian)
keep the arrays' shapes, and with them the compiled kernels of the suture terms, which a
planner would otherwise compile again, and keep, for each shape."""


@dataclasses.dataclass(frozen=True)
class EndPatches:
    """Bar ends spread over a patch of a surface: a suture's bite of physical size.

    A spread end is the weighted mean of the surface points of its patch, x = sum_j w_j x_j
    (a distributing coupling of translations: the bar's force is shared out over the
    patch's nodes as w_j f), with w_j = int N_j phi dA / int phi dA over the surface faces
    near the end's point X_b(xi) and the kernel phi = (1 - s^2)^2 (0 beyond s = 1) of the
    scaled distance s^2 = (|d|^2 - (d.t)^2) / R^2 + (d.t)^2 / A^2, d = X - X_b: a disc of
    radius R (A = R, t = 0), or an ellipse of half-width R across and half-length A along
    the unit tangent t (a mattress suture's pass along the buckle's edge). The weights
    follow xi smoothly (a differentiable param), so bites still move with the design. An
    end that is not spread is the point x = sum_a N_a(xi) x_a of its face.

    Attributes:
      nodes: (n, m) node ids; columns 0-3 are the face holding the end's point, the
        padding columns repeat column 0 (no face refers to them; m and f are padded
        to a multiple of PATCH_PADDING).
      faces: (n, f, 4) the patch's faces as column indices into ``nodes``.
      face_mask: (n, f) 1 for a face of the patch, 0 for padding (and for a point end).
      spread: (n,) True for an end spread over its patch.
      radius: the patch's (half-)width R, mm.
      half_length: A, mm: its half-length along ``along`` (A = R: a disc).
      along: (n, 3) unit tangents of the patches' long axes (zeros for discs).
    """

    nodes: np.ndarray
    faces: np.ndarray
    face_mask: np.ndarray
    spread: np.ndarray
    radius: float
    half_length: float | None = None
    along: np.ndarray | None = None

    @property
    def elongated(self) -> bool:
        """True for elliptic patches (half-length differs from the radius)."""
        return self.half_length is not None and self.half_length != self.radius

    def data(self) -> dict:
        """The arrays :func:`patch_weights` reads (leading axis n)."""
        n = len(self.nodes)
        A = self.radius if self.half_length is None else self.half_length
        t = np.zeros((n, 3)) if self.along is None else np.asarray(self.along, float)
        return {"faces": self.faces, "mask": self.face_mask,
                "spread": self.spread.astype(float), "R": np.full(n, float(self.radius)),
                "A": np.full(n, float(A)), "t": t}


def end_patches(node_xyz, surface_faces, nodes4, xi, spread, radius, margin=None,
                half_length=None, toward=None) -> EndPatches:
    """The patches of bar ends on a surface (:class:`EndPatches`).

    Args:
      node_xyz: (n_nodes, 3) reference coordinates, mm.
      surface_faces: (s, 4) the surface's quadrilaterals (node ids).
      nodes4: (n, 4) the face holding each end; xi: (n, 2) its parametric coordinates.
      spread: (n,) bool, the ends to spread (the others stay points).
      radius: R, mm (> 0): the disc's radius, or the ellipse's half-width.
      margin: faces within max(R, A) + margin of an end's point are kept (default R / 2),
        so that the end can move by that much with the design before its patch is cut short.
      half_length: A, mm (> 0; default R: a disc): the half-length of an elliptic patch,
        whose long axis is the surface tangent across the bar, t = n x (p - X_b) / |...|
        (n the surface normal at the end's point X_b): a suture's pass along the buckle's
        edge when the bar crosses the edge.
      toward: (n, 3) the point p each bar pulls toward (its other end, reference), mm;
        needed for an elliptic patch.
    """
    if not radius > 0:
        raise ValueError(f"bite patch radius = {radius} mm; must be > 0 (0: point bites)")
    if half_length is not None and not half_length > 0:
        raise ValueError(f"bite patch half-length = {half_length} mm; must be > 0")
    X = np.asarray(node_xyz, float)
    nodes4 = np.asarray(nodes4, np.int64).reshape(-1, 4)
    xi = np.asarray(xi, float).reshape(-1, 2)
    spread = np.broadcast_to(np.asarray(spread, bool), (len(nodes4),)).copy()
    sf = np.asarray(surface_faces, np.int64)
    cen = X[sf].mean(1)
    circ = np.linalg.norm(X[sf] - cen[:, None], axis=2).max(1)
    long = radius if half_length is None else max(radius, half_length)
    reach = long + (0.5 * radius if margin is None else margin)
    points = np.einsum("na,nai->ni", bilinear(xi), X[nodes4])
    along = None
    if half_length is not None and half_length != radius:
        along = _patch_axes(X, nodes4, xi, points, toward, spread)
    node_lists, face_lists = [], []
    for i in range(len(nodes4)):
        if not spread[i]:
            node_lists.append(list(nodes4[i]))
            face_lists.append(np.zeros((0, 4), np.int64))
            continue
        near = sf[np.linalg.norm(cen - points[i], axis=1) < reach + circ]
        ids = list(nodes4[i]) + [v for v in np.unique(near) if v not in nodes4[i]]
        col = {v: j for j, v in enumerate(ids)}
        node_lists.append(ids)
        face_lists.append(np.vectorize(col.__getitem__)(near).reshape(-1, 4))
    m = -(-max(len(v) for v in node_lists) // PATCH_PADDING) * PATCH_PADDING
    f = -(-max(1, max(len(v) for v in face_lists)) // PATCH_PADDING) * PATCH_PADDING
    nodes = np.array([v + [v[0]] * (m - len(v)) for v in node_lists], np.int64)
    faces = np.zeros((len(nodes4), f, 4), np.int64)
    faces[:] = np.arange(4)
    mask = np.zeros((len(nodes4), f))
    for i, fl in enumerate(face_lists):
        faces[i, :len(fl)] = fl
        mask[i, :len(fl)] = 1.0
    return EndPatches(nodes, faces, mask, spread, float(radius),
                      None if half_length is None else float(half_length), along)


def _patch_axes(X, nodes4, xi, points, toward, spread):
    """Unit long axes (n, 3) of elliptic patches: the surface tangent normal to the bar,
    n x (p - X_b) normalised (:func:`end_patches`); zeros for the ends not spread."""
    if toward is None:
        raise ValueError("an elongated bite patch needs the point each bar pulls toward "
                         "(toward=, its other end) to orient the patch along the buckle's edge")
    toward = np.asarray(toward, float).reshape(-1, 3)
    if toward.shape != points.shape:
        raise ValueError(f"toward has shape {toward.shape}; expected {points.shape} (one "
                         "point per bar end)")
    T = np.einsum("nak,nai->nki", dbilinear(xi), X[nodes4])
    normal = np.cross(T[:, 0], T[:, 1])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    axis = np.cross(normal, toward - points)
    size = np.linalg.norm(axis, axis=1)
    bad = np.flatnonzero(spread & (size < 1e-6 * np.linalg.norm(toward - points, axis=1)
                                   + 1e-12))
    if len(bad):
        raise ValueError(f"bar end {bad[0]}: the bar is normal to the surface (or has zero "
                         "length), so an elongated patch has no direction across it; use a "
                         "disc (half_length = radius)")
    return np.where(spread[:, None], axis / np.where(size > 0, size, 1.0)[:, None], 0.0)


def patch_weights(X, xi, pdata):
    """Weights (n, m) of the nodes of each end (JAX-traceable; :class:`EndPatches`).

    X: (n, m, 3) reference coordinates of the ends' nodes, mm; xi: (n, 2);
    pdata: :meth:`EndPatches.data`. A spread end's weights sum to 1 and are smooth in xi;
    a point end's are its face's bilinear shape functions.
    """
    n, m = X.shape[:2]
    N4 = bilinear(xi)
    point = jnp.einsum("na,nai->ni", N4, X[:, :4])
    rows = jnp.broadcast_to(jnp.arange(n)[:, None, None], pdata["faces"].shape)
    Xf = X[rows, pdata["faces"]]  # (n, f, 4, 3)
    Nq, dN = bilinear(_GAUSS_XI), dbilinear(_GAUSS_XI)  # (g, 4), (g, 4, 2)
    Xq = jnp.einsum("ga,nfai->nfgi", Nq, Xf)
    T = jnp.einsum("gak,nfai->nfgki", dN, Xf)
    dA = jnp.linalg.norm(jnp.cross(T[..., 0, :], T[..., 1, :]), axis=-1) * _GAUSS_WT
    d = Xq - point[:, None, None]
    dt2 = jnp.einsum("nfgi,ni->nfg", d, pdata["t"]) ** 2
    s2 = ((jnp.sum(d**2, -1) - dt2) / pdata["R"][:, None, None] ** 2
          + dt2 / pdata["A"][:, None, None] ** 2)
    phi = jnp.where(s2 < 1.0, (1.0 - s2) ** 2, 0.0) * dA * pdata["mask"][..., None]
    nodal = jnp.einsum("nfg,ga->nfa", phi, Nq)  # (n, f, 4)
    w = jnp.zeros((n, m)).at[rows, pdata["faces"]].add(nodal)
    total = jnp.sum(w, axis=1, keepdims=True)
    w = w / jnp.where(total > 0, total, 1.0)
    w_point = jnp.concatenate([N4, jnp.zeros((n, m - 4))], axis=1)
    return jnp.where(pdata["spread"][:, None] > 0, w, w_point)


def reference_end_positions(node_xyz, nodes4, xi, patch: EndPatches | None = None):
    """Reference positions (n, 3), mm, of bar ends (nodes4 (n, 4), xi (n, 2)): the points
    in their faces, or the centroids of their patches."""
    nodes = np.asarray(nodes4, np.int64).reshape(-1, 4) if patch is None else patch.nodes
    X = np.asarray(node_xyz, float)[nodes]
    return np.asarray(_end_positions(X, 0 * X, np.asarray(xi, float).reshape(-1, 2),
                                     None if patch is None else patch.data()))


def end_positions(X, u, xi, pdata=None):
    """Current positions (n, 3) of bar ends: point ends (X, u (n, 4, 3)) without
    ``pdata``, else ends with patches (X, u (n, m, 3); :func:`patch_weights`)."""
    if pdata is None:
        return embedded_positions(X, u, xi)
    return jnp.einsum("nm,nmi->ni", patch_weights(X, xi, pdata), X + u)


_end_positions = jax.jit(end_positions)
""":func:`end_positions` compiled, for host-side reference positions."""


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
      patch_a, patch_b: :class:`EndPatches` of the ends a and b (sutures' bites of physical
        size; their ``nodes`` replace nodes_a / nodes_b), or None: point ends.
    """

    name: str
    nodes_a: np.ndarray
    nodes_b: np.ndarray
    xi_a: np.ndarray
    xi_b: np.ndarray
    node_xyz: np.ndarray
    EA: float | np.ndarray = 1.0
    tension_only: bool = False
    patch_a: EndPatches | None = None
    patch_b: EndPatches | None = None

    def __post_init__(self):
        na = np.asarray(self.nodes_a, np.int64).reshape(-1, 4)
        nb = np.asarray(self.nodes_b, np.int64).reshape(-1, 4)
        for patch, ends in ((self.patch_a, na), (self.patch_b, nb)):
            if patch is not None and not np.array_equal(patch.nodes[:, :4], ends):
                raise ValueError(f"bars '{self.name}': an end patch does not start with the "
                                 "faces of its ends (build it with end_patches from them)")
        na = na if self.patch_a is None else self.patch_a.nodes
        nb = nb if self.patch_b is None else self.patch_b.nodes
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
        object.__setattr__(self, "_ma", na.shape[1])
        data = {"X": X[nodes8]}
        for key, patch in (("pa", self.patch_a), ("pb", self.patch_b)):
            if patch is not None:
                data[key] = patch.data()
        xa, xb = self.endpoints(np.zeros((n, 3 * nodes8.shape[1])), {"xi": xi}, data)
        L0 = np.linalg.norm(np.asarray(xb) - np.asarray(xa), axis=1)
        if np.any(L0 <= 1e-12):
            i = int(np.argmin(L0))
            raise ValueError(f"bars '{self.name}': bar {i} has zero initial length; its ends "
                             "coincide")
        object.__setattr__(self, "dofs", (3 * nodes8[:, :, None] + np.arange(3)).reshape(n, -1))
        object.__setattr__(self, "params", {"EA": EA, "shortening": np.zeros(n), "xi": xi})
        object.__setattr__(self, "data", {**data, "L0": L0})

    def _patch_key(self):
        return (self._ma, self.patch_a is not None, self.patch_b is not None)

    def static_key(self):
        return (self.tension_only,) + self._patch_key()

    def endpoints(self, q_loc, params, data):
        """Current end positions xa, xb (n, 3), mm."""
        X = data["X"]
        u = q_loc.reshape(X.shape)
        ma = self._ma
        xa = end_positions(X[:, :ma], u[:, :ma], params["xi"][:, 0], data.get("pa"))
        xb = end_positions(X[:, ma:], u[:, ma:], params["xi"][:, 1], data.get("pb"))
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

    def axial_forces(self, q_loc, params, data):
        """Axial force per bar (n,), N: dE/dl (JAX-traceable)."""
        L0 = data["L0"]
        s = self.lengths(q_loc, params, data) - L0 * (1.0 - params["shortening"])
        if self.tension_only:
            s = jnp.maximum(s, 0.0)
        return params["EA"] / L0 * s

    def forces(self, q, params):
        """Axial force per bar (n,), N (positive in tension; numpy)."""
        return host_forces(self, q, params)

    def report(self, q, params):
        f = self.forces(q, params)
        return {"max_force_N": float(f.max()) if len(f) else 0.0}


def host_forces(term, q, params) -> np.ndarray:
    """A bar term's ``axial_forces`` (n,), N, at state q (n_dof,) on the host (compiled)."""
    return np.asarray(host_kernel(term, "axial_forces")(np.asarray(q)[term.dofs], params,
                                                        term.data))


def bar_lines(term, q, params):
    """(points (2n, 3) mm, "line", cells (n, 2), {"force_N": (n,), "length_mm": (n,)}) of a
    bar term with ``endpoints`` and ``forces``."""
    xa, xb = (np.asarray(a) for a in host_kernel(term, "endpoints")(
        np.asarray(q)[term.dofs], params, term.data))
    n = len(xa)
    points = np.stack([xa, xb], axis=1).reshape(2 * n, 3)
    return (points, "line", np.arange(2 * n).reshape(n, 2),
            {"force_N": np.asarray(term.forces(q, params), np.float64),
             "length_mm": np.linalg.norm(xb - xa, axis=1)})


def rotate_z(x, angle):
    """Points x (n, 3) turned by ``angle`` (rad; scalar or (n,)) about the z axis."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1], x[:, 2]], axis=1)


def rotate_z_np(x, angle: float) -> np.ndarray:
    """:func:`rotate_z` on the host: points x (n, 3) numpy, one angle (rad)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1], x[:, 2]], axis=1)


@dataclasses.dataclass(frozen=True, eq=False)
class AnchoredBars(Term):
    """Bars from embedded points to anchors that move with rigid bodies (sutures over a
    rigid buckle).

    End a: a point in a face (nodes_a (n, 4), params xi (n, 2)); end b: an anchor at
    anchor_xyz (n, 3) moved by d[body] * dir + s[body] * dir2 + dr[body] * dir3 (the
    buckle's motion, params "d", "s", "dr" (n_bodies,); dir, dir2, dir3 (n, 3) per anchor)
    and then turned by rot[body] (rad) about the z axis. Energy EA / (2 L0) (l - (L0 - tightening))^2 with the
    tied length L0 (n,) and the tightening (n,) (mm) params: the suture is tied snug at
    the state where it is made, then shortened. Param "tied" (n,): 1 once tied, else 0
    (default); the energy does not read it, the reported suture force is the force times
    it.

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
      patch: :class:`EndPatches` of the ends a (bites of physical size; its ``nodes``
        replace nodes_a), or None: point bites. L0 is then measured from the patches'
        centroids (:func:`reference_end_positions`).
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
    patch: EndPatches | None = None

    def __post_init__(self):
        na = np.asarray(self.nodes_a, np.int64).reshape(-1, 4)
        if self.patch is not None:
            if not np.array_equal(self.patch.nodes[:, :4], na):
                raise ValueError(f"bars '{self.name}': the end patch does not start with the "
                                 "faces of the ends (build it with end_patches from them)")
            na = self.patch.nodes
        n = len(na)
        L0 = np.broadcast_to(np.asarray(self.L0, float), (n,)).copy()
        if np.any(L0 <= 0):
            raise ValueError(f"bars '{self.name}': bar {int(np.argmin(L0))} has tied length "
                             f"{L0.min():.3g} mm; must be > 0")
        EA = np.broadcast_to(np.asarray(self.EA, float), (n,)).copy()
        if np.any(EA <= 0):
            raise ValueError(f"bars '{self.name}': axial stiffness EA must be > 0 N")
        nb = self.n_bodies
        dofs = (3 * na[:, :, None] + np.arange(3)).reshape(n, -1)
        if self.extra_dof >= 0:
            if nb != 1:
                raise ValueError(f"bars '{self.name}': a free body motion needs n_bodies = 1")
            dofs = np.concatenate([dofs, np.full((n, 1), self.extra_dof)], axis=1)
        object.__setattr__(self, "dofs", dofs)
        object.__setattr__(self, "params", {"EA": EA, "tightening": np.zeros(n), "L0": L0,
                                            "tied": np.zeros(n),
                                            "xi": np.asarray(self.xi_a, float).reshape(n, 2),
                                            "d": np.zeros(nb), "s": np.zeros(nb),
                                            "dr": np.zeros(nb), "rot": np.zeros(nb)})
        dir3 = np.zeros((n, 3)) if self.dirs3 is None else np.asarray(self.dirs3, float)
        object.__setattr__(self, "data", {"X": self.node_xyz[na], "anchor": np.asarray(
            self.anchor_xyz, float), "body": np.asarray(self.body, np.int64),
            "dir": np.asarray(self.dirs, float), "dir2": np.asarray(self.dirs2, float),
            "dir3": dir3, **({} if self.patch is None else {"pa": self.patch.data()})})

    def static_key(self):
        return (self.tension_only, self.smoothing, self.extra_dof >= 0, self.patch is not None)

    def endpoints(self, q_loc, params, data):
        """Current positions (n, 3), mm, of the bites xa and the moved anchors xb."""
        m = data["X"].shape[1]
        xa = end_positions(data["X"], q_loc[:, :3 * m].reshape(-1, m, 3), params["xi"],
                           data.get("pa"))
        d = params["d"][data["body"]]
        if self.extra_dof >= 0:
            d = d + q_loc[:, 3 * m]
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
        """Axial force per bar (n,), N (positive in tension; numpy)."""
        return host_forces(self, q, params)

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
    (default: the reference lengths), "tied" (n,) 1 once the bar is tied, else 0 (default):
    the energy does not read it, the reported suture force is the force times it}.
    """

    smoothing: float = 2e-4

    def __post_init__(self):
        super().__post_init__()
        p = self.params
        object.__setattr__(self, "params", {"EA": p["EA"], "xi": p["xi"], "L0": self.data["L0"].copy(),
                                            "tightening": np.zeros(len(p["EA"])),
                                            "tied": np.zeros(len(p["EA"]))})

    def static_key(self):
        return (self.smoothing,) + self._patch_key()

    def _raw(self, q_loc, params, data):
        return self.lengths(q_loc, params, data) - (params["L0"] - params["tightening"])

    def local_energy(self, q_loc, params, data):
        e = self.smoothing
        p = e * jnp.logaddexp(self._raw(q_loc, params, data) / e, 0.0)
        return 0.5 * params["EA"] / params["L0"] * p**2

    def axial_forces(self, q_loc, params, data):
        """Axial force per bar (n,), N: dE/dl (JAX-traceable)."""
        s = self._raw(q_loc, params, data)
        e = self.smoothing
        p = e * jnp.logaddexp(s / e, 0.0)
        return params["EA"] / params["L0"] * p * jax.nn.sigmoid(s / e)
