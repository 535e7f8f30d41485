"""Surface geometry of bilinear quadrilateral faces and the follower pressure loads.

A follower pressure p (MPa) pushes against the face normals n (given by the node order,
out of the solid). Its nodal forces, on any surface, are

    f_a = -p integral over the current faces of N_a n da                       [N]

(:class:`FollowerPressure`). They derive from a potential only in special cases:

    Pi_p = p * sum_faces V_f,     V_f = 1/3 integral over the face of (x - x0) . n da   [N mm]

(:class:`PressureLoad`) has the gradient -f_a plus line terms 1/3 p (x - x0) x dx along
the surface's open edges (they cancel between neighbouring faces). So the potential is
exact for a closed surface, and in displacements for an open one whose open edges lie
in planes through x0 and slide in them (symmetry planes) or are held; there the
reactions normal to those planes carry the line terms. Its Hessian, the consistent load
stiffness, is symmetric. Anywhere else the load stiffness of f_a is not symmetric (its
antisymmetric part lives on the open edges), and ``PressureLoad`` hands such a surface
to ``FollowerPressure``. 2x2 Gauss integrates both exactly on bilinear faces.
"""

from __future__ import annotations

import dataclasses
import inspect
import logging

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.mesh import Mesh, face_edges, quad_gauss_points, quad_shape
from eyefem.fem.terms import Term

log = logging.getLogger(__name__)

_XG, _WG = quad_gauss_points()
_N, _DN = quad_shape(_XG)  # (4g, 4a), (4g, 4a, 2)
_FIELDS = inspect.signature(lambda name, mesh, face_set, pressure=0.0, origin=(0.0, 0.0, 0.0): 0)
"""PressureLoad's constructor arguments (read before the dataclass builds the term)."""


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


def face_forces(x, p):
    """Follower pressure residual p integral N_a n da of bilinear faces, exactly (2x2 Gauss).

    Args:
      x: (n_faces, 4, 3) current face node positions, mm.
      p: pressure, MPa (> 0 pushes against the normals).
    Returns: (n_faces, 4, 3) nodal residual, N (the applied force is its negative).
    """
    t1 = jnp.einsum("ga,fai->fgi", _DN[..., 0], x)
    t2 = jnp.einsum("ga,fai->fgi", _DN[..., 1], x)
    return p * jnp.einsum("g,ga,fgi->fai", _WG, _N, jnp.cross(t1, t2))


def open_edges(faces, with_faces=False):
    """Edges (m, 2) that belong to one face of the set only: a closed surface has none.

    Args: faces (n_faces, 4) node ids; with_faces: also return the index of each edge's
    face (m,). Returns node id pairs (m, 2), sorted within a pair.
    """
    faces = np.asarray(faces, np.int64)
    e = np.sort(face_edges(faces), axis=1)
    owner = np.repeat(np.arange(len(faces)), 4)
    if not len(e):
        return (e, owner) if with_faces else e
    _, inv, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    one = counts[inv.ravel()] == 1
    return (e[one], owner[one]) if with_faces else e[one]


def off_plane_edges(nodes, faces, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The open edges (m, 2) of a face set that do not lie in one of the planes x = x0_x,
    y = x0_y, z = x0_z through ``origin`` crossed by their face (a symmetry plane: the
    edge's nodes in it, within 1e-9 of the mesh size; its face not).

    On such an edge the cone-volume potential (:class:`PressureLoad`) is not the follower
    load unless the edge's nodes are held in all three directions.

    Args: nodes (n, 3) mm; faces (n_faces, 4); origin (3,) mm.
    """
    faces = np.asarray(faces, np.int64)
    e, owner = open_edges(faces, with_faces=True)
    if not len(e):
        return e
    X = np.asarray(nodes, np.float64)
    tol = 1e-9 * max(float(np.ptp(X, axis=0).max()), 1e-300)
    near = np.abs(X - np.asarray(origin, np.float64)) <= tol  # (n, 3): node in plane i
    in_plane = near[e].all(axis=1) & ~near[faces[owner]].all(axis=1)  # (m, 3)
    return e[~in_plane.any(axis=1)]


def pressure_term(name: str, mesh: Mesh, face_set: str, pressure: float = 0.0) -> Term:
    """The follower pressure for an imported model: :class:`PressureLoad` (conservative,
    symmetric tangent) on a closed face set, :class:`FollowerPressure` on an open one (its
    forces and reactions exact whatever holds the open edges)."""
    if len(open_edges(mesh.face_set(face_set))):
        return FollowerPressure(name, mesh, face_set, pressure)
    return PressureLoad(name, mesh, face_set, pressure)


@dataclasses.dataclass(frozen=True, eq=False)
class PressureLoad(Term):
    """Follower pressure p (MPa) on a named face set, pushing against the face normals,
    as the potential p * (cone volumes about ``origin``) (module docstring).

    Exact on a closed face set and on one whose open edges lie in the planes through
    ``origin`` (symmetry planes that hold them in their normal direction). A face set
    with an open edge elsewhere is built as a :class:`FollowerPressure` instead (logged):
    ``PressureLoad(...)`` then returns that subclass, right whatever holds the edge.

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
    potential = True
    """The term's residual is the gradient of its energy (see :class:`FollowerPressure`)."""

    def __new__(cls, *args, **kwargs):
        if cls is PressureLoad and (args or kwargs):
            bound = _FIELDS.bind(*args, **kwargs).arguments
            mesh, face_set = bound["mesh"], bound["face_set"]
            origin = bound.get("origin", (0.0, 0.0, 0.0))
            off = off_plane_edges(mesh.nodes, mesh.face_set(face_set), origin)
            if len(off):
                log.info("pressure '%s': face set '%s' has %d open edges off the planes "
                         "through %s (e.g. nodes %d-%d): applied as a follower pressure "
                         "(exact forces, non-symmetric load stiffness)", bound["name"],
                         face_set, len(off), tuple(origin), off[0, 0], off[0, 1])
                cls = FollowerPressure
        return object.__new__(cls)

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


class FollowerPressure(PressureLoad):
    """Follower pressure p (MPa) on any face set, open or closed: nodal forces
    f_a = -p integral N_a n da over the current faces (:func:`face_forces`).

    Not a potential (``potential`` False): the model takes its residual from
    :meth:`residual`, not from an energy (``eyefem.solve.model``). Its load stiffness
    d(residual)/dq is not symmetric on an open surface; the Newton tangent takes its
    symmetric part (the linear solvers are symmetric: FEBio's ``symmetric_stiffness``
    default does the same), so the residual and the converged state are exact and
    Newton converges linearly rather than quadratically where the antisymmetric part
    matters. Tangent-vector products (:meth:`eyefem.solve.model.Model.hvp`) are exact.
    The adjoint refuses a model with this term (it needs the transposed tangent).

    Args: as :class:`PressureLoad` (``origin`` is not used).
    """

    potential = False

    def local_energy(self, q_loc, params, data):
        raise TypeError(f"pressure '{self.name}' is a follower load on an open surface and "
                        "has no energy; use its residual (FollowerPressure.residual)")

    def local_residual(self, q_loc, params, data):
        """Local residuals (n_faces, 12), N, from local displacements q_loc (n_faces, 12) mm."""
        x = data["X"] + q_loc.reshape(-1, 4, 3)
        return face_forces(x, params["p"]).reshape(-1, 12)

    def residual(self, q, params, data, dofs):
        """The term's residual (n_dof,), N, from the global dof vector q (n_dof,)."""
        r = self.local_residual(q[dofs], params, data)
        return jnp.zeros_like(q).at[dofs.ravel()].add(r.ravel())

    def local_grad_hess(self, q_loc, params, data):
        """Local residuals (n, 12), N, and the symmetric part of their Jacobians
        (n, 12, 12), N/mm."""
        J = self.local_jacobian(q_loc, params, data)
        return self.local_residual(q_loc, params, data), 0.5 * (J + jnp.swapaxes(J, 1, 2))

    def local_jacobian(self, q_loc, params, data):
        """The exact, non-symmetric Jacobians (n, 12, 12) of the local residuals, N/mm."""
        def one(x, X):
            return self.local_residual(x[None], params, {"X": X[None]})[0]
        return jax.vmap(jax.jacfwd(one))(q_loc, data["X"])
