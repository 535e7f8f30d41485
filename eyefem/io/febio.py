"""FEBio 4 input decks (``<febio_spec version="4.0">``): write a model's stages (reading
a deck back: eyefem.io.febio_read).

Mapping (see docs/febio.md):

* nodes and elements: FEBio numbers from 1; its hex8 node order is eyefem's (VTK's,
  :data:`eyefem.fem.mesh.HEX_CORNERS`: FEBio's FEHex8 shape functions have node 0 at
  (-1,-1,-1), 1 at (+1,-1,-1), 2 at (+1,+1,-1), 3 at (-1,+1,-1), then 4-7 at zeta = +1);
  quad4 faces keep their node order (right-hand normal out of the solid in both codes);
* materials: eyefem's W = c10 (I1bar - 3) + c01 (I2bar - 3), incompressible through the
  element multiplier, becomes FEBio's uncoupled "Mooney-Rivlin" (c1 = c10, c2 = c01) with
  the bulk modulus k = ``bulk_factor`` (c10 + c01) (default 1000) and FEBio's augmented
  Lagrangian (the SolidDomain's <laugon>1</laugon> and <atol> AUGMENTATION_TOL, type
  "three-field-solid": FEBio 4 reads them there): its augmentations drive each
  three-field element's volume ratio Jbar = v / V to 1, the Q1P0 element's constraint, and
  the reader takes laugon = 1 back as exactly incompressible; higher-order terms (c20,
  c30, ...) have no FEBio "Mooney-Rivlin" equivalent and are dropped with a warning;
  FEBio's own laws (eyefem.fem.materials.UncoupledMooneyRivlin with its k,
  CoupledMooneyRivlin) are written as what they are ("Mooney-Rivlin" with that k,
  "neo-Hookean", "coupled Mooney-Rivlin"), and read back as such;
* stages: each a <step> (one stage: FEBio's single analysis, no <Step>); each param's
  value at the stages' ends on a load curve (stage k spans FEBio time [k - 1, k]);
* loads: prescribed displacements (a dof d is node d // 3, component d % 3) become
  "zero displacement" / "prescribed displacement" boundary conditions on node sets, each
  surface pressure (eyefem.fem.surface.PressureLoad: a follower load, positive against
  the outward normal as in FEBio) a "pressure" surface load;
* bars (eyefem.fem.bars.Bars) and node springs (NodeSprings) become FEBio's linear
  springs (the same energies: E = EA / L0; node springs as three springs to fixed ground
  nodes GROUND_ARM away along x, y, z);
* an encircling rigid buckle (eyefem.fem.buckle_contact.BuckleContact) becomes
  BUCKLE_SEGMENTS rigid bodies of quad4 facets translated radially, each in
  sliding-elastic contact with the sclera; a closed cavity (eyefem.fem.cavity.FluidCavity)
  FEBio's volume constraint (penalty -K / V_ini).

What FEBio cannot be given (sutures tied and tightened in a later stage, the orbit's
springs on a ring's rigid motion, ...) or is given approximately is returned, logged and
written in the deck's header comment. What FEBio 4.11 gives for the exported decks:
docs/febio.md.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from eyefem.fem.bars import Bars
from eyefem.fem.buckle_contact import BuckleContact
from eyefem.fem.cavity import FluidCavity
from eyefem.fem.mesh import Mesh
from eyefem.fem.solid import SolidQ1P0
from eyefem.fem.solid_compressible import SolidCompressible
from eyefem.fem.surface import PressureLoad
from eyefem.fem.terms import NodeSprings
from eyefem.io.febio_read import SPEC_VERSION, FebError, build_stages, read_feb
from eyefem.solve.problem import Setup
from eyefem.solve.solver import Stage

log = logging.getLogger(__name__)

BULK_FACTOR = 1000.0
"""Default FEBio bulk modulus k as a multiple of c10 + c01 (Poisson's ratio about 0.4997)."""

_XYZ = "xyz"

GROUND_ARM = 1e6
"""Rest length (mm) of the three springs along x, y and z that give FEBio a node spring
(eyefem.fem.terms.NodeSprings, 1/2 k |u|^2): their energy 1/2 k sum_i (|a e_i + u| - a)^2
is 1/2 k |u|^2 to a relative O(|u| / a) (5e-8 at 0.1 mm). A zero-length spring would be
the same energy, but FEBio's spring has no stiffness across itself at zero length
(FESpringMaterial::Stiffness), so a node held only by such springs is loose in the first
iteration."""

AUGMENTATION_TOL = 1e-3
"""FEBio's <atol> written with <laugon>1</laugon> for an exactly incompressible material:
its augmentations stop when the norm of the element pressures changes by less than this
fraction (FE3FieldElasticSolidDomain::Augment; FEBio's default 0.01)."""


# --------------------------------------------------------------------------- writing
def _fmt(v: float) -> str:
    return repr(float(v))


def safe_names(names) -> dict[str, str]:
    """eyefem set name -> FEBio name: characters other than letters, digits, '_' and '-'
    (the '/' of merged parts) become '_'; clashes get a numeric suffix."""
    out, used = {}, set()
    for n in names:
        base = re.sub(r"[^A-Za-z0-9_\-]", "_", n) or "set"
        s, k = base, 1
        while s in used:
            k += 1
            s = f"{base}_{k}"
        used.add(s)
        out[n] = s
    return out


def _ids(values) -> str:
    return ",".join(str(int(v) + 1) for v in values)


def write_feb(setup: Setup, path, *, stages: int | None = None,
              bulk_factor: float = BULK_FACTOR, fit: bool = True) -> list[str]:
    """Write a Setup's stages as an FEBio 4 input deck: one <step> per stage.

    Args:
      setup: a problem's Setup (its model and stages, or those of its ``whole`` for a
        reduced model such as the mirror half; the terms active in any exported
        stage are written, from the default design ``model.theta0()``, with each param's
        value at every stage's end on a load curve).
      path: the .feb file to write.
      stages: how many stages to export (default: all); one stage is written without
        <Step> (FEBio's single analysis).
      bulk_factor: FEBio's k = bulk_factor (c10 + c01) per exactly incompressible
        material (a material with its own k, or a coupled one, is written as it is).
      fit: where a stage's hook refits a buckle (a ring fitted snug on the pressurised
        eye), solve the deck's stages before it with eyefem (read back) and write the
        buckle's segments at the hook's fit on that state (:func:`fitted_buckles`);
        False: at the buckle's initial fit.
    Returns: the omissions (what FEBio cannot be given, or is given approximately), also
      written in the deck's header comment and logged.
    Raises: ValueError for a stage count outside 1..len(setup.stages) or a model without
      solid elements; OSError.
    """
    fits = fitted_buckles(setup, stages, bulk_factor=bulk_factor) if fit else {}
    setup = _whole(setup)  # a reduced model (the mirror half): FEBio gets the whole
    n_all = len(setup.stages)
    stages = n_all if stages is None else stages
    if not 1 <= stages <= n_all:
        raise ValueError(f"write_feb: stages = {stages}; '{setup.name}' has {n_all} stage(s) "
                         f"(give 1..{n_all}, or leave it out for all)")
    if not bulk_factor > 0:
        raise ValueError(f"write_feb: bulk_factor = {bulk_factor}; must be > 0")
    exp = list(setup.stages[:stages])
    model, stage = setup.model, exp[0]
    mesh, theta = model.mesh, model.theta0()

    def on(t, st):
        return st.active is None or t.name in st.active

    active = [t for t in model.terms if any(on(t, st) for st in exp)]
    warnings: list[str] = []
    solids = [t for t in active if isinstance(t, (SolidQ1P0, SolidCompressible))]
    if not solids:
        raise ValueError(f"write_feb: '{setup.name}' stage '{stage.name}' has no active solid "
                         "elements to export")
    loads = [t for t in active if isinstance(t, PressureLoad)]
    links = [t for t in active if type(t) is Bars]
    springs = [t for t in active if isinstance(t, NodeSprings)]
    cavities = [t for t in active if isinstance(t, FluidCavity)]
    buckles = [t for t in active if isinstance(t, BuckleContact)]
    for t in active:
        if t in solids or t in loads or t in links or t in springs or t in cavities \
                or t in buckles:
            continue
        why = _SKIPPED.get(type(t).__name__,
                           f"{type(t).__name__}: no FEBio equivalent exported")
        warnings.append(f"term '{t.name}' skipped ({why})")

    # materials: one per (name) used by the exported elements
    elem_mat = np.full(mesh.n_elem, -1, np.int64)
    coeffs, volumetric = {}, {}
    for t in solids:
        c = np.asarray(theta[t.name]["coeffs"])
        el = np.asarray(t.elements)
        elem_mat[el] = mesh.material_ids[el]
        for m in np.unique(mesh.material_ids[el]):
            coeffs.setdefault(int(m), c[m])
            if isinstance(t, SolidCompressible):  # (k, (c1, c2, lam)) of FEBio's own laws
                volumetric.setdefault(int(m), (float(np.asarray(theta[t.name]["k"])[m]),
                                               np.asarray(theta[t.name]["coupled"])[m]))
    exported = np.nonzero(elem_mat >= 0)[0]
    mat_ids = sorted(coeffs)

    root = ET.Element("febio_spec", version=SPEC_VERSION)
    header = ET.Comment("")
    root.append(header)
    ET.SubElement(root, "Module", type="solid")
    if len(exp) == 1:
        _write_control(ET.SubElement(root, "Control"), stage.n_steps,
                       newton=bool(buckles))

    mat_names = safe_names([mesh.materials[m] for m in mat_ids])
    mats = ET.SubElement(root, "Material")
    incompressible = set()  # FEBio 4: laugon and atol are the three-field domain's
    for i, m in enumerate(mat_ids, start=1):
        c = coeffs[m]
        name = mesh.materials[m]
        if m in volumetric:
            _write_febio_law(mats, i, mat_names[name], c, *volumetric[m], name, warnings)
            continue
        extra = [f"c{r}{s}" for r in range(c.shape[0]) for s in range(c.shape[1])
                 if (r + s > 1) and c[r, s] != 0.0]
        if extra:
            warnings.append(f"material '{name}': {', '.join(extra)} dropped (FEBio's "
                            "Mooney-Rivlin has c1 = c10 and c2 = c01 only)")
        k = bulk_factor * (c[1, 0] + c[0, 1])
        el = ET.SubElement(mats, "material", id=str(i), name=mat_names[name],
                           type="Mooney-Rivlin")
        el.append(ET.Comment(f" eyefem c10 = {c[1, 0]:g}, c01 = {c[0, 1]:g} MPa, incompressible; "
                             f"k = {bulk_factor:g} (c10 + c01) with FEBio's augmented "
                             "Lagrangian (laugon: Jbar -> 1 per element, eyefem's constraint) "))
        ET.SubElement(el, "density").text = "1"
        ET.SubElement(el, "c1").text = _fmt(c[1, 0])
        ET.SubElement(el, "c2").text = _fmt(c[0, 1])
        ET.SubElement(el, "k").text = _fmt(k)
        incompressible.add(m)
    n_mat = len(mat_ids)

    # extra nodes: the springs' fixed ground nodes, the buckle's rigid segments
    extra_xyz: list[np.ndarray] = []

    def add_nodes(x):
        first = mesh.n_nodes + sum(len(a) for a in extra_xyz)
        extra_xyz.append(np.asarray(x, float).reshape(-1, 3))
        return first + np.arange(len(extra_xyz[-1]))

    discrete = []  # (set name, (m, 2) node ids, type, E N/mm)
    for t in links:
        discrete += _bar_springs(t, theta, exp, mesh, warnings)
    ground = []
    for t in springs:  # three springs of rest length GROUND_ARM along x, y, z per node
        arms = mesh.nodes[t.nodes][:, None, :] + GROUND_ARM * np.eye(3)[None]
        g = add_nodes(arms.reshape(-1, 3))
        ground.append(g)
        discrete.append((f"{t.name}", np.stack([np.repeat(t.nodes, 3), g], 1),
                         "linear spring", np.full(len(g), float(theta[t.name]["k"]))))
        if any(float(st.params.get(t.name, {}).get("k", theta[t.name]["k"]))
               != float(theta[t.name]["k"]) for st in exp):
            warnings.append(f"springs '{t.name}': a stiffness changed by a stage is written "
                            "at its initial value")
    segments = []  # (name, quads (f, 4) node ids, direction (3,), d per stage end)
    for t in buckles:
        segments += _buckle_segments(t, theta, exp, add_nodes, warnings, fits.get(t.name))

    xml_mesh = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(xml_mesh, "Nodes", name="nodes")
    all_xyz = np.concatenate([mesh.nodes] + extra_xyz)
    for i, x in enumerate(all_xyz, start=1):
        ET.SubElement(nodes, "node", id=str(i)).text = ",".join(_fmt(v) for v in x)
    order = exported[np.argsort(elem_mat[exported], kind="stable")]
    eid = 0
    for m in mat_ids:
        block = ET.SubElement(xml_mesh, "Elements", type="hex8",
                              name=f"part_{mat_names[mesh.materials[m]]}")
        for e in order[elem_mat[order] == m]:
            eid += 1
            ET.SubElement(block, "elem", id=str(eid)).text = _ids(mesh.hexes[e])
    for name, quads, _, _ in segments:
        block = ET.SubElement(xml_mesh, "Elements", type="quad4", name=name)
        for f in quads:
            eid += 1
            ET.SubElement(block, "elem", id=str(eid)).text = _ids(f)
    surf_names = safe_names(mesh.face_sets)
    for name, faces in mesh.face_sets.items():
        s = ET.SubElement(xml_mesh, "Surface", name=surf_names[name])
        for j, f in enumerate(faces, start=1):
            ET.SubElement(s, "quad4", id=str(j)).text = _ids(f)
    taken = set(surf_names.values())
    contact_pairs = []  # one per rigid segment (FEBio's contact: one secondary body)
    for t in buckles:
        for seg in segments:
            if not seg[0].startswith(f"{t.name}_segment"):
                continue
            nm = _unique(f"{seg[0]}_surface", taken)
            s = ET.SubElement(xml_mesh, "Surface", name=nm)
            for j, f in enumerate(seg[1], start=1):
                ET.SubElement(s, "quad4", id=str(j)).text = _ids(f)
            pair = _unique(f"{seg[0]}_contact", taken)
            sp = ET.SubElement(xml_mesh, "SurfacePair", name=pair)
            ET.SubElement(sp, "primary").text = surf_names.get(t.node_set, t.node_set)
            ET.SubElement(sp, "secondary").text = nm
            contact_pairs.append((t, pair))
    set_names = safe_names(mesh.node_sets)
    for name, ids in mesh.node_sets.items():
        ET.SubElement(xml_mesh, "NodeSet", name=set_names[name]).text = _ids(ids)
    taken |= set(set_names.values())
    bcs = _boundary_sets(exp, mesh.n_nodes, warnings)
    held = [b[1] for b in bcs] + [np.asarray(t.nodes, np.int64) for t in springs] + [
        np.zeros(0, np.int64)]
    _warn_unheld(mesh, exported, np.concatenate(held), warnings)
    bc_sets = []
    for label, nodes_, spec in bcs:
        nm = _unique(label, taken)
        ET.SubElement(xml_mesh, "NodeSet", name=nm).text = _ids(nodes_)
        bc_sets.append((nm, spec))
    ground_set = None
    if ground:
        ground_set = _unique("spring_ground", taken)
        ET.SubElement(xml_mesh, "NodeSet", name=ground_set).text = _ids(np.concatenate(ground))
    for name, conn, _, _ in discrete:
        ds = ET.SubElement(xml_mesh, "DiscreteSet", name=name)
        for a, b in conn:
            ET.SubElement(ds, "delem").text = f"{a + 1},{b + 1}"

    doms = ET.SubElement(root, "MeshDomains")
    for m in mat_ids:
        nm = mat_names[mesh.materials[m]]
        if m in incompressible:  # FEBio's augmented Lagrangian on Jbar, per element
            dom = ET.SubElement(doms, "SolidDomain", name=f"part_{nm}", mat=nm,
                                type="three-field-solid")
            ET.SubElement(dom, "laugon").text = "1"
            ET.SubElement(dom, "atol").text = _fmt(AUGMENTATION_TOL)
        else:
            ET.SubElement(doms, "SolidDomain", name=f"part_{nm}", mat=nm)
    for i, (name, _, _, _) in enumerate(segments, start=n_mat + 1):
        el = ET.SubElement(mats, "material", id=str(i), name=name, type="rigid body")
        ET.SubElement(el, "density").text = "1"
        dom = ET.SubElement(doms, "ShellDomain", name=name, mat=name)
        ET.SubElement(dom, "shell_thickness").text = "0"

    curves = _Curves(len(exp))
    boundary = ET.SubElement(root, "Boundary")
    for nm, spec in bc_sets:
        if spec[0] == "zero":
            bc = ET.SubElement(boundary, "bc", name=nm, node_set=nm, type="zero displacement")
            for c in _XYZ:
                ET.SubElement(bc, f"{c}_dof").text = "1" if c in spec[1] else "0"
        else:
            _, comp, path_ = spec
            lc, value = curves.scaled([0.0, *path_])
            bc = ET.SubElement(boundary, "bc", name=nm, node_set=nm,
                               type="prescribed displacement")
            ET.SubElement(bc, "dof").text = comp
            ET.SubElement(bc, "value", lc=str(lc)).text = _fmt(value)
            ET.SubElement(bc, "relative").text = "0"
    if ground_set:
        bc = ET.SubElement(boundary, "bc", name=ground_set, node_set=ground_set,
                           type="zero displacement")
        for c in _XYZ:
            ET.SubElement(bc, f"{c}_dof").text = "1"

    if segments:
        rigid = ET.SubElement(root, "Rigid")
        for name, _, direction, d in segments:
            fx = ET.SubElement(rigid, "rigid_bc", name=f"{name}_turn", type="rigid_fixed")
            ET.SubElement(fx, "rb").text = name
            for dof in ("Ru", "Rv", "Rw"):
                ET.SubElement(fx, f"{dof}_dof").text = "1"
            lc = curves.add(d)
            for c, comp in enumerate(_XYZ):
                rd = ET.SubElement(rigid, "rigid_bc", name=f"{name}_{comp}",
                                   type="rigid_displacement")
                ET.SubElement(rd, "rb").text = name
                ET.SubElement(rd, "dof").text = comp
                ET.SubElement(rd, "value", lc=str(lc)).text = _fmt(direction[c])
                ET.SubElement(rd, "relative").text = "0"

    xml_loads = ET.SubElement(root, "Loads")
    for t in loads:
        vals = [float(theta[t.name]["p"])]
        for st in exp:
            held_by_cavity = any(on(c, st) and t.face_set in c.face_sets[0] for c in cavities)
            if on(t, st):
                vals.append(float(st.params.get(t.name, {}).get("p", vals[-1])))
            else:  # a closed cavity takes over at the pressure it closed at
                vals.append(vals[-1] if held_by_cavity else 0.0)
        lc, value = curves.scaled(vals)
        sl = ET.SubElement(xml_loads, "surface_load", name=t.name, type="pressure",
                           surface=surf_names[t.face_set])
        sl.append(ET.Comment(f" eyefem PressureLoad '{t.name}': "
                             f"{' -> '.join(f'{v:g}' for v in vals)} MPa at the stages' ends "))
        ET.SubElement(sl, "pressure", lc=str(lc)).text = _fmt(value)
        ET.SubElement(sl, "symmetric_stiffness").text = "0"

    if discrete:
        dis = ET.SubElement(root, "Discrete")
        for i, (name, _, kind, E) in enumerate(discrete, start=1):
            dm = ET.SubElement(dis, "discrete_material", id=str(i), name=name, type=kind)
            ET.SubElement(dm, "E").text = _fmt(E[0])
        for i, (name, _, _, _) in enumerate(discrete, start=1):
            ET.SubElement(dis, "discrete", dmat=str(i), discrete_set=name)

    always = [(t, pair) for t, pair in contact_pairs if all(on(t, st) for st in exp)]
    if always:
        _write_contacts(ET.SubElement(root, "Contact"), always)

    for t in cavities:
        if all(on(t, st) for st in exp):
            _write_volume_constraint(root, t, theta, exp, surf_names, warnings)
    if len(exp) > 1:
        steps = ET.SubElement(root, "Step")
        for k, st in enumerate(exp):
            se = ET.SubElement(steps, "step", id=str(k + 1), name=st.name)
            staged = [(t, pair) for t, pair in contact_pairs
                      if on(t, st) and (t, pair) not in always]
            _write_control(ET.SubElement(se, "Control"), st.n_steps,
                           newton=bool(always) or any(on(t, st) for t, _ in contact_pairs))
            if staged:  # FEBio deactivates a step's components at its end: one per step
                _write_contacts(ET.SubElement(se, "Contact"), staged)
            for t in cavities:
                if on(t, st) and not all(on(t, s_) for s_ in exp) and (
                        k == 0 or not on(t, exp[k - 1])):
                    _write_volume_constraint(se, t, theta, exp, surf_names, warnings)
                    later = [s_.name for s_ in exp[k + 1:] if on(t, s_)]
                    if later:
                        warnings.append(
                            f"cavity '{t.name}': FEBio's constraint in step '{st.name}' acts "
                            f"in that step only; in {', '.join(repr(n) for n in later)} the "
                            "cavity's volume is not held (a constraint written again would "
                            "take the volume at that step's start)")

    data = ET.SubElement(root, "LoadData")
    for i, pts in enumerate(curves.points, start=1):
        lc = ET.SubElement(data, "load_controller", id=str(i), type="loadcurve")
        ET.SubElement(lc, "interpolate").text = "LINEAR"
        ET.SubElement(lc, "extend").text = "CONSTANT"
        xp = ET.SubElement(lc, "points")
        for t_, v in pts:
            ET.SubElement(xp, "pt").text = f"{_fmt(t_)},{_fmt(v)}"
    out = ET.SubElement(root, "Output")
    plot = ET.SubElement(out, "plotfile", type="febio")
    for var in ("displacement", "stress", "relative volume"):
        ET.SubElement(plot, "var", type=var)
    log_file = ET.SubElement(out, "logfile")  # the nodes' displacements as text, every step
    ET.SubElement(log_file, "node_data", data="ux;uy;uz", delim=",",
                  file=f"{Path(path).stem}_displacement.txt")

    names = ", ".join(f"'{st.name}' ({st.n_steps} steps)" for st in exp)
    lines = [f" written by eyefem from '{setup.name}': {len(exp)} stage(s) {names}; units mm, "
             "N, MPa. What FEBio 4.11 gives for eyefem's exported decks: docs/febio.md. "]
    lines += [f" not exported or approximated: {w} " for w in warnings]
    header.text = "\n".join(lines) if len(lines) > 1 else lines[0]
    ET.indent(root, space="  ")
    path = Path(path)
    path.write_bytes(ET.tostring(root, encoding="ISO-8859-1", xml_declaration=True) + b"\n")
    for w in warnings:
        log.warning("export-feb: %s", w)
    log.info("wrote %s: %d nodes, %d hex8 in %d materials, %d boundary conditions, %d "
             "pressure loads, %d spring sets, %d rigid segments, %d step(s)", path,
             len(all_xyz), len(exported), len(mat_ids), len(bc_sets), len(loads),
             len(discrete), len(segments), len(exp))
    return warnings


_SKIPPED = {
    "AnchoredBars": "sutures from scleral bites to anchors on a rigid buckle: each is tied "
                    "at a length L0 in a later stage and shortened by its tightening; FEBio's "
                    "springs and trusses rest at their nodes' reference distance and act from "
                    "the first step, so the sutures and their tightening are not written",
    "TiedBars": "sutures over a deformable buckle, tied at a length in a later stage and "
                "shortened: no FEBio equivalent (springs rest at their reference length)",
    "OrbitSpring": "springs on the best-fit rigid motion of a ring of nodes (the orbit's "
                   "support): no FEBio discrete element; FEBio holds the eye by its "
                   "boundary conditions only",
    "RigidContact": "contact with triangulated rigid bodies: not written",
}


def _unique(label, taken: set) -> str:
    nm, k = label, 1
    while nm in taken:
        k += 1
        nm = f"{label}_{k}"
    taken.add(nm)
    return nm


def _write_contacts(con, pairs) -> None:
    """FEBio's frictionless sliding-elastic penalty contacts of the sclera against the
    buckle's rigid segments, one per (term, surface pair), into <Contact> ``con``."""
    for t, pair in pairs:
        area = float(np.mean(t.node_area))
        eps = float(np.mean(np.asarray(t.data["alpha"]))) / area
        c = ET.SubElement(con, "contact", name=pair, surface_pair=pair, type="sliding-elastic")
        c.append(ET.Comment(f" eyefem's penalty {np.mean(t.data['alpha']):.6g} N/mm per "
                            f"node over the mean nodal area {area:.6g} mm^2 "))
        for tag, v in (("laugon", "0"), ("penalty", _fmt(eps)), ("auto_penalty", "0"),
                       ("two_pass", "0"), ("tension", "0"), ("fric_coeff", "0"),
                       ("symmetric_stiffness", "0"), ("search_tol", "0.01")):
            ET.SubElement(c, tag).text = v


def _write_control(ctrl, n_steps: int, newton: bool = False) -> None:
    """A step's <Control>; ``newton``: FEBio's full Newton (qn_method max_ups 0: the
    stiffness reformed every iteration) for a step with contact: its first iteration
    moves the rigid segments onto the sclera with no contact stiffness in the matrix,
    which BFGS would only update; full Newton takes the contact's into the next one."""
    ET.SubElement(ctrl, "analysis").text = "STATIC"
    ET.SubElement(ctrl, "time_steps").text = str(n_steps)
    ET.SubElement(ctrl, "step_size").text = _fmt(1.0 / n_steps)
    ts = ET.SubElement(ctrl, "time_stepper", type="default")
    ET.SubElement(ts, "max_retries").text = "5"
    ET.SubElement(ts, "opt_iter").text = "10"
    ET.SubElement(ts, "dtmin").text = "0"
    ET.SubElement(ts, "dtmax").text = _fmt(1.0 / n_steps)
    solver = ET.SubElement(ctrl, "solver", type="solid")  # FEBio 4 needs it in each step
    ET.SubElement(solver, "max_refs").text = "25"
    qn = ET.SubElement(solver, "qn_method", type="BFGS")  # FEBio's default quasi-Newton
    if newton:
        ET.SubElement(qn, "max_ups").text = "0"


class _Curves:
    """FEBio load curves over the stages: stage k (1-based) spans FEBio time [k - 1, k];
    a curve is its values at t = 0, 1, ..., K, linear between (identical curves shared)."""

    def __init__(self, n_stages: int):
        self.n, self.points = n_stages, []

    def add(self, values) -> int:
        pts = [(float(k), float(v)) for k, v in enumerate(values)]
        if len(pts) != self.n + 1:
            raise ValueError(f"a load curve needs {self.n + 1} values, got {len(pts)}")
        while len(pts) > 2 and pts[-1][1] == pts[-2][1]:
            pts.pop()  # held at the end: CONSTANT extension
        if pts not in self.points:
            self.points.append(pts)
        return self.points.index(pts) + 1

    def scaled(self, values) -> tuple[int, float]:
        """(curve id, scale) with curve x scale = values (the curve's largest value 1)."""
        big = max(values, key=abs)
        scale = big if big != 0 else 1.0
        return self.add([v / scale for v in values]), scale


def _trajectory(theta, exp, name, key):
    """A term param's value at t = 0 and at each stage's end (carried where not given)."""
    v = np.asarray(theta[name][key], float)
    out = [v]
    for st in exp:
        v = np.asarray(st.params.get(name, {}).get(key, v), float)
        out.append(v)
    return out


def _bar_springs(t, theta, exp, mesh, warnings) -> list:
    """eyefem.fem.bars.Bars as FEBio linear springs (FELinearSpring, force E (l - L0)):
    E = EA / L0 gives Bars' energy EA / (2 L0) (l - L0)^2 exactly (FEBio's linear truss,
    E A ln(lam) / lam, differs at second order). An end inside a face (xi not at a node)
    moves to the face's node of largest shape function (listed); one set per distinct E."""
    from eyefem.fem.bars import bilinear

    na, nb = np.asarray(t.nodes_a).reshape(-1, 4), np.asarray(t.nodes_b).reshape(-1, 4)
    xi = np.asarray(theta[t.name]["xi"], float)
    ends, moved = [], 0.0
    for nodes4, x in ((na, xi[:, 0]), (nb, xi[:, 1])):
        w = bilinear(x)
        pick = nodes4[np.arange(len(nodes4)), np.argmax(w, axis=1)]
        pos = np.einsum("na,nai->ni", w, mesh.nodes[nodes4])
        moved = max(moved, float(np.max(np.linalg.norm(mesh.nodes[pick] - pos, axis=1))))
        ends.append(pick)
    conn = np.stack(ends, 1)
    if moved > 1e-9:
        warnings.append(f"bars '{t.name}': ends inside faces moved to the faces' nearest "
                        f"nodes (by at most {moved:.3g} mm) for FEBio's node-to-node springs")
    if any(np.any(v != 0) for v in _trajectory(theta, exp, t.name, "shortening")):
        warnings.append(f"bars '{t.name}': their shortening (a change of rest length) is not "
                        "written; FEBio's springs rest at their reference length")
    if t.tension_only:
        kind = "tension-only linear spring"
    else:
        kind = "linear spring"
    L0 = np.linalg.norm(mesh.nodes[conn[:, 1]] - mesh.nodes[conn[:, 0]], axis=1)
    E = np.asarray(theta[t.name]["EA"], float) / L0
    out = []
    for j, e in enumerate(np.unique(E)):
        sel = E == e
        out.append((f"{t.name}_{j + 1}" if len(np.unique(E)) > 1 else t.name, conn[sel],
                    kind, E[sel]))
    return out


BUCKLE_SEGMENTS = 24
"""Rigid segments an encircling buckle is written as: each translates along the inward
radius through its middle, so their surface stays within d (1 - cos(pi / 24)) = 0.86 % of
the radial tightening d of eyefem's uniformly shrinking ring."""


def _ring(t):
    """The BuckleContact of a term, or of the term a reduced model wraps (``inner``)."""
    while not isinstance(t, BuckleContact) and getattr(t, "inner", None) is not None:
        t = t.inner
    return t if isinstance(t, BuckleContact) else None


def fitted_buckles(setup: Setup, stages: int | None = None, *,
                   bulk_factor: float = BULK_FACTOR) -> dict[str, tuple[float, str]]:
    """{buckle term name: (dr, stage name)}: the radial fit (mm, added to the ring's radius)
    that the first stage's hook gives a buckle where the buckle acts from a stage with a
    ``before`` hook (eyefem fits the ring snug on the pressurised eye there), taken on the
    deck's own pressurised eye: the stages before it are written (whole, without a buckle
    fit), read back (eyefem.io.febio_read) and solved by eyefem, the state FEBio reaches
    there (docs/febio.md: to 1.6e-6 mm), and the hook is given that state. eyefem's own
    pressurised eye differs by the export's omissions (the orbit's springs, ...): a ring
    fitted on it would start the tighten step pressed into the deck's sclera (0.069 mm on
    case 1's coarse mesh). {} when no hook refits one."""
    import tempfile

    from eyefem.solve.solver import solve

    names = [t.name for t in setup.model.terms if _ring(t) is not None]
    exp = setup.stages[:stages]
    k = next((i for i, st in enumerate(exp) if st.before is not None and any(
        st.active is None or n in st.active for n in names)), None)
    if not names or not k:
        return {}
    whole = _whole(setup)
    log.info("export-feb: solving the deck's step(s) %s with eyefem to fit the buckle as "
             "stage '%s' does", ", ".join(repr(st.name) for st in exp[:k]), exp[k].name)
    with tempfile.TemporaryDirectory() as tmp:
        deck = Path(tmp) / "before.feb"
        quiet, log.disabled = log.disabled, True
        try:
            write_feb(whole, deck, stages=k, bulk_factor=bulk_factor, fit=False)
        finally:
            log.disabled = quiet
        model, sts = build_stages(*read_feb(deck))
    sol = solve(model, sts)
    n = whole.model.mesh.n_nodes
    q = np.zeros(whole.model.n_dof)
    q[: 3 * n] = np.asarray(sol.q)[: 3 * n]
    refit, _, _ = whole.stages[k].before(whole.model, q, whole.model.theta0())
    out = {}
    for nm in names:
        dr = _ring(refit.term(nm)).radius - _ring(whole.model.term(nm)).radius
        if dr != 0.0:
            out[nm] = (float(dr), exp[k].name)
    return out


def _whole(setup: Setup) -> Setup:
    """The Setup itself, or the whole model of a reduced one (the mirror half)."""
    if setup.whole is None:
        return setup
    return dataclasses.replace(setup, model=setup.whole.model,
                               stages=list(setup.whole.stages), q0=setup.whole.q0, whole=None)


def _buckle_segments(t, theta, exp, add_nodes, warnings, fit=None) -> list:
    """An encircling eyefem.fem.buckle_contact.BuckleContact (its analytic inner surface)
    as BUCKLE_SEGMENTS rigid bodies of quad4 facets: [(name, quads (f, 4) node ids,
    inward unit direction (3,), the radial motion d at t = 0 and each stage's end)];
    ``fit``: (dr mm, stage) the ring's radius refitted by that stage (:func:`fitted_buckles`)."""
    extra = [0.0]  # the ring's own radial unknown, where a stage prescribes it
    for st in exp if t.extra_dof >= 0 else ():
        hit = np.nonzero(np.asarray(st.prescribed[0]) == t.extra_dof)[0]
        extra.append(float(np.asarray(st.prescribed[1])[hit[0]]) if hit.size else np.nan)
    if t.shape != "ring" or np.isnan(extra).any():
        warnings.append(f"buckle '{t.name}': a {t.shape} buckle"
                        f"{' with a free radial motion' if np.isnan(extra).any() else ''} is "
                        "not written (only an encircling ring moved as prescribed is)")
        return []
    traj = {k: _trajectory(theta, exp, t.name, k) for k in ("d", "s", "ridge", "dr", "rot")}
    if t.extra_dof >= 0:
        traj["d"] = [v + e for v, e in zip(traj["d"], extra)]
    for k in ("s", "dr", "rot"):
        if any(np.any(v != 0) for v in traj[k]):
            warnings.append(f"buckle '{t.name}': its motion '{k}' is not written (the "
                            "segments translate radially only)")
    ridge = float(traj["ridge"][-1][0])
    if any(float(v[0]) != ridge for v in traj["ridge"][1:]) and ridge != 0.0:
        warnings.append(f"buckle '{t.name}': its ridge is written at its final height "
                        f"{ridge:g} mm from the start (eyefem raises it over a stage)")
    params = {k: np.zeros(1) for k in ("d", "s", "dr", "rot")}
    params["ridge"] = np.array([ridge])
    if fit is not None:
        params["dr"] = np.array([fit[0]])
        warnings.append(f"buckle '{t.name}': fitted snug as eyefem's stage '{fit[1]}' fits it, "
                        f"on the deck's own pressurised eye (its radius {fit[0]:+.6g} mm, from "
                        "eyefem's solve of the deck's steps before; FEBio's segments are placed "
                        "there from the start)")
    n_seg, per = BUCKLE_SEGMENTS, 4
    P, _ = t.surface(np.zeros(max(3 * t.mesh.n_nodes, t.extra_dof + 1)), params,
                     n_around=n_seg * per,
                     n_across=6)
    nu, nv = n_seg * per + 1, 7
    grid = np.arange(nu * nv).reshape(nu, nv)
    warnings.append(f"buckle '{t.name}': written as {n_seg} rigid segments translated along "
                    "their middle's inward radius (eyefem shrinks the ring uniformly), in "
                    "sliding-elastic contact with a penalty per area from eyefem's per-node "
                    "penalty, in the steps of the stages where it is active, without "
                    "eyefem's smoothed penetration")
    out = []
    for j in range(n_seg):
        cols = grid[j * per:(j + 1) * per + 1]
        pts = P[cols.ravel()]
        ids = add_nodes(pts).reshape(cols.shape)
        a, b, c, d = ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]
        quads = np.stack([a, b, c, d], -1).reshape(-1, 4)
        mid = P[cols[per // 2, nv // 2]]
        inward = -mid / np.linalg.norm(mid)
        x = pts.reshape(cols.shape + (3,))
        nrm = np.cross(x[1, 0] - x[0, 0], x[0, 1] - x[0, 0])
        if nrm @ inward < 0:
            quads = quads[:, ::-1]  # facets face the eye (toward the axis)
        out.append((f"{t.name}_segment_{j + 1}", quads, inward,
                    [float(v[0]) for v in traj["d"]]))
    return out


def _write_volume_constraint(parent, t, theta, exp, surf_names, warnings) -> None:
    """A closed fluid cavity (eyefem.fem.cavity.FluidCavity, P = P_ini - K_eff (V - V_ini) /
    V_ini) as FEBio's volume constraint (FEVolumeConstraint: penalty, laugon 0): FEBio's
    multiplier p = eps (V - V0) pushes along the faces' normals, so eps = -K_eff / V_ini
    reproduces the liquid's stiffness on either orientation of the faces; V0 is the volume
    when the step activates it (eyefem's closing) and P_ini is the pressure load held.
    FEBio's stiffness of it (FEVolumeConstraint::StiffnessMatrix) is each face's own
    eps^2 (n da)(n da)^T, not the liquid's eps (dV/du)(dV/du)^T coupling every face: with
    the liquid's |eps| (0.43 MPa/mm^3 for the eye) a step that presses the cavity in
    diverges (docs/febio.md, "Surgery case 1 in FEBio")."""
    p = theta[t.name]
    K = float(np.ravel(p["bulk"])[0])
    c = float(np.ravel(p["c_out"])[0])
    V = float(np.ravel(p["v_ini"])[0])
    keff = K / (1.0 + K * c / V)
    if len(t.face_sets) != 1 or len(t.face_sets[0]) != 1:
        warnings.append(f"cavity '{t.name}': several cavities or face sets are not written")
        return
    if t.symmetry_planes or t.regulation is not None:
        warnings.append(f"cavity '{t.name}': symmetry planes and volume regulation are not "
                        "written")
        return
    if any(np.any(v != 0) for v in _trajectory(theta, exp, t.name, "dv")):
        warnings.append(f"cavity '{t.name}': an exchanged volume dv is not written")
    cons = ET.SubElement(parent, "Constraints")
    el = ET.SubElement(cons, "constraint", name=t.name, type="volume",
                       surface=surf_names[t.face_sets[0][0]])
    el.append(ET.Comment(f" eyefem FluidCavity '{t.name}': K = {K:g} MPa, V_ini ~ {V:.6g} mm^3 "
                         "(the reference volume; eyefem's is the volume when it closes) "))
    ET.SubElement(el, "laugon").text = "0"
    ET.SubElement(el, "penalty").text = _fmt(-keff / V)
    warnings.append(f"cavity '{t.name}': FEBio's volume constraint with the penalty "
                    f"-K / V_ini = {-keff / V:.4g} MPa/mm^3 from the reference volume (eyefem "
                    "takes V_ini when the cavity closes)")


def _warn_unheld(mesh: Mesh, elements, held_nodes, warnings: list):
    """Warn about each body (connected set of exported elements) without a prescribed
    displacement: in eyefem skipped terms (springs, bars) may hold it, in the FEBio deck
    it is free to move as a rigid body and FEBio's solve fails."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    hexes = mesh.hexes[elements]
    if not len(hexes):
        return
    rows = np.repeat(hexes[:, :1], 8, axis=1).ravel()
    graph = coo_matrix((np.ones(rows.size), (rows, hexes.ravel())),
                       shape=(mesh.n_nodes, mesh.n_nodes))
    _, label = connected_components(graph, directed=False)
    used = np.unique(hexes)
    held = set(label[np.asarray(held_nodes, np.int64)].tolist())
    for comp in np.unique(label[used]):
        if comp not in held:
            nodes = used[label[used] == comp]
            owner = [m for m in mesh.materials
                     if m in {mesh.materials[i] for i in mesh.material_ids[elements][
                         np.any(np.isin(hexes, nodes), axis=1)]}]
            warnings.append(f"a body of {nodes.size} nodes (materials {owner}) has no "
                            "prescribed displacement: only skipped terms hold it, so FEBio "
                            "will find it free to move; add a boundary condition in FEBio "
                            "Studio")


def _write_febio_law(mats, i, febio_name, c, k, cc, name, warnings) -> None:
    """A material of eyefem.fem.solid_compressible as the FEBio law it is: uncoupled
    "Mooney-Rivlin" with its own k, "neo-Hookean" (E, v from c1 = mu / 2 and lam) where
    c2 = 0, else "coupled Mooney-Rivlin" (c1, c2, k = lam)."""
    if cc[0] > 0:
        c1, c2, lam = (float(v) for v in cc)
        if c2 == 0.0:
            mu = 2.0 * c1
            el = ET.SubElement(mats, "material", id=str(i), name=febio_name, type="neo-Hookean")
            ET.SubElement(el, "density").text = "1"
            ET.SubElement(el, "E").text = _fmt(mu * (3.0 * lam + 2.0 * mu) / (lam + mu))
            ET.SubElement(el, "v").text = _fmt(lam / (2.0 * (lam + mu)))
            return
        el = ET.SubElement(mats, "material", id=str(i), name=febio_name,
                           type="coupled Mooney-Rivlin")
        ET.SubElement(el, "density").text = "1"
        for tag, v in (("c1", c1), ("c2", c2), ("k", lam)):
            ET.SubElement(el, tag).text = _fmt(v)
        return
    extra = [f"c{r}{s}" for r in range(c.shape[0]) for s in range(c.shape[1])
             if (r + s > 1) and c[r, s] != 0.0]
    if extra:
        warnings.append(f"material '{name}': {', '.join(extra)} dropped (FEBio's "
                        "Mooney-Rivlin has c1 = c10 and c2 = c01 only)")
    el = ET.SubElement(mats, "material", id=str(i), name=febio_name, type="Mooney-Rivlin")
    el.append(ET.Comment(f" eyefem c10 = {c[1, 0]:g}, c01 = {c[0, 1]:g}, k = {k:g} MPa "
                         "(nearly incompressible, U(J) = k/2 ln^2 J) "))
    ET.SubElement(el, "density").text = "1"
    for tag, v in (("c1", c[1, 0]), ("c2", c[0, 1]), ("k", k)):
        ET.SubElement(el, tag).text = _fmt(v)


def _boundary_sets(stages, n_nodes: int, warnings: list) -> list:
    """Group the stages' prescribed dofs into node sets: [(label, nodes, spec)] with spec
    ("zero", components) for components held at zero in every stage or ("value",
    component, (target at each stage's end, mm)) for each distinct path of a component.
    The dofs are the first stage's; a later stage that prescribes others is listed."""
    first = stages[0]
    dofs = np.asarray(first.prescribed[0])
    keep = dofs < 3 * n_nodes
    if not np.all(keep):
        log.info("export-feb: %d prescribed dofs beyond the nodal displacements (extra "
                 "unknowns such as a rigid buckle's motion: written with its body)",
                 int(np.sum(~keep)))
    dofs = dofs[keep]
    paths = np.zeros((len(dofs), len(stages)))
    for k, st in enumerate(stages):
        d, v = np.asarray(st.prescribed[0]), np.asarray(st.prescribed[1])
        if not np.array_equal(np.sort(d[d < 3 * n_nodes]), np.sort(dofs)):
            warnings.append(f"stage '{st.name}': it prescribes other dofs than stage "
                            f"'{first.name}'; the first stage's dofs are written for all")
            paths[:, k] = paths[:, k - 1] if k else 0.0
            continue
        where = dict(zip(d.tolist(), v.tolist()))
        paths[:, k] = [where[int(i)] for i in dofs]
    node, comp = dofs // 3, dofs % 3
    out = []
    zero = np.all(paths == 0.0, axis=1)
    mask = np.zeros(n_nodes, np.int64)
    np.add.at(mask, node[zero], 1 << comp[zero])
    for bits in range(1, 8):
        sel = np.nonzero(mask == bits)[0]
        if sel.size:
            comps = "".join(c for i, c in enumerate(_XYZ) if bits & (1 << i))
            out.append((f"fixed_{comps}", sel, ("zero", comps)))
    for c in range(3):
        on = (~zero) & (comp == c)
        for path in np.unique(paths[on], axis=0) if on.any() else []:
            sel = np.sort(node[on & np.all(paths == path, axis=1)])
            k = sum(1 for o in out if o[0].startswith(f"prescribed_{_XYZ[c]}"))
            out.append((f"prescribed_{_XYZ[c]}_{k + 1}", sel,
                        ("value", _XYZ[c], tuple(float(v) for v in path))))
    return out
