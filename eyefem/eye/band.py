"""A deformable encircling band or tire on the eye (surgery ``buckle_body = "deformable"``),
and the helpers it shares with the deformable sponge (:mod:`eyefem.eye.sponge`).

The band (or the tire with its band, one silicone body: :func:`eyefem.eye.buckle_meshes.deformable_band`)
waits parked BAND_PARK mm off the sclera while the eye is pressurised, is fitted snug on
the pressurised eye when the cavity closes (its stress-free state), and is tightened in
one of two ways (case field ``deformable_tightening``):

- "pulled_ends": the band is cut at +y and its two ends are pulled past each other
  (the seed's displacement condition at the band ends, 6.1 stage 2);
- "shortened_loop": the band is a closed loop whose rest length is shortened
  (:class:`eyefem.fem.loop_solid.ShortenedLoopSolid`): what pulling the ends through a
  sleeve does to the loop, without the cut and the overlapping ends.

It is held by its contact on the sclera and weak springs on its rigid motion;
three-bar tension-only sutures tie it down in stage 3.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from eyefem.eye.buckle_meshes import deformable_band, ring_fit_groups
from eyefem.eye.sutures import generate_sutures, suture_bars
from eyefem.fem.bars import TiedBars
from eyefem.fem.contact import SurfaceContact
from eyefem.fem.mesh import merge
from eyefem.fem.terms import OrbitSpring
from eyefem.solve.model import Model, node_dofs

if TYPE_CHECKING:
    from eyefem.eye.parts import SurgeryParts

BAND_PARK = 0.3
"""Gap between the sclera and the deformable band while it waits for stage 2, mm."""
BAND_CLEARANCE = 4e-3
"""Gap of the band fitted snug on the pressurised eye over its outermost scleral node, mm."""
BAND_SPRING = (1e-2, 1e-3)
"""Weak springs on the band's rigid motion (its centre line's best-fit rotation, N mm/rad,
and mean lateral displacement, N/mm; eyefem.fem.terms.OrbitSpring), against a free drift
of the band before contact holds it. The band's material slides toward the pulled ends
(its mean displacement is about 0.5 mm at 5 mm of tightening), so the springs must be
this weak: their force (band_springs/force_N, about 5e-4 N) is then negligible next to
the band tension (about 0.3 N)."""
BAND_SMOOTHING = 2e-3
"""Smoothing length of the band's contact on the sclera, mm (SurfaceContact smoothing)."""
TIRE_SMOOTHING = 1e-2
"""Smoothing length of a deformable tire's contact on the sclera, mm: as the rigid ring's
(RING_SMOOTHING), for the touch-down of a ridged tire's base beside its ridge."""
BAND_OUTPUTS = ("band_tension_N", "band_loop_shortening_mm", "band_stretch_mm",
                "band_shortening_mm")


@dataclasses.dataclass
class BandInfo:
    """Node ids of a deformable band in the merged mesh: all (n,), end0 / end1 (k,) (the
    ends on the cut; on a closed loop both the cross-section at +y), mid-line inner nodes
    (m,) ordered around from end0 to end1."""

    nodes: np.ndarray
    end0: np.ndarray
    end1: np.ndarray
    line: np.ndarray
    n_circ: int
    closed: bool

    def __init__(self, mesh, n_circ, closed=False):
        self.nodes, self.n_circ, self.closed = mesh.node_set("band"), n_circ, closed
        self.end0, self.end1 = mesh.node_set("band/end0"), mesh.node_set("band/end1")
        line = np.intersect1d(mesh.node_set("band/mid"), mesh.node_set("band/inner"))
        X = mesh.nodes[line]
        ang = np.mod(np.arctan2(X[:, 1], X[:, 0]) - np.pi / 2, 2 * np.pi)  # from the cut (+y)
        if not closed:
            ang[np.isin(line, self.end1)] = 2 * np.pi
        self.line = line[np.argsort(ang, kind="stable")]


def with_band(eye_mesh, band_mesh, name="band"):
    """The eye mesh with the band (or another body) appended: the eye's sets keep their
    names, the band's get the prefix 'band/' (node set 'band': all its nodes)."""
    m = merge(("e", eye_mesh), (name, band_mesh))
    strip = lambda d: {(k[2:] if k.startswith("e/") else k): v for k, v in d.items() if k != "e"}
    return m.replace(node_sets=strip(m.node_sets), face_sets=strip(m.face_sets),
                     element_sets=strip(m.element_sets))


def fit_band(parts: SurgeryParts, scale: float, q):
    """The mesh with the band's reference moved snug onto the pressurised eye (state q):
    first onto the sphere of radius scale R + BAND_CLEARANCE, then each group of band
    nodes (:func:`eyefem.eye.buckle_meshes.ring_fit_groups`: a radial column, or a ridged
    tire's cross-section) moved radially so that its inner node closest to the (faceted)
    outer sclera lies BAND_CLEARANCE off it: the band's stress-free state, touching all
    around."""
    b, g, mesh, info = parts.buckle, parts.eye.geometry, parts.eye.mesh, parts.band
    band = deformable_band(b, g, scale * g.scleral_radius + BAND_CLEARANCE, info.n_circ,
                           closed=info.closed)
    groups = ring_fit_groups(b, info.n_circ, closed=info.closed)
    nodes = mesh.nodes.copy()
    nodes[info.nodes] = band.nodes
    inner = mesh.node_set("band/inner")
    q = np.asarray(q)
    for _ in range(3):
        m = mesh.replace(nodes=nodes)
        c = SurfaceContact("fit", m, "band/inner", "eye/sclera_outer",
                           normals=parts.p["contact_normals"]).update(q, None)
        gap, node, _ = c._gaps(q)
        if len(node) != len(inner):
            raise RuntimeError(f"fit_band: {len(inner) - len(node)} band nodes find no sclera "
                               "under them")
        shift = np.full(groups.max() + 1, -np.inf)
        np.maximum.at(shift, groups[node - info.nodes[0]], BAND_CLEARANCE - gap)
        if not np.all(np.isfinite(shift)):
            raise RuntimeError("fit_band: a group of band nodes has no inner node")
        X = nodes[info.nodes]
        nodes[info.nodes] += shift[groups][:, None] * X / np.linalg.norm(X, axis=1, keepdims=True)
    return mesh.replace(nodes=nodes)


def with_refitted_terms(model, mesh, terms: dict) -> Model:
    """The model on ``mesh`` (a buckle's reference refitted) with the solid and these terms
    new (name -> term)."""
    new = {"solid": dataclasses.replace(model.term("solid"), mesh=mesh), **terms}
    return Model(mesh, tuple(new.get(t.name, t) for t in model.terms), model.n_dof)


def three_bar_shortening(suture_tightening, n_sutures: int):
    """Shortening (3 n_sutures,), mm, of each bar of three-bar sutures over a deformable
    buckle, each loop shortened by ``suture_tightening`` mm (numpy or JAX): the two bite
    bars by half of it each, the bar over the buckle 0 (tied at its length)."""
    return np.tile([0.5, 0.0, 0.5], n_sutures) * suture_tightening


def three_bar_tightening(p) -> np.ndarray:
    """:func:`three_bar_shortening` of the case parameters p (suture_tightening, n_sutures)."""
    return three_bar_shortening(p["suture_tightening"], p["n_sutures"])


def band_dofs(parts: SurgeryParts) -> dict:
    """Prescribed band dofs: z of the centre-line nodes (holds its position across the
    globe and its tilt), x of the two ends (the cut is at +y, so x is along the band; a
    closed loop's cross-section at +y, held at x = 0 against its spin about the axis)."""
    mesh = parts.eye.mesh
    out = {"mid_z": node_dofs(mesh.node_set("band/mid"), "z"),
           "end0_x": node_dofs(parts.band.end0, "x")}
    if not parts.band.closed:
        out["end1_x"] = node_dofs(parts.band.end1, "x")
    return out


def tightened_band(parts: SurgeryParts, fixed: np.ndarray, tightening: float):
    """(prescribed dofs, values at the end of the tightening) of a deformable band or tire:
    its centre line held across the globe, and either its ends pulled past each other by
    tightening / 2 each (mm), or a closed loop's +y cross-section held along the loop (its
    rest length shortened by the param "shortening": eyefem.eye.bodies.DeformableRing.
    design_params)."""
    bd = band_dofs(parts)
    held = np.r_[fixed, bd["mid_z"]]
    if parts.band.closed:
        return np.r_[held, bd["end0_x"]], np.zeros(len(held) + len(bd["end0_x"]))
    half = 0.5 * tightening
    return (np.r_[held, bd["end0_x"], bd["end1_x"]],
            np.r_[np.zeros(len(held)), np.full(len(bd["end0_x"]), half),
                  np.full(len(bd["end1_x"]), -half)])


def band_spring_term(parts: SurgeryParts) -> OrbitSpring:
    """Weak springs on the band's rigid-body motion (BAND_SPRING)."""
    line = parts.band.line
    k_rot, k_trans = BAND_SPRING
    return OrbitSpring("band_springs", line, parts.eye.mesh.nodes[line], k_rot=(k_rot,) * 3,
                       k_trans=k_trans)


def band_contact_term(parts: SurgeryParts, sclera_c10: float) -> SurfaceContact:
    """Node-to-segment contact of the band's inner nodes (slave) on the outer sclera
    (master; its faces or their Nagata patches, the case's contact_normals); penalty from
    the sclera's Young's modulus; smoothing: the case's contact_smoothing, or automatic (BAND_SMOOTHING for a
    band, TIRE_SMOOTHING for a tire)."""
    eps = parts.p.get("contact_smoothing", 0.0) or (
        BAND_SMOOTHING if parts.buckle.kind == "band" else TIRE_SMOOTHING)
    return SurfaceContact("buckle", parts.eye.mesh, "band/inner", "eye/sclera_outer",
                          modulus=6 * sclera_c10, smoothing=eps,
                          normals=parts.p["contact_normals"])


def band_suture_term(parts: SurgeryParts) -> TiedBars:
    """Sutures over the deformable band: per suture three tension-only bars, bite A ->
    the band's outer face near edge A -> near edge B -> bite B (points embedded in the
    band's outer faces at +-0.45 of its width from the centre line)."""
    b, p, mesh = parts.buckle, parts.p, parts.eye.mesh
    cen, acr, nrm, _ = parts.frame
    layout = generate_sutures(mesh.nodes, mesh.face_set("eye/sclera_outer"), cen, acr, nrm,
                              width=p["suture_width"], angle_deg=p["suture_angle_deg"], n_bars=3,
                              buckle_faces=mesh.face_set("band/outer"),
                              buckle_half_width=0.45 * b.width)
    return suture_bars("sutures", layout, mesh.nodes, mesh.face_set("eye/sclera_outer"),
                       EA=p["suture_EA"], bite_radius=p["bite_radius"],
                       bite_length=p["bite_length"])


def band_outcomes(parts: SurgeryParts, model, q, theta) -> dict:
    """Band tension (N: the pull on end0; a closed loop's d(energy)/d(shortening)), loop
    shortening (2 pi x the drop of the mean cylindrical radius of its inner centre line
    since the snug fit, mm), its stretch (that line's length over its rest length: the
    snug fit's, less a closed loop's shortening, mm) and the prescribed shortening (end
    overlap, or the loop's rest length taken up, mm)."""
    mesh, info = model.mesh, parts.band  # the band's reference as refitted in stage 2
    d = band_dofs(parts)
    X = mesh.nodes[info.line]
    x = X + q[: 3 * mesh.n_nodes].reshape(-1, 3)[info.line]
    rho = lambda y: np.hypot(y[:, 0], y[:, 1]).mean()
    loop = (lambda y: np.vstack([y, y[:1]])) if info.closed else (lambda y: y)
    length = lambda y: np.linalg.norm(np.diff(loop(y), axis=0), axis=1).sum()
    if info.closed:
        tension = model.term("solid").tension(q, theta["solid"])
        shortening = float(theta["solid"]["shortening"])
    else:
        tension = float(model.gradient(q, theta, ("solid",))[d["end0_x"]].sum())
        shortening = float(q[d["end0_x"]].mean() - q[d["end1_x"]].mean())
    rest = length(X) - (shortening if info.closed else 0.0)  # the loop's rest length
    return {"band_tension_N": tension,
            "band_loop_shortening_mm": float(2 * np.pi * (rho(X) - rho(x))),
            "band_stretch_mm": float(length(x) - rest),
            "band_shortening_mm": shortening}
