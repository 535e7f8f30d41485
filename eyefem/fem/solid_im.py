"""The Q1P0 hexahedron enriched with incompatible modes (Wilson-Taylor), for thin walls.

A trilinear brick bends by shearing: its parasitic shear strain stiffens a wall that is
thin beside the element's length (shear locking). Incompatible modes M_k = 1 - xi_k^2
supply the quadratic displacement a bent brick lacks. Mode k moves the element along its
two other natural directions g_i = dX/dxi_i (at the centre, i != k): six amplitudes
alpha per element, a material enhancement of the displacement gradient

    H(alpha) = sum over (k, i) of alpha_ki g_i (x) dM_k/dX,     F = F_c(u) (I + H(alpha))

with dM_k/dX from the Jacobian J0 at the element's centre, scaled by det J0 / det J (Taylor,
Beresford and Wilson 1976; Simo and Rifai 1990), so that H integrates to zero over every
element and the patch test passes. H is defined on the reference element, so a rotation
of the deformed element rotates F and the energy is objective. The element energy is

    Pi_e(u, lambda) = min over alpha of  integral [ W(F) + 2 lambda (J(F_c) - 1) ] dV0

The deviatoric energy W (of the reduced invariants, unchanged by a volume change) sees the
enriched F; the element's incompressibility stays the Q1P0 mean dilatation of F_c. At
small strain this is the Q1/E6 element with a constant pressure: the modes' volumetric
strain integrates to zero over the element, so a constant pressure does no work on it.
Modes along their own direction (alpha_kk) are left out: they would add pointwise volume
changes that neither W nor the one pressure resists, three zero-energy modes.

alpha is condensed inside the element (Newton from alpha = 0 at every evaluation), so the
global unknowns, the tangent's pattern and the saddle-point solver are those of
:class:`eyefem.fem.solid.SolidQ1P0`; the tangent is the condensed one,
K_uu - K_ua K_aa^-1 K_au.

**Not for the eye model.** At small strain the element does not lock in bending (a
cantilever of bricks 8 times as long as thick reaches 0.94 of beam theory, the plain
brick 0.40), but at finite strain it is spuriously unstable in tension: a thin plate
stretched homogeneously, equibiaxially by 3 % or uniaxially by 7 %, has a negative
tangent eigenvalue where the plain brick's are positive, the
known weakness of incompatible-mode and enhanced-strain bricks at large strain (Wriggers
and Korelc 1996, Comput Mech 18:413; Wriggers and Reese 1996, Comput Methods Appl Mech
Eng 135:201). The eye's wall stretches by 5-6 % under the seed's constants, and
case 1 stalled in its tightening (docs/convergence.md, "Shear locking"). No case file
selects it; it is here, verified (tests/test_solid_im.py, ``eyefem verify-tangents``),
for small-strain studies and as the base of a stabilised element.

Local dof order as SolidQ1P0: u[a, i] (24), then lambda (1).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.mesh import hex_gauss_points, hex_shape
from eyefem.fem.solid import (
    SolidQ1P0, _inv_grad_hess, deformation_gradient, element_coeffs, element_fields,
    point_energy, point_fields)

INNER_ITERATIONS = 4
"""Newton iterations on the modes' amplitudes alpha per evaluation, from alpha = 0. At 20 %
strain one iteration leaves |dPi/dalpha| at 1e-2 of its start, two at 1e-5, three at
round-off (tests/test_solid_im.py); at 60 % four do."""


def mode_gradients(nodes, hexes):
    """The incompatible modes' geometry: their gradients dM_k/dX (n_elem, 8 Gauss points,
    3 modes, 3), 1/mm, at the 2x2x2 Gauss points ((dM_k/dxi) J0^-1 det J0 / det J), and the
    natural directions J0 = dX/dxi at the element's centre (n_elem, 3, 3), mm (column i is
    g_i)."""
    xe = np.asarray(nodes, np.float64)[np.asarray(hexes)]
    xg, _ = hex_gauss_points()
    _, dn0 = hex_shape(np.zeros(3))
    _, dn = hex_shape(xg)
    j0 = np.einsum("eai,aj->eij", xe, dn0)  # dX_i/dxi_j at the centre
    jg = np.einsum("eai,gaj->egij", xe, dn)
    det0, detg = np.linalg.det(j0), np.linalg.det(jg)
    dm = np.einsum("gk,kj->gkj", -2.0 * xg, np.eye(3))  # dM_k/dxi_j (8, 3, 3)
    inv0 = np.linalg.inv(j0)  # dxi_j/dX_i
    return np.einsum("gkj,eji,e,eg->egki", dm, inv0, det0, 1.0 / detg), j0


MODES = tuple((k, i) for k in range(3) for i in range(3) if k != i)
"""The enriched (mode k, natural direction i) pairs: M_k moves the element along its two
directions across xi_k (u ~ (1 - xi_k^2) g_i, the shape of a brick bent in the k-i
plane). The three along their own direction would be zero-energy modes of an
incompressible brick (module docstring; tests/test_solid_im.py)."""
N_MODES = len(MODES)
_SELECT = np.zeros((N_MODES, 3, 3))
_SELECT[np.arange(N_MODES), [k for k, _ in MODES], [i for _, i in MODES]] = 1.0


def mode_operators(gm, frame):
    """dH/dalpha (..., 8, 6, 3, 3), the material enhancement of each mode (module
    docstring), from the mode gradients gm (..., 8, 3, 3) and natural directions frame
    (..., 3, 3) of :func:`mode_gradients`."""
    return jnp.einsum("mki,...pi,...gkj->...gmpj", _SELECT, frame, gm)


def pushed_operators(F_c, E):
    """dF/dalpha = F_c dH/dalpha (n, 8, 6, 3, 3) from F_c (n, 8, 3, 3) and E of
    :func:`mode_operators`: F = F_c + sum_m alpha_m (F_c E_m)."""
    return jnp.einsum("egip,egmpj->egmij", F_c, E)


def _deviatoric_density(F, c):
    """W(I1bar, I2bar), MPa, at one point (F (3, 3), c (4, 4) MPa): the plain element's
    point energy without its pressure term."""
    return point_energy(F, 0.0, c)


_stress_tangent = jax.vmap(jax.vmap(
    lambda F, c: (jax.grad(_deviatoric_density)(F, c), jax.hessian(_deviatoric_density)(F, c)),
    (0, None)), (0, 0))
"""P = dW/dF (n, 8, 3, 3) and A = d2W/dF2 (n, 8, 3, 3, 3, 3), MPa, of the deviatoric energy at
F (n, 8, 3, 3) with coefficient tables c (n, 4, 4)."""


def mode_residual_tangent(F, D, dv, c):
    """The modes' residual dPi/dalpha (n, 6), N mm, and tangent d2Pi/dalpha2 (n, 6, 6) at
    deformation gradients F (n, 8, 3, 3), F linear in alpha with dF/dalpha = D
    (n, 8, 6, 3, 3): from W's derivatives in its invariants (I1, I2, J) and the invariants'
    closed-form first and second derivatives along the six directions D_m, X = D_m, Y = D_p:

        d2 I1 [X, Y] = 2 X:Y
        d2 I2 [X, Y] = 4 (F:X)(F:Y) + 2 I1 X:Y - 2 X:(Y C + F Y^T F + F F^T Y)
        d2 J  [X, Y] = J (tr(F^-1 X) tr(F^-1 Y) - tr(F^-1 X F^-1 Y))

    (0.044 s against 0.12 s with autodiff's d2W/dF2 contracted, 2,470 elements; dv (n, 8) mm^3,
    c (n, 4, 4) MPa)."""
    C = jnp.swapaxes(F, -1, -2) @ F
    I1 = jnp.trace(C, axis1=-2, axis2=-1)
    I2 = 0.5 * (I1 * I1 - jnp.sum(C * C, axis=(-2, -1)))
    J = jnp.linalg.det(F)
    Finv = jnp.linalg.inv(F)
    dW, ddW = _inv_grad_hess(jnp.stack([I1, I2, J], -1), jnp.zeros(F.shape[0], F.dtype), c)
    Fg, Cg, Fig = F[:, :, None], C[:, :, None], Finv[:, :, None]  # broadcast over the modes

    def dot(X, Y):  # X:Y (n, 8, 6, 6)
        return jnp.einsum("egmij,egpij->egmp", X, Y)

    FX = jnp.sum(Fg * D, axis=(-2, -1))  # (n, 8, 6)
    FCX = jnp.sum((F @ C)[:, :, None] * D, axis=(-2, -1))
    FiX = Fig @ D  # F^-1 X
    trX = jnp.trace(FiX, axis1=-2, axis2=-1)
    v = jnp.stack([2.0 * FX, 2.0 * (I1[..., None] * FX - FCX), J[..., None] * trX], 2)  # (n,8,3,6)
    g = jnp.einsum("eg,ega,egam->em", dv, dW, v)
    XY = dot(D, D)
    rest = dot(D, D @ Cg + Fg @ jnp.swapaxes(D, -1, -2) @ Fg + (F @ jnp.swapaxes(F, -1, -2))[:, :, None] @ D)
    d2I2 = 4.0 * FX[..., :, None] * FX[..., None, :] + 2.0 * I1[..., None, None] * XY - 2.0 * rest
    d2J = J[..., None, None] * (trX[..., :, None] * trX[..., None, :]
                                - dot(FiX, jnp.swapaxes(FiX, -1, -2)))
    K = jnp.einsum("eg,egab,egam,egbp->emp", dv, ddW, v, v) + jnp.einsum(
        "eg,egmp->emp", dv, 2.0 * dW[..., 0, None, None] * XY + dW[..., 1, None, None] * d2I2
        + dW[..., 2, None, None] * d2J)
    return g, K


def condensed_modes(F_c, E, dv, c, iterations: int = INNER_ITERATIONS):
    """The modes' amplitudes alpha (n, 6) that minimise each element's deviatoric energy
    sum_g dv W(F_c + sum_m alpha_m D_m) for compatible deformation gradients F_c
    (n, 8, 3, 3): Newton from alpha = 0, ``iterations`` steps.

    Args: E (n, 8, 6, 3, 3) the modes' dF/dalpha, D (:func:`pushed_operators`); dv (n, 8)
    mm^3; c (n, 4, 4) MPa."""
    def step(_, a):
        g, K = mode_residual_tangent(F_c + jnp.einsum("em,egmij->egij", a, E), E, dv, c)
        return a - jnp.linalg.solve(_unenriched_identity(K), g[..., None])[..., 0]
    return jax.lax.fori_loop(0, iterations, step, jnp.zeros(F_c.shape[:1] + (N_MODES,), F_c.dtype))


def _unenriched_identity(K):
    """K (n, 6, 6) with the identity in place of the zero block of an element without modes
    (its mode gradients set to zero): alpha stays 0 there."""
    off = jnp.all(K == 0.0, axis=(1, 2))
    return K + off[:, None, None] * jnp.eye(N_MODES, dtype=K.dtype)


def _energy_at(q_loc, alpha, c, G, E, dv):
    """Element energies (n,), N mm, at local dofs q_loc (n, 25) and modes alpha (n, 6)."""
    F_c = deformation_gradient(q_loc[:, :24].reshape(-1, 8, 3), G)
    F = F_c + jnp.einsum("em,egmij->egij", alpha, pushed_operators(F_c, E))
    w = jax.vmap(jax.vmap(_deviatoric_density, (0, None)), (0, 0))(F, c)
    return jnp.sum(dv * (w + 2.0 * q_loc[:, 24:25] * (jnp.linalg.det(F_c) - 1.0)), axis=1)


def _optimal_modes(q_loc, c, G, E, dv):
    F_c = deformation_gradient(q_loc[:, :24].reshape(-1, 8, 3), G)
    return condensed_modes(F_c, pushed_operators(F_c, E), dv, c)


@jax.custom_jvp
def condensed_energy(q_loc, c, G, E, dv):
    """Element energies (n,), N mm, with the modes at their optimum alpha*(u): Pi_e(u,
    lambda) of the module docstring. q_loc (n, 25); c (n, 4, 4) MPa; G (n, 8, 8, 3) dN/dX;
    E (n, 8, 6, 3, 3) :func:`mode_operators`; dv (n, 8) mm^3.

    Its derivative is the partial one at fixed alpha* (alpha* minimises, dPi/dalpha = 0),
    so a gradient costs one inner solve and no derivative of it; differentiating that
    derivative again goes through the inner Newton iterations (exact at their
    convergence). G, E and dv are reference geometry: their tangents are ignored."""
    return _energy_at(q_loc, _optimal_modes(q_loc, c, G, E, dv), c, G, E, dv)


@condensed_energy.defjvp
def _condensed_energy_jvp(primals, tangents):
    q_loc, c, G, E, dv = primals
    alpha = _optimal_modes(q_loc, c, G, E, dv)
    return jax.jvp(lambda q, cc: _energy_at(q, alpha, cc, G, E, dv), (q_loc, c), tangents[:2])


@dataclasses.dataclass(frozen=True, eq=False)
class SolidQ1P0IM(SolidQ1P0):
    """:class:`eyefem.fem.solid.SolidQ1P0` with six incompatible modes per element,
    condensed inside the element (module docstring). Same arguments and dofs, and:

    Args:
      enriched_materials: names of the materials whose elements carry the modes (None:
        all); the others are plain Q1P0 elements.
    """

    enriched_materials: tuple | None = None

    def __post_init__(self):
        super().__post_init__()
        m = self.mesh
        grad_m, frame_m = mode_gradients(m.nodes, m.hexes[self.elements])
        if self.enriched_materials is not None:
            unknown = sorted(set(self.enriched_materials) - set(m.materials))
            if unknown:
                raise ValueError(f"solid '{self.name}': enriched_materials {unknown} are not "
                                 f"materials of the mesh; it has {list(m.materials)}")
            ids = [m.materials.index(name) for name in self.enriched_materials]
            grad_m = grad_m * np.isin(m.material_ids[self.elements], ids)[:, None, None, None]
        data = dict(self.data, grad_m=grad_m, frame_m=frame_m)
        object.__setattr__(self, "data", data)

    def _modes(self, q_loc, params, data):
        """F_c (n, 8, 3, 3), c (n, 4, 4), E = dH/dalpha and D = dF/dalpha (n, 8, 6, 3, 3)
        and alpha* (n, 6)."""
        F_c = deformation_gradient(q_loc[:, :24].reshape(-1, 8, 3), data["grad_n"])
        c = element_coeffs(params["coeffs"], data)
        E = mode_operators(data["grad_m"], data["frame_m"])
        D = pushed_operators(F_c, E)
        return F_c, c, E, D, condensed_modes(F_c, D, data["dv"], c)

    def local_energy(self, q_loc, params, data):
        return condensed_energy(q_loc, element_coeffs(params["coeffs"], data), data["grad_n"],
                                mode_operators(data["grad_m"], data["frame_m"]), data["dv"])

    def _blocks(self, q_loc, params, data):
        """g_u (n, 24), g_lambda (n,), K_uu (n, 24, 24) and K_ulambda (n, 24) of the element
        with its modes condensed at alpha*(u): K_uu - K_ua K_aa^-1 K_au and
        g_u - K_ua K_aa^-1 g_a (g_a ~ 0 at alpha*).

        With F = F_c (I + H): dF_ij/du_bk = delta_ik (G_b (I + H))_j, dF/dalpha_m = F_c E_m,
        and d2F/du_bk dalpha_m = delta_ik (G_b E_m)_j."""
        F_c, c, E, D, alpha = self._modes(q_loc, params, data)
        G, dv = data["grad_n"], data["dv"]
        lam = q_loc[:, 24]
        H = jnp.einsum("em,egmij->egij", alpha, E)
        P, A = _stress_tangent(F_c + jnp.einsum("egip,egpj->egij", F_c, H), c)
        Gh = G + jnp.einsum("egbl,eglj->egbj", G, H)  # G (I + H)
        n = q_loc.shape[0]
        gu = jnp.einsum("eg,egij,egaj->eai", dv, P, Gh).reshape(n, 24)
        ga = jnp.einsum("eg,egij,egmij->em", dv, P, D)
        AG = jnp.einsum("egijkl,egbl->egijbk", A, Gh)
        kuu = jnp.einsum("eg,egaj,egijbk->eaibk", dv, Gh, AG).reshape(n, 24, 24)
        kua = (jnp.einsum("eg,egmij,egijbk->ebkm", dv, D, AG)
               + jnp.einsum("eg,egkj,egbl,egmlj->ebkm", dv, P, G, E)).reshape(n, 24, N_MODES)
        kaa = jnp.einsum("eg,egmij,egijkl,egpkl->emp", dv, D, A, D)
        sol = jnp.linalg.solve(_unenriched_identity(kaa), jnp.concatenate([jnp.swapaxes(kua, 1, 2), ga[..., None]], 2))
        kuu = kuu - jnp.einsum("eam,emb->eab", kua, sol[:, :, :24])
        gu = gu - jnp.einsum("eam,em->ea", kua, sol[:, :, 24])
        # the pressure's part, 2 lambda (J(F_c) - 1): as SolidQ1P0
        J = jnp.linalg.det(F_c)
        u_ = jnp.einsum("egji,egaj->egai", jnp.linalg.inv(F_c), G)  # G F_c^-1
        wj = 2.0 * lam[:, None] * dv * J
        kuu = kuu + (jnp.einsum("eg,egai,egbk->eaibk", wj, u_, u_)
                     - jnp.einsum("eg,egak,egbi->eaibk", wj, u_, u_)).reshape(n, 24, 24)
        gu = gu + 2.0 * lam[:, None] * jnp.einsum("eg,egai->eai", dv * J, u_).reshape(n, 24)
        kul = 2.0 * jnp.einsum("eg,egai->eai", dv * J, u_).reshape(n, 24)
        gl = 2.0 * jnp.sum(dv * (J - 1.0), axis=1)
        return gu, gl, kuu, kul

    def fields(self, q, params):
        """As :meth:`SolidQ1P0.fields`, from the enriched deformation gradient F_c + H."""
        return _im_fields(np.asarray(q)[self.dofs], params, self.data)


def _im_fields(q_loc, params, data):
    c = element_coeffs(params["coeffs"], data)
    F_c = deformation_gradient(q_loc[:, :24].reshape(-1, 8, 3), data["grad_n"])
    D = pushed_operators(F_c, mode_operators(data["grad_m"], data["frame_m"]))
    F = F_c + jnp.einsum("em,egmij->egij", condensed_modes(F_c, D, data["dv"], c), D)
    return element_fields(*(np.asarray(a) for a in point_fields(F, q_loc[:, 24], c)),
                          data["dv"])
