"""Penalty contact: deformable-deformable (seed 4.3); deformable-rigid (seed 4.4) is
eyefem.fem.rigid_contact, and the helpers both use are here.

Both are *dynamic* terms: the pairing (which node meets which target point) is found
outside JAX by :meth:`update` before every Newton iteration; the energy of the
current pairing is a JAX function, so residual and tangent come from autodiff.

Deformable-rigid (frictionless): a contact node x (slave set) and its closest point c
on a rigid triangle surface moved by d * direction, with the triangle's outward
normal n:

    g = (x - c - d dir) . n,      e = 1/2 alpha <-g>^2                       [N mm]

(the seed's Phi_c = 1/2 alpha (u_n - u_cd)^2). The closest point and normal are
frozen during one iteration; the re-pairing lets nodes slide across triangles.

Deformable-deformable, node to quadrilateral segment: a hitting node x_h against a
master face with current nodes x_1..x_4 at frozen parametric point xi:
x_t = sum N_a(xi) x_a, n_t the unit normal of the face at xi,

    sliding:   g = (x_h - x_t) . n_t,      e = 1/2 alpha <-g>^2
    sticking:  d = |x_h - x_t(xi_0)|,      e = 1/2 alpha d^2  (xi_0 recorded at first contact)

with 15 dofs per pair (the seed's D vector of length 15). Two-pass (symmetric)
contact adds the same term with the roles of the surfaces swapped.

Penalty: by default alpha = factor * E * h per node (E: Young's modulus of the slave
material, MPa; h: mean edge length of the slave faces, mm; factor 100): the
penetration is then about 1% of the elastic indentation of a patch of one element.

Length: the node-to-segment term with its pairing, Nagata patches and their
projections, which only it uses; about 400 lines.
"""

from __future__ import annotations

import copy
import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from eyefem.fem.mesh import Mesh, boundary_faces
from eyefem.fem.terms import Term

log = logging.getLogger(__name__)

PENALTY_FACTOR = 100.0


def _bucket(n: int) -> int:
    """Padded pair count: the next power of two >= n (at least 16), to limit recompiles."""
    return max(16, 1 << int(np.ceil(np.log2(max(n, 1)))))


def node_areas(mesh: Mesh, nodes: np.ndarray):
    """Tributary boundary area (n,) mm^2 and mean boundary edge length (mm) of nodes."""
    bf = boundary_faces(mesh.hexes)
    x = mesh.nodes[bf]
    a = 0.5 * np.linalg.norm(np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1]), axis=1)
    area = np.bincount(bf.ravel(), np.repeat(a / 4, 4), minlength=mesh.n_nodes)[nodes]
    sel = np.any(np.isin(bf, nodes), axis=1)
    e = np.linalg.norm(x[sel] - np.roll(x[sel], 1, axis=1), axis=2)
    return area, float(e.mean()) if e.size else 1.0


# --- deformable-deformable ------------------------------------------------------------------

_C = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)


def _shape(xi, xp=jnp):
    """Bilinear shape functions N (..., 4) and their derivatives dN (..., 4, 2) at xi (...,
    2); ``xp``: jax.numpy (traced) or numpy (the host's closest-point search, where eager
    JAX dispatched each operation: a quarter of a contact run's time)."""
    N = 0.25 * (1 + xi[..., None, 0] * _C[:, 0]) * (1 + xi[..., None, 1] * _C[:, 1])
    dN = xp.stack([0.25 * _C[:, 0] * (1 + xi[..., None, 1] * _C[:, 1]),
                   0.25 * _C[:, 1] * (1 + xi[..., None, 0] * _C[:, 0])], -1)
    return N, dN


def project_to_quads(x, quads_x, cand, iters=25):
    """Closest parametric points of points x (n, 3) on candidate bilinear faces.

    Args: quads_x (m, 4, 3) face node positions; cand (n, k) candidate face ids.
    Returns: face id (n,), xi (n, 2), distance (n,).
    """
    n, k = cand.shape
    best = (np.zeros(n, np.int64), np.zeros((n, 2)), np.full(n, np.inf))
    for j in range(k):
        f = cand[:, j]
        xf = quads_x[f]
        xi = np.zeros((n, 2))
        for _ in range(iters):
            N, dN = _shape(xi, np)
            p = np.einsum("na,nai->ni", N, xf)
            t = np.einsum("nak,nai->nki", dN, xf)  # (n, 2, 3)
            r = x - p
            A = np.einsum("nki,nli->nkl", t, t)
            b = np.einsum("nki,ni->nk", t, r)
            step = np.linalg.solve(A + 1e-14 * np.eye(2), b[..., None])[..., 0]
            xi = np.clip(xi + step, -1.0, 1.0)
            if np.abs(step).max() < 1e-12:
                break
        N, _ = _shape(xi, np)
        dist = np.linalg.norm(x - np.einsum("na,nai->ni", N, xf), axis=1)
        better = dist < best[2]
        best[0][better], best[1][better], best[2][better] = f[better], xi[better], dist[better]
    return best


def followed_xi(q_loc, data):
    """Closest points xi (P, 2) of the hitting nodes on their bilinear faces as a JAX
    function of the pairs' dofs q_loc (P, 15) (data: SurfaceContact's, with the pairing's
    xi (P, 2)): one Newton step on F(xi) = t(xi) . (x_h - x_t(xi)) = 0 from the paired xi,
    dF/dxi = dt/dxi . r - t t^T. Where the paired xi is the closest point (F = 0) the
    value is the paired xi and its first derivative the implicit one, -dF/dxi^-1 dF/dq,
    so an energy of the gap, stationary in xi there, gets its exact Hessian. Pairs clamped
    to a face edge (a |xi| = 1, where the pairing's projection, clipped, is not the
    stationary point) and padding keep their xi."""
    xi0 = data["xi"]
    x = data["X"] + q_loc.reshape(-1, 5, 3)
    N, dN = _shape(xi0)
    xf = x[:, 1:]
    r = x[:, 0] - jnp.einsum("pa,pai->pi", N, xf)
    t = jnp.einsum("pak,pai->pki", dN, xf)
    F = jnp.einsum("pki,pi->pk", t, r)
    twist = jnp.einsum("a,pai->pi", 0.25 * _C[:, 0] * _C[:, 1], xf)  # d t_0/d xi_1
    off = jnp.einsum("pi,pi->p", r, twist)
    J = (-jnp.einsum("pki,pli->pkl", t, t)
         + off[:, None, None] * jnp.array([[0.0, 1.0], [1.0, 0.0]]))
    ok = (data["w"] > 0) & jnp.all(jnp.abs(xi0) < 1 - 1e-9, axis=1)
    J = jnp.where(ok[:, None, None], J, -jnp.eye(2))
    step = -jnp.linalg.solve(J, F[..., None])[..., 0]
    return xi0 + jnp.where(ok[:, None], step, 0.0)


_NAGATA_EDGES = ((0, 1), (1, 2), (3, 2), (0, 3))
"""A face's edges (from node, to node) along s = (xi_0 + 1) / 2 at t = 0, along t at s = 1,
along s at t = 1, along t at s = 0 (t = (xi_1 + 1) / 2)."""


def nagata_coefficients(xf, n4, xnp=np):
    """Curvature vectors c (n, 4, 3) of a face's edges (_NAGATA_EDGES): the edge from x_i to
    x_j is the quadratic x(s) = (1 - s) x_i + s x_j - s (1 - s) c, with
    c = a (n_i + n_j) / (1 + n_i . n_j), a = d . (n_i - n_j) / 2 (d = x_j - x_i; n_i,
    n_j the unit nodal normals): the symmetric part of Nagata's (2005) least-norm c, whose
    end tangents d -+ c are normal to n_i and n_j when the edge is a circular arc
    (d . n_i = -d . n_j). Nagata's full c adds e (n_i - n_j) / (1 - n_i . n_j),
    e = d . (n_i + n_j) / 2, which grows as 1 / angle^2 between nearly parallel normals: a
    node moved by 0.1 mm off its held normals' surface (a Newton step) bent a 0.5 mm edge
    of the default eye's sclera by tens of mm. Symmetric in i, j (neighbouring patches
    share their edge curves); straight where n_i = n_j; linear in the positions xf
    (n, 4, 3) for given normals n4 (n, 4, 3)."""
    cs = []
    for i, j in _NAGATA_EDGES:
        d, ni, nj = xf[:, j] - xf[:, i], n4[:, i], n4[:, j]
        a = 0.5 * xnp.sum(d * (ni - nj), axis=-1)
        cs.append((a / (1.0 + xnp.sum(ni * nj, axis=-1)))[:, None] * (ni + nj))
    return xnp.stack(cs, axis=1)


def nagata_patch(xi, xf, n4, xnp=np):
    """Point (n, 3) and tangents d/dxi (n, 2, 3) of the quadratic Nagata patch through a
    face's nodes xf (n, 4, 3) with nodal normals n4 (n, 4, 3) at xi (n, 2) in [-1, 1]^2:
    the bilinear face less the edges' curvature terms blended over it,
    x = sum_a N_a x_a - c_1 s(1-s)(1-t) - c_2 s t(1-t) - c_3 s(1-s) t - c_4 (1-s) t(1-t).
    Neighbouring patches share their edge curves (continuous surface), and the tangent
    planes at the nodes are normal to n_a (the normal's jump across an edge is of second
    order in the facet angle, not of first as between flat faces)."""
    N, dN = _shape(xi)
    c = nagata_coefficients(xf, n4, xnp)
    s, t = 0.5 * (xi[:, 0] + 1.0), 0.5 * (xi[:, 1] + 1.0)
    b = xnp.stack([s * (1 - s) * (1 - t), s * t * (1 - t), s * (1 - s) * t, (1 - s) * t * (1 - t)], 1)
    bs = xnp.stack([(1 - 2 * s) * (1 - t), t * (1 - t), (1 - 2 * s) * t, -t * (1 - t)], 1)
    bt = xnp.stack([-s * (1 - s), s * (1 - 2 * t), s * (1 - s), (1 - s) * (1 - 2 * t)], 1)
    x = xnp.einsum("na,nai->ni", N, xf) - xnp.einsum("ne,nei->ni", b, c)
    tan = xnp.einsum("nak,nai->nki", dN, xf) - 0.5 * xnp.stack(
        [xnp.einsum("ne,nei->ni", bs, c), xnp.einsum("ne,nei->ni", bt, c)], axis=1)
    return x, tan


def project_to_patches(x, xf, n4, xi, iters=12):
    """Closest points xi (n, 2) (clipped to the face) of points x (n, 3) on the Nagata
    patches of faces xf (n, 4, 3) with normals n4, from xi (n, 2) (Gauss-Newton)."""
    for _ in range(iters):
        p, tan = (np.asarray(a) for a in nagata_patch(xi, xf, n4))
        A = np.einsum("nki,nli->nkl", tan, tan)
        b = np.einsum("nki,ni->nk", tan, x - p)
        step = np.linalg.solve(A + 1e-14 * np.eye(2), b[..., None])[..., 0]
        xi = np.clip(xi + step, -1.0, 1.0)
    return xi


def penalty_gauss_newton(a, g, G, eps):
    """Gradients (n, k) and Gauss-Newton Hessians (n, k, k) of penalty energies
    1/2 a p(g)^2, p = eps softplus(-g / eps), from the gaps g (n,) mm, their gradients
    G (n, k) and a (n,) N/mm: a p p' G and a (p'^2 + p p'') G G^T (the term a p p'
    grad^2 g of the surface's curvature dropped; positive semidefinite)."""
    s = jax.nn.sigmoid(-g / eps)
    p = eps * jnp.logaddexp(-g / eps, 0.0)
    h = a * (s * s + p * s * (1.0 - s) / eps)
    return (-a * p * s)[:, None] * G, h[:, None, None] * G[:, :, None] * G[:, None, :]


@dataclasses.dataclass(frozen=True, eq=False)
class SurfaceContact(Term):
    """Node-to-segment penalty contact of a slave node set against a master face set.

    Args:
      name: term name; params {"scale": penalty multiplier (1)}.
      mesh: the mesh (both bodies).
      slave: node set of hitting nodes.
      master: face set of target quadrilaterals (normals out of the master body).
      mode: "sliding" (frictionless) or "sticking".
      modulus: Young's modulus of the softer body, MPa (default penalty).
      penalty: alpha per node, N/mm (overrides the default).
      search_gap: pairing distance, mm (default 1.5 h).
      max_initial_penetration: error beyond this initial depth, mm (default h / 2).
      smoothing: sliding mode only: eps (mm) of a smoothed penetration eps softplus(-g / eps)
        in place of <-g> (as eyefem.fem.buckle_contact): C-infinity, with stiffness at a
        touching gap, and a stand-off force alpha eps ln 2 / 2 at g = 0; None: plain.
      normals: sliding mode: "facet" (the flat bilinear faces) or "nodal": the master
        surface is the quadratic Nagata patches (:func:`nagata_patch`) through the faces'
        nodes with their area-averaged nodal normals (computed at each re-pairing, held
        between them): continuous, with a tangent plane that turns smoothly over an edge
        where the flat faces' jumps by the angle between them, so a slave node sliding
        across a facet edge feels no jump of the force direction. The target point, gap
        and normal are then taken on the patch as on a face.
    """

    name: str
    mesh: Mesh
    slave: str
    master: str
    mode: str = "sliding"
    modulus: float = 1.0
    penalty: float | None = None
    search_gap: float | None = None
    max_initial_penetration: float | None = None
    smoothing: float | None = None
    normals: str = "facet"
    dynamic = True
    contact = True

    def __post_init__(self):
        if self.normals not in ("facet", "nodal"):
            raise ValueError(f"contact '{self.name}': normals '{self.normals}'; use 'facet' or "
                             "'nodal'")
        if self.normals == "nodal" and self.mode != "sliding":
            raise ValueError(f"contact '{self.name}': normals 'nodal' needs mode 'sliding' "
                             f"(mode '{self.mode}')")
        if self.smoothing is not None and not (self.smoothing > 0 and self.mode == "sliding"):
            raise ValueError(f"contact '{self.name}': smoothing = {self.smoothing} mm; needs "
                             "mode 'sliding' and a value > 0 (or None)")
        if self.mode not in ("sliding", "sticking"):
            raise ValueError(f"contact '{self.name}': mode '{self.mode}'; use 'sliding' or 'sticking'")
        nodes = self.mesh.node_set(self.slave)
        faces = self.mesh.face_set(self.master)
        overlap = np.intersect1d(nodes, np.unique(faces))
        nodes = np.setdiff1d(nodes, overlap)
        area, h = node_areas(self.mesh, nodes)
        alpha = self.penalty if self.penalty is not None else PENALTY_FACTOR * self.modulus * h
        if not alpha > 0:
            raise ValueError(f"contact '{self.name}': penalty {alpha} N/mm; must be > 0")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "area", np.maximum(area, 1e-12))
        object.__setattr__(self, "alpha", float(alpha))
        object.__setattr__(self, "h", h)
        object.__setattr__(self, "params", {"scale": 1.0})
        object.__setattr__(self, "stick", {})  # slave node -> (face, xi) recorded at first contact
        self._pair(np.zeros(3 * self.mesh.n_nodes), initial=True)

    def static_key(self):
        return (self.mode, self.smoothing is not None, self.normals,
                getattr(self, "following", False))

    def following_pairing(self) -> "SurfaceContact":
        """This term with its target points following the state: each pair's xi the
        closest point of its face to the hitting node, a function of the pair's dofs (one
        Newton correction from the paired xi, exact to first order where xi is the
        closest point: :func:`followed_xi`), where the pairing's energy holds xi fixed.
        At a state paired at itself (``update(q)``) the two energies and residuals agree;
        the tangent of this one has the term of the target points sliding over the faces
        (the response of a frictionless contact whose pairing follows the state, as
        re-pairing makes it), which the held pairing's lacks: the adjoint's tangent
        (eyefem.solve.adjoint). Flat faces in sliding mode only (sticking points and the
        Nagata patches' held normals: this term itself)."""
        if self.mode != "sliding" or self.normals != "facet":
            return self
        new = copy.copy(self)
        object.__setattr__(new, "following", True)
        return new

    def _nodal_normals(self, qx):
        """Unit normals (m, 4, 3) of the master faces' nodes: the sums of the adjacent
        faces' area vectors, normalised; qx (m, 4, 3) the faces' node positions."""
        area = 0.5 * np.cross(qx[:, 2] - qx[:, 0], qx[:, 3] - qx[:, 1])  # (m, 3)
        nodal = np.zeros((self.mesh.n_nodes, 3))
        np.add.at(nodal, self.faces.ravel(), np.repeat(area, 4, axis=0))
        nodal /= np.maximum(np.linalg.norm(nodal, axis=1, keepdims=True), 1e-300)
        return nodal[self.faces]

    def _pair(self, q, initial=False):
        u = q[: 3 * self.mesh.n_nodes].reshape(-1, 3)
        xall = self.mesh.nodes + u
        x = xall[self.nodes]
        qx = xall[self.faces]
        tree = cKDTree(qx.mean(axis=1))
        k = min(4, len(self.faces))
        _, cand = tree.query(x, k=k)
        f, xi, _ = project_to_quads(x, qx, cand.reshape(len(x), k))
        N, dN = (np.asarray(a) for a in _shape(xi))
        p = np.einsum("na,nai->ni", N, qx[f])
        t = np.einsum("nak,nai->nki", dN, qx[f])
        if self.normals == "nodal":  # from the face's closest point on to its patch's
            n4_all = self._nodal_normals(qx)
            n4 = n4_all[f]
            xi = project_to_patches(x, qx[f], n4, xi)
            p, t = (np.asarray(a) for a in nagata_patch(xi, qx[f], n4))
        nrm = np.cross(t[:, 0], t[:, 1])
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        g = np.einsum("ni,ni->n", x - p, nrm)
        sg = self.search_gap if self.search_gap is not None else 1.5 * self.h
        inside = np.all(np.abs(xi) < 1 - 1e-9, axis=1) | (np.abs(g) < sg)
        sel = np.nonzero((g < sg) & (g > -2 * sg) & inside)[0]
        if initial:
            tol = (self.max_initial_penetration if self.max_initial_penetration is not None
                   else 0.5 * self.h)
            bad = sel[g[sel] < -tol]
            if bad.size:
                j = bad[np.argmin(g[bad])]
                raise ValueError(f"contact '{self.name}': node {self.nodes[j]} starts {-g[j]:.3g} mm "
                                 f"inside face set '{self.master}' (tolerance {tol:.3g} mm); "
                                 "separate the bodies")
        if self.mode == "sticking":
            stick = dict(self.stick)
            for j in sel[g[sel] < 0]:
                stick.setdefault(int(self.nodes[j]), (int(f[j]), xi[j].copy()))
            object.__setattr__(self, "stick", stick)
            keys = np.array(sorted(stick), dtype=np.int64)
            fsel = np.array([stick[int(k_)][0] for k_ in keys], dtype=np.int64)
            xsel = np.array([stick[int(k_)][1] for k_ in keys]).reshape(-1, 2)
            slave_nodes = keys
            # slaves not yet stuck but approaching: sliding-type gap contact is not applied
        else:
            slave_nodes, fsel, xsel = self.nodes[sel], f[sel], xi[sel]
        P = _bucket(len(slave_nodes))
        pad = P - len(slave_nodes)
        snode = np.concatenate([slave_nodes, np.full(pad, self.nodes[0])])
        fc = np.concatenate([fsel, np.zeros(pad, np.int64)])
        xi_p = np.concatenate([xsel, np.zeros((pad, 2))])
        nodes5 = np.concatenate([snode[:, None], self.faces[fc]], axis=1)
        w = np.concatenate([np.ones(len(slave_nodes)), np.zeros(pad)])
        amap = dict(zip(self.nodes.tolist(), self.area.tolist()))
        area = np.array([amap.get(int(s), 1.0) for s in snode])
        object.__setattr__(self, "dofs", (3 * nodes5[:, :, None] + np.arange(3)).reshape(P, 15))
        data = {"X": self.mesh.nodes[nodes5], "xi": xi_p, "w": w,
                "alpha": np.full(P, self.alpha), "area": area,
                "eps": np.full(P, self.smoothing or 1.0)}
        if self.normals == "nodal":
            data["n4"] = np.concatenate([n4[sel], np.repeat(n4_all[:1], pad, axis=0)])
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "n_pairs", len(slave_nodes))

    def update(self, q, params):
        new = copy.copy(self)
        object.__setattr__(new, "stick", dict(self.stick))
        new._pair(np.asarray(q))
        return new

    @staticmethod
    def kinematics(q_loc, data):
        """Hitting node x_h (P, 3), target point x_t (P, 3), unit normal n_t (P, 3) (on the
        Nagata patch of held nodal normals where data has them, "n4" (P, 4, 3))."""
        x = data["X"] + q_loc.reshape(-1, 5, 3)
        if "n4" in data:
            xt, t = nagata_patch(data["xi"], x[:, 1:], data["n4"], jnp)
        else:
            N, dN = _shape(data["xi"])
            xt = jnp.einsum("pa,pai->pi", N, x[:, 1:])
            t = jnp.einsum("pak,pai->pki", dN, x[:, 1:])
        n = jnp.cross(t[:, 0], t[:, 1])
        n = n / jnp.linalg.norm(n, axis=1, keepdims=True)
        return x[:, 0], xt, n

    def local_energy(self, q_loc, params, data):
        if getattr(self, "following", False):
            data = {**data, "xi": followed_xi(q_loc, data)}
        xh, xt, n = self.kinematics(q_loc, data)
        a = params["scale"] * data["w"] * data["alpha"]
        if self.mode == "sticking":
            d = xh - xt
            return 0.5 * a * jnp.sum(d * d, axis=1)
        g = jnp.einsum("pi,pi->p", xh - xt, n)
        if self.smoothing is not None:
            p = data["eps"] * jnp.logaddexp(-g / data["eps"], 0.0)
            return 0.5 * a * p * p
        g = jnp.minimum(g, 0.0)
        return 0.5 * a * g * g

    def local_gaps(self, q_loc, data):
        """Signed normal gaps (P,) mm of the pairs at local dofs q_loc (P, 15)."""
        xh, xt, n = self.kinematics(q_loc, data)
        return jnp.einsum("pi,pi->p", xh - xt, n)

    def grad_hess_gauss_newton(self, q, params, data, dofs):
        """Local gradients (P, 15) and Hessians (P, 15, 15) without the curvature term
        a p p' grad^2 g of the gap (sliding; a sticking pair's are exact): a (p'^2 + p p'')
        grad g grad g^T, positive semidefinite (``NewtonOptions.contact_curvature``). A
        slave node pressed on the faceted master surface near a facet edge or on a curved
        face has a negative tangential stiffness in that term."""
        q_loc = q[dofs]
        if self.mode == "sticking":
            return self.local_grad_hess(q_loc, params, data)
        g = self.local_gaps(q_loc, data)
        G = jax.grad(lambda x: jnp.sum(self.local_gaps(x, data)))(q_loc)  # pair i: row i
        a = params["scale"] * data["w"] * data["alpha"]
        if self.smoothing is not None:
            return penalty_gauss_newton(a, g, G, data["eps"])
        grad, h = (a * jnp.minimum(g, 0.0))[:, None] * G, a * (g < 0)
        return grad, h[:, None, None] * G[:, :, None] * G[:, None, :]

    def _gaps(self, q):
        xh, xt, n = (np.asarray(a) for a in self.kinematics(np.asarray(q)[self.dofs], self.data))
        w = self.data["w"] > 0
        return np.einsum("pi,pi->p", xh - xt, n)[w], self.dofs[w, 0] // 3, self.data["area"][w]

    def _forces(self, g):
        """Normal force magnitudes (n,), N, at gaps g (n,) (per unit penalty scale)."""
        if self.smoothing is None:
            return self.alpha * np.maximum(-g, 0.0)
        from scipy.special import expit

        e = self.smoothing
        return self.alpha * e * np.logaddexp(-g / e, 0.0) * expit(-g / e)

    def report(self, q, params):
        g, _, _ = self._gaps(q)
        pen = np.maximum(-g, 0.0)
        return {"active": int(np.sum(pen > 0)) if self.mode == "sliding" else self.n_pairs,
                "max_penetration_mm": float(pen.max(initial=0.0)),
                "force_N": float(params["scale"] * self._forces(g).sum())}

    def point_fields(self, q, params, n_nodes):
        """'<name>_gap_mm' (NaN at unpaired nodes), '<name>_pressure_MPa' (0 off contact)."""
        g, node, area = self._gaps(q)
        gap, pres = np.full(n_nodes, np.nan), np.zeros(n_nodes)
        gap[node] = g
        pres[node] = self._forces(g) / area
        return {f"{self.name}_gap_mm": gap, f"{self.name}_pressure_MPa": pres}
