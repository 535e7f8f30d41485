"""FEBio 4 input decks (``<febio_spec version="4.0">``): write a model's first stage
(reading a deck back: eyefem.io.febio_read).

Mapping (see docs/febio.md):

* nodes and elements: FEBio numbers from 1; its hex8 node order is eyefem's (VTK's,
  :data:`eyefem.fem.mesh.HEX_CORNERS`: FEBio's FEHex8 shape functions have node 0 at
  (-1,-1,-1), 1 at (+1,-1,-1), 2 at (+1,+1,-1), 3 at (-1,+1,-1), then 4-7 at zeta = +1);
  quad4 faces keep their node order (right-hand normal out of the solid in both codes);
* materials: eyefem's W = c10 (I1bar - 3) + c01 (I2bar - 3), incompressible through the
  element multiplier, becomes FEBio's uncoupled "Mooney-Rivlin" (c1 = c10, c2 = c01) with
  the bulk modulus k = ``bulk_factor`` (c10 + c01) (default 1000) and FEBio's augmented
  Lagrangian (<laugon>1</laugon>, <atol> AUGMENTATION_TOL): its augmentations drive each
  three-field element's volume ratio Jbar = v / V to 1, the Q1P0 element's constraint, and
  the reader takes laugon = 1 back as exactly incompressible; higher-order terms (c20, c30, ...) have no FEBio "Mooney-Rivlin"
  equivalent and are dropped with a warning; FEBio's own laws (eyefem.fem.materials.
  UncoupledMooneyRivlin with its k, CoupledMooneyRivlin) are written as what they are
  ("Mooney-Rivlin" with that k, "neo-Hookean", "coupled Mooney-Rivlin"), and read back
  as such (eyefem.io.febio_read);
* loads: prescribed displacements (a dof d is node d // 3, component d % 3) become
  "zero displacement" / "prescribed displacement" boundary conditions on node sets, each
  surface pressure (eyefem.fem.surface.PressureLoad: a follower load, positive against the
  outward normal as in FEBio) a "pressure" surface load; both ramp linearly from the
  stage's start to its end through load curves, over time_steps = the stage's n_steps.

What is not exported: fluid cavities (eyefem.fem.cavity.FluidCavity: no FEBio 4.0
equivalent that can be checked here), contact, bars (sutures, zonule), springs: each is
written as an XML comment and logged as a warning.
"""

from __future__ import annotations

import logging
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from eyefem.fem.mesh import Mesh
from eyefem.fem.solid import SolidQ1P0
from eyefem.fem.solid_compressible import SolidCompressible
from eyefem.fem.surface import PressureLoad
from eyefem.io.runner import Setup
from eyefem.solve.solver import Stage

log = logging.getLogger(__name__)

SPEC_VERSION = "4.0"
BULK_FACTOR = 1000.0
"""Default FEBio bulk modulus k as a multiple of c10 + c01 (Poisson's ratio about 0.4997)."""

_XYZ = "xyz"

AUGMENTATION_TOL = 1e-3
"""FEBio's <atol> written with <laugon>1</laugon> for an exactly incompressible material:
its augmentations stop when the norm of the element pressures changes by less than this
fraction (FE3FieldElasticSolidDomain::Augment; FEBio's default 0.01)."""


class FebError(ValueError):
    """An FEBio deck that eyefem cannot read (names the file and the offending tag)."""


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


def write_feb(setup: Setup, path, *, stages: int = 1,
              bulk_factor: float = BULK_FACTOR) -> list[str]:
    """Write the first stage of a Setup as an FEBio 4 input deck.

    Args:
      setup: a problem's Setup (its model and stages; the stage's active terms are
        exported, from the default design ``model.theta0()``).
      path: the .feb file to write.
      stages: how many stages to export; only 1 is supported (later stages of the
        surgery need contact, sutures and a closed cavity, which FEBio decks from here
        cannot carry).
      bulk_factor: FEBio's k = bulk_factor (c10 + c01) per exactly incompressible
        material (a material with its own k, or a coupled one, is written as it is).
    Returns: the warnings (terms and coefficients not exported), also logged.
    Raises: ValueError for stages != 1 or a model without solid elements; OSError.
    """
    if stages != 1:
        raise ValueError(f"write_feb: stages = {stages}; only the first stage can be exported "
                         "(stages=1)")
    if not bulk_factor > 0:
        raise ValueError(f"write_feb: bulk_factor = {bulk_factor}; must be > 0")
    model, stage = setup.model, setup.stages[0]
    mesh, theta = model.mesh, model.theta0()
    active = [t for t in model.terms if stage.active is None or t.name in stage.active]
    warnings: list[str] = []
    solids = [t for t in active if isinstance(t, (SolidQ1P0, SolidCompressible))]
    if not solids:
        raise ValueError(f"write_feb: '{setup.name}' stage '{stage.name}' has no active solid "
                         "elements to export")
    loads = [t for t in active if isinstance(t, PressureLoad)]
    for t in model.terms:
        if type(t).__name__ == "FluidCavity" and t not in active:
            log.info("export-feb: fluid cavity '%s' is open (inactive) in stage '%s': the "
                     "stage's surface pressure is the whole fluid load", t.name, stage.name)
    for t in active:
        if t in solids or t in loads:
            continue
        what = ("a fluid cavity: FEBio 4.0 has no equivalent checked here; its pressure is "
                "not applied" if type(t).__name__ == "FluidCavity"
                else f"{type(t).__name__}: no FEBio equivalent exported")
        warnings.append(f"term '{t.name}' skipped ({what})")

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
    root.append(ET.Comment(f" written by eyefem from '{setup.name}', stage '{stage.name}' "
                           f"({stage.n_steps} steps); units mm, N, MPa "))
    ET.SubElement(root, "Module", type="solid")
    ctrl = ET.SubElement(root, "Control")
    ET.SubElement(ctrl, "analysis").text = "STATIC"
    ET.SubElement(ctrl, "time_steps").text = str(stage.n_steps)
    ET.SubElement(ctrl, "step_size").text = _fmt(1.0 / stage.n_steps)
    ts = ET.SubElement(ctrl, "time_stepper", type="default")
    ET.SubElement(ts, "max_retries").text = "5"
    ET.SubElement(ts, "opt_iter").text = "10"
    ET.SubElement(ts, "dtmin").text = "0"
    ET.SubElement(ts, "dtmax").text = _fmt(1.0 / stage.n_steps)

    mat_names = safe_names([mesh.materials[m] for m in mat_ids])
    mats = ET.SubElement(root, "Material")
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
        ET.SubElement(el, "laugon").text = "1"
        ET.SubElement(el, "atol").text = _fmt(AUGMENTATION_TOL)

    xml_mesh = ET.SubElement(root, "Mesh")
    nodes = ET.SubElement(xml_mesh, "Nodes", name="nodes")
    for i, x in enumerate(mesh.nodes, start=1):
        ET.SubElement(nodes, "node", id=str(i)).text = ",".join(_fmt(v) for v in x)
    order = exported[np.argsort(elem_mat[exported], kind="stable")]
    eid = 0
    for m in mat_ids:
        block = ET.SubElement(xml_mesh, "Elements", type="hex8",
                              name=f"part_{mat_names[mesh.materials[m]]}")
        for e in order[elem_mat[order] == m]:
            eid += 1
            ET.SubElement(block, "elem", id=str(eid)).text = _ids(mesh.hexes[e])
    surf_names = safe_names(mesh.face_sets)
    for name, faces in mesh.face_sets.items():
        s = ET.SubElement(xml_mesh, "Surface", name=surf_names[name])
        for j, f in enumerate(faces, start=1):
            ET.SubElement(s, "quad4", id=str(j)).text = _ids(f)
    set_names = safe_names(mesh.node_sets)
    for name, ids in mesh.node_sets.items():
        ET.SubElement(xml_mesh, "NodeSet", name=set_names[name]).text = _ids(ids)
    bcs = _boundary_sets(stage, mesh.n_nodes, warnings)
    _warn_unheld(mesh, exported, np.concatenate([b[1] for b in bcs]) if bcs else [], warnings)
    taken = set(set_names.values()) | set(surf_names.values())
    bc_sets = []
    for label, nodes_, spec in bcs:
        nm, k = label, 1
        while nm in taken:
            k += 1
            nm = f"{label}_{k}"
        taken.add(nm)
        ET.SubElement(xml_mesh, "NodeSet", name=nm).text = _ids(nodes_)
        bc_sets.append((nm, spec))

    doms = ET.SubElement(root, "MeshDomains")
    for m in mat_ids:
        nm = mat_names[mesh.materials[m]]
        ET.SubElement(doms, "SolidDomain", name=f"part_{nm}", mat=nm)

    boundary = ET.SubElement(root, "Boundary")
    for nm, spec in bc_sets:
        if spec[0] == "zero":
            bc = ET.SubElement(boundary, "bc", name=nm, node_set=nm, type="zero displacement")
            for c in _XYZ:
                ET.SubElement(bc, f"{c}_dof").text = "1" if c in spec[1] else "0"
        else:
            _, comp, value = spec
            bc = ET.SubElement(boundary, "bc", name=nm, node_set=nm,
                               type="prescribed displacement")
            ET.SubElement(bc, "dof").text = comp
            ET.SubElement(bc, "value", lc="1").text = _fmt(value)
            ET.SubElement(bc, "relative").text = "0"

    xml_loads = ET.SubElement(root, "Loads")
    curves = [(0.0, 1.0)]  # load controller 1: the stage's linear ramp
    for t in loads:
        p0 = float(theta[t.name]["p"])
        p1 = float(stage.params.get(t.name, {}).get("p", p0))
        if p0 == 0.0:
            lc, value = 1, p1
        else:
            curves.append((p0, p1))
            lc, value = len(curves), 1.0
        sl = ET.SubElement(xml_loads, "surface_load", name=t.name, type="pressure",
                           surface=surf_names[t.face_set])
        sl.append(ET.Comment(f" eyefem PressureLoad '{t.name}': {p0:g} -> {p1:g} MPa "))
        ET.SubElement(sl, "pressure", lc=str(lc)).text = _fmt(value)
        ET.SubElement(sl, "symmetric_stiffness").text = "0"
    for w in warnings:
        root.append(ET.Comment(f" not exported: {w} "))

    data = ET.SubElement(root, "LoadData")
    for i, (a, b) in enumerate(curves, start=1):
        lc = ET.SubElement(data, "load_controller", id=str(i), type="loadcurve")
        ET.SubElement(lc, "interpolate").text = "LINEAR"
        ET.SubElement(lc, "extend").text = "CONSTANT"
        pts = ET.SubElement(lc, "points")
        ET.SubElement(pts, "pt").text = f"0,{_fmt(a)}"
        ET.SubElement(pts, "pt").text = f"1,{_fmt(b)}"
    out = ET.SubElement(root, "Output")
    plot = ET.SubElement(out, "plotfile", type="febio")
    for var in ("displacement", "stress", "relative volume"):
        ET.SubElement(plot, "var", type=var)

    ET.indent(root, space="  ")
    path = Path(path)
    path.write_bytes(ET.tostring(root, encoding="ISO-8859-1", xml_declaration=True) + b"\n")
    for w in warnings:
        log.warning("export-feb: %s", w)
    log.info("wrote %s: %d nodes, %d hex8 in %d materials, %d boundary conditions, %d "
             "pressure loads", path, mesh.n_nodes, len(exported), len(mat_ids), len(bc_sets),
             len(loads))
    return warnings


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


def _boundary_sets(stage: Stage, n_nodes: int, warnings: list) -> list:
    """Group a stage's prescribed dofs into node sets: [(label, nodes, spec)] with spec
    ("zero", components) for held components or ("value", component, mm) for each
    distinct non-zero target of a component."""
    dofs, vals = stage.prescribed
    keep = dofs < 3 * n_nodes
    if not np.all(keep):
        warnings.append(f"{int(np.sum(~keep))} prescribed dofs beyond the nodal displacements "
                        "(extra unknowns such as a rigid buckle's motion) skipped")
    dofs, vals = dofs[keep], vals[keep]
    node, comp = dofs // 3, dofs % 3
    out = []
    zero = vals == 0.0
    mask = np.zeros(n_nodes, np.int64)
    np.add.at(mask, node[zero], 1 << comp[zero])
    for bits in range(1, 8):
        sel = np.nonzero(mask == bits)[0]
        if sel.size:
            comps = "".join(c for i, c in enumerate(_XYZ) if bits & (1 << i))
            out.append((f"fixed_{comps}", sel, ("zero", comps)))
    for c in range(3):
        on = (~zero) & (comp == c)
        for v in np.unique(vals[on]):
            sel = np.sort(node[on & (vals == v)])
            k = sum(1 for o in out if o[0].startswith(f"prescribed_{_XYZ[c]}"))
            out.append((f"prescribed_{_XYZ[c]}_{k + 1}", sel, ("value", _XYZ[c], float(v))))
    return out
