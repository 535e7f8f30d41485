"""Q1P0 solid whose closed encircling loop is tightened by shortening its rest length.

An encircling band tightened by pulling its ends through a sleeve shortens the material
length of its loop. :class:`ShortenedLoopSolid` models that on a closed ring (no cut,
no ends): the loop's reference configuration is moved toward the optical axis (z) by
d = shortening / (2 pi),

    X_ref = X - d e_rho(X),      e_rho = (x, y, 0) / rho,

which shortens every circumferential fibre, whatever its radius rho, by exactly
``shortening`` (2 pi (rho - d) = 2 pi rho - shortening) and keeps the cross-section.
The elastic energy is the Q1P0 energy of :mod:`eyefem.fem.solid` with the loop's elements
measured from X_ref (deformation gradient dx/dX_ref, volume of X_ref, incompressible
relative to it); x = X + u is unchanged, so u_ref = x - X_ref = u + d e_rho at the nodes.
The shortening (mm) is the term parameter ``shortening`` (differentiable, ramped by a
stage like any parameter); at 0 the term is :class:`eyefem.fem.solid.SolidQ1P0`.

The band tension (N) is the energy's derivative with respect to the shortening at fixed
positions (:meth:`ShortenedLoopSolid.tension`): the work a pull does per mm of loop
taken up, the circumference-averaged hoop force of the loop.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.mesh import element_geometry
from eyefem.fem.solid import SolidQ1P0, _fields


@dataclasses.dataclass(frozen=True, eq=False)
class ShortenedLoopSolid(SolidQ1P0):
    """:class:`eyefem.fem.solid.SolidQ1P0` with a closed loop of elements tightened by
    shortening (params ``shortening``, mm, default 0).

    Args (beyond SolidQ1P0's):
      loop_nodes: node ids of the loop (a closed ring about the z axis, no node on it);
        the elements whose 8 nodes are all loop nodes form the loop.
    """

    loop_nodes: np.ndarray | None = None

    chunked_kernel = False  # data also holds the loop's own arrays (loop_el, loop_X)

    def __post_init__(self):
        super().__post_init__()
        if self.loop_nodes is None:
            raise ValueError(f"term '{self.name}': give loop_nodes, the node ids of the loop")
        m = self.mesh
        loop = np.zeros(m.n_nodes, bool)
        loop[np.asarray(self.loop_nodes, np.int64)] = True
        hexes = m.hexes[self.elements]
        el = np.nonzero(loop[hexes].all(axis=1))[0]
        if len(el) == 0:
            raise ValueError(f"term '{self.name}': no element has all its nodes in loop_nodes")
        X = m.nodes[hexes[el]]  # (m, 8, 3)
        rho = np.hypot(X[..., 0], X[..., 1])
        if rho.min() <= 1e-9 * max(rho.max(), 1.0):
            raise ValueError(f"term '{self.name}': a loop node lies on the z axis (rho = "
                             f"{rho.min():.3g} mm); the loop must encircle the axis")
        e_rho = np.stack([X[..., 0] / rho, X[..., 1] / rho, np.zeros_like(rho)], axis=-1)
        object.__setattr__(self, "params", {**self.params, "shortening": np.float64(0.0)})
        object.__setattr__(self, "data", {**self.data, "loop_el": el, "loop_X": X,
                                          "loop_shift": e_rho / (2 * np.pi)})

    def _referred(self, q_loc, params, data, xp=jnp):
        """(q_loc, data) with the loop's displacements and geometry measured from X_ref."""
        el, shift = data["loop_el"], params["shortening"] * data["loop_shift"]  # (m, 8, 3) mm
        grad_n, dv, _ = element_geometry(data["loop_X"] - shift, xp)
        if xp is np:
            q_loc, g, v = q_loc.copy(), data["grad_n"].copy(), data["dv"].copy()
            q_loc[el, :24] += shift.reshape(-1, 24)
            g[el], v[el] = grad_n, dv
        else:
            q_loc = q_loc.at[el, :24].add(shift.reshape(-1, 24))
            g, v = data["grad_n"].at[el].set(grad_n), data["dv"].at[el].set(dv)
        return q_loc, {**data, "grad_n": g, "dv": v}

    def local_energy(self, q_loc, params, data):
        q_ref, data_ref = self._referred(q_loc, params, data)
        return SolidQ1P0.local_energy(self, q_ref, params, data_ref)

    def _blocks(self, q_loc, params, data):
        q_ref, data_ref = self._referred(q_loc, params, data)
        return SolidQ1P0._blocks(self, q_ref, params, data_ref)

    def fields(self, q, params):
        q_ref, data_ref = self._referred(np.asarray(q)[self.dofs], params, self.data, np)
        return _fields(q_ref, params, data_ref)

    def tension(self, q, params) -> float:
        """Band tension, N: d(elastic energy)/d(shortening) at fixed positions q (n_dof,)."""
        return float(_tension(self, jnp.asarray(q)[self.dofs], params, self.data))


@functools.partial(jax.jit, static_argnums=0)
def _tension(term, q_loc, params, data):
    def energy(s):
        return jnp.sum(term.local_energy(q_loc, {**params, "shortening": s}, data))

    return jax.grad(energy)(params["shortening"])
