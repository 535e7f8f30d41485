"""PNG pictures of a deformed mesh coloured by an element field (like the seed's figures).

- :func:`section_polygons` / :func:`plot_section`: the cut of the deformed mesh by a
  plane through the origin (a meridional section of the eye), each cut element drawn
  as a polygon coloured by its value;
- :func:`plot_outside`: the deformed outer boundary seen from a direction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eyefem.fem.mesh import HEX_FACES, boundary_faces
from eyefem.io.output import atomic_path

_HEX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                       [0, 4], [1, 5], [2, 6], [3, 7]])


def section_polygons(x, hexes, normal, values=None):
    """Polygons where the plane {p : p . normal = 0} cuts the elements.

    Args: x (n, 3) deformed positions; hexes (e, 8); normal (3,); values (e,) optional.
    Returns: list of (k, 3) polygons, the list of cut element ids.
    """
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    s = x @ normal
    se = s[hexes]
    cut = np.nonzero((se.min(1) < 0) & (se.max(1) > 0))[0]
    polys, ids = [], []
    for e in cut:
        pts = []
        for a, b in _HEX_EDGES:
            sa, sb = se[e, a], se[e, b]
            if (sa < 0) != (sb < 0):
                t = sa / (sa - sb)
                pts.append(x[hexes[e, a]] + t * (x[hexes[e, b]] - x[hexes[e, a]]))
        if len(pts) < 3:
            continue
        pts = np.array(pts)
        c = pts.mean(0)
        u = pts[0] - c
        u /= np.linalg.norm(u) + 1e-300
        v = np.cross(normal, u)
        ang = np.arctan2((pts - c) @ v, (pts - c) @ u)
        polys.append(pts[np.argsort(ang)])
        ids.append(e)
    return polys, np.array(ids, dtype=np.int64)


def _colormap(values, vmin, vmax, cmap="jet"):
    import matplotlib

    norm = matplotlib.colors.Normalize(vmin=vmin, vmax=vmax)
    return matplotlib.colormaps[cmap](norm(values)), norm


def plot_section(path: Path, x, hexes, values, *, normal=(0.0, 1.0, 0.0), axes=(0, 2),
                 label="von Mises stress, MPa", title="", vmax=None, highlight=None):
    """Meridional section coloured by an element field; written atomically as PNG.

    Args: x (n, 3) deformed node positions, mm; hexes (e, 8); values (e,); normal of the
    cutting plane through the origin; axes: which coordinates to draw (x=0, y=1, z=2);
    highlight: optional list of (polygon (k, 3), colour) overlays (e.g. rigid buckles).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    polys, ids = section_polygons(np.asarray(x), hexes, normal)
    vals = np.asarray(values)[ids]
    vmax = vmax if vmax is not None else float(np.percentile(vals, 99)) if len(vals) else 1.0
    colors, norm = _colormap(vals, 0.0, vmax)
    fig, ax = plt.subplots(figsize=(6.5, 6), dpi=130)
    pc = PolyCollection([p[:, axes] for p in polys], facecolors=colors, edgecolors="k",
                        linewidths=0.1)
    ax.add_collection(pc)
    for poly, col in highlight or []:
        ax.fill(poly[:, axes[0]], poly[:, axes[1]], color=col, alpha=0.6)
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel("xyz"[axes[0]] + ", mm")
    ax.set_ylabel("xyz"[axes[1]] + ", mm")
    sm = plt.cm.ScalarMappable(norm=norm, cmap="jet")
    fig.colorbar(sm, ax=ax, label=label, shrink=0.8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def plot_outside(path: Path, x, hexes, values, *, elev=10.0, azim=-60.0,
                 label="von Mises stress, MPa", title="", vmax=None):
    """Outside view of the deformed boundary coloured by the owning element's value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    faces = hexes[:, HEX_FACES].reshape(-1, 4)
    owner = np.repeat(np.arange(len(hexes)), 6)
    key = np.sort(faces, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    keep = cnt[inv.ravel()] == 1
    faces, owner = faces[keep], owner[keep]
    assert len(faces) == len(boundary_faces(hexes))
    vals = np.asarray(values)[owner]
    vmax = vmax if vmax is not None else float(np.percentile(vals, 99)) if len(vals) else 1.0
    colors, norm = _colormap(vals, 0.0, vmax)
    fig = plt.figure(figsize=(7, 6), dpi=130)
    ax = fig.add_subplot(projection="3d")
    pc = Poly3DCollection(np.asarray(x)[faces], facecolors=colors, edgecolors="k",
                          linewidths=0.05)
    ax.add_collection3d(pc)
    lo, hi = np.asarray(x).min(0), np.asarray(x).max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()
    sm = plt.cm.ScalarMappable(norm=norm, cmap="jet")
    fig.colorbar(sm, ax=ax, label=label, shrink=0.6)
    if title:
        ax.set_title(title)
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
