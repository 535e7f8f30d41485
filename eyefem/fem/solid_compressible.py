"""The displacement hexahedron of FEBio's compressible and nearly incompressible laws
(Total Lagrangian, trilinear, 2 x 2 x 2 Gauss points, no element multiplier).

Element energy, with F_g, J_g = det F_g the deformation gradient at Gauss point g and
dv_g its reference volume (weight times Jacobian):

    Pi_e = sum_g dv_g [ W(I1bar_g, I2bar_g) + W_c(I1_g, I2_g, J_g) ] + V_e U(Jbar_e)   [N mm]

    V_e = sum_g dv_g,   Jbar_e = v_e / V_e = (sum_g dv_g J_g) / V_e,   U(J) = k/2 (ln J)^2

* W(I1bar, I2bar) = sum c_rs (I1bar - 3)^r (I2bar - 3)^s: the uncoupled (deviatoric) part
  of eyefem.fem.materials.UncoupledMooneyRivlin, at every Gauss point;
* U on the element's volume ratio Jbar = v / V: FEBio's three-field hexahedron
  (FE3FieldElasticSolidDomain, its default for uncoupled materials on hex8), whose
  piecewise-constant dilatation theta and pressure p are condensed here exactly: the
  three-field functional sum_g dv_g W(F_g) + V [U(theta) + p (Jbar - theta)] is stationary
  in p and theta at theta = Jbar, p = U'(Jbar), and what is left is Pi_e above, a function
  of the displacements alone. Its gradient is sum_g dv_g [dW/dF + U'(Jbar) cof F_g] : dF,
  i.e. the Cauchy stress at a Gauss point is dev-part(F_g) + U'(Jbar) I, FEBio's
  (UpdateElementStress: ep = UJ(eJ), eJ = v / V);
* W_c = c1 (I1 - 3) + c2 (I2 - 3) - 2 (c1 + 2 c2) ln J + lam/2 (ln J)^2: FEBio's coupled
  Mooney-Rivlin and neo-Hookean (eyefem.fem.materials.CoupledMooneyRivlin), at every Gauss
  point: the plain displacement element FEBio uses for coupled materials
  (FEElasticSolidDomain). A coupled material has its volumetric stiffness in W_c, so it
  needs no multiplier and no averaged dilatation.

The exactly incompressible material (k = 0, eyefem.fem.materials.MooneyRivlin) stays on
the Q1P0 element with its multiplier (eyefem.fem.solid.SolidQ1P0); eyefem.solve.model.
solid_model puts each element on the term its material needs. The residual and tangent
are JAX's derivatives of Pi_e (the tangent exact and symmetric, the saddle-point solver
sees no multiplier: a plain symmetric solve).

Local dof order: u[a, i] for node a = 0..7, component i = 0..2 (24).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.materials import coupled_energy, strain_energy, volumetric_energy
from eyefem.fem.mesh import Mesh, hex_geometry
from eyefem.fem.solid import (cofactor, deformation_gradient, det3, element_coeffs,
                              element_fields)
from eyefem.fem.terms import Term


def element_constants(params, data):
    """The elements' c_rs tables (n, 4, 4), bulk moduli k (n,) and coupled constants
    (n, 3) (c1, c2, lam), MPa: their material's, or the volume fractions' weighted sums
    (all three enter the energy linearly: the Voigt mixture, as
    eyefem.fem.solid.element_coeffs)."""
    c = element_coeffs(params["coeffs"], data)
    if "mix" in data:
        return (c, data["mix"] @ params["k"], data["mix"] @ params["coupled"])
    return c, params["k"][data["mat"]], params["coupled"][data["mat"]]


def point_energy(F, c, cc):
    """W(I1bar, I2bar) + W_c(I1, I2, J) at Gauss points (..., 3, 3), MPa (without U)."""
    C = jnp.swapaxes(F, -1, -2) @ F
    i1 = jnp.trace(C, axis1=-2, axis2=-1)
    i2 = 0.5 * (i1 * i1 - jnp.sum(C * C, axis=(-2, -1)))
    J = det3(F)
    dev = strain_energy(J ** (-2.0 / 3.0) * i1, J ** (-4.0 / 3.0) * i2, c)
    return dev + coupled_energy(i1, i2, J, cc)


def volume_ratio(F, dv):
    """Jbar = sum_g dv_g J_g / sum_g dv_g (n,) of F (n, 8, 3, 3), dv (n, 8)."""
    return jnp.sum(dv * det3(F), axis=1) / jnp.sum(dv, axis=1)


def _element_grad_hess(P, A, F, G, dv, V, ddU):
    """Element gradients (n, 24) and Hessians (n, 24, 24) of a three-field element from
    its points' first Piola stress P (n, 8, 3, 3) and tangent A = dP/dF (n, 8, 3, 3, 3, 3)
    (the Jbar pressure term inside), deformation gradients F, shape-function gradients G
    (n, 8, 8, 3), point volumes dv (n, 8), element volumes V (n,) and U''(Jbar) (n,):
    K = sum_g dv G^T A G + V U'' a a^T with a = sum_g dv G^T cof(F) / V."""
    g = jnp.einsum("eg,egij,egaj->eai", dv, P, G).reshape(-1, 24)
    K = jnp.einsum("eg,egaj,egijkl,egbl->eaibk", dv, G, A, G).reshape(-1, 24, 24)
    a = jnp.einsum("eg,egij,egaj->eai", dv, cofactor(F), G).reshape(-1, 24) / V[:, None]
    return g, K + (V * ddU)[:, None, None] * a[:, :, None] * a[:, None, :]


@dataclasses.dataclass(frozen=True, eq=False)
class SolidCompressible(Term):
    """Hexahedra of FEBio's nearly incompressible and compressible laws (module docstring).

    Args:
      name: term name.
      mesh: the mesh; element e uses material ``mesh.material_ids[e]`` (or the volume
        fractions' mixture, ``mesh.material_fractions``).
      coeffs: (n_materials, 4, 4) uncoupled c_rs tables, MPa, indexed like
        ``mesh.materials`` (zero for a coupled material).
      k: (n_materials,) bulk moduli of U(Jbar) = k/2 (ln Jbar)^2, MPa (0 for a coupled one).
      coupled: (n_materials, 3) (c1, c2, lam) of the coupled energy W_c, MPa (zero for an
        uncoupled one).
      elements: the element ids this term holds (default all).
    """

    name: str
    mesh: Mesh
    coeffs: np.ndarray
    k: np.ndarray
    coupled: np.ndarray
    elements: np.ndarray | None = None
    multiplier_slots = ()
    chunked_kernel = True  # data holds per-element arrays only

    def __post_init__(self):
        m = self.mesh
        el = np.arange(m.n_elem) if self.elements is None else np.asarray(self.elements)
        hexes = m.hexes[el]
        grad_n, dv, _ = hex_geometry(m.nodes, hexes)
        dofs = (3 * hexes[:, :, None] + np.arange(3)).reshape(-1, 24)
        object.__setattr__(self, "elements", el)
        object.__setattr__(self, "dofs", dofs)
        object.__setattr__(self, "params", {
            "coeffs": np.asarray(self.coeffs, np.float64),
            "k": np.asarray(self.k, np.float64).reshape(-1),
            "coupled": np.asarray(self.coupled, np.float64).reshape(-1, 3)})
        data = {"grad_n": grad_n, "dv": dv, "mat": m.material_ids[el]}
        if m.material_fractions is not None:
            data["mix"] = m.material_fractions[el]
        object.__setattr__(self, "data", data)

    def local_energy(self, q_loc, params, data):
        F = deformation_gradient(q_loc.reshape(-1, 8, 3), data["grad_n"])
        c, k, cc = element_constants(params, data)
        dv = data["dv"]
        w = point_energy(F, c[:, None], cc[:, None])
        V = jnp.sum(dv, axis=1)
        return jnp.sum(w * dv, axis=1) + V * volumetric_energy(volume_ratio(F, dv), k)

    def local_grad_hess(self, q_loc, params, data):
        """Gradients (n, 24) and Hessians (n, 24, 24), from the Gauss points' derivatives
        of phi(F) = W(F) + p J(F) (3 x 3 -> autodiff), p = U'(Jbar) fixed, and the
        rank-one term of U'' (G: shape-function gradients, dv: point volumes):

            g = sum_g dv_g G_g^T (dphi/dF),  a = sum_g dv_g G_g^T (J F^-T) / V,
            K = sum_g dv_g G_g^T (d2phi/dF2) G_g + V U''(Jbar) a a^T
        """
        G, dv = data["grad_n"], data["dv"]
        F = deformation_gradient(q_loc.reshape(-1, 8, 3), G)
        c, k, cc = element_constants(params, data)
        V = jnp.sum(dv, axis=1)
        jbar = volume_ratio(F, dv)
        dU = jax.grad(volumetric_energy)
        p = jax.vmap(dU)(jbar, k)
        ddU = jax.vmap(jax.grad(dU))(jbar, k)

        def phi(f, c_, cc_, p_):
            return point_energy(f, c_, cc_) + p_ * det3(f)

        over_points = jax.vmap(jax.vmap(lambda f, c_, cc_, p_: (
            jax.grad(phi)(f, c_, cc_, p_), jax.hessian(phi)(f, c_, cc_, p_)),
            (0, None, None, None)), (0, 0, 0, 0))
        P, A = over_points(F, c, cc, p)  # (n, 8, 3, 3), (n, 8, 3, 3, 3, 3)
        return _element_grad_hess(P, A, F, G, dv, V, ddU)

    def fields(self, q, params):
        """Per-element fields as :meth:`eyefem.fem.solid.SolidQ1P0.fields` ('cauchy',
        'von_mises', 'pressure', 'J', 'green_lagrange', 'max_principal_strain'); 'lambda'
        is U'(Jbar) / 2, MPa (the multiplier the Q1P0 element would carry for the same
        mean stress of the uncoupled part; 0 for a coupled material)."""
        return element_fields(*(np.asarray(a) for a in _point_fields(
            np.asarray(q)[self.dofs], params, self.data)), self.data["dv"])


@jax.jit
def _point_fields(q_loc, params, data):
    """Cauchy stress (n, 8, 3, 3), J (n, 8), U'(Jbar) / 2 (n,) and Green-Lagrange strain
    (n, 8, 3, 3) at the Gauss points."""
    F = deformation_gradient(q_loc.reshape(-1, 8, 3), data["grad_n"])
    c, k, cc = element_constants(params, data)
    P = jax.grad(lambda f: jnp.sum(point_energy(f, c[:, None], cc[:, None])))(F)
    J = det3(F)
    jbar = volume_ratio(F, data["dv"])
    p = jax.vmap(jax.grad(volumetric_energy))(jbar, k)  # U'(Jbar)
    sig = jnp.einsum("egij,egkj->egik", P, F) / J[..., None, None] \
        + p[:, None, None, None] * jnp.eye(3)
    E = 0.5 * (jnp.einsum("egki,egkj->egij", F, F) - jnp.eye(3))
    return sig, J, 0.5 * p, E


@dataclasses.dataclass(frozen=True, eq=False)
class SolidFebioLaw(Term):
    """Hexahedra of one of FEBio's further laws (eyefem.fem.materials.FebioLaw: Ogden,
    Holmes-Mow, trans iso Mooney-Rivlin, solid mixtures, ...), on the same displacement
    element as :class:`SolidCompressible`:

        Pi_e = sum_g dv_g W(F_g; a0_g) + V_e U(Jbar_e)                          [N mm]

    with W the law's energy (its uncoupled parts of Fbar_g = J_g^(-1/3) F_g), U = k/2
    (ln J)^2 on the element's volume ratio Jbar = v / V for an uncoupled law (FEBio's
    three-field hex8), none for a coupled one (k = 0: FEBio's displacement element).

    Args:
      name: term name.
      mesh: the mesh.
      law: the material (eyefem.fem.materials.FebioLaw).
      elements: the element ids of this material (n,).
      fibers: (n, 8, n_fibers, 3) unit fibre directions at the Gauss points in the
        reference configuration (FEBio's order of the law's fibred parts), or None for a
        law without fibres.
      constants: the law's constants to start from (m,), default law.constants().
    params: {"c": the law's constants (m,), MPa or dimensionless as FEBio's; "k": its bulk
      modulus, MPa}.
    """

    name: str
    mesh: Mesh
    law: object
    elements: np.ndarray
    fibers: np.ndarray | None = None
    constants: np.ndarray | None = None
    multiplier_slots = ()
    chunked_kernel = True

    def __post_init__(self):
        m = self.mesh
        el = np.asarray(self.elements, np.int64)
        hexes = m.hexes[el]
        grad_n, dv, _ = hex_geometry(m.nodes, hexes)
        n_fib = max(self.law.n_fibers, 1)
        a0 = np.zeros((len(el), 8, n_fib, 3))
        if self.law.n_fibers:
            a0 = np.asarray(self.fibers, np.float64).reshape(len(el), 8, n_fib, 3)
        object.__setattr__(self, "elements", el)
        object.__setattr__(self, "dofs", (3 * hexes[:, :, None] + np.arange(3)).reshape(-1, 24))
        object.__setattr__(self, "params", {"c": (self.law.constants() if self.constants is None
                                                  else np.asarray(self.constants, np.float64)),
                                            "k": np.float64(self.law.k)})
        object.__setattr__(self, "data", {"grad_n": grad_n, "dv": dv, "a0": a0})

    def static_key(self):
        return (self.law.structure(), bool(self.law.uncoupled))

    def _point_energy(self, F, c, a0):
        """W at Gauss points: F (..., 3, 3), a0 (..., n_fib, 3) -> (...)."""
        from eyefem.fem.materials import febio_law_energy
        structure = self.law.structure()
        f = lambda f_, a_: febio_law_energy(structure, f_, c, a_)  # noqa: E731
        lead = F.shape[:-2]
        out = jax.vmap(f)(F.reshape(-1, 3, 3), a0.reshape((-1,) + a0.shape[-2:]))
        return out.reshape(lead)

    def local_energy(self, q_loc, params, data):
        F = deformation_gradient(q_loc.reshape(-1, 8, 3), data["grad_n"])
        dv = data["dv"]
        w = self._point_energy(F, params["c"], data["a0"])
        out = jnp.sum(w * dv, axis=1)
        if self.law.uncoupled:
            out = out + jnp.sum(dv, axis=1) * volumetric_energy(volume_ratio(F, dv),
                                                                params["k"])
        return out

    def local_grad_hess(self, q_loc, params, data):
        """As :meth:`SolidCompressible.local_grad_hess`: the Gauss points' derivatives of
        phi(F) = W(F) + p J(F), p = U'(Jbar) fixed, plus V U''(Jbar) a a^T."""
        from eyefem.fem.materials import febio_law_energy
        G, dv = data["grad_n"], data["dv"]
        F = deformation_gradient(q_loc.reshape(-1, 8, 3), G)
        structure, c = self.law.structure(), params["c"]
        V = jnp.sum(dv, axis=1)
        jbar = volume_ratio(F, dv)
        if self.law.uncoupled:
            kk = jnp.broadcast_to(params["k"], jbar.shape)
            dU = jax.grad(volumetric_energy)
            p = jax.vmap(dU)(jbar, kk)
            ddU = jax.vmap(jax.grad(dU))(jbar, kk)
        else:
            p = jnp.zeros_like(jbar)
            ddU = jnp.zeros_like(jbar)

        def phi(f, a_, p_):
            return febio_law_energy(structure, f, c, a_) + p_ * det3(f)

        over_points = jax.vmap(jax.vmap(lambda f, a_, p_: (
            jax.grad(phi)(f, a_, p_), jax.hessian(phi)(f, a_, p_)), (0, 0, None)), (0, 0, 0))
        P, A = over_points(F, data["a0"], p)
        return _element_grad_hess(P, A, F, G, dv, V, ddU)

    def fields(self, q, params):
        """Per-element fields as :meth:`SolidCompressible.fields`."""
        F = deformation_gradient(jnp.asarray(np.asarray(q)[self.dofs]).reshape(-1, 8, 3),
                                 self.data["grad_n"])
        dv = self.data["dv"]
        P = jax.grad(lambda f: jnp.sum(self._point_energy(f, params["c"], self.data["a0"])))(F)
        J = det3(F)
        p = (jax.vmap(jax.grad(volumetric_energy))(volume_ratio(F, dv), jnp.broadcast_to(
            params["k"], (F.shape[0],))) if self.law.uncoupled else jnp.zeros(F.shape[0]))
        sig = jnp.einsum("egij,egkj->egik", P, F) / J[..., None, None] \
            + p[:, None, None, None] * jnp.eye(3)
        E = 0.5 * (jnp.einsum("egki,egkj->egij", F, F) - jnp.eye(3))
        return element_fields(np.asarray(sig), np.asarray(J), np.asarray(0.5 * p),
                              np.asarray(E), np.asarray(dv))
