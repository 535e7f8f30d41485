"""Stability of a converged state: the eigenvalues of the constrained tangent nearest zero.

An equilibrium q of the total energy is stable when the second variation is positive on
every admissible direction: displacements zero on the prescribed dofs that keep the
linearised constraints (B^T x = 0: each Q1P0 element's volume). The eigenpairs of the
tangent restricted to that space,

    K phi + B psi = mu phi,    B^T phi = 0,    phi on the free dofs, |phi| = 1,

with K the exact tangent of Newton's method (follower pressures, a closed cavity's
rank-one terms and the contacts' curvature included), are the stiffnesses of the state's
modes. A negative mu: the state is unstable, a bifurcation or limit point lies behind it
on the load path. A mu falling towards zero along a path: a critical point ahead, with phi
the mode it grows into.

They are found as the eigenvalues of largest magnitude of the inverse operator
S: f -> x of the saddle-point system [[K, B], [B^T, 0]] (x, y) = (f, 0) (ARPACK's
Lanczos iteration, one solve on Newton's factorisation per vector); S is symmetric and
its nonzero eigenvalues are 1 / mu. The mu are in N/mm in the Euclidean metric of the
nodal displacements: their sign and their trend along a path do not depend on that
metric, their size does (it changes with the mesh).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, eigsh

from eyefem.solve.assembly import Assembler
from eyefem.solve.diagnosis import rigid_modes
from eyefem.solve.model import Model, check_x64


class StabilityError(RuntimeError):
    """The eigenvalues could not be found (ARPACK did not converge, too few free dofs)."""


@dataclasses.dataclass(frozen=True)
class Modes:
    """The eigenpairs of the constrained tangent nearest zero, ascending.

    Attributes:
      values: (k,) eigenvalues mu, N/mm.
      shapes: (k, n_dof) mode shapes phi, unit Euclidean norm over the free displacement
        dofs, zero on prescribed dofs and multipliers, sign fixed so that the largest
        component is positive.
      residuals: (k,) |S phi - phi / mu| |mu|, relative (the eigenpairs' accuracy).
    """

    values: np.ndarray
    shapes: np.ndarray
    residuals: np.ndarray

    @property
    def stable(self) -> bool:
        """All eigenvalues found are positive."""
        return bool(np.all(self.values > 0))


def lowest_modes(model: Model, q, theta, prescribed: np.ndarray, active=None, k: int = 6, *,
                 beta: float = 1e4, backend: str | None = None, tol: float = 1e-10,
                 seed: int = 0, exclude: np.ndarray | None = None) -> Modes:
    """The k eigenpairs of the constrained tangent at q (n_dof,) of smallest magnitude.

    Args:
      model, q, theta: a converged state (the contact pairing is updated at q).
      prescribed: (n_dof,) bool, the dofs held (those of the stage that reached q).
      active: the energy terms of that stage (None: all).
      k: how many eigenpairs.
      beta: augmentation of the saddle-point solve (any value gives the same pairs).
      backend: linear solver backend (eyefem.solve.linsolve).
      tol: ARPACK's relative accuracy of the eigenvalues.
      seed: seed of the Lanczos start vector (results are reproducible).
      exclude: (n_dof, r) directions the modes are held orthogonal to (R^T phi = 0, say the
        rigid motions of a floating body, whose soft modes would fill the lowest ones);
        constraints only raise eigenvalues, so a state stable without them is stable with.

    Raises StabilityError when ARPACK does not converge or k is not below the number
    of free dofs.
    """
    check_x64()
    q = np.asarray(q, np.float64)
    model = model.update(q, theta)
    asm = Assembler(model, np.asarray(prescribed, bool), beta=beta)
    _, K, B, D, low_rank = asm.assemble(q, theta, active)
    solver = asm.solver(K, B, D, low_rank, backend)
    n = asm.n_p
    if not 0 < k < n - 1:
        raise StabilityError(f"{k} eigenpairs asked of {n} free dofs; ask for 1 to {n - 2}")

    def inverse(f):
        return solver.solve(np.asarray(f, np.float64).ravel())[0]

    apply = inverse
    if exclude is not None:  # S f - W (R^T W)^-1 W^T f, W = S R: the inverse on R^T x = 0
        R = np.asarray(exclude, np.float64).reshape(model.n_dof, -1)[asm.free_primal]
        W = np.stack([inverse(R[:, j]) for j in range(R.shape[1])], axis=1)
        G = np.linalg.inv(R.T @ W)

        def apply(f):
            x = inverse(f)
            return x - W @ (G @ (W.T @ np.ravel(f)))

    op = LinearOperator((n, n), matvec=apply, dtype=np.float64)
    v0 = np.random.default_rng(seed).standard_normal(n)
    try:
        nu, X = eigsh(op, k=k, which="LM", tol=tol, v0=v0, ncv=min(n, max(2 * k + 1, 20)))
    except ArpackNoConvergence as exc:
        raise StabilityError(f"ARPACK found {len(exc.eigenvalues)} of {k} eigenpairs; ask "
                             "for fewer (k) or a looser tol") from None
    if np.any(nu == 0):
        raise StabilityError("a zero eigenvalue of the inverse tangent: ask for fewer pairs")
    mu = 1.0 / nu
    order = np.argsort(mu)
    mu, X = mu[order], X[:, order]
    residuals = np.array([np.linalg.norm(apply(X[:, j]) - nu[order][j] * X[:, j])
                          / abs(nu[order][j]) for j in range(k)])
    shapes = np.zeros((k, model.n_dof))
    for j in range(k):
        x = X[:, j] / np.linalg.norm(X[:, j])
        x = x * np.sign(x[np.argmax(np.abs(x))])
        shapes[j] = asm.expand(x, np.zeros(asm.n_m))
    return Modes(mu, shapes, residuals)


def rigid_motions(model: Model, q) -> np.ndarray:
    """The six rigid motions (6, n_dof) of the mesh's nodes at their positions in q
    (zero on every other dof): three translations, three rotations about the centroid."""
    n = model.mesh.n_nodes
    out = np.zeros((6, model.n_dof))
    x = model.mesh.nodes + np.asarray(q)[: 3 * n].reshape(n, 3)
    out[:, : 3 * n] = rigid_modes(x).reshape(6, -1)
    return out


def rigid_shares(modes: Modes, rigid: np.ndarray, prescribed: np.ndarray) -> np.ndarray:
    """The share (k,) of each mode's squared norm on the free dofs that rigid motions
    (r, n_dof) of the mesh make up (1: a rigid motion)."""
    free = ~np.asarray(prescribed, bool)
    basis = np.linalg.qr(rigid[:, free].T)[0]
    return np.sum((modes.shapes[:, free] @ basis) ** 2, axis=1)


def stage_end(model: Model, q, theta, prescribed: np.ndarray, active=None, k: int = 3,
              **kw) -> dict:
    """The stability record of a stage's end state (a run's summary.json): whether the
    k eigenvalues nearest zero are positive, the lowest (N/mm) and its mode's rigid
    share (on a mesh; None without one). kw: lowest_modes's."""
    modes = lowest_modes(model, q, theta, prescribed, active, k, **kw)
    share = None
    if model.mesh is not None:
        share = float(rigid_shares(modes, rigid_motions(model, q), prescribed)[0])
    return {"stable": modes.stable, "lowest_eigenvalue_N_per_mm": float(modes.values[0]),
            "lowest_mode_rigid_share": share}
