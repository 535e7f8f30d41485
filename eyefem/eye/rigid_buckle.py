"""The rigid buckle: an exact analytic ring (band, tire) or sponge surface that moves
radially (tightening) and along the meridian (shift), and the sutures that tie it down
(two tension-only bars each, from the bites to the buckle's edges)."""

from __future__ import annotations

import dataclasses

import numpy as np

from eyefem.eye.buckles import KINDS, SPONGE_LENGTH, suture_anchor_frame
from eyefem.eye.parts import SurgeryParts
from eyefem.eye.presets import SEED_MATERIALS
from eyefem.eye.sutures import generate_sutures
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
