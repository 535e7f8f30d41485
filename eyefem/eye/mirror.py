"""The mirror half: a surgery solved on the half of the eye with y >= 0.

The eye is symmetric about the plane y = 0 (the plane through the optical axis z and the
optic nerve, which leaves toward +x); an encircling buckle with sutures spaced evenly
in meridian, or a segmental one centred on that plane, keeps the symmetry. The whole
eye's symmetric state is then found on half the eye: the elements whose centroid has
y > 0, the nodes on the plane held in y (their normal displacement), and every energy
term of the whole model restricted to symmetric states and halved:

    Pi_half(q_h) = Pi(P q_h) / 2,

where P lifts a half state q_h to the whole eye's symmetric state (a node with y < 0
moves as its mirror node with the y component reversed; an element's pressure
multiplier is its mirror element's). A mirror-invariant energy (Pi(M q) = Pi(q), M the
reflection) has a symmetric critical point wherever its restriction to symmetric states
has one (the principle of symmetric criticality), so the half's equilibrium is the
whole's symmetric equilibrium. Whether that state is the stable one the half cannot
tell (an ovalisation breaks the symmetry; ``eyefem stability`` on the whole eye does).

How each term is halved (:func:`half_model`):

- the solid: built on the half mesh (every element on one side: no element has its
  centroid on the plane); a relaxing wall (ViscoelasticQ1P0) too, its per-Gauss-point
  history the kept elements' (theta_half), lifted to an element with y < 0 from its
  mirror element's mirror Gauss points, each tensor reflected, R S R (theta_whole);
- the liquid cavity: a FluidCavity on the half of the wetted surface, open on the plane
  (``symmetry_planes = ("y",)``, its cone volumes about a point on the plane), whose
  volume is half the whole's: its extensive params (CAVITY_VOLUME_KEYS: volumes, the
  reservoir's compliance and, with volume regulation, the outflow facility, production,
  choroidal blood, removed volumes and the histories of produced and outflowed aqueous)
  are the whole's halved, its intensive ones (pressures, p_b, the clock and dt) the
  whole's, so its energy is W(2 V_half) / 2 and its pressure the whole's at every step
  of the surgery's timeline; its reported volumes and flows are doubled to the whole's;
- the surface pressure: a PressureLoad on the half of the wetted surface (its cone
  volumes about a point on the plane);
- every other term (zonule, lens springs, orbit, rigid buckle contact, sutures, ...),
  item by item (:class:`HalfTerm`): an item (bar, node, face) whose mirror image is
  another item is kept on the side y >= 0 with its full weight and dropped on the other;
  an item that is its own mirror image (a bar or contact node on the plane, the orbit's
  ring round the globe) or crosses the plane is kept with half its weight, evaluated on
  the lifted state. So a bar or suture lying on the plane carries half its stiffness.

The symmetry is checked, not assumed (:func:`check_mirror`): the mesh must map onto
itself under y -> -y (nodes within MIRROR_TOL of the mesh size, elements with their
tissues, node and face sets), every term's energy must be invariant under the
reflection at random states, the held dofs must be symmetric, and the half must
reproduce half the whole's energy of every term at random symmetric states; otherwise a
ValueError says which and why. The outcomes are those of the whole eye: each step's
half state is lifted to the whole and measured on the whole model (IOP, volumes, forces,
the plane's nodes). So are the written results (the Setup's ``whole``: VTU frames on the
whole mesh with the lifted state's fields, the reactions lifted from the half's residual,
:meth:`Mirror.lift_residual`) and the stability checks (``eyefem stability``, ``eyefem run
--stability``: the whole model's tangent at the lifted state, its modes free to break the
symmetry).
"""

from __future__ import annotations

import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.cavity import FluidCavity
from eyefem.fem.mesh import Mesh, hex_gauss_points, hex_shape
from eyefem.fem.solid import SolidQ1P0
from eyefem.fem.surface import PressureLoad
from eyefem.fem.terms import Term
from eyefem.fem.viscoelastic import ViscoelasticQ1P0
from eyefem.solve.model import Model
from eyefem.solve.problem import Setup, Whole

log = logging.getLogger(__name__)

__all__ = ["MIRROR_TOL", "Mirror", "HalfTerm", "HalfContact", "HalfCavity",
           "mirror", "half_model", "half_term", "check_mirror", "mirror_of", "mirror_setup",
           "theta_half", "theta_whole", "CAVITY_VOLUME_KEYS"]

MIRROR_TOL = 1e-8
"""Tolerance of the mirror map, relative to the mesh's size (its largest |coordinate|):
a node's mirror node lies within it of (x, -y, z), a node within it of y = 0 is on the
plane."""

ENERGY_RTOL = 1e-8
"""Relative tolerance of the energy checks (invariance under the reflection; the half's
energy against half the whole's), of each term's largest |energy| over the states tried."""

CAVITY_VOLUME_KEYS = ("v_ini", "dv", "c_out", "facility", "production", "blood_max",
                      "paracentesis", "drainage", "aq_produced", "aq_outflow")
"""A FluidCavity's params that scale with its volume (mm^3, mm^3/MPa; with volume
regulation, eyefem.fem.regulation: mm^3/(min MPa), mm^3/min, mm^3): the half cavity's are
the whole's halved. The others (p_ini, bulk, p_ev, blood_scale: MPa; time, dt: min) are
the whole's."""

REGULATION_VOLUME_FIELDS = ("facility", "production", "blood_max")
"""The extensive constants of a Regulation (the half cavity's are the whole's halved)."""

CAVITY_REPORT_SUFFIXES = ("_mm3", "_ul_min")
"""A cavity report's keys that scale with its volume (volumes, flows): the half's are
doubled to the whole eye's."""


@dataclasses.dataclass(frozen=True)
class Mirror:
    """The mirror map of a mesh about y = 0 and the half it keeps.

    Attributes:
      partner: (n_nodes,) each node's mirror node.
      partner_elem: (n_elem,) each element's mirror element.
      on_plane: (n_nodes,) nodes within the tolerance of y = 0.
      node_new: (n_nodes,) the half's node id of each node (a node with y < 0: its
        mirror node's).
      elem_new: (n_elem,) the half's element id of each element (one with its centroid
        at y < 0: its mirror element's).
      keep_nodes: (n_h,) whole ids of the half's nodes (y >= 0), ascending.
      keep_elems: (m_h,) whole ids of the half's elements (centroid y > 0), ascending.
      mesh: the half mesh (node and face sets restricted and renumbered).
      n_dof, n_dof_half: sizes of the whole's and the half's state vectors.
      dof_map: (n_dof,) the half's dof of each whole dof; dof_sign: (n_dof,) +1 or -1
        (the y component of a node with y < 0).
    """

    partner: np.ndarray
    partner_elem: np.ndarray
    on_plane: np.ndarray
    node_new: np.ndarray
    elem_new: np.ndarray
    keep_nodes: np.ndarray
    keep_elems: np.ndarray
    mesh: Mesh
    n_dof: int
    n_dof_half: int
    dof_map: np.ndarray
    dof_sign: np.ndarray

    @property
    def reflect_dofs(self) -> tuple[np.ndarray, np.ndarray]:
        """(index (n_dof,), sign (n_dof,)): (M q)[d] = sign[d] q[index[d]], the whole state
        reflected about y = 0."""
        n, m = len(self.partner), len(self.partner_elem)
        idx = np.arange(self.n_dof)
        sign = np.ones(self.n_dof)
        nodes = np.arange(3 * n) // 3
        comp = np.arange(3 * n) % 3
        idx[:3 * n] = 3 * self.partner[nodes] + comp
        sign[:3 * n][comp == 1] = -1.0
        idx[3 * n:3 * n + m] = 3 * n + self.partner_elem
        return idx, sign

    def lift(self, q_h) -> np.ndarray:
        """The whole eye's symmetric state (n_dof,) of a half state q_h (n_dof_half,)."""
        return self.dof_sign * np.asarray(q_h)[self.dof_map]

    def lift_traced(self, q_h):
        """:meth:`lift` for a JAX array q_h (n_dof_half,): traceable, so that a function of
        the whole eye's state is differentiated through it (the design simulators' stage
        carries and outcomes on the half)."""
        return jnp.asarray(self.dof_sign) * q_h[jnp.asarray(self.dof_map)]

    def lift_residual(self, g_h) -> np.ndarray:
        """The whole eye's residual dPi/dq (n_dof,) at the symmetric state lifted from a half
        state, from the half's residual g_h (n_dof_half,) there. The half's energy is half
        the whole's, so g_h = P^T g / 2: a half dof with two whole preimages (a node off the
        plane, an element) carries the whole's force at each, one with a single preimage (a
        node on the plane) half of it; the y force on the plane is 0 by the reflection
        (the half's is the hold's reaction)."""
        weight = 2.0 / np.bincount(self.dof_map, minlength=self.n_dof_half)
        g = np.asarray(g_h, np.float64) * weight
        g[self.plane_y_dofs] = 0.0
        return self.lift(g)

    def restrict(self, q) -> np.ndarray:
        """The half state (n_dof_half,) of a whole state q (n_dof,) (its y >= 0 side)."""
        own = self._own
        out = np.zeros(self.n_dof_half)
        out[self.dof_map[own]] = np.asarray(q)[own]
        return out

    @property
    def _own(self) -> np.ndarray:
        """Whole dofs that are the half's own (nodes y >= 0, kept elements, extras)."""
        n, m = len(self.partner), len(self.partner_elem)
        own = np.ones(self.n_dof, bool)
        node_own = np.isin(np.arange(n), self.keep_nodes)
        own[:3 * n] = np.repeat(node_own, 3)
        own[3 * n:3 * n + m] = np.isin(np.arange(m), self.keep_elems)
        return own

    @property
    def plane_y_dofs(self) -> np.ndarray:
        """The half's dofs of the plane nodes' y displacement (held at 0)."""
        return 3 * self.node_new[np.nonzero(self.on_plane)[0]] + 1


def _size(mesh: Mesh) -> float:
    return float(np.abs(mesh.nodes).max())


def mirror(mesh: Mesh, n_dof: int) -> Mirror:
    """The mirror map of ``mesh`` about y = 0 and its half (Mirror), for a model with
    ``n_dof`` unknowns (3 per node, one multiplier per element, then extras).

    ValueError, saying what is not symmetric, when a node has no mirror node within
    MIRROR_TOL, an element no mirror element of the same tissue, an element has its
    centroid on the plane, or a node or face set is not its own mirror image."""
    X = mesh.nodes
    tol = MIRROR_TOL * _size(mesh)
    from scipy.spatial import cKDTree

    tree = cKDTree(X)
    dist, partner = tree.query(X * np.array([1.0, -1.0, 1.0]))
    bad = np.nonzero(dist > tol)[0]
    if bad.size:
        i = int(bad[np.argmax(dist[bad])])
        raise ValueError(f"the mesh is not symmetric about y = 0: {bad.size} of {len(X)} nodes "
                         f"have no mirror node within {tol:.2g} mm (node {i} at "
                         f"{np.round(X[i], 4).tolist()} mm: the nearest to its mirror point is "
                         f"{dist[i]:.3g} mm away); symmetry = 'mirror' needs a mesh that maps "
                         "onto itself under y -> -y: set symmetry = 'none'")
    on_plane = np.abs(X[:, 1]) <= tol
    if not np.array_equal(partner[on_plane], np.nonzero(on_plane)[0]):
        raise ValueError("the mesh is not symmetric about y = 0: nodes on the plane are not "
                         "their own mirror nodes (duplicate nodes?); set symmetry = 'none'")
    keys = {tuple(sorted(h)): e for e, h in enumerate(mesh.hexes.tolist())}
    partner_elem = np.empty(mesh.n_elem, np.int64)
    for e, h in enumerate(mesh.hexes):
        j = keys.get(tuple(sorted(partner[h].tolist())))
        if j is None or mesh.material_ids[j] != mesh.material_ids[e]:
            other = "" if j is None else mesh.materials[mesh.material_ids[j]]
            what = ("no mirror element" if j is None
                    else f"a mirror element ({j}) of another tissue ('{other}')")
            raise ValueError(f"the mesh is not symmetric about y = 0: element {e} "
                             f"('{mesh.materials[mesh.material_ids[e]]}', centroid "
                             f"{np.round(X[h].mean(0), 3).tolist()} mm) has {what}; set "
                             "symmetry = 'none'")
        partner_elem[e] = j
    if mesh.material_fractions is not None and not np.allclose(
            mesh.material_fractions, mesh.material_fractions[partner_elem], atol=1e-9):
        raise ValueError("the mesh is not symmetric about y = 0: the tissues' volume "
                         "fractions (tissue_mixing) differ between mirror elements; set "
                         "symmetry = 'none'")
    cy = X[mesh.hexes].mean(1)[:, 1]
    mid = np.nonzero(np.abs(cy) <= tol)[0]
    if mid.size:
        raise ValueError(f"{mid.size} elements have their centroid on the plane y = 0 (e.g. "
                         f"element {mid[0]}): the half model cuts the mesh between elements; "
                         "set symmetry = 'none'")
    for name, ids in mesh.node_sets.items():
        if set(partner[ids].tolist()) != set(ids.tolist()):
            raise ValueError(f"node set '{name}' is not its own mirror image about y = 0; "
                             "set symmetry = 'none'")
    for name, faces in mesh.face_sets.items():
        have = {tuple(sorted(f)) for f in faces.tolist()}
        if {tuple(sorted(partner[f].tolist())) for f in faces} != have:
            raise ValueError(f"face set '{name}' is not its own mirror image about y = 0; "
                             "set symmetry = 'none'")
    keep_nodes = np.nonzero(X[:, 1] >= -tol)[0]
    keep_elems = np.nonzero(cy > 0)[0]
    node_new = np.full(len(X), -1, np.int64)
    node_new[keep_nodes] = np.arange(len(keep_nodes))
    neg = node_new < 0
    node_new[neg] = node_new[partner[neg]]
    elem_new = np.full(mesh.n_elem, -1, np.int64)
    elem_new[keep_elems] = np.arange(len(keep_elems))
    elem_new[elem_new < 0] = elem_new[partner_elem[elem_new < 0]]
    half = _half_mesh(mesh, keep_nodes, keep_elems, node_new)
    n, m, n_h, m_h = len(X), mesh.n_elem, len(keep_nodes), len(keep_elems)
    n_extra = n_dof - 3 * n - m
    dof_map = np.concatenate([(3 * node_new[:, None] + np.arange(3)).ravel(),
                              3 * n_h + elem_new, 3 * n_h + m_h + np.arange(n_extra)])
    dof_sign = np.ones(n_dof)
    dof_sign[3 * np.nonzero(X[:, 1] < -tol)[0] + 1] = -1.0
    return Mirror(partner, partner_elem, on_plane, node_new, elem_new, keep_nodes, keep_elems,
                  half, n_dof, 3 * n_h + m_h + n_extra, dof_map, dof_sign)


def _half_mesh(mesh: Mesh, keep_nodes, keep_elems, node_new) -> Mesh:
    """The mesh of the kept nodes and elements, its node and face sets restricted to them
    (renumbered), its element sets dropped."""
    kept = np.zeros(mesh.n_nodes, bool)
    kept[keep_nodes] = True
    node_sets = {k: node_new[v[kept[v]]] for k, v in mesh.node_sets.items()}
    face_sets = {k: node_new[v[np.all(kept[v], axis=1)]] for k, v in mesh.face_sets.items()}
    fr = None if mesh.material_fractions is None else mesh.material_fractions[keep_elems]
    return Mesh(mesh.nodes[keep_nodes], node_new[mesh.hexes[keep_elems]],
                mesh.material_ids[keep_elems], mesh.materials, node_sets, face_sets,
                material_fractions=fr)


def _take_items(tree, items, n_whole: int):
    """The leaves of ``tree`` with leading dimension ``n_whole`` (> 1) indexed by items;
    other leaves (global arrays, scalars) unchanged."""
    def take(a):
        if n_whole > 1 and np.ndim(a) >= 1 and np.shape(a)[0] == n_whole:
            return a[items]
        return a
    return jax.tree_util.tree_map(take, tree)


@dataclasses.dataclass(frozen=True)
class HalfTerm(Term):
    """A term of the whole model restricted to symmetric states, on the half's dofs: the
    items it keeps (``data["items"]`` of the whole term's), each weighted (1: its mirror
    image is a dropped item; 1/2: it is its own mirror image or crosses the plane) and
    evaluated on the lifted local state (local dof values times ``data["s"]``, -1 on the
    y component of a node with y < 0).

    Args: inner (the whole model's term); dofs (n, k) the half's dofs; data {"in": the
    inner term's data of the kept items, "items": (n,) their ids, "w": (n,) weights or
    None (all 1), "s": (n, k) signs or None (all +1)}. params: the whole term's (per-item
    params are taken at the kept items)."""

    name: str
    inner: Term
    dofs: np.ndarray
    data: dict
    n_whole: int
    mirror: Mirror = dataclasses.field(default=None, compare=False, repr=False)
    """The mirror map (lifts the half's state for the whole term's reports and fields)."""

    def __post_init__(self):
        for attr in ("contact", "dynamic", "pressure_stiffness"):
            object.__setattr__(self, attr, getattr(self.inner, attr))
        object.__setattr__(self, "multiplier_slots", self.inner.multiplier_slots)
        if self.inner.grad_hess_gauss_newton is not None:
            object.__setattr__(self, "grad_hess_gauss_newton", self._gauss_newton)

    @property
    def params(self):
        return self.inner.params

    def static_key(self) -> tuple:
        return ("half", type(self.inner), self.inner.static_key(), self.n_whole,
                self.data["w"] is None, self.data["s"] is None)

    def report(self, q, params) -> dict:
        """The whole term's report at the lifted state (forces of the whole eye)."""
        return self.inner.report(self.mirror.lift(q), params)

    def point_fields(self, q, params, n_nodes) -> dict:
        """The whole term's nodal fields at the lifted state, at the half's nodes."""
        n = len(self.mirror.partner)
        out = self.inner.point_fields(self.mirror.lift(q), params, n)
        return {k: (np.asarray(v)[self.mirror.keep_nodes] if np.shape(v)[:1] == (n,) else v)
                for k, v in out.items()}

    def geometry(self, q, params):
        """The whole term's own shape (a rigid buckle's surface, every suture) at the
        lifted state."""
        return self.inner.geometry(self.mirror.lift(q), params)

    def _args(self, q_loc, params, data):
        s = data["s"]
        return (q_loc if s is None else q_loc * s,
                _take_items(params, data["items"], self.n_whole), data["in"])

    def local_energy(self, q_loc, params, data):
        e = self.inner.local_energy(*self._args(q_loc, params, data))
        return e if data["w"] is None else data["w"] * e

    def local_grad_hess(self, q_loc, params, data):
        g, H = self.inner.local_grad_hess(*self._args(q_loc, params, data))
        return _weighted(g, H, data)

    def _gauss_newton(self, q, params, data, dofs):
        x, p, d = self._args(q[dofs], params, data)
        flat = jnp.arange(x.size).reshape(x.shape)
        g, H = self.inner.grad_hess_gauss_newton(x.ravel(), p, d, flat)
        return _weighted(g, H, data)


@dataclasses.dataclass(frozen=True)
class HalfContact(HalfTerm):
    """A HalfTerm of a penalty-contact term (energy 1/2 alpha p(g)^2 per item): its gaps'
    linearisation for the solver's look-ahead, ``data["alpha"]`` the kept items' penalties
    times their weights, ``smoothing`` the whole term's."""

    @property
    def smoothing(self):
        return self.inner.smoothing

    def gap_linearisation(self, q_loc, dq_loc, params, data):
        s = data["s"]
        x, p, d = self._args(q_loc, params, data)
        out = self.inner.gap_linearisation(x, dq_loc if s is None else dq_loc * s, p, d)
        if out is None:
            return None
        g, dg, G, g_new = out
        return g, dg, (G if s is None else G * s), g_new


def half_term(term: Term, mir: Mirror, n_nodes: int) -> HalfTerm:
    """The whole model's item term ``term`` restricted to symmetric states on the half
    (module docstring: which items it keeps and how they are weighted)."""
    if type(term).energy is not Term.energy or type(term).grad_hess is not Term.grad_hess \
            or type(term).low_rank is not Term.low_rank:
        raise ValueError(f"term '{term.name}' ({type(term).__name__}) couples its items "
                         "through the global state; the mirror half does not split it: set "
                         "symmetry = 'none'")
    if term.dynamic or type(term).update is not Term.update:
        raise ValueError(f"term '{term.name}' ({type(term).__name__}) re-pairs its items "
                         "between iterations; the mirror half does not split it: set "
                         "symmetry = 'none'")
    dofs = np.asarray(term.dofs)
    n_items, k = dofs.shape
    node_of = np.where(dofs < 3 * n_nodes, dofs // 3, -1)
    y_side = np.zeros(n_nodes, np.int64)  # +1 above, -1 below, 0 on the plane
    y_side[mir.keep_nodes] = 1
    y_side[mir.on_plane] = 0
    below = np.ones(n_nodes, bool)
    below[mir.keep_nodes] = False
    y_side[below] = -1
    keys = []
    for i in range(n_items):
        nodes = node_of[i][node_of[i] >= 0]
        keys.append(frozenset(nodes.tolist()))
    index: dict = {}
    for i, key in enumerate(keys):
        index.setdefault(key, []).append(i)
    keep, weights = [], []
    for i, key in enumerate(keys):
        nodes = np.array(sorted(key), np.int64)
        side = y_side[nodes]
        mkey = frozenset(mir.partner[nodes].tolist())
        js = index.get(mkey, [])
        paired = len(js) == 1 and js[0] != i and len(index[key]) == 1
        if paired and np.all(side >= 0):
            keep.append(i), weights.append(1.0)
        elif paired and np.all(y_side[np.array(sorted(mkey), np.int64)] >= 0):
            continue  # its mirror image is kept
        else:  # its own mirror image, or crossing the plane: half of it, lifted
            keep.append(i), weights.append(0.5)
    keep = np.asarray(keep, np.int64)
    w = np.asarray(weights)
    kd = dofs[keep]
    s = mir.dof_sign[kd]
    data = {"in": _take_items(term.data, keep, n_items), "items": keep,
            "w": None if np.all(w == 1.0) else w, "s": None if np.all(s == 1.0) else s}
    if type(term).gap_linearisation is Term.gap_linearisation:
        return HalfTerm(term.name, term, mir.dof_map[kd], data, n_items, mir)
    data["alpha"] = np.asarray(data["in"]["alpha"]) * (1.0 if data["w"] is None else data["w"])
    return HalfContact(term.name, term, mir.dof_map[kd], data, n_items, mir)


@dataclasses.dataclass(frozen=True)
class HalfCavity(FluidCavity):
    """The half of a FluidCavity (open on the plane y = 0): the FluidCavity's energy and
    pressure, its reported volumes (mm^3) and flows (uL/min) doubled to the whole eye's
    (CAVITY_REPORT_SUFFIXES); pressures and the clock as they are."""

    def report(self, q, params) -> dict:
        return {k: (2.0 * v if k.endswith(CAVITY_REPORT_SUFFIXES) else v)
                for k, v in super().report(q, params).items()}


def _plane_origin(origin) -> tuple:
    o = np.asarray(origin, np.float64).reshape(-1, 3)[0]
    return (float(o[0]), 0.0, float(o[2]))


def half_model(model: Model, mir: Mirror) -> Model:
    """The half of ``model`` (module docstring): the solid and cavity and surface pressures
    rebuilt on the half mesh, every other term a :class:`HalfTerm`."""
    terms = []
    for t in model.terms:
        if type(t) in (SolidQ1P0, ViscoelasticQ1P0):
            if t.elements is not None and len(t.elements) != model.mesh.n_elem:
                raise ValueError(f"term '{t.name}': a solid on a subset of the elements; the "
                                 "mirror half needs the whole mesh's solid")
            terms.append(dataclasses.replace(t, mesh=mir.mesh, elements=None,
                                             multiplier_offset=3 * mir.mesh.n_nodes))
        elif isinstance(t, FluidCavity):
            if t.symmetry_planes:
                raise ValueError(f"cavity '{t.name}' is already open on symmetry planes "
                                 f"{t.symmetry_planes}; the mirror half takes whole cavities")
            half = lambda v: None if v is None else np.asarray(v, np.float64) / 2  # noqa: E731
            origin = _plane_origin(t.data["origin"])
            fields = {f.name: getattr(t, f.name) for f in dataclasses.fields(t) if f.init}
            reg = t.regulation if t.regulation is None else dataclasses.replace(
                t.regulation, **{k: half(getattr(t.regulation, k))
                                 for k in REGULATION_VOLUME_FIELDS})
            terms.append(HalfCavity(**{**fields, "mesh": mir.mesh, "symmetry_planes": ("y",),
                                       "origin": origin, "v_ini": half(t.v_ini),
                                       "outflow_compliance": half(t.outflow_compliance),
                                       "regulation": reg}))
        elif type(t) is PressureLoad:
            terms.append(dataclasses.replace(t, mesh=mir.mesh,
                                             origin=_plane_origin(t.origin)))
        else:
            if isinstance(t, (SolidQ1P0, PressureLoad)):
                raise ValueError(f"term '{t.name}' ({type(t).__name__}): the mirror half "
                                 "rebuilds the plain Q1P0 solid and PressureLoad only; set "
                                 "symmetry = 'none' (or wall_element = 'q1p0')")
            terms.append(half_term(t, mir, model.mesh.n_nodes))
    return Model(mir.mesh, tuple(terms), mir.n_dof_half)


def theta_half(theta: dict, model: Model, mir: Mirror | None = None) -> dict:
    """The half's design pytree of the whole's ``theta``: a FluidCavity's volume-like
    params (CAVITY_VOLUME_KEYS) halved, a relaxing solid's per-element history
    (SOLID_HISTORY_KEYS) that of the kept elements (needs ``mir``), everything else the
    whole's."""
    out = _scaled(theta, model, 0.5)
    for t in _relaxing(model, theta):
        out[t.name] = {**out[t.name], **{k: np.asarray(theta[t.name][k])[_need(mir).keep_elems]
                                         for k in SOLID_HISTORY_KEYS}}
    return out


def theta_whole(theta: dict, model: Model, mir: Mirror | None = None) -> dict:
    """The whole's design pytree of the half's ``theta`` (the inverse of theta_half): a
    relaxing solid's history of an element with y < 0 is its mirror element's at the
    mirror Gauss points, reflected (R S R, R = diag(1, -1, 1))."""
    out = _scaled(theta, model, 2.0)
    for t in _relaxing(model, theta):
        m = _need(mir)
        e, g = _gauss_partner(m, model.mesh)
        R = np.array([1.0, -1.0, 1.0])
        h = np.asarray(theta[t.name]["h"])[m.elem_new[:, None], g]  # (n, 8, k, 3, 3)
        s = np.asarray(theta[t.name]["s_prev"])[m.elem_new[:, None], g]  # (n, 8, 3, 3)
        flip = np.where(e, 1.0, R[:, None] * R[None, :])  # (n, 3, 3) per element
        out[t.name] = {**out[t.name], "h": h * flip[:, None, None], "s_prev": s * flip[:, None]}
    return out


SOLID_HISTORY_KEYS = ("h", "s_prev")
"""A relaxing solid's (ViscoelasticQ1P0) per-element, per-Gauss-point history params."""


def _relaxing(model: Model, theta: dict) -> list:
    return [t for t in model.terms if isinstance(t, ViscoelasticQ1P0) and t.name in theta]


def _need(mir):
    if mir is None:
        raise ValueError("a relaxing solid's history needs the mirror map: pass mir")
    return mir


def _gauss_partner(mir: Mirror, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """(own (n_elem, 1, 1) bool: the element is the half's own; g (n_elem, 8): the Gauss
    point of the half's element that each whole element's Gauss point is the mirror image
    of (its own for a kept element)), cached on the Mirror."""
    got = mir.__dict__.get("_gauss")
    if got is not None:
        return got
    n_g, _ = hex_shape(hex_gauss_points()[0])  # (8 g, 8 a)
    xg = np.einsum("ga,eai->egi", n_g, mesh.nodes[mesh.hexes])  # (n, 8, 3)
    own = np.zeros(mesh.n_elem, bool)
    own[mir.keep_elems] = True
    src = np.where(own, np.arange(mesh.n_elem), mir.partner_elem)
    target = xg[src]  # the source element's Gauss points
    mine = xg * np.array([1.0, -1.0, 1.0])
    mine[own] = xg[own]
    d = np.linalg.norm(mine[:, :, None, :] - target[:, None, :, :], axis=-1)  # (n, 8, 8)
    g = np.argmin(d, axis=2)
    tol = MIRROR_TOL * _size(mesh)
    if np.any(d.min(axis=2) > tol) or np.any(np.sort(g, axis=1) != np.arange(8)):
        raise ValueError("the mirror map of the Gauss points is not one to one; set "
                         "symmetry = 'none'")
    got = (own[:, None, None], g)
    object.__setattr__(mir, "_gauss", got)
    return got


def _scaled(theta: dict, model: Model, f: float) -> dict:
    out = dict(theta)
    for t in model.terms:
        if isinstance(t, FluidCavity) and t.name in theta:
            out[t.name] = {k: (v * f if k in CAVITY_VOLUME_KEYS else v)
                           for k, v in theta[t.name].items()}
    return out


def _stage_params(params: dict, model: Model) -> dict:
    return _scaled(params, model, 0.5)


def half_prescribed(prescribed, mir: Mirror, stage: str) -> tuple[np.ndarray, np.ndarray]:
    """A stage's held dofs and targets on the half, with the plane nodes' y displacement
    held at 0. ValueError when the whole's targets are not symmetric."""
    dofs, vals = (np.asarray(a) for a in prescribed)
    hd, hv = mir.dof_map[dofs], mir.dof_sign[dofs] * vals
    order = np.argsort(hd, kind="stable")
    hd, hv = hd[order], hv[order]
    first = np.r_[True, hd[1:] != hd[:-1]]
    ref = np.repeat(hv[first], np.diff(np.r_[np.nonzero(first)[0], len(hd)]))
    if np.any(np.abs(hv - ref) > 1e-12 * max(1.0, np.abs(vals).max(initial=0.0))):
        raise ValueError(f"stage '{stage}': its prescribed displacements are not symmetric "
                         "about y = 0; set symmetry = 'none'")
    hd, hv = hd[first], hv[first]
    plane = mir.plane_y_dofs
    on = np.isin(hd, plane)
    if np.any(np.abs(hv[on]) > 0):
        raise ValueError(f"stage '{stage}': it prescribes a y displacement to nodes on the "
                         "plane y = 0; set symmetry = 'none'")
    extra = plane[~np.isin(plane, hd)]
    return np.r_[hd, extra], np.r_[hv, np.zeros(len(extra))]


CHECK_STATES = ((0.3, 0.0), (0.6, 0.0), (-0.3, -1.0))
"""The states of the symmetry checks: (radial displacement of every node, mm; value of
every extra unknown), with random displacements, multipliers and extras (0.02) on top.
Pushed out, the sclera presses into a rigid buckle (its contact works); pulled in with the
buckle moved out by 1 mm, the sutures are stretched (their energy is not zero)."""


def _random_states(model: Model, rng):
    """The whole states of CHECK_STATES (n_dof,) each."""
    X = model.mesh.nodes
    r = np.linalg.norm(X, axis=1, keepdims=True)
    radial = (X / np.maximum(r, 1e-12)).ravel()
    n_extra = model.n_dof - 3 * len(X) - model.mesh.n_elem
    out = []
    for push, extra in CHECK_STATES:
        q = rng.normal(scale=0.02, size=model.n_dof)
        q[:3 * len(X)] += push * radial
        q[model.n_dof - n_extra:] += extra
        out.append(q)
    return out


def check_mirror(model: Model, theta: dict, half: Model, mir: Mirror, where: str,
                 seed: int = 0, names=None) -> None:
    """Check (ValueError naming the term) that every term (or those in ``names``) of the
    whole ``model`` that the half splits item by item (a :class:`HalfTerm`: the buckle's
    contact, the sutures, the zonule, springs...) is invariant under the reflection about
    y = 0 at random states with the design ``theta``, and that its half has half its
    energy at the symmetric states lifted from random half states; and that each liquid
    cavity's half (:class:`HalfCavity`, its params theta_half's: with volume regulation
    the step's dt and history as ``theta`` has them) has half the whole cavity's energy
    at those states. The solid (isotropic tissues), the cavity and the surface pressure
    are symmetric when the mesh, its tissues and face sets are, which :func:`mirror`
    checks."""
    rng = np.random.default_rng(seed)
    idx, sign = mir.reflect_dofs
    th_h = theta_half(theta, model, mir)
    states = _random_states(model, rng)
    for t in model.terms:
        if names is not None and t.name not in names:
            continue
        if isinstance(half.term(t.name), HalfCavity):
            _check_half_cavity(model, t, theta[t.name], half, th_h[t.name], mir, states,
                               sign, idx, where)
        if not isinstance(half.term(t.name), HalfTerm):
            continue  # the solid, cavity and pressure: symmetric with the mesh (mirror())
        p = theta[t.name]
        energy = model._kernel(t, "energy")  # compiled (and shared with the solver's)
        e = [float(energy(jnp.asarray(q), p, t.data, t.dofs)) for q in states]
        em = [float(energy(jnp.asarray(sign * q[idx]), p, t.data, t.dofs)) for q in states]
        scale = max(max(abs(v) for v in e + em), 1e-30)
        worst = max(abs(a - b) for a, b in zip(e, em))
        if worst > ENERGY_RTOL * scale:
            raise ValueError(
                f"{where}: term '{t.name}' is not symmetric about the plane y = 0 (its energy "
                f"changes by {worst / scale:.2g} of itself when the state is reflected): "
                "symmetry = 'mirror' needs an encircling buckle with its sutures spaced "
                "evenly round it and not turned (suture_angle_deg = 0), or a segmental "
                "buckle centred on the plane (buckle_meridian_deg = 0 or 180); set "
                "symmetry = 'none' for this case")
        h = half.term(t.name)
        ph = th_h[t.name]
        energy_h = half._kernel(h, "energy")
        for q in states:
            qs = mir.restrict(0.5 * (q + sign * q[idx]))
            qs[mir.plane_y_dofs] = 0.0
            ew = float(energy(jnp.asarray(mir.lift(qs)), p, t.data, t.dofs))
            eh = float(energy_h(jnp.asarray(qs), ph, h.data, h.dofs))
            if abs(2 * eh - ew) > ENERGY_RTOL * max(abs(ew), scale):
                raise ValueError(f"{where}: the half of term '{t.name}' has energy {eh:.6g} "
                                 f"at a symmetric state, not half the whole's {ew:.6g}; the "
                                 "mirror half cannot represent this term: set symmetry = "
                                 "'none'")


def _check_half_cavity(model: Model, t: FluidCavity, p: dict, half: Model, ph: dict,
                       mir: Mirror, states, sign, idx, where: str) -> None:
    """ValueError unless the half of cavity ``t`` (params ``ph``) has half the energy of
    the whole's (params ``p``) at the symmetric states of ``states`` (whole, (n_dof,)
    each): its extensive params halved right (CAVITY_VOLUME_KEYS)."""
    h = half.term(t.name)
    energy, energy_h = model._kernel(t, "energy"), half._kernel(h, "energy")
    for q in states:
        qs = mir.restrict(0.5 * (q + sign * q[idx]))
        qs[mir.plane_y_dofs] = 0.0
        ew = float(energy(jnp.asarray(mir.lift(qs)), p, t.data, t.dofs))
        eh = float(energy_h(jnp.asarray(qs), ph, h.data, h.dofs))
        if not abs(2 * eh - ew) <= ENERGY_RTOL * max(abs(ew), abs(2 * eh), 1e-30):
            raise ValueError(f"{where}: the half of cavity '{t.name}' has energy {eh:.6g} N mm "
                             f"at a symmetric state, not half the whole's {ew:.6g} N mm: a "
                             "param of the cavity does not scale with its volume as "
                             "CAVITY_VOLUME_KEYS says; set symmetry = 'none'")


class _NotDifferentiable:
    """The Setup.parts of a mirror half: what reads the parts works on the whole eye (the
    design simulators keep the whole Setup's parts and halve it themselves,
    eyefem.eye.simulators.SurgerySimulator) and is refused here with the reason."""

    def __getattr__(self, name):
        raise ValueError("symmetry = 'mirror' solves half the eye, and the parts of a surgery "
                         "describe the whole eye: build them from the case with symmetry = "
                         "'none' (eyefem.eye.surgery.surgery)")


def mirror_of(model: Model) -> Mirror | None:
    """The mirror map of ``model``'s mesh (:func:`mirror`), or None with a warning for a
    symmetric mesh that the half cannot cut between elements (elements across the plane
    y = 0: odd levels such as 'half', 'graded_half'), which is solved whole."""
    cy = model.mesh.nodes[model.mesh.hexes].mean(1)[:, 1]
    across = int(np.sum(np.abs(cy) <= MIRROR_TOL * _size(model.mesh)))
    if across:
        log.warning("symmetry = 'mirror': %d elements of this mesh lie across the plane y = 0 "
                    "(a level with an odd number of elements per patch edge, such as 'half'), "
                    "so the half model cannot cut it between elements: the whole eye is "
                    "solved", across)
        return None
    return mirror(model.mesh, model.n_dof)


def mirror_setup(setup: Setup, check: bool = True, mir: Mirror | None = None) -> Setup:
    """The mirror half of a surgery's Setup (module docstring): its model on the half,
    its stages with the plane nodes held in y and their hooks run on the lifted whole
    state, its probe measuring the whole eye, its ``whole`` (eyefem.solve.problem.Whole)
    lifting a half state to the whole eye's for the written results (VTU frames on the
    whole mesh, reactions lifted from the half's residual) and the stability checks.
    ValueError (say why) when the case is not symmetric about y = 0. A mesh with elements across the plane (odd levels: 'half',
    'graded_half', ...) cannot be cut between elements: the whole Setup, with a warning.
    ``mir``: the mesh's mirror map when the caller has it (:func:`mirror_of`)."""
    p = getattr(setup.parts, "p", {}) or {}
    for key, off, why in (("buckle_body", "rigid", "a deformable buckle's band, tire or sponge"),):
        if p.get(key, off) != off:
            raise ValueError(f"symmetry = 'mirror' with {key} = {p[key]!r}: the mirror half "
                             f"is implemented for the rigid buckle without {why}; set "
                             f"symmetry = 'none' or {key} = {off!r}")
    whole = setup.model
    mir = mirror_of(whole) if mir is None else mir
    if mir is None:  # a symmetric mesh the half cannot cut (an odd count of elements per edge)
        return setup
    half = half_model(whole, mir)
    theta0 = whole.theta0()
    for st in setup.stages:  # each stage's params on the model they act on
        theta0 = {**theta0, **{k: {**theta0.get(k, {}), **v} for k, v in st.params.items()
                               if k in theta0}}
    if check:
        check_mirror(whole, theta0, half, mir, "the case")
    wholes = {id(half): (half, whole)}  # each half model's whole (kept alive with it)

    def whole_of(model_h):
        got = wholes.get(id(model_h))
        return got[1] if got is not None and got[0] is model_h else wholes["last"][1]

    wholes["last"] = (half, whole)

    def hooked(before, stage_name):
        if before is None:
            return None

        def hook(model_h, q_h, theta_h):
            mw = whole_of(model_h)
            mw2, qw2, thw2 = before(mw, mir.lift(q_h), theta_whole(theta_h, mw, mir))
            changed = [t.name for t, u in zip(mw.terms, mw2.terms) if t is not u]
            halves = {t.name: t for t in model_h.terms}
            new_h = half_model(mw2, mir) if changed else model_h
            if changed:  # unchanged terms keep their halves (and compiled kernels)
                new_h = new_h.with_terms([halves[t.name] if t.name not in changed else t
                                          for t in new_h.terms])
                if check:
                    check_mirror(mw2, thw2, new_h, mir, f"stage '{stage_name}'", names=changed)
            wholes[id(new_h)] = wholes["last"] = (new_h, mw2)
            q2 = mir.restrict(qw2)
            q2[mir.plane_y_dofs] = 0.0
            return new_h, q2, theta_half(thw2, mw2, mir)
        return hook

    stages = [dataclasses.replace(st, prescribed=half_prescribed(st.prescribed, mir, st.name),
                                  params=_stage_params(st.params, whole),
                                  before=hooked(st.before, st.name))
              for st in setup.stages]

    def lift(model_h, q_h, theta_h):
        mw = whole_of(model_h)
        return mw, mir.lift(q_h), theta_whole(theta_h, mw, mir)

    def probe(model_h, q_h, theta_h):
        return setup.probe(*lift(model_h, q_h, theta_h))

    log.info("mirror half: %d of %d elements, %d of %d nodes (%d on the plane y = 0), %d of "
             "%d unknowns; it finds the symmetric state (the results are written on the whole "
             "eye; --stability checks the whole eye's modes, which may break the symmetry)",
             mir.mesh.n_elem, whole.mesh.n_elem, mir.mesh.n_nodes, whole.mesh.n_nodes,
             int(mir.on_plane.sum()), mir.n_dof_half, whole.n_dof)
    q0 = None if setup.q0 is None else mir.restrict(setup.q0)
    whole_setup = Whole(whole, list(setup.stages), setup.q0, lift, solved="mirror half y > 0",
                        residual=mir.lift_residual)
    return dataclasses.replace(setup, model=half, stages=stages, probe=probe,
                               parts=_NotDifferentiable(), q0=q0, whole=whole_setup)


def _weighted(g, H, data):
    """Item gradients (n, k) and Hessians (n, k, k) with the half term's dof signs ``s``
    (n, k) and item weights ``w`` (n,) applied (each None when it does not apply)."""
    s, w = data["s"], data["w"]
    if s is not None:
        g, H = g * s, H * s[:, :, None] * s[:, None, :]
    if w is not None:
        g, H = g * w[:, None], H * w[:, None, None]
    return g, H
