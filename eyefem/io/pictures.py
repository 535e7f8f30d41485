"""PNG pictures of a deformed mesh coloured by an element field, with what acts on it.

- :func:`section_polygons` / :func:`section_segments`: the cut of elements / surface
  polygons by a plane through the origin (a meridional section of the eye);
- :func:`plot_section`: the section coloured by an element field, with the undeformed
  outline (dashed), a rigid buckle's section curve, the sutures near the plane, and a
  zoomed panel at the buckle with a radial dimension (the indentation) marked;
- :func:`plot_outside`: the deformed outer boundary seen from a direction, with the
  buckle surface, the sutures on the visible side and an orientation triad.

Colours: a perceptual colormap (viridis by default); the scale runs from ``vmin`` to the
true maximum of the drawn values unless ``vmax`` clips it, and then the colour bar has an
extend arrow. Elements in ``exclude`` (a deformable buckle, whose stress is orders of
magnitude above the eye's) are drawn grey, outside the colour scale. matplotlib only
(Agg backend, no display needed).

Length: the two views share the colour scale, colour bar, title wrapping, saving and
the buckle and suture drawing, so they stay in one module (about 500 lines).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from eyefem.fem.mesh import HEX_FACES
from eyefem.io.output import atomic_path

_HEX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                       [0, 4], [1, 5], [2, 6], [3, 7]])
BUCKLE_COLOUR = "#c0392b"
BUCKLE_FILL = "#efc4bf"
SUTURE_COLOUR = "#ff7f0e"
EXCLUDED_COLOUR = "0.72"


@dataclasses.dataclass(frozen=True)
class Zoom:
    """A zoomed panel of a section around ``centre`` with a radial dimension marked.

    Attributes: centre (3,) mm, the point to zoom on (on the buckle); half_size, mm, half
    the panel's width; r_inner, r_outer: radii (mm, from the origin) between which a double
    arrow is drawn along the direction of ``centre`` (the indentation: the sclera's radius
    under the buckle and beside it), none if either is None; label: its text.
    """

    centre: tuple
    half_size: float = 7.0
    r_inner: float | None = None
    r_outer: float | None = None
    label: str = ""


@dataclasses.dataclass(frozen=True)
class Drawn:
    """What a plot function drew: the PNG path, the colour scale (vmin, vmax; data_max the
    true maximum of the coloured values; extend 'max' where vmax clips it), the title and
    the counts of buckle segments / triangles and suture lines drawn."""

    path: Path
    vmin: float
    vmax: float
    data_max: float
    extend: str
    title: str
    n_buckle: int
    n_sutures: int


def plane_basis(normal):
    """Unit in-plane axes (e1, e2) of the plane with this normal: e1 = n x z (horizontal),
    e2 = e1 x n (z for a meridional plane); e1 = x for a plane normal to z."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.cross(n, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-9:
        e1 = np.array([1.0, 0.0, 0.0]) - n[0] * n
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(e1, n)


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


def section_segments(x, polygons, normal):
    """Segments where the plane {p : p . normal = 0} cuts surface polygons.

    Args: x (n, 3) positions, mm; polygons (k, m) node ids (triangles m = 3, quads m = 4;
    split into triangles); normal (3,). Returns (s, 2, 3) segment end points, mm.
    """
    x, poly = np.asarray(x, float), np.asarray(polygons, np.int64)
    if not len(poly):
        return np.zeros((0, 2, 3))
    tris = np.concatenate([poly[:, [0, i, i + 1]] for i in range(1, poly.shape[1] - 1)])
    s = x @ (np.asarray(normal, float) / np.linalg.norm(normal))
    st = s[tris]
    tris = tris[(st.min(1) < 0) & (st.max(1) >= 0)]
    st = s[tris]
    ends = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        sa, sb = st[:, a], st[:, b]
        cross = (sa < 0) != (sb < 0)
        t = np.where(cross, sa / np.where(cross, sa - sb, 1.0), 0.0)
        p = x[tris[:, a]] + t[:, None] * (x[tris[:, b]] - x[tris[:, a]])
        ends.append((cross, p))
    segs = []
    for (c1, p1), (c2, p2) in ((ends[0], ends[1]), (ends[1], ends[2]), (ends[0], ends[2])):
        both = c1 & c2
        segs.append(np.stack([p1[both], p2[both]], 1))
    return np.concatenate(segs)


def boundary_quads(hexes):
    """(f, 4) faces of the hexes (e, 8) that belong to one element only, and their owner
    element ids (f,)."""
    faces = np.asarray(hexes)[:, HEX_FACES].reshape(-1, 4)
    owner = np.repeat(np.arange(len(hexes)), 6)
    _, inv, cnt = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True,
                            return_counts=True)
    keep = cnt[inv.ravel()] == 1
    return faces[keep], owner[keep]


def _scale(values, vmin, vmax, cmap):
    """Colours (k, 4), the Normalize, the true maximum and the colour bar's extend."""
    import matplotlib

    values = np.asarray(values, float)
    finite = values[np.isfinite(values)]
    data_max = float(finite.max()) if len(finite) else 1.0
    top = data_max if vmax is None else float(vmax)
    top = top if top > vmin else vmin + 1.0
    norm = matplotlib.colors.Normalize(vmin=vmin, vmax=top)
    extend = "max" if data_max > top * (1 + 1e-12) else "neither"
    return matplotlib.colormaps[cmap](norm(values)), norm, data_max, extend


def _colorbar(fig, norm, cmap, label, extend, data_max, **kw):
    import matplotlib.pyplot as plt

    sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    note = f" (max {data_max:.3g}, clipped)" if extend == "max" else ""
    return fig.colorbar(sm, label=label + note, extend=extend, **kw)


def _wrapped(title: str, width: int) -> str:
    """The title with each of its lines wrapped at ``width`` characters."""
    import textwrap

    return "\n".join(textwrap.fill(line, width) for line in title.splitlines())


def _save(fig, path):
    import matplotlib.pyplot as plt

    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _near_lines(lines, normal, near):
    """The (2, 3) suture lines whose midpoint lies within ``near`` mm of the plane, and
    their forces."""
    if lines is None or not len(lines[0]):
        return np.zeros((0, 2, 3)), np.zeros(0)
    pts, cells, force = lines
    seg = np.asarray(pts)[np.asarray(cells)]
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    ok = np.abs(seg.mean(1) @ n) < near
    return seg[ok], np.asarray(force)[ok]


def _draw_section(ax, proj, polys, colours, excluded, outline, buckle_segs, sutures,
                  body=(), lw_scale=1.0):
    from matplotlib.collections import LineCollection, PolyCollection

    ax.add_collection(PolyCollection([proj(p) for p in polys], facecolors=colours,
                                     edgecolors="k", linewidths=0.1 * lw_scale))
    if excluded:
        ax.add_collection(PolyCollection([proj(p) for p in excluded],
                                         facecolors=EXCLUDED_COLOUR, edgecolors="0.4",
                                         linewidths=0.2 * lw_scale, hatch="///"))
    if len(outline):
        ax.add_collection(LineCollection(proj(outline), colors="0.25", linestyles=(0, (4, 3)),
                                         linewidths=0.7 * lw_scale))
    if len(body):
        ax.add_collection(PolyCollection(list(proj(body)), facecolors=BUCKLE_FILL,
                                         edgecolors=BUCKLE_FILL, linewidths=0.5, zorder=0.9))
    if len(buckle_segs):
        ax.add_collection(LineCollection(proj(buckle_segs), colors=BUCKLE_COLOUR,
                                         linewidths=2.2 * lw_scale, capstyle="round"))
    if len(sutures[0]):
        ax.add_collection(LineCollection(proj(sutures[0]), colors=SUTURE_COLOUR,
                                         linewidths=1.6 * lw_scale))


def plot_section(path: Path, x, hexes, values, *, normal=(0.0, 1.0, 0.0), axes=None,
                 label="von Mises stress, MPa", title="", vmin=0.0, vmax=None,
                 cmap="viridis", reference=None, exclude=None, exclude_label="excluded",
                 buckle=None, buckle_thickness=0.0, buckle_tube=False, sutures=None, near=3.0,
                 zoom: Zoom | None = None,
                 xlabel=None, ylabel=None, highlight=None) -> Drawn:
    """Section of the deformed mesh by the plane normal . p = 0, coloured by an element
    field; written atomically as PNG.

    Args:
      x: (n, 3) deformed node positions, mm; hexes (e, 8); values (e,) element field.
      normal: normal of the cutting plane through the origin.
      axes: coordinates drawn, e.g. (0, 2) for x and z; None: the plane's own axes
        (:func:`plane_basis`: horizontal n x z and vertical z).
      vmin, vmax: colour scale; vmax None: the true maximum of the cut elements' values.
      reference: (n, 3) undeformed positions: their outline is drawn dashed.
      exclude: element ids drawn grey (hatched) outside the colour scale (a deformable
        buckle), named ``exclude_label`` in the legend.
      buckle: (points (m, 3), triangles (k, 3)) a rigid buckle's contact surface, drawn
        as its section curve and, with ``buckle_thickness`` (mm) > 0, the body of a ring
        (encircling) buckle shaded up to its outer face (:func:`_ring_body`); with
        ``buckle_tube`` the region between its inner and outer section arcs (a sponge cut
        along its axis) shaded.
      sutures: (points (2s, 3), lines (s, 2), force_N (s,)) drawn, projected on the
        plane, where their midpoint lies within ``near`` mm of it.
      zoom: a zoomed panel at the buckle with the indentation marked (:class:`Zoom`).
      highlight: list of (polygon (k, 3), colour) filled overlays.
    Returns: :class:`Drawn`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    x, hexes = np.asarray(x, float), np.asarray(hexes)
    if axes is None:
        e1, e2 = plane_basis(normal)
        basis = np.stack([e1, e2], 1)
        xlabel = xlabel or "in-plane horizontal, mm"
        ylabel = ylabel or "z, mm"
    else:
        basis = np.eye(3)[:, list(axes)]
        xlabel = xlabel or "xyz"[axes[0]] + ", mm"
        ylabel = ylabel or "xyz"[axes[1]] + ", mm"

    def proj(p):
        return np.asarray(p) @ basis

    polys, ids = section_polygons(x, hexes, normal)
    skip = np.isin(ids, np.asarray(exclude if exclude is not None else [], np.int64))
    coloured = [p for p, s in zip(polys, skip, strict=True) if not s]
    excluded = [p for p, s in zip(polys, skip, strict=True) if s]
    vals = np.asarray(values, float)[ids[~skip]]
    colours, norm, data_max, extend = _scale(vals, vmin, vmax, cmap)
    outline = (section_segments(reference, boundary_quads(hexes)[0], normal)
               if reference is not None else np.zeros((0, 2, 3)))
    buckle_segs = (section_segments(buckle[0], buckle[1], normal) if buckle is not None
                   else np.zeros((0, 2, 3)))
    near_sutures = _near_lines(sutures, normal, near)

    fig = plt.figure(figsize=(11.5, 6.2) if zoom else (7.2, 6.2), dpi=130)
    ax = fig.add_axes([0.07, 0.1, 0.5, 0.74] if zoom else [0.1, 0.1, 0.66, 0.74])
    body = (_tube_body(buckle_segs, proj) if buckle_tube else
            _ring_body(buckle_segs, buckle_thickness, basis[:, 0] if axes is None else None))
    drawn = (coloured, colours, excluded, outline, buckle_segs, near_sutures, body)
    _draw_section(ax, proj, *drawn)
    for poly, col in highlight or []:
        p2 = proj(poly)
        ax.fill(p2[:, 0], p2[:, 1], color=col, alpha=0.6)
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    handles = []
    if len(outline):
        handles.append(Line2D([], [], color="0.25", ls=(0, (4, 3)), lw=0.9, label="undeformed"))
    if len(buckle_segs):
        handles.append(Patch(facecolor=BUCKLE_FILL, edgecolor=BUCKLE_COLOUR, lw=1.5,
                             label="buckle") if len(body) else
                       Line2D([], [], color=BUCKLE_COLOUR, lw=2.2, label="buckle"))
    if len(near_sutures[0]):
        handles.append(Line2D([], [], color=SUTURE_COLOUR, lw=1.6,
                              label=f"sutures (max {near_sutures[1].max():.2f} N)"))
    if excluded:
        handles.append(Patch(facecolor=EXCLUDED_COLOUR, edgecolor="0.4", hatch="///",
                             label=exclude_label))
    if handles:
        ax.legend(handles=handles, loc="lower left", fontsize=7.5, framealpha=0.85)
    if zoom is not None:
        _zoom_panel(fig, ax, proj, zoom, drawn)
        cax = fig.add_axes([0.62, 0.1, 0.33, 0.03])
        _colorbar(fig, norm, cmap, label, extend, data_max, cax=cax, orientation="horizontal")
    else:
        cax = fig.add_axes([0.8, 0.15, 0.03, 0.62])
        _colorbar(fig, norm, cmap, label, extend, data_max, cax=cax)
    if title:
        fig.suptitle(_wrapped(title, 140 if zoom else 80), fontsize=10)
    _save(fig, path)
    return Drawn(Path(path), float(norm.vmin), float(norm.vmax), data_max, extend, title,
                 len(buckle_segs), len(near_sutures[0]))


def _ring_body(segs, thickness, e1):
    """(k, 4, 3) quads between a ring buckle's section segments (k, 2, 3) and its outer
    face: the arc at the radius of the section's outermost point + thickness (mm), on
    each side (sign of p . e1; e1 None: one side)."""
    if not len(segs) or thickness <= 0:
        return np.zeros((0, 4, 3))
    r = np.linalg.norm(segs, axis=2, keepdims=True)
    side = np.ones(len(segs), bool) if e1 is None else segs.mean(1) @ e1 > 0
    top = np.where(side, r[side].max() if side.any() else 0.0,
                   r[~side].max() if (~side).any() else 0.0)
    out = segs / np.maximum(r, 1e-9) * (top[:, None, None] + thickness)
    return np.concatenate([segs, out[:, ::-1]], 1)


def _tube_body(segs, proj):
    """(1, k, 3) polygon between the inner and outer arcs of a tube's section (the
    segments' end points nearer to / farther from the origin than their mid radius),
    each ordered by polar angle in the drawing plane."""
    if not len(segs):
        return np.zeros((0, 4, 3))
    pts = np.unique(np.round(segs.reshape(-1, 3), 9), axis=0)
    r = np.linalg.norm(pts, axis=1)
    inner = r < (r.min() + r.max()) / 2
    p2 = proj(pts)
    ang = np.arctan2(p2[:, 1], p2[:, 0])
    a, b = pts[inner][np.argsort(ang[inner])], pts[~inner][np.argsort(-ang[~inner])]
    return np.concatenate([a, b])[None]


def _zoom_panel(fig, ax, proj, zoom: Zoom, drawn):
    """The zoomed panel at zoom.centre, boxed on the main axes, with the dimension."""
    axz = fig.add_axes([0.62, 0.24, 0.33, 0.6])
    _draw_section(axz, proj, *drawn, lw_scale=1.8)
    c = proj(np.asarray(zoom.centre, float))
    h = zoom.half_size
    axz.set_xlim(c[0] - h, c[0] + h)
    axz.set_ylim(c[1] - h, c[1] + h)
    axz.set_aspect("equal")
    axz.tick_params(labelsize=7)
    axz.set_title("at the buckle", fontsize=9)
    ax.indicate_inset_zoom(axz, edgecolor="0.2")
    if zoom.r_inner is None or zoom.r_outer is None:
        return
    u3 = np.asarray(zoom.centre, float) / np.linalg.norm(zoom.centre)
    u = proj(u3)
    u /= np.linalg.norm(u)
    a, b = zoom.r_inner * u, zoom.r_outer * u
    axz.annotate("", xy=a, xytext=b, arrowprops={
        "arrowstyle": "<|-|>", "color": "k", "lw": 1.2, "shrinkA": 0, "shrinkB": 0,
        "mutation_scale": 9})
    ang = np.arctan2(u[1], u[0])  # the sclera's level beside the buckle: a dotted arc
    span = 1.3 * h / zoom.r_outer
    arc = np.linspace(ang - span, ang + span, 60)
    axz.plot(zoom.r_outer * np.cos(arc), zoom.r_outer * np.sin(arc), ":", color="k", lw=1.0,
             label="sclera beside the buckle\n(mean radius)")
    axz.legend(loc="lower right", fontsize=7, framealpha=0.85)
    if zoom.label:
        side = np.array([-u[1], u[0]])
        axz.annotate(zoom.label, xy=(a + b) / 2, xytext=(a + b) / 2 + 0.6 * h * u
                     + 0.15 * h * side, fontsize=9, ha="center", va="center",
                     bbox={"boxstyle": "round", "fc": "w", "ec": "0.5", "alpha": 0.9},
                     arrowprops={"arrowstyle": "-", "color": "0.3", "lw": 0.8})


def plot_outside(path: Path, x, hexes, values, *, elev=10.0, azim=-60.0,
                 label="von Mises stress, MPa", title="", vmin=0.0, vmax=None,
                 cmap="viridis", exclude=None, exclude_label="excluded from the colour scale",
                 buckle=None, buckle_lift=None, sutures=None, directions=None) -> Drawn:
    """Outside view of the deformed boundary coloured by the owning element's value.

    Args:
      x: (n, 3) deformed positions, mm; hexes (e, 8); values (e,).
      elev, azim: the view (degrees, matplotlib's convention).
      vmin, vmax: colour scale; vmax None: the true maximum of the drawn faces' values.
      exclude: element ids whose faces are grey, outside the colour scale, named
        ``exclude_label`` in the legend.
      buckle: (points (m, 3), triangles (k, 3)) a rigid buckle's contact surface; with
        ``buckle_lift`` (mm; a ring's thickness) not None its points are moved radially
        to the radius of its outermost point + buckle_lift (a ring's outer face).
      sutures: (points (2s, 3), lines (s, 2), force_N (s,)): those on the visible side.
      directions: name -> (3,) unit vector of the orientation triad (default x, y, z).
    Returns: :class:`Drawn`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    x, hexes = np.asarray(x, float), np.asarray(hexes)
    faces, owner = boundary_quads(hexes)
    grey = np.isin(owner, np.asarray(exclude if exclude is not None else [], np.int64))
    colours = np.empty((len(faces), 4))
    rgba, norm, data_max, extend = _scale(np.asarray(values, float)[owner[~grey]], vmin, vmax,
                                          cmap)
    colours[~grey] = rgba
    colours[grey] = matplotlib.colors.to_rgba(EXCLUDED_COLOUR)
    polys = list(x[faces])
    face_colours = list(colours)
    n_buckle = 0
    if buckle is not None:
        bp = np.asarray(buckle[0], float)
        if buckle_lift is not None:  # a ring: its outer face
            r = np.maximum(np.linalg.norm(bp, axis=1), 1e-9)[:, None]
            bp = bp / r * (r.max() + buckle_lift)
        tris = np.asarray(buckle[1])
        polys += list(bp[tris])
        face_colours += [matplotlib.colors.to_rgba(BUCKLE_COLOUR)] * len(tris)
        n_buckle = len(tris)
    fig = plt.figure(figsize=(7.5, 6.5), dpi=130)
    ax = fig.add_axes([0.0, 0.0, 0.82, 0.86], projection="3d")
    ax.computed_zorder = False  # the sutures over the surface (only the visible side's)
    edges = [(0.0, 0.0, 0.0, 1.0)] * len(faces) + face_colours[len(faces):]
    # autolim=False: the limits are set below from x (autoscaling from the collections
    # starts at matplotlib's infinite initial limits and can overflow)
    ax.add_collection3d(Poly3DCollection(polys, facecolors=face_colours, edgecolors=edges,
                                         linewidths=0.05), autolim=False)
    view = np.array([np.cos(np.radians(elev)) * np.cos(np.radians(azim)),
                     np.cos(np.radians(elev)) * np.sin(np.radians(azim)),
                     np.sin(np.radians(elev))])
    n_sut = 0
    if sutures is not None and len(sutures[0]):
        seg = np.asarray(sutures[0], float)[np.asarray(sutures[1])]
        seg = seg[seg.mean(1) @ view > 0]
        seg = seg * (1 + 0.3 / np.linalg.norm(seg, axis=2))[..., None]  # off the sclera
        if len(seg):  # an empty collection autoscales the axes from infinite limits
            ax.add_collection3d(Line3DCollection(seg, colors=SUTURE_COLOUR, linewidths=1.8,
                                                 zorder=10), autolim=False)
        n_sut = len(seg)
    lo, hi = x.min(0), x.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()
    _triad(fig, elev, azim, directions or {"+x": (1, 0, 0), "+y": (0, 1, 0), "+z": (0, 0, 1)})
    handles = []
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    if n_buckle:
        handles.append(Patch(color=BUCKLE_COLOUR, label="buckle"))
    if n_sut:
        handles.append(Line2D([], [], color=SUTURE_COLOUR, lw=1.8, label="sutures (visible side)"))
    if grey.any():
        handles.append(Patch(color=EXCLUDED_COLOUR, label=exclude_label))
    if handles:
        ax.legend(handles=handles, loc="upper left", fontsize=8, framealpha=0.85)
    cax = fig.add_axes([0.84, 0.2, 0.03, 0.55])
    _colorbar(fig, norm, cmap, label, extend, data_max, cax=cax)
    if title:
        fig.suptitle(_wrapped(title, 85), fontsize=10)
    _save(fig, path)
    return Drawn(Path(path), float(norm.vmin), float(norm.vmax), data_max, extend, title,
                 n_buckle, n_sut)


def _triad(fig, elev, azim, directions):
    """A small 3-D axes in the lower left corner with labelled arrows, seen like the
    main view."""
    ax = fig.add_axes([0.01, 0.01, 0.22, 0.22], projection="3d")
    for (name, d), col in zip(directions.items(), ("#1b9e77", "#7570b3", "#d95f02", "k")):
        d = np.asarray(d, float) / np.linalg.norm(d)
        ax.quiver(0, 0, 0, *d, color=col, lw=1.5, arrow_length_ratio=0.25)
        ax.text(*(1.12 * d), " " + name, color=col, fontsize=7.5, ha="left", va="bottom")
    for lim in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
        lim(-1, 1)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()
