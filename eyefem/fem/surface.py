"""Surface geometry of bilinear quadrilateral faces and the follower pressure load.

The pressure load is written as a potential: with the current positions x = X + u,

    Pi_p = p * sum_faces V_f,     V_f = 1/3 integral over the face of (x - x0) . n da   [N mm]

where n is the face normal given by the node order (pointing out of the solid). Its
gradient is the seed's follower load r_e = integral N^T p J F^-T n0 dS (the
boundary-line terms of the per-face V_f cancel between neighbouring faces) and its
Hessian the consistent load stiffness, symmetric. This is exact for a closed surface
and for an open one whose boundary is held fixed or slides in planes through x0
(symmetry planes); 2x2 Gauss integrates V_f exactly for bilinear faces.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from eyefem.fem.mesh import Mesh, quad_gauss_points, quad_shape
from eyefem.fem.terms import Term

_XG, _WG = quad_gauss_points()
_N, _DN = quad_shape(_XG)  # (4g, 4a), (4g, 4a, 2)


def face_cone_volume(x, origin):
    """1/3 integral (x - origin) . n da over bilinear faces, exactly.

    Args:
      x: (n_faces, 4, 3) current face node positions, mm.
      origin: (3,) apex of the cone, mm.
    Returns: (n_faces,) signed volumes, mm^3.
    """
    xg = jnp.einsum("ga,fai->fgi", _N, x) - origin
    t1 = jnp.einsum("ga,fai->fgi", _DN[..., 0], x)
    t2 = jnp.einsum("ga,fai->fgi", _DN[..., 1], x)
    return jnp.einsum("g,fgi,fgi->f", _WG, xg, jnp.cross(t1, t2)) / 3.0


def face_normals_area(x):
    """Area-weighted normals (n_faces, 4g, 3) at the 2x2 Gauss points (n da per unit weight)."""
    t1 = np.einsum("ga,fai->fgi", _DN[..., 0], x)
    t2 = np.einsum("ga,fai->fgi", _DN[..., 1], x)
    return np.cross(t1, t2)


def enclosed_volume(nodes, faces):
    """Volume enclosed by a closed face set whose normals point into the enclosed region.

    Args: nodes (n, 3) mm; faces (n_faces, 4). Returns: mm^3 (numpy float).
    """
    return -float(np.sum(face_cone_volume(jnp.asarray(nodes[faces]), jnp.zeros(3))))


def face_dofs(faces):
    """(n_faces, 12) displacement dof indices of quadrilateral faces."""
    return (3 * faces[:, :, None] + np.arange(3)).reshape(-1, 12)


@dataclasses.dataclass(frozen=True, eq=False)
class PressureLoad(Term):
    """Follower pressure p (MPa) on a named face set, pushing against the face normals.

    Args:
      name: term name; params {"p": pressure, MPa}.
      mesh: the mesh holding the face set.
      face_set: name of the face set (normals out of the solid).
      pressure: initial value of p, MPa.
      origin: apex for the cone volumes (a point on every symmetry plane), mm.
    """

    name: str
    mesh: Mesh
    face_set: str
    pressure: float = 0.0
    origin: tuple = (0.0, 0.0, 0.0)

    pressure_stiffness = True

    def __post_init__(self):
        faces = self.mesh.face_set(self.face_set)
        object.__setattr__(self, "dofs", face_dofs(faces))
        object.__setattr__(self, "params", {"p": float(self.pressure)})
        object.__setattr__(self, "data", {"X": self.mesh.nodes[faces],
                                          "origin": np.asarray(self.origin, dtype=np.float64)})

    def local_energy(self, q_loc, params, data):
        x = data["X"] + q_loc.reshape(-1, 4, 3)
        return params["p"] * face_cone_volume(x, data["origin"])

    def point_fields(self, q, params, n_nodes) -> dict:
        """'<name>_pressure_MPa' (n_nodes,): the applied pressure p on loaded nodes, 0
        elsewhere."""
        f = np.zeros(n_nodes)
        f[self.dofs[:, ::3] // 3] = float(params["p"])
        return {f"{self.name}_pressure_MPa": f}
