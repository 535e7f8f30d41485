"""Reading FEBio 4 input decks into eyefem (the mapping: eyefem.io.febio, docs/febio.md).

Materials as FEBio defines them (eyefem.fem.materials): "Mooney-Rivlin" is uncoupled,
W = c1 (I1bar - 3) + c2 (I2bar - 3) + k/2 (ln J)^2 with the deck's k, on FEBio's
three-field hex8 (U on the element's volume ratio; eyefem.fem.solid_compressible);
"neo-Hookean" (E, v) and "coupled Mooney-Rivlin" (c1, c2, k) are coupled, at every Gauss
point; FEBio's further laws (Ogden, Holmes-Mow, trans iso, orthotropic, ..., solid
mixtures, prescribed active contraction; eyefem.fem.materials.FEBIO_LAWS) are FebioLaw
materials on eyefem.fem.solid_compressible.SolidFebioLaw, with their fibres and material
axes. Beyond the hex8 solids: linear trusses (:class:`LinearTruss`, FEBio's E ln(lam)
law), discrete linear springs (:class:`LinearSpring`), rigid bodies whose six dofs are
all fixed or prescribed (their nodes prescribed), frictionless penalty sliding-elastic
contact against a rigid body's facets (eyefem.fem.rigid_contact.RigidContact) and the
penalty volume constraint (a closed liquid cavity, eyefem.fem.cavity.FluidCavity). Other
types, parameters and sections are refused by name.

Decks are checked like case files: ids and id ranges (bounded by the deck's node count
before anything is allocated), finite numbers, the material constants against the case
files' ranges (eyefem.io.casefile), the number of load steps (MAX_TIME_STEPS), the
analysis type (static only). A pressure on an open surface is FEBio's follower load
(eyefem.fem.surface.pressure_term).

Length: one reader per deck section, each with the messages that name the file, the tag
and the value it cannot read; about 2100 lines.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import logging
import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from eyefem.fem.materials import (FEBIO_LAWS, CoupledMooneyRivlin, FebioLaw, MooneyRivlin,
                                  UncoupledMooneyRivlin, febio_neo_hookean)
from eyefem.fem.mesh import Mesh, hex_geometry
from eyefem.fem.surface import pressure_term
from eyefem.fem.terms import NodalForce, Term
from eyefem.io.casefile import material_c10_field, unit_slip
from eyefem.solve.problem import Setup
from eyefem.solve.model import Model, node_dofs, solid_model
from eyefem.solve.solver import Stage

SPEC_VERSION = "4.0"
"""The FEBio input format written and read (febio_spec version)."""


class FebError(ValueError):
    """An FEBio deck that eyefem cannot read (names the file and the offending tag)."""


log = logging.getLogger(__name__)

_XYZ = "xyz"

MAX_TIME_STEPS = 10_000
"""Most load steps (``<time_steps>``) a deck may ask for: each is a Newton solve, and
eyefem ramps a step's loads linearly, so tens of steps suffice. The environment
variable EYEFEM_MAX_STEPS raises it."""

STIFF_SOLID_C1 = 1e6
"""MPa: a deck's c1 (or E / (4 (1 + v))) above the case files' impossible bound (1e4 MPa,
eyefem.io.casefile) and up to this is warned, not refused. An FEBio deck states its own
materials, and the suite's decks include steel (E = 200 GPa: c1 = 3.8e4 MPa) and stiff
indenters (c1 = 1e5 MPa); no solid is stiffer than diamond (c1 about 3e5 MPa), so a value
above 1e6 MPa is still refused as a unit slip (25 MPa rubber written in Pa: 2.5e7)."""

MIN_SHEAR_MODULUS = 1e-6
"""MPa (1 Pa): a material's initial shear modulus 2 (c1 + c2) below it is refused (no
solid the reader solves is that soft; the tangent would be singular to roundoff)."""


def max_time_steps() -> int:
    """MAX_TIME_STEPS, or the environment's EYEFEM_MAX_STEPS where set (a whole number)."""
    raw = os.environ.get("EYEFEM_MAX_STEPS", "").strip()
    try:
        return int(raw) if raw else MAX_TIME_STEPS
    except ValueError:
        raise FebError(f"EYEFEM_MAX_STEPS = '{raw}' is not a whole number; unset it or give "
                       "the most load steps a deck may ask for, e.g. 100000") from None


# --------------------------------------------------------------------------- reading
@dataclasses.dataclass(frozen=True)
class FebLoads:
    """The load step of a deck, in eyefem's terms.

    Attributes:
      prescribed: (dofs (n,), targets (n,) mm) at the end of the step (from zero).
      pressures: (name, face set, p at the start, p at the end) per pressure load, MPa.
      n_steps: FEBio's time_steps.
      bulk_moduli: material name -> the deck's <k> (MPa; 0 for neo-Hookean, which has
        none). eyefem uses it (eyefem.fem.materials), except with <laugon>1</laugon>
        (exactly incompressible).
      steps: one :class:`FebStep` per FEBio step (prescribed, pressures and n_steps above
        are the first one's).
      forces: (name, dofs (n,), f at t = 0 (n,) N) per nodal force term (nodal loads, and
        body loads as the nodal forces of the element volumes).
      links: one :class:`FebLinks` per truss domain and per discrete set.
      rigid: rigid body name -> its node ids (n,) (each moved as the deck prescribes).
      contacts: one :class:`FebContact` per sliding contact with a rigid surface.
      volumes: (name, face set, FEBio's penalty eps MPa/mm^3, step index or None: the
        model's) per volume constraint (:func:`volume_term`).
      fibers: material name -> (n, 8, n_fibers, 3) unit fibre directions at the Gauss
        points of its n elements (mesh order), for the FebioLaw materials with fibres.
      law_constants: material name -> its constants at t = 0, for the FebioLaw materials
        with constants on a load curve (each step's are in its params, "solid:<name>").
    """

    prescribed: tuple[np.ndarray, np.ndarray]
    pressures: tuple[tuple[str, str, float, float], ...]
    n_steps: int
    bulk_moduli: dict
    steps: tuple = ()
    forces: tuple = ()
    links: tuple = ()
    rigid: dict = dataclasses.field(default_factory=dict)
    contacts: tuple = ()
    volumes: tuple = ()
    fibers: dict = dataclasses.field(default_factory=dict)
    law_constants: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class FebLinks:
    """Two-node elements of a deck: a truss domain or a discrete set.

    Attributes:
      name: the domain's or the set's name.
      kind: "linear truss" (FEBio's truss material: :class:`LinearTruss`), "linear spring"
        or "tension-only linear spring" (FEBio's discrete springs: eyefem.fem.bars.Bars).
      nodes: (m, 2) node ids.
      stiffness: (m,) E x A (N) of a truss; E (N/mm) of a spring.
    """

    name: str
    kind: str
    nodes: np.ndarray
    stiffness: np.ndarray


@dataclasses.dataclass(frozen=True)
class FebContact:
    """FEBio's frictionless "sliding-elastic" contact of a deformable surface (primary)
    against a rigid body's facets (secondary), as eyefem.fem.rigid_contact.RigidContact.

    Attributes: name; primary: the face set; body: the rigid body's name; facets (m, 4)
      node ids of the secondary faces; direction (3,) unit direction of the body's motion;
      d (n_steps,) its motion along it at each step's end, mm; penalty: eyefem's alpha
      per node, N/mm (FEBio's penalty, MPa/mm, times the primary nodes' mean tributary
      area, mm^2); steps: the indices of the steps it acts in (a step's <Contact>: FEBio
      deactivates a step's components at its end), or None (the model's: every step).
    """

    name: str
    primary: str
    body: str
    facets: np.ndarray
    direction: np.ndarray
    d: tuple
    penalty: float
    steps: tuple | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class LinearTruss(Term):
    """FEBio's "linear truss" (FELinearTrussMaterial on a linear-truss domain): the
    Kirchhoff stress tau = E ln(lam), lam = l / L, and the axial force T = tau A L / l
    (FELinearTrussDomain::ElementInternalForces), i.e. the energy per truss

        e = 1/2 E A L (ln(l / L))^2                                      [N mm]

    It differs from eyefem.fem.bars.Bars (1/2 EA / L (l - L)^2) at second order in the
    strain (the force EA ln(lam) / lam against EA (lam - 1): 1.5 % apart at 1 % strain), so
    a deck's trusses are this term. FEBio's Poisson's ratio <v> changes only the reported
    stress, not the force.

    Args: name; nodes (m, 2) node ids; node_xyz (n_nodes, 3) reference positions, mm;
      EA (m,) E x cross-sectional area, N (params {"EA"}).
    """

    name: str
    nodes: np.ndarray
    node_xyz: np.ndarray
    EA: np.ndarray

    def __post_init__(self):
        n = np.asarray(self.nodes, np.int64).reshape(-1, 2)
        X = np.asarray(self.node_xyz, np.float64)[n]
        L = np.linalg.norm(X[:, 1] - X[:, 0], axis=1)
        EA = np.broadcast_to(np.asarray(self.EA, np.float64), (len(n),)).copy()
        if np.any(L <= 0) or np.any(EA <= 0):
            raise ValueError(f"truss '{self.name}': every truss needs two distinct nodes and "
                             "E A > 0")
        object.__setattr__(self, "dofs", (3 * n[:, :, None] + np.arange(3)).reshape(-1, 6))
        object.__setattr__(self, "params", {"EA": EA})
        object.__setattr__(self, "data", {"X": X.reshape(-1, 6), "L0": L})

    def local_energy(self, q_loc, params, data):
        x = (data["X"] + q_loc).reshape(-1, 2, 3)
        l = jnp.sqrt(jnp.sum((x[:, 1] - x[:, 0]) ** 2, axis=1))
        return 0.5 * params["EA"] * data["L0"] * jnp.log(l / data["L0"]) ** 2

    def forces(self, q, params):
        """Axial force per truss (m,), N (positive in tension): EA ln(lam) / lam."""
        x = (self.data["X"] + np.asarray(q)[self.dofs]).reshape(-1, 2, 3)
        lam = np.linalg.norm(x[:, 1] - x[:, 0], axis=1) / self.data["L0"]
        return np.asarray(params["EA"]) * np.log(lam) / lam

    def report(self, q, params):
        f = self.forces(q, params)
        return {"max_force_N": float(np.abs(f).max()) if len(f) else 0.0}


@dataclasses.dataclass(frozen=True)
class FebStep:
    """One FEBio <step> (or the deck's single analysis) in eyefem's terms.

    Attributes:
      name: the step's name.
      n_steps: its time_steps.
      t_end: FEBio's time at its end (the sum of time_steps x step_size so far).
      prescribed: (dofs, targets mm) held during the step: the model's boundary conditions
        and the step's own, at the step's end time.
      params: term name -> params at the step's end: {"p": MPa} per pressure, {"f": (n,) N}
        per nodal force (zero where the load is not active in the step).
    """

    name: str
    n_steps: int
    t_end: float
    prescribed: tuple[np.ndarray, np.ndarray]
    params: dict


def _err(path, msg):
    return FebError(f"{path}: {msg}")


def _penalty_form(path, el, where: str, why: str):
    """Refuse an element whose <laugon> asks for anything but the penalty form (0, PENALTY,
    FALSE), saying ``why`` after its name ``where``."""
    lau = (el.findtext("laugon") or "0").strip().upper()
    if lau not in ("0", "PENALTY", "FALSE"):
        raise _err(path, f"{where}: <laugon> {lau}: {why}")


def _floats(text, path, what, hint="give a finite number") -> list[float]:
    """The numbers of a tag's text (comma or space separated); FebError naming ``what``
    and the token for text or a value that is not finite (``hint``: the fix)."""
    out = []
    for tok in (text or "").replace(",", " ").split():
        try:
            v = float(tok)
        except ValueError:
            raise _err(path, f"{what}: '{tok[:40]}' is not a number ({hint})") from None
        if not math.isfinite(v):
            raise _err(path, f"{what}: '{tok[:40]}' is not a finite number ({hint})")
        out.append(v)
    return out


def _ints(text, path, what, limit: int) -> list[int]:
    """Comma-separated ids with FEBio's 'a:b' (and 'a:b:step') ranges. A reversed range, a
    range or a list longer than ``limit`` ids (the deck's node count: more cannot name
    distinct nodes) is refused before any list is built."""
    out, n = [], 0
    for tok in (text or "").replace(",", " ").split():
        try:
            parts = [int(v) for v in tok.split(":")]
        except ValueError:
            parts = []
        if not 1 <= len(parts) <= 3:
            raise _err(path, f"{what}: '{tok[:40]}' is not a node or element id (a whole "
                       "number, or a range first:last)")
        if len(parts) == 1:
            out.append(parts[0])
            n += 1
            if n > limit:
                raise _err(path, f"{what}: more ids than the {limit} nodes in <Nodes>; give "
                           "each id once")
            continue
        a, b, step = parts if len(parts) == 3 else (*parts, 1)
        if step < 1:
            raise _err(path, f"{what}: range '{tok}' has step {step}; the step of "
                       "'first:last:step' must be >= 1")
        if b < a:
            raise _err(path, f"{what}: range '{tok}' is reversed (it names no id); write it "
                       f"first:last, e.g. '{b}:{a}'")
        count = (b - a) // step + 1
        if n + count > limit:
            raise _err(path, f"{what}: range '{tok}' makes {n + count} ids, more than the "
                       f"{limit} nodes in <Nodes> (the bound of a set); give ids of nodes the "
                       "deck defines")
        out.extend(range(a, b + 1, step))
        n += count
    return out


def _id(el, path, what) -> int:
    """The whole-number ``id`` attribute of a tag; FebError naming the tag when it is
    missing or not a whole number."""
    raw = el.get("id")
    if raw is None:
        raise _err(path, f"{what}: a <{el.tag}> has no id attribute; give each "
                   f"<{el.tag} id=\"N\"> a whole number")
    try:
        return int(raw)
    except ValueError:
        raise _err(path, f"{what}: <{el.tag} id=\"{raw[:40]}\">: the id is not a whole "
                   f"number; give each <{el.tag}> a whole-number id") from None


def _child_float(el, tag, path, where, default=None, hint="give a finite number") -> float:
    c = el.find(tag)
    if c is None:
        if default is not None:
            return default
        raise _err(path, f"{where}: <{tag}> is missing")
    v = _floats(c.text, path, f"{where} <{tag}>", hint)
    if len(v) != 1:
        raise _err(path, f"{where} <{tag}>: expected one number, got '{c.text}'")
    return v[0]


_IGNORED = {"Globals", "Output", "Module", "Control", "Material", "Mesh", "MeshDomains",
            "Boundary", "Loads", "LoadData", "Step", "Discrete", "Rigid", "Contact",
            "Constraints"}


def read_feb(path) -> tuple[Mesh, dict, FebLoads]:
    """Read an FEBio 4 deck (static steps of hex8 solids, trusses, springs, rigid bodies
    moved as prescribed, contact against them, volume constraints; see the module).

    Returns: the mesh (materials named as in the deck, face sets from the Surfaces, node
      sets from the NodeSets; a rigid body's elements left out), the materials (name ->
      UncoupledMooneyRivlin with c10 = c1, c01 = c2 and the deck's k, or MooneyRivlin where
      k = 0 or laugon = 1; CoupledMooneyRivlin for "neo-Hookean" and "coupled
      Mooney-Rivlin"; FebioLaw for the further laws and mixtures) and the loads
      (:class:`FebLoads`: steps, loads, trusses and springs, rigid bodies, contacts, volume
      constraints, fibre directions).
    Raises: FebError (a ValueError) naming the file and the tag, element or value it
      cannot read: another spec version, tetrahedra or deformable shells, another material
      or material parameter, a pressure model other than FEBio's default, contact or a
      constraint eyefem does not map, a rigid body with a free dof, a dynamic analysis, an
      interpolation FEBio has and eyefem does not, ids or id ranges that name no node,
      numbers that are not finite, material constants outside the case files' ranges, more
      than MAX_TIME_STEPS steps; OSError.
    """
    return read_feb_deck(path)[:3]


def deck_sha256(path) -> str:
    """The sha256 (hex) of a deck's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def read_feb_deck(path) -> tuple[Mesh, dict, FebLoads, str]:
    """:func:`read_feb`'s mesh, materials and loads, and the sha256 (hex) of the bytes
    read (the deck's identity for run records)."""
    path = Path(path)
    data = path.read_bytes()
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise _err(path, f"not valid XML ({exc})") from None
    if root.tag != "febio_spec":
        raise _err(path, f"root tag <{root.tag}>; an FEBio deck starts with <febio_spec>")
    if root.get("version") != SPEC_VERSION:
        raise _err(path, f"febio_spec version '{root.get('version')}'; this reader reads "
                   f"version {SPEC_VERSION} (save the model as FEBio 4 in FEBio Studio)")
    for el in root:
        if not isinstance(el.tag, str):
            continue
        if el.tag == "MeshData":
            _check_mesh_data(el, path)
            continue
        if el.tag not in _IGNORED and len(el):
            raise _err(path, f"<{el.tag}> is not supported (eyefem reads hex8 solids, "
                       "linear trusses, linear springs and rigid bodies moved as prescribed, "
                       "with displacement, pressure, nodal and body loads; remove it or run "
                       "the deck in FEBio)")
    module = root.find("Module")
    if module is not None and module.get("type", "solid") != "solid":
        raise _err(path, f"<Module type=\"{module.get('type')}\">; only 'solid' is supported")
    _check_analysis(root.find("Control"), path)
    step_els = [] if root.find("Step") is None else [
        st for st in root.find("Step") if isinstance(st.tag, str)]
    for st in step_els:
        if st.tag != "step":
            raise _err(path, f"<Step><{st.tag}> is not supported; give each step as <step>")
        for child in st:
            if isinstance(child.tag, str) and child.tag not in (
                    "Control", "Boundary", "Loads", "Rigid", "Constraints",
                    "Contact") and len(child):
                raise _err(path, f"<step name=\"{st.get('name')}\"><{child.tag}> is not "
                           "supported (eyefem reads a step's Control, Boundary, Loads, Rigid, "
                           "Constraints and Contact)")
        _check_analysis(st.find("Control"), path)

    materials, bulk, by_id = _read_materials(root, path)
    nodes, node_index = _read_nodes(root, path)
    hexes, blocks, elem_ids, lines = _read_elements(root, path, node_index)
    mat_of_block, truss_of_block = _read_domains(root, path, blocks, materials, bulk, by_id,
                                                 lines)
    shells = {b: lines.pop(b)[1] for b in list(lines) if isinstance(lines[b], tuple)}
    _check_jacobians(nodes, hexes, elem_ids, path)
    # a rigid body's elements leave the solid: their nodes move as the deck prescribes
    rigid, keep, start = {}, np.ones(len(hexes), bool), 0
    for b, n in blocks:
        if isinstance(materials[mat_of_block[b]], _Special):
            rigid.setdefault(mat_of_block[b], set()).update(hexes[start:start + n].ravel().tolist())
            keep[start:start + n] = False
        start += n
    for b, ids in shells.items():
        rigid.setdefault(truss_of_block.pop(b)[0], set()).update(ids.tolist())
    hexes = hexes[keep]
    elem_ids = [e for e, k in zip(elem_ids, keep) if k]
    blocks = [(b, n) for b, n in blocks if not isinstance(materials[mat_of_block[b]], _Special)]
    used = sorted({mat_of_block[b] for b, _ in blocks}, key=list(materials).index)
    for ctrl in [root.find("Control")] + [st.find("Control") for st in step_els]:
        flag = None if ctrl is None else ctrl.findtext("use_three_field_hex")
        if flag is not None and flag.strip().lower() in ("0", "false") and any(
                _uncoupled(materials[m]) for m in used):
            raise _err(path, "<Control><use_three_field_hex> = 0 is not supported; eyefem "
                       "evaluates an uncoupled material's U(J) on the element's volume ratio "
                       "(FEBio's default three-field hex8)")
    mids = np.concatenate([np.full(n, used.index(mat_of_block[b]), np.int64)
                           for b, n in blocks] + [np.zeros(0, np.int64)])
    face_sets, node_sets, discrete_sets, pairs = _read_sets(root, path, node_index)
    mesh = Mesh(nodes, hexes, mids, tuple(used), node_sets, face_sets)
    density = _densities(root, path, mesh, used, blocks, mat_of_block)
    fibers = _fibers(root, path, mesh, materials, used, blocks, elem_ids, hexes)

    curves = _read_curves(root, path)
    top = _Sources(root.find("Boundary"), root.find("Loads"), root.find("Rigid"))
    for b in [] if top.boundary is None else top.boundary:
        if isinstance(b.tag, str) and b.get("type") == "rigid":
            rb = _rigid_name(b, path, f"<bc name=\"{b.get('name')}\" type=\"rigid\">",
                             materials, by_id)
            rigid.setdefault(rb, set()).update(
                _nodes_of(mesh, b.get("node_set"), path, f"<bc name=\"{b.get('name')}\">")
                .tolist())
    rigid = {k: np.array(sorted(v), np.int64) for k, v in rigid.items()}
    links = _read_links(root, path, nodes, materials, lines, truss_of_block, discrete_sets)
    if not mesh.n_elem and not links:
        raise _err(path, "<Mesh> has no <Elements> of a solid, truss or spring" + (
            " (only rigid bodies, whose joints and free motions eyefem does not model; run "
            "the deck in FEBio)" if rigid else ""))
    if not step_els:
        specs = [("step_1", root.find("Control"), None)]
    else:
        specs = [(st.get("name") or f"step_{i + 1}", st.find("Control"), st)
                 for i, st in enumerate(step_els)]
    terms: dict = {}  # term name -> (kind, data, value at t per step or None)
    steps, t, step_moves = [], 0.0, []
    for k, (name, ctrl, st) in enumerate(specs):
        n, dt = _read_control(ctrl, root.find("Control") if st is not None else None, path)
        t0, t = t, t + n * dt
        own = _Sources(None if st is None else st.find("Boundary"),
                       None if st is None else st.find("Loads"),
                       None if st is None else st.find("Rigid"))
        *rig, moves = _read_rigid([top.rigid, own.rigid], path, rigid, curves, t, k == 0,
                                  materials, by_id)
        step_moves.append(moves)
        prescribed = _read_boundary([top.boundary, own.boundary], path, mesh, curves, t,
                                    relative_ok=(k == 0), rigid=rig)
        params = {}
        for scope, src in (("", top.loads), (f"{name}:" if st is not None else "", own.loads)):
            for tname, kind, dat, value in _read_loads(src, path, mesh, curves, scope,
                                                        density):
                terms.setdefault(tname, (kind, dat, value(t0)))
                params[tname] = {"p" if kind == "pressure" else "f": value(t)}
        steps.append((name, n, t, prescribed, params))
    contacts = _read_contacts(_scoped(root, specs, "Contact"), path, mesh, pairs, rigid,
                              step_moves)
    volumes = _read_volumes(_scoped(root, specs, "Constraints"), path, mesh)
    if contacts:
        mesh = dataclasses.replace(mesh, node_sets={
            **mesh.node_sets, **{f"contact:{c.name}": np.unique(mesh.face_sets[c.primary])
                                 for c in contacts}})
    law_c = {}  # material -> t -> its constants (those on a load curve scaled)
    for m in used:
        law = materials[m]
        if isinstance(law, FebioLaw) and law.curves:
            for _, lc in law.curves:
                if lc not in curves:
                    raise _err(path, f"material '{m}': load controller {lc} is not defined in "
                               "<LoadData>")
            law_c[m] = (lambda t, law=law: np.array([
                c * (curves[lc](t) if lc is not None else 1.0) for c, lc in zip(
                    law.constants(), [dict(law.curves).get(i) for i in
                                      range(len(law.constants()))])]))
    out_steps = []
    for k, (name, n, t_end, prescribed, params) in enumerate(steps):
        full = {tn: params.get(tn, {"p" if kind == "pressure" else "f":
                                    0.0 if kind == "pressure" else np.zeros(len(dat))})
                for tn, (kind, dat, _) in terms.items()}
        for m, c_of in law_c.items():
            full[f"solid:{m}"] = {"c": c_of(t_end), "k": np.float64(materials[m].k)}
        for c in contacts:
            full[f"contact:{c.name}"] = {"d": np.array([c.d[k]]), "s": np.zeros(1)}
        out_steps.append(FebStep(name, n, t_end, prescribed, full))
    pressures = tuple((tn, dat, float(v0), float(out_steps[0].params[tn]["p"]))
                      for tn, (kind, dat, v0) in terms.items() if kind == "pressure")
    forces = tuple((tn, dat, np.asarray(v0, np.float64))
                   for tn, (kind, dat, v0) in terms.items() if kind == "force")
    loads = FebLoads(out_steps[0].prescribed, pressures, out_steps[0].n_steps,
                     {m: bulk[m] for m in used}, tuple(out_steps), forces, links, rigid,
                     contacts, volumes, fibers, {m: c_of(0.0) for m, c_of in law_c.items()})
    log.info("read %s: %d nodes, %d hex8, materials %s, %d step(s), %d pressure loads, "
             "%d nodal force terms, %d truss / spring sets, %d rigid bodies", path,
             mesh.n_nodes, mesh.n_elem, list(used), len(out_steps), len(pressures),
             len(forces), len(links), len(rigid))
    return mesh, {m: materials[m] for m in used}, loads, hashlib.sha256(data).hexdigest()


@dataclasses.dataclass(frozen=True)
class _Sources:
    boundary: object
    loads: object
    rigid: object = None


def _check_analysis(ctrl, path) -> None:
    """FebError unless a <Control>'s <analysis> (FEBio 4: its text; 2.5: type="...") is
    static: eyefem solves static equilibrium only, and never solves a dynamic deck as a
    static one."""
    el = None if ctrl is None else ctrl.find("analysis")
    if el is None:
        return
    kind = ((el.text or "").strip() or el.get("type") or "").strip()
    if kind.upper() != "STATIC":
        raise _err(path, f"<Control><analysis> is '{kind}': eyefem solves static equilibrium "
                   "only (no inertia, no time-dependent material); set <analysis>STATIC"
                   "</analysis> for the static problem, or run the deck in FEBio")


def _check_constant(value, tag, name, where, path, label=None) -> None:
    """A Mooney-Rivlin constant (<c1> or <c2>, MPa) against the case files' ranges of c10
    (eyefem.io.casefile.material_c10_field): FebError outside the impossible range, a
    warning outside the plausible one, each naming the likely unit slip."""
    f = material_c10_field(name)
    for rng, refuse in ((f.refuse, True), (f.warn, False)):
        if rng is None or rng[0] <= value <= rng[1]:
            continue
        if refuse and material_c10_field("").refuse[1] < value <= STIFF_SOLID_C1:
            log.warning("%s: %s <%s>: %s = %g MPa is above the case files' range (%g to %g "
                        "MPa, soft tissues and rubbers): read as a stiff solid (metal, "
                        "bone); check its unit", path, where, tag, label or tag, value,
                        rng[0], rng[1])
            return
        slip = unit_slip(value, f.warn or rng, f.unit, f.slips)
        msg = (f"{where} <{tag}>: {label} = {value:g} MPa is " if label else
               f"{where} <{tag}> = {value:g} MPa is ")
        msg += (f"{'impossible' if refuse else 'outside the plausible range'} "
                f"({rng[0]:g} to {rng[1]:g} MPa)" + (f": {slip}" if slip else ""))
        if refuse:
            raise _err(path, msg + f"; give <{tag}> in MPa")
        log.warning("%s: %s; check the value and its unit", path, msg)
        return


_MATERIAL_PARAMETERS = {
    "mooney-rivlin": {"c1", "c2", "k", "density", "pressure_model", "laugon", "atol",
                      "minaug", "maxaug"},
    "neo-hookean": {"E", "v", "density"},
    "coupled mooney-rivlin": {"c1", "c2", "k", "density"},
    "rigid body": {"density", "E", "v", "center_of_mass"},
    "linear truss": {"E", "v", "density"},
}
"""The material types the reader implements (FEBio's names, case-insensitive) and the
parameters each may carry; any other type or parameter is refused by name. <density>
does not enter a static solve."""

_PRESSURE_MODELS = ("default", "0")
"""FEBio's U(J) choices (<pressure_model>) read: its default, U = k/2 (ln J)^2."""


def _flag(el, tag) -> str:
    return (el.findtext(tag) or "0").strip().lower()


def _read_materials(root, path):
    """name -> material, name -> the deck's k (MPa; 0 for neo-Hookean), FEBio id -> name.

    "Mooney-Rivlin" (uncoupled: c1, c2, k) becomes UncoupledMooneyRivlin (k > 0: FEBio's
    U(J) = k/2 (ln J)^2 on the three-field element) or the exactly incompressible
    MooneyRivlin (Q1P0) with <laugon>1</laugon> (FEBio's augmented Lagrangian, whose
    limit is the Q1P0 constraint Jbar = 1 per element: what eyefem's export writes) or
    k = 0; "neo-Hookean" (E, v) and "coupled Mooney-Rivlin" (c1, c2,
    k) become CoupledMooneyRivlin. Other types and parameters are refused by name."""
    sec = root.find("Material")
    if sec is None or not len(sec):
        raise _err(path, "no <Material> section; define a Mooney-Rivlin material")
    materials, bulk, by_id = {}, {}, {}
    for el in sec:
        if not isinstance(el.tag, str):
            continue
        name = el.get("name") or f"material_{el.get('id')}"
        where = f"material '{name}' (id {el.get('id')})"
        kind = (el.get("type") or "").lower()
        if kind in _LAW_TYPES:
            by_id[el.get("id")] = name
            materials[name] = _febio_law(el, kind, name, where, path)
            bulk[name] = materials[name].k
            continue
        if kind not in _MATERIAL_PARAMETERS:
            raise _err(path, f"{where}: type '{el.get('type')}' is not supported; eyefem "
                       "reads \"Mooney-Rivlin\" (c1, c2, k), \"neo-Hookean\" (E, v), "
                       "\"coupled Mooney-Rivlin\" (c1, c2, k), \"rigid body\", \"linear "
                       f"truss\" (E), {_LAW_LIST}")
        for child in el:
            if isinstance(child.tag, str) and child.tag not in _MATERIAL_PARAMETERS[kind]:
                raise _err(path, f"{where}: parameter <{child.tag}> of '{el.get('type')}' is "
                           "not supported (eyefem reads "
                           f"{', '.join(sorted(_MATERIAL_PARAMETERS[kind]))}); remove it or "
                           "run the deck in FEBio")
        by_id[el.get("id")] = name
        if kind in _SPECIAL:
            E = 0.0 if kind == "rigid body" else _child_float(
                el, "E", path, where, hint="give Young's modulus, e.g. <E>1e3</E>")
            if kind == "linear truss" and not E > 0:
                raise _err(path, f"{where} <E> = {E:g}: must be > 0")
            materials[name], bulk[name] = _Special(kind, E), 0.0
            continue
        try:
            if kind == "neo-hookean":
                materials[name], bulk[name] = _neo_hookean(el, name, where, path), 0.0
            else:
                materials[name], bulk[name] = _mooney_rivlin(el, kind, name, where, path)
        except ValueError as exc:
            if isinstance(exc, FebError):
                raise
            raise _err(path, f"{where}: {exc}") from None
    return materials, bulk, by_id


@dataclasses.dataclass(frozen=True)
class _Special:
    """A material that is not a solid's strain energy: "rigid body" (its elements move as
    the deck prescribes) or "linear truss" (E: Young's modulus, MPa)."""

    kind: str
    E: float


_SPECIAL = ("rigid body", "linear truss")


def _neo_hookean(el, name, where, path):
    E = _child_float(el, "E", path, where, hint="give Young's modulus in MPa, e.g. <E>1</E>")
    v = _child_float(el, "v", path, where, hint="give Poisson's ratio, e.g. <v>0.3</v>")
    if not (E > 0 and 0 <= v < 0.5):
        raise _err(path, f"{where}: E = {E:g} MPa, v = {v:g}; eyefem's neo-Hookean needs "
                   "E > 0 and 0 <= v < 0.5 (FEBio's lam = v E / ((1 + v)(1 - 2 v)) >= 0)")
    _check_constant(E / (4.0 * (1.0 + v)), "E", name, where, path,
                    label="c1 = E / (4 (1 + v))")
    return febio_neo_hookean(name, E, v)


def _mooney_rivlin(el, kind, name, where, path):
    c1 = _child_float(el, "c1", path, where, hint="give c1 in MPa, e.g. <c1>0.1</c1>")
    c2 = _child_float(el, "c2", path, where, default=0.0, hint="give c2 in MPa, e.g. <c2>0</c2>")
    k = _child_float(el, "k", path, where, default=0.0,
                     hint="give the bulk modulus in MPa, e.g. <k>1000</k>")
    _check_constant(c1, "c1", name, where, path)
    if c2 != 0.0:  # c2 = 0 is FEBio's default, no unit slip
        _check_constant(c2, "c2", name, where, path)
    if 0 <= c1 and 0 <= c2 and 2 * (c1 + c2) < MIN_SHEAR_MODULUS:
        raise _err(path, f"{where}: c1 = {c1:g} MPa, c2 = {c2:g} MPa: the shear modulus "
                   f"2 (c1 + c2) = {2 * (c1 + c2):g} MPa is below {MIN_SHEAR_MODULUS:g} MPa "
                   "(1 Pa: no solid eyefem solves is that soft); give c1 and c2 in MPa")
    if k < 0:
        raise _err(path, f"{where} <k> = {k:g} MPa: a bulk modulus must be >= 0; give it "
                   "in MPa, e.g. <k>1000</k>")
    if kind == "coupled mooney-rivlin":
        if not (c1 > 0 and k > 0):
            raise _err(path, f"{where}: c1 = {c1:g} MPa, k = {k:g} MPa; FEBio's coupled "
                       "Mooney-Rivlin needs c1 > 0 and k > 0")
        return CoupledMooneyRivlin(name, c1, c2, k), k
    model = _flag(el, "pressure_model")
    if model not in _PRESSURE_MODELS:
        raise _err(path, f"{where} <pressure_model> = '{el.findtext('pressure_model')}': "
                   "eyefem implements FEBio's default U(J) = k/2 (ln J)^2 only; remove the "
                   "tag or set it to 'default'")
    if _flag(el, "laugon") not in ("0", "false"):
        if _flag(el, "laugon") not in ("1", "true"):
            raise _err(path, f"{where} <laugon> = '{el.findtext('laugon').strip()}'; give 0 "
                       "(penalty k) or 1 (augmented Lagrangian: exactly incompressible)")
        # FEBio's augmented Lagrangian adds multipliers L += k ln(Jbar) per element until
        # they settle (atol): its limit is Jbar = v / V = 1 per element, the Q1P0 constraint
        log.info("%s: %s has laugon = 1: exactly incompressible (eyefem's Q1P0 element, "
                 "the limit of FEBio's augmentations)", path, where)
        return MooneyRivlin.from_terms(name, {"c10": c1, "c01": c2}), k
    if k == 0.0:
        log.warning("%s: %s has k = 0: FEBio needs a bulk modulus > 0; eyefem solves the "
                    "material exactly incompressible (Q1P0)", path, where)
    return MooneyRivlin.from_terms(name, {"c10": c1, "c01": c2, "k": k}), k


_MIXTURES = ("solid mixture", "uncoupled solid mixture")
_LAW_TYPES = tuple(k for k in FEBIO_LAWS if k not in _MATERIAL_PARAMETERS and "fiber-exp" not in k
                   ) + _MIXTURES
"""The FEBio types read as eyefem.fem.materials.FebioLaw (top level; fiber-exp-linear and
the types of _MATERIAL_PARAMETERS also as a mixture's constituents)."""

_LAW_LIST = ("\"Ogden\", \"Ogden unconstrained\", \"isotropic elastic\", \"isotropic "
             "Hencky\", \"Holmes-Mow\", \"uncoupled Holmes-Mow\", \"Arruda-Boyce\", "
             "\"Veronda-Westmann\", \"Yeoh\", \"trans iso Mooney-Rivlin\", \"trans iso "
             "Veronda-Westmann\", \"orthotropic elastic\", \"Fung orthotropic\", "
             "\"Fung-ortho-compressible\" and solid mixtures of these with "
             "\"fiber-exp-linear\" and the prescribed active contractions")

_FIBER_TYPES = ("vector", "local", "spherical", "user")


def _law_part(el, kind, where, path, top_uncoupled):
    """(type, constants, fibre spec or None) of one law (a material or a mixture's
    <solid>): its parameters in FEBIO_LAWS' order with FEBio's defaults."""
    fn, uncoupled, params, fibred = FEBIO_LAWS[kind]
    names = {n for n, _ in params}
    allowed = names | {"density"} | ({"k", "pressure_model"} if uncoupled or kind.startswith(
        "uncoupled") else set())
    fiber, curves = None, []
    for child in el:
        if not isinstance(child.tag, str):
            continue
        if child.tag == "fiber" and fibred == 1:
            fiber = _fiber_spec(child, where, path)
            continue
        if child.tag == "mat_axis" and fibred == 3:
            fiber = _mat_axis(child, where, path)
            continue
        if child.tag not in allowed:
            why = {"active_contraction": "active contraction (a non-conservative fibre stress)",
                   "mat_axis": "a material axis (the fibre is read in global coordinates)"
                   }.get(child.tag, "")
            known = allowed | {1: {"fiber"}, 3: {"mat_axis"}}.get(int(fibred), set())
            raise _err(path, f"{where}: parameter <{child.tag}> of '{el.get('type')}' is not "
                       f"supported{' (' + why + ')' if why else ''} (eyefem reads "
                       f"{', '.join(sorted(known))}); remove it or run the deck in FEBio")
        if child.get("type") is not None:
            raise _err(path, f"{where} <{child.tag}>: a parameter map (type=\"{child.get('type')}"
                       "\") is not supported; give a constant")
        if child.get("lc") is not None:
            if child.tag not in names:
                raise _err(path, f"{where} <{child.tag}>: a load curve on this parameter is not "
                           "supported")
            curves.append(([n for n, _ in params].index(child.tag), child.get("lc")))
    if fibred == 1 and fiber is None:
        fiber = ("vector", (1.0, 0.0, 0.0))  # FEBio's default fibre: the x axis
    if fibred == 3 and fiber is None:
        fiber = ("axes", tuple(map(tuple, np.eye(3))))  # no mat_axis: the global axes
    if _flag(el, "pressure_model") not in _PRESSURE_MODELS:
        raise _err(path, f"{where} <pressure_model> = '{el.findtext('pressure_model')}': "
                   "eyefem implements FEBio's default U(J) = k/2 (ln J)^2 only")
    consts = []
    for n, default in params:
        consts.append(_child_float(el, n, path, where, default=default,
                                   hint=f"give {n}, a finite number"))
    c = dict(zip([n for n, _ in params], consts))
    if "E" in c and "v" in c and not (c["E"] > 0 and -1.0 < c["v"] < 0.5):
        raise _err(path, f"{where}: E = {c['E']:g}, v = {c['v']:g}; FEBio needs E > 0 and "
                   "-1 < v < 0.5")
    for n in ("m1", "m2", "m3", "m4", "m5", "m6"):
        if c.get(n, 1.0) == 0:
            raise _err(path, f"{where} <{n}> = 0: FEBio's Ogden exponents must not be 0")
    if kind in ("uncoupled holmes-mow", "holmes-mow") and not c["beta"] > 0:
        raise _err(path, f"{where} <beta> = {c['beta']:g}: eyefem needs beta > 0 (W divides "
                   "by it)")
    lam1 = c.get("lambda", c.get("lam_max"))
    if lam1 is not None:  # the fibre of fiber-exp-linear and the trans iso laws
        if min(c["c3"], c["c4"], c["c5"]) < 0 or lam1 < 1 or (c["c3"] == 0 and c["c4"] == 0):
            raise _err(path, f"{where}: c3 = {c['c3']:g}, c4 = {c['c4']:g}, c5 = "
                       f"{c['c5']:g}, lambda = {lam1:g}; FEBio's fibre needs c3, c4, c5 >= 0, "
                       "lambda >= 1 and c4 > 0 where c3 = 0")
    return kind, tuple(consts), fiber, tuple(curves)


def _mat_axis(el, where, path):
    """A <mat_axis type="vector"> (a, d) as ("axes", rows e1, e2, e3): FEBio's
    FEMat3dVectorMap, e1 = a, e3 = a x d, e2 = e3 x e1 (normalised; d replaced by x or y
    where it is parallel to a)."""
    if (el.get("type") or "vector") == "angles":  # FEMat3dSphericalAngleMap, degrees
        th = math.radians(_child_float(el, "theta", path, f"{where} <mat_axis>", default=0.0))
        ph = math.radians(_child_float(el, "phi", path, f"{where} <mat_axis>", default=90.0))
        return ("axes", ((math.cos(th) * math.sin(ph), math.sin(th) * math.sin(ph),
                          math.cos(ph)), (-math.sin(th), math.cos(th), 0.0),
                         (-math.cos(th) * math.cos(ph), -math.sin(th) * math.cos(ph),
                          math.sin(ph))))
    if (el.get("type") or "vector") != "vector":
        raise _err(path, f"{where}: <mat_axis type=\"{el.get('type')}\"> is not supported "
                   "(eyefem reads type=\"vector\" and \"angles\")")
    a = np.array(_floats(el.findtext("a") or "1,0,0", path, f"{where} <mat_axis><a>"))
    d = np.array(_floats(el.findtext("d") or "0,1,0", path, f"{where} <mat_axis><d>"))
    if a.shape != (3,) or d.shape != (3,) or not a.any() or not d.any():
        raise _err(path, f"{where} <mat_axis>: give two non-zero vectors <a> and <d>")
    a, d = a / np.linalg.norm(a), d / np.linalg.norm(d)
    if abs(a @ d) > 0.999:
        d = np.array([1.0, 0.0, 0.0]) if abs(a[0]) <= 0.999 else np.array([0.0, 1.0, 0.0])
    c = np.cross(a, d)
    b = np.cross(c, a)
    return ("axes", tuple(tuple(v / np.linalg.norm(v)) for v in (a, b, c)))


def _fiber_spec(el, where, path):
    """A <fiber type="..."> as ("vector", (3,)), ("local", (n1, n2)), ("spherical",
    center (3,), vector (3,)) or ("user",) (element data of the <MeshData>)."""
    kind = (el.get("type") or "vector").lower()
    if kind not in _FIBER_TYPES:
        raise _err(path, f"{where}: <fiber type=\"{el.get('type')}\"> is not supported "
                   f"(eyefem reads {', '.join(_FIBER_TYPES)})")
    for child in el:
        if isinstance(child.tag, str) and child.tag not in ("vector", "local", "center"):
            raise _err(path, f"{where}: <fiber><{child.tag}> is not supported")

    def vec(tag, default):
        t = el.findtext(tag)
        v = tuple(default) if t is None else tuple(_floats(t, path, f"{where} <fiber><{tag}>"))
        if len(v) != 3 or (tag == "vector" and not any(v)):
            raise _err(path, f"{where} <fiber><{tag}>: give three numbers (a non-zero vector)")
        return v
    if kind == "vector":
        return ("vector", vec("vector", (1.0, 0.0, 0.0)))
    if kind == "spherical":
        return ("spherical", vec("center", (0.0, 0.0, 0.0)), vec("vector", (1.0, 0.0, 0.0)))
    if kind == "local":
        n = [int(v) for v in _floats(el.findtext("local") or "0,0", path,
                                     f"{where} <fiber><local>")]
        if n == [0, 0]:
            n = [1, 2]
        if len(n) != 2 or not all(1 <= i <= 8 for i in n) or n[0] == n[1]:
            raise _err(path, f"{where} <fiber><local>: give two local node numbers 1-8")
        return ("local", tuple(n))
    return ("user",)


def _febio_law(el, kind, name, where, path) -> FebioLaw:
    """One of FEBio's further laws or a solid mixture of them (FebioLaw)."""
    if kind in _MIXTURES:
        uncoupled = kind == "uncoupled solid mixture"
        allowed = {"density", "solid"} | ({"k", "pressure_model"} if uncoupled else set())
        parts = []
        for child in el:
            if not isinstance(child.tag, str):
                continue
            if child.tag not in allowed:
                raise _err(path, f"{where}: <{child.tag}> of a '{el.get('type')}' is not "
                           f"supported (eyefem reads {', '.join(sorted(allowed))})")
            if child.tag != "solid":
                continue
            ck = (child.get("type") or "").lower()
            cw = f"{where} <solid type=\"{child.get('type')}\">"
            if ck not in FEBIO_LAWS or ck in _MIXTURES:
                raise _err(path, f"{cw} is not supported; a mixture's constituents may be "
                           f"{_LAW_LIST}, \"Mooney-Rivlin\", \"neo-Hookean\", \"coupled "
                           "Mooney-Rivlin\"")
            if not uncoupled and FEBIO_LAWS[ck][1]:
                raise _err(path, f"{cw}: an uncoupled constituent of a (coupled) solid mixture "
                           "is not supported (FEBio adds its own U(J) at the Gauss points); use "
                           "an \"uncoupled solid mixture\" or a coupled law")
            parts.append(_law_part(child, ck, cw, path, uncoupled))
        if not parts:
            raise _err(path, f"{where}: a solid mixture without <solid> constituents")
        if _flag(el, "pressure_model") not in _PRESSURE_MODELS:
            raise _err(path, f"{where} <pressure_model> = '{el.findtext('pressure_model')}': "
                       "eyefem implements FEBio's default U(J) = k/2 (ln J)^2 only")
    else:
        uncoupled = FEBIO_LAWS[kind][1]
        parts = [_law_part(el, kind, where, path, uncoupled)]
    k = _child_float(el, "k", path, where, default=0.0) if uncoupled else 0.0
    if uncoupled and not k > 0:
        raise _err(path, f"{where} <k> = {k:g}: FEBio's uncoupled '{el.get('type')}' needs a "
                   "bulk modulus k > 0 (MPa)")
    for n in ("E", "c1", "mu"):
        for pk, consts, _, _ in parts:
            pn = [p for p, _ in FEBIO_LAWS[pk][2]]
            if n in pn:
                val = consts[pn.index(n)]
                if n == "E":
                    v = consts[pn.index("v")]
                    _check_constant(val / (4.0 * (1.0 + v)), "E", name, where, path,
                                    label="c1 = E / (4 (1 + v))")
                elif val > 0:
                    _check_constant(val / 2.0 if n == "mu" else val, n, name, where, path,
                                    label=("c1 = mu / 2" if n == "mu" else None))
    curves, at = [], 0
    for pk, consts, _, pc in parts:
        curves += [(at + i, lc) for i, lc in pc]
        at += len(consts)
    try:
        return FebioLaw(name, el.get("type"), tuple((pk, c) for pk, c, _, _ in parts),
                        uncoupled, k, tuple(f for _, _, f, _ in parts if f is not None),
                        tuple(curves))
    except ValueError as exc:
        raise _err(path, f"{where}: {exc}") from None


def _uncoupled(mat) -> bool:
    """True for a material whose U(J) eyefem puts on the element's volume ratio."""
    return isinstance(mat, UncoupledMooneyRivlin) or (isinstance(mat, FebioLaw)
                                                       and mat.uncoupled)


def _check_mesh_data(sec, path) -> None:
    """FebError unless every entry of <MeshData> is one eyefem reads: element data of
    type "fiber" (a material's fibre directions, :func:`_fibers`) or "shell thickness"
    (shells are read only as a rigid body's facets, whose thickness a static solve does
    not use; a deformable shell is refused by its domain)."""
    for d in sec:
        if not isinstance(d.tag, str):
            continue
        kind = d.get("type")
        if d.tag == "ElementData" and kind in ("fiber", "shell thickness"):
            continue
        what = f"type=\"{kind}\"" if kind else f"name=\"{d.get('name')}\""
        raise _err(path, f"<MeshData><{d.tag} {what}> is not supported (eyefem reads element "
                   "data of type \"fiber\" and a rigid shell's \"shell thickness\"; no maps "
                   "of material parameters, material axes or prestrain)")


def _element_sets(root, path, blocks, elem_ids) -> dict:
    """name -> mesh element indices (in the set's order) of every hex8 <Elements> block
    and <ElementSet> (FEBio element ids) over the solid's elements."""
    out, start = {}, 0
    for b, n in blocks:
        out[b] = np.arange(start, start + n)
        start += n
    index = {str(e).strip(): i for i, e in enumerate(elem_ids)}
    for es in root.find("Mesh").findall("ElementSet"):
        ids = [e.get("id") for e in es.findall("e")]
        if not ids:
            ids = [str(i) for i in _ints(es.text, path, f"element set '{es.get('name')}'",
                                         max(len(elem_ids), 1) * 10)]
        out[es.get("name")] = np.array([index.get(i.strip(), -1) for i in ids], np.int64)
    return out


def _fibers(root, path, mesh, materials, used, blocks, elem_ids, hexes) -> dict:
    """material name -> (n, 8, n_fibers, 3) unit fibre directions (reference
    configuration) at the 2 x 2 x 2 Gauss points of its n elements, in mesh order, for the
    FebioLaw materials with fibres: FEBio's "vector" (FEConstValueVec3), "local" (the
    element's nodes n1 -> n2, FELocalVectorGenerator), "spherical" (the vector rotated as
    e1 onto X - center at the Gauss point, FESphericalVectorGenerator) and "user" (the
    <MeshData> element data of type "fiber")."""
    from eyefem.fem.mesh import hex_gauss_points, hex_shape
    out = {}
    need = [m for m in used if isinstance(materials[m], FebioLaw) and materials[m].n_fibers]
    if not need:
        return out
    shape, _ = hex_shape(hex_gauss_points()[0])  # (8g, 8a)
    user = {}
    sets = None
    for sec in root.findall("MeshData"):
        for d in sec.findall("ElementData"):
            if d.get("type") != "fiber":
                continue
            sets = sets or _element_sets(root, path, blocks, elem_ids)
            where = f"<MeshData><ElementData type=\"fiber\" elem_set=\"{d.get('elem_set')}\">"
            if d.get("elem_set") not in sets:
                raise _err(path, f"{where}: no hex8 element block or element set of that name")
            members = sets[d.get("elem_set")]
            for e in d.findall("e"):
                lid = int(_floats(e.get("lid"), path, f"{where} lid")[0])
                if not 1 <= lid <= len(members) or members[lid - 1] < 0:
                    raise _err(path, f"{where}: lid {lid} is not an element of the set")
                v = _floats(e.text, path, f"{where} <e lid=\"{lid}\">")
                if len(v) != 3 or not any(v):
                    raise _err(path, f"{where} <e lid=\"{lid}\">: give a non-zero vector x,y,z")
                user[int(members[lid - 1])] = v
    for m in need:
        law = materials[m]
        el = np.nonzero(mesh.material_ids == used.index(m))[0]
        xe = mesh.nodes[hexes[el]]  # (n, 8, 3)
        xg = np.einsum("ga,eai->egi", shape, xe)
        dirs = []
        for spec in law.fibers:
            if spec[0] == "axes":
                for row in spec[1]:
                    dirs.append(np.broadcast_to(np.asarray(row, float), xg.shape))
                continue
            if spec[0] == "vector":
                a = np.broadcast_to(np.asarray(spec[1], float), xg.shape)
            elif spec[0] == "local":
                a = np.broadcast_to((xe[:, spec[1][1] - 1] - xe[:, spec[1][0] - 1])[:, None],
                                    xg.shape)
            elif spec[0] == "spherical":
                a = _rotate_e1_onto(xg - np.asarray(spec[1]), np.asarray(spec[2], float))
            else:
                missing = [i for i in el if int(i) not in user]
                if missing:
                    raise _err(path, f"material '{m}': <fiber type=\"user\"> but element "
                               f"{elem_ids[missing[0]]} has no <MeshData> ElementData of "
                               "type \"fiber\"")
                a = np.broadcast_to(np.array([user[int(i)] for i in el])[:, None], xg.shape)
            norm = np.linalg.norm(a, axis=-1, keepdims=True)
            if np.any(norm == 0):
                raise _err(path, f"material '{m}': a fibre direction of zero length (local "
                           "nodes that coincide, or a Gauss point at the spherical centre)")
            dirs.append(a / norm)
        out[m] = np.stack(dirs, axis=2)
    return out


def _rotate_e1_onto(r, v):
    """FEBio's spherical fibre: v rotated by the rotation that takes e1 onto r / |r|
    (quatd(e1, a).RotateVector), r (..., 3) -> (..., 3). Rodrigues' formula about e1 x a."""
    a = r / np.linalg.norm(r, axis=-1, keepdims=True)
    e1 = np.array([1.0, 0.0, 0.0])
    axis = np.cross(e1, a)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)
    c = a[..., :1]
    k = np.where(s > 1e-12, axis / np.where(s > 1e-12, s, 1.0), np.array([0.0, 0.0, 1.0]))
    vb = np.broadcast_to(v, a.shape)
    out = vb * c + np.cross(k, vb) * s + k * np.sum(k * vb, axis=-1, keepdims=True) * (1.0 - c)
    return np.where(s > 1e-12, out, vb)  # parallel or opposite: FEBio leaves v as it is


def _read_nodes(root, path):
    mesh = root.find("Mesh")
    if mesh is None:
        raise _err(path, "no <Mesh> section")
    ids, xyz = [], []
    for block in mesh.findall("Nodes"):
        where = f"<Nodes name=\"{block.get('name')}\">"
        for n in block.findall("node"):
            i = _id(n, path, where)
            x = _floats(n.text, path, f"{where} node {i}", "give three finite coordinates, mm")
            if len(x) != 3:
                raise _err(path, f"{where} node {i}: {len(x)} coordinates; expected 3")
            ids.append(i)
            xyz.append(x)
    if not ids:
        raise _err(path, "<Mesh> has no <Nodes>")
    index = {i: k for k, i in enumerate(ids)}
    if len(index) != len(ids):
        seen = set()
        dup = next(i for i in ids if i in seen or seen.add(i))
        raise _err(path, f"node id {dup} appears twice in <Nodes>; give each node its own id")
    return np.array(xyz, np.float64), index


def _read_elements(root, path, node_index):
    """(hex8 connectivity (e, 8), [(block name, count)], element ids, two-node blocks
    {name: (m, 2) node indices})."""
    hexes, blocks, elem_ids, lines = [], [], [], {}
    for block in root.find("Mesh").findall("Elements"):
        etype, name = block.get("type"), block.get("name")
        if etype in ("quad4", "tri3"):  # shells: a rigid body's facets only
            ids = []
            for e in block.findall("elem"):
                c = _ints(e.text, path, f"element {e.get('id')}", len(node_index))
                try:
                    ids += [node_index[i] for i in c]
                except KeyError as exc:
                    raise _err(path, f"element {e.get('id')}: node {exc.args[0]} is not in "
                               "<Nodes>") from None
            lines[name] = ("shell", np.unique(np.array(ids, np.int64)))
            continue
        if etype in ("line2", "truss2"):
            conn = []
            for e in block.findall("elem"):
                c = _ints(e.text, path, f"element {e.get('id')}", len(node_index))
                if len(c) != 2:
                    raise _err(path, f"element {e.get('id')}: {len(c)} nodes; {etype} needs 2")
                try:
                    conn.append([node_index[i] for i in c])
                except KeyError as exc:
                    raise _err(path, f"element {e.get('id')}: node {exc.args[0]} is not in "
                               "<Nodes>") from None
            lines[name] = np.array(conn, np.int64).reshape(-1, 2)
            continue
        if etype != "hex8":
            kind = ("tetrahedra" if (etype or "").startswith("tet") else f"'{etype}' elements")
            raise _err(path, f"<Elements name=\"{name}\"> holds {kind}: hexahedra are needed "
                       "(type=\"hex8\"); mesh the part with 8-node bricks")
        n = 0
        for e in block.findall("elem"):
            conn = _ints(e.text, path, f"element {e.get('id')}", len(node_index))
            if len(conn) != 8:
                raise _err(path, f"element {e.get('id')}: {len(conn)} nodes; hex8 needs 8")
            try:
                hexes.append([node_index[i] for i in conn])
            except KeyError as exc:
                raise _err(path, f"element {e.get('id')}: node {exc.args[0]} is not in "
                           "<Nodes>") from None
            elem_ids.append(e.get("id"))
            n += 1
        blocks.append((name, n))
    return np.array(hexes, np.int64).reshape(-1, 8), blocks, elem_ids, lines


def _read_domains(root, path, blocks, materials, bulk, by_id, lines):
    """{hex block: material name}, {two-node block: (material name, cross-sectional area
    mm^2)}: SolidDomains (a "rigid body" material's block: a rigid body) and the
    BeamDomains / TrussDomains of type "linear-truss" with a "linear truss" material."""
    doms = root.find("MeshDomains")
    if doms is None:
        raise _err(path, "no <MeshDomains> section; assign a material to every element block")
    out, trusses, laugon_of = {}, {}, {}
    for d in doms:
        if not isinstance(d.tag, str):
            continue
        mat = d.get("mat")
        mat = by_id.get(mat, mat)
        if d.tag == "ShellDomain":
            spec = materials.get(mat)
            if not (isinstance(spec, _Special) and spec.kind == "rigid body") or not isinstance(
                    lines.get(d.get("name")), tuple):
                raise _err(path, f"<ShellDomain name=\"{d.get('name')}\">: shells are read "
                           "only as a rigid body's facets (a \"rigid body\" material on "
                           "quad4 / tri3 elements); deformable shells are not supported")
            trusses[d.get("name")] = (mat, None)
            continue
        if d.tag in ("BeamDomain", "TrussDomain"):
            where = f"<{d.tag} name=\"{d.get('name')}\">"
            if d.get("name") not in lines or isinstance(lines[d.get("name")], tuple):
                raise _err(path, f"{where}: no line2 <Elements> block of that name")
            spec = materials.get(mat)
            if d.get("type") != "linear-truss" or not (
                    isinstance(spec, _Special) and spec.kind == "linear truss"):
                raise _err(path, f"{where}: type=\"{d.get('type')}\" with material "
                           f"'{d.get('mat')}' is not supported; eyefem reads type="
                           "\"linear-truss\" with a \"linear truss\" material (no beams, no "
                           "elastic-truss)")
            for child in d:
                if isinstance(child.tag, str) and child.tag != "cross_sectional_area":
                    raise _err(path, f"{where}: <{child.tag}> is not supported "
                               "(cross_sectional_area)")
            area = _child_float(d, "cross_sectional_area", path, where,
                                hint="give the truss's area, mm^2")
            if not area > 0:
                raise _err(path, f"{where} <cross_sectional_area> = {area:g}: must be > 0")
            trusses[d.get("name")] = (mat, area)
            continue
        if d.tag != "SolidDomain":
            raise _err(path, f"<MeshDomains><{d.tag} name=\"{d.get('name')}\">: not "
                       "supported (eyefem reads SolidDomain and linear-truss BeamDomain; no "
                       "shells, beams or discrete domains)")
        if mat not in materials:
            raise _err(path, f"SolidDomain '{d.get('name')}': material '{d.get('mat')}' is not "
                       f"defined in <Material>")
        if isinstance(materials[mat], _Special) and materials[mat].kind != "rigid body":
            raise _err(path, f"SolidDomain '{d.get('name')}': material '{d.get('mat')}' is a "
                       f"{materials[mat].kind}; give it a linear-truss BeamDomain")
        etype = (d.get("elem_type") or "HEX8G8").upper()
        if etype != "HEX8G8":
            raise _err(path, f"SolidDomain '{d.get('name')}': elem_type=\"{d.get('elem_type')}\""
                       " is not supported; eyefem integrates hex8 with 2 x 2 x 2 Gauss points "
                       "(HEX8G8)")
        if (d.get("three_field") or "on") != "on" and _uncoupled(materials[mat]):
            raise _err(path, f"SolidDomain '{d.get('name')}': three_field=\"{d.get('three_field')}"
                       "\" is not supported; eyefem evaluates an uncoupled material's U(J) on "
                       "the element's volume ratio (FEBio's default three-field hex8)")
        lau = _flag(d, "laugon") not in ("0", "false")  # FEBio 4: the three-field domain's
        if laugon_of.setdefault(mat, lau) != lau:
            raise _err(path, f"SolidDomain '{d.get('name')}': material '{mat}' is used with "
                       "and without <laugon>1</laugon> in different domains; give each "
                       "its own material")
        if lau:
            _domain_laugon(root, d, mat, materials, bulk, path)
        out[d.get("name")] = mat
    for name, _ in blocks:
        if name not in out:
            raise _err(path, f"element block '{name}' has no SolidDomain in <MeshDomains>")
    for name in lines:
        if name not in trusses:
            raise _err(path, f"element block '{name}' (line2 or shells) has no linear-truss "
                       "BeamDomain (or rigid ShellDomain) in <MeshDomains>")
    return out, trusses


def _domain_laugon(root, dom, mat, materials, bulk, path) -> None:
    """A SolidDomain with <laugon>1</laugon> (FEBio 4 puts the three-field element's
    augmented Lagrangian on the domain): its uncoupled Mooney-Rivlin becomes exactly
    incompressible in ``materials`` (and ``bulk``), as a material with
    <laugon>1</laugon> (FEBio 2.5 / 3) does. Other laws keep their penalty k, with a
    warning."""
    where = f"SolidDomain '{dom.get('name')}'"
    if _flag(dom, "laugon") not in ("1", "true"):
        raise _err(path, f"{where} <laugon> = '{dom.findtext('laugon').strip()}'; give 0 "
                   "(penalty k) or 1 (augmented Lagrangian: exactly incompressible)")
    if not isinstance(materials[mat], UncoupledMooneyRivlin):
        if _uncoupled(materials[mat]):
            log.warning("%s: %s: laugon = 1 on a material other than Mooney-Rivlin; eyefem "
                        "keeps its penalty k (FEBio's augmentations drive Jbar to 1: the "
                        "results differ by about c1 / k)", path, where)
        return
    el = copy.deepcopy(next(e for e in root.find("Material") if isinstance(e.tag, str) and (
        e.get("name") or f"material_{e.get('id')}") == mat))
    for old in el.findall("laugon"):
        el.remove(old)
    ET.SubElement(el, "laugon").text = "1"
    materials[mat], bulk[mat] = _mooney_rivlin(el, "mooney-rivlin", mat,
                                               f"material '{mat}' in {where}", path)


def _check_jacobians(nodes, hexes, elem_ids, path):
    if not len(hexes):
        return
    _, _, det = hex_geometry(nodes, hexes)
    bad = np.nonzero(np.min(det, axis=1) <= 0)[0]
    if bad.size:
        raise _err(path, f"element {elem_ids[bad[0]]}: non-positive Jacobian; the element is "
                   "inverted or its nodes are not in FEBio's hex8 order (bottom face "
                   f"counter-clockwise seen from inside, then the top face) ({bad.size} such "
                   "elements)")


def _read_sets(root, path, node_index):
    mesh = root.find("Mesh")
    faces, nsets, dsets, pairs = {}, {}, {}, {}

    def nid(i, where):
        try:
            return node_index[i]
        except KeyError:
            raise _err(path, f"{where}: node {i} is not in <Nodes>") from None

    for el in mesh:
        if el.tag in ("Nodes", "Elements"):
            continue
        name = el.get("name")
        if el.tag == "Surface":
            fs = []
            for f in el:
                if f.tag != "quad4":
                    raise _err(path, f"surface '{name}': <{f.tag}> faces are not supported; "
                               "quad4 faces of hexahedra are needed")
                conn = _ints(f.text, path, f"surface '{name}' face {f.get('id')}",
                             len(node_index))
                fs.append([nid(i, f"surface '{name}'") for i in conn])
            faces[name] = np.array(fs, np.int64).reshape(-1, 4)
        elif el.tag == "NodeSet":
            ids = _ints(el.text, path, f"node set '{name}'", len(node_index)) + [
                _id(n, path, f"node set '{name}'") for n in el.findall("n")]
            nsets[name] = np.array([nid(i, f"node set '{name}'") for i in ids], np.int64)
        elif el.tag == "ElementSet":
            continue
        elif el.tag == "SurfacePair":
            pairs[name] = ((el.findtext("primary") or "").strip(),
                           (el.findtext("secondary") or "").strip())
        elif el.tag == "DiscreteSet":
            delems = []
            for d in el:
                if not isinstance(d.tag, str):
                    continue
                conn = _ints(d.text, path, f"discrete set '{name}'", len(node_index))
                if d.tag != "delem" or len(conn) != 2:
                    raise _err(path, f"discrete set '{name}': give each spring as "
                               "<delem>node,node</delem>")
                delems.append([nid(i, f"discrete set '{name}'") for i in conn])
            dsets[name] = np.array(delems, np.int64).reshape(-1, 2)
        else:
            raise _err(path, f"<Mesh><{el.tag} name=\"{name}\"> is not supported (edges "
                       "and other sets have no eyefem reader)")
    return faces, nsets, dsets, pairs


def _read_control(ctrl, fallback, path):
    """(time_steps, step_size) of a <Control> (a step's; ``fallback``: the deck's top-level
    <Control> for the values a step does not give)."""
    if ctrl is None and fallback is None:
        raise _err(path, "no <Control> section (time_steps, step_size)")
    vals = []
    for tag, hint in (("time_steps", "give the number of load steps, e.g. "
                       "<time_steps>10</time_steps>"),
                      ("step_size", "give the step's time increment, e.g. "
                       "<step_size>0.1</step_size>")):
        src = ctrl if ctrl is not None and ctrl.find(tag) is not None else fallback
        if src is None:
            src = ctrl
        vals.append(_child_float(src, tag, path, "<Control>", hint=hint))
    steps, dt = vals
    if steps != int(steps) or steps < 1 or not dt > 0:
        raise _err(path, f"<Control>: time_steps = {steps:g}, step_size = {dt:g}; time_steps "
                   "must be a whole number >= 1 and step_size > 0")
    bound = max_time_steps()
    if steps > bound:
        raise _err(path, f"<Control> time_steps = {steps:g}: more than {bound} load steps (each "
                   "is a Newton solve; eyefem ramps the loads linearly, so tens suffice); "
                   "lower time_steps, or raise the bound with EYEFEM_MAX_STEPS")
    return int(steps), dt


_INTERPOLATIONS = ("LINEAR", "STEP", "SMOOTH", "SMOOTH STEP")
_EXTENSIONS = ("CONSTANT", "EXTRAPOLATE", "REPEAT", "REPEAT OFFSET")


@dataclasses.dataclass(frozen=True)
class LoadCurve:
    """FEBio's load curve (FECore PointCurve::value, ExtendValue): points (t, v) sorted by
    t, ``interpolate`` LINEAR, STEP (the value of the next point), SMOOTH (Lagrange
    quadratics through three points, blended linearly between two of them) or SMOOTH STEP
    (f0 + (f1 - f0) w^3 (10 - 15 w + 6 w^2)); ``extend`` CONSTANT, EXTRAPOLATE, REPEAT or
    REPEAT OFFSET outside the points. ``error``: why the curve cannot be evaluated (another
    interpolation or controller type), raised only where a load uses it (a curve that only
    drives the time stepper's dtmax is never a load)."""

    lid: str
    t: tuple
    v: tuple
    interpolate: str = "LINEAR"
    extend: str = "CONSTANT"
    error: str | None = None

    def __call__(self, time: float) -> float:
        if self.error:
            raise FebError(self.error)
        t, v = self.t, self.v
        n = len(t)
        if n == 1:
            return v[0]
        if time == t[0]:
            return v[0]
        if time == t[-1]:
            return v[-1]
        if time < t[0] or time > t[-1]:
            return self._extend(time)
        i = int(np.searchsorted(t, time, side="right"))  # FEBio's binarySearch: first t > time
        mode = self.interpolate
        if mode == "STEP":
            return v[i]
        if mode == "LINEAR" or (mode == "SMOOTH" and n == 2):
            return _lerp(time, t[i - 1], v[i - 1], t[i], v[i])
        if mode == "SMOOTH STEP":
            w = (time - t[i - 1]) / (t[i] - t[i - 1])
            return v[i - 1] + (v[i] - v[i - 1]) * w ** 3 * (10.0 - 15.0 * w + 6.0 * w * w)
        # SMOOTH, three or more points
        if n == 3 or i == 1:
            return _qerp(time, t[:3], v[:3])
        if i == n - 1:
            return _qerp(time, t[n - 3:], v[n - 3:])
        q1 = _qerp(time, t[i - 2:i + 1], v[i - 2:i + 1])
        q2 = _qerp(time, t[i - 1:i + 2], v[i - 1:i + 2])
        return _lerp(time, t[i - 1], q1, t[i], q2)

    def _extend(self, time):
        t, v = self.t, self.v
        span = t[-1] - t[0]
        if span == 0:
            return v[0]
        if self.extend == "CONSTANT" or (self.extend == "EXTRAPOLATE"
                                         and self.interpolate in ("STEP", "SMOOTH STEP")):
            return v[0] if time < t[0] else v[-1]
        if self.extend == "EXTRAPOLATE":
            if self.interpolate == "LINEAR":
                return (_lerp(time, t[0], v[0], t[1], v[1]) if time < t[0] else
                        _lerp(time, t[-2], v[-2], t[-1], v[-1]))
            dt = 0.001 * span
            return (_lerp(time, t[0], v[0], t[0] + dt, self(t[0] + dt)) if time < t[0] else
                    _lerp(time, t[-1] - dt, self(t[-1] - dt), t[-1], v[-1]))
        k = 0
        while time < t[0]:
            time, k = time + span, k - 1
        while time > t[-1]:
            time, k = time - span, k + 1
        off = k * (v[-1] - v[0]) if self.extend == "REPEAT OFFSET" else 0.0
        return self(time) + off


def _lerp(time, t0, f0, t1, f1):
    return f0 + (f1 - f0) * (time - t0) / (t1 - t0)


def _qerp(time, t, f):
    (t0, t1, t2), (f0, f1, f2) = t, f
    q0 = ((t2 - time) * (t1 - time)) / ((t2 - t0) * (t1 - t0))
    q1 = ((t2 - time) * (time - t0)) / ((t2 - t1) * (t1 - t0))
    q2 = ((time - t1) * (time - t0)) / ((t2 - t1) * (t2 - t0))
    return f0 * q0 + f1 * q1 + f2 * q2


def _read_curves(root, path):
    """Load controller id -> :class:`LoadCurve` (FEBio's interpolations)."""
    out = {}
    data = root.find("LoadData")
    for lc in ([] if data is None else data):
        if not isinstance(lc.tag, str):
            continue
        lid = lc.get("id")
        where = f"load controller {lid}"
        if lc.tag != "load_controller" or lc.get("type") != "loadcurve":
            out[lid] = LoadCurve(lid, (0.0,), (0.0,), error=(
                f"{path}: {where}: <{lc.tag} type=\"{lc.get('type')}\"> is not supported; "
                "eyefem reads type=\"loadcurve\""))
            continue
        pts = [_floats(p.text, path, f"load curve {lid} point") for p in lc.iter("pt")]
        if len(pts) < 1 or any(len(p) != 2 for p in pts):
            raise _err(path, f"load curve {lid}: <points> needs <pt>time,value</pt> pairs")
        pts.sort(key=lambda p: p[0])
        mode = " ".join((lc.findtext("interpolate") or "LINEAR").strip().upper().split())
        ext = " ".join((lc.findtext("extend") or "CONSTANT").strip().upper().split())
        error = None
        if mode not in _INTERPOLATIONS:
            error = (f"{path}: load curve {lid}: <interpolate>{mode}</interpolate> is not "
                     f"supported (eyefem evaluates {', '.join(_INTERPOLATIONS)} as FEBio does)")
        elif ext not in _EXTENSIONS:
            error = (f"{path}: load curve {lid}: <extend>{ext}</extend> is not supported "
                     f"({', '.join(_EXTENSIONS)})")
        t, v = zip(*pts)
        out[lid] = LoadCurve(lid, tuple(t), tuple(v), mode, ext, error)
    return out


def _value(el, path, curves, where, size=1):
    """t -> the parameter's value at FEBio time t: its number(s) times its curve's value
    (``lc``; constant without one). ``size`` numbers (a vector for 3)."""
    if el.get("type") in ("map", "math"):
        raise _err(path, f"{where}: value type '{el.get('type')}' is not supported; give "
                   f"{'one number' if size == 1 else f'{size} numbers'}")
    v = _floats(el.text, path, where)
    if len(v) != size:
        raise _err(path, f"{where}: expected {size} number(s), got '{el.text}'")
    vec = np.array(v)
    lc = el.get("lc")
    if lc is None:
        return lambda t: vec.copy() if size > 1 else float(vec[0])
    if lc not in curves:
        raise _err(path, f"{where}: load controller {lc} is not defined in <LoadData>")
    curve = curves[lc]
    return lambda t: vec * curve(t) if size > 1 else float(vec[0] * curve(t))


def _nodes_of(mesh, ns, path, where):
    """Node ids of a <bc>/<nodal_load>'s node_set: a NodeSet, or '@surface:NAME' (the
    nodes of a Surface)."""
    if ns is not None and ns.startswith("@surface:") and ns[9:] in mesh.face_sets:
        return np.unique(mesh.face_sets[ns[9:]])
    if ns not in mesh.node_sets:
        raise _err(path, f"{where}: node set '{ns}' is not defined in <Mesh>")
    return mesh.node_sets[ns]


def _relative(el, path, where) -> bool:
    raw = (el.findtext("relative") or "0").strip().lower()
    if raw not in ("0", "1", "false", "true"):
        raise _err(path, f"{where} <relative> = '{raw}'; give 0 or 1")
    return raw in ("1", "true")


def _read_boundary(secs, path, mesh, curves, t, relative_ok, rigid=None):
    """(dofs, targets at FEBio time t) of the boundary conditions of ``secs`` (the model's
    and the step's <Boundary>). A prescribed displacement is FEBio's u = value x lc(t)
    (relative = 1 adds the displacement when the condition becomes active: the same in
    the first step, where it starts from the undeformed state; refused in later steps).
    ``rigid``: (dofs, targets) of the rigid bodies' nodes (:func:`_read_rigid`), added."""
    dofs, vals = ([], []) if rigid is None else ([rigid[0]], [rigid[1]])
    for sec in secs:
        for bc in ([] if sec is None else sec):
            if not isinstance(bc.tag, str):
                continue
            ns, kind = bc.get("node_set"), bc.get("type")
            where = f"<bc name=\"{bc.get('name')}\" type=\"{kind}\">"
            if bc.tag != "bc":
                raise _err(path, f"<Boundary><{bc.tag}> is not supported; give <bc>")
            if kind == "rigid":
                if sec is not secs[0]:
                    raise _err(path, f"{where} in a step: a node set joined to a rigid body "
                               "after the first step is not supported; give it in the "
                               "model's <Boundary>")
                continue
            if kind not in ("zero displacement", "prescribed displacement"):
                raise _err(path, f"{where}: boundary condition type '{kind}' is not supported "
                           "(zero displacement, prescribed displacement)")
            nodes = _nodes_of(mesh, ns, path, where)
            if kind == "zero displacement":
                comps = "".join(c for c in _XYZ
                                if _child_float(bc, f"{c}_dof", path, where, default=0.0) != 0)
                d = node_dofs(nodes, comps)
                dofs.append(d)
                vals.append(np.zeros(len(d)))
                continue
            comp = (bc.findtext("dof") or "").strip()
            if comp not in ("x", "y", "z"):
                raise _err(path, f"{where}: <dof> '{comp}'; expected x, y or z")
            if _relative(bc, path, where) and not relative_ok and sec is secs[-1]:
                raise _err(path, f"{where}: relative = 1 in a later step (the displacement "
                           "added to the one at the step's start) is not supported; give the "
                           "absolute displacement")
            val = bc.find("value")
            if val is None:
                raise _err(path, f"{where}: <value> is missing")
            d = node_dofs(nodes, comp)
            dofs.append(d)
            vals.append(np.full(len(d), _value(val, path, curves, where)(t)))
    if not dofs:
        return np.zeros(0, np.int64), np.zeros(0)
    d, v = np.concatenate(dofs), np.concatenate(vals)
    u, cnt = np.unique(d, return_counts=True)
    if np.any(cnt > 1):
        bad = u[cnt > 1][0]
        if np.ptp(v[d == bad]) > 0:
            raise _err(path, f"node {bad // 3 + 1} component {_XYZ[bad % 3]} is prescribed "
                       f"twice with different values {sorted(set(v[d == bad]))}")
        _, first = np.unique(d, return_index=True)
        d, v = d[np.sort(first)], v[np.sort(first)]
    return d, v


_RIGID_DOFS = ("Rx", "Ry", "Rz", "Ru", "Rv", "Rw")


def _rigid_name(el, path, where, materials, by_id) -> str:
    """The rigid body (a "rigid body" material's name) an element's <rb> names (by name or
    by FEBio id)."""
    rb = (el.findtext("rb") or el.get("rb") or "").strip()
    rb = by_id.get(rb, rb)
    spec = materials.get(rb)
    if not (isinstance(spec, _Special) and spec.kind == "rigid body"):
        raise _err(path, f"{where}: <rb> '{rb}' is not a \"rigid body\" material of <Material>")
    return rb


def _read_rigid(secs, path, rigid, curves, t, first, materials, by_id):
    """(dofs, targets at FEBio time t) of every rigid body's nodes.

    eyefem's rigid bodies move as prescribed only: each body's six degrees of freedom
    must all be held by <rigid_bc>s of the model and the step ("rigid_fixed" Rx_dof ..
    Rw_dof, "rigid_displacement" x, y, z with a value and a load curve, "rigid_rotation"
    of value zero). Its nodes then translate by the prescribed displacement (a rotation
    held at zero: no turn). A body with a free degree of freedom, a non-zero rotation, a
    rigid load or a rigid connector is refused by name."""
    held = {rb: {} for rb in rigid}  # rb -> dof -> value at t
    for sec in secs:
        for el in ([] if sec is None else sec):
            if not isinstance(el.tag, str):
                continue
            kind = el.get("type")
            where = f"<{el.tag} name=\"{el.get('name')}\" type=\"{kind}\">"
            if el.tag != "rigid_bc" or kind not in ("rigid_fixed", "rigid_displacement",
                                                     "rigid_rotation"):
                raise _err(path, f"{where} is not supported (eyefem reads rigid_bc "
                           "rigid_fixed, rigid_displacement and a zero rigid_rotation: rigid "
                           "bodies that move as prescribed; no rigid loads or connectors)")
            rb = _rigid_name(el, path, where, materials, by_id)
            if rb not in held:  # a body without elements or nodes moves nothing
                continue
            if kind == "rigid_fixed":
                for d in _RIGID_DOFS:
                    if _child_float(el, f"{d}_dof", path, where, default=0.0) != 0:
                        held[rb][d] = 0.0
                continue
            comp = (el.findtext("dof") or "").strip()
            allowed = ("x", "y", "z") if kind == "rigid_displacement" else ("Ru", "Rv", "Rw")
            if comp not in allowed:
                raise _err(path, f"{where}: <dof> '{comp}'; expected {', '.join(allowed)}")
            if _relative(el, path, where) and not first and sec is secs[-1]:
                raise _err(path, f"{where}: relative = 1 in a later step is not supported; "
                           "give the absolute displacement")
            val = el.find("value")
            if val is None:
                raise _err(path, f"{where}: <value> is missing")
            v = _value(val, path, curves, where)(t)
            d = "R" + comp if kind == "rigid_displacement" else comp
            if kind == "rigid_rotation" and v != 0.0:
                raise _err(path, f"{where}: a prescribed rotation ({comp} = {v:g} rad) is not "
                           "supported; eyefem's rigid bodies translate (rotations held at 0)")
            held[rb][d] = v
    dofs, vals = [np.zeros(0, np.int64)], [np.zeros(0)]
    for rb, h in held.items():
        free = [d for d in _RIGID_DOFS if d not in h]
        if free:
            raise _err(path, f"rigid body '{rb}': degrees of freedom {', '.join(free)} are "
                       "free; eyefem's rigid bodies move as prescribed only (fix or prescribe "
                       "all six with <rigid_bc>, or run the deck in FEBio)")
        for c in range(3):
            d = node_dofs(rigid[rb], _XYZ[c])
            dofs.append(d)
            vals.append(np.full(len(d), h[_RIGID_DOFS[c]]))
    moves = {rb: np.array([h[d] for d in _RIGID_DOFS[:3]]) for rb, h in held.items()}
    return np.concatenate(dofs), np.concatenate(vals), moves


_CONTACT_FLAGS = {"two_pass": "0", "tension": "0", "auto_penalty": "0", "fric_coeff": "0",
                  "smooth_aug": "0", "node_reloc": "0", "flip_primary": "0",
                  "flip_secondary": "0", "shell_bottom_primary": "0",
                  "shell_bottom_secondary": "0", "update_penalty": "0"}
"""sliding-elastic parameters eyefem maps only at these values (anything else refused);
the search and augmentation tolerances (tolerance, gaptol, search_tol, search_radius,
minaug, maxaug, knmult, seg_up, symmetric_stiffness) do not change a penalty solution."""


def _scoped(root, specs, tag) -> list:
    """[(step index or None, the <tag> section or None)]: the model's (None: every step)
    and each step's own (FEBio ends a step's components with the step)."""
    return [(None, root.find(tag))] + [(k, None if st is None else st.find(tag))
                                       for k, (_, _, st) in enumerate(specs)]


def _read_contacts(secs, path, mesh, pairs, rigid, step_moves) -> tuple:
    """:class:`FebContact` per <contact>: FEBio's "sliding-elastic" with a penalty (laugon
    0 / PENALTY), no friction, no auto-penalty, between a deformable surface and the
    facets of a rigid body moved along one direction. FEBio integrates the traction
    eps <-g> over the primary faces; eyefem's RigidContact puts alpha <-g> at each primary
    node with alpha = eps x the nodes' mean tributary area: the same total force for a
    uniform gap (tests/test_febio_links.py), and both tend to the exact contact
    constraint as the penalty grows. Other contact is refused by name. ``secs``: (step
    index or None, <Contact> or None): the model's and each step's; a contact written
    again in several steps (the same definition) is one contact acting in those steps."""
    out = []
    for step, sec in secs:
        for el in ([] if sec is None else sec):
            if isinstance(el.tag, str):
                c = _read_contact(el, path, mesh, pairs, rigid, step_moves, len(out))
                same = [i for i, o in enumerate(out) if o.name == c.name]
                if same and step is not None and out[same[0]].steps is not None and \
                        _same_contact(out[same[0]], c):
                    o = out[same[0]]
                    out[same[0]] = dataclasses.replace(o, steps=o.steps + (step,))
                elif same:
                    raise _err(path, f"<contact name=\"{c.name}\">: defined twice with "
                               "different settings (or in the model and in a step); give "
                               "each contact its own name")
                else:
                    out.append(dataclasses.replace(
                        c, steps=None if step is None else (step,)))
    return tuple(out)


def _same_contact(a: FebContact, b: FebContact) -> bool:
    return (a.primary, a.body, a.penalty) == (b.primary, b.body, b.penalty) and \
        np.array_equal(a.facets, b.facets)


def _read_contact(el, path, mesh, pairs, rigid, step_moves, n_before) -> FebContact:
    """One <contact> (see :func:`_read_contacts`)."""
    kind, name = el.get("type"), el.get("name") or f"contact_{n_before + 1}"
    where = f"<contact name=\"{name}\" type=\"{kind}\">"
    if el.tag != "contact" or kind != "sliding-elastic":
        raise _err(path, f"{where} is not supported (eyefem reads frictionless "
                   "sliding-elastic contact against a rigid body with a penalty)")
    _penalty_form(path, el, where, "eyefem's contact is a penalty (laugon 0 / PENALTY); "
                  "the augmented Lagrangian is not supported")
    for tag, want in _CONTACT_FLAGS.items():
        got = (el.findtext(tag) or want).strip()
        if float(got) != float(want):
            raise _err(path, f"{where}: <{tag}> {got} is not supported (eyefem maps "
                       f"{tag} = {want} only)")
    eps = _child_float(el, "penalty", path, where, hint="give the penalty, MPa/mm")
    if el.find("penalty").get("lc") is not None or not eps > 0:
        raise _err(path, f"{where}: <penalty> must be a number > 0 without a load curve")
    pair = pairs.get(el.get("surface_pair"))
    if pair is None:
        raise _err(path, f"{where}: surface pair '{el.get('surface_pair')}' is not "
                   "defined in <Mesh>")
    primary, secondary = pair
    for surf in pair:
        if surf not in mesh.face_sets:
            raise _err(path, f"{where}: surface '{surf}' is not defined in <Mesh>")
    sec_nodes = np.unique(mesh.face_sets[secondary])
    body = [rb for rb, nodes in rigid.items() if np.all(np.isin(sec_nodes, nodes))]
    on_rigid = [rb for rb, nodes in rigid.items()
                if np.any(np.isin(np.unique(mesh.face_sets[primary]), nodes))]
    if not body or on_rigid:
        raise _err(path, f"{where}: eyefem reads contact of a deformable primary "
                   "surface against the facets of one rigid body (secondary); contact "
                   "between deformable bodies is not supported")
    rb = body[0]
    moves = np.array([m[rb] for m in step_moves])
    big = moves[np.argmax(np.linalg.norm(moves, axis=1))]
    direction = big / np.linalg.norm(big) if np.linalg.norm(big) > 0 else np.eye(3)[2]
    d = moves @ direction
    if np.max(np.linalg.norm(moves - d[:, None] * direction, axis=1), initial=0.0) > \
            1e-12 * max(1.0, float(np.abs(d).max())):
        raise _err(path, f"{where}: rigid body '{rb}' moves along different directions "
                   "in different steps; eyefem's contact body moves along one")
    faces = mesh.face_sets[primary]
    x = mesh.nodes[faces]
    area = 0.5 * np.linalg.norm(np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1]), axis=1)
    tributary = np.bincount(faces.ravel(), np.repeat(area / 4, 4),
                            minlength=mesh.n_nodes)[np.unique(faces)]
    return FebContact(name, primary, rb, mesh.face_sets[secondary], direction,
                      tuple(float(v) for v in d), eps * float(tributary.mean()))


def contact_term(c: FebContact, mesh: Mesh) -> Term:
    """eyefem.fem.rigid_contact.RigidContact of a :class:`FebContact`: the primary
    surface's nodes against the rigid body's facets (two triangles per quad, their normals
    as the deck orders them: FEBio's secondary normals face the primary surface, eyefem's
    point out of the rigid body), moved by d along the body's direction."""
    from eyefem.fem.rigid import RigidBody
    from eyefem.fem.rigid_contact import RigidContact

    used, inv = np.unique(c.facets, return_inverse=True)
    quads = inv.reshape(-1, 4)
    P = mesh.nodes[used]
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    try:
        body = RigidBody(c.body, P, tris, tuple(c.direction))
    except ValueError as exc:
        raise FebError(f"contact '{c.name}': {exc}") from None
    return RigidContact(f"contact:{c.name}", mesh, f"contact:{c.name}", (body,),
                        penalty=c.penalty)


def _read_volumes(secs, path, mesh) -> tuple:
    """(name, face set, eps, step) per FEBio "volume" constraint (FEVolumeConstraint) of
    the model's (step None) and each step's <Constraints>: the penalty form only (laugon
    0 / PENALTY) with eps < 0 (a liquid); anything else refused by name."""
    out = []
    for step, sec in secs:
        for el in ([] if sec is None else sec):
            if not isinstance(el.tag, str):
                continue
            kind, name = el.get("type"), el.get("name") or f"volume_{len(out) + 1}"
            where = f"<constraint name=\"{name}\" type=\"{kind}\">"
            if el.tag != "constraint" or kind != "volume":
                raise _err(path, f"{where} is not supported (eyefem reads the \"volume\" "
                           "constraint as a closed liquid cavity)")
            _penalty_form(path, el, where, "FEBio's augmented Lagrangian holds the volume "
                          "exactly; eyefem's cavity is a compressible liquid (give laugon 0 "
                          "and a penalty)")
            for child in el:
                if isinstance(child.tag, str) and child.tag not in ("laugon", "penalty",
                                                                     "augtol"):
                    raise _err(path, f"{where}: <{child.tag}> is not supported (laugon, "
                               "penalty)")
            eps = _child_float(el, "penalty", path, where, hint="give the penalty, MPa/mm^3")
            if not eps < 0:
                raise _err(path, f"{where}: <penalty> = {eps:g}: FEBio's p = eps (V - V0) acts "
                           "along the faces' normals, so a liquid resisting its compression "
                           "needs eps < 0 (eps > 0 pushes the volume away from V0)")
            surf = el.get("surface")
            if surf not in mesh.face_sets:
                raise _err(path, f"{where}: surface '{surf}' is not defined in <Mesh>")
            out.append((name, surf, eps, step))
    return tuple(out)


def volume_term(name, mesh, surf, eps, path="deck"):
    """FEBio's volume constraint as eyefem.fem.cavity.FluidCavity: FEBio's multiplier
    p = eps (V - V0) pushes along the faces' normals with V = 1/3 integral x . n da over
    them (FEVolumeConstraint::LoadVector), i.e. a liquid of pressure P = eps (V_c - V0) on
    either orientation of the faces (V_c the enclosed volume): the cavity's law P = P_ini -
    K (V_c - V_ini) / V_ini with P_ini = 0, V_ini = V0 and K = -eps V0. The faces are
    turned to face the liquid where the deck's face away from it. Returns (term, the mesh
    with the face set used)."""
    from eyefem.fem.cavity import FluidCavity

    faces = mesh.face_sets[surf]
    x = mesh.nodes[faces]  # the sign of FEBio's V (two triangles per face about 0)
    v_febio = sum(np.einsum("fi,fi->f", x[:, 0], np.cross(x[:, i], x[:, i + 1])).sum()
                  for i in (1, 2)) / 6.0
    if v_febio > 0:  # normals out of the enclosed region: eyefem's face the liquid
        key = f"volume:{name}"
        mesh = dataclasses.replace(mesh, face_sets={**mesh.face_sets, key: faces[:, ::-1]})
        surf = key
    try:
        probe = FluidCavity(f"volume:{name}", mesh, surf, bulk=0.0)
        V0 = float(np.ravel(probe.params["v_ini"])[0])
        term = FluidCavity(f"volume:{name}", mesh, surf, p_ini=0.0, bulk=-eps * V0,
                           v_ini=V0)
    except ValueError as exc:
        raise FebError(f"{path}: volume constraint '{name}': {exc}") from None
    return term, mesh


def _close_volume(model, q, theta, name, eps):
    """A step's volume constraint acts from the step's start: V0 the volume then, FEBio's
    multiplier 0 (P_ini = 0), K = -eps V0 (a Stage ``before`` hook)."""
    term = model.term(name)
    _, V = term.pressures(q, theta[name])
    V = float(np.ravel(V)[0])
    new = {**theta[name], "p_ini": term._shape(0.0), "v_ini": term._shape(V),
           "dv": term._shape(0.0), "bulk": term._shape(-eps * V)}
    return model, q, {**theta, name: new}


_SPRINGS = ("linear spring", "tension-only linear spring")


def _read_links(root, path, nodes, materials, lines, truss_of_block, discrete_sets):
    """:class:`FebLinks` of the truss domains and of <Discrete>'s springs."""
    out = []
    for name, conn in lines.items():
        mat, area = truss_of_block[name]
        out.append(FebLinks(name, "linear truss", conn,
                            np.full(len(conn), materials[mat].E * area)))
    sec = root.find("Discrete")
    dmats = {}
    for el in ([] if sec is None else sec):
        if not isinstance(el.tag, str):
            continue
        where = f"<{el.tag} name=\"{el.get('name')}\" type=\"{el.get('type')}\">"
        if el.tag == "discrete_material":
            if el.get("type") not in _SPRINGS:
                raise _err(path, f"{where}: discrete material type '{el.get('type')}' is not "
                           f"supported (eyefem reads {', '.join(_SPRINGS)})")
            for child in el:
                if isinstance(child.tag, str) and child.tag != "E":
                    raise _err(path, f"{where}: <{child.tag}> is not supported (E)")
            E = _child_float(el, "E", path, where, hint="give the spring's stiffness, N/mm")
            if not E > 0:
                raise _err(path, f"{where} <E> = {E:g} N/mm: must be > 0")
            dmats[el.get("id")] = dmats[el.get("name")] = (el.get("type"), E)
        elif el.tag == "discrete":
            dm, ds = el.get("dmat"), el.get("discrete_set")
            where = f"<discrete dmat=\"{dm}\" discrete_set=\"{ds}\">"
            if dm not in dmats:
                raise _err(path, f"{where}: discrete material '{dm}' is not defined above it")
            if ds not in discrete_sets:
                raise _err(path, f"{where}: discrete set '{ds}' is not defined in <Mesh>")
            conn = discrete_sets[ds]
            out.append(FebLinks(ds, dmats[dm][0], conn, np.full(len(conn), dmats[dm][1])))
        else:
            raise _err(path, f"<Discrete><{el.tag}> is not supported (discrete_material, "
                       "discrete)")
    return tuple(out)


def _densities(root, path, mesh, used, blocks, mat_of_block):
    """Density (FEBio's <density>, default 1) of each element, for body loads."""
    rho = {}
    for el in root.find("Material"):
        if isinstance(el.tag, str):
            name = el.get("name") or f"material_{el.get('id')}"
            rho[name] = _child_float(el, "density", path, f"material '{name}'", default=1.0)
    return np.array([rho.get(mesh.materials[m], 1.0) for m in mesh.material_ids])


def _element_node_integrals(mesh, density):
    """(n_nodes,) sum over the elements of density x the integral of N_a over the reference
    volume (2 x 2 x 2 Gauss, as FEBio integrates a hex8's body force)."""
    from eyefem.fem.mesh import hex_gauss_points, hex_shape
    xg, _ = hex_gauss_points()
    shape, _ = hex_shape(xg)  # (8g, 8a)
    _, dv, _ = hex_geometry(mesh.nodes, mesh.hexes)  # (e, 8g)
    per = np.einsum("ga,eg->ea", shape, dv) * density[:, None]
    out = np.zeros(mesh.n_nodes)
    np.add.at(out, mesh.hexes.ravel(), per.ravel())
    return out


def _face_node_integrals(mesh, faces):
    """(n_nodes,) the integral of N_a over the quad4 faces' reference area (2 x 2 Gauss,
    FEBio's FESurface::LoadVector with the reference coordinates): a traction's nodal
    weights."""
    g = 1.0 / np.sqrt(3.0)
    out = np.zeros(mesh.n_nodes)
    x = mesh.nodes[faces]  # (f, 4, 3), corners counter-clockwise
    r0, s0 = np.array([-1.0, 1.0, 1.0, -1.0]), np.array([-1.0, -1.0, 1.0, 1.0])
    for r, s in ((-g, -g), (g, -g), (g, g), (-g, g)):
        n = 0.25 * (1 + r0 * r) * (1 + s0 * s)
        dr = np.einsum("a,fai->fi", 0.25 * r0 * (1 + s0 * s), x)
        ds = np.einsum("a,fai->fi", 0.25 * s0 * (1 + r0 * r), x)
        da = np.linalg.norm(np.cross(dr, ds), axis=1)
        np.add.at(out, faces.ravel(), (n[None, :] * da[:, None]).ravel())
    return out


def _read_loads(sec, path, mesh, curves, scope, density):
    """[(term name, kind, data, value(t))]: kind "pressure" (data: the surface; value in
    MPa) or "force" (data: dofs; value: (n,) N) per load of a <Loads>.

    Surface pressure: FEBio's follower pressure. Traction (FETractionLoad): the dead force
    scale(t) t integral N_a dA over the reference faces. Nodal loads: ``nodal_force`` (value x, y,
    z) and ``nodal_load`` (one dof x, y or z, scale), dead loads on the node set's nodes.
    Body load ``const`` (x, y, z per unit mass): FEBio adds -rho b N_a over the reference
    volume to its residual (FEElasticSolidDomain::BodyForce), i.e. the nodal forces
    -b rho integral N_a dV (gravity along -z is given as z = +9.81)."""
    out = []
    for sl in ([] if sec is None else sec):
        if not isinstance(sl.tag, str):
            continue
        kind = sl.get("type")
        where = f"<{sl.tag} type=\"{kind}\">"
        tname = scope + (sl.get("name") or f"{sl.tag}_{len(out) + 1}")
        if sl.tag == "surface_load" and kind == "pressure":
            surf = sl.get("surface")
            if surf not in mesh.face_sets:
                raise _err(path, f"{where}: surface '{surf}' is not defined in <Mesh>")
            p = sl.find("pressure")
            if p is None:
                raise _err(path, f"{where}: <pressure> is missing")
            if (sl.findtext("linear") or "0").strip() not in ("0", "false"):
                log.warning("%s: %s on '%s' has linear = 1 (a dead load); eyefem applies a "
                            "follower pressure", path, where, surf)
            out.append((tname, "pressure", surf, _value(p, path, curves, where)))
        elif sl.tag == "nodal_load" and kind in ("nodal_force", "nodal_load"):
            nodes = _nodes_of(mesh, sl.get("node_set"), path, where)
            if _relative(sl, path, where):
                raise _err(path, f"{where}: relative = 1 is not supported")
            if kind == "nodal_force":
                el = sl.find("value")
                if el is None:
                    raise _err(path, f"{where}: <value> is missing")
                vec = _value(el, path, curves, where, size=3)
                dofs = node_dofs(nodes, "xyz")
                out.append((tname, "force", dofs,
                            lambda t, vec=vec, n=len(nodes): np.tile(vec(t), n)))
            else:
                comp = (sl.findtext("dof") or "").strip()
                if comp not in ("x", "y", "z"):
                    raise _err(path, f"{where}: <dof> '{comp}'; eyefem reads x, y or z")
                el = sl.find("scale")
                if el is None:
                    raise _err(path, f"{where}: <scale> is missing")
                sc = _value(el, path, curves, where)
                out.append((tname, "force", node_dofs(nodes, comp),
                            lambda t, sc=sc, n=len(nodes): np.full(n, sc(t))))
        elif sl.tag == "surface_load" and kind == "traction":
            surf = sl.get("surface")
            if surf not in mesh.face_sets:
                raise _err(path, f"{where}: surface '{surf}' is not defined in <Mesh>")
            for child in sl:
                if isinstance(child.tag, str) and child.tag not in (
                        "scale", "traction", "shell_bottom", "linear"):
                    raise _err(path, f"{where}: <{child.tag}> is not supported (scale, "
                               "traction)")
            if (sl.findtext("shell_bottom") or "0").strip() not in ("0", "false"):
                raise _err(path, f"{where}: shell_bottom = 1 is not supported (no shells)")
            tr = sl.find("traction")
            if tr is None or tr.get("type") is not None or tr.get("lc") is not None:
                raise _err(path, f"{where}: give <traction>x,y,z</traction> (a constant "
                           "vector; its curve on <scale>)")
            vec = np.array(_floats(tr.text, path, f"{where} <traction>"))
            if vec.shape != (3,):
                raise _err(path, f"{where} <traction>: give three numbers x,y,z")
            sc = (_value(sl.find("scale"), path, curves, where) if sl.find("scale") is not None
                  else (lambda t: 1.0))
            w = _face_node_integrals(mesh, mesh.face_sets[surf])
            used = np.nonzero(w)[0]
            out.append((tname, "force", node_dofs(used, "xyz"),
                        lambda t, sc=sc, w=w[used], v=vec: (w[:, None] * (sc(t) * v)).ravel()))
        elif sl.tag == "body_load" and kind == "const":
            if sl.get("elem_set"):
                raise _err(path, f"{where}: elem_set is not supported (the whole mesh)")
            comps = [_value(sl.find(c), path, curves, f"{where} <{c}>") if sl.find(c) is not None
                     else (lambda t: 0.0) for c in _XYZ]
            for child in sl:
                if isinstance(child.tag, str) and child.tag not in _XYZ:
                    raise _err(path, f"{where}: <{child.tag}> is not supported (x, y, z)")
            mass = _element_node_integrals(mesh, density)
            used = np.nonzero(mass)[0]
            out.append((tname, "force", node_dofs(used, "xyz"),
                        lambda t, comps=comps, m=mass[used]:
                        -(m[:, None] * np.array([c(t) for c in comps])[None, :]).ravel()))
        else:
            raise _err(path, f"{where}: <{sl.tag} type=\"{kind}\"> is not supported (eyefem "
                       "reads surface_load pressure and traction, nodal_load nodal_force / "
                       "nodal_load and body_load const)")
    return out


def build_stages(mesh: Mesh, materials: dict, loads: FebLoads) -> tuple[Model, list]:
    """The eyefem model (the solid, FEBio's follower pressure per pressure load:
    eyefem.fem.surface.pressure_term, a NodalForce per nodal or body load) and one Stage
    per FEBio step: the step's time_steps, its boundary conditions and the loads at its
    end time, reached linearly from the previous step's end (for the elastic solids read,
    the state at a step's end depends on the loads there only, not on the path)."""
    terms = [pressure_term(name, mesh, surf, p0) for name, surf, p0, _ in loads.pressures]
    terms += [NodalForce(name, dofs, {"f": f0}) for name, dofs, f0 in loads.forces]
    terms += [link_term(lk, mesh.nodes) for lk in loads.links]
    for name, surf, eps, _ in loads.volumes:
        term, mesh = volume_term(name, mesh, surf, eps)
        terms.append(term)
    terms += [contact_term(c, mesh) for c in loads.contacts]
    if mesh.n_elem and any(isinstance(materials[m], FebioLaw) for m in mesh.materials):
        model = _law_model(mesh, materials, loads, tuple(terms))
    elif mesh.n_elem:
        model = solid_model(mesh, materials, tuple(terms))
    else:  # trusses and springs only
        model = Model(mesh, tuple(terms), 3 * mesh.n_nodes)
    steps = loads.steps or (FebStep("load", loads.n_steps, 1.0, loads.prescribed,
                                    {n: {"p": p1} for n, _, _, p1 in loads.pressures}),)
    names = [t.name for t in model.terms]
    stages = []
    for k, st in enumerate(steps):
        scoped = [(f"volume:{n}", eps) for n, _, eps, step in loads.volumes if step == k]
        off = {f"volume:{n}" for n, _, _, step in loads.volumes if step not in (None, k)}
        off |= {f"contact:{c.name}" for c in loads.contacts
                if c.steps is not None and k not in c.steps}
        before = None
        if scoped:
            def before(model, q, theta, scoped=scoped):
                for name, eps in scoped:
                    model, q, theta = _close_volume(model, q, theta, name, eps)
                return model, q, theta
        stages.append(Stage(st.name, st.n_steps, st.prescribed, params=st.params,
                            active=tuple(n for n in names if n not in off) if off else None,
                            before=before))
    return model, stages


def _law_model(mesh, materials, loads, extra) -> Model:
    """The model of a deck with FebioLaw materials: one SolidFebioLaw term per such
    material ("solid:<name>"), the other materials' elements on the terms solid_model
    gives them (SolidCompressible; Q1P0 with one multiplier per element for the exactly
    incompressible ones)."""
    from eyefem.fem.materials import bulk_modulus, coupled_constants, is_compressible
    from eyefem.fem.solid import SolidQ1P0
    from eyefem.fem.solid_compressible import SolidCompressible, SolidFebioLaw
    n_u = 3 * mesh.n_nodes
    names = list(mesh.materials)
    law = np.array([isinstance(materials[m], FebioLaw) for m in names], bool)
    comp = np.array([not lw and is_compressible(materials[m]) for m, lw in zip(names, law)])
    terms, n_mult = [], 0
    coeffs = np.stack([materials[m].coeffs for m in names])
    inc = np.nonzero(~law[mesh.material_ids] & ~comp[mesh.material_ids])[0]
    if len(inc):
        terms.append(SolidQ1P0("solid", mesh, coeffs, multiplier_offset=n_u, elements=inc))
        n_mult = len(inc)
    on = np.nonzero(comp[mesh.material_ids])[0]
    if len(on):
        k = np.array([0.0 if lw else bulk_modulus(materials[m]) for m, lw in zip(names, law)])
        cc = np.stack([np.zeros(3) if lw else coupled_constants(materials[m])
                       for m, lw in zip(names, law)])
        terms.append(SolidCompressible("solid_compressible", mesh, coeffs, k, cc, elements=on))
    for i, m in enumerate(names):
        if law[i]:
            terms.append(SolidFebioLaw(f"solid:{m}", mesh, materials[m],
                                       np.nonzero(mesh.material_ids == i)[0],
                                       loads.fibers.get(m), loads.law_constants.get(m)))
    return Model(mesh, (*terms, *extra), n_u + n_mult)


@dataclasses.dataclass(frozen=True, eq=False)
class LinearSpring(Term):
    """FEBio's "linear spring" between two nodes (FELinearSpring on a discrete set): the
    force E (l - L0) along the spring, the energy

        e = 1/2 E (l - L0)^2                                             [N mm]

    with E in N/mm: eyefem.fem.bars.Bars with node ends and EA = E L0 where L0 > 0 (the
    same energy; tests/test_febio_links.py), and also a spring of zero length (L0 = 0: e =
    1/2 E |x_b - x_a|^2, a node tied to another; Bars refuses it). ``tension_only``:
    FEBio's "tension-only linear spring", E max(l - L0, 0).

    Args: name; nodes (m, 2) node ids; node_xyz (n_nodes, 3), mm; E (m,) N/mm (params
      {"E"}); tension_only.
    """

    name: str
    nodes: np.ndarray
    node_xyz: np.ndarray
    E: np.ndarray
    tension_only: bool = False

    def __post_init__(self):
        n = np.asarray(self.nodes, np.int64).reshape(-1, 2)
        X = np.asarray(self.node_xyz, np.float64)[n]
        E = np.broadcast_to(np.asarray(self.E, np.float64), (len(n),)).copy()
        if np.any(E <= 0):
            raise ValueError(f"spring '{self.name}': stiffness E must be > 0 N/mm")
        object.__setattr__(self, "dofs", (3 * n[:, :, None] + np.arange(3)).reshape(-1, 6))
        object.__setattr__(self, "params", {"E": E})
        object.__setattr__(self, "data", {"X": X.reshape(-1, 6),
                                          "L0": np.linalg.norm(X[:, 1] - X[:, 0], axis=1)})

    def static_key(self):
        return (self.tension_only,)

    def local_energy(self, q_loc, params, data):
        x = (data["X"] + q_loc).reshape(-1, 2, 3)
        dd = jnp.sum((x[:, 1] - x[:, 0]) ** 2, axis=1)
        L0 = data["L0"]
        pos = L0 > 0
        s = jnp.sqrt(jnp.where(pos, dd, 1.0)) - L0  # the safe branch: no NaN slope at l = 0
        if self.tension_only:
            s = jnp.maximum(s, 0.0)
        return 0.5 * params["E"] * jnp.where(pos, s * s, dd)

    def forces(self, q, params):
        """Spring force per spring (m,), N (positive in tension)."""
        x = (self.data["X"] + np.asarray(q)[self.dofs]).reshape(-1, 2, 3)
        s = np.linalg.norm(x[:, 1] - x[:, 0], axis=1) - self.data["L0"]
        return np.asarray(params["E"]) * (np.maximum(s, 0.0) if self.tension_only else s)

    def report(self, q, params):
        f = self.forces(q, params)
        return {"max_force_N": float(np.abs(f).max()) if len(f) else 0.0}


def link_term(link: FebLinks, node_xyz) -> Term:
    """The eyefem term of a truss domain (:class:`LinearTruss`) or a discrete set
    (:class:`LinearSpring`)."""
    name = f"{link.kind.replace(' ', '_')}:{link.name}"
    if link.kind == "linear truss":
        return LinearTruss(name, link.nodes, node_xyz, link.stiffness)
    return LinearSpring(name, link.nodes, node_xyz, link.stiffness,
                        tension_only=link.kind.startswith("tension-only"))


def build_model(mesh: Mesh, materials: dict, loads: FebLoads) -> tuple[Model, Stage]:
    """:func:`build_stages` of a deck with one step: the model and its Stage."""
    model, stages = build_stages(mesh, materials, loads)
    if len(stages) != 1:
        raise FebError(f"the deck has {len(stages)} steps; use build_stages (one Stage per "
                       "step)")
    return model, stages[0]


def deck_pieces(path) -> dict:
    """What a deck holds, counted from its XML without building a model (a deck that
    :func:`read_feb` refuses, e.g. one with contact, can still be checked piece by piece):
    {"nodes": int, "elements": {type: count}, "springs": {discrete material type: count},
    "rigid_bodies": int, "contacts": {type: count}, "constraints": {type: count} (the
    model's and the steps'), "steps": [names], "surface_loads": int, "omissions": [the
    header's 'not exported or approximated' lines]}."""
    import collections
    import re

    path = Path(path)
    try:
        root = ET.parse(path, ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
                        ).getroot()
    except ET.ParseError as exc:
        raise _err(path, f"not valid XML ({exc})") from None
    nodes, _ = _read_nodes(root, path)
    elements = collections.Counter()
    for block in root.iterfind("Mesh/Elements"):
        elements[block.get("type")] += len(block.findall("elem"))
    dsets = {d.get("name"): len(d.findall("delem")) for d in root.iterfind("Mesh/DiscreteSet")}
    dmat = {m.get("id"): m.get("type") for m in root.iterfind("Discrete/discrete_material")}
    springs = collections.Counter()
    for d in root.iterfind("Discrete/discrete"):
        springs[dmat.get(d.get("dmat"))] += dsets.get(d.get("discrete_set"), 0)
    contacts = collections.Counter(c.get("type") for c in root.iter("contact"))
    constraints = collections.Counter(c.get("type") for c in root.iter("constraint"))
    omissions = []
    for el in root:
        if el.tag is ET.Comment and el.text:
            omissions += [m.strip() for m in
                          re.findall(r"not exported or approximated: (.*)", el.text)]
    return {"nodes": len(nodes), "elements": dict(elements), "springs": dict(springs),
            "rigid_bodies": sum(m.get("type") == "rigid body"
                                for m in root.iterfind("Material/material")),
            "contacts": dict(contacts), "constraints": dict(constraints),
            "steps": [st.get("name") for st in root.iterfind("Step/step")],
            "surface_loads": len(root.findall("Loads/surface_load")),
            "omissions": omissions}


def feb_setup(path) -> Setup:
    """A Setup (for eyefem.run.runner.run_setup) of an FEBio deck: probe records the largest
    nodal displacement (mm); the summary gives its final value, the deck's sizes and the
    sha256 of the deck read (``deck_sha256``)."""
    path = Path(path)
    mesh, materials, loads, sha = read_feb_deck(path)
    model, stages = build_stages(mesh, materials, loads)
    n = mesh.n_nodes

    def probe(model, q, theta):
        u = np.asarray(q[: 3 * n]).reshape(n, 3)
        return {"max_displacement_mm": float(np.max(np.linalg.norm(u, axis=1)))}

    def finish(rows, out_dir, plots):
        return {"deck": str(path), "deck_sha256": sha, "nodes": n, "elements": mesh.n_elem,
                "max_displacement_mm": rows[-1]["max_displacement_mm"] if rows else 0.0}

    return Setup(path.stem, model, stages, probe, finish)


def solution_norm(mesh, stage, q, loads: FebLoads | None = None) -> float:
    """FEBio's ``solution_norm`` at the end of ``stage`` (its TestSuite's gold standard):
    |u| (mm) over the dofs of nodes in elements (solids; with ``loads``, also its trusses
    and springs) that the stage neither fixes nor prescribes (a rigid body's nodes are
    prescribed). Args: mesh; stage (its ``prescribed``); q (n_dof,) the state."""
    free = np.ones(3 * mesh.n_nodes, bool)
    free[stage.prescribed[0]] = False
    used = np.zeros(mesh.n_nodes, bool)
    used[np.unique(mesh.hexes)] = True
    for lk in () if loads is None else loads.links:
        used[np.asarray(lk.nodes).ravel()] = True
    free &= np.repeat(used, 3)
    return float(np.linalg.norm(np.asarray(q)[: 3 * mesh.n_nodes][free]))
