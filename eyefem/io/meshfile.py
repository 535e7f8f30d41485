"""A user's hexahedral mesh from a file meshio reads (gmsh .msh, Abaqus .inp, VTU...).

Named sets become eyefem's:
- gmsh physical groups (``field_data`` name -> (tag, dimension), ``gmsh:physical`` cell
  data): volumes name the materials of their hexahedra; surfaces become face sets (the
  mesh's boundary faces whose four nodes they cover, oriented outward whatever the file's
  quad orientation) and node sets; curves and points become node sets;
- Abaqus ``.inp`` (read here, not by meshio, whose reader loses sets of sets, several
  ``*NODE`` blocks and ``*SOLID SECTION``): ``*SOLID SECTION, ELSET=e, MATERIAL=m`` names
  the materials (without sections: the ``ELSET=`` of the ``*ELEMENT`` lines if they cover
  every C3D8 element, else the smallest element sets, which must not overlap); every ``*ELSET`` (also ``ELSET=`` on ``*ELEMENT``) is an element set, every ``*NSET``
  (also ``NSET=`` on ``*NODE``) a node set and a face set (the boundary faces it covers),
  every ``*SURFACE`` (element faces S1-S6, or nodes) a face set and node set; set names
  as spelled where defined, references to them case-insensitive (as in Abaqus),
  ``GENERATE`` ranges, sets of sets and ``*INCLUDE`` are understood;
- always: the node set "all", and the face set "boundary" (every boundary face).
Hexahedra are needed: other volume cells (tetrahedra, wedges) are refused by name.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eyefem.fem.mesh import Mesh, boundary_faces

VOLUME_CELLS = {"tetra", "tetra10", "wedge", "wedge15", "pyramid", "pyramid13",
                "hexahedron20", "hexahedron27"}
"""meshio volume cell types eyefem cannot use (its elements are 8-node hexahedra)."""


class MeshFileError(ValueError):
    """A mesh file eyefem cannot use; the message names the file and what is wrong."""


def read_hex_mesh(path: str | Path) -> Mesh:
    """The Mesh of a hexahedral mesh file, with materials and named sets (module doc)."""
    import meshio

    path = Path(path)
    if path.suffix.lower() == ".inp":
        return _abaqus_mesh(path)
    try:
        m = meshio.read(path)
    except Exception as exc:  # noqa: BLE001 - meshio raises many types for a bad file
        raise MeshFileError(f"{path}: meshio cannot read it ({type(exc).__name__}: {exc}); "
                            "give a gmsh .msh, Abaqus .inp or VTU hexahedral mesh") from None
    kinds = [c.type for c in m.cells]
    other = sorted({k for k in kinds if k in VOLUME_CELLS})
    if "hexahedron" not in kinds:
        raise MeshFileError(f"{path}: no hexahedra (cells: {', '.join(sorted(set(kinds))) or 'none'})"
                            "; eyefem needs 8-node hexahedra: mesh the volume with hexahedra "
                            "(gmsh: Mesh.RecombineAll = 1 and Mesh.Recombine3DAll = 1, or a "
                            "transfinite volume)")
    if other:
        raise MeshFileError(f"{path}: {', '.join(other)} cells; eyefem needs 8-node hexahedra "
                            "only (remesh the volume with hexahedra)")
    hex_blocks = [i for i, k in enumerate(kinds) if k == "hexahedron"]
    hexes = np.concatenate([m.cells[i].data for i in hex_blocks]).astype(np.int64)
    used = np.unique(hexes)
    renumber = np.full(len(m.points), -1, np.int64)
    renumber[used] = np.arange(len(used))
    nodes = np.asarray(m.points, float)[used]
    if nodes.shape[1] == 2:
        raise MeshFileError(f"{path}: 2-D points; eyefem needs a 3-D hexahedral mesh")
    groups = _groups(m, hex_blocks)
    mat_names = [name for name, (dim, _) in groups.items() if dim == 3] or ["default"]
    material_ids = np.full(len(hexes), -1, np.int64)
    for j, name in enumerate(mat_names):
        if name in groups:
            material_ids[groups[name][1]] = j
    if np.any(material_ids < 0):
        if groups and any(dim == 3 for dim, _ in groups.values()):
            first = int(np.nonzero(material_ids < 0)[0][0])
            raise MeshFileError(f"{path}: hexahedron {first} (and {int(np.sum(material_ids < 0)) - 1} "
                                "more) is in no volume group; put every hexahedron in a named "
                                "physical volume / element set (its material)")
        material_ids[:] = 0
    hexes = renumber[hexes]
    bfaces = boundary_faces(hexes)
    node_sets = {"all": np.arange(len(nodes))}
    face_sets = {"boundary": bfaces}
    for name, (dim, ids) in groups.items():
        if dim == "points":
            node_sets[name] = np.unique(renumber[ids][renumber[ids] >= 0])
        elif dim in (0, 1, 2):
            node_sets[name] = np.unique(renumber[ids][renumber[ids] >= 0])
            if dim == 2:
                inside = np.zeros(len(nodes), bool)
                inside[node_sets[name]] = True
                face_sets[name] = bfaces[inside[bfaces].all(axis=1)]
    return Mesh(nodes, hexes, material_ids, tuple(mat_names), node_sets=node_sets,
                face_sets=face_sets)


def _groups(m, hex_blocks) -> dict:
    """name -> (dimension, ids): dimension 3 with hexahedron indices (counted over the hex
    blocks in order), 0-2 with point ids of the group's cells, "points" with point ids."""
    out = {}
    offsets = np.cumsum([0] + [len(m.cells[i].data) for i in hex_blocks])
    phys = m.cell_data.get("gmsh:physical")
    for name, (tag, dim) in ((k, (int(v[0]), int(v[1]))) for k, v in (m.field_data or {}).items()
                             if len(v) >= 2 and phys is not None):
        if dim == 3:
            ids = [offsets[j] + np.nonzero(phys[i] == tag)[0] for j, i in enumerate(hex_blocks)]
            out[name] = (3, np.concatenate(ids))
        else:
            pts = [m.cells[i].data[phys[i] == tag].ravel() for i in range(len(m.cells))
                   if i not in hex_blocks]
            out[name] = (dim, np.unique(np.concatenate(pts)) if pts else np.zeros(0, np.int64))
    for name, per_block in (m.cell_sets or {}).items():
        if name in out or name.startswith("gmsh:"):
            continue
        ids = [offsets[j] + np.asarray(per_block[i], np.int64)
               for j, i in enumerate(hex_blocks) if i < len(per_block) and per_block[i] is not None]
        if ids and sum(len(x) for x in ids):
            out[name] = (3, np.concatenate(ids))
    for name, ids in (m.point_sets or {}).items():
        out.setdefault(name, ("points", np.asarray(ids, np.int64)))
    return out


ABAQUS_REFUSED = {"C3D4": "tetra", "C3D10": "tetra10", "C3D6": "wedge", "C3D15": "wedge15",
                  "C3D5": "pyramid", "C3D20": "hexahedron20", "C3D27": "hexahedron27"}
"""Abaqus solid element families (type prefixes) eyefem cannot use, with meshio's names."""

ABAQUS_HEX_FACES = np.array([[0, 1, 2, 3], [4, 7, 6, 5], [0, 4, 5, 1], [1, 5, 6, 2],
                             [2, 6, 7, 3], [3, 7, 4, 0]])
"""Local nodes of the faces S1-S6 of an Abaqus C3D8 element (0-based)."""


def _inp_lines(path: Path, seen=()):
    """(file, line number, text) of the data and keyword lines of an .inp file, its
    ``*INCLUDE, INPUT=...`` files inserted (relative to the including file)."""
    if path.resolve() in seen:
        raise MeshFileError(f"{path}: *INCLUDE of itself (a loop through {seen[-1]})")
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise MeshFileError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    for k, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("**"):
            continue
        if line.startswith("*"):
            word, params = _inp_keyword(line)
            if word == "INCLUDE":
                if "INPUT" not in params:
                    raise MeshFileError(f"{path}:{k}: *INCLUDE without INPUT=FILE")
                yield from _inp_lines(path.parent / params["INPUT"], (*seen, path.resolve()))
                continue
        yield path, k, line


def _inp_keyword(line: str) -> tuple[str, dict]:
    """'*Elset, elset=Soft, generate' -> ('ELSET', {'ELSET': 'Soft', 'GENERATE': ''})."""
    head, *rest = line[1:].split(",")
    params = {}
    for item in rest:
        key, _, value = item.partition("=")
        if key.strip():
            params[key.strip().upper().replace(" ", "")] = value.strip().strip('"')
    return " ".join(head.upper().split()), params


def _abaqus_mesh(path: Path) -> Mesh:
    """The Mesh of an Abaqus .inp file (module doc)."""
    nodes, node_index = [], {}  # node number -> row
    hexes, hex_index = [], {}  # element number -> hexahedron index (C3D8*)
    nsets, elsets, names = {}, {}, {}  # upper name -> numbers; upper name -> spelling
    sections, surfaces, refused, parts, block_sets = [], {}, set(), 0, []
    word, params, where, pending, block_start = "", {}, "", [], ""

    def add_set(table, name, numbers):
        names.setdefault((table is nsets, name.upper()), name)
        table.setdefault(name.upper(), []).extend(numbers)

    def resolve(table, token, kind, at):
        """The numbers of the set ``token`` (any case) referred to at ``at`` (file:line)."""
        if token.upper() not in table:
            have = sorted((names[(kind == "node set", k)] for k in table), key=str.lower)
            raise MeshFileError(f"{at}: {kind} '{token}' is not defined before this line; the "
                                f"{kind}s of {path}: {', '.join(have) or 'none'}")
        return table[token.upper()]

    def numbers(line):
        return [t.strip() for t in line.split(",") if t.strip()]

    for file, k, line in _inp_lines(path):
        where = f"{file}:{k}"
        if line.startswith("*"):
            if pending:
                raise MeshFileError(f"{block_start}: an element line with {len(pending)} numbers "
                                    "left over; a C3D8 element is its number and 8 nodes")
            word, params = _inp_keyword(line)
            block_start = where
            parts += word == "PART"
            if word == "ELEMENT" and "TYPE" not in params:
                raise MeshFileError(f"{where}: *ELEMENT without TYPE=")
            if word in ("NSET", "ELSET") and word not in params:
                raise MeshFileError(f"{where}: *{word} without {word}=NAME")
            if word in ("NSET", "ELSET"):
                add_set(nsets if word == "NSET" else elsets, params[word], [])
            if word == "ELEMENT" and "ELSET" in params:  # known, if of no C3D8 elements
                add_set(elsets, params["ELSET"], [])
            if word == "NSET" and "ELSET" in params:  # the nodes of an element set
                add_set(nsets, params["NSET"], [
                    n for e in resolve(elsets, params["ELSET"], "element set", where)
                    if e in hex_index for n in hexes[hex_index[e]]])
            if word == "SOLID SECTION":
                if "ELSET" not in params or "MATERIAL" not in params:
                    raise MeshFileError(f"{where}: *SOLID SECTION needs ELSET= and MATERIAL=")
                sections.append((params["ELSET"], params["MATERIAL"], where))
            if word == "SURFACE":
                surfaces[params.get("NAME", f"surface{len(surfaces)}")] = (
                    params.get("TYPE", "ELEMENT").upper(), [], where)
            continue
        try:
            if word == "NODE":
                v = numbers(line)
                if len(v) != 4:
                    raise MeshFileError(f"{where}: node line '{line}'; eyefem needs 3-D "
                                        "nodes: number, x, y, z")
                node_index[int(v[0])] = len(nodes)
                nodes.append([float(x) for x in v[1:]])
                if "NSET" in params:
                    add_set(nsets, params["NSET"], [int(v[0])])
            elif word == "ELEMENT":
                etype = params["TYPE"].upper()
                v = [int(t) for t in numbers(line)]
                if etype.startswith("C3D8"):  # C3D8, C3D8R, C3D8H, C3D8I, C3D8RH...
                    pending.extend(v)
                    if "ELSET" in params and params["ELSET"].upper() not in block_sets:
                        block_sets.append(params["ELSET"].upper())
                    while len(pending) >= 9:
                        number, conn = pending[0], pending[1:9]
                        del pending[:9]
                        hex_index[number] = len(hexes)
                        hexes.append(conn)
                        if "ELSET" in params:
                            add_set(elsets, params["ELSET"], [number])
                else:
                    family = next((f for f in ABAQUS_REFUSED if etype.startswith(f)), None)
                    if family:
                        refused.add(f"{ABAQUS_REFUSED[family]} ({etype})")
            elif word in ("NSET", "ELSET"):
                table = nsets if word == "NSET" else elsets
                tokens = numbers(line)
                if "GENERATE" in params:
                    a, b, *step = (int(t) for t in tokens)
                    ids = list(range(a, b + 1, step[0] if step else 1))
                elif all(t.lstrip("-").isdigit() for t in tokens):
                    ids = [int(t) for t in tokens]
                else:
                    kind = "node set" if word == "NSET" else "element set"
                    ids = [i for t in tokens for i in (resolve(table, t, kind, where)
                                                       if not t.isdigit() else [int(t)])]
                add_set(table, params[word], ids)
            elif word == "SURFACE":
                next(reversed(surfaces.values()))[1].append(numbers(line))
        except MeshFileError:
            raise
        except ValueError as exc:
            raise MeshFileError(f"{where}: cannot read '{line}' under *{word} ({exc})") from None

    if pending:
        raise MeshFileError(f"{block_start}: an element line with {len(pending)} numbers left "
                            "over; a C3D8 element is its number and 8 nodes")
    if parts > 1:
        raise MeshFileError(f"{path}: {parts} *PART blocks; eyefem reads one mesh: write the "
                            "model as a flat input file (one part, or no parts)")
    if not hexes:
        kinds = ", ".join(sorted(refused)) or "none"
        raise MeshFileError(f"{path}: no hexahedra (C3D8 elements; solid cells: {kinds}); eyefem "
                            "needs 8-node hexahedra: mesh the volume with C3D8 elements")
    if refused:
        raise MeshFileError(f"{path}: {', '.join(sorted(refused))} elements; eyefem needs 8-node "
                            "hexahedra only (remesh the volume with C3D8 elements)")
    missing = sorted({n for h in hexes for n in h if n not in node_index})
    if missing:
        raise MeshFileError(f"{path}: elements use nodes {missing[:10]} that no *NODE defines")
    hexes = np.array([[node_index[n] for n in h] for h in hexes], np.int64)
    used = np.unique(hexes)
    renumber = np.full(len(nodes), -1, np.int64)
    renumber[used] = np.arange(len(used))
    points = np.asarray(nodes, np.float64)[used]
    hexes = renumber[hexes]
    bfaces = boundary_faces(hexes)
    inside_key = {tuple(sorted(f)): f for f in bfaces.tolist()}

    def node_rows(numbers_):
        rows = renumber[[node_index[n] for n in numbers_ if n in node_index]]
        return np.unique(rows[rows >= 0])

    def covered_faces(rows):
        inside = np.zeros(len(points), bool)
        inside[rows] = True
        return bfaces[inside[bfaces].all(axis=1)]

    element_sets = {names[(False, k)]: np.unique([hex_index[n] for n in v if n in hex_index])
                    for k, v in elsets.items()}
    element_sets = {k: v.astype(np.int64) for k, v in element_sets.items() if len(v)}
    node_sets = {"all": np.arange(len(points))}
    face_sets = {"boundary": bfaces}
    for k, v in nsets.items():
        rows = node_rows(v)
        node_sets[names[(True, k)]] = rows
        faces = covered_faces(rows)
        if len(faces):
            face_sets[names[(True, k)]] = faces
    for name, (kind, rows, where) in surfaces.items():
        if kind == "NODE":
            ids = [i for r in rows for i in (resolve(nsets, r[0], "node set", where)
                                             if not r[0].isdigit() else [int(r[0])])]
            node_sets[name] = node_rows(ids)
            face_sets[name] = covered_faces(node_sets[name])
            continue
        faces = []
        for r in rows:
            if len(r) < 2 or not _is_face_label(r[1]):
                raise MeshFileError(f"{where}: *SURFACE '{name}' line {r}; expected "
                                    "'ELSET or element, S1..S6'")
            elems = (resolve(elsets, r[0], "element set", where) if not r[0].isdigit()
                     else [int(r[0])])
            s = int(r[1][1:]) - 1
            for e in elems:
                if e not in hex_index:
                    continue
                face = hexes[hex_index[e]][ABAQUS_HEX_FACES[s]]
                key = tuple(sorted(face.tolist()))
                if key not in inside_key:
                    raise MeshFileError(f"{where}: *SURFACE '{name}': face {r[1]} of element "
                                        f"{e} is inside the mesh; a surface must be on its "
                                        "boundary")
                faces.append(inside_key[key])
        face_sets[name] = np.array(faces, np.int64).reshape(-1, 4)
        node_sets.setdefault(name, np.unique(face_sets[name]))
    block_sets = [names[(False, k)] for k in block_sets]
    materials, material_ids = _abaqus_materials(path, len(hexes), element_sets, block_sets,
                                                sections, hex_index, resolve, elsets)
    return Mesh(points, hexes, material_ids, materials, node_sets=node_sets,
                face_sets=face_sets, element_sets=element_sets)


def _is_face_label(label: str) -> bool:
    """Whether ``label`` names a C3D8 face, S1-S6."""
    return len(label) == 2 and label[0].upper() == "S" and label[1] in "123456"


def _abaqus_materials(path, n_hex, element_sets, block_sets, sections, hex_index, resolve,
                      elsets):
    """(material names, material id per hexahedron) from *SOLID SECTION lines; else from
    the ``ELSET=`` of the *ELEMENT lines when they cover every hexahedron; else from the
    smallest element sets (none inside another), which must not overlap."""
    ids = np.full(n_hex, -1, np.int64)
    covered = np.zeros(n_hex, bool)
    for k in block_sets:
        covered[element_sets.get(k, [])] = True
    if sections:
        mats = list(dict.fromkeys(m for _, m, _ in sections))
        for elset, mat, where in sections:
            members = [hex_index[n] for n in resolve(elsets, elset, "element set", where)
                       if n in hex_index]
            ids[members] = mats.index(mat)
        how = "in no *SOLID SECTION's element set"
    elif block_sets and covered.all():
        mats = block_sets
        for j, k in enumerate(mats):
            ids[element_sets[k]] = j
        how = "in no ELSET= of an *ELEMENT line"
    elif element_sets:
        sets = {k: set(v.tolist()) for k, v in element_sets.items()}
        smallest = [k for k, v in sets.items() if not any(o < v for o in sets.values())]
        for i, a in enumerate(smallest):
            for b in smallest[i + 1:]:
                if sets[a] & sets[b]:
                    raise MeshFileError(
                        f"{path}: element sets '{a}' and '{b}' overlap, so they cannot both "
                        "name a material; name the materials with *SOLID SECTION, ELSET=..., "
                        "MATERIAL=... lines (element sets: "
                        f"{', '.join(sorted(element_sets, key=str.lower))})")
        mats = smallest
        for j, k in enumerate(mats):
            ids[element_sets[k]] = j
        how = f"in none of the element sets {mats}"
    else:
        return ("default",), np.zeros(n_hex, np.int64)
    if np.any(ids < 0):
        number = {v: k for k, v in hex_index.items()}
        bad = np.nonzero(ids < 0)[0]
        raise MeshFileError(f"{path}: element {number[int(bad[0])]} (and {len(bad) - 1} more) is "
                            f"{how}; give every C3D8 element a material")
    return tuple(mats), ids
