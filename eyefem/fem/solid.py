"""The Q1P0 mixed hexahedron for incompressible hyperelasticity (Total Lagrangian).

Element energy (seed 4.1), 2x2x2 Gauss quadrature:

    Pi_e = integral over V0_e of [ W(I1bar, I2bar) + 2 lambda_e (J - 1) ] dV0     [N mm]

with trilinear displacements (8 nodes x 3 dofs) and one constant Lagrange multiplier
lambda_e per element (MPa). The Cauchy stress is sigma = J^-1 (dW/dF) F^T + 2 lambda I,
so the hydrostatic pressure is p = -2 lambda (at J = 1).

Local dof order: u[a, i] for node a = 0..7, component i = 0..2 (24), then lambda (1).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.materials import strain_energy
from eyefem.fem.mesh import Mesh, hex_geometry
from eyefem.fem.terms import Term, condense

N_LOCAL = 25


def cofactor(F):
    """cof F = det(F) F^-T of matrices F (..., 3, 3), closed form (each entry a 2 x 2 minor).

    Batched 3 x 3 determinants and inverses through ``jnp.linalg`` go through an LU
    factorisation per matrix: on the CPU they took 0.028 s of the Q1P0 tangent kernel's
    0.2 s for 96,000 Gauss points (12,000 hexahedra), the minors 0.008 s
    (docs/performance.md, "The kernels' determinants and chunks")."""
    rows = []
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        rows.append(jnp.stack([F[..., i1, (j + 1) % 3] * F[..., i2, (j + 2) % 3]
                               - F[..., i1, (j + 2) % 3] * F[..., i2, (j + 1) % 3]
                               for j in range(3)], axis=-1))
    return jnp.stack(rows, axis=-2)


def det3(F, cof=None):
    """det F (...,) of matrices F (..., 3, 3): the expansion along the first row, with
    ``cof`` = :func:`cofactor` (F) where the caller has it."""
    if cof is not None:
        return jnp.sum(F[..., 0, :] * cof[..., 0, :], axis=-1)
    return (F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
            + F[..., 0, 1] * (F[..., 1, 2] * F[..., 2, 0] - F[..., 1, 0] * F[..., 2, 2])
            + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0]))


def reduced_invariants(F):
    """I1bar, I2bar and J of deformation gradients F (..., 3, 3)."""
    J = jnp.linalg.det(F)
    C = jnp.swapaxes(F, -1, -2) @ F
    i1 = jnp.trace(C, axis1=-2, axis2=-1)
    i2 = 0.5 * (i1 * i1 - jnp.sum(C * C, axis=(-2, -1)))
    return J ** (-2.0 / 3.0) * i1, J ** (-4.0 / 3.0) * i2, J


def point_energy(F, lam, coeffs):
    """Energy density W(F) + 2 lambda (J - 1) at one point, MPa.

    Args: F (3, 3); lam scalar, MPa; coeffs (4, 4) c_rs, MPa.
    """
    i1b, i2b, J = reduced_invariants(F)
    return strain_energy(i1b, i2b, coeffs) + 2.0 * lam * (J - 1.0)


def deformation_gradient(u_e, grad_n):
    """F (n_elem, 8, 3, 3) from element displacements (n_elem, 8, 3) and dN/dX (n_elem, 8, 8, 3)."""
    return jnp.eye(3) + jnp.einsum("eai,egaj->egij", u_e, grad_n)


_point_grad = jax.vmap(jax.vmap(jax.grad(point_energy, argnums=0), (0, None, None)), (0, 0, 0))


def invariant_energy(inv, lam, coeffs):
    """The point energy of :func:`point_energy` as a function of the unreduced invariants
    inv = (I1, I2, J) (3,): W(J^-2/3 I1, J^-4/3 I2) + 2 lambda (J - 1), MPa."""
    i1, i2, J = inv[0], inv[1], inv[2]
    return strain_energy(J ** (-2.0 / 3.0) * i1, J ** (-4.0 / 3.0) * i2, coeffs) + 2.0 * lam * (J - 1.0)


def element_coeffs(coeffs, data):
    """The c_rs tables (n, 4, 4), MPa, of the elements of ``data``: their material's
    (coeffs[data["mat"]]) or, with data["mix"] (n, n_materials) volume fractions, the
    fractions' weighted sum of the materials' tables. W is linear in c_rs, so an element cut
    by a tissue boundary stores f_a W_a + f_b W_b: the Voigt mixture of the tissues'
    energies in the proportions of its volume (coeffs: (n_materials, 4, 4))."""
    if "mix" in data:
        return jnp.einsum("et,trs->ers", data["mix"], coeffs)
    return coeffs[data["mat"]]


KERNEL_CHUNK = {"cpu": 250}
"""Elements per chunk of the Q1P0 tangent kernel, per JAX backend (absent: one chunk). On
the CPU the kernel's intermediates (per Gauss point: 8 x 24 x 24 and the like) of 12,000
elements at once took about 300 MB more at the peak than chunks evaluated in turn
(``jax.lax.map``); chunks of 250 elements, whose intermediates stay in the caches, took
0.13-0.19 s on the default eye (11,862 hexahedra) where chunks of 1,000 took 0.26-0.31 s
(medians of three alternating runs; docs/performance.md, "The kernels' determinants and
chunks")."""


def chunked(fn, data, dofs, chunk: int | None):
    """``fn(data, dofs)`` evaluated over chunks of ``chunk`` items in turn (jax.lax.map),
    the outputs concatenated: the same values with the intermediates of one chunk alive at
    a time. data: arrays with the items on their first axis; dofs (n, k). The last chunk is
    padded by repeating the last item (its results are dropped)."""
    n = dofs.shape[0]
    if not chunk or n <= chunk:
        return fn(data, dofs)
    m = -(-n // chunk)
    pad = m * chunk - n

    def split(a):
        a = jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]) if pad else a
        return a.reshape((m, chunk) + a.shape[1:])

    out = jax.lax.map(lambda xs: fn(*xs), (jax.tree_util.tree_map(split, data), split(dofs)))
    return jax.tree_util.tree_map(lambda a: a.reshape((m * chunk,) + a.shape[2:])[:n], out)


def chunked_sum(fn, data, dofs, chunk: int | None):
    """``fn(data, dofs)``, a sum over the items (a residual, a tangent-vector product, a
    design derivative: any pytree), accumulated over chunks of ``chunk`` items in turn
    (jax.lax.scan) and the remainder: the same value to roundoff, with the intermediates of
    one chunk alive at a time. data: arrays with the items on their first axis; dofs (n, k)."""
    n = dofs.shape[0]
    if not chunk or n <= chunk:
        return fn(data, dofs)
    m = n // chunk
    cut = m * chunk

    def head(a):
        return a[:cut].reshape((m, chunk) + a.shape[1:])

    def tail(a):
        return a[cut:]

    shape = jax.eval_shape(fn, jax.tree_util.tree_map(lambda a: a[:chunk], data), dofs[:chunk])
    zero = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shape)

    def add(total, xs):
        return jax.tree_util.tree_map(jnp.add, total, fn(*xs)), None

    total, _ = jax.lax.scan(add, zero, (jax.tree_util.tree_map(head, data), head(dofs)))
    if cut < n:
        total = jax.tree_util.tree_map(jnp.add, total, fn(jax.tree_util.tree_map(tail, data),
                                                          tail(dofs)))
    return total


_inv_grad_hess = jax.vmap(jax.vmap(
    lambda inv, lam, c: (jax.grad(invariant_energy)(inv, lam, c),
                         jax.hessian(invariant_energy)(inv, lam, c)), (0, None, None)), (0, 0, 0))


@dataclasses.dataclass(frozen=True, eq=False)
class SolidQ1P0(Term):
    """Q1P0 incompressible hyperelastic elements of a mesh (all materials in one term).

    Args:
      name: term name.
      mesh: the mesh; element e uses material ``mesh.material_ids[e]``, or, where the mesh
        has ``material_fractions``, the tissues' coefficient tables weighted by the
        element's volume fractions (:func:`element_coeffs`).
      coeffs: (n_materials, 4, 4) c_rs tables in MPa, indexed like ``mesh.materials``.
      multiplier_offset: global dof index of lambda_0 (lambda_e = offset + e).
      elements: optional subset of element ids (default all).
    """

    name: str
    mesh: Mesh
    coeffs: np.ndarray
    multiplier_offset: int
    elements: np.ndarray | None = None
    multiplier_slots = (24,)
    chunked_kernel = True  # data holds per-element arrays only (see :func:`chunked`)

    def __post_init__(self):
        m = self.mesh
        el = np.arange(m.n_elem) if self.elements is None else np.asarray(self.elements)
        hexes = m.hexes[el]
        grad_n, dv, _ = hex_geometry(m.nodes, hexes)
        udofs = (3 * hexes[:, :, None] + np.arange(3)).reshape(-1, 24)
        dofs = np.concatenate([udofs, (self.multiplier_offset + np.arange(len(el)))[:, None]], 1)
        object.__setattr__(self, "elements", el)
        object.__setattr__(self, "dofs", dofs)
        object.__setattr__(self, "params", {"coeffs": np.asarray(self.coeffs, dtype=np.float64)})
        data = {"grad_n": grad_n, "dv": dv, "mat": m.material_ids[el]}
        if m.material_fractions is not None:
            data["mix"] = m.material_fractions[el]
        object.__setattr__(self, "data", data)

    def local_energy(self, q_loc, params, data):
        u = q_loc[:, :24].reshape(-1, 8, 3)
        lam = q_loc[:, 24]
        F = deformation_gradient(u, data["grad_n"])
        c = element_coeffs(params["coeffs"], data)
        e = jax.vmap(jax.vmap(point_energy, (0, None, None)), (0, 0, 0))(F, lam, c)
        return jnp.sum(e * data["dv"], axis=1)

    def local_grad_hess(self, q_loc, params, data):
        """Gradients (n, 25) and Hessians (n, 25, 25) (see ``_blocks``)."""
        gu, gl, kuu, kul = self._blocks(q_loc, params, data)
        n = q_loc.shape[0]
        H = jnp.zeros((n, 25, 25), q_loc.dtype)
        H = H.at[:, :24, :24].set(kuu).at[:, :24, 24].set(kul).at[:, 24, :24].set(kul)
        return jnp.concatenate([gu, gl[:, None]], axis=1), H

    def grad_hess_condensed(self, q, params, data, dofs, beta):
        def one(data, dofs):
            gu, gl, kuu, kul = self._blocks(q[dofs], params, data)
            return (jnp.concatenate([gu, gl[:, None]], axis=1),) + condense(kuu, kul, beta)
        chunk = KERNEL_CHUNK.get(jax.default_backend()) if self.chunked_kernel else None
        return chunked(one, data, dofs, chunk)

    def _blocks(self, q_loc, params, data):
        """Blocks g_u (n, 24), g_lambda (n,), K_uu (n, 24, 24), K_ulambda (n, 24).

        The energy density is a function of the invariants I = (I1, I2, J) of F; its
        derivatives W_a and W_ab (3 and 3 x 3) come from autodiff at each Gauss point, and
        the element blocks from the closed-form derivatives of the invariants, contracted
        with the shape function gradients G (dN_a/dX_J) without forming d2W/dF2:

            dI1/dF = 2 F,  dI2/dF = 2 (I1 F - F C),  dJ/dF = J F^-T,
            K = sum_ab W_ab v_a v_b^T + sum_a W_a G^T (d2I_a/dF2) G

        with v_a = G^T dI_a/dF (24,); the second derivatives of the invariants are sums of
        Kronecker products of 8 x 8 and 3 x 3 matrices and of rank-one terms (about 3x
        faster than forward-over-reverse d2W/dF2 and its contraction).
        """
        u = q_loc[:, :24].reshape(-1, 8, 3)
        lam = q_loc[:, 24]
        G, dv = data["grad_n"], data["dv"]  # (n, 8 gauss, 8 nodes, 3), (n, 8)
        F = deformation_gradient(u, G)
        c = element_coeffs(params["coeffs"], data)
        C = jnp.swapaxes(F, -1, -2) @ F
        I1 = jnp.trace(C, axis1=-2, axis2=-1)
        I2 = 0.5 * (I1 * I1 - jnp.sum(C * C, axis=(-2, -1)))
        cof = cofactor(F)  # J F^-T
        J = det3(F, cof)
        Finv = jnp.swapaxes(cof, -1, -2) / J[..., None, None]
        dW, ddW = _inv_grad_hess(jnp.stack([I1, I2, J], axis=-1), lam, c)  # (n, 8, 3), (n, 8, 3, 3)
        W1, W2, WJ = dW[..., 0], dW[..., 1], dW[..., 2]
        FC = F @ C
        P = (2.0 * W1 + 2.0 * W2 * I1)[..., None, None] * F - 2.0 * W2[..., None, None] * FC \
            + WJ[..., None, None] * cof
        gu = jnp.einsum("eg,egij,egaj->eai", dv, P, G).reshape(-1, 24)
        gl = 2.0 * jnp.sum(dv * (J - 1.0), axis=1)
        kul = 2.0 * jnp.einsum("eg,egij,egaj->eai", dv, cof, G).reshape(-1, 24)
        # v_a = G^T dI_a/dF, per Gauss point (n, 8, 8 nodes, 3)
        vF = jnp.einsum("egij,egaj->egai", F, G)
        vFC = jnp.einsum("egij,egaj->egai", FC, G)
        u_ = jnp.einsum("egji,egaj->egai", Finv, G)  # G F^-1: dJ/dF projected, over J
        V = jnp.stack([2.0 * vF, 2.0 * (I1[..., None, None] * vF - vFC),
                       J[..., None, None] * u_], axis=2).reshape(*vF.shape[:2], 3, 24)
        n = F.shape[0]
        K = jnp.einsum("eg,egpA,egpq,egqB->eAB", dv, V, ddW, V)
        # second derivatives of the invariants, weighted by W_a dv
        gram = jnp.einsum("egaj,egbj->egab", G, G)
        gcg = jnp.einsum("egaj,egjl,egbl->egab", G, C, G)
        w1, w2, wj = dv * W1, dv * W2, dv * WJ * J
        iso = jnp.einsum("eg,egab->eab", 2.0 * w1 + 2.0 * w2 * I1, gram) \
            - 2.0 * jnp.einsum("eg,egab->eab", w2, gcg)  # times delta_ik
        K4 = jnp.einsum("eab,ik->eaibk", iso, jnp.eye(3))
        K4 = K4 - 2.0 * jnp.einsum("eg,egab,egik->eaibk", w2, gram, F @ jnp.swapaxes(F, -1, -2))
        K4 = K4 + 4.0 * jnp.einsum("eg,egai,egbk->eaibk", w2, vF, vF)
        K4 = K4 - 2.0 * jnp.einsum("eg,egbi,egak->eaibk", w2, vF, vF)
        K4 = K4 + jnp.einsum("eg,egai,egbk->eaibk", wj, u_, u_)
        K4 = K4 - jnp.einsum("eg,egak,egbi->eaibk", wj, u_, u_)
        kuu = K + K4.reshape(n, 24, 24)
        return gu, gl, kuu, kul

    def fields(self, q, params):
        """Per-element post-processing from the global dof vector q (numpy).

        Returns dict of (n_elem, ...) arrays averaged over the Gauss points: 'cauchy'
        (3, 3) MPa, 'von_mises' MPa, 'pressure' (-tr sigma / 3) MPa, 'lambda' MPa, 'J',
        'green_lagrange' E = (F^T F - I) / 2 (3, 3) and its largest eigenvalue
        'max_principal_strain' (dimensionless).
        """
        return _fields(q[self.dofs], params, self.data)


def point_fields(F, lam, c):
    """Cauchy stress sigma (n, 8, 3, 3) MPa, J (n, 8), lambda (n,) and Green-Lagrange
    strain (n, 8, 3, 3) at the Gauss points from their deformation gradients F (n, 8, 3, 3),
    the elements' multipliers lam (n,) and coefficient tables c (n, 4, 4)."""
    P = _point_grad(F, lam, c)
    J = det3(F)
    sig = jnp.einsum("egij,egkj->egik", P, F) / J[..., None, None]
    E = 0.5 * (jnp.einsum("egki,egkj->egij", F, F) - jnp.eye(3))
    return sig, J, lam, E


@jax.jit
def _fields_jit(q_loc, c, grad_n):
    return point_fields(deformation_gradient(q_loc[:, :24].reshape(-1, 8, 3), grad_n),
                        q_loc[:, 24], c)


def element_fields(sig, J, lam, E, dv) -> dict:
    """The fields of :meth:`SolidQ1P0.fields` from :func:`point_fields`' Gauss-point values
    (numpy), averaged with the points' volumes dv (n, 8)."""
    w = dv / dv.sum(axis=1, keepdims=True)
    s = np.einsum("eg,egij->eij", w, sig)
    p = -np.trace(s, axis1=1, axis2=2) / 3.0
    dev = s + p[:, None, None] * np.eye(3)
    vm = np.sqrt(1.5 * np.sum(dev * dev, axis=(1, 2)))
    E = np.einsum("eg,egij->eij", w, E)
    return {"cauchy": s, "von_mises": vm, "pressure": p, "lambda": lam,
            "J": np.einsum("eg,eg->e", w, J), "green_lagrange": E,
            "max_principal_strain": np.linalg.eigvalsh(E)[:, -1]}


def _fields(q_loc, params, data):
    return element_fields(*(np.asarray(a) for a in _fields_jit(
        q_loc, element_coeffs(params["coeffs"], data), data["grad_n"])), data["dv"])
