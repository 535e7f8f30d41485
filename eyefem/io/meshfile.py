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

Inputs stay inputs (docs/errors.md, "Mesh files"): the mesh file must be a regular file of
at most MAX_MESH_BYTES (with its ``*INCLUDE`` files); an ``*INCLUDE`` must name a regular
file below the including file's folder (or below a folder of ``allow_include`` /
``EYEFEM_ALLOW_INCLUDE``), at most MAX_INCLUDE_DEPTH levels deep, each file once (no cycle,
no fan-out); GENERATE ranges are checked against the nodes/elements defined before they
are expanded; duplicate node and element numbers (Abaqus) or tags (gmsh) and non-finite
coordinates are refused by file, line and number; gmsh files must be ASCII.
"""

from __future__ import annotations

import dataclasses
import errno
import math
import os
import stat
from array import array
from pathlib import Path

import numpy as np

from eyefem.fem.mesh import Mesh, boundary_faces

VOLUME_CELLS = {"tetra", "tetra10", "wedge", "wedge15", "pyramid", "pyramid13",
                "hexahedron20", "hexahedron27"}
"""meshio volume cell types eyefem cannot use (its elements are 8-node hexahedra)."""


class MeshFileError(ValueError):
    """A mesh file eyefem cannot use; the message names the file and what is wrong."""


MAX_INCLUDE_DEPTH = 16
"""Most nested Abaqus ``*INCLUDE`` levels (raise: EYEFEM_MAX_INCLUDE_DEPTH or
read_hex_mesh(..., max_include_depth=N))."""

MAX_MESH_BYTES = 512 * 2**20
"""Most bytes of a mesh file and its ``*INCLUDE`` files together, 512 MB (raise:
EYEFEM_MAX_MESH_BYTES or read_hex_mesh(..., max_bytes=N))."""

ENV_ALLOW_INCLUDE = "EYEFEM_ALLOW_INCLUDE"
"""Folders (separated by os.pathsep) below which ``*INCLUDE`` may also read files."""
ENV_MAX_INCLUDE_DEPTH = "EYEFEM_MAX_INCLUDE_DEPTH"
ENV_MAX_MESH_BYTES = "EYEFEM_MAX_MESH_BYTES"

MESH_SUFFIXES = (".msh", ".inp", ".vtu", ".vtk", ".xdmf", ".med")
"""Suffixes listed when a folder is given as the mesh file."""


MESH_FILE = "a mesh file (gmsh .msh, Abaqus .inp or VTU)"
INCLUDED_FILE = "an Abaqus .inp text file below the including file's folder"


@dataclasses.dataclass(frozen=True)
class MeshLimits:
    """The bounds of reading a mesh file (module constants, environment, arguments)."""

    allow_include: tuple[Path, ...] = ()
    max_include_depth: int = MAX_INCLUDE_DEPTH
    max_bytes: int = MAX_MESH_BYTES


def _env_int(name: str, default: int) -> int:
    raw = os.environ.get(name, "").strip()
    if not raw:
        return default
    try:
        value = int(raw.replace("_", ""))
    except ValueError:
        value = 0
    if value < 1:
        raise MeshFileError(f"environment variable {name} = '{raw[:40]}' is not a positive "
                            f"integer; unset it (default {default}) or give one, e.g. "
                            f"{name}={default * 2}")
    return value


def mesh_limits(allow_include=(), max_include_depth: int | None = None,
                max_bytes: int | None = None) -> MeshLimits:
    """The MeshLimits of the arguments, else of the environment (EYEFEM_ALLOW_INCLUDE,
    EYEFEM_MAX_INCLUDE_DEPTH, EYEFEM_MAX_MESH_BYTES), else of the module constants."""
    dirs = [Path(d) for d in (allow_include or ())]
    dirs += [Path(d) for d in os.environ.get(ENV_ALLOW_INCLUDE, "").split(os.pathsep) if d]
    for d in dirs:
        if not d.expanduser().is_dir():
            raise MeshFileError(f"allowed include folder '{d}' ({ENV_ALLOW_INCLUDE} or "
                                "allow_include) is not a folder; give an existing folder")
    depth = max_include_depth if max_include_depth is not None else _env_int(
        ENV_MAX_INCLUDE_DEPTH, MAX_INCLUDE_DEPTH)
    size = max_bytes if max_bytes is not None else _env_int(ENV_MAX_MESH_BYTES, MAX_MESH_BYTES)
    return MeshLimits(tuple(Path(os.path.realpath(d.expanduser())) for d in dirs),
                      int(depth), int(size))


def _file_kind(mode: int) -> str:
    return ("a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a character device"
            if stat.S_ISCHR(mode) else "a block device" if stat.S_ISBLK(mode) else
            "a socket" if stat.S_ISSOCK(mode) else "not a regular file")


def _stat_regular(path: Path, label: str, what: str) -> os.stat_result:
    """The stat of ``path``, a regular file; else a MeshFileError '``label``: why; fix'
    (``what``: what the file should be). Never opens anything."""
    try:
        st = os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise MeshFileError(f"{label}: a symbolic link loop ({exc.strerror}); point it at "
                                f"{what}") from None
        if exc.errno in (errno.ENOENT, errno.ENOTDIR):
            raise MeshFileError(f"{label}: no such file ({path}); give {what}") from None
        raise MeshFileError(f"{label}: cannot read it ({exc.strerror or exc}); give {what} "
                            "you can read") from None
    if stat.S_ISDIR(st.st_mode):
        try:
            held = sorted(p.name for p in Path(path).iterdir()
                          if p.suffix.lower() in MESH_SUFFIXES)[:5]
        except OSError:
            held = []
        hint = f" (it holds {', '.join(held)})" if held else ""
        raise MeshFileError(f"{label}: is a directory{hint}; give {what}, not a folder")
    if not stat.S_ISREG(st.st_mode):
        raise MeshFileError(f"{label}: {_file_kind(st.st_mode)}, not a regular file; give "
                            f"{what} (a regular file)")
    return st


def _too_big(label: str, limits: MeshLimits) -> MeshFileError:
    n = limits.max_bytes
    size = f"{n // 2**20} MB" if n % 2**20 == 0 else f"{n} bytes"
    return MeshFileError(
        f"{label}: the mesh file and its *INCLUDE files would exceed {size} "
        "(MAX_MESH_BYTES, the bound on a mesh's files together); if the mesh is really this "
        f"large, raise it with {ENV_MAX_MESH_BYTES}=BYTES (or read_hex_mesh(..., max_bytes=...))")


def _read_regular(path: Path, label: str, what: str, budget: int, limits: MeshLimits) -> bytes:
    """The bytes of the regular file ``path``, at most ``budget`` of them (else the size
    bound's error); opened without blocking and checked again once open."""
    st = _stat_regular(path, label, what)
    if st.st_size > budget:
        raise _too_big(label, limits)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise MeshFileError(f"{label}: cannot read it ({exc.strerror or exc}); give {what} "
                            "you can read") from None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise MeshFileError(f"{label}: not a regular file; give {what} (a regular file)")
        data = f.read(budget + 1)
    if len(data) > budget:
        raise _too_big(label, limits)
    return data


def read_hex_mesh(path: str | Path, *, allow_include=(), max_include_depth: int | None = None,
                  max_bytes: int | None = None) -> Mesh:
    """The Mesh of a hexahedral mesh file, with materials and named sets (module doc).

    ``allow_include``: folders below which an Abaqus ``*INCLUDE`` may also read (besides
    the including file's folder; also EYEFEM_ALLOW_INCLUDE); ``max_include_depth``,
    ``max_bytes``: raise MAX_INCLUDE_DEPTH, MAX_MESH_BYTES (also EYEFEM_MAX_INCLUDE_DEPTH,
    EYEFEM_MAX_MESH_BYTES)."""
    import meshio

    path = Path(path)
    limits = mesh_limits(allow_include, max_include_depth, max_bytes)
    st = _stat_regular(path, str(path), MESH_FILE)
    if path.suffix.lower() == ".inp":
        return _abaqus_mesh(path, limits)
    if st.st_size > limits.max_bytes:
        raise _too_big(str(path), limits)
    if path.suffix.lower() == ".msh":
        _check_gmsh(path)
    try:
        m = meshio.read(path)
    except Exception as exc:  # noqa: BLE001 - meshio raises many types for a bad file
        raise MeshFileError(f"{path}: meshio cannot read it ({type(exc).__name__}: "
                            f"{str(exc)[:200]}); give a gmsh .msh, Abaqus .inp or VTU "
                            "hexahedral mesh") from None
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
    finite = np.all(np.isfinite(nodes), axis=1)
    if not finite.all():  # a .msh is checked by tag before; VTU points have no numbers
        bad = used[~finite]
        raise MeshFileError(f"{path}: point {int(bad[0])} (numbered from 0 in the file's "
                            f"order; {len(bad)} such points) has a non-finite coordinate "
                            f"{nodes[~finite][0].tolist()}; give finite coordinates")
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


GMSH_ASCII_FIX = ("save it as ASCII in gmsh (File > Export > Gmsh MSH with 'Save in binary "
                  "format' unticked, or Mesh.Binary = 0; e.g. gmsh -3 -format msh41 -bin 0 "
                  "mesh.geo)")


def _check_gmsh(path: Path) -> None:
    """Refuse a .msh file that is not ASCII gmsh (2.x, 4.0, 4.1), or whose $Nodes or
    $Elements repeat a tag or whose nodes have a non-finite coordinate (by line and tag);
    meshio would let the last definition of a node win."""
    with open(path, "rb") as f:
        first = f.readline(64).strip()
        while first == b"$Comments":
            for line in f:
                if line.strip() == b"$EndComments":
                    break
            first = f.readline(64).strip()
        header = f.readline(64).split() if first == b"$MeshFormat" else []
    if len(header) < 2 or header[1] not in (b"0", b"1"):
        raise MeshFileError(f"{path}: not a gmsh .msh file (it does not begin with a "
                            "$MeshFormat header); export the mesh from gmsh as an ASCII .msh "
                            "(format 2.2 or 4.1)")
    if header[1] == b"1":
        raise MeshFileError(f"{path}: a binary gmsh file (eyefem checks the node and element "
                            f"tags of ASCII .msh files only); {GMSH_ASCII_FIX}")
    try:
        version = float(header[0])
    except ValueError:
        version = 0.0
    if not 2 <= version < 5:
        raise MeshFileError(f"{path}: gmsh format '{header[0].decode(errors='replace')[:10]}' "
                            "(eyefem reads 2.2, 4.0 and 4.1); export the mesh from gmsh as "
                            "ASCII .msh format 2.2 or 4.1")
    seen = {"Nodes": set(), "Elements": set()}
    for section, k, tag, coords in _gmsh_entries(path, version):
        kind = "node" if section == "Nodes" else "element"
        if tag in seen[section]:
            first = next(kk for sec, kk, t, _ in _gmsh_entries(path, version)
                         if sec == section and t == tag)
            raise MeshFileError(f"{path}:{k}: {kind} tag {tag} is defined twice (first at line "
                                f"{first}); give each {kind} its own tag (meshio would keep "
                                "the last definition)")
        seen[section].add(tag)
        for c in coords:
            try:
                x = float(c)
            except ValueError:
                raise MeshFileError(f"{path}:{k}: $Nodes: coordinate '{c[:20]}' of node {tag} "
                                    "is not a number; give x y z") from None
            if not math.isfinite(x):
                raise MeshFileError(f"{path}:{k}: node {tag} has a non-finite coordinate "
                                    f"{c[:20]}; give finite coordinates")


def _gmsh_entries(path: Path, version: float):
    """(section, line, tag, coordinates) of the nodes ("Nodes", x y z tokens) and
    (section, line, tag, ()) of the elements ("Elements") of an ASCII gmsh file; the
    counts of the file are trusted for nothing but to walk its blocks."""
    v4, v41 = version >= 4, version >= 4.1
    with open(path, encoding="utf-8", errors="replace") as f:
        lines = enumerate(f, 1)

        def take(section):
            for k, line in lines:
                tokens = line.split()
                if tokens and tokens[0].startswith("$"):
                    raise MeshFileError(f"{path}:{k}: ${section} ends early ({tokens[0][:20]} "
                                        "before its last entry); export the mesh again from "
                                        "gmsh")
                if tokens:
                    return k, tokens
            raise MeshFileError(f"{path}: ${section} ends early (end of file); export the mesh "
                                "again from gmsh")

        def integer(k, tokens, i, section, what):
            if len(tokens) <= i:
                raise MeshFileError(f"{path}:{k}: ${section}: {len(tokens)} numbers where a "
                                    f"{what} was expected; export the mesh again from gmsh")
            try:
                return int(tokens[i])
            except ValueError:
                raise MeshFileError(f"{path}:{k}: ${section}: {what} '{tokens[i][:20]}' is not "
                                    "an integer; export the mesh again from gmsh") from None

        for _, line in lines:
            section = line.strip()[1:]
            if section not in ("Nodes", "Elements"):
                continue
            k, head = take(section)
            blocks = integer(k, head, 0, section, "count") if v4 else 1
            for _ in range(blocks):
                if v4:
                    k, block = take(section)
                    count = integer(k, block, 3, section, "block size")
                else:
                    count = integer(k, head, 0, section, "count")
                if v41 and section == "Nodes":  # the tags, then the coordinates
                    tags = []
                    for _ in range(count):
                        k, t = take(section)
                        tags.append(integer(k, t, 0, section, "node tag"))
                    for tag in tags:
                        k, t = take(section)
                        yield section, k, tag, t[:3]
                    continue
                for _ in range(count):
                    k, t = take(section)
                    tag = integer(k, t, 0, section, "tag")
                    yield section, k, tag, (t[1:4] if section == "Nodes" else ())


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


def _inp_lines(path: Path, limits: MeshLimits):
    """(file, line number, text) of the data and keyword lines of an .inp file, its
    ``*INCLUDE, INPUT=...`` files inserted (relative to the including file; module doc:
    below its folder or an allowed one, regular files, MAX_INCLUDE_DEPTH levels, each file
    once, MAX_MESH_BYTES in all). Nothing outside is opened: the checks come first."""
    total = [0]
    real = Path(os.path.realpath(path))
    seen = {real: f"{path} (the mesh file)"}

    def walk(shown: Path, real: Path, label: str, stack: tuple):
        data = _read_regular(real, label, MESH_FILE if len(stack) == 1 else INCLUDED_FILE,
                             limits.max_bytes - total[0], limits)
        total[0] += len(data)
        for k, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), 1):
            line = line.strip()
            if not line or line.startswith("**"):
                continue
            if line.startswith("*"):
                word, params = _inp_keyword(line)
                if word == "INCLUDE":
                    yield from include(shown, real, k, params, stack)
                    continue
            yield shown, k, line

    def include(shown, real, k, params, stack):
        value = params.get("INPUT", "")
        if not value:
            raise MeshFileError(f"{shown}:{k}: *INCLUDE without INPUT=FILE; give the file to "
                                "include, relative to this file's folder")
        at = f"{shown}:{k}: *INCLUDE, INPUT={value[:200]}"
        target = Path(os.path.realpath(real.parent / value))
        roots = (real.parent, *limits.allow_include)
        if not any(target == r or target.is_relative_to(r) for r in roots):
            raise MeshFileError(
                f"{at}: outside the folder of {shown.name} ({real.parent}); an *INCLUDE reads "
                "files below the including file's folder only: copy the file there, or allow "
                f"its folder with {ENV_ALLOW_INCLUDE}=DIR (or read_hex_mesh(..., "
                "allow_include=[DIR]))")
        if target in stack:
            names = " -> ".join(p.name for p in stack[stack.index(target):])
            raise MeshFileError(f"{at}: an include cycle ({names} -> {target.name}); remove "
                                "the *INCLUDE that closes it")
        if target in seen:
            raise MeshFileError(f"{at}: {target.name} is already included (at {seen[target]}); "
                                "each file is included once (a repeated *INCLUDE defines its "
                                "nodes and elements again; many of them are an include "
                                "bomb): remove the repeated *INCLUDE")
        if len(stack) > limits.max_include_depth:
            raise MeshFileError(
                f"{at}: *INCLUDE nested more than {limits.max_include_depth} levels deep "
                "(MAX_INCLUDE_DEPTH); flatten the includes, or raise the bound with "
                f"{ENV_MAX_INCLUDE_DEPTH}=N (or read_hex_mesh(..., max_include_depth=N))")
        seen[target] = f"{shown}:{k}"
        yield from walk(shown.parent / value, target, at, (*stack, target))

    yield from walk(path, real, str(path), (real,))


def _inp_keyword(line: str) -> tuple[str, dict]:
    """'*Elset, elset=Soft, generate' -> ('ELSET', {'ELSET': 'Soft', 'GENERATE': ''})."""
    head, *rest = line[1:].split(",")
    params = {}
    for item in rest:
        key, _, value = item.partition("=")
        if key.strip():
            params[key.strip().upper().replace(" ", "")] = value.strip().strip('"')
    return " ".join(head.upper().split()), params


def _abaqus_mesh(path: Path, limits: MeshLimits = MeshLimits()) -> Mesh:
    """The Mesh of an Abaqus .inp file (module doc)."""
    nodes, node_index = [], {}  # node number -> row
    hexes, hex_index = [], {}  # element number -> hexahedron index (C3D8*)
    files, file_no = [], {}  # the files read; file -> its index in files
    node_at, hex_at = (array("q"), array("q")), (array("q"), array("q"))  # (file, line)
    other_elements = 0  # data lines of *ELEMENT blocks of other types (for GENERATE)
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

    def first_at(at, row):
        return f"{files[at[0][row]]}:{at[1][row]}"

    def mark(at, file, k):
        if file not in file_no:
            file_no[file] = len(files)
            files.append(file)
        at[0].append(file_no[file])
        at[1].append(k)

    for file, k, line in _inp_lines(path, limits):
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
                number, xyz = int(v[0]), [float(x) for x in v[1:]]
                if number in node_index:
                    raise MeshFileError(
                        f"{where}: node {number} is defined twice (first at "
                        f"{first_at(node_at, node_index[number])}); give each node its own "
                        "number (else the last definition would silently move the node)")
                bad = next((t for t, x in zip(v[1:], xyz) if not math.isfinite(x)), None)
                if bad is not None:
                    raise MeshFileError(f"{where}: node {number} has a non-finite coordinate "
                                        f"{bad[:20]}; give finite x, y, z")
                node_index[number] = len(nodes)
                mark(node_at, file, k)
                nodes.append(xyz)
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
                        if number in hex_index:
                            raise MeshFileError(
                                f"{where}: element {number} is defined twice (first at "
                                f"{first_at(hex_at, hex_index[number])}); give each element "
                                "its own number")
                        hex_index[number] = len(hexes)
                        mark(hex_at, file, k)
                        hexes.append(conn)
                        if "ELSET" in params:
                            add_set(elsets, params["ELSET"], [number])
                else:
                    other_elements += 1
                    family = next((f for f in ABAQUS_REFUSED if etype.startswith(f)), None)
                    if family:
                        refused.add(f"{ABAQUS_REFUSED[family]} ({etype})")
            elif word in ("NSET", "ELSET"):
                table = nsets if word == "NSET" else elsets
                tokens = numbers(line)
                if "GENERATE" in params:
                    ids = _generate(tokens, where, word, len(nodes) if word == "NSET"
                                    else len(hexes) + other_elements)
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


def _generate(tokens: list, where: str, word: str, defined: int) -> range:
    """The numbers of a ``*NSET/*ELSET, GENERATE`` line 'FIRST, LAST[, STEP]', checked
    before anything is allocated: a positive step, FIRST <= LAST, and no more numbers than
    the nodes (elements) defined above the line."""
    at = f"{where}: *{word}, GENERATE '{', '.join(t[:20] for t in tokens[:4])}'"
    form = "FIRST, LAST[, STEP]"
    if len(tokens) not in (2, 3):
        raise MeshFileError(f"{at}: {len(tokens)} numbers; a GENERATE line is {form}")
    try:
        first, last, step = (*(int(t) for t in tokens[:2]),
                             int(tokens[2]) if len(tokens) == 3 else 1)
    except ValueError:
        bad = next(t for t in tokens if not t.lstrip("+-").isdigit())
        raise MeshFileError(f"{at}: '{bad[:20]}' is not an integer; a GENERATE line is "
                            f"{form}") from None
    if step < 1:
        raise MeshFileError(f"{at}: step {step}; a GENERATE step must be at least 1 ({form})")
    if last < first:
        raise MeshFileError(f"{at}: a reversed range (LAST {last} below FIRST {first}); write "
                            f"it as {last}, {first}" + (f", {step}" if len(tokens) == 3 else ""))
    kind = "node" if word == "NSET" else "element"
    count = (last - first) // step + 1
    if count > defined:
        raise MeshFileError(f"{at}: {count} {kind} numbers, more than the {defined} {kind}s "
                            f"defined above this line; a GENERATE range names {kind}s defined "
                            f"before it: correct the range (or put the set after its *"
                            f"{'NODE' if kind == 'node' else 'ELEMENT'} lines)")
    return range(first, last + 1, step)


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
