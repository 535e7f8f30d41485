"""Closed fluid cavities strongly coupled to the solid (seed 4.2).

A cavity is a closed face set whose normals point out of the solid, into the liquid
(it may span several bodies: the eye wall and the lens). Its volume, exact for
bilinear faces, is V(q) = -sum_f 1/3 integral (x . n) da. The liquid obeys the seed's
law P = P_ini - K (V - V_ini) / V_ini, written as the energy

    Pi_c = -P_ini e + K e^2 / (2 V_ini),     e = V - V_ini - dV                [N mm]

with dV the liquid volume injected (> 0) or drained (< 0), a param ramped by stages.
Then dPi_c/dq = -P dV/dq (the follower pressure load) and

    d2Pi_c/dq2 = -P d2V/dq2 + (K / V_ini) g g^T,     g = dV/dq,

a sparse part (face blocks) and a rank-one part over every wetted dof, which is
never formed: the linear solver applies it with the Woodbury identity.

An outflow compliance C_out (mm^3/MPa, a compliant reservoir in series: choroidal
blood, leakage through a sclerotomy) lets liquid leave in proportion to the pressure
rise; it replaces K by K / (1 + K C_out / V_ini) and the outflow volume is reported.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .mesh import Mesh, check_face_orientation, open_edges
from .surface import enclosed_volume, face_cone_volume, face_dofs
from .terms import Term
from .units import MMHG


def check_closed(mesh: Mesh, face_set: str) -> np.ndarray:
    """Faces of a set after checking it is closed and consistently oriented."""
    faces = mesh.face_set(face_set)
    oe = open_edges(faces)
    if len(oe):
        raise ValueError(f"cavity face set '{face_set}' is not closed: {len(oe)} open edges, "
                         f"e.g. between nodes {oe[:5].tolist()}; a cavity needs a closed surface")
    check_face_orientation(faces, f"cavity face set '{face_set}'")
    return faces


@dataclasses.dataclass(frozen=True, eq=False)
class FluidCavity(Term):
    """A liquid-filled closed cavity.

    Args:
      name: term name; params {"p_ini" MPa, "v_ini" mm^3, "bulk" MPa, "dv" mm^3}.
      mesh: the mesh holding the face set.
      face_set: closed face set, normals out of the solid.
      p_ini: initial pressure, MPa.
      bulk: liquid bulk modulus K, MPa (seed: 2083.3).
      v_ini: initial volume, mm^3 (default: the enclosed volume of the mesh).
      outflow_compliance: C_out, mm^3/MPa (0: closed cavity).
    """

    name: str
    mesh: Mesh
    face_set: str
    p_ini: float = 0.0
    bulk: float = 2083.3
    v_ini: float | None = None
    outflow_compliance: float = 0.0

    def __post_init__(self):
        faces = check_closed(self.mesh, self.face_set)
        v0 = enclosed_volume(self.mesh.nodes, faces)
        if v0 <= 0:
            raise ValueError(f"cavity '{self.name}': face set '{self.face_set}' encloses "
                             f"{v0:.4g} mm^3 <= 0; its normals must point into the liquid "
                             "(out of the solid)")
        if self.bulk <= 0:
            raise ValueError(f"cavity '{self.name}': bulk modulus {self.bulk} MPa; must be > 0")
        if self.outflow_compliance < 0:
            raise ValueError(f"cavity '{self.name}': outflow compliance must be >= 0")
        v_ini = v0 if self.v_ini is None else float(self.v_ini)
        object.__setattr__(self, "dofs", face_dofs(faces))
        object.__setattr__(self, "params", {"p_ini": float(self.p_ini), "v_ini": v_ini,
                                            "bulk": float(self.bulk), "dv": 0.0,
                                            "c_out": float(self.outflow_compliance)})
        object.__setattr__(self, "data", {"X": self.mesh.nodes[faces]})

    # --- volume and pressure ---------------------------------------------------------------
    @staticmethod
    def face_volumes(q_loc, data):
        """Signed contributions (n_faces,) to the enclosed volume, mm^3."""
        return -face_cone_volume(data["X"] + q_loc.reshape(-1, 4, 3), jnp.zeros(3))

    @staticmethod
    def effective_bulk(params):
        return params["bulk"] / (1.0 + params["bulk"] * params["c_out"] / params["v_ini"])

    def local_energy(self, q_loc, params, data):
        """Per-face share of the energy at the current volume (sums to Pi_c)."""
        vf = self.face_volumes(q_loc, data)
        e = jnp.sum(vf) - params["v_ini"] - params["dv"]
        k = self.effective_bulk(params)
        pi = -params["p_ini"] * e + k * e * e / (2.0 * params["v_ini"])
        return pi * vf / jnp.sum(vf)

    def energy(self, q, params, data, dofs):
        vf = self.face_volumes(q[dofs], data)
        e = jnp.sum(vf) - params["v_ini"] - params["dv"]
        return -params["p_ini"] * e + self.effective_bulk(params) * e * e / (2.0 * params["v_ini"])

    def pressure_of(self, q, params):
        """Cavity pressure P (MPa) and volume V (mm^3) at q (numpy)."""
        V = float(np.sum(np.asarray(self.face_volumes(jnp.asarray(q)[self.dofs], self.data))))
        e = V - params["v_ini"] - params["dv"]
        return float(params["p_ini"] - self.effective_bulk(params) * e / params["v_ini"]), V

    # --- derivatives -------------------------------------------------------------------------
    def grad_hess(self, q, params, data, dofs):
        """Local gradients -P dV_f/dq (n, 12) and Hessians -P d2V_f/dq2 (n, 12, 12)."""
        q_loc = q[dofs]

        def gv(x):
            return jax.grad(lambda y: jnp.sum(self.face_volumes(y, data)))(x)

        g = gv(q_loc)
        basis = jnp.broadcast_to(jnp.eye(12)[:, None, :], (12,) + q_loc.shape)
        hv = jnp.transpose(jax.vmap(lambda v: jax.jvp(gv, (q_loc,), (v,))[1])(basis), (1, 2, 0))
        e = jnp.sum(self.face_volumes(q_loc, data)) - params["v_ini"] - params["dv"]
        P = params["p_ini"] - self.effective_bulk(params) * e / params["v_ini"]
        return -P * g, -P * hv

    def low_rank(self, q, params, data, dofs):
        """The rank-one coupling (K / V_ini) g g^T, g = dV/dq (n_dof,)."""
        gv = jax.grad(lambda y: jnp.sum(self.face_volumes(y, data)))(jnp.asarray(q)[dofs])
        g = np.bincount(dofs.ravel(), np.asarray(gv).ravel(), minlength=len(q))
        return [(float(self.effective_bulk(params) / params["v_ini"]), g)]

    # --- outputs -------------------------------------------------------------------------------
    def report(self, q, params):
        P, V = self.pressure_of(q, params)
        return {"pressure_MPa": P, "pressure_mmHg": P / MMHG, "volume_mm3": V,
                "injected_mm3": float(params["dv"]),
                "outflow_mm3": float(params["c_out"] * (P - params["p_ini"]))}

    def point_fields(self, q, params, n_nodes):
        P, _ = self.pressure_of(q, params)
        f = np.zeros(n_nodes)
        f[self.dofs[:, ::3].ravel() // 3] = P
        return {f"{self.name}_pressure": f}


def close_cavity(cavity: str, pressure_term: str | None = None):
    """A Stage ``before`` hook: close the cavity at the current pressure and volume.

    P_ini becomes the current value of the PressureLoad ``pressure_term`` (the seed's
    stage 1 -> 2: inflate by surface pressure, then close the cavity), V_ini the
    current enclosed volume, dV = 0.
    """

    def hook(model, q, theta):
        term = model.term(cavity)
        p0 = float(theta[pressure_term]["p"]) if pressure_term else float(theta[cavity]["p_ini"])
        V = float(np.sum(np.asarray(term.face_volumes(jnp.asarray(q)[term.dofs], term.data))))
        theta = dict(theta)
        theta[cavity] = {**theta[cavity], "p_ini": p0, "v_ini": V, "dv": 0.0}
        return model, q, theta

    return hook


def _cavity_check(rng):
    """Hand-coded cavity tangent on the closed boundary of a deformed hexahedron."""
    from .handcoded import pressure_face_residual_tangent
    from .mesh import HEX_CORNERS, HEX_FACES
    from .verify import CheckData, random_deformation

    X = HEX_CORNERS * 0.5
    x = (X @ random_deformation(rng, 0.3).T + 0.05 * rng.standard_normal((8, 3))).ravel()
    faces = HEX_FACES[:, ::-1]  # normals into the enclosed region
    mesh = Mesh(X, np.arange(8)[None], [0], face_sets={"c": faces})
    term = FluidCavity("cav", mesh, "c", p_ini=0.002, bulk=2.0)
    p = term.params
    u = x - X.ravel()
    E = jax.jit(lambda y: term.energy(y, p, term.data, term.dofs))
    grad = jax.jit(jax.grad(E))
    H = np.asarray(jax.hessian(E)(jnp.asarray(u)))
    P, V = term.pressure_of(u, p)
    r = np.zeros(24)
    K = np.zeros((24, 24))
    for f in faces:  # -P dV/dx = the follower load of pressure P on the reversed faces
        rf, kf = pressure_face_residual_tangent(x.reshape(8, 3)[f[::-1]], -P)
        d = (3 * f[::-1, None] + np.arange(3)).ravel()
        r[d] += rf
        K[np.ix_(d, d)] += kf
    g = -r / P  # dV/dx
    K += term.effective_bulk(p) / p["v_ini"] * np.outer(g, g)
    return CheckData(np.asarray(grad(jnp.asarray(u))), r, H, K,
                     lambda y: np.asarray(grad(jnp.asarray(y))), u,
                     f"P = {P / MMHG:.2f} mmHg, V/V0 = {V / p['v_ini']:.3f}")


def _register():
    from .verify import register_check

    register_check("fluid_cavity", _cavity_check)


_register()
