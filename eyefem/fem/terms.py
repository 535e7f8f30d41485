"""Energy terms: the pieces the total potential energy is summed from.

A term is a sum of local energies ``e_i(q[dofs[i]], params, data_i)``: one per element,
face, bar or contact pair. JAX differentiates the local energy; the assembler
scatters local gradients (n_items, k) and Hessians (n_items, k, k) into the global
residual and sparse tangent through the term's ``dofs`` (n_items, k).

``params`` is the term's slice of the design pytree ``theta`` (differentiable:
material constants, load magnitudes, suture geometry...); ``data`` holds fixed arrays
(reference geometry, quadrature). Both are passed as arguments, never closed over, so
a compiled kernel is reused for every value.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def condense(Hpp, b, beta):
    """Augment primal blocks Hpp (n, k, k) by d b b^T, d = beta |mean diag Hpp| / |b|^2 (n,)."""
    diag = jnp.abs(jnp.einsum("nii->n", Hpp)) / Hpp.shape[1]
    d = beta * diag / jnp.maximum(jnp.einsum("ni,ni->n", b, b), 1e-300)
    return Hpp + d[:, None, None] * b[:, :, None] * b[:, None, :], b, d


class Term(abc.ABC):
    """Base class of every energy term.

    Attributes (set by subclasses):
      name: unique name; the key of this term's params in ``theta``.
      dofs: (n_items, k) global dof indices each local energy touches.
      params: default parameter pytree (MPa, mm, N...).
      data: dict of fixed arrays with leading axis n_items (or global).
      multiplier_slots: local positions (within k) that hold Lagrange multipliers
        (zero diagonal block; condensed by the saddle-point solver).
      dynamic, contact: see below.

    Terms whose energy is not a sum of independent local energies (a fluid cavity:
    the pressure depends on the whole enclosed volume) override ``energy`` and
    ``grad_hess`` (which see the global q) and put the coupling in ``low_rank``.
    """

    name: str
    dofs: np.ndarray
    params: Any
    data: dict
    multiplier_slots: tuple[int, ...] = ()
    dynamic: bool = False
    """True if ``dofs`` change between Newton iterations (contact pairing): assembled
    without a precomputed pattern."""
    contact: bool = False
    """True for a contact term (penalty contact, analytic or re-paired): its force switches
    on and off with the state, so a load step may not start from the previous step's
    tangent (``NewtonOptions.tangent_predictor``)."""
    pressure_stiffness: bool = False
    """True if the Hessian is a follower pressure's load stiffness (-p d2V/dq2, a closed
    cavity or a pressure load): the Newton solver leaves it out of its tangent far from
    convergence (``NewtonOptions.pressure_stiffness``)."""

    @abc.abstractmethod
    def local_energy(self, q_loc, params, data):
        """Local energies (n_items,) from local dof values q_loc (n_items, k)."""

    def local_grad_hess(self, q_loc, params, data):
        """Local gradients (n_items, k) and Hessians (n_items, k, k).

        The default differentiates ``local_energy``: items are independent, so one
        forward-over-reverse product per local direction gives column j of every
        item's Hessian at once (k products, no per-item parameter slicing).
        """
        def grad(x):
            return jax.grad(lambda y: jnp.sum(self.local_energy(y, params, data)))(x)

        g = grad(q_loc)
        k = q_loc.shape[1]
        basis = jnp.broadcast_to(jnp.eye(k, dtype=q_loc.dtype)[:, None, :], (k,) + q_loc.shape)
        cols = jax.vmap(lambda v: jax.jvp(grad, (q_loc,), (v,))[1])(basis)  # (k, n, k)
        return g, jnp.transpose(cols, (1, 2, 0))

    def energy(self, q, params, data, dofs):
        """Total energy of the term (scalar) from the global dof vector q (n_dof,)."""
        return jnp.sum(self.local_energy(q[dofs], params, data))

    def grad_hess(self, q, params, data, dofs):
        """Local gradients and Hessians from the global dof vector q (n_dof,)."""
        return self.local_grad_hess(q[dofs], params, data)

    def grad_hess_condensed(self, q, params, data, dofs, beta):
        """Local gradients with the primal Hessian block augmented by the multiplier column.

        Returns g (n, k), H_pp + d b b^T (n, k_p, k_p), b (n, k_p), d (n,), where b is the
        multiplier column of the local Hessian and d = beta |mean diag H_pp| / |b|^2 (see
        linsolve); b and d are None for a term without multipliers.
        """
        g, H = self.grad_hess(q, params, data, dofs)
        if not self.multiplier_slots:
            return g, H, None, None
        m = self.multiplier_slots[0]
        prim = np.array([i for i in range(H.shape[1]) if i != m])
        return (g,) + condense(H[:, prim][:, :, prim], H[:, prim, m], beta)

    def low_rank(self, q, params, data, dofs):
        """Rank-k parts of the Hessian not in the local blocks: list of (alpha, vector (n_dof,)).

        The tangent is sum(local blocks) + sum alpha_j v_j v_j^T. Default: none.
        """
        return []

    grad_hess_gauss_newton = None
    """Penalty-contact terms: ``f(q, params, data, dofs) -> (g (n, k), H (n, k, k))``, the
    local gradients and the Hessians without the contact surface's curvature term (the
    Gauss-Newton part, positive semidefinite), for the solver's modified tangent. None
    (default): the term has no such approximation."""

    def gap_linearisation(self, q_loc, dq_loc, params, data):
        """Penalty-contact terms (energy 1/2 alpha p(g)^2 per item, p a smoothed <-g>):
        the gaps g (n,) mm at q_loc, their change along the step dq_loc to first order
        (n,), their gradients (n, k) and the exact gaps at q_loc + dq_loc (n,), for the
        Newton solver's active-set look-ahead (``eyefem.solve.solver``). None (default): not
        such a term."""
        return None

    def low_rank_values(self, q, params) -> list:
        """The scalars c_j(q) whose gradients are the low-rank vectors v_j (same order; a
        cavity's volume, mm^3), for the solver's second-order restoration along a Newton
        step (see ``eyefem.solve.solver``). Default: none."""
        return []

    def report(self, q: np.ndarray, params) -> dict:
        """Scalar outputs logged and written to CSV every step (e.g. cavity pressure)."""
        return {}

    def point_fields(self, q: np.ndarray, params, n_nodes: int) -> dict:
        """Nodal fields (n_nodes, ...) for the VTU output (e.g. contact pressure)."""
        return {}

    def geometry(self, q: np.ndarray, params) -> tuple | None:
        """This term's own shape for the VTU output, in the current configuration:
        (points (n, 3) mm, meshio cell type, cells (m, k), cell data name -> (m,)), e.g.
        a rigid buckle's surface or the sutures as lines with their forces; None
        (default): nothing beyond the mesh."""
        return None

    def static_key(self) -> tuple:
        """Hashable configuration that changes the compiled code (not the arrays)."""
        return ()

    def update(self, q: np.ndarray, params) -> "Term":
        """Host-side update between Newton iterations (contact search); default: self."""
        return self


_HOST_KERNELS: dict = {}


def host_kernel(term: Term, method: str):
    """``term.<method>`` compiled (jax.jit), shared by every term of its class and static
    key as the solver's kernels are (eyefem.solve.model.Model._kernel): the method reads
    arrays only from its arguments. For host-side outputs at a state (forces, gaps,
    positions): one small XLA program where eager JAX compiles one per operation on a
    machine's first run."""
    key = (type(term), method, term.static_key())
    fn = _HOST_KERNELS.get(key)
    if fn is None:
        fn = _HOST_KERNELS[key] = jax.jit(getattr(term, method))
    return fn


@dataclasses.dataclass(frozen=True)
class NodalForce(Term):
    """Dead nodal loads: energy -sum f . u over the loaded dofs.

    Args:
      name: term name.
      dofs: (n,) global dof indices.
      params: {"f": (n,) force per dof, N}.
    """

    name: str
    dofs: np.ndarray
    params: dict
    data: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "dofs", np.asarray(self.dofs, dtype=np.int64).reshape(-1, 1))

    def local_energy(self, q_loc, params, data):
        return -q_loc[:, 0] * params["f"]


@dataclasses.dataclass(frozen=True)
class NodeSprings(Term):
    """Springs tying nodes to their reference positions: energy 1/2 k |u|^2 per node.

    Used with a tiny k to hold bodies that only contact and sutures support (a sponge
    before it touches the sclera): numerical stabilisation, its force is reported so
    that it can be checked to be negligible.

    Args: name; nodes (n,) node ids; k: stiffness per node, N/mm (params {"k"}).
    """

    name: str
    nodes: np.ndarray
    k: float = 1e-6
    params: dict = dataclasses.field(default_factory=dict)
    data: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        n = np.asarray(self.nodes, np.int64).ravel()
        if self.k < 0:
            raise ValueError(f"springs '{self.name}': k = {self.k} N/mm; must be >= 0")
        object.__setattr__(self, "dofs", (3 * n[:, None] + np.arange(3)))
        object.__setattr__(self, "params", {"k": float(self.k)})

    def local_energy(self, q_loc, params, data):
        return 0.5 * params["k"] * jnp.sum(q_loc * q_loc, axis=1)

    def report(self, q, params):
        f = params["k"] * np.linalg.norm(np.asarray(q)[self.dofs], axis=1)
        return {"max_force_N": float(f.max()) if len(f) else 0.0}


@dataclasses.dataclass(frozen=True, eq=False)
class OrbitSpring(Term):
    """Springs on the rigid-body motion of a ring of nodes: its best-fit small rotation
    about the x, y, z axes through the ring's centroid c, its mean lateral (x, y)
    translation (or the translation along two other directions, ``shift_axes``) and its
    mean axial translation (along the normal of those two: z by default).

    rotation theta = I^-1 sum_i r_i x u_i (rad; r_i = X_i - c, I = sum_i |r_i|^2 1 - r_i r_i^T:
    the rigid rotation that best fits u), translation t = mean_i u_i (mm); energy
    1/2 sum_a k_a theta_a^2 + 1/2 k_t (t_x^2 + t_y^2) + 1/2 k_z t_z^2. A deformation with
    no net rotation or shift (any one symmetric about the x = 0 and y = 0 planes, with
    k_z = 0) stores nothing and feels no force.

    Args: name; nodes (n,) node ids; xyz (n, 3) their reference positions, mm;
      k_rot: rotational stiffnesses about x, y, z, N mm/rad (3,); k_trans: lateral
      stiffness, N/mm; k_axial: axial stiffness, N/mm (params {"k": (6,)}: k_rot, k_trans
      twice, k_axial); shift_axes: (2, 3) unit directions of the lateral translation
      (default x and y; a deformable sponge uses its across and along directions, leaving
      free its motion into the sclera).
    """

    name: str
    nodes: np.ndarray
    xyz: np.ndarray
    k_rot: tuple = (1.0, 1.0, 1.0)
    k_trans: float = 0.0
    shift_axes: tuple | None = None
    k_axial: float = 0.0

    def __post_init__(self):
        n = np.asarray(self.nodes, np.int64).ravel()
        axes = np.eye(3)[:2] if self.shift_axes is None else np.asarray(self.shift_axes, float)
        if (axes.shape != (2, 3) or not np.allclose(np.linalg.norm(axes, axis=1), 1.0)
                or np.linalg.norm(np.cross(axes[0], axes[1])) < 1e-6):
            raise ValueError(f"orbit spring '{self.name}': shift_axes = {self.shift_axes}; "
                             "expected two unit, non-parallel vectors (2, 3)")
        r = np.asarray(self.xyz, np.float64).reshape(len(n), 3)
        r = r - r.mean(axis=0)
        inertia = np.sum(r * r) * np.eye(3) - r.T @ r
        k = np.r_[np.asarray(self.k_rot, np.float64).ravel(), self.k_trans, self.k_trans,
                  self.k_axial]
        if len(k) != 6 or np.any(k < 0) or np.linalg.cond(inertia) > 1e12:
            raise ValueError(f"orbit spring '{self.name}': k_rot = {self.k_rot} N mm/rad (three "
                             f"values >= 0), k_trans = {self.k_trans} N/mm and k_axial = "
                             f"{self.k_axial} N/mm (>= 0), on {len(n)} nodes that must not "
                             "lie on one line")
        object.__setattr__(self, "dofs", (3 * n[:, None] + np.arange(3)).reshape(1, -1))
        object.__setattr__(self, "params", {"k": k})
        # d (sum r x u) / du per node: the rows of -[r]x, (3, n, 3)
        z = np.zeros(len(n))
        cross = np.stack([np.stack([z, -r[:, 2], r[:, 1]], 1), np.stack([r[:, 2], z, -r[:, 0]], 1),
                          np.stack([-r[:, 1], r[:, 0], z], 1)])
        rot = np.linalg.solve(inertia, cross.reshape(3, -1))
        normal = np.cross(axes[0], axes[1])
        axes = np.vstack([axes, normal / np.linalg.norm(normal)])
        shift = np.repeat(axes[:, None, :], len(n), axis=1) / len(n)
        modes = np.vstack([rot, shift.reshape(3, -1)])  # (6, 3n): d (theta, t) / du
        object.__setattr__(self, "data", {"modes": modes[None]})

    def motion(self, q):
        """(rotation about x, y, z (rad), translation along the shift axes and the axial
        direction (mm)) at q (6,)."""
        return self.data["modes"][0] @ np.asarray(q)[self.dofs[0]]

    def local_energy(self, q_loc, params, data):
        m = jnp.einsum("emj,ej->em", data["modes"], q_loc)
        return 0.5 * jnp.sum(params["k"] * m * m, axis=1)

    def report(self, q, params):
        m = self.motion(q)
        deg = np.degrees(m[:3])
        return {"twist_deg": float(deg[2]), "tilt_deg": float(np.hypot(deg[0], deg[1])),
                "shift_mm": float(np.hypot(m[3], m[4])), "axial_shift_mm": float(m[5]),
                "moment_Nmm": float(np.linalg.norm(params["k"][:3] * m[:3])),
                "force_N": float(np.linalg.norm(params["k"][3:] * m[3:]))}


@dataclasses.dataclass(frozen=True, eq=False)
class DofForce(Term):
    """A generalised force doing work on one unknown: energy -f * gain * q[dof].

    Used to pull an encircling band with a prescribed tension: the unknown is the
    band's free radial motion (mm) and gain converts it to circumference shortening,
    so f is the tension (N) and the work is tension x shortening.

    Args: name; dof: global dof index; gain: mm of the work-conjugate motion per unit
    of q[dof]; params {"f"}: the force, N.
    """

    name: str
    dof: int
    gain: float = 1.0
    params: dict = dataclasses.field(default_factory=dict)
    data: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if self.dof < 0:
            raise ValueError(f"force '{self.name}': dof {self.dof}; must be >= 0")
        object.__setattr__(self, "dofs", np.array([[int(self.dof)]], np.int64))
        object.__setattr__(self, "params", {"f": 0.0})
        object.__setattr__(self, "data", {"gain": np.full(1, float(self.gain))})

    def local_energy(self, q_loc, params, data):
        return -params["f"] * data["gain"] * q_loc[:, 0]

    def report(self, q, params):
        return {"force_N": float(params["f"]),
                "motion_mm": float(self.gain * np.asarray(q)[self.dof])}
