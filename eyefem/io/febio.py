"""FEBio 4 input decks (``<febio_spec version="4.0">``): write a model's first stage, read
a hexahedral Mooney-Rivlin deck back into eyefem.

Mapping (see docs/febio.md):

* nodes and elements: FEBio numbers from 1; its hex8 node order is eyefem's (VTK's,
  :data:`eyefem.fem.mesh.HEX_CORNERS`: FEBio's FEHex8 shape functions have node 0 at
  (-1,-1,-1), 1 at (+1,-1,-1), 2 at (+1,+1,-1), 3 at (-1,+1,-1), then 4-7 at zeta = +1);
  quad4 faces keep their node order (right-hand normal out of the solid in both codes);
* materials: eyefem's W = c10 (I1bar - 3) + c01 (I2bar - 3), incompressible through the
  element multiplier, becomes FEBio's uncoupled "Mooney-Rivlin" (c1 = c10, c2 = c01) with
  the penalty bulk modulus k = ``bulk_factor`` (c10 + c01) (default 1000: the two agree
  as k grows); higher-order terms (c20, c30, ...) have no FEBio "Mooney-Rivlin"
  equivalent and are dropped with a warning; reading, k is ignored (eyefem is exactly
  incompressible) with a warning when k < 100 (c1 + c2);
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

import dataclasses
import logging
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from eyefem.fem.materials import MooneyRivlin
from eyefem.fem.mesh import Mesh, hex_geometry
from eyefem.fem.solid import SolidQ1P0
from eyefem.fem.surface import PressureLoad
from eyefem.io.runner import Setup
from eyefem.solve.model import Model, node_dofs, solid_model
from eyefem.solve.solver import Stage

log = logging.getLogger(__name__)

SPEC_VERSION = "4.0"
BULK_FACTOR = 1000.0
"""Default FEBio bulk modulus k as a multiple of c10 + c01 (Poisson's ratio about 0.4997)."""

_XYZ = "xyz"


class FebError(ValueError):
    """An FEBio deck that eyefem cannot read (names the file and the offending tag)."""


# --------------------------------------------------------------------------- writing
def _fmt(v: float) -> str:
    return repr(float(v))


def _safe_names(names) -> dict[str, str]:
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
      bulk_factor: FEBio's k = bulk_factor (c10 + c01) per material.
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
    solids = [t for t in active if isinstance(t, SolidQ1P0)]
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
    coeffs = {}
    for t in solids:
        c = np.asarray(theta[t.name]["coeffs"])
        el = np.asarray(t.elements)
        elem_mat[el] = mesh.material_ids[el]
        for m in np.unique(mesh.material_ids[el]):
            coeffs.setdefault(int(m), c[m])
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

    mat_names = _safe_names([mesh.materials[m] for m in mat_ids])
    mats = ET.SubElement(root, "Material")
    for i, m in enumerate(mat_ids, start=1):
        c = coeffs[m]
        name = mesh.materials[m]
        extra = [f"c{r}{s}" for r in range(c.shape[0]) for s in range(c.shape[1])
                 if (r + s > 1) and c[r, s] != 0.0]
        if extra:
            warnings.append(f"material '{name}': {', '.join(extra)} dropped (FEBio's "
                            "Mooney-Rivlin has c1 = c10 and c2 = c01 only)")
        k = bulk_factor * (c[1, 0] + c[0, 1])
        el = ET.SubElement(mats, "material", id=str(i), name=mat_names[name],
                           type="Mooney-Rivlin")
        el.append(ET.Comment(f" eyefem c10 = {c[1, 0]:g}, c01 = {c[0, 1]:g} MPa, incompressible; "
                             f"k = {bulk_factor:g} (c10 + c01) "))
        ET.SubElement(el, "density").text = "1"
        ET.SubElement(el, "c1").text = _fmt(c[1, 0])
        ET.SubElement(el, "c2").text = _fmt(c[0, 1])
        ET.SubElement(el, "k").text = _fmt(k)

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
    surf_names = _safe_names(mesh.face_sets)
    for name, faces in mesh.face_sets.items():
        s = ET.SubElement(xml_mesh, "Surface", name=surf_names[name])
        for j, f in enumerate(faces, start=1):
            ET.SubElement(s, "quad4", id=str(j)).text = _ids(f)
    set_names = _safe_names(mesh.node_sets)
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


# --------------------------------------------------------------------------- reading
@dataclasses.dataclass(frozen=True)
class FebLoads:
    """The load step of a deck, in eyefem's terms.

    Attributes:
      prescribed: (dofs (n,), targets (n,) mm) at the end of the step (from zero).
      pressures: (name, face set, p at the start, p at the end) per pressure load, MPa.
      n_steps: FEBio's time_steps.
      bulk_moduli: material name -> FEBio's k (MPa), not used by eyefem.
    """

    prescribed: tuple[np.ndarray, np.ndarray]
    pressures: tuple[tuple[str, str, float, float], ...]
    n_steps: int
    bulk_moduli: dict


def _err(path, msg):
    return FebError(f"{path}: {msg}")


def _floats(text, path, what) -> list[float]:
    try:
        return [float(v) for v in (text or "").replace(",", " ").split()]
    except ValueError:
        shown = (text or "").strip()[:60]
        raise _err(path, f"{what}: '{shown}' is not a list of numbers") from None


def _ints(text, path, what) -> list[int]:
    """Comma-separated ids, with FEBio's 'a:b' ranges."""
    out = []
    for tok in (text or "").replace(",", " ").split():
        try:
            if ":" in tok:
                a, b = tok.split(":")[:2]
                out.extend(range(int(a), int(b) + 1))
            else:
                out.append(int(tok))
        except ValueError:
            raise _err(path, f"{what}: '{tok}' is not a node or element id") from None
    return out


def _child_float(el, tag, path, where, default=None) -> float:
    c = el.find(tag)
    if c is None:
        if default is not None:
            return default
        raise _err(path, f"{where}: <{tag}> is missing")
    v = _floats(c.text, path, f"{where} <{tag}>")
    if len(v) != 1:
        raise _err(path, f"{where} <{tag}>: expected one number, got '{c.text}'")
    return v[0]


_IGNORED = {"Globals", "Output", "Module", "Control", "Material", "Mesh", "MeshDomains",
            "Boundary", "Loads", "LoadData", "Step"}


def read_feb(path) -> tuple[Mesh, dict, FebLoads]:
    """Read an FEBio 4 deck of hex8 Mooney-Rivlin solids with fixed / prescribed
    displacements and surface pressures (one step, loads linear in time).

    Returns: the mesh (materials named as in the deck, face sets from the Surfaces, node
      sets from the NodeSets), the materials (name -> MooneyRivlin with c10 = c1,
      c01 = c2) and the loads (:class:`FebLoads`).
    Raises: FebError (a ValueError) naming the file and the tag, element or value it
      cannot read: another spec version, tetrahedra or shells, another material, contact,
      more than one step, a load curve that is not linear over the step; OSError.
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
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
        if el.tag not in _IGNORED and len(el):
            raise _err(path, f"<{el.tag}> is not supported (eyefem reads hex8 Mooney-Rivlin "
                       "solids with displacement and pressure loads; remove it)")
    module = root.find("Module")
    if module is not None and module.get("type", "solid") != "solid":
        raise _err(path, f"<Module type=\"{module.get('type')}\">; only 'solid' is supported")
    sections = {t: root.find(t) for t in ("Control", "Boundary", "Loads")}
    steps = root.find("Step")
    if steps is not None and len(steps):
        if len(steps) > 1:
            raise _err(path, f"<Step> has {len(steps)} steps; eyefem imports one step")
        for t, top in list(sections.items()):
            inner = steps[0].find(t)
            if inner is not None:
                if top is not None and len(top) and t != "Control":
                    raise _err(path, f"<{t}> both at the top and in the step; merge them")
                sections[t] = inner

    materials, bulk, by_id = _read_materials(root, path)
    nodes, node_index = _read_nodes(root, path)
    hexes, blocks, elem_ids = _read_elements(root, path, node_index)
    mat_of_block = _read_domains(root, path, blocks, materials, by_id)
    used = sorted({mat_of_block[b] for b, _ in blocks}, key=list(materials).index)
    mids = np.concatenate([np.full(n, used.index(mat_of_block[b])) for b, n in blocks])
    _check_jacobians(nodes, hexes, elem_ids, path)
    face_sets, node_sets = _read_sets(root, path, node_index)
    mesh = Mesh(nodes, hexes, mids, tuple(used), node_sets, face_sets)

    n_steps, t_end = _read_control(sections["Control"], path)
    curves = _read_curves(root, path, t_end)
    prescribed = _read_boundary(sections["Boundary"], path, mesh, curves)
    pressures = _read_loads(sections["Loads"], path, mesh, curves)
    loads = FebLoads(prescribed, tuple(pressures), n_steps,
                     {m: bulk[m] for m in used})
    log.info("read %s: %d nodes, %d hex8, materials %s, %d prescribed dofs, %d pressure "
             "loads, %d steps", path, mesh.n_nodes, mesh.n_elem, list(used),
             len(prescribed[0]), len(pressures), n_steps)
    return mesh, {m: materials[m] for m in used}, loads


def _read_materials(root, path):
    sec = root.find("Material")
    if sec is None or not len(sec):
        raise _err(path, "no <Material> section; define a Mooney-Rivlin material")
    materials, bulk, by_id = {}, {}, {}
    for el in sec:
        if not isinstance(el.tag, str):
            continue
        name = el.get("name") or f"material_{el.get('id')}"
        where = f"material '{name}' (id {el.get('id')})"
        if (el.get("type") or "").lower() != "mooney-rivlin":
            raise _err(path, f"{where}: type '{el.get('type')}' is not supported; eyefem "
                       "reads type=\"Mooney-Rivlin\" (c1, c2, k) only")
        c1 = _child_float(el, "c1", path, where)
        c2 = _child_float(el, "c2", path, where, default=0.0)
        k = _child_float(el, "k", path, where, default=0.0)
        try:
            materials[name] = MooneyRivlin.from_terms(name, {"c10": c1, "c01": c2})
        except ValueError as exc:
            raise _err(path, f"{where}: {exc}") from None
        if k < 100.0 * (c1 + c2):
            log.warning("%s: %s has k = %g MPa < 100 (c1 + c2): FEBio treats it as "
                        "compressible, eyefem as incompressible; the results will differ",
                        path, where, k)
        bulk[name] = k
        by_id[el.get("id")] = name
    return materials, bulk, by_id


def _read_nodes(root, path):
    mesh = root.find("Mesh")
    if mesh is None:
        raise _err(path, "no <Mesh> section")
    ids, xyz = [], []
    for block in mesh.findall("Nodes"):
        for n in block.findall("node"):
            x = _floats(n.text, path, f"node {n.get('id')}")
            if len(x) != 3:
                raise _err(path, f"node {n.get('id')}: {len(x)} coordinates; expected 3")
            ids.append(int(n.get("id")))
            xyz.append(x)
    if not ids:
        raise _err(path, "<Mesh> has no <Nodes>")
    index = {i: k for k, i in enumerate(ids)}
    if len(index) != len(ids):
        raise _err(path, "a node id appears twice in <Nodes>")
    return np.array(xyz, np.float64), index


def _read_elements(root, path, node_index):
    hexes, blocks, elem_ids = [], [], []
    for block in root.find("Mesh").findall("Elements"):
        etype, name = block.get("type"), block.get("name")
        if etype != "hex8":
            kind = ("tetrahedra" if (etype or "").startswith("tet") else f"'{etype}' elements")
            raise _err(path, f"<Elements name=\"{name}\"> holds {kind}: hexahedra are needed "
                       "(type=\"hex8\"); mesh the part with 8-node bricks")
        n = 0
        for e in block.findall("elem"):
            conn = _ints(e.text, path, f"element {e.get('id')}")
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
    if not hexes:
        raise _err(path, "<Mesh> has no <Elements>")
    return np.array(hexes, np.int64), blocks, elem_ids


def _read_domains(root, path, blocks, materials, by_id):
    doms = root.find("MeshDomains")
    if doms is None:
        raise _err(path, "no <MeshDomains> section; assign a material to every element block")
    out = {}
    for d in doms:
        if not isinstance(d.tag, str):
            continue
        if d.tag != "SolidDomain":
            raise _err(path, f"<MeshDomains><{d.tag} name=\"{d.get('name')}\">: only "
                       "SolidDomain is supported (no shells, beams or rigid bodies)")
        mat = d.get("mat")
        mat = by_id.get(mat, mat)
        if mat not in materials:
            raise _err(path, f"SolidDomain '{d.get('name')}': material '{d.get('mat')}' is not "
                       f"defined in <Material>")
        out[d.get("name")] = mat
    for name, _ in blocks:
        if name not in out:
            raise _err(path, f"element block '{name}' has no SolidDomain in <MeshDomains>")
    return out


def _check_jacobians(nodes, hexes, elem_ids, path):
    _, _, det = hex_geometry(nodes, hexes)
    bad = np.nonzero(np.min(det, axis=1) <= 0)[0]
    if bad.size:
        raise _err(path, f"element {elem_ids[bad[0]]}: non-positive Jacobian; the element is "
                   "inverted or its nodes are not in FEBio's hex8 order (bottom face "
                   f"counter-clockwise seen from inside, then the top face) ({bad.size} such "
                   "elements)")


def _read_sets(root, path, node_index):
    mesh = root.find("Mesh")
    faces, nsets = {}, {}

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
                conn = _ints(f.text, path, f"surface '{name}' face {f.get('id')}")
                fs.append([nid(i, f"surface '{name}'") for i in conn])
            faces[name] = np.array(fs, np.int64).reshape(-1, 4)
        elif el.tag == "NodeSet":
            ids = _ints(el.text, path, f"node set '{name}'") + [
                int(n.get("id")) for n in el.findall("n")]
            nsets[name] = np.array([nid(i, f"node set '{name}'") for i in ids], np.int64)
        elif el.tag == "ElementSet":
            continue
        else:
            raise _err(path, f"<Mesh><{el.tag} name=\"{name}\"> is not supported (contact "
                       "pairs, edges and discrete sets have no eyefem reader)")
    return faces, nsets


def _read_control(ctrl, path):
    if ctrl is None:
        raise _err(path, "no <Control> section (time_steps, step_size)")
    n = int(_child_float(ctrl, "time_steps", path, "<Control>"))
    dt = _child_float(ctrl, "step_size", path, "<Control>")
    if n < 1 or not dt > 0:
        raise _err(path, f"<Control>: time_steps = {n}, step_size = {dt}; both must be > 0")
    return n, n * dt


def _read_curves(root, path, t_end):
    """Load controller id -> (value at t = 0, value at the end); linear curves only."""
    out = {}
    data = root.find("LoadData")
    for lc in ([] if data is None else data):
        if not isinstance(lc.tag, str):
            continue
        lid = lc.get("id")
        if lc.tag != "load_controller" or lc.get("type") != "loadcurve":
            raise _err(path, f"load controller {lid}: <{lc.tag} type=\"{lc.get('type')}\"> is "
                       "not supported; use type=\"loadcurve\"")
        pts = [_floats(p.text, path, f"load curve {lid} point") for p in lc.iter("pt")]
        if len(pts) < 1 or any(len(p) != 2 for p in pts):
            raise _err(path, f"load curve {lid}: <points> needs <pt>time,value</pt> pairs")
        t, v = np.array(pts).T
        mode = (lc.findtext("interpolate") or "LINEAR").strip().upper()
        ts = np.linspace(0.0, t_end, 11)
        vs = np.interp(ts, t, v)
        line = vs[0] + (vs[-1] - vs[0]) * ts / t_end
        if np.max(np.abs(vs - line)) > 1e-9 * max(1.0, np.max(np.abs(vs))) or (
                mode != "LINEAR" and len(pts) > 2):
            raise _err(path, f"load curve {lid}: not linear over the step [0, {t_end:g}]; "
                       "eyefem ramps loads linearly within a step")
        out[lid] = (float(vs[0]), float(vs[-1]))
    return out


def _scale(el, path, curves, where):
    """(start, end) of a parameter ``value lc=...`` (constant without lc)."""
    if el.get("type") == "map" or el.get("type") == "math":
        raise _err(path, f"{where}: value type '{el.get('type')}' is not supported; give one "
                   "number per boundary condition")
    v = _floats(el.text, path, where)
    if len(v) != 1:
        raise _err(path, f"{where}: expected one number, got '{el.text}'")
    lc = el.get("lc")
    if lc is None:
        return v[0], v[0]
    if lc not in curves:
        raise _err(path, f"{where}: load controller {lc} is not defined in <LoadData>")
    a, b = curves[lc]
    return v[0] * a, v[0] * b


def _read_boundary(sec, path, mesh, curves):
    dofs, vals = [], []
    for bc in ([] if sec is None else sec):
        if not isinstance(bc.tag, str):
            continue
        ns, kind = bc.get("node_set"), bc.get("type")
        where = f"<bc name=\"{bc.get('name')}\" type=\"{kind}\">"
        if bc.tag != "bc" or ns not in mesh.node_sets:
            raise _err(path, f"{where}: node set '{ns}' is not defined in <Mesh>")
        nodes = mesh.node_sets[ns]
        if kind == "zero displacement":
            comps = "".join(c for c in _XYZ
                            if _child_float(bc, f"{c}_dof", path, where, default=0.0) != 0)
            d = node_dofs(nodes, comps)
            dofs.append(d)
            vals.append(np.zeros(len(d)))
        elif kind == "prescribed displacement":
            comp = (bc.findtext("dof") or "").strip()
            if comp not in ("x", "y", "z"):
                raise _err(path, f"{where}: <dof> '{comp}'; expected x, y or z")
            val = bc.find("value")
            if val is None:
                raise _err(path, f"{where}: <value> is missing")
            start, end = _scale(val, path, curves, where)
            if start != 0.0:
                raise _err(path, f"{where}: the displacement is {start:g} mm at t = 0; eyefem "
                           "starts from the undeformed state (make the load curve start at 0)")
            d = node_dofs(nodes, comp)
            dofs.append(d)
            vals.append(np.full(len(d), end))
        else:
            raise _err(path, f"{where}: boundary condition type '{kind}' is not supported "
                       "(zero displacement, prescribed displacement)")
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


def _read_loads(sec, path, mesh, curves):
    out = []
    for sl in ([] if sec is None else sec):
        if not isinstance(sl.tag, str):
            continue
        where = f"<{sl.tag} type=\"{sl.get('type')}\">"
        if sl.tag != "surface_load" or sl.get("type") != "pressure":
            raise _err(path, f"{where}: only surface_load type=\"pressure\" is supported")
        surf = sl.get("surface")
        if surf not in mesh.face_sets:
            raise _err(path, f"{where}: surface '{surf}' is not defined in <Mesh>")
        p = sl.find("pressure")
        if p is None:
            raise _err(path, f"{where}: <pressure> is missing")
        if (sl.findtext("linear") or "0").strip() not in ("0", "false"):
            log.warning("%s: %s on '%s' has linear = 1 (a dead load); eyefem applies a "
                        "follower pressure", path, where, surf)
        p0, p1 = _scale(p, path, curves, where)
        name = sl.get("name") or f"pressure_{len(out) + 1}"
        out.append((name, surf, p0, p1))
    return out


def build_model(mesh: Mesh, materials: dict, loads: FebLoads) -> tuple[Model, Stage]:
    """The eyefem model (Q1P0 solid + a PressureLoad per pressure) and its one Stage."""
    terms = tuple(PressureLoad(name, mesh, surf, p0) for name, surf, p0, _ in loads.pressures)
    model = solid_model(mesh, materials, terms)
    stage = Stage("load", loads.n_steps, loads.prescribed,
                  params={name: {"p": p1} for name, _, _, p1 in loads.pressures})
    return model, stage


def feb_setup(path) -> Setup:
    """A Setup (for eyefem.io.runner.run_setup) of an FEBio deck: probe records the largest
    nodal displacement (mm); the summary gives its final value and the deck's sizes."""
    path = Path(path)
    mesh, materials, loads = read_feb(path)
    model, stage = build_model(mesh, materials, loads)
    n = mesh.n_nodes

    def probe(model, q, theta):
        u = np.asarray(q[: 3 * n]).reshape(n, 3)
        return {"max_displacement_mm": float(np.max(np.linalg.norm(u, axis=1)))}

    def finish(rows, out_dir, plots):
        return {"deck": str(path), "nodes": n, "elements": mesh.n_elem,
                "max_displacement_mm": rows[-1]["max_displacement_mm"] if rows else 0.0}

    return Setup(path.stem, model, [stage], probe, finish)
