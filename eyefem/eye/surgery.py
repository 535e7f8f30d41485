"""Scleral buckling surgery (seed 6.1, 6.2): the eye model, a buckle, sutures, staged.

Stages:
  1. ``pressurise``: surface pressure to the IOP (15 mmHg) on the wetted surface (wall
     inside and lens), the cavity open;
  2. ``tighten`` (encircling) or ``place`` (segmental): the cavity is closed at that
     pressure and volume (P_ini, V_ini); the buckle is fitted snug on the pressurised
     eye, then its rigid segments move radially by d = tightening / (2 pi) (the band
     circumference shortened by ``tightening`` mm); optional drainage of fluid;
  3. ``suture``: the sutures (bite -> buckle edge, tension-only bars) are tied at their
     current length, then each bar is shortened by ``suture_tightening / 2`` mm.

The design (tightening, suture width, buckle shift along the meridian, suture
tightening) maps onto term params (``design_theta``), so the adjoint gives gradients of
the outcomes with respect to it.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from eyefem.eye.band import (
    BAND_OUTPUTS,
    BAND_PARK,
    BandInfo,
    band_contact_term,
    band_outcomes,
    band_spring_term,
    band_suture_term,
    fit_band,
    rereference,
    three_bar_tightening,
    tightened_band,
    with_band,
    with_refitted_terms,
)
from eyefem.eye.buckle_meshes import (
    BAND_C10,
    RING_KINDS,
    SPONGE_C10,
    TIRE_C10,
    band_n_circ,
    deformable_band,
)
from eyefem.eye.buckles import KINDS, SPONGE_LENGTH, Buckle, suture_anchor_frame
from eyefem.eye.eyemodel import LEVELS, EyeGeometry, axial_length, build_eye
from eyefem.eye.parts import SurgeryParts
from eyefem.eye.sponge import (
    SPONGE_PARK,
    fit_sponge,
    sponge_contact_term,
    sponge_mesh,
    sponge_spring_term,
    sponge_suture_term,
)
from eyefem.eye.sutures import generate_sutures
from eyefem.fem.bars import AnchoredBars, Bars
from eyefem.fem.buckle_contact import BuckleContact
from eyefem.fem.cavity import WATER_BULK, FluidCavity, close_cavity
from eyefem.fem.loop_solid import ShortenedLoopSolid
from eyefem.fem.materials import MooneyRivlin
from eyefem.fem.surface import PressureLoad
from eyefem.fem.terms import DofForce, NodeSprings, OrbitSpring
from eyefem.fem.units import MMHG
from eyefem.io.casefile import Field, positive
from eyefem.io.output import write_csv
from eyefem.io.runner import Setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage

log = logging.getLogger(__name__)

SEED_MATERIALS = {  # neo-Hookean c (MPa), seed 6.1; limbus: mean of cornea and sclera
    "cornea": 0.0333, "limbus": 0.0583, "sclera": 0.0833, "ciliary_body": 0.01,
    "choroid": 0.0083, "retina": 0.0008, "optic_nerve": 0.05, "lens": 10.0}

BODIES = ("rigid", "deformable")
"""Buckle bodies: the rigid analytic surface, or a deformable hexahedral band, tire (with
its band) or radial sponge."""

TIGHTENINGS = ("pulled_ends", "shortened_loop")
"""How a deformable band or tire is tightened (eyefem.eye.band)."""

SURGERY_FIELDS = [
    Field("mesh", str, "default", f"eye mesh level: {', '.join(LEVELS)}", lambda v: v in LEVELS,
          f"one of {list(LEVELS)}"),
    Field("buckle", str, "tire_flat", f"buckle kind: {', '.join(KINDS)}", lambda v: v in KINDS,
          f"one of {list(KINDS)}"),
    Field("buckle_body", str, "rigid", "'rigid' (exact analytic surface, radial motion) or "
          "'deformable' (hexahedral silicone band, or tire with its band, tightened as "
          "deformable_tightening says: buckle = 'band', 'tire_flat', 'tire_ridged'; or "
          "hexahedral radial sponge "
          "sewn on: buckle = 'sponge_radial')",
          lambda v: v in BODIES, f"one of {list(BODIES)}"),
    Field("buckle_distance", float, 12.0, "buckle centre behind the limbus (arc), mm "
          "(position A = 12, B = 15)", lambda v: 2 <= v <= 20, "2 to 20 mm"),
    Field("buckle_meridian_deg", float, 0.0, "meridian of a segmental buckle, degrees"),
    Field("buckle_shift", float, 0.0, "extra posterior shift of the fitted buckle, mm "
          "(a differentiable design variable)"),
    Field("tightening", float, 5.0, "band circumference shortening, mm (weak 5, strong 10; "
          "segmental: radial push of the sponge x 2 pi)", lambda v: 0 <= v <= 30, "0 to 30 mm"),
    Field("deformable_tightening", str, "shortened_loop", "how a deformable band or tire is "
          "tightened: 'pulled_ends' (cut at +y, its ends pulled past each other by tightening / 2 "
          "each: the seed's displacement condition at the band ends) or 'shortened_loop' (a "
          "closed loop whose rest length is shortened by tightening: the loop a pull through "
          "the sleeve leaves, without the cut)", lambda v: v in TIGHTENINGS,
          f"one of {list(TIGHTENINGS)}"),
    Field("band_tension", float, 0.0, "encircling band pulled with this tension instead of a "
          "prescribed shortening (then tightening must be 0), N; 0: shortening prescribed",
          lambda v: v >= 0, ">= 0"),
    Field("suture_width", float, 9.0, "bite span across the buckle, mm", positive, "> 0"),
    Field("n_sutures", int, 8, "number of sutures", positive, ">= 1"),
    Field("suture_angle_deg", float, 0.0, "suture angle about the buckle normal, degrees"),
    Field("suture_tightening", float, 0.6, "shortening of each suture loop when tied, mm "
          "('the same suture tension' in every case)", lambda v: v >= 0, ">= 0"),
    Field("suture_EA", float, 40.0, "suture axial stiffness E*A, N (5-0 polyester ~ 40)",
          positive, "> 0"),
    Field("iop_mmhg", float, 15.0, "pre-operative IOP, mmHg", positive, "> 0"),
    Field("liquid_bulk", float, WATER_BULK, "liquid bulk modulus, MPa", positive, "> 0"),
    Field("drain_volume", float, 0.0, "fluid drained during stage 2, mm^3 (= uL)",
          lambda v: v >= 0, ">= 0"),
    Field("zonule_E", float, 100.0, "zonule Young's modulus, MPa", positive, "> 0"),
    Field("globe_torsion", float, 7.0, "the orbit's hold on the globe's torsion about the "
          "optical axis (extraocular muscles, Tenon's capsule), N mm/rad; 0: the nerve stub "
          "alone", lambda v: v >= 0, ">= 0"),
    Field("globe_rotation", float, 70.0, "the hold on the globe's rotation about the x and y "
          "axes during surgery (rectus traction sutures, extraocular muscles), N mm/rad; "
          "0: the nerve stub alone", lambda v: v >= 0, ">= 0"),
    Field("globe_translation", float, 1.0, "the orbit's hold on the globe's lateral (x, y) "
          "translation (orbital fat, Tenon's capsule), N/mm; 0: the nerve stub alone",
          lambda v: v >= 0, ">= 0"),
    Field("globe_axial", float, 0.0, "the orbit's hold on the globe's axial (z) translation, "
          "N/mm; 0: the nerve stub alone (the deformable band's and flat tire's case files set 1)",
          lambda v: v >= 0, ">= 0"),
    Field("steps_pressurise", int, 2, "load steps of stage 1", positive, ">= 1"),
    Field("steps_tighten", int, 8, "load steps of stage 2", positive, ">= 1"),
    Field("steps_suture", int, 3, "load steps of stage 3", positive, ">= 1"),
    Field("contact_smoothing", float, 0.0, "buckle contact smoothing length eps, mm: the "
          "penalty acts on eps softplus(-gap / eps) (larger: a softer touch-down, easier "
          "Newton steps, a stand-off of about eps); 0: automatic, 0.01 mm for an encircling "
          "buckle, 0.002 mm for a sponge (whose indentation is ten times smaller) and for a "
          "deformable band (0.01 mm for a deformable tire)",
          lambda v: v == 0 or 1e-4 <= v <= 0.1, "0 (automatic) or 1e-4 to 0.1 mm"),
    Field("contact_normals", str, "facet", "a deformable buckle's contact on the faceted "
          "sclera: 'facet' (its flat faces) or 'nodal' (the quadratic Nagata patches through "
          "them with the nodes' normals: no jump of the contact normal at facet edges)",
          lambda v: v in ("facet", "nodal"), "'facet' or 'nodal'"),
    Field("n_segments", int, 24, "facets of an encircling buckle's ring / 8", lambda v: v >= 3,
          ">= 3"),
]


def _materials(materials):
    out = {k: MooneyRivlin.from_terms(k, {"c10": c}) for k, c in SEED_MATERIALS.items()}
    out["band"] = MooneyRivlin.from_terms("band", {"c10": BAND_C10})  # a deformable band,
    out["tire"] = MooneyRivlin.from_terms("tire", {"c10": TIRE_C10})  # tire,
    out["sponge"] = MooneyRivlin.from_terms("sponge", {"c10": SPONGE_C10})  # ... or sponge
    out.update(materials or {})
    return out


def suture_layout(parts: SurgeryParts, width: float, meridian_deg: float | None = None):
    """Bites of the sutures for a suture width (mm), on the reference outer sclera; a
    segmental buckle turned to ``meridian_deg`` (default: its own meridian)."""
    b, p, mesh = parts.buckle, parts.p, parts.eye.mesh
    cen, acr, nrm, _ = parts.frame
    if meridian_deg is not None and meridian_deg != b.meridian_deg:
        turned = dataclasses.replace(b, meridian_deg=meridian_deg)
        cen, acr, nrm, _ = suture_anchor_frame(turned, parts.eye.geometry, p["n_sutures"])
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
    parts.layout = layout
    R = g.scleral_radius * scale
    anchors, nodes_a, xi_a, d1, d2, d3 = [], [], [], [], [], []
    for side, sgn in ((layout.bite_a, -1.0), (layout.bite_b, 1.0)):
        if b.encircling:  # the tire is seated on its flat base; its ridge protrudes inward
            top = (R + b.thickness) * nrm + sgn * 0.5 * b.width * acr
            d1.append(-top / np.linalg.norm(top, axis=1, keepdims=True))
            d2.append(np.stack([_meridian(t) for t in top]))
        else:
            n0, m0, _ = _sponge_frame(parts)
            top = (R + b.width / 2) * nrm + sgn * 0.5 * b.width * acr
            d1.append(np.tile(-n0, (len(top), 1)))
            d2.append(np.tile(m0, (len(top), 1)))
        anchors.append(top)
        d3.append(nrm)  # d top / d R
        nodes_a.append(side.nodes)
        xi_a.append(side.xi)
    anchors, nodes_a, xi_a, d1, d2, d3 = (np.concatenate(v) for v in
                                          (anchors, nodes_a, xi_a, d1, d2, d3))
    L0 = np.linalg.norm(anchors - np.einsum("na,nai->ni", _N(xi_a), mesh.nodes[nodes_a]), axis=1)
    return AnchoredBars("sutures", nodes_a, xi_a, anchors, np.zeros(len(anchors), int), d1, d2,
                        1, mesh.nodes, L0, EA=p["suture_EA"], tension_only=True,
                        extra_dof=parts.extra_dof, dirs3=d3)


def _meridian(x):
    """Unit meridian tangent (toward the posterior) at x (3,)."""
    r = np.linalg.norm(x)
    th, ph = np.arccos(x[2] / r), np.arctan2(x[1], x[0])
    return np.array([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)])


def _sponge_frame(parts: SurgeryParts):
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
                             modulus=6 * SEED_MATERIALS["sclera"], extra_dof=parts.extra_dof,
                             smoothing=contact_smoothing(parts))
    n0, m0, ax = _sponge_frame(parts)
    return BuckleContact("buckle", parts.eye.mesh, "eye/sclera_outer", "sponge", R,
                         n0=tuple(n0), m0=tuple(m0), axis=tuple(ax), sponge_radius=w / 2,
                         sponge_length=SPONGE_LENGTH, modulus=6 * SEED_MATERIALS["sclera"],
                         extra_dof=parts.extra_dof, curved=b.kind == "sponge_radial",
                         smoothing=contact_smoothing(parts))


def _N(xi):
    from eyefem.fem.bars import bilinear

    return bilinear(xi)


def surgery(p, materials):
    """Build the surgery Setup from case parameters (see SURGERY_FIELDS)."""
    check_parameters(p)
    deformable = p.get("buckle_body", "rigid") == "deformable"
    eye = build_eye(EyeGeometry(), p["mesh"])
    mesh = eye.mesh
    faces = np.concatenate([mesh.face_set("eye/inner"), mesh.face_set("lens/surface")])
    mesh = mesh.replace(face_sets={**mesh.face_sets, "wetted": faces},
                        node_sets={**mesh.node_sets, "eye/sclera_outer":
                                   np.unique(mesh.face_set("eye/sclera_outer"))})
    g = eye.geometry
    b = Buckle(p["buckle"], p["buckle_distance"], p["buckle_meridian_deg"], p["n_segments"])
    band = None
    sponge = deformable and not b.encircling
    if sponge and p["mesh"] != "coarse" and (p["buckle_meridian_deg"] % 90 == 0 or
                                             p["contact_normals"] != "nodal" or
                                             not p["globe_axial"]):
        log.warning("deformable %s on the %s eye mesh at meridian %g deg, contact_normals = "
                    "'%s', globe_axial = %g: off the coarse eye the deformable sponge has run "
                    "to the end with the settings of cases/surgery/deformable_sponge_default"
                    ".toml (a meridian off the eye mesh's symmetry planes, contact_normals = "
                    "'nodal', globe_axial = 1); at meridian 0 its suture steps were cut until "
                    "they stopped (docs/surgery.md)", b.kind, p["mesh"],
                    p["buckle_meridian_deg"], p["contact_normals"], p["globe_axial"])
    elif deformable and not sponge and p["mesh"] not in ("coarse", "default"):
        log.warning("deformable %s on the %s eye mesh: the deformable band and tires have "
                    "been run to the end on the coarse and default eyes only, with their "
                    "case files' settings (docs/surgery.md)", b.kind, p["mesh"])
    if sponge:  # parked SPONGE_PARK mm off the sclera until stage 2 fits it snug
        mesh = with_band(mesh, sponge_mesh(b, g, p["mesh"], SPONGE_PARK), "sponge")
    elif deformable:  # parked BAND_PARK mm off the sclera until stage 2 fits it snug
        n_circ = band_n_circ(mesh, mesh.node_set("eye/sclera_outer"), b, g)
        closed = p["deformable_tightening"] == "shortened_loop"
        mesh = with_band(mesh, deformable_band(b, g, g.scleral_radius + BAND_PARK, n_circ,
                                               closed=closed))
        band = BandInfo(mesh, n_circ, closed)
    eye = dataclasses.replace(eye, mesh=mesh)
    frame = suture_anchor_frame(b, g, p["n_sutures"])
    parts = SurgeryParts(eye, b, p, mesh.node_set("eye/sclera_outer"), frame,
                         extra_dof=3 * mesh.n_nodes + mesh.n_elem, band=band, sponge=sponge)
    mats = _materials(materials)
    lens_eq, zf, zxi = eye.zonule
    zonule = Bars("zonule", np.repeat(lens_eq[:, None], 4, 1), zf, np.zeros((len(lens_eq), 2)),
                  zxi, mesh.nodes, EA=p["zonule_E"] * g.zonule_area)
    iop = PressureLoad("iop", mesh, "wetted", 0.0)
    cavity = FluidCavity("cavity", mesh, [("wetted",)], bulk=p["liquid_bulk"])
    if sponge:
        sutures, parts.layout = sponge_suture_term(mesh, b, frame, p)
        buckle = sponge_contact_term(mesh, SEED_MATERIALS["sclera"], p["contact_normals"])
        band_hold = (sponge_spring_term(mesh, b, g),)
    elif deformable:
        sutures = band_suture_term(parts)
        buckle = band_contact_term(parts, SEED_MATERIALS["sclera"])
        band_hold = (band_spring_term(parts),)
    else:
        sutures = suture_term(parts, 1.0)
        buckle = buckle_term(parts, 1.0)
        band_hold = ()
    lens_hold = NodeSprings("lens_springs", mesh.node_set("lens"), k=1e-3)
    orbit = orbit_spring(mesh, parts.sclera_nodes, p)
    # encircling: the circumference 2 pi R sin(theta_b) shortens by `tightening`
    parts.d_per_mm = 1.0 / (2 * np.pi * (np.sin(b.centre_angle(g)) if b.encircling else 1.0))
    pulled = p["band_tension"] > 0
    extra = (DofForce("band_pull", parts.extra_dof, gain=1.0 / parts.d_per_mm),) if pulled else ()
    model = solid_model(mesh, {m: mats[m] for m in mesh.materials},
                        (zonule, iop, cavity, buckle, sutures, lens_hold, orbit) + band_hold
                        + extra, n_extra_dofs=1)
    if band is not None and band.closed:  # the band's loop tightened by its rest length
        s = model.term("solid")
        model = model.with_terms([ShortenedLoopSolid(s.name, mesh, s.coeffs, s.multiplier_offset,
                                                     loop_nodes=band.nodes)]
                                 + [t for t in model.terms if t is not s])
    fix = node_dofs(mesh.node_set("eye/nerve_end"))
    # the buckle's own radial motion (extra dof) is held, except a segmental buckle's
    # while its sutures are tightened: they pull it in against the sclera
    held = (np.r_[fix, parts.extra_dof], np.zeros(len(fix) + 1))
    held_eye = (fix, np.zeros(len(fix)))
    p_iop = p["iop_mmhg"] * MMHG

    def place_buckle(model, q, theta):
        model, q, theta = close_cavity(model, q, theta, "cavity", "iop")
        scale = float(snug_scale(parts, q))
        sut, new_buckle = suture_term(parts, scale), buckle_term(parts, scale)
        model = model.with_terms([new_buckle if t.name == "buckle" else sut if t.name == "sutures"
                                  else t for t in model.terms])
        parts.scale = scale
        return model, q, theta

    def place_band(model, q, theta):
        """Close the cavity; re-reference the (held, undeformed) band snug on the
        pressurised eye: its stress-free state is the snug fit."""
        model, q, theta = close_cavity(model, q, theta, "cavity", "iop")
        scale = float(snug_scale(parts, q))
        rereference(parts, fit_band(parts, scale, q), scale)
        contact = band_contact_term(parts, SEED_MATERIALS["sclera"]).update(q, None)
        model = with_refitted_terms(model, parts, {"buckle": contact,
                                                   "sutures": band_suture_term(parts),
                                                   "band_springs": band_spring_term(parts)})
        return model, q, theta

    def place_sponge(model, q, theta):
        """Close the cavity; re-reference the (held, undeformed) sponge snug on the
        pressurised eye."""
        model, q, theta = close_cavity(model, q, theta, "cavity", "iop")
        scale = float(snug_scale(parts, q))
        new_mesh = rereference(parts, fit_sponge(parts.eye.mesh, b, g, p["mesh"], scale, q,
                                                 p["contact_normals"]), scale)
        sut, parts.layout = sponge_suture_term(new_mesh, b, frame, p)
        model = with_refitted_terms(model, parts, {
            "buckle": sponge_contact_term(new_mesh, SEED_MATERIALS["sclera"],
                                          p["contact_normals"]).update(q, None),
            "sutures": sut, "sponge_springs": sponge_spring_term(new_mesh, b, g)})
        return model, q, theta

    def tie_sutures(model, q, theta):
        t = model.term("sutures")
        L = np.asarray(t.lengths(np.asarray(q)[t.dofs], theta["sutures"], t.data))
        return model, q, {**theta, "sutures": {**theta["sutures"], "L0": L}}

    base = ("solid", "zonule", "lens_springs", "orbit")
    if sponge:
        sponge_all = node_dofs(mesh.node_set("sponge"))
        parked = (np.r_[held[0], sponge_all], np.zeros(len(held[0]) + len(sponge_all)))
        tight = three_bar_tightening(p)
        sponge_terms = ("cavity", "buckle", "sponge_springs")
        stages = [
            Stage("pressurise", p["steps_pressurise"], parked, params={"iop": {"p": p_iop}},
                  active=base + ("iop",)),
            Stage("place", 1, parked, params={"cavity": {"dv": -p["drain_volume"]}},
                  active=base + sponge_terms, before=place_sponge),
            Stage("suture", p["steps_suture"], held, params={"sutures": {"tightening": tight}},
                  active=base + sponge_terms + ("sutures",), before=tie_sutures),
        ]
    elif deformable:
        band_all = node_dofs(mesh.node_set("band"))
        held = (np.r_[held[0], band_all], np.zeros(len(held[0]) + len(band_all)))
        *tightened, shorten = tightened_band(parts, np.r_[fix, parts.extra_dof], p["tightening"])
        tight = three_bar_tightening(p)
        band_terms = ("cavity", "buckle", "band_springs")
        stages = [
            Stage("pressurise", p["steps_pressurise"], held, params={"iop": {"p": p_iop}},
                  active=base + ("iop",)),
            Stage("tighten", p["steps_tighten"], tuple(tightened),
                  params={"cavity": {"dv": -p["drain_volume"]}, **shorten},
                  active=base + band_terms, before=place_band),
            Stage("suture", p["steps_suture"], tuple(tightened),
                  params={"sutures": {"tightening": tight}},
                  active=base + band_terms + ("sutures",), before=tie_sutures),
        ]
    else:
        motion = {"d": np.full(1, p["tightening"] * parts.d_per_mm),
                  "s": np.full(1, p["buckle_shift"])}
        ridge = {"ridge": np.full(1, KINDS[b.kind][2])}
        # a pulled band (force control) moves freely: its radial motion is an unknown
        held_band = held_eye if pulled else held
        pull = {"band_pull": {"f": p["band_tension"]}} if pulled else {}
        stages = [
            Stage("pressurise", p["steps_pressurise"], held, params={"iop": {"p": p_iop}},
                  active=base + ("iop",)),
            Stage("tighten" if b.encircling else "place", p["steps_tighten"], held_band,
                  params={"buckle": {**motion, **ridge}, "sutures": motion,
                          "cavity": {"dv": -p["drain_volume"]}, **pull},
                  active=base + ("cavity", "buckle") + tuple(pull), before=place_buckle),
            Stage("suture", p["steps_suture"], held_band if b.encircling else held_eye,
                  params={"sutures": {"tightening": np.full(2 * p["n_sutures"],
                                                            p["suture_tightening"] / 2)}},
                  active=base + ("cavity", "buckle", "sutures") + tuple(pull),
                  before=tie_sutures),
        ]
    last = {}

    def probe(model, q, theta):
        out = outcomes(parts, model, q, theta)
        last["state"] = (model, q, theta)
        return out

    def finish(rows, out_dir, plots):
        summary = stage_summary(rows)
        write_csv(Path(out_dir) / "stages.csv", summary)
        if plots and "state" in last:
            pictures(parts, *last["state"], Path(out_dir))
        final = summary[-1]
        out = {"iop_mmhg": final["iop_mmhg"], "indentation_mm": final["indentation_mm"],
               "axial_length_change_mm": final["axial_length_change_mm"],
               "volume_change_mm3": final["volume_change_mm3"],
               "max_suture_force_N": final["max_suture_force_N"],
               "iop_after_tightening_mmhg": summary[1]["iop_mmhg"] if len(summary) > 1 else None,
               "elements": int(mesh.n_elem), "buckle_body": p.get("buckle_body", "rigid")}
        if band is not None and rows:
            out.update({k: rows[-1][k] for k in BAND_OUTPUTS})
        return out

    setup = Setup("surgery", model, stages, probe, finish)
    setup.parts = parts
    return setup


def check_parameters(p):
    """Checks across fields (each field alone is checked by its schema): ValueError
    naming the values and the fix. ``eyefem new-case`` runs it before writing a case."""
    if p.get("band_tension", 0.0) > 0:
        if p["buckle"].startswith("sponge"):  # as Buckle.encircling
            raise ValueError(f"band_tension = {p['band_tension']} N needs an encircling buckle "
                             f"(buckle = '{p['buckle']}' is segmental); set band_tension = 0")
        if p["tightening"] != 0:
            raise ValueError(f"band_tension = {p['band_tension']} N and tightening = "
                             f"{p['tightening']} mm: give one; set tightening = 0 to pull the band")
    if p.get("buckle_body", "rigid") == "deformable":
        _check_deformable(p)


def _check_deformable(p):
    """Clear errors for the cases a deformable buckle does not cover."""
    kinds = RING_KINDS + ("sponge_radial",)
    if p["buckle"] not in kinds:
        raise ValueError(f"buckle_body = 'deformable' is implemented for buckle = "
                         f"{', '.join(repr(k) for k in kinds)}; got '{p['buckle']}' (the "
                         "circumferential sponge is a rigid body only): set buckle to one of "
                         "those, or buckle_body = 'rigid'")
    for name, unit in (("band_tension", "N"), ("buckle_shift", "mm")):
        if p[name] != 0:
            raise ValueError(f"{name} = {p[name]} {unit} applies to the rigid buckle only; with "
                             f"buckle_body = 'deformable' set {name} = 0")
    if p["buckle"] == "sponge_radial" and p["tightening"] != 0:
        raise ValueError(f"tightening = {p['tightening']} mm: a deformable sponge is pressed in "
                         "by its sutures alone (suture_tightening); set tightening = 0")


def snug_scale(parts: SurgeryParts, q, node=None):
    """Radial scale of a buckle fitted snug on the eye at state q (n_dof,): the largest
    |x| / |X| of the outer scleral nodes under it (jax or numpy). ``node``: evaluate at
    that node instead (the maximiser, for a derivative). See :func:`snug_node`."""
    mesh = parts.eye.mesh
    s = snug_node(parts, q) if node is None else node
    x = mesh.nodes[s] + q[3 * s: 3 * s + 3]
    return jnp.linalg.norm(x) / np.linalg.norm(mesh.nodes[s])


def snug_node(parts: SurgeryParts, q) -> int:
    """The outer scleral node under the buckle that the snug buckle touches (numpy q)."""
    mesh = parts.eye.mesh
    s = parts.sclera_nodes[buckle_zone(parts)]
    x = mesh.nodes[s] + np.asarray(q)[: 3 * mesh.n_nodes].reshape(-1, 3)[s]
    return int(s[np.argmax(np.linalg.norm(x, axis=1) / np.linalg.norm(mesh.nodes[s], axis=1))])


def orbit_spring(mesh, sclera_nodes, p) -> OrbitSpring:
    """The orbit's hold on the globe: springs on the rigid rotation (N mm/rad) and lateral
    translation (N/mm) of the outer scleral ring at the equator (case fields
    globe_torsion, globe_rotation, globe_translation).

    On the nerve stub alone the globe twists, turns and shifts almost freely (about
    0.3 N mm/rad in torsion), held otherwise only by the buckle's smoothed contact
    forces. The passive stiffness of the extraocular muscles and orbital
    tissue is about 1 gram-force per degree at the tendon insertions (Robinson, 1975),
    7 N mm/rad at the scleral radius (globe_torsion). Against tilt (globe_rotation) the
    default is ten times that: during the operation the surgeon holds the globe by
    traction sutures under the rectus muscles, and with 7 N mm/rad the encircled globe
    (its nerve leaves 15 degrees nasally) has two equilibria late in the tightening of
    coarse case 2, tilted by 0.1 or 0.5 degrees, which the Newton path picks between
    (docs/surgery.md). The lateral hold of the orbital fat and Tenon's capsule, 1 N/mm
    by default, is an order-of-magnitude estimate. A deformation without net rotation or
    lateral shift feels nothing."""
    X = mesh.nodes[sclera_nodes]
    rho = np.hypot(X[:, 0], X[:, 1])
    ring = np.abs(X[:, 2] - X[np.argmax(rho), 2]) < 1e-6
    k_rot = (p["globe_rotation"], p["globe_rotation"], p["globe_torsion"])
    return OrbitSpring("orbit", sclera_nodes[ring], X[ring], k_rot=k_rot,
                       k_trans=p["globe_translation"], k_axial=p["globe_axial"])


def _buckle_coords(parts: SurgeryParts):
    """Across (a) and along coordinates (mm) of the outer scleral nodes relative to the
    buckle centre line, and a mask of nodes within the buckle's length."""
    eye, b = parts.eye, parts.buckle
    g = eye.geometry
    X = eye.mesh.nodes[parts.sclera_nodes]
    th = np.arccos(np.clip(X[:, 2] / np.linalg.norm(X, axis=1), -1, 1))
    if b.encircling:
        return g.scleral_radius * (th - b.centre_angle(g)), np.ones(len(X), bool)
    cen, acr, nrm, _ = suture_anchor_frame(b, g, 1)
    v = X - cen[0]
    return v @ acr[0], np.abs(v @ np.cross(nrm[0], acr[0])) < 2.0


def buckle_zone(parts: SurgeryParts):
    """Mask of the outer scleral nodes under the buckle."""
    a, ok = _buckle_coords(parts)
    if not parts.buckle.encircling:
        cen, acr, nrm, _ = suture_anchor_frame(parts.buckle, parts.eye.geometry, 1)
        v = parts.eye.mesh.nodes[parts.sclera_nodes] - cen[0]
        ok = np.abs(v @ np.cross(nrm[0], acr[0])) < 5.0
    return ok & (np.abs(a) < parts.buckle.width / 2)


def indentation(parts: SurgeryParts, x) -> float:
    """Buckle indentation height (mm): mean outer radius of the sclera 1.5-3 mm beside
    the buckle minus that under its central half, in the buckle's cross-section
    (encircling: all around; segmental: within 2 mm of the sponge centre)."""
    b = parts.buckle
    rho = np.linalg.norm(x[parts.sclera_nodes], axis=1)
    a, ok = _buckle_coords(parts)
    under = ok & (np.abs(a) < b.width / 4)
    beside = ok & (np.abs(a) > b.width / 2 + 1.5) & (np.abs(a) < b.width / 2 + 3.0)
    if not under.any() or not beside.any():
        raise ValueError("indentation: no scleral nodes under or beside the buckle; refine the mesh")
    return float(rho[beside].mean() - rho[under].mean())


def outcomes(parts: SurgeryParts, model, q, theta) -> dict:
    """IOP (mmHg), cavity volume (mm^3), axial length (mm), indentation (mm), max suture force (N)."""
    mesh = parts.eye.mesh
    x = mesh.nodes + q[: 3 * mesh.n_nodes].reshape(-1, 3)
    cav = model.term("cavity")
    P, V = cav.pressures(q, theta["cavity"])
    closed = theta["iop"]["p"] == 0.0  # close_cavity releases the surface load
    iop = float(P[0]) if closed else float(theta["iop"]["p"])
    L0 = axial_length(mesh, mesh.nodes)
    forces = model.term("sutures").forces(q, theta["sutures"])
    out = {"iop_mmhg": iop / MMHG, "volume_mm3": float(V[0]),
           "axial_length_mm": axial_length(mesh, x),
           "axial_length_change_unloaded_mm": axial_length(mesh, x) - L0,
           "indentation_mm": indentation(parts, x),
           "max_suture_force_N": float(forces.max()) if np.any(theta["sutures"]["tightening"])
           else 0.0}
    if parts.band is not None:
        out.update(band_outcomes(parts, model, q, theta))
    elif not parts.sponge:
        out["buckle_free_motion_mm"] = float(q[parts.extra_dof])
        out["band_shortening_mm"] = (parts.p["tightening"] + float(q[parts.extra_dof]) / parts.d_per_mm
                                     if parts.buckle.encircling else 0.0)
    return out


def stage_summary(rows) -> list[dict]:
    """The last row of every stage, with the volume and axial length changes since the
    end of the first stage (the pressurised pre-operative eye)."""
    out, v_closed, l_preop = [], None, None
    for i, r in enumerate(rows):
        if i + 1 == len(rows) or rows[i + 1]["stage"] != r["stage"]:
            if v_closed is None:
                v_closed = r["volume_mm3"]
            if l_preop is None:
                l_preop = r["axial_length_mm"]
            out.append({"stage": r["stage"], "iop_mmhg": r["iop_mmhg"],
                        "indentation_mm": r["indentation_mm"],
                        "axial_length_mm": r["axial_length_mm"],
                        "axial_length_change_mm": r["axial_length_mm"] - l_preop,
                        "volume_change_mm3": r["volume_mm3"] - v_closed,
                        "max_suture_force_N": r["max_suture_force_N"]})
    return out


def pictures(parts: SurgeryParts, model, q, theta, out_dir: Path):
    """Meridional section and outside view coloured by von Mises stress (PNG)."""
    from eyefem.io.pictures import plot_outside, plot_section

    mesh = parts.eye.mesh
    x = mesh.nodes + q[: 3 * mesh.n_nodes].reshape(-1, 3)
    vm = model.terms[0].fields(q, theta["solid"])["von_mises"] / 1e-3  # kPa
    normal = (0.0, 1.0, 0.0)
    if not parts.buckle.encircling:
        ph = np.radians(parts.buckle.meridian_deg)
        normal = (-np.sin(ph), np.cos(ph), 0.0)
    vmax, title = None, ""
    body = "band" if parts.band is not None else "sponge" if parts.sponge else None
    if body:  # the silicone buckle (MPa) would set the eye's colour scale
        eye_el = np.setdiff1d(np.arange(mesh.n_elem), mesh.element_sets[body])
        name = "tire" if parts.buckle.kind.startswith("tire") else body
        vmax, title = float(np.percentile(vm[eye_el], 99)), f" with the deformable {name}"
    plot_section(out_dir / "section_von_mises.png", x, mesh.hexes, vm, normal=normal,
                 title="meridional section" + title, label="von Mises stress, kPa", vmax=vmax)
    plot_outside(out_dir / "outside_von_mises.png", x, mesh.hexes, vm,
                 title="outside view" + title, label="von Mises stress, kPa", vmax=vmax)


surgery.check = check_parameters
PROBLEMS = {"surgery": (SURGERY_FIELDS, surgery)}
