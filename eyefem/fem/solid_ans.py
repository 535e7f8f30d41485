"""The Q1P0 hexahedron with assumed natural strains across its thickness (solid shell).

A trilinear brick bends by shearing: across a thin wall its transverse shear strains
E_xi-zeta and E_eta-zeta vary linearly along the element where bending leaves none, and
stiffen the wall (shear locking). With assumed natural strains (Dvorkin and Bathe 1984)
the covariant components of the Green-Lagrange strain, E_ij = (x_,i . x_,j - X_,i . X_,j)
/ 2 with x_,i = dx/dxi_i, are sampled where they carry no parasitic part and interpolated
to the Gauss points:

    E_13 (xi-zeta)   from (0, -1) and (0, +1), linear in eta
    E_23 (eta-zeta)  from (-1, 0) and (+1, 0), linear in xi
    E_33 (thickness) compatible; with ``ans_thickness`` from the four corners (+-1, +-1),
                     bilinear in xi, eta (Betsch and Stein 1995)

each at the Gauss point's own zeta. zeta must be the element's thickness direction (the
eye's wall elements: their nodes 0-3 inner, 4-7 outer). The energy density is the
generalised Mooney-Rivlin W of the right Cauchy-Green tensor C = I + 2 J^-T E J^-1 (J =
dX/dxi at the Gauss point), from its reduced invariants, and the element's one pressure
holds the mean dilatation of the same strains:

    Pi_e = integral [ W(C_ans) + 2 lambda (sqrt(det C_ans) - 1) ] dV0

(with det F of the compatible field in the constraint instead, the pressure's geometric
stiffness and W's disagree, and a thin plate stretched by 3 % loses its stability). No
internal unknowns: residual and tangent are autodiff's of one energy (forward over
reverse, over chunks of ANS_CHUNK elements). The assumed strains reproduce a homogeneous
deformation exactly on parallelepiped elements.

The thickness strain stays compatible by default: sampled at the corners it reads
oppositely tilted thickness edges as stretched, so the pressure lets an element lose
volume that way, and the eye's sclera did under the band in case 1 (the tightening
stalled; docs/formulation.md, "Assumed natural strains").

Verified (tests/test_solid_im.py): a clamped beam of bricks 8, 4 and 2 times as long as
thick at 0.945, 0.974 and 0.986 of Timoshenko's deflection (Q1P0: 0.40, 0.70, 0.87);
stable in tension to 40 % where the incompatible-mode brick (eyefem.fem.solid_im) fails at
3 %; the patch test; objectivity; residual and tangent against central differences; case
1 on the coarse eye with the wall of this element (slow). Case field ``wall_element =
"ans"`` (eyefem.eye.wall) puts it in the eye's cornea, limbus and sclera.

Local dof order as SolidQ1P0: u[a, i] (24), then lambda (1).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.materials import strain_energy
from eyefem.fem.mesh import hex_gauss_points, hex_shape
from eyefem.fem.solid import SolidQ1P0, chunked, deformation_gradient, element_coeffs
from eyefem.fem.terms import Term


def _sampling_derivatives():
    """Natural shape-function derivatives (8 Gauss points, 8 samples, 8 nodes, 3) at each
    Gauss point's samples (at its zeta): 0-1 for E_13 ((0, -+1)), 2-3 for E_23 ((-+1, 0)),
    4-7 for E_33 (the corners), and the interpolation weights (8 Gauss points, 8)."""
    xg, _ = hex_gauss_points()
    pts, wts = [], []
    for xi, eta, zeta in xg:
        p = [(0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (1, -1), (1, 1), (-1, 1)]
        pts.append([(a, b, zeta) for a, b in p])
        w = [(1 - eta) / 2, (1 + eta) / 2, (1 - xi) / 2, (1 + xi) / 2]
        w += [(1 + a * xi) * (1 + b * eta) / 4 for a, b in p[4:]]
        wts.append(w)
    _, dn = hex_shape(np.asarray(pts, np.float64))
    return dn, np.asarray(wts)


def _covariant_strain(xe, Xe, dn):
    """Covariant Green-Lagrange strains (..., 3, 3) at points with natural derivatives dn
    (..., 8, 3) of an element with current and reference nodes xe, Xe (8, 3)."""
    g = jnp.einsum("ai,...ak->...ik", xe, dn)  # columns x_,k
    G = jnp.einsum("ai,...ak->...ik", Xe, dn)
    return 0.5 * (jnp.swapaxes(g, -1, -2) @ g - jnp.swapaxes(G, -1, -2) @ G)


def assumed_strain(u_e, X_e, jinv, thickness=False):
    """Cartesian Green-Lagrange strains (8 Gauss points, 3, 3) of one element with the
    assumed natural strains: u_e, X_e (8, 3) mm; jinv (8, 3, 3) the inverse of dX/dxi at the
    Gauss points; ``thickness`` False: E_33 stays the compatible one (transverse shears
    assumed only)."""
    dn_s, w = _SAMPLES
    _, dn_g = hex_shape(hex_gauss_points()[0])
    x_e = X_e + u_e
    E = _covariant_strain(x_e, X_e, jnp.asarray(dn_g))  # (8, 3, 3)
    ns = 8 if thickness else 4  # the corners' samples only for E_33
    Es = _covariant_strain(x_e, X_e, jnp.asarray(dn_s[:, :ns]))  # (8, ns, 3, 3)
    e13 = w[:, 0] * Es[:, 0, 0, 2] + w[:, 1] * Es[:, 1, 0, 2]
    e23 = w[:, 2] * Es[:, 2, 1, 2] + w[:, 3] * Es[:, 3, 1, 2]
    E = E.at[:, 0, 2].set(e13).at[:, 2, 0].set(e13)
    E = E.at[:, 1, 2].set(e23).at[:, 2, 1].set(e23)
    if thickness:
        E = E.at[:, 2, 2].set(jnp.einsum("gc,gc->g", w[:, 4:], Es[:, 4:, 2, 2]))
    return jnp.swapaxes(jinv, -1, -2) @ E @ jinv


_SAMPLES = _sampling_derivatives()

ANS_CHUNK = 250
"""Elements per chunk of the autodiff tangent kernel (:func:`eyefem.fem.solid.chunked`)."""


def _density(E, c):
    """W(I1bar, I2bar), MPa, of C = I + 2 E (3, 3); c (4, 4) MPa."""
    C = jnp.eye(3) + 2.0 * E
    i1 = jnp.trace(C)
    i2 = 0.5 * (i1 * i1 - jnp.sum(C * C))
    j2 = jnp.linalg.det(C)
    return strain_energy(j2 ** (-1.0 / 3.0) * i1, j2 ** (-2.0 / 3.0) * i2, c)


@dataclasses.dataclass(frozen=True, eq=False)
class SolidQ1P0ANS(SolidQ1P0):
    """:class:`eyefem.fem.solid.SolidQ1P0` with assumed natural strains across zeta (module
    docstring). Same arguments and dofs, and:

    Args:
      ans_materials: names of the materials whose elements use the assumed strains (None:
        all); the others are plain Q1P0 elements.

    ``fields`` are SolidQ1P0's, from the compatible deformation gradient.
    """

    ans_materials: tuple | None = None
    ans_thickness: bool = False

    def __post_init__(self):
        super().__post_init__()
        m = self.mesh
        xe = m.nodes[m.hexes[self.elements]]
        _, dn = hex_shape(hex_gauss_points()[0])
        jinv = np.linalg.inv(np.einsum("eai,gaj->egij", xe, dn))
        on = np.ones(len(self.elements), bool)
        if self.ans_materials is not None:
            unknown = sorted(set(self.ans_materials) - set(m.materials))
            if unknown:
                raise ValueError(f"solid '{self.name}': ans_materials {unknown} are not "
                                 f"materials of the mesh; it has {list(m.materials)}")
            on = np.isin(m.material_ids[self.elements],
                         [m.materials.index(t) for t in self.ans_materials])
        object.__setattr__(self, "data", dict(self.data, X=xe, jinv=jinv, ans=on.astype(float)))

    def local_energy(self, q_loc, params, data):
        u = q_loc[:, :24].reshape(-1, 8, 3)
        c = element_coeffs(params["coeffs"], data)
        F = deformation_gradient(u, data["grad_n"])
        E_plain = 0.5 * (jnp.swapaxes(F, -1, -2) @ F - jnp.eye(3))
        E_ans = jax.vmap(assumed_strain, (0, 0, 0, None))(u, data["X"], data["jinv"],
                                                        self.ans_thickness)
        on = data["ans"][:, None, None, None]
        E = on * E_ans + (1.0 - on) * E_plain
        w = jax.vmap(jax.vmap(_density, (0, None)), (0, 0))(E, c)
        vol = jnp.sqrt(jnp.linalg.det(jnp.eye(3) + 2.0 * E)) - 1.0
        return jnp.sum(data["dv"] * (w + 2.0 * q_loc[:, 24:25] * vol), axis=1)

    local_grad_hess = Term.local_grad_hess

    def static_key(self) -> tuple:
        """The thickness strain's rule changes the compiled code: the two variants share no
        kernel (eyefem.solve.model.Model._kernel keys by class and this)."""
        return (self.ans_thickness,)

    def grad_hess_condensed(self, q, params, data, dofs, beta):
        """:meth:`Term.grad_hess_condensed` (autodiff) over chunks of ANS_CHUNK elements in
        turn: at once, the forward-over-reverse intermediates of the default eye's 11,862
        elements held 10.7 GB."""
        def one(data, dofs):
            return Term.grad_hess_condensed(self, q, params, data, dofs, beta)
        return chunked(one, data, dofs, ANS_CHUNK)
