"""Result files: VTU and XDMF time series (ParaView), CSV tables and PNG plots, written atomically.

Every file is first written under a temporary name in the same directory and then
renamed, so an interrupted or failed run never leaves a half-written file: what is
on disk is complete and belongs to converged steps.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import logging
import os
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _file_mode() -> int:
    """The mode a new file gets from the process umask (mkstemp's own is 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_path(path: Path):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success, with
    the permissions of a file created directly (the umask's, not the temporary's 0600)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, _file_mode())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def write_text(path: Path, text: str):
    """Write a text file atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_csv(path: Path, rows: Iterable[Mapping[str, float]]):
    """Write rows (dicts with the same keys) as a CSV file atomically."""
    rows = list(rows)
    buf = io.StringIO()
    if rows:
        keys = list(rows[0])
        for r in rows[1:]:
            keys += [k for k in r if k not in keys]
        w = csv.DictWriter(buf, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.10g}" if isinstance(v, float) else v) for k, v in r.items()})
    write_text(path, buf.getvalue())


@dataclasses.dataclass(frozen=True)
class Part:
    """One further dataset of a time series frame (a rigid buckle, sutures...).

    Attributes: points (n, 3) mm in the current configuration; cell_type a meshio cell
    type ("triangle", "line", "hexahedron"...); cells (m, k) point indices; point_data
    name -> (n, ...); cell_data name -> (m, ...).
    """

    points: np.ndarray
    cell_type: str
    cells: np.ndarray
    point_data: Mapping = dataclasses.field(default_factory=dict)
    cell_data: Mapping = dataclasses.field(default_factory=dict)


def write_vtu(path: Path, nodes, hexes, point_data: Mapping, cell_data: Mapping,
              field_data: Mapping | None = None, cell_type: str = "hexahedron"):
    """Write one VTU file (one cell block) atomically with meshio.

    Args: nodes (n, 3); hexes (e, k) cells of ``cell_type``; point_data name -> (n, ...);
    cell_data name -> (e, ...) (trailing dimensions flattened, a (3, 3) tensor as 9
    components); field_data name -> number or 1-D array (ParaView's field data).
    """
    import meshio

    hexes = np.asarray(hexes)
    cd = {}
    for k, v in cell_data.items():
        v = np.asarray(v)
        cd[k] = [v.reshape(len(hexes), -1) if v.ndim > 2 else v]
    mesh = meshio.Mesh(np.asarray(nodes, np.float64), [(cell_type, hexes)],
                       point_data={k: np.asarray(v) for k, v in point_data.items()},
                       cell_data=cd)
    with atomic_path(Path(path)) as tmp:
        meshio.write(tmp, mesh, file_format="vtu")
        if field_data:
            _add_field_data(tmp, field_data)


def _add_field_data(path: Path, field_data: Mapping):
    """Insert a <FieldData> block of ASCII Float64 arrays into a VTU file written by
    meshio (whose VTU writer drops ``field_data``; its reader and ParaView read it)."""
    from xml.sax.saxutils import quoteattr

    arrays = []
    for k, v in field_data.items():
        v = np.atleast_1d(np.asarray(v, dtype=np.float64)).ravel()
        arrays.append(f'<DataArray type="Float64" Name={quoteattr(str(k))} '
                      f'NumberOfTuples="{len(v)}" format="ascii">'
                      + " ".join(f"{x:.17g}" for x in v) + "</DataArray>")
    text = Path(path).read_text()
    tag = "<UnstructuredGrid>"
    if text.count(tag) != 1:
        raise RuntimeError(f"{path}: expected one {tag} in meshio's VTU output; cannot add "
                           "field data (meshio's writer changed?)")
    Path(path).write_text(text.replace(tag, tag + "\n<FieldData>\n" + "\n".join(arrays)
                                       + "\n</FieldData>", 1))


def write_pvd(path: Path, entries: list[tuple[float, str]], parts: Mapping[str, str] | None = None):
    """A ParaView collection file listing (time, relative vtu file) entries.

    ``parts`` maps a file name prefix (the text before ``_NNNN.vtu``) to a dataset name;
    files of one prefix form one part (ParaView shows one block per part, named by the
    ``name`` attribute). Entries whose prefix is not in ``parts`` form part 0.
    """
    parts = dict(parts or {})
    order = list(dict.fromkeys(parts.values()))
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    for t, f in entries:
        prefix = Path(f).name.rsplit("_", 1)[0]
        name = parts.get(prefix, "")
        if name:
            k = order.index(name)
            lines.append(f'    <DataSet timestep="{t:.10g}" group="" part="{k}" name="{name}" '
                         f'file="{f}"/>')
        else:
            lines.append(f'    <DataSet timestep="{t:.10g}" group="" part="0" file="{f}"/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    write_text(path, "\n".join(lines))


class SeriesWriter:
    """Writes one frame per converged step and keeps the .pvd collection up to date.

    A frame is the main hexahedral dataset ``vtu/<name>_NNNN.vtu`` (part 0 of the PVD,
    named ``name``) and optionally further datasets ``vtu/<name>-<part>_NNNN.vtu`` (the
    rigid buckle, the sutures...), each its own part of the same series. ``entries`` is
    the list of (time, relative file) written so far (what a checkpoint stores).

    Args:
      directory: output directory (created).
      name: base name of the files.
    """

    def __init__(self, directory: Path, name: str = "result"):
        self.dir = Path(directory)
        self.name = name
        self.entries: list[tuple[float, str]] = []

    def _parts(self) -> dict:
        """File prefix -> dataset name of every part in ``entries`` (main first)."""
        out = {self.name: self.name}
        for _, f in self.entries:
            prefix = Path(f).name.rsplit("_", 1)[0]
            if prefix.startswith(f"{self.name}-"):
                out[prefix] = prefix[len(self.name) + 1:]
        return out

    @property
    def n_frames(self) -> int:
        """Frames written so far (main datasets in ``entries``)."""
        return sum(Path(f).name.rsplit("_", 1)[0] == self.name for _, f in self.entries)

    def add(self, time: float, nodes, hexes, point_data, cell_data, field_data=None,
            parts: Mapping[str, Part] | None = None):
        """Write one frame at ``time`` (monotone) and rewrite the .pvd.

        Args: nodes (n, 3) reference coordinates, mm; hexes (e, 8); point_data,
        cell_data, field_data as :func:`write_vtu`; parts: dataset name -> Part (names
        of letters, digits and underscores), written with the same field data.
        """
        if self.entries and time < self.entries[-1][0]:
            raise ValueError(f"SeriesWriter '{self.name}': time {time} after "
                             f"{self.entries[-1][0]}; frame times must not decrease")
        frame = self.n_frames
        fname = f"vtu/{self.name}_{frame:04d}.vtu"
        write_vtu(self.dir / fname, nodes, hexes, point_data, cell_data, field_data)
        self.entries.append((time, fname))
        for pname, part in (parts or {}).items():
            if not pname.replace("_", "").isalnum():
                raise ValueError(f"SeriesWriter '{self.name}': part name '{pname}'; use "
                                 "letters, digits and underscores")
            fname = f"vtu/{self.name}-{pname}_{frame:04d}.vtu"
            write_vtu(self.dir / fname, part.points, part.cells, part.point_data,
                      part.cell_data, field_data, cell_type=part.cell_type)
            self.entries.append((time, fname))
        write_pvd(self.dir / f"{self.name}.pvd", self.entries, self._parts())


def xdmf_data_format() -> str:
    """The XDMF data format :class:`XdmfSeriesWriter` uses by default: "HDF" (arrays in an
    HDF5 file beside the .xdmf) when h5py is importable, else "XML" (arrays as text)."""
    import importlib.util

    return "HDF" if importlib.util.find_spec("h5py") is not None else "XML"


class XdmfSeriesWriter:
    """The main hexahedral dataset of every frame as one XDMF time series, ``<name>.xdmf``
    (and with data_format "HDF" its arrays in ``<name>.h5``), through meshio's
    ``meshio.xdmf.TimeSeriesWriter``: the mesh once (reference coordinates), then per frame
    the same point and cell fields as the VTU frames (a (3, 3) tensor as 9 components).

    The .xdmf is rewritten atomically after every frame (its HDF5 arrays are flushed
    first), so it lists complete frames only. "XML" rewrites every array each time: use
    "HDF" (install h5py) for long series of large meshes. ``entries`` lists (time, label)
    of the frames written. Field data and further parts (buckle, sutures) are VTU-only.

    Args:
      directory: output directory (created).
      name: base name of the files.
      data_format: "HDF" or "XML"; None: :func:`xdmf_data_format`.
    """

    def __init__(self, directory: Path, name: str = "result", data_format: str | None = None):
        self.dir = Path(directory)
        self.name = name
        self.data_format = data_format or xdmf_data_format()
        if self.data_format not in ("HDF", "XML"):
            raise ValueError(f"XdmfSeriesWriter '{name}': data_format '{self.data_format}'; "
                             "use 'HDF' (needs h5py) or 'XML'")
        self.entries: list[tuple[float, str]] = []
        self._writer = None

    @property
    def path(self) -> Path:
        """The .xdmf file."""
        return self.dir / f"{self.name}.xdmf"

    @property
    def h5_path(self) -> Path:
        """The HDF5 file of the arrays (data_format "HDF")."""
        return self.dir / f"{self.name}.h5"

    def _open(self, nodes, hexes):
        from meshio.xdmf import TimeSeriesWriter

        self.dir.mkdir(parents=True, exist_ok=True)
        w = TimeSeriesWriter(self.path, data_format=self.data_format)
        if self.data_format == "HDF":
            import h5py

            # meshio's __enter__ would put the .h5 in the current directory; the .xdmf
            # refers to it by its bare name, i.e. beside itself
            w.h5_filename = str(self.h5_path)
            w.h5_file = h5py.File(self.h5_path, "w")
        hexes = np.asarray(hexes)
        w.write_points_cells(np.asarray(nodes, np.float64), [("hexahedron", hexes)])
        self._writer, self._n_cells = w, len(hexes)

    def add(self, time: float, nodes, hexes, point_data: Mapping, cell_data: Mapping,
            field_data=None, parts=None):
        """Append one frame at ``time`` (monotone) and rewrite the .xdmf. Args as
        :meth:`SeriesWriter.add`; nodes and hexes are written with the first frame only,
        field_data and parts are ignored."""
        if self.entries and time < self.entries[-1][0]:
            raise ValueError(f"XdmfSeriesWriter '{self.name}': time {time} after "
                             f"{self.entries[-1][0]}; frame times must not decrease")
        if self._writer is None:
            self._open(nodes, hexes)
        n_cells = self._n_cells

        def plain(v):
            v = np.asarray(v)
            return v.astype(np.int32) if v.dtype == bool else v

        cd = {k: [plain(v).reshape(n_cells, -1) if np.ndim(v) > 2 else plain(v)]
              for k, v in cell_data.items()}
        self._writer.write_data(float(time), point_data={k: plain(v) for k, v in point_data.items()},
                                cell_data=cd)
        if self.data_format == "HDF":
            self._writer.h5_file.flush()
        with atomic_path(self.path) as tmp:
            ET.ElementTree(self._writer.xdmf_file).write(tmp)
        self.entries.append((float(time), f"{self.path.name}#{len(self.entries)}"))

    def resume(self, until: float):
        """Continue the series of an earlier run: copy its frames with time <= ``until``
        (the end of the last completed stage) into a fresh series; none if it has no
        readable series."""
        from meshio.xdmf import TimeSeriesReader

        self.close()
        self.entries = []
        if not self.path.is_file():
            log.warning("%s: no XDMF series of the earlier run; the XDMF series starts at the "
                        "resumed stage", self.path)
            return
        old = self.path.with_name(f".{self.name}.resumed.xdmf")
        os.replace(self.path, old)
        moved = []
        if self.h5_path.is_file():
            os.replace(self.h5_path, old.with_suffix(".h5"))
            moved.append(old.with_suffix(".h5"))
            text = old.read_text().replace(f"{self.h5_path.name}:/", f"{old.stem}.h5:/")
            old.write_text(text)
        try:
            with TimeSeriesReader(old) as r:
                points, cells = r.read_points_cells()
                for k in range(r.num_steps):
                    t, pd, cd = r.read_data(k)
                    if t > until + 1e-9:
                        break
                    self.add(t, points, cells[0].data, pd, {n: v[0] for n, v in cd.items()})
        finally:
            for p in (old, *moved):
                with contextlib.suppress(FileNotFoundError):
                    os.remove(p)

    def close(self):
        """Close the HDF5 file (the .xdmf is complete after every frame)."""
        if self._writer is not None and self.data_format == "HDF":
            self._writer.h5_file.close()
        self._writer = None


def plot_curves(path: Path, x, curves: Mapping[str, tuple], *, xlabel: str, ylabel: str,
                title: str = ""):
    """Plot named curves to a PNG atomically: curves name -> (y, style) with style like 'o' or '-'."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.2), dpi=120)
    for label, (xy, style) in curves.items():
        xs, ys = xy if isinstance(xy, tuple) else (x, xy)
        ax.plot(xs, ys, style, label=label, ms=4)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def write_case(path: Path, problem: str, title: str, parameters: dict,
               materials: dict | None = None, description: str = "",
               solver: dict | None = None):
    """Write a case file atomically (TOML); ``solver``: its ``[solver]`` section (NewtonOptions
    fields), left out when empty."""
    import tomli_w

    doc = {"case": {"problem": problem, "title": title or problem}}
    if description:
        doc["case"]["description"] = description
    doc["parameters"] = parameters
    if materials:
        doc["materials"] = materials
    if solver:
        doc["solver"] = solver
    write_text(Path(path), tomli_w.dumps(doc))
