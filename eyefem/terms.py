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
      dynamic: see below.

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

    def low_rank_values(self, q, params) -> list:
        """The scalars c_j(q) whose gradients are the low-rank vectors v_j (same order; a
        cavity's volume, mm^3), for the solver's second-order restoration along a Newton
        step (see ``eyefem.solver``). Default: none."""
        return []

    def report(self, q: np.ndarray, params) -> dict:
        """Scalar outputs logged and written to CSV every step (e.g. cavity pressure)."""
        return {}

    def point_fields(self, q: np.ndarray, params, n_nodes: int) -> dict:
        """Nodal fields (n_nodes, ...) for the VTU output (e.g. contact pressure)."""
        return {}

    def static_key(self) -> tuple:
        """Hashable configuration that changes the compiled code (not the arrays)."""
        return ()

    def update(self, q: np.ndarray, params) -> "Term":
        """Host-side update between Newton iterations (contact search); default: self."""
        return self


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
class TwistSpring(Term):
    """A torsional spring on the mean twist of a ring of nodes about the z axis.

    twist = sum_i (X_i x u_i)_z / sum_i rho_i^2 (rad; rho_i = distance of X_i from the
    axis: the rigid rotation that best fits u), energy 1/2 k twist^2. A deformation
    with no net twist (any symmetric one) stores nothing and feels no force.

    Args: name; nodes (n,) node ids; xyz (n, 3) their reference positions, mm;
      k: torsional stiffness, N mm/rad (params {"k"}).
    """

    name: str
    nodes: np.ndarray
    xyz: np.ndarray
    k: float = 1.0

    def __post_init__(self):
        n = np.asarray(self.nodes, np.int64).ravel()
        X = np.asarray(self.xyz, np.float64).reshape(len(n), 3)
        rho2 = float(np.sum(X[:, 0] ** 2 + X[:, 1] ** 2))
        if self.k < 0 or not rho2 > 0:
            raise ValueError(f"twist spring '{self.name}': k = {self.k} N mm/rad (must be >= 0) "
                             f"on {len(n)} nodes at sum rho^2 = {rho2} mm^2 (must be > 0)")
        object.__setattr__(self, "dofs", (3 * n[:, None] + np.arange(3)).reshape(1, -1))
        object.__setattr__(self, "params", {"k": float(self.k)})
        # d twist / d u: (-y, x, 0) / sum rho^2 per node
        w = np.stack([-X[:, 1], X[:, 0], np.zeros(len(n))], axis=1) / rho2
        object.__setattr__(self, "data", {"w": w.reshape(1, -1)})

    def twist(self, q):
        """Mean twist of the ring (rad) at q (n_dof,)."""
        return float(np.asarray(q)[self.dofs[0]] @ self.data["w"][0])

    def local_energy(self, q_loc, params, data):
        t = jnp.sum(q_loc * data["w"], axis=1)
        return 0.5 * params["k"] * t * t

    def report(self, q, params):
        t = self.twist(q)
        return {"twist_deg": float(np.degrees(t)), "moment_Nmm": params["k"] * t}


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
