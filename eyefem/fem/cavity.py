"""Closed fluid cavities strongly coupled to the solid (seed 4.2; issue 3).

A cavity is a closed set of boundary faces whose normals point out of the solid, into
the liquid. It may span several bodies (the eye wall and a floating lens) and several
face sets. Its volume, exact for bilinear faces, is

    V(q) = -sum_f 1/3 integral_f (x - x0) . n da                                [mm^3]

(x0: a fixed apex; any point for a closed surface). The liquid obeys the seed's law
P = P_ini - K (V - V_ini) / V_ini, extended by a prescribed exchanged volume dV,
written as the energy

    Pi_c = -P_ini e + K e^2 / (2 V_ini),     e = V - V_ini - dV                 [N mm]
    P    = -dPi_c/dV = P_ini - K e / V_ini                                      [MPa]

dV (mm^3) is liquid injected (> 0) or drained (< 0), a param ramped by stages. Then
dPi_c/dq = -P g with g = dV/dq (the follower pressure load) and

    d2Pi_c/dq2 = -P d2V/dq2 + (K / V_ini) g g^T,

a sparse part (per-face 12 x 12 blocks, :meth:`FluidCavity.grad_hess`) and a rank-one
part over every wetted dof (:meth:`FluidCavity.low_rank`), never formed: the linear
solver adds it to the sparse factorisation with the Woodbury identity.

Outflow compliance (optional, ``c_out`` mm^3/MPa, default 0): a compliant reservoir
in series (choroidal blood volume, leakage through a sclerotomy) takes up
C_out (P - P_ini) of liquid, so P = P_ini - K (V - V_ini - dV + C_out (P - P_ini)) / V_ini,
that is the law above with K replaced by K_eff = K / (1 + K C_out / V_ini). The
outflow volume is reported.

Symmetry: a cavity cut by symmetry planes through x0 (an octant of an eye) has open
edges on those planes; pass ``symmetry_planes`` and hold the plane nodes in their
planes. The cone volumes through x0 of the plane parts are zero, so V is the volume
of the modelled part (1/8 of the whole for an octant) and the law holds unchanged.

Volume regulation (optional, ``regulation``, issue 74): aqueous production and outflow
(Goldmann's law), a choroidal blood compartment, paracentesis and drainage over time, by
backward Euler; the pressure is then the condensed root of the step's volume balance
(eyefem.fem.regulation, whose docstring states the laws, the incremental potential and
the sources). The term advances its history (produced and outflowed volumes, the clock)
after each converged step (:meth:`FluidCavity.advance`) and reports the balance.

Several cavities: one term holds any number (one per entry of ``face_sets``) with
vector params, one compiled kernel and one rank-one vector per cavity.

Length: the cavity term, its low-rank tangent, closing and the pressure report share
the volume kernel; about 500 lines.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from eyefem.fem.mesh import Mesh, face_edges, open_edges
from eyefem.fem.regulation import (HISTORY_KEYS, Regulation, advanced_history, balance,
                                   regulated_state)
from eyefem.fem.surface import face_cone_volume, face_dofs
from eyefem.fem.terms import Term
from eyefem.fem.units import MMHG

log = logging.getLogger(__name__)

WATER_BULK = 2083.3
"""Bulk modulus of the intraocular liquid used by the seed, MPa."""

PARAM_KEYS = ("p_ini", "v_ini", "bulk", "dv", "c_out")


# --- geometry and law (pure JAX; everything from data/params so kernels are shared) ---------

def _face_volumes(q_loc, data):
    """Signed contributions (n_faces,) of each face to the volume of its cavity, mm^3."""
    x = data["X"] + q_loc.reshape(-1, 4, 3)
    return -face_cone_volume(x, data["origin"][data["cav"]][:, None, :])


def _volumes(q_loc, data):
    """Volumes (n_cav,) of all cavities of a term, mm^3."""
    return jax.ops.segment_sum(_face_volumes(q_loc, data), data["cav"],
                               num_segments=data["origin"].shape[0])


def _law(V, params):
    """Pressure P (n_cav,) MPa, energy Pi (n_cav,) N mm and -dP/dV (n_cav,) MPa/mm^3
    (K_eff / V_ini without regulation)."""
    if "facility" in params:  # a regulated cavity (the params' keys are static under jit)
        s = regulated_state(V, params)
        return s["P"], s["Pi"], s["alpha"]
    n = V.shape[0]
    p0, v0, k, dv, c = (jnp.broadcast_to(jnp.asarray(params[key], V.dtype), (n,))
                        for key in PARAM_KEYS)
    keff = k / (1.0 + k * c / v0)
    e = V - v0 - dv
    return p0 - keff * e / v0, -p0 * e + keff * e * e / (2.0 * v0), keff / v0


def _face_volume_grad(q_loc, data):
    """dV_f/dq_loc (n_faces, 12)."""
    return jax.grad(lambda y: jnp.sum(_face_volumes(y, data)))(q_loc)


@jax.jit
def cavity_state(q, params, data, dofs):
    q_loc = q[dofs]
    V = _volumes(q_loc, data)
    P, _, alpha = _law(V, params)
    return P, V, alpha, _face_volume_grad(q_loc, data)


@jax.jit
def _volumes_and_stiffness(q_loc, params, data):
    """Volumes (n_cav,) mm^3 and -dP/dV (n_cav,) MPa/mm^3 of a term's cavities (compiled:
    volumes only, no face gradients)."""
    V = _volumes(q_loc, data)
    return V, _law(V, params)[2]


_face_cone_volume = jax.jit(face_cone_volume)
""":func:`eyefem.fem.surface.face_cone_volume` compiled, for host-side checks."""


def cavity_pressures(q, params, data, dofs):
    """Pressures (n_cav,) MPa and volumes (n_cav,) mm^3 as JAX values (differentiable).

    For objectives of adjoint gradients: ``cavity_pressures(q, theta[name], term.data,
    term.dofs)``.
    """
    V = _volumes(jnp.asarray(q)[dofs], data)
    return _law(V, params)[0], V


# --- construction checks --------------------------------------------------------------------

def _face_components(faces):
    """Connected components (through shared edges) of a face set: (n_comp, labels (n_faces,))."""
    e = face_edges(faces)
    key = np.sort(e, axis=1)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    fid = np.repeat(np.arange(len(faces)), 4)
    inc = sp.csr_matrix((np.ones(len(fid)), (fid, inv)), shape=(len(faces), inv.max() + 1))
    return connected_components(inc @ inc.T, directed=False)


def check_cavity_faces(mesh: Mesh, faces: np.ndarray, label: str, symmetry_planes=(),
                       origin=(0.0, 0.0, 0.0)) -> float:
    """Check that faces bound a cavity; return its reference volume (mm^3).

    Raises ValueError naming the open edges (a hole in the surface), the faces that
    traverse an edge in the same direction (inconsistent orientation) or the
    components enclosing negative volume (normals into the solid).
    """
    if len(faces) == 0:
        raise ValueError(f"cavity '{label}': the face set is empty")
    e = face_edges(faces)
    _, idx, counts = np.unique(e, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        bad = e[idx[counts > 1][0]]
        fb = np.nonzero(np.any(faces == bad[0], axis=1) & np.any(faces == bad[1], axis=1))[0]
        raise ValueError(
            f"cavity '{label}': faces {fb.tolist()} (nodes {faces[fb].tolist()}) traverse edge "
            f"({bad[0]}, {bad[1]}) in the same direction ({int((counts > 1).sum())} such edges): "
            "inconsistent orientation; every face must be ordered so that its normal points "
            "out of the solid, into the liquid (reverse the node order of the wrong faces)")
    ekey = np.sort(e, axis=1)
    _, einv, ecount = np.unique(ekey, axis=0, return_inverse=True, return_counts=True)
    if np.any(ecount > 2):
        bad = ekey[np.nonzero(ecount[einv.ravel()] > 2)[0][0]]
        raise ValueError(f"cavity '{label}': edge ({bad[0]}, {bad[1]}) is shared by more than "
                         "two faces (a non-manifold surface); split it into separate cavities")
    oe = open_edges(faces)
    if len(oe):
        X = mesh.nodes
        size = float(np.ptp(X[faces.ravel()], axis=0).max())
        on = np.zeros(len(oe), bool)
        for ax in symmetry_planes:
            k = "xyz".index(ax)
            on |= np.all(np.abs(X[oe, k] - origin[k]) <= 1e-9 * size, axis=1)
        if not np.all(on):
            bad = oe[~on]
            hint = (f" (edges on the symmetry planes {tuple(symmetry_planes)} through "
                    f"{tuple(origin)} are allowed)" if symmetry_planes else "")
            raise ValueError(
                f"cavity '{label}': the face set is not closed: {len(bad)} open edges{hint}, "
                f"e.g. between nodes {bad[:6].tolist()} at {X[bad[0]].round(6).tolist()}; "
                "add the missing faces (a cavity spanning several bodies lists all their "
                "wetted face sets) or declare the symmetry planes")
    x0 = np.asarray(origin, np.float64)
    vf = -np.asarray(_face_cone_volume(mesh.nodes[faces], x0))
    v = float(vf.sum())
    if not v > 0:
        n_comp, lab = _face_components(faces)
        comps = [(np.nonzero(lab == c)[0], float(vf[lab == c].sum())) for c in range(n_comp)]
        desc = "; ".join(f"faces {f[:6].tolist()}{'...' if len(f) > 6 else ''} "
                         f"({len(f)} faces): {vol:.6g} mm^3" for f, vol in comps[:6])
        raise ValueError(
            f"cavity '{label}': the faces enclose {v:.6g} mm^3 <= 0, so their normals point "
            f"into the solid. Connected components: {desc}. Reverse the node order of the "
            "faces of the outer wall (normals must point out of the solid, into the liquid; "
            "an inner body such as a lens legitimately encloses a negative volume)")
    return v


def _as_cavity_list(face_sets):
    """face_sets -> list of tuples of face-set names (one tuple per cavity)."""
    if isinstance(face_sets, str):
        return [(face_sets,)], True
    out = []
    for fs in face_sets:
        out.append((fs,) if isinstance(fs, str) else tuple(fs))
    if not out:
        raise ValueError("FluidCavity: face_sets is empty; give at least one face set")
    return out, False


# --- the term ---------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True, eq=False)
class FluidCavity(Term):
    """Liquid-filled closed cavities (one or many) coupled to the solid.

    Args:
      name: term name.
      mesh: the mesh holding the face sets.
      face_sets: one face-set name (one cavity, scalar params) or a sequence with one
        entry per cavity (vector params (n_cav,)); an entry may be a tuple of face-set
        names whose union bounds one cavity (eye wall + lens). Normals out of the solid.
      p_ini: initial pressure P_ini, MPa (scalar or (n_cav,)).
      bulk: liquid bulk modulus K, MPa (>= 0; 0: pressure-controlled, P = P_ini).
      v_ini: initial volume V_ini, mm^3 (default: the enclosed reference volume).
      outflow_compliance: C_out, mm^3/MPa (0: no outflow).
      symmetry_planes: subset of ("x", "y", "z"): planes through ``origin`` on which the
        cavity surface may be open (symmetric models).
      regulation: eyefem.fem.regulation.Regulation (facility, episcleral venous pressure,
        production, choroidal blood), or None (default): no volume regulation, the seed's
        law.
      origin: (3,) apex of the cone volumes for symmetric cavities, mm; closed cavities
        use their reference centroid.

    params: {"p_ini" MPa, "v_ini" mm^3, "bulk" MPa, "dv" mm^3, "c_out" mm^3/MPa}, floats
    for one cavity, (n_cav,) arrays for several (a scalar target is broadcast). With
    regulation also "facility" mm^3/(min MPa), "p_ev" MPa, "production" mm^3/min,
    "blood_max" mm^3, "blood_scale" MPa, "paracentesis" and "drainage" mm^3 (removed,
    cumulative, ramped by stages), the history "aq_produced", "aq_outflow" mm^3 and
    "time" min (set by :meth:`advance`), and the step's duration "dt" min (set by the
    load path); "time" and "dt" are scalars.
    """

    name: str
    mesh: Mesh
    face_sets: str | Sequence
    p_ini: float | Sequence[float] = 0.0
    bulk: float | Sequence[float] = WATER_BULK
    v_ini: float | Sequence[float] | None = None
    outflow_compliance: float | Sequence[float] = 0.0
    symmetry_planes: tuple[str, ...] = ()
    origin: tuple = (0.0, 0.0, 0.0)
    regulation: Regulation | None = None

    pressure_stiffness = True

    def __post_init__(self):
        cavs, single = _as_cavity_list(self.face_sets)
        for ax in self.symmetry_planes:
            if ax not in ("x", "y", "z"):
                raise ValueError(f"cavity '{self.name}': symmetry plane '{ax}'; use 'x', 'y', 'z'")
        faces_all, cav_id, origins, v0 = [], [], [], []
        labels = ["+".join(c) for c in cavs]
        for i, (c, label) in enumerate(zip(cavs, labels)):
            faces = np.concatenate([self.mesh.face_set(fs) for fs in c])
            o = (np.asarray(self.origin, np.float64) if self.symmetry_planes
                 else self.mesh.nodes[np.unique(faces)].mean(axis=0))
            v0.append(check_cavity_faces(self.mesh, faces, f"{self.name}: {label}",
                                         self.symmetry_planes, o))
            faces_all.append(faces)
            cav_id.append(np.full(len(faces), i, np.int64))
            origins.append(o)
        n = len(cavs)
        faces = np.concatenate(faces_all)
        v0 = np.array(v0)

        def vec(val, what, unit, lo):
            a = np.broadcast_to(np.asarray(val, np.float64), (n,)).copy() if np.ndim(val) == 0 \
                else np.asarray(val, np.float64)
            if a.shape != (n,):
                raise ValueError(f"cavity '{self.name}': {what} has shape {a.shape}; expected a "
                                 f"scalar or ({n},) (one per cavity: {labels})")
            if not np.all(np.isfinite(a)) or np.any(a < lo):
                raise ValueError(f"cavity '{self.name}': {what} = {a.tolist()} {unit}; "
                                 f"must be finite and >= {lo}")
            return a

        p = {"p_ini": vec(self.p_ini, "p_ini", "MPa", -np.inf),
             "v_ini": v0 if self.v_ini is None else vec(self.v_ini, "v_ini", "mm^3", 0.0),
             "bulk": vec(self.bulk, "bulk", "MPa", 0.0),
             "dv": np.zeros(n),
             "c_out": vec(self.outflow_compliance, "outflow_compliance", "mm^3/MPa", 0.0)}
        if np.any(p["v_ini"] <= 0):
            raise ValueError(f"cavity '{self.name}': v_ini = {p['v_ini'].tolist()} mm^3; must be > 0")
        if self.regulation is not None:
            p.update(self.regulation.params(n, self.name))
        if single:
            p = {k: float(v[0]) for k, v in p.items()}
        if self.regulation is not None:
            p.update(dt=0.0, time=0.0)
        object.__setattr__(self, "dofs", face_dofs(faces))
        object.__setattr__(self, "params", p)
        object.__setattr__(self, "data", {"X": self.mesh.nodes[faces],
                                          "cav": np.concatenate(cav_id),
                                          "origin": np.stack(origins)})
        object.__setattr__(self, "cavity_labels", tuple(labels))
        object.__setattr__(self, "single", single)
        cav = self.data["cav"]
        object.__setattr__(self, "_faces_of", [np.nonzero(cav == i)[0] for i in range(n)])
        log.info("cavity '%s': %d cavit%s, %d wetted faces, reference volume %s mm^3",
                 self.name, n, "y" if n == 1 else "ies", len(faces), _numbers(v0, "%.6g"))

    @property
    def n_cavities(self) -> int:
        return len(self.cavity_labels)

    @property
    def history_keys(self) -> tuple[str, ...]:
        """Params holding the state of the last converged step (the load path carries them
        from step to step instead of ramping them): the regulation's, or none."""
        return HISTORY_KEYS if self.regulation is not None else ()

    def static_key(self) -> tuple:
        return ("regulated",) if self.regulation is not None else ()

    def advance(self, q, params) -> dict:
        """The params after a converged step of ``params["dt"]`` minutes at q: the produced
        and outflowed volumes and the clock moved on, dt back to 0 (the state q is in
        equilibrium with both: the pressure is unchanged)."""
        if self.regulation is None:
            return params
        P, _ = self.pressures(q, params)
        new = advanced_history(P if not self.single else float(P[0]),
                               {k: np.asarray(v) for k, v in params.items()})
        return {**params, "dt": 0.0, "time": float(new["time"]),
                "aq_produced": self._shape(new["aq_produced"]),
                "aq_outflow": self._shape(new["aq_outflow"])}

    def history_after(self, q, params) -> dict:
        """:meth:`advance`'s new history values as JAX values of (q, params), differentiable
        (the gradient through time, eyefem.solve.transient)."""
        P = cavity_pressures(q, params, self.data, self.dofs)[0]
        return advanced_history(P[0] if self.single else P, params)

    # --- energy and derivatives (kernels: everything from q, params, data, dofs) ----------
    def local_energy(self, q_loc, params, data):
        """Per-face shares of the energy (n_faces,), summing to Pi_c (not independent)."""
        vf = _face_volumes(q_loc, data)
        V = jax.ops.segment_sum(vf, data["cav"], num_segments=data["origin"].shape[0])
        _, pi, _ = _law(V, params)
        return (pi / V)[data["cav"]] * vf

    def energy(self, q, params, data, dofs):
        """Pi_c (scalar, N mm) from the global q (n_dof,)."""
        _, pi, _ = _law(_volumes(q[dofs], data), params)
        return jnp.sum(pi)

    def grad_hess(self, q, params, data, dofs):
        """Local gradients -P dV_f/dq (n_faces, 12) and Hessians -P d2V_f/dq2 (n_faces, 12, 12).

        P is each face's cavity pressure at the global volume; the rank-one coupling is
        in :meth:`low_rank`.
        """
        q_loc = q[dofs]
        g = _face_volume_grad(q_loc, data)
        basis = jnp.broadcast_to(jnp.eye(12, dtype=q_loc.dtype)[:, None, :], (12,) + q_loc.shape)
        cols = jax.vmap(lambda v: jax.jvp(lambda y: _face_volume_grad(y, data),
                                          (q_loc,), (v,))[1])(basis)
        H = jnp.transpose(cols, (1, 2, 0))
        P, _, _ = _law(jax.ops.segment_sum(_face_volumes(q_loc, data), data["cav"],
                                           num_segments=data["origin"].shape[0]), params)
        Pf = P[data["cav"]]
        return -Pf[:, None] * g, -Pf[:, None, None] * H

    def low_rank(self, q, params, data, dofs):
        """[(K_eff / V_ini, g (n_dof,))] per cavity, g = dV/dq; cavities with K = 0 omitted."""
        _, _, alpha, gf = cavity_state(jnp.asarray(q), params, data, dofs)
        alpha, gf = np.asarray(alpha), np.asarray(gf)
        out = []
        for c, sel in enumerate(self._faces_of):
            if alpha[c] != 0.0:
                out.append((float(alpha[c]), np.bincount(dofs[sel].ravel(), gf[sel].ravel(),
                                                         minlength=len(q))))
        return out

    def low_rank_values(self, q, params) -> list:
        """Volumes (mm^3) of the cavities in :meth:`low_rank` (those with K != 0)."""
        V, alpha = _volumes_and_stiffness(np.asarray(q)[self.dofs], params, self.data)
        return [float(v) for v, a in zip(np.asarray(V), np.asarray(alpha)) if a != 0.0]

    # --- host-side state and outputs ---------------------------------------------------------
    def pressures(self, q, params) -> tuple[np.ndarray, np.ndarray]:
        """Pressures (n_cav,) MPa and volumes (n_cav,) mm^3 at q (numpy)."""
        P, V, _, _ = cavity_state(jnp.asarray(q), params, self.data, self.dofs)
        return np.asarray(P), np.asarray(V)

    def _shape(self, a):
        """Params value for this term: float for one cavity, (n_cav,) array for several."""
        a = np.broadcast_to(np.asarray(a, np.float64), (self.n_cavities,)).copy()
        return float(a[0]) if self.single else a

    def report(self, q, params) -> dict:
        """Per cavity: pressure_MPa, pressure_mmHg, volume_mm3, injected_mm3 (dV),
        outflow_mm3 (C_out (P - P_ini), the linear reservoir); keys prefixed '<face set>/'
        for several cavities. With regulation also (volumes since the closing, mm^3)
        produced_mm3, aqueous_outflow_mm3 (Goldmann), blood_expelled_mm3,
        paracentesis_mm3, drainage_mm3, drained_mm3 (their sum), compressed_mm3 (the
        liquid's compression), balance_mm3 (V - V_ini minus the sum of the flows: zero to
        roundoff), the rates outflow_rate_ul_min and production_ul_min, and time_min."""
        P, V = self.pressures(q, params)
        if self.regulation is not None:
            return self._regulated_report(V, params)
        n = self.n_cavities
        dv = np.broadcast_to(np.asarray(params["dv"], np.float64), (n,))
        c = np.broadcast_to(np.asarray(params["c_out"], np.float64), (n,))
        p0 = np.broadcast_to(np.asarray(params["p_ini"], np.float64), (n,))
        out = {}
        for i, label in enumerate(self.cavity_labels):
            pre = "" if self.single else f"{label}/"
            out.update({f"{pre}pressure_MPa": float(P[i]), f"{pre}pressure_mmHg": float(P[i] / MMHG),
                        f"{pre}volume_mm3": float(V[i]), f"{pre}injected_mm3": float(dv[i]),
                        f"{pre}outflow_mm3": float(c[i] * (P[i] - p0[i]))})
        return out

    def _regulated_report(self, V, params) -> dict:
        s = {k: np.asarray(v) for k, v in
             regulated_state(jnp.asarray(V), jax.tree_util.tree_map(jnp.asarray, params)).items()}
        n = self.n_cavities
        res = balance(V, s, np.broadcast_to(np.asarray(params["v_ini"], float), (n,)))
        p_ev = np.broadcast_to(np.asarray(params["p_ev"], float), (n,))
        fac = np.broadcast_to(np.asarray(params["facility"], float), (n,))
        prod = np.broadcast_to(np.asarray(params["production"], float), (n,))
        para = np.broadcast_to(np.asarray(params["paracentesis"], float), (n,))
        drain = np.broadcast_to(np.asarray(params["drainage"], float), (n,))
        out = {}
        for i, label in enumerate(self.cavity_labels):
            pre = "" if self.single else f"{label}/"
            P = float(s["P"][i])
            out.update({
                f"{pre}pressure_MPa": P, f"{pre}pressure_mmHg": P / MMHG,
                f"{pre}volume_mm3": float(V[i]), f"{pre}injected_mm3": float(s["injected"][i]),
                f"{pre}outflow_mm3": float(s["reservoir"][i]),
                f"{pre}produced_mm3": float(s["produced"][i]),
                f"{pre}aqueous_outflow_mm3": float(s["outflow"][i]),
                f"{pre}blood_expelled_mm3": float(s["blood"][i]),
                f"{pre}paracentesis_mm3": float(para[i]), f"{pre}drainage_mm3": float(drain[i]),
                f"{pre}drained_mm3": float(s["drained"][i]),
                f"{pre}compressed_mm3": float(s["compressed"][i]),
                f"{pre}balance_mm3": float(res[i]),
                f"{pre}outflow_rate_ul_min": float(fac[i] * (P - p_ev[i])),
                f"{pre}production_ul_min": float(prod[i])})
        out["time_min"] = float(params["time"]) + float(params["dt"])
        return out

    def point_fields(self, q, params, n_nodes) -> dict:
        """'<name>_pressure_MPa' (n_nodes,): the cavity pressure on wetted nodes, 0 elsewhere."""
        P, _ = self.pressures(q, params)
        f = np.zeros(n_nodes)
        f[self.dofs[:, ::3] // 3] = P[self.data["cav"]][:, None]
        return {f"{self.name}_pressure_MPa": f}


# --- closing a cavity between stages ----------------------------------------------------------

def close_cavity(model, q, theta, cavity: str, pressure_term: str | None = None, *,
                 bulk=None, release_load: bool = True):
    """Close a cavity at the current state (the seed's stage 1 -> 2); a Stage ``before`` hook
    through :func:`closing_hook` or ``functools.partial``.

    Sets P_ini = the pressure p of the PressureLoad ``pressure_term`` (or, without one, the
    cavity's own current pressure), V_ini = the current enclosed volume, dV = 0 (and, with
    regulation, the removed, produced and outflowed volumes; the clock runs on), and the
    bulk modulus to ``bulk`` if given (MPa; e.g. after a pressure-controlled stage with
    bulk 0). With ``release_load`` the pressure term's p is set to 0, so that the liquid
    replaces the surface load and the state stays in equilibrium whether or not that term
    stays active.

    Returns: (model, q, theta) with a new theta.
    """
    term = model.term(cavity)
    if not isinstance(term, FluidCavity):
        raise TypeError(f"close_cavity: term '{cavity}' is a {type(term).__name__}, not a FluidCavity")
    P, V = term.pressures(q, theta[cavity])
    if pressure_term is not None:
        if "p" not in theta.get(pressure_term, {}):
            model.term(pressure_term)
            raise ValueError(f"close_cavity: term '{pressure_term}' has no pressure param 'p'")
        P = np.full_like(V, float(theta[pressure_term]["p"]))
    new = {**theta[cavity], "p_ini": term._shape(P), "v_ini": term._shape(V), "dv": term._shape(0.0)}
    if term.regulation is not None:  # the balance restarts from the closed state
        new.update({k: term._shape(0.0) for k in ("paracentesis", "drainage", "aq_produced",
                                                  "aq_outflow")})
    if bulk is not None:
        if np.any(np.asarray(bulk) < 0):
            raise ValueError(f"close_cavity: bulk = {bulk} MPa; must be >= 0")
        new["bulk"] = term._shape(bulk)
    theta = {**theta, cavity: new}
    if pressure_term is not None and release_load:
        theta[pressure_term] = {**theta[pressure_term], "p": 0.0}
    log.info("cavity '%s' closed at P = %s mmHg, V = %s mm^3", cavity,
             _numbers(np.asarray(P) / MMHG, "%.4g"), _numbers(V, "%.7g"))
    return model, q, theta


def closing_hook(cavity: str, pressure_term: str | None = None, **kwargs):
    """A Stage ``before`` hook ``f(model, q, theta)`` running :func:`close_cavity`."""

    def hook(model, q, theta):
        return close_cavity(model, q, theta, cavity, pressure_term, **kwargs)

    return hook


def _numbers(values, fmt: str, most: int = 5) -> str:
    """'4846.79' for one value, '1, 2, 3 ...' for several (log messages print numbers,
    not arrays)."""
    v = np.ravel(np.asarray(values, float))
    out = ", ".join(fmt % x for x in v[:most])
    return out + (" ..." if len(v) > most else "")
