"""Result files: VTU time series (ParaView), CSV tables and PNG plots, all written atomically.

Every file is first written under a temporary name in the same directory and then
renamed, so an interrupted or failed run never leaves a half-written file: what is
on disk is complete and belongs to converged steps.
"""

from __future__ import annotations

import contextlib
import csv
import io
import logging
import os
import tempfile
from pathlib import Path
from typing import Iterable, Mapping

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


def write_vtu(path: Path, nodes, hexes, point_data: Mapping, cell_data: Mapping,
              field_data: Mapping | None = None):
    """Write one hexahedral VTU file atomically with meshio.

    Args: nodes (n, 3); hexes (e, 8); point_data name -> (n, ...); cell_data name -> (e, ...).
    """
    import meshio

    cd = {}
    for k, v in cell_data.items():
        v = np.asarray(v)
        cd[k] = [v.reshape(len(hexes), -1) if v.ndim > 2 else v]
    mesh = meshio.Mesh(np.asarray(nodes), [("hexahedron", np.asarray(hexes))],
                       point_data={k: np.asarray(v) for k, v in point_data.items()},
                       cell_data=cd,
                       field_data={k: np.atleast_1d(np.asarray(v, dtype=np.float64))
                                   for k, v in (field_data or {}).items()})
    with atomic_path(Path(path)) as tmp:
        meshio.write(tmp, mesh, file_format="vtu")


def write_pvd(path: Path, entries: list[tuple[float, str]]):
    """A ParaView collection file listing (time, relative vtu file) entries."""
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    lines += [f'    <DataSet timestep="{t:.8g}" group="" part="0" file="{f}"/>' for t, f in entries]
    lines += ["  </Collection>", "</VTKFile>", ""]
    write_text(path, "\n".join(lines))


class SeriesWriter:
    """Writes one VTU per converged step and keeps the .pvd collection up to date.

    Args:
      directory: output directory (created).
      name: base name of the files.
    """

    def __init__(self, directory: Path, name: str = "result"):
        self.dir = Path(directory)
        self.name = name
        self.entries: list[tuple[float, str]] = []

    def add(self, time: float, nodes, hexes, point_data, cell_data, field_data=None):
        fname = f"{self.name}_{len(self.entries):04d}.vtu"
        write_vtu(self.dir / "vtu" / fname, nodes, hexes, point_data, cell_data, field_data)
        self.entries.append((time, f"vtu/{fname}"))
        write_pvd(self.dir / f"{self.name}.pvd", self.entries)


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
