"""What a tangent check returns, and the helpers checks share (finite differences, random
deformations)."""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

HAND_TOL = 1e-8
FD_TOL = 1e-5


@dataclasses.dataclass(frozen=True)
class CheckData:
    """What a check returns: residuals (n,), tangents (n, n), the residual function and state x (n,)."""

    r_ad: np.ndarray
    r_hand: np.ndarray
    K_ad: np.ndarray
    K_hand: np.ndarray
    r_fun: Callable[[np.ndarray], np.ndarray]
    x: np.ndarray
    state: str = ""


@dataclasses.dataclass(frozen=True)
class TangentCheck:
    """Relative differences for one term."""

    name: str
    r_hand: float
    K_hand: float
    K_fd: float
    state: str

    @property
    def passed(self) -> bool:
        return self.r_hand <= HAND_TOL and self.K_hand <= HAND_TOL and self.K_fd <= FD_TOL


def relative_difference(a, b) -> float:
    """|a - b| / |b| (Frobenius / Euclidean norms)."""
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(b), 1e-300))


def fd_tangent(r_fun, x, h=1e-6):
    """Central finite-difference Jacobian (n, n) of r_fun at x, step h * max(1, |x|_inf)."""
    step = h * max(1.0, float(np.abs(x).max()))
    cols = []
    for j in range(len(x)):
        e = np.zeros_like(x)
        e[j] = step
        cols.append((np.asarray(r_fun(x + e)) - np.asarray(r_fun(x - e))) / (2 * step))
    return np.stack(cols, axis=1)


def random_deformation(rng, scale=0.5):
    """A random rotation times a stretch of order 1.5 (not isochoric): F (3, 3)."""
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))
    U = np.diag(1.0 + scale * rng.uniform(0.2, 1.0, 3)) + 0.1 * rng.standard_normal((3, 3))
    return Q @ (0.5 * (U + U.T))


def row_hessians(f: Callable, x) -> np.ndarray:
    """The diagonal blocks (n, k, k) of the Hessian of a scalar JAX function ``f`` of x (n,
    k) in which no two rows are coupled (a sum over contact pairs or points, each of one row
    of local dofs): k Hessian-vector products, where the whole Hessian is (n, k, n, k).
    Block i's column j is row i of the product with e_j put in every row."""
    import jax
    import jax.numpy as jnp

    x = jnp.asarray(x)
    grad = jax.grad(f)
    column = jax.jit(lambda v: jax.jvp(grad, (x,), (v,))[1])
    return np.stack([np.asarray(column(jnp.zeros_like(x).at[:, j].set(1.0)))
                     for j in range(x.shape[1])], axis=2)
