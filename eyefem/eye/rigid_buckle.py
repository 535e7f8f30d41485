"""The rigid buckle: an exact analytic ring (band, tire) or sponge surface that moves
radially (tightening) and along the meridian (shift), and the sutures that tie it down
(two tension-only bars each, from the bites to the buckle's edges)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from eyefem.eye.buckles import KINDS, SPONGE_LENGTH, suture_anchor_frame
from eyefem.eye.parts import SurgeryParts, drained
from eyefem.eye.presets import SEED_MATERIALS
from eyefem.eye.sutures import generate_sutures, radial_bites
from eyefem.fem.bars import AnchoredBars, end_patches, reference_end_positions
from eyefem.fem.buckle_contact import BuckleContact


def suture_frame(parts: SurgeryParts, meridian_deg: float | None = None):
    """Centres, across directions and outward normals (n_sutures, 3) each of the sutures
    over the buckle; a segmental buckle turned to ``meridian_deg`` (default: its own)."""
    b = parts.buckle
    cen, acr, nrm, _ = parts.frame
    if meridian_deg is not None and meridian_deg != b.meridian_deg:
        turned = dataclasses.replace(b, meridian_deg=meridian_deg)
        cen, acr, nrm, _ = suture_anchor_frame(turned, parts.eye.geometry, parts.p["n_sutures"])
    return cen, acr, nrm


def suture_layout(parts: SurgeryParts, width: float, meridian_deg: float | None = None):
    """Bites of the sutures for a suture width (mm), on the reference outer sclera; a
    segmental buckle turned to ``meridian_deg`` (default: its own meridian)."""
    b, p, mesh = parts.buckle, parts.p, parts.eye.mesh
    cen, acr, nrm = suture_frame(parts, meridian_deg)
    return generate_sutures(mesh.nodes, mesh.face_set("eye/sclera_outer"), cen, acr, nrm,
                            width=width, angle_deg=p["suture_angle_deg"], n_bars=3,
                            buckle_half_width=b.width / 2)


def rigid_motion(parts: SurgeryParts, tightening, shift) -> dict:
    """The rigid buckle's motion params (numpy or JAX): radial d = tightening x d_per_mm
    (mm; encircling: the circumference shortened by ``tightening`` mm) and posterior shift
    s = ``shift`` (mm); the same for its suture anchors."""
    return {"d": tightening * parts.d_per_mm, "s": shift}


def rigid_design_params(parts: SurgeryParts, design) -> tuple[dict, dict]:
    """The params (term -> param -> scalar; numpy or JAX) the design (name -> value:
    tightening, buckle_shift, drain_volume, band_tension, suture_tightening) sets in the
    rigid buckle's tightening (or placing) stage - the buckle's and its anchors' motion
    (:func:`rigid_motion`), the drained volume (eyefem.eye.parts.drained), a pulled band's
    tension f (cases with band_tension > 0) - and in its suture stage: each bar of a
    two-bar loop shortened by suture_tightening / 2. The forward run
    (eyefem.eye.bodies.RigidBuckle) and the design map
    (eyefem.eye.simulators.SurgerySimulator.design_map) both read them from here."""
    motion = rigid_motion(parts, design["tightening"], design["buckle_shift"])
    tighten = {"buckle": motion, "sutures": motion, "cavity": drained(design["drain_volume"])}
    if parts.p["band_tension"] > 0:
        tighten["band_pull"] = {"f": design["band_tension"]}
    return tighten, {"sutures": {"tightening": design["suture_tightening"] / 2}}


@dataclasses.dataclass(frozen=True)
class BiteRays:
    """The suture bites of one layout as a function of the design (suture width, meridian).

    Bite i is where the ray from the globe centre through p_i = R_z(m - meridian_deg)
    (centres_i + side_i w/2 across_i) meets its face (eyefem.eye.sutures.radial_bites):
    w the suture width (mm), m the buckle's meridian (degrees; a segmental buckle turns
    about the eye's axis z, an encircling one does not), across_i the across direction
    turned by the suture angle.

    Attributes: centres, across (n, 3) at the layout's meridian; side (n,) -1 (bite A) or
    +1 (bite B); meridian_deg: the layout's; turns: whether the meridian turns the
    bites; faces_xyz (n, 4, 3) reference positions of each bite's face, mm; xi (n, 2) the
    layout's bites (Newton's start).
    """

    centres: np.ndarray
    across: np.ndarray
    side: np.ndarray
    meridian_deg: float
    turns: bool
    faces_xyz: np.ndarray
    xi: np.ndarray

    def xi_of(self, width, meridian_deg):
        """The bites' parametric coordinates (n, 2) at suture width ``width`` (mm) and
        meridian ``meridian_deg`` (degrees); JAX, differentiable in both."""
        p = self.centres + 0.5 * width * self.side[:, None] * self.across
        if self.turns:
            a = (meridian_deg - self.meridian_deg) * (np.pi / 180)
            c, s = jnp.cos(a), jnp.sin(a)
            p = jnp.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]], 1)
        return radial_bites(p, self.faces_xyz, self.xi)


def bite_rays(parts: SurgeryParts, width: float, meridian_deg: float) -> BiteRays:
    """The :class:`BiteRays` of the sutures laid out at ``width`` (mm) and ``meridian_deg``
    (the bites in the order of :func:`suture_term`: every bite A, then every bite B)."""
    layout = suture_layout(parts, width, meridian_deg)
    cen, acr, nrm = suture_frame(parts, meridian_deg)
    ang = np.radians(parts.p["suture_angle_deg"])
    a_rot = np.cos(ang) * acr + np.sin(ang) * np.cross(nrm, acr)
    n = len(cen)
    nodes = np.concatenate([layout.bite_a.nodes, layout.bite_b.nodes])
    return BiteRays(np.concatenate([cen, cen]), np.concatenate([a_rot, a_rot]),
                    np.repeat([-1.0, 1.0], n), float(meridian_deg),
                    not parts.buckle.encircling, parts.eye.mesh.nodes[nodes],
                    np.concatenate([layout.bite_a.xi, layout.bite_b.xi]))


def suture_term(parts: SurgeryParts, scale: float, width: float | None = None,
                meridian_deg: float | None = None):
    """Suture bars (AnchoredBars, tension-only) for the buckle fitted at radial scale
    ``scale``: from each bite to the buckle's edge on its side; the anchors move with the
    buckle (d inward, s posterior, dr: fitted radius; rot: turn about the eye axis).
    ``width``: suture width, mm (default: the case's); ``meridian_deg``: bites of the
    segmental buckle turned to that meridian (its anchors are turned by the param rot)."""
    eye, b, p = parts.eye, parts.buckle, parts.p
    g = eye.geometry
    cen, acr, nrm, _ = parts.frame
    mesh = eye.mesh
    layout = suture_layout(parts, p["suture_width"] if width is None else width, meridian_deg)
    R = g.scleral_radius * scale
    anchors, nodes_a, xi_a, d1, d2, d3 = [], [], [], [], [], []
    for side, sgn in ((layout.bite_a, -1.0), (layout.bite_b, 1.0)):
        if b.encircling:  # the tire is seated on its flat base; its ridge protrudes inward
            top = (R + b.thickness) * nrm + sgn * 0.5 * b.width * acr
            d1.append(-top / np.linalg.norm(top, axis=1, keepdims=True))
            d2.append(np.stack([meridian(t) for t in top]))
        else:
            n0, m0, _ = sponge_frame(parts)
            top = (R + b.width / 2) * nrm + sgn * 0.5 * b.width * acr
            d1.append(np.tile(-n0, (len(top), 1)))
            d2.append(np.tile(m0, (len(top), 1)))
        anchors.append(top)
        d3.append(nrm)  # d top / d R
        nodes_a.append(side.nodes)
        xi_a.append(side.xi)
    anchors, nodes_a, xi_a, d1, d2, d3 = (np.concatenate(v) for v in
                                          (anchors, nodes_a, xi_a, d1, d2, d3))
    patch = (end_patches(mesh.nodes, mesh.face_set("eye/sclera_outer"), nodes_a, xi_a, True,
                         p["bite_radius"], half_length=p["bite_length"] / 2 or None,
                         toward=anchors) if p["bite_radius"] else None)
    L0 = np.linalg.norm(anchors - reference_end_positions(mesh.nodes, nodes_a, xi_a, patch), axis=1)
    return AnchoredBars("sutures", nodes_a, xi_a, anchors, np.zeros(len(anchors), int), d1, d2,
                        1, mesh.nodes, L0, EA=p["suture_EA"], tension_only=True,
                        extra_dof=parts.extra_dof, dirs3=d3, patch=patch)


def meridian(x):
    """Unit meridian tangent (toward the posterior) at x (3,)."""
    r = np.linalg.norm(x)
    th, ph = np.arccos(x[2] / r), np.arctan2(x[1], x[0])
    return np.array([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)])


def sponge_frame(parts: SurgeryParts):
    """Sponge centre direction n0, meridian tangent m0 and axis (3,) each."""
    b, g = parts.buckle, parts.eye.geometry
    th, ph = b.centre_angle(g), np.radians(b.meridian_deg)
    n0 = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    m0 = np.array([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)])
    e0 = np.array([-np.sin(ph), np.cos(ph), 0.0])
    return n0, m0, (m0 if b.kind == "sponge_radial" else e0)


RING_SMOOTHING, SPONGE_SMOOTHING = 0.01, 0.002
"""Automatic buckle contact smoothing lengths, mm (case field contact_smoothing = 0)."""


def contact_smoothing(parts: SurgeryParts) -> float:
    """The buckle contact's smoothing length eps, mm (docs/surgery.md)."""
    eps = parts.p["contact_smoothing"]
    if eps:
        return eps
    return RING_SMOOTHING if parts.buckle.encircling else SPONGE_SMOOTHING


def buckle_term(parts: SurgeryParts, scale: float) -> BuckleContact:
    """The analytic buckle contact fitted at radial scale ``scale``."""
    b, g = parts.buckle, parts.eye.geometry
    R = g.scleral_radius * scale
    w, _, ridge, rw = KINDS[b.kind]
    if b.encircling:
        return BuckleContact("buckle", parts.eye.mesh, "eye/sclera_outer", "ring", R,
                             theta_b=b.centre_angle(g), width=w, ridge=ridge, ridge_width=rw,
                             ridge_flank=parts.p["ridge_flank"],
                             edge_width=parts.p["buckle_edge"],
                             modulus=6 * SEED_MATERIALS["sclera"], extra_dof=parts.extra_dof,
                             smoothing=contact_smoothing(parts),
                             quadrature=parts.p["contact_quadrature"])
    n0, m0, ax = sponge_frame(parts)
    return BuckleContact("buckle", parts.eye.mesh, "eye/sclera_outer", "sponge", R,
                         n0=tuple(n0), m0=tuple(m0), axis=tuple(ax), sponge_radius=w / 2,
                         sponge_length=SPONGE_LENGTH, modulus=6 * SEED_MATERIALS["sclera"],
                         extra_dof=parts.extra_dof, curved=b.kind == "sponge_radial",
                         smoothing=contact_smoothing(parts),
                         quadrature=parts.p["contact_quadrature"],
                         end_width=parts.p["sponge_end"])
