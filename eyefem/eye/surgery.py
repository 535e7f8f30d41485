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

:func:`surgery` assembles the eye (eyefem.eye.eyemodel), a buckle body
(eyefem.eye.bodies: what each kind of buckle adds, its stages and outcomes) and the
common outcomes (eyefem.eye.outcomes). The design variables (tightening, suture width,
buckle shift, ...) map onto term params (eyefem.eye.design), so the adjoint gives
gradients of the outcomes with respect to them.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from eyefem.eye.biometry import BIOMETRY_FIELDS, eye_geometry
from eyefem.eye.bodies import BASE_TERMS, LoadPath, buckle_body
from eyefem.eye.buckle_meshes import BAND_C10, RING_KINDS, SPONGE_C10, TIRE_C10
from eyefem.eye.buckles import KINDS, SPONGE_LENGTH, Buckle, suture_anchor_frame
from eyefem.eye.eyemodel import LEVEL_EXPECTED, LEVEL_HELP, SURGICAL_LEVEL, build_eye, is_level
from eyefem.eye.mesh_error import mesh_error
from eyefem.eye.outcomes import outcomes, stage_summary, stress_patches
from eyefem.eye.parts import SurgeryParts
from eyefem.eye.presets import PRESETS, SEED_MATERIALS, with_overrides
from eyefem.eye.timeline import (TIMELINE_FIELDS, plot_timeline, regulation, timed_stages,
                                  timeline_outcomes)
from eyefem.eye.relaxation import RELAXATION_FIELDS, with_relaxation
from eyefem.eye.wall import WALL_ELEMENT_FIELD, with_wall_element
from eyefem.fem.buckle_contact import EDGE_WIDTH, RIDGE_FLANK
from eyefem.fem.cavity import WATER_BULK, FluidCavity
from eyefem.fem.materials import MooneyRivlin
from eyefem.fem.mesh import face_edges
from eyefem.fem.surface import PressureLoad
from eyefem.fem.terms import OrbitSpring
from eyefem.fem.units import MMHG
from eyefem.io.casefile import Field, positive
from eyefem.io.output import write_csv
from eyefem.solve.problem import Setup
from eyefem.solve.linsolve import physical_memory_kb
from eyefem.solve.model import node_dofs, solid_model

log = logging.getLogger(__name__)

__all__ = ["SEED_MATERIALS", "SURGERY_FIELDS", "CONVERGING_MODEL", "EARLIER_MODEL", "surgery",
           "check_parameters", "resolve_model", "orbit_spring", "pictures", "PROBLEMS",
           "BASE_TERMS"]

BODIES = ("rigid", "deformable")
"""Buckle bodies: the rigid analytic surface, or a deformable hexahedral band, tire (with
its band) or radial sponge."""

TIGHTENINGS = ("pulled_ends", "shortened_loop")
"""How a deformable band or tire is tightened (eyefem.eye.band)."""

CONVERGING_MODEL = {"lens_support": 0.343, "buckle_edge": 1.0, "ridge_flank": 1.5,
                    "sponge_end": 1.0}
"""The model fields' defaults: the model whose outcomes converge with the mesh
(docs/convergence.md, "Results: the case files' model"), which the surgical case files
carry and ``new-case`` writes into a new case: the lens's springs, 0.343 N/mm in all (the
sum the default level's 1e-3 N/mm per node gave), shared by its nodes, so the lens is held
alike on every level; a rigid band's or tire's edges lifting over 1 mm; the ridged tire's
ridge with 1.5 mm flanks; a rigid sponge's ends rounding off over 1 mm (then the case's
``[solver]`` wants CURVED_CONTACT_SOLVER)."""

EARLIER_MODEL = {"lens_support": 0.0, "buckle_edge": EDGE_WIDTH, "ridge_flank": RIDGE_FLANK,
                 "sponge_end": 0.0}
"""What ``model = "earlier"`` sets (the results recorded before the mesh study, whose
outcomes move with the mesh): lens_support 0, i.e. LENS_SPRING_PER_NODE = 1e-3 N/mm on
every lens node (a sum that follows the lens mesh: 0.125 N/mm on coarse, 0.729 on fine);
0.5 mm ring edges (curvature up to 7.2 per mm); 1 mm ridge flanks; a sponge's contact
fading out over about 0.1 mm beyond each end."""

MODELS = ("converged", "earlier")
"""The values of the ``model`` switch. One switch, not four earlier values to remember:
the earlier model is kept only so that the results recorded with it reproduce bit for
bit; a case that wants one of its pieces (say 0.5 mm edges) with the rest converged gives
that field with ``model = "converged"``. Its per-node lens springs exist only behind the
switch, so that ``lens_support`` means one thing, N/mm in all (the price: per-node springs
combine with the earlier shapes only)."""

LENS_SUPPORT_FIELD = Field(
    "lens_support", float, CONVERGING_MODEL["lens_support"],
    "the springs that hold the floating lens in place, N/mm in all, shared by its nodes, "
    "so the lens is held alike on every mesh level (the springs set the anterior chamber "
    "depth change; docs/convergence.md, 'The lens's support'); model = 'earlier' puts "
    "1e-3 N/mm on every lens node instead", lambda v: 1e-4 <= v <= 100, "1e-4 to 100 N/mm")
"""The surgery's ``lens_support`` (replacing BIOMETRY_FIELDS' own, whose 0 means 1e-3 N/mm
per node: here that is ``model = "earlier"``)."""


def resolve_model(p: dict) -> dict:
    """The parameters ``p`` (every field filled in) with the ``model`` switch applied: a
    new dict, with EARLIER_MODEL's values for ``model = "earlier"`` (``p`` unchanged for
    "converged" or without the field). ValueError, naming the field and the fix, when an
    earlier-model case gives one of the four fields another value than its default (the
    switch sets them; a value equal to the default cannot be told from a field left out
    and is replaced too)."""
    if p.get("model", "converged") != "earlier":
        return dict(p)
    for k, v in CONVERGING_MODEL.items():
        if k in p and p[k] != v:
            raise ValueError(f"{k} = {p[k]} with model = 'earlier': the earlier model sets "
                             f"{k} = {EARLIER_MODEL[k]}; remove {k} or set model = "
                             "'converged'")
    return {**p, **EARLIER_MODEL}


def model_fields(values: dict) -> dict:
    """The model fields (CONVERGING_MODEL's names) that apply to the buckle of
    ``values`` (every field filled in), name -> value in ``values``: lens_support always;
    buckle_edge for a rigid ring; ridge_flank for a rigid ridged tire; sponge_end for a
    rigid sponge."""
    rigid = values.get("buckle_body", "rigid") == "rigid"
    sponge = values["buckle"].startswith("sponge")
    applies = {"lens_support": True, "buckle_edge": rigid and values["buckle"] in RING_KINDS,
               "ridge_flank": rigid and values["buckle"] == "tire_ridged",
               "sponge_end": rigid and sponge}
    return {k: values[k] for k in CONVERGING_MODEL if applies[k] and k in values}


SURGERY_FIELDS = [
    Field("mesh", str, SURGICAL_LEVEL, LEVEL_HELP, is_level, LEVEL_EXPECTED),
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
    Field("bite_radius", float, 1.5, "radius of a suture bite's patch on the outer sclera, "
          "mm: the suture's pull is spread over it with the weight (1 - (r/R)^2)^2 (about the "
          "area of a 3 mm partial-thickness scleral pass; docs/surgery.md, 'Suture bites'); 0: a "
          "point bite (the force on the four nodes of one face, mesh-dependent)",
          lambda v: v == 0 or 0.2 <= v <= 5, "0 (point bites) or 0.2 to 5 mm"),
    Field("bite_length", float, 0.0, "length of a suture bite's patch along the buckle's "
          "edge, mm (a mattress suture's pass: an ellipse of half-width bite_radius across "
          "the edge and half-length bite_length / 2 along it; docs/surgery.md, 'Suture "
          "bites'); 0: a disc of radius bite_radius",
          lambda v: v == 0 or 0.4 <= v <= 12, "0 (a disc) or 0.4 to 12 mm"),
    Field("n_sutures", int, 8, "number of sutures", positive, ">= 1"),
    Field("suture_angle_deg", float, 0.0, "suture angle about the buckle normal, degrees"),
    Field("suture_tightening", float, 0.6, "shortening of each suture loop when tied, mm "
          "('the same suture tension' in every case)", lambda v: v >= 0, ">= 0"),
    Field("suture_EA", float, 40.0, "suture axial stiffness E*A, N (5-0 polyester ~ 40)",
          positive, "> 0"),
    Field("iop_mmhg", float, 15.0, "pre-operative IOP, mmHg", positive, "> 0",
          warn=(5.0, 60.0), refuse=(0.1, 200.0), unit="mmHg",
          slips=(("MPa", 1 / MMHG), ("kPa", 1e-3 / MMHG), ("Pa", 1e-6 / MMHG))),
    Field("materials_preset", str, "seed", f"tissue constants: {', '.join(PRESETS)} "
          "(eyefem.eye.presets; [materials] tables override single tissues)",
          lambda v: v in PRESETS, f"one of {list(PRESETS)}"),
    Field("liquid_bulk", float, WATER_BULK, "liquid bulk modulus, MPa", positive, "> 0",
          warn=(200.0, 5000.0), unit="MPa", slips=(("GPa", 1e3),)),
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
    Field("globe_axial", float, 10.0, "the hold on the globe's axial (z) translation against "
          "the buckle during surgery (the surgeon's traction sutures, the orbit), N/mm; 0: the "
          "nerve stub alone (an encircled globe then slides almost freely through the "
          "band, and the outcomes hang on that shift: docs/surgery.md)",
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
    Field("contact_quadrature", int, 0, "a rigid buckle's contact penalty: 0, one per outer "
          "scleral node (node to surface); n = 1 to 4, integrated over the outer scleral faces "
          "with n x n Gauss points each, the same stiffness per unit area (a footprint a few "
          "elements wide is sampled by the faces' points, not by the nodes that fall in it: "
          "docs/surgery.md)", lambda v: 0 <= v <= 4, "0 (nodes) or 1 to 4"),
    Field("contact_normals", str, "facet", "a deformable buckle's contact on the faceted "
          "sclera: 'facet' (its flat faces) or 'nodal' (the quadratic Nagata patches through "
          "them with the nodes' normals: no jump of the contact normal at facet edges)",
          lambda v: v in ("facet", "nodal"), "'facet' or 'nodal'"),
    Field("ridge_flank", float, CONVERGING_MODEL["ridge_flank"], "width of each flank of a "
          "rigid ridged tire's ridge (a quintic shoulder inside the ridge's 3 mm base), mm: "
          "narrower flanks have shoulders sharper than the scleral elements can follow "
          "(docs/surgery.md)", lambda v: 0.05 <= v <= 1.5, "0.05 to 1.5 mm"),
    Field("buckle_edge", float, CONVERGING_MODEL["buckle_edge"], "width over which each edge "
          "of a rigid band or tire lifts 0.3 mm off the sclera (a cubic rise whose curvature "
          "reaches 1.8 / width^2 per mm), mm: narrower edges are sharper than the scleral "
          "elements can follow, and the outcomes then grow with the mesh "
          "(docs/convergence.md, 'The flat tire's edges')",
          lambda v: 0.2 <= v <= 2.0, "0.2 to 2 mm"),
    Field("sponge_end", float, CONVERGING_MODEL["sponge_end"], "length over which each end "
          "of a rigid sponge rounds off, lifting 0.3 mm off the sclera (a cubic rise, twice "
          "differentiable), mm; 0: a fade-out about 0.1 mm long beyond each end, once "
          "differentiable, whose outcomes depend on where the ends sit among the nodes "
          "(docs/convergence.md, 'The sponge's ends')",
          lambda v: v == 0 or 0.2 <= v <= 2.0, "0 or 0.2 to 2 mm"),
    Field("model", str, "converged", "'converged': the model whose outcomes converge with the "
          "mesh (the defaults of buckle_edge, ridge_flank, sponge_end and lens_support); "
          "'earlier': the model of the results recorded before the mesh study (0.5 mm ring "
          "edges, 1 mm ridge flanks, a sponge's ends fading out, 1e-3 N/mm on every lens "
          "node), which sets those four fields: leave them out (docs/convergence.md)",
          lambda v: v in MODELS, f"one of {list(MODELS)}"),
    Field("n_segments", int, 24, "facets of an encircling buckle's ring / 8", lambda v: v >= 3,
          ">= 3"),
    WALL_ELEMENT_FIELD,
    Field("symmetry", str, "none", "'mirror': solve the half of the eye with y >= 0 (the "
          "plane through the optical axis and the optic nerve), the plane's nodes held in "
          "y, and report the whole eye's outcomes (about half the unknowns: a faster, "
          "smaller run); refused, with the reason, unless the mesh, buckle, sutures, "
          "contact and loads are symmetric about that plane (an encircling buckle with "
          "sutures spaced evenly about it; not with a deformable buckle or the timeline; "
          "the design simulators solve it whole; docs/case_files.md); 'none': the whole eye",
          lambda v: v in ("none", "mirror"), "'none' or 'mirror'"),
] + [LENS_SUPPORT_FIELD if f.name == "lens_support" else f
     for f in BIOMETRY_FIELDS] + TIMELINE_FIELDS + RELAXATION_FIELDS


def _materials(materials, preset: str = "seed"):
    bodies = {"band": MooneyRivlin.from_terms("band", {"c10": BAND_C10}),  # a deformable band,
              "tire": MooneyRivlin.from_terms("tire", {"c10": TIRE_C10}),  # tire,
              "sponge": MooneyRivlin.from_terms("sponge", {"c10": SPONGE_C10})}  # or sponge
    return with_overrides(preset, {**bodies, **(materials or {})}, log)


RUN_MEMORY_GB = (1.0, 1.8e-4)
"""Peak resident memory of a surgical run, GB: a + b x hexahedra, an estimate from the
measured runs (fine, 25,166 hexahedra: 4.5-6.1 GB; finer, 48,324: 10.5-11.6 GB; finest,
72,920: 11.9 GB; docs/performance.md)."""


def warn_memory(n_elem: int, level: str) -> bool:
    """Say (log warning) and return True when a surgical run on ``n_elem`` hexahedra
    needs more than 80 % of this machine's memory (RUN_MEMORY_GB): the system would kill
    it without a word."""
    need = RUN_MEMORY_GB[0] + RUN_MEMORY_GB[1] * n_elem
    have = physical_memory_kb() / 1024.0 ** 2
    if need <= 0.8 * have:
        return False
    log.warning("eye mesh level '%s' (%d hexahedra): a surgical run needs about %.0f GB of "
                "memory (docs/performance.md) and this machine has %.0f GB; the system may "
                "stop it without a message. Choose a coarser level (--mesh fine or "
                "default) or a machine with more memory", level, n_elem, need, have)
    return True


def surgery(p, materials):
    """Scleral buckling on the parametric eye: the eye, a buckle body and the staged procedure.

    Builds the Setup from case parameters (SURGERY_FIELDS) and material overrides (name ->
    MooneyRivlin); a time-dependent wall (RELAXATION_FIELDS) is applied to the model the
    buckle body hands back. The ``model`` switch is applied here (:func:`resolve_model`): the Setup's parts hold
    the parameters the model was built with."""
    check_parameters(p)
    p = resolve_model(p)
    buckle = Buckle(p["buckle"], p["buckle_distance"], p["buckle_meridian_deg"], p["n_segments"])
    body = buckle_body(p, buckle)
    body.warn(p, buckle)
    eye = build_eye(eye_geometry(p), p["mesh"])
    warn_memory(eye.mesh.n_elem, p["mesh"])
    g = eye.geometry
    mesh, band = body.with_mesh(_with_wetted_surface(eye.mesh), buckle, g, p)
    # encircling: the circumference 2 pi R sin(theta_b) shortens by `tightening`
    d_per_mm = 1.0 / (2 * np.pi * (np.sin(buckle.centre_angle(g)) if buckle.encircling else 1.0))
    parts = SurgeryParts(dataclasses.replace(eye, mesh=mesh), buckle, p,
                         mesh.node_set("eye/sclera_outer"),
                         suture_anchor_frame(buckle, g, p["n_sutures"]), d_per_mm=d_per_mm,
                         extra_dof=3 * mesh.n_nodes + mesh.n_elem, band=band,
                         sponge=body.body_set == "sponge")
    mats = _materials(materials, p.get("materials_preset", "seed"))
    contact, sutures, holds = body.terms(parts)
    wall = _eye_terms(parts)
    model = solid_model(mesh, {m: mats[m] for m in mesh.materials},
                        wall[:3] + (contact, sutures) + wall[3:] + holds, n_extra_dofs=1)
    model = with_relaxation(body.model(with_wall_element(model, p["wall_element"]), parts), p)
    path = LoadPath(node_dofs(mesh.node_set("eye/nerve_end")), parts.extra_dof,
                    p["iop_mmhg"] * MMHG)
    last, patches = {}, {}  # the stress patches per model mesh (a deformable body's merges)

    def probe(model, q, theta):
        last["state"] = (model, q, theta)
        if model.mesh.n_elem not in patches:
            patches[model.mesh.n_elem] = stress_patches(model.mesh)
        return {**outcomes(parts, model, q, theta, patches[model.mesh.n_elem]),
                **body.outcomes(parts, model, q, theta)}

    def finish(rows, out_dir, plots):
        summary = stage_summary(rows)
        write_csv(Path(out_dir) / "stages.csv", summary)
        if plots and "state" in last:
            pictures(parts, *last["state"], Path(out_dir), summary=summary[-1])
        final = summary[-1]
        out = {k: final[k] for k in ("iop_mmhg", "indentation_mm", "axial_length_change_mm",
                                     "volume_change_mm3", "max_suture_force_N",
                                     "refraction_change_D", "corneal_power_change_D",
                                     "corneal_astigmatism_D", "anterior_chamber_depth_change_mm",
                                     "scleral_stress_kPa", "scleral_stress_fraction_of_strength",
                                     "suture_force_fraction_of_break")}
        out.update({"iop_after_tightening_mmhg": summary[1]["iop_mmhg"] if len(summary) > 1
                    else None, "elements": int(mesh.n_elem),
                    "buckle_body": p.get("buckle_body", "rigid")})
        if rows:
            out.update({k: rows[-1][k] for k in body.summary_outcomes})
        timeline = timeline_outcomes(rows, p)
        out.update(timeline)
        if plots and timeline:
            plot_timeline(Path(out_dir) / "iop_timeline.png", rows, p, timeline)
        out["mesh_error"] = run_mesh_error(p, parts.buckle.encircling, out)
        warn_high_iop(out["iop_mmhg"]) or warn_low_iop(out["iop_mmhg"])
        if parts.buckle.encircling and len(summary) > 1:
            warn_broken_symmetry(final["corneal_astigmatism_D"]
                                 - summary[0]["corneal_astigmatism_D"])
        return out

    setup = Setup("surgery", model, timed_stages(body.stages(parts, path), p), probe, finish,
                  parts=parts)
    if p.get("symmetry", "none") == "mirror":
        from eyefem.eye.mirror import mirror_setup
        return mirror_setup(setup)
    return setup


def run_mesh_error(p: dict, encircling: bool, out: dict) -> dict:
    """summary.json's "mesh_error": the mesh study's error estimates at the run's level
    (eyefem.eye.mesh_error), with the run's own values for the errors in units."""
    values = {**out, "iop_rise_mmhg": out["iop_mmhg"] - p["iop_mmhg"]}
    err = mesh_error(p["mesh"], encircling, values)
    preset = p.get("materials_preset", "seed")
    if preset != err["materials"]:
        err["note"] = (err["note"] + " " if err["note"] else "") + (
            f"The study used the {err['materials']} materials; this run uses the {preset} "
            "preset, so the figures are those of the studied cases, not of this run.")
    if p.get("buckle_body", "rigid") != "rigid":
        err["note"] = (err["note"] + " " if err["note"] else "") + (
            "The study used rigid buckles; this run's buckle is deformable.")
    models = [{**STUDY_MODEL, **m} for m in err.get("model", {}).values()] or [STUDY_MODEL]
    rigid_only = ("buckle_edge", "ridge_flank",  # the rigid buckle's, unused otherwise
                  "contact_quadrature", "sponge_end")
    unused = ("sponge_end",) if encircling else ("buckle_edge", "ridge_flank")  # the ring's
    changed = [f"{k} = {p[k]!r}" for k in STUDY_MODEL  # or the sponge's shape, not both
               if k in p and all(p[k] != m[k] for m in models) and k not in unused
               and not (k in rigid_only and p.get("buckle_body", "rigid") != "rigid")]
    if changed:
        err["note"] = (err["note"] + " " if err["note"] else "") + (
            f"The study's cases ran another model; this run sets {', '.join(changed)}, which "
            "changes how its outcomes move with the mesh (docs/convergence.md).")
    return err


STUDY_MODEL = {f.name: f.default for f in SURGERY_FIELDS
               if f.name in ("buckle_edge", "ridge_flank", "lens_support",
                             "zonule_insertion_radius", "tissue_mixing", "wall_element",
                             "contact_quadrature", "sponge_end")}
"""The model fields that change how outcomes move with the mesh, at their defaults: the
mesh study's record (eyefem/eye/mesh_study.json) holds the values each studied case ran
with ("model"; these defaults where it does not); a run whose value matches none of the
studied cases' gets the study's mesh error with a note saying so."""


def warn_high_iop(iop_mmhg: float) -> bool:
    """Say (log warning) and return True when the post-surgery IOP (mmHg) is above
    IOP_PERFUSION_MMHG."""
    if not iop_mmhg > IOP_PERFUSION_MMHG:
        return False
    log.warning(
        "IOP after the surgery is %.0f mmHg, above the ~%.0f mmHg at which the central "
        "retinal artery stops perfusing the retina. The model's cavity is closed (no "
        "aqueous outflow or choroidal blood expulsion; it loses only the case's "
        "drain_volume), so the buckle's indentation compresses the whole contents; with "
        "the physiological preset's stiff wall that takes a high pressure "
        "(docs/validation.md, Limitations). Less tightening, or draining (drain_volume, "
        "uL), lowers it.", iop_mmhg, IOP_PERFUSION_MMHG)
    return True


IOP_HYPOTONY_MMHG = 5.0
"""Post-surgery IOP below which a run warns: ocular hypotony (a pressure below zero is a
liquid under tension, which the contents of a real eye do not hold)."""


def warn_low_iop(iop_mmhg: float) -> bool:
    """Say (log warning) and return True when the post-surgery IOP (mmHg) is below
    IOP_HYPOTONY_MMHG (typically: more drained, ``drain_volume``, than the buckle
    displaced)."""
    if not iop_mmhg < IOP_HYPOTONY_MMHG:
        return False
    log.warning(
        "IOP after the surgery is %.1f mmHg, below the %.0f mmHg of ocular hypotony%s. "
        "More fluid was drained (drain_volume) than the buckle's indentation displaced; "
        "drain less.", iop_mmhg, IOP_HYPOTONY_MMHG,
        ": a negative pressure is a liquid under tension, which the contents of a real "
        "eye cannot hold (the choroid would detach), so the state is not physical"
        if iop_mmhg < 0 else "")
    return True


SYMMETRY_ASTIGMATISM_D = 0.05
"""Corneal astigmatism induced by an encircling buckle above which its state is taken to
have broken the eye's near-axial symmetry, dioptres (the encircling seed cases that keep
it induce below 0.01 D)."""


def warn_broken_symmetry(induced_astigmatism_d: float) -> bool:
    """Say (log warning) and return True when an encircling buckle induced more corneal
    astigmatism (D, since the pressurised eye) than SYMMETRY_ASTIGMATISM_D."""
    if not induced_astigmatism_d > SYMMETRY_ASTIGMATISM_D:
        return False
    log.warning(
        "the encircling buckle induced %.2f D of corneal astigmatism: the eye's state has "
        "left its near-axial symmetry (an ovalisation of the globe in the strongly "
        "tightened band, which has more than one equilibrium there), so its axial length "
        "change, refraction and astigmatism depend on the load steps; quote its IOP and "
        "indentation, and check that its stages end stable (eyefem run --stability; "
        "docs/convergence.md, case 4).", induced_astigmatism_d)
    return True


def _with_wetted_surface(mesh):
    """The eye mesh with the face set "wetted" (wall inside and lens: the liquid's
    boundary) and the node set "eye/sclera_outer"."""
    faces = np.concatenate([mesh.face_set("eye/inner"), mesh.face_set("lens/surface")])
    return mesh.replace(face_sets={**mesh.face_sets, "wetted": faces},
                        node_sets={**mesh.node_sets, "eye/sclera_outer":
                                   np.unique(mesh.face_set("eye/sclera_outer"))})


def _eye_terms(parts: SurgeryParts) -> tuple:
    """The eye's own terms: zonule, IOP load, cavity, lens springs, orbit."""
    eye, p, mesh = parts.eye, parts.p, parts.eye.mesh
    return (eye.zonule_bars(p["zonule_E"]), PressureLoad("iop", mesh, "wetted", 0.0),
            FluidCavity("cavity", mesh, [("wetted",)], bulk=p["liquid_bulk"],
                        regulation=regulation(p)),
            eye.lens_springs(),
            orbit_spring(mesh, p))


def check_parameters(p):
    """Checks across fields (each field alone is checked by its schema): ValueError
    naming the values and the fix. ``eyefem new-case`` runs it before writing a case."""
    given, p = p, resolve_model(p)
    if p.get("tissue_relaxation", "none") != "none" and not p.get("volume_regulation", False):
        raise ValueError(f"tissue_relaxation = {p['tissue_relaxation']!r} relaxes the tissues "
                         "over time, and time passes only on the surgery's timeline: set "
                         "volume_regulation = true (or tissue_relaxation = 'none')")
    if p.get("band_tension", 0.0) > 0:
        if p["buckle"].startswith("sponge"):  # as Buckle.encircling
            raise ValueError(f"band_tension = {p['band_tension']} N needs an encircling buckle "
                             f"(buckle = '{p['buckle']}' is segmental); set band_tension = 0")
        if p["tightening"] != 0:
            raise ValueError(f"band_tension = {p['band_tension']} N and tightening = "
                             f"{p['tightening']} mm: give one; set tightening = 0 to pull the band")
    if p.get("bite_length", 0.0) > 0:
        if p["bite_radius"] == 0:
            raise ValueError(f"bite_length = {p['bite_length']} mm needs a bite of physical "
                             "size: bite_radius = 0 makes point bites; set bite_radius (the "
                             "half-width across the edge, e.g. 0.5 mm) or bite_length = 0")
        if p["bite_length"] < 2 * p["bite_radius"]:
            raise ValueError(f"bite_length = {p['bite_length']} mm is shorter than the patch's "
                             f"width 2 x bite_radius = {2 * p['bite_radius']} mm: bite_length is "
                             "the full length along the buckle's edge and bite_radius the "
                             "half-width across it; lengthen bite_length or narrow bite_radius")
    _check_feasible(p)
    edge = p.get("buckle_edge", EDGE_WIDTH)
    if p["buckle"] in KINDS and not p["buckle"].startswith("sponge") \
            and not edge < KINDS[p["buckle"]][0] / 2:
        raise ValueError(f"buckle_edge = {edge} mm: the edges of the {p['buckle']} "
                         f"({KINDS[p['buckle']][0]} mm wide) lift over less than half its "
                         f"width; set buckle_edge below {KINDS[p['buckle']][0] / 2} mm")
    if p.get("sponge_end", 0.0) not in (0.0, CONVERGING_MODEL["sponge_end"]) \
            and not p["buckle"].startswith("sponge"):
        raise ValueError(f"sponge_end = {p['sponge_end']} mm rounds a sponge's ends; the "
                         f"{p['buckle']} is a ring: leave sponge_end out (its edges are "
                         "buckle_edge)")
    if p.get("buckle_body", "rigid") == "deformable":
        _check_deformable(given)
        if p.get("wall_element", "q1p0") != "q1p0":
            raise ValueError(f"wall_element = '{p['wall_element']}' is implemented with the "
                             "rigid buckle only (a deformable band's model replaces the solid); "
                             "set buckle_body = 'rigid' or wall_element = 'q1p0'")


DRAIN_FRACTION_MAX = 0.25
"""The largest drained volume, as a fraction of the vitreous cavity's (about 4.7 mL on the
default eye): beyond it the closed cavity collapses before the buckle is placed."""


SPONGE_SUTURE_GAP = 0.5
"""The least distance between two sutures of a sponge, mm."""


def _check_feasible(p):
    """Clear errors for surgical inputs no eye or buckle can carry out (the run would grind
    for minutes and fail, or end in a meaningless state): a drained volume beyond a
    quarter of the cavity, sutures shortened by more than the span they cross, more sutures
    than fit round the buckle."""
    g = eye_geometry(p)
    inner = g.scleral_radius - g.sclera_equator - g.choroid_thickness - g.retina_thickness
    cavity = 4.0 / 3.0 * np.pi * inner**3  # the vitreous sphere, mm^3 (the lens left in)
    drained = p.get("drain_volume", 0.0)
    if drained > DRAIN_FRACTION_MAX * cavity:
        raise ValueError(f"drain_volume = {drained:g} mm^3 (uL) is more than "
                         f"{DRAIN_FRACTION_MAX:.0%} of the vitreous cavity (about {cavity:.0f} "
                         f"mm^3 on this eye): the globe would collapse; drainage removes "
                         f"tens to a few hundred uL: give at most "
                         f"{DRAIN_FRACTION_MAX * cavity:.0f} mm^3")
    span = p.get("suture_width", 9.0)
    short = p.get("suture_tightening", 0.0)
    if short >= span:
        raise ValueError(f"suture_tightening = {short:g} mm: a suture loop cannot shorten by "
                         f"its whole span across the buckle (suture_width = {span:g} mm); "
                         "tied sutures shorten by tenths of a mm to about 1.5 mm: give less "
                         "than suture_width")
    n = p.get("n_sutures", 8)
    if p["buckle"].startswith("sponge"):  # spread over its central 60%; the bites may overlap
        room, gap = 0.6 * SPONGE_LENGTH, SPONGE_SUTURE_GAP
        fits = int(room // gap) + 1
        if n > fits:
            raise ValueError(f"n_sutures = {n}: a sponge's sutures are spread over its central "
                             f"{room:g} mm, and at most {fits} fit there {gap:g} mm apart; "
                             f"give n_sutures <= {fits} (cases 5 and 6 use 2)")
        return
    bite = max(2.0 * p.get("bite_radius", 0.0), 1.0)  # a bite's patch across, mm
    room = 2 * np.pi * g.scleral_radius
    fits = int(room // bite)
    if n > fits:
        raise ValueError(f"n_sutures = {n}: at most {fits} sutures fit round the globe's "
                         f"circumference ({room:.0f} mm) with bites {bite:g} mm across "
                         f"(bite_radius = {p.get('bite_radius', 0.0):g} mm); give n_sutures "
                         f"<= {fits}")


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
    for name, default, unit, what, why in (
            ("buckle_edge", CONVERGING_MODEL["buckle_edge"], " mm",
             "shapes the rigid ring's edges", "a deformable buckle has its own mesh"),
            ("sponge_end", CONVERGING_MODEL["sponge_end"], " mm", "rounds the rigid sponge's ends",
             "a deformable sponge has its own mesh"),
            ("contact_quadrature", 0, "", "integrates the rigid buckle's contact over the "
             "scleral faces", "a deformable buckle's contact is node to surface")):
        if p.get(name, default) != default:
            raise ValueError(f"{name} = {p[name]}{unit} {what}; {why}: with buckle_body = "
                             f"'deformable' leave {name} at {default}")
    if p["buckle"] == "sponge_radial" and p["tightening"] != 0:
        raise ValueError(f"tightening = {p['tightening']} mm: a deformable sponge is pressed in "
                         "by its sutures alone (suture_tightening); set tightening = 0")


def equatorial_ring(X, faces) -> np.ndarray:
    """Node ids (k,) of the globe's equatorial ring on the outer scleral surface: the closed
    path of surface edges through the widest node (largest distance from the eye axis z)
    that goes round the axis keeping nearest that node's z.

    Args: X (n_nodes, 3) reference positions, mm; faces (m, 4) the outer scleral quads.
    On the uniform levels with an even count per edge the ring is the node row in the
    plane z = 0; on graded levels and odd counts, whose rows near the equator are not
    plane, it is the row nearest the equator, never a few nodes of it."""
    nbrs = {}
    for a, b in face_edges(faces):
        nbrs.setdefault(int(a), set()).add(int(b))
        nbrs.setdefault(int(b), set()).add(int(a))
    nodes = np.array(sorted(nbrs))
    rho = np.hypot(X[:, 0], X[:, 1])
    phi = np.arctan2(X[:, 1], X[:, 0])
    start = int(nodes[np.argmax(rho[nodes])])
    z0 = X[start, 2]
    ring, cur, turned = [start], start, 0.0
    while True:
        ahead = [b for b in nbrs[cur]
                 if 0.0 < (phi[b] - phi[cur]) % (2 * np.pi) < np.pi / 4]
        if not ahead:
            raise ValueError(f"the orbit's equatorial ring: no surface edge leads round the "
                             f"eye axis from node {cur} (z = {X[cur, 2]:.4g} mm); the outer "
                             "scleral surface does not go round the globe")
        nxt = min(ahead, key=lambda b: abs(X[b, 2] - z0))
        turned += (phi[nxt] - phi[cur]) % (2 * np.pi)
        if nxt == start or turned >= 2 * np.pi - 1e-9:
            break
        if len(ring) >= len(nodes):
            raise ValueError("the orbit's equatorial ring: the path round the eye axis from "
                             f"node {start} does not close; the outer scleral surface is "
                             "not a closed band round the globe")
        ring.append(nxt)
        cur = nxt
    return np.sort(ring)  # ascending ids: the order the plane rows had, sums and all


def orbit_spring(mesh, p) -> OrbitSpring:
    """The orbit's hold on the globe: springs on the rigid rotation (N mm/rad) and the
    lateral and axial translation (N/mm) of the outer scleral ring at the equator (case
    fields globe_torsion, globe_rotation, globe_translation, globe_axial).

    On the nerve stub alone the globe twists, turns and shifts almost freely (about
    0.3 N mm/rad in torsion), held otherwise only by the buckle's smoothed contact
    forces. The passive stiffness of the extraocular muscles and orbital
    tissue is about 1 gram-force per degree at the tendon insertions (Robinson, 1975),
    7 N mm/rad at the scleral radius (globe_torsion). Against tilt (globe_rotation) the
    default is ten times that: during the operation the surgeon holds the globe by
    traction sutures under the rectus muscles, and with 7 N mm/rad the encircled globe
    (its nerve leaves 15 degrees nasally) has two equilibria late in the tightening of
    coarse case 2, tilted by 0.1 or 0.5 degrees, which the Newton path picks between
    (docs/surgery.md). The lateral hold of the orbital fat and Tenon's capsule, 1 N/mm by
    default, is an order-of-magnitude estimate. The axial hold is ten times that, for
    the same reason as the tilt's: without it an encircled globe is held along its axis
    by the nerve stub alone, and a sphere shifted along the axis of a ring round it
    changes the ring's contact radius only to second order (a tight ring even pushes it
    out), so that shift is nearly free, Newton crawls along it, and the outcomes hang on
    it: coarse case 2's largest suture force is 0.216 N without the hold, 0.162 N with
    0.1 N/mm and 0.142 N with 10 N/mm, where 3 N/mm moves no other outcome by more than
    0.05%. A deformation without net rotation or shift feels nothing."""
    ring = equatorial_ring(mesh.nodes, mesh.face_set("eye/sclera_outer"))
    k_rot = (p["globe_rotation"], p["globe_rotation"], p["globe_torsion"])
    return OrbitSpring("orbit", ring, mesh.nodes[ring], k_rot=k_rot,
                       k_trans=p["globe_translation"], k_axial=p["globe_axial"])


def pictures(parts: SurgeryParts, model, q, theta, out_dir: Path, *, summary=None,
             title: str = ""):
    """Meridional section (with a zoomed panel at the buckle, its indentation marked) and
    outside view, coloured by von Mises stress (kPa): section_von_mises.png and
    outside_von_mises.png in out_dir.

    Drawn: the buckle (a rigid one's surface; a deformable one's elements grey), the
    sutures, the undeformed outline (dashed). Title: ``title`` (default: the buckle and
    its placement from the case parameters), the stage and the headline outcomes of
    ``summary`` (a row of eyefem.eye.outcomes.stage_summary; default: the state's IOP and
    indentation from eyefem.eye.outcomes.outcomes). Returns the two Drawn records.
    """
    from eyefem.eye.outcomes import outcome_nodes, positions
    from eyefem.io.pictures import (
        Zoom,
        plane_basis,
        plot_outside,
        plot_section,
        section_segments,
    )

    mesh, p, b = model.mesh, parts.p, parts.buckle
    q = np.asarray(q)
    x = mesh.nodes + q[: 3 * mesh.n_nodes].reshape(-1, 3)
    vm = model.terms[0].fields(q, theta["solid"])["von_mises"] / 1e-3  # kPa
    names = [t.name for t in model.terms]
    rigid = model.term("buckle").geometry(q, theta["buckle"]) if "buckle" in names else None
    buckle = (rigid[0], rigid[2]) if rigid is not None and rigid[1] == "triangle" else None
    sut = model.term("sutures").geometry(q, theta["sutures"]) if "sutures" in names else None
    lines = (sut[0], sut[2], sut[3]["force_N"]) if sut is not None else None
    ph = np.radians(b.meridian_deg)
    if b.encircling and lines is not None and len(lines[1]):  # the section through a suture
        mid = np.asarray(lines[0])[np.asarray(lines[1])[0]].mean(0)
        ph = float(np.arctan2(mid[1], mid[0]))
    normal = (-np.sin(ph), np.cos(ph), 0.0)
    body = "band" if parts.band is not None else "sponge" if parts.sponge else None
    exclude = mesh.element_sets[body] if body else None
    name = "tire and band" if body == "band" and b.kind.startswith("tire") else body
    s = summary or {"stage": "final", **outcomes(parts, model, q, theta)}
    head = [f"IOP {s['iop_mmhg']:.1f} mmHg", f"indentation {s['indentation_mm']:.2f} mm"]
    for key, fmt in (("axial_length_change_mm", "axial length {:+.3f} mm"),
                     ("refraction_change_D", "refraction {:+.2f} D")):
        if key in s:
            head.append(fmt.format(s[key]))
    title = title or (f"{b.kind.replace('_', ' ')} ({p.get('buckle_body', 'rigid')}), "
                      f"tightening {p['tightening']:g} mm, suture width {p['suture_width']:g} "
                      f"mm, {b.distance:g} mm behind the limbus")
    full = f"{title}\nstage '{s['stage']}': " + ", ".join(head)
    nodes = outcome_nodes(parts)
    under, beside = (positions(mesh.nodes, q, bw.ids) for bw in (nodes.under, nodes.beside))
    e1 = plane_basis(normal)[0]
    near = (section_segments(buckle[0], buckle[1], normal).reshape(-1, 3) if buckle
            else under[np.abs(under @ np.asarray(normal)) < 2.0])  # at the buckle
    side = near[near @ e1 > 0]
    centre = (side if len(side) else under).mean(0)
    r_in = float(np.linalg.norm(under, axis=1).mean())
    r_out = float(np.linalg.norm(beside, axis=1).mean())
    zoom = Zoom(tuple(centre / np.linalg.norm(centre) * r_in), b.width / 2 + 3.5, r_in, r_out,
                f"indentation\n{s['indentation_mm']:.2f} mm")
    kw = {"label": "von Mises stress, kPa", "exclude": exclude, "buckle": buckle,
          "sutures": lines, "exclude_label": f"deformable {name} (grey: not to scale)"}
    section = plot_section(out_dir / "section_von_mises.png", x, mesh.hexes, vm, normal=normal,
                           title=full, reference=mesh.nodes, zoom=zoom,
                           buckle_thickness=b.thickness if b.encircling else 0.0,
                           buckle_tube=not b.encircling, near=3.0 if b.encircling else 6.0,
                           xlabel=f"meridian {np.degrees(ph):.0f}\N{DEGREE SIGN} from +x "
                                  "(+x nasal), mm", ylabel="z (+ anterior), mm", **kw)
    outside = plot_outside(out_dir / "outside_von_mises.png", x, mesh.hexes, vm, title=full,
                           directions={"nasal +x": (1, 0, 0), "+y": (0, 1, 0),
                                       "anterior +z": (0, 0, 1)},
                           buckle_lift=b.thickness if b.encircling else None,
                           azim=-60.0 if b.encircling else b.meridian_deg - 50.0, elev=15.0,
                           **kw)
    return section, outside


ADVANCED_FIELDS = frozenset({
    "globe_torsion", "globe_rotation", "globe_translation", "globe_axial", "steps_pressurise",
    "steps_tighten", "steps_suture", "contact_smoothing", "contact_quadrature",
    "contact_normals", "n_segments",
    "ridge_flank", "buckle_edge", "sponge_end", "bite_length", "limbus_width",
    "zonule_insertion_radius", "tissue_mixing",
    "liquid_bulk", "zonule_E", "suture_EA", "suture_angle_deg", "sclera_thickness_limbus",
    "sclera_thickness_equator", "sclera_thickness_pole", "wall_element", "lens_support",
    "model", "symmetry", *(f.name for f in TIMELINE_FIELDS), *(f.name for f in RELAXATION_FIELDS)})
"""Fields ``eyefem new-case surgery`` leaves at their defaults unless asked for all
(``--all``): the orbit's hold, load steps, contact, model and material details, the
timeline."""

DESCRIBE_FIRST = ("buckle", "buckle_body", "tightening", "band_tension",
                  "deformable_tightening", "buckle_distance", "buckle_meridian_deg",
                  "buckle_shift", "suture_width", "n_sutures", "suture_tightening",
                  "bite_radius", "iop_mmhg", "materials_preset", "drain_volume",
                  "volume_regulation", "paracentesis_volume", "paracentesis_delay_minutes",
                  "followup", "cra_closing_mmhg", "tissue_relaxation")
"""The fields ``eyefem describe surgery`` lists first, in this order: what a surgeon or a
researcher changes first (the buckle and its tightening, the sutures' placement, the
pressure, the tissues, the drainage, the timeline's switch, paracentesis and follow-up
times). The other fields outside DESCRIBE_ADVANCED follow (the mesh, the biometry)."""

DESCRIBE_ADVANCED = ADVANCED_FIELDS - set(DESCRIBE_FIRST)
"""The fields ``eyefem describe surgery`` lists under its "Advanced" heading: the numerical
settings and model details (ADVANCED_FIELDS, less the timeline's switches listed first)."""

SEGMENTAL_DEFAULTS = {"n_sutures": 2, "suture_width": 8.5, "tightening": 0.0}
"""A segmental sponge's defaults in ``new-case`` (those of cases 5 and 6)."""

IOP_PERFUSION_MMHG = 60.0
"""Post-surgery IOP above which a run warns: about the pressure at which the central
retinal artery stops perfusing the retina (the ophthalmic artery's diastolic pressure)."""

NEW_CASE_DEFAULTS = {"materials_preset": "physiological"}
"""``new-case``'s defaults for every buckle: a new case gets the calibrated tissues (the
field's own default, for case files that leave it out, stays the seed's, so that the
seed's cases 1-6 reproduce)."""

REGULATED_NEW_CASE = {"volume_regulation": True}
"""``new-case``'s default, asked, for the calibrated tissues without a drained volume: the
surgery's timeline (docs/surgery_timeline.md). The calibrated eye's closed cavity, which
loses no liquid, ends a new case's surgery on the coarse mesh at 622 mmHg (its steps cut
on the way); on the timeline the same case peaks at 77 mmHg on the table, ends the surgery
at 28 mmHg and is at 17 mmHg after 48 hours."""


def regulated_by_default(values: dict) -> bool:
    """Whether ``new-case`` proposes the timeline (REGULATED_NEW_CASE) for these answers:
    the calibrated tissues and no volume drained."""
    return (values.get("materials_preset") == "physiological"
            and float(values.get("drain_volume", 0.0)) == 0.0)


def questions(values: dict) -> tuple[frozenset, dict]:
    """What ``eyefem new-case surgery`` asks, given the answers so far (``values``, with
    every field's default filled in): (names of the fields that do not apply to the chosen
    buckle, or are advanced: not asked, kept at their defaults; the chosen buckle's own
    defaults, name -> value: NEW_CASE_DEFAULTS, a sponge's SEGMENTAL_DEFAULTS, the
    CONVERGING_MODEL's fields that apply to it (:func:`model_fields`) and, for the
    calibrated tissues without a drained volume, the timeline (REGULATED_NEW_CASE, asked),
    written into the case so that it states its model)."""
    segmental = values["buckle"].startswith("sponge")
    skip = set(ADVANCED_FIELDS)
    skip |= ({"band_tension", "deformable_tightening"} if segmental
             else {"buckle_meridian_deg"})
    if values["buckle_body"] == "rigid":
        skip.add("deformable_tightening")
    model = ({k: CONVERGING_MODEL[k] for k in model_fields({**values, **CONVERGING_MODEL})}
             if values.get("model", "converged") == "converged" else {})
    regulated = {}
    if regulated_by_default(values):
        regulated = dict(REGULATED_NEW_CASE)
        skip -= set(REGULATED_NEW_CASE)
    return frozenset(skip), {**NEW_CASE_DEFAULTS, **(SEGMENTAL_DEFAULTS if segmental else {}),
                             **model, **regulated}


CURVED_CONTACT_SOLVER = {"contact_curvature": 1e-3}
"""The ``[solver]`` settings of the case files whose rigid buckle's surface curves sharply
under the nodes it presses (the ridged tire's shoulders, a sponge's rounded ends): the
contact tangent without the surface's curvature while the step's residual is above 1e-3 of
its first (``NewtonOptions.contact_curvature``); with the exact tangent that curvature, a
negative tangential stiffness, can make the tangent singular (docs/convergence.md, "The
sponge's ends")."""


def solver_settings(values: dict) -> dict:
    """The ``[solver]`` section ``eyefem new-case surgery`` writes for these parameters
    (``values``: every field, defaults filled in): CURVED_CONTACT_SOLVER for a rigid ridged
    tire and a rigid sponge with rounded ends, else nothing. These are the solver's
    defaults for such a case: a case file whose ``[solver]`` leaves them out wants them
    too."""
    values = resolve_model(values)
    if values["buckle_body"] != "rigid":
        return {}
    curved = (values["buckle"] == "tire_ridged"
              or (values["buckle"].startswith("sponge") and values.get("sponge_end", 0) > 0))
    return dict(CURVED_CONTACT_SOLVER) if curved else {}


surgery.check = check_parameters
surgery.questions = questions
surgery.solver_settings = solver_settings
surgery.first = DESCRIBE_FIRST
surgery.advanced = DESCRIBE_ADVANCED
PROBLEMS = {"surgery": (SURGERY_FIELDS, surgery)}
