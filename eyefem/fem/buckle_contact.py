"""Smooth analytic contact of the sclera with rigid buckles (no pairing, no facets).

The surgery cases use the buckle's exact surface instead of its triangulation: the gap
of an outer scleral node x is a smooth function of x and of the buckle's motion, so
Newton converges quadratically (no facet-edge or pairing chatter) and the outcomes are
differentiable with respect to the motion (tightening, position) by the adjoint.

Encircling ring (band or tire) about the globe centre, in spherical coordinates
(r = |x|, polar angle tau): across-coordinate a = R (tau - theta_b) - s (mm, s: shift of
the buckle toward the posterior), inner surface radius

    S(a) = R - k b(a) + lift(a) - d,      g = S(a) - r   (g < 0: penetration)

with b the ridge shape (1 on the ridge, quintic smoothstep flanks ``ridge_flank`` wide
inside its edges, 0 beyond: twice differentiable, so the response to a buckle shift is
smooth; the shoulders' curvature, about 5.8 k / flank^2, is a negative tangential
stiffness of a node pressed on them, so flanks much narrower than the scleral elements
make the tangent near-singular) and k its
current protrusion (param "ridge", ramped from 0 when the tire is seated on its flat
base), lift the upturned edges (0.3 mm over the last ``edge_width`` mm of each side,
0.5 by default, growing cubically beyond, so contact fades out smoothly past the edge;
its curvature rises from 0 to 1.8 / edge_width^2 per mm, so narrow edges are sharper
than the scleral elements follow) and d the radial tightening (the
ring's circumference shortens by 2 pi d sin theta_b).

Sponge: a cylinder (radius r_s, length L, axis t) whose axis passes through
C = (R + r_s - d) n0 + s m0: g = |x - C - ((x - C) . t) t| - r_s + e(|(x - C) . t|), with
the ends' term e(a) = 10 max(a - L/2, 0)^2 (``end_width`` = 0, the default: a fade-out
about 0.1 mm long beyond each end, once differentiable) or, with ``end_width`` = w > 0,
e(a) = 0.3 (max(a - (L/2 - w), 0) / w)^3: the ends round off, lifting 0.3 mm over their
last w mm as a ring's edges do, twice differentiable (its curvature rises from 0 to
1.8 / w^2 per mm), so the contact fades out over about a millimetre with w = 1 and a
node passing under an end does not jump in stiffness.

A radial sponge lies along the meridian and follows the globe's curvature (``curved``):
its centre line is the arc of radius rho0 = R + r_s - d about the globe centre in the
plane of n0 and m0, g = sqrt((rho - rho0)^2 + w^2) - r_s + e(|psi| rho0)
with (rho, psi) the polar coordinates of x in that plane (psi from n0, shifted by
s / rho0) and w its distance from the plane.

With ``extra_dof`` the buckle's radial position is also an unknown: d = param d + q[extra]
(a segmental sponge pulled in by its sutures finds its own depth).

Two more params move the fitted buckle without rebuilding the term, so that the design
gradients see them (eyefem.eye.design): "dr" adds to the fitted radius R (a snug fit on an
eye inflated differently), "rot" turns the buckle about the eye axis z (rad; a
segmental buckle's meridian): the gap of x is the gap of Rz(-rot) x.

Energy per node 1/2 alpha p^2 with the smoothed penetration p = eps softplus(-g / eps)
(eps = ``smoothing`` mm): C-infinity, so a node touching down or lifting off does not
make Newton's method cycle; for -g >> eps it is the plain penalty 1/2 alpha <-g>^2, at
g = 0 it leaves a stand-off force alpha eps ln 2 (about 1e-3 N per node by default).
The default penalty alpha = BUCKLE_PENALTY_FACTOR E h: stiff enough that penetrations
stay a few micrometres under the buckle loads, soft enough to keep the Newton
system well conditioned against the thin, soft scleral shell.

With ``quadrature`` = n > 0 the penalty is integrated over the faces of the candidate
surface instead of lumped at its nodes: the energy is the sum over faces and over their
n x n Gauss points of 1/2 k_A w J p(g)^2, with g the gap of the point of the bilinear
face (its position interpolated from the face's nodes), w J its area weight (mm^2) and
k_A = alpha / (mean tributary area of the nodes) the penalty per unit area (N/mm^3), so
that on a uniform mesh both integrations are equally stiff. A contact footprint a few
elements wide is then sampled by its faces' points rather than by the nodes that fall
in it: the contact pressure of a uniform penetration is uniform (the nodal version's
follows the nodes' areas), and a buckle's outcomes depend less on where it sits among
the nodes. Each contact point is one item of the term (its face's 12 dofs, and the free
radial dof).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.bars import rotate_z, rotate_z_np
from eyefem.fem.contact import node_areas, penalty_gauss_newton
from eyefem.fem.mesh import Mesh, quad_shape
from eyefem.fem.rigid import grid_triangles
from eyefem.fem.terms import Term, host_kernel

BUCKLE_PENALTY_FACTOR = 10.0
"""Default buckle penalty alpha = factor * E * h per node (N/mm)."""

EDGE_WIDTH = 0.5
"""Default width over which a ring's edges lift 0.3 mm, mm (the recorded results' tire:
curvature up to 7.2 per mm, a radius of 0.14 mm at the edge)."""

RIDGE_FLANK = 1.0
"""Default width of a ridge's flanks, mm (shoulder radius about 0.23 mm for a 0.75 mm ridge;
0.5 mm flanks left shoulders too sharp for the default eye mesh's scleral elements)."""


def smooth_penetration(g, eps):
    """eps softplus(-g / eps) (mm), overflow-safe: the smoothed <-g>."""
    return eps * jnp.logaddexp(-g / eps, 0.0)


def face_points(nodes: np.ndarray, faces: np.ndarray, n: int):
    """The n x n Gauss points of bilinear faces (f, 4) (node ids into nodes (n_nodes, 3),
    mm): each point's face (q, 4) node ids, shape function values N (q, 4) and area weight
    w J (q,) mm^2, q = f n^2 rows, face by face, in the configuration ``nodes``."""
    t, w = np.polynomial.legendre.leggauss(n)
    xi = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    w2 = np.outer(w, w).ravel()
    N, dN = quad_shape(xi)  # (q, 4), (q, 4, 2)
    T = np.einsum("qak,fai->fqki", dN, nodes[faces])
    J = np.linalg.norm(np.cross(T[:, :, 0], T[:, :, 1]), axis=-1)  # (f, q)
    return (np.repeat(faces, len(w2), axis=0), np.tile(N, (len(faces), 1)),
            (w2 * J).ravel())


def edge_lift(a, length, width):
    """The lift (mm) of a buckle's surface at a distance ``a`` (mm, >= 0) from its middle
    across a ring or along a sponge ``length`` mm long whose edges round off over their last
    ``width`` mm: 0.3 (max(a - (length / 2 - width), 0) / width)^3, twice differentiable,
    0.3 mm at the edge, its curvature rising from 0 to 1.8 / width^2 per mm there."""
    return 0.3 * (jnp.maximum(a - (length / 2 - width), 0.0) / width) ** 3


def sponge_end_lift(a, length, end_width):
    """The lift (mm) of a sponge's surface at a distance ``a`` (mm, >= 0) from its middle
    along its axis: 10 max(a - length / 2, 0)^2 for ``end_width`` = 0 (a static Python
    float: the earlier model), else :func:`edge_lift` (rounded ends)."""
    if end_width == 0:
        return 10.0 * jnp.maximum(a - length / 2, 0.0) ** 2
    return edge_lift(a, length, end_width)


def ring_profile(a, width, ridge, ridge_width, flank=RIDGE_FLANK, edge=EDGE_WIDTH):
    """Inner-surface offset of a ring above R (mm) at across-coordinates a (jax or numpy):
    -ridge on the ridge, 0 on the flat base, rising at the edges by 0.3 (|a| - (width / 2 -
    edge))^3 / edge^3 over their last ``edge`` mm; the ridge's flanks span ``flank`` mm
    inside its edges at +-ridge_width / 2."""
    aa = jnp.abs(a)
    t = jnp.clip((aa - (ridge_width / 2 - flank)) / flank, 0.0, 1.0)
    bump = jnp.where(ridge_width > 0, 1.0 - t**3 * (10.0 - 15.0 * t + 6.0 * t**2), 0.0)
    return -ridge * bump + edge_lift(aa, width, edge)


_ring_profile = jax.jit(ring_profile)
""":func:`ring_profile` compiled, for the host-side surface of the buckle."""


@dataclasses.dataclass(frozen=True, eq=False)
class BuckleContact(Term):
    """Frictionless penalty contact of scleral nodes with an analytic rigid buckle.

    Args:
      name: term name; params {"d": (1,) inward motion, mm; "s": (1,) posterior shift, mm;
        "ridge": (1,) current ridge protrusion, mm (ramp it to ``ridge``); "dr": (1,)
        change of the fitted radius R, mm; "rot": (1,) turn about the z axis, rad}.
      mesh: the mesh; node_set: candidate (outer scleral) nodes.
      shape: "ring" or "sponge".
      radius: R, the scleral radius the buckle was fitted to, mm.
      theta_b: polar angle of the buckle centre line, rad (ring) ; for a sponge its
        centre direction n0 (3,), meridian tangent m0 (3,) and axis (3,).
      width, ridge, ridge_width, ridge_flank, edge_width: ring profile, mm; sponge_radius,
        sponge_length: mm.
      modulus: Young's modulus of the sclera (default penalty), MPa; penalty: N/mm.
      smoothing: eps of the smoothed penetration, mm.
      extra_dof: global dof of the buckle's free radial motion (mm, inward), or -1.
      curved: sponge only: its axis is the arc along the meridian (a radial sponge).
      quadrature: 0 (default): one penalty per candidate node; n in 1..4: the penalty
        integrated over the candidate surface's faces (the face set named ``node_set``)
        with n x n Gauss points each (module docstring).
      end_width: sponge only: 0 (default), its ends fade out over about 0.1 mm beyond them
        (once differentiable); w > 0, mm: they round off over their last w mm (twice
        differentiable; module docstring).
    """

    contact = True

    name: str
    mesh: Mesh
    node_set: str
    shape: str
    radius: float
    theta_b: float = np.pi / 2
    n0: tuple = (1.0, 0.0, 0.0)
    m0: tuple = (0.0, 0.0, -1.0)
    axis: tuple = (0.0, 0.0, -1.0)
    width: float = 2.5
    ridge: float = 0.0
    ridge_width: float = 0.0
    ridge_flank: float = RIDGE_FLANK
    edge_width: float = EDGE_WIDTH
    sponge_radius: float = 2.5
    sponge_length: float = 10.0
    modulus: float = 0.5
    penalty: float | None = None
    smoothing: float = 2e-3
    extra_dof: int = -1
    curved: bool = False
    quadrature: int = 0
    end_width: float = 0.0

    def __post_init__(self):
        if self.shape not in ("ring", "sponge"):
            raise ValueError(f"buckle contact '{self.name}': shape '{self.shape}'; use 'ring' or "
                             "'sponge'")
        nodes = self.mesh.node_set(self.node_set)
        area, h = node_areas(self.mesh, nodes)
        alpha = (self.penalty if self.penalty is not None
                 else BUCKLE_PENALTY_FACTOR * self.modulus * h)
        if not alpha > 0:
            raise ValueError(f"buckle contact '{self.name}': penalty {alpha} N/mm; must be > 0")
        if self.shape == "ring" and not 0 < self.edge_width < self.width / 2:
            raise ValueError(f"buckle contact '{self.name}': edge_width = {self.edge_width} mm; "
                             f"the edges of a ring {self.width} mm wide lift over 0 to "
                             f"{self.width / 2} mm (exclusive) of each side")
        if self.shape == "sponge" and not 0 <= self.end_width < self.sponge_length / 2:
            raise ValueError(f"buckle contact '{self.name}': end_width = {self.end_width} mm; "
                             f"the ends of a sponge {self.sponge_length} mm long round off over "
                             f"0 (the earlier 0.1 mm fade-out beyond them) to "
                             f"{self.sponge_length / 2} mm (exclusive)")
        if not self.smoothing > 0:
            raise ValueError(f"buckle contact '{self.name}': smoothing {self.smoothing} mm; "
                             "must be > 0")
        if self.quadrature not in (0, 1, 2, 3, 4):
            raise ValueError(f"buckle contact '{self.name}': quadrature = {self.quadrature}; use "
                             "0 (a penalty per node) or 1 to 4 Gauss points per face edge")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "alpha", float(alpha))
        node_dofs = 3 * nodes[:, None] + np.arange(3)
        object.__setattr__(self, "node_dofs", node_dofs)
        object.__setattr__(self, "params", {"d": np.zeros(1), "s": np.zeros(1),
                                            "ridge": np.zeros(1), "dr": np.zeros(1),
                                            "rot": np.zeros(1)})
        geo = np.array([self.radius, self.theta_b, self.width, self.ridge, self.ridge_width,
                        self.sponge_radius, self.sponge_length, self.ridge_flank,
                        self.edge_width])
        frame = np.array([self.n0, self.m0, self.axis], float)
        object.__setattr__(self, "node_area", np.maximum(area, 1e-12))
        if self.quadrature:
            faces, N, wJ = face_points(self.mesh.nodes, self.mesh.face_set(self.node_set),
                                       self.quadrature)
            per_area = alpha / float(np.mean(area))
            dofs = (3 * faces[:, :, None] + np.arange(3)).reshape(len(faces), 12)
            data = {"X": self.mesh.nodes[faces], "N": N, "alpha": per_area * wJ,
                    "area": wJ, "geo": geo, "frame": frame}
            object.__setattr__(self, "faces", faces)
        else:
            dofs = node_dofs
            data = {"X": self.mesh.nodes[nodes], "alpha": np.full(len(nodes), alpha),
                    "area": self.node_area, "geo": geo, "frame": frame}
        if self.extra_dof >= 0:
            dofs = np.concatenate([dofs, np.full((len(dofs), 1), self.extra_dof)], axis=1)
        object.__setattr__(self, "dofs", dofs)
        object.__setattr__(self, "data", data)

    @property
    def n_points(self) -> int:
        """Number of contact points (items): the candidate nodes, or the faces' Gauss points
        with ``quadrature``."""
        return len(self.dofs)

    def static_key(self):
        return (self.shape, self.extra_dof >= 0, self.curved, self.quadrature > 0,
                self.end_width)

    def gaps(self, q_loc, params, data):
        """Signed gaps (n,) of the contact points, mm (negative: penetration), from their
        items' local dofs q_loc (n, k): a node's 3 (nodes) or its face's 12 (quadrature),
        then the free radial dof where there is one."""
        if "N" in data:
            u = q_loc[:, :12].reshape(-1, 4, 3)
            x = jnp.einsum("na,nai->ni", data["N"], data["X"] + u)
            extra = q_loc[:, 12] if self.extra_dof >= 0 else None
        else:
            x = data["X"] + q_loc[:, :3]
            extra = q_loc[:, 3] if self.extra_dof >= 0 else None
        return self.gaps_at(x, extra, params, data)

    def gaps_at(self, x, extra, params, data):
        """Signed gaps (n,), mm, of current points x (n, 3) mm; ``extra`` (n,): the free
        radial dof's value at each (mm) or None."""
        x = rotate_z(x, -params["rot"][0])
        R, th, w, _, rw, rs, L, fl, ew = (data["geo"][i] for i in range(9))
        R = R + params["dr"][0]
        d, s = params["d"][0], params["s"][0]
        if extra is not None:
            d = d + extra
        if self.shape == "ring":
            r = jnp.sqrt(jnp.sum(x * x, axis=1))
            rho = jnp.sqrt(x[:, 0] ** 2 + x[:, 1] ** 2 + 1e-30)  # finite gradient on the axis
            tau = jnp.arctan2(rho, x[:, 2])
            a = R * (tau - th) - s
            prof = ring_profile(a, w, params["ridge"][0], rw, fl, ew)
            return R + prof - d - r
        n0, m0, t = data["frame"][0], data["frame"][1], data["frame"][2]
        if self.curved:
            rho0 = R + rs - d
            u, v, w = x @ n0, x @ m0, x @ jnp.cross(n0, m0)
            rho = jnp.sqrt(u * u + v * v)
            psi = jnp.arctan2(v, u) - s / rho0
            dist = jnp.sqrt((rho - rho0) ** 2 + w * w + 1e-30)
            return dist - rs + sponge_end_lift(jnp.abs(psi) * rho0, L, self.end_width)
        C = jnp.asarray(R + rs - d)[..., None] * n0 + s * m0
        v = x - C
        along = v @ t
        rad = v - along[:, None] * t
        dist = jnp.sqrt(jnp.sum(rad * rad, axis=1) + 1e-30)
        return dist - rs + sponge_end_lift(jnp.abs(along), L, self.end_width)

    def local_energy(self, q_loc, params, data):
        p = smooth_penetration(self.gaps(q_loc, params, data), self.smoothing)
        return 0.5 * data["alpha"] * p * p

    def gap_gradients(self, q_loc, params, data):
        """Gradients (n, k) of the gaps: row i is d g_i / d q_loc[i] (item i's gap depends
        on its own row only)."""
        return jax.grad(lambda x: jnp.sum(self.gaps(x, params, data)))(q_loc)

    def grad_hess_gauss_newton(self, q, params, data, dofs):
        """Local gradients (n, k) and Hessians (n, k, k) without the curvature term
        alpha p p' grad^2 g: alpha (p'^2 + p p'') grad g grad g^T, positive semidefinite.
        At the buckle's curved flanks and rounded edges the dropped term is a negative
        tangential stiffness (a node pressed on a convex corner slides off it) that can
        exceed the soft sclera's own and make the tangent near-singular."""
        q_loc = q[dofs]
        g = self.gaps(q_loc, params, data)
        return penalty_gauss_newton(data["alpha"], g, self.gap_gradients(q_loc, params, data),
                                    self.smoothing)

    def gap_linearisation(self, q_loc, dq_loc, params, data):
        g, dg = jax.jvp(lambda x: self.gaps(x, params, data), (q_loc,), (dq_loc,))
        G = self.gap_gradients(q_loc, params, data)
        return g, dg, G, self.gaps(q_loc + dq_loc, params, data)

    def _gap_np(self, q, params):
        return np.asarray(host_kernel(self, "gaps")(np.asarray(q)[self.dofs], params, self.data))

    def node_gaps(self, q, params) -> np.ndarray:
        """Gaps (n_nodes_in_set,) of the candidate nodes themselves, mm (numpy)."""
        q = np.asarray(q)
        x = self.mesh.nodes[self.nodes] + q[self.node_dofs]
        extra = np.full(len(x), q[self.extra_dof]) if self.extra_dof >= 0 else None
        return np.asarray(host_kernel(self, "gaps_at")(x, extra, params, self.data))

    def report(self, q, params):
        """'active': the contact points whose gap is below the smoothing width eps (each
        carries at least 24 % of the force it would at zero gap; with the smoothed
        penetration a pressed point can sit at a small positive gap), 'penetrating': those
        with a negative gap, 'max_penetration_mm', 'force_N' (all points' normal forces)."""
        g = self._gap_np(q, params)
        pen = np.maximum(-g, 0.0)
        return {"active": int(np.sum(g < self.smoothing)), "penetrating": int(np.sum(g < 0)),
                "max_penetration_mm": float(pen.max(initial=0.0)),
                "force_N": float(self.contact_forces(g).sum())}

    def contact_forces(self, g):
        """Normal contact force magnitudes (n,), N, of the contact points at their gaps g
        (n,) mm: alpha p dp/d(-g) (alpha: the point's penalty, N/mm)."""
        from scipy.special import expit

        z = -np.asarray(g) / self.smoothing
        p = self.smoothing * np.logaddexp(z, 0.0)  # smooth_penetration on the host
        return self.data["alpha"] * p * expit(z)

    def _motion(self, q, params):
        """(R + dr, d (with the free radial motion), s, rot) as floats."""
        d = float(params["d"][0]) + (float(np.asarray(q)[self.extra_dof])
                                     if self.extra_dof >= 0 else 0.0)
        return (self.radius + float(params["dr"][0]), d, float(params["s"][0]),
                float(params["rot"][0]))

    def facing(self, q, params) -> np.ndarray:
        """(n,) bool: candidate nodes over the buckle's footprint (across the ring's
        width; along the sponge, within its radius of its axis sideways, on its side of
        the globe), where the gap is the distance to the buckle under the node (elsewhere
        it is the smooth fade-out of the penalty or the distance to a far side)."""
        x = self.mesh.nodes[self.nodes] + np.asarray(q)[self.node_dofs]
        R, d, s, rot = self._motion(q, params)
        x = rotate_z_np(x, -rot)
        n0, m0, t = (np.asarray(v, float) for v in (self.n0, self.m0, self.axis))
        if self.shape == "ring":
            tau = np.arctan2(np.hypot(x[:, 0], x[:, 1]), x[:, 2])
            return np.abs(R * (tau - self.theta_b) - s) <= self.width / 2
        rs, half = self.sponge_radius, self.sponge_length / 2
        if self.curved:
            rho0 = R + rs - d
            psi = np.arctan2(x @ m0, x @ n0) - s / rho0
            return ((np.abs(psi) * rho0 <= half) & (np.abs(psi) < np.pi / 2)
                    & (np.abs(x @ np.cross(n0, m0)) <= rs))
        v = x - (R + rs - d) * n0 - s * m0
        side = np.cross(t, n0)
        return ((np.abs(v @ t) <= half) & (np.abs(v @ side) <= rs * np.linalg.norm(side))
                & (x @ n0 > 0))

    def point_fields(self, q, params, n_nodes):
        """'<name>_gap_mm' (NaN off the candidate nodes and off the buckle's footprint)
        and '<name>_pressure_MPa' (the nodes' contact forces / their tributary areas; with
        ``quadrature`` the points' forces distributed to the face nodes by the shape
        functions; 0 off contact)."""
        gap, pres = np.full(n_nodes, np.nan), np.zeros(n_nodes)
        g = self._gap_np(q, params)
        f = self.contact_forces(g)
        at_nodes = self.node_gaps(q, params) if self.quadrature else g
        gap[self.nodes] = np.where(self.facing(q, params), at_nodes, np.nan)
        if self.quadrature:
            nodal = np.bincount(self.faces.ravel(), (f[:, None] * self.data["N"]).ravel(),
                                minlength=n_nodes)
            pres[self.nodes] = nodal[self.nodes] / self.node_area
        else:
            pres[self.nodes] = f / self.node_area
        return {f"{self.name}_gap_mm": gap, f"{self.name}_pressure_MPa": pres}

    def surface(self, q, params, n_around: int = 144, n_across: int = 12):
        """The buckle's contact surface as triangles in its current position.

        Ring: the inner surface S(a) over the width, all around the eye axis; sponge:
        the cylinder (or, ``curved``, the tube along the meridian arc) of radius r_s over
        its length. Returns points (m, 3) mm and triangles (k, 3).
        """
        R, d, s, rot = self._motion(q, params)
        rs, L = self.sponge_radius, self.sponge_length
        u = np.linspace(0.0, 2 * np.pi, n_around + 1)
        if self.shape == "ring":
            a = np.linspace(-self.width / 2, self.width / 2, n_across + 1)
            r = R + np.asarray(_ring_profile(a, self.width, float(params["ridge"][0]),
                                             self.ridge_width, self.ridge_flank,
                                             self.edge_width)) - d
            tau = self.theta_b + (a + s) / R
            U, T = np.meshgrid(u, tau, indexing="ij")
            rr = np.broadcast_to(r, U.shape)
            P = np.stack([rr * np.sin(T) * np.cos(U), rr * np.sin(T) * np.sin(U),
                          rr * np.cos(T)], -1)
        else:
            n0, m0, t = (np.asarray(v, float) for v in (self.n0, self.m0, self.axis))
            if self.curved:
                rho0 = R + rs - d
                b = np.cross(n0, m0)
                psi = s / rho0 + np.linspace(-L / 2, L / 2, n_across + 1) / rho0
                U, PS = np.meshgrid(u, psi, indexing="ij")
                er = np.cos(PS)[..., None] * n0 + np.sin(PS)[..., None] * m0
                P = (rho0 + rs * np.cos(U))[..., None] * er + (rs * np.sin(U))[..., None] * b
            else:
                e1 = n0 - (n0 @ t) * t
                e1 /= np.linalg.norm(e1)
                e2 = np.cross(t, e1)
                C = (R + rs - d) * n0 + s * m0
                U, A = np.meshgrid(u, np.linspace(-L / 2, L / 2, n_across + 1), indexing="ij")
                P = (C + A[..., None] * t + rs * np.cos(U)[..., None] * e1
                     + rs * np.sin(U)[..., None] * e2)
        P = rotate_z_np(P.reshape(-1, 3), rot)
        return P, grid_triangles(n_around, n_across, closed_u=True)

    def geometry(self, q, params):
        """The buckle's contact surface (triangles; see :meth:`surface`)."""
        P, tris = self.surface(q, params)
        return P, "triangle", tris, {}
