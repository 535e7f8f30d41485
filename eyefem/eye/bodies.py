"""Buckle bodies: how each kind of buckle enters the surgery, behind one interface.

A :class:`BuckleBody` says what it adds to the eye mesh (a deformable buckle's
elements), which terms it contributes (its contact on the sclera, its sutures, what
holds it), which stages follow the pressurised eye (fitting the buckle, tightening,
suturing) and which outcomes it reports beside the common ones
(:func:`eyefem.eye.outcomes.outcomes`). :func:`eyefem.eye.surgery.surgery` assembles an
eye, a body and the procedure without a branch per buckle kind.

The bodies:

- :class:`RigidBuckle`: the exact analytic ring (band, flat or ridged tire) or sponge,
  moved radially by the tightening, or a ring pulled by a band tension (force control);
- :class:`DeformableRing`: a hexahedral silicone band or tire with its band
  (:mod:`eyefem.eye.band`), tightened by its pulled ends or its shortened rest length;
- :class:`DeformableSponge`: a hexahedral silicone sponge sewn on (:mod:`eyefem.eye.sponge`).

Stage hooks (``Stage.before``) return a new model; the parts they were built from are
never changed (a refitted deformable buckle lives in the new model's mesh). What the
stages hand on, as the design gradients differentiate it (eyefem.eye.simulators), is
written here once in JAX: :func:`preop_carry` (the closed volume, the snug scale, the
pre-operative optics) and :func:`tied_lengths` (the sutures' rest lengths, which the
suture stage's hook :func:`tie_sutures` evaluates).
"""

from __future__ import annotations

import abc
import dataclasses
import logging
from typing import Callable

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
    three_bar_shortening,
    three_bar_tightening,
    tightened_band,
    with_band,
    with_refitted_terms,
)
from eyefem.eye.buckle_meshes import band_n_circ, deformable_band
from eyefem.eye.buckles import KINDS, Buckle
from eyefem.eye.eyemodel import EyeGeometry
from eyefem.eye.outcomes import eye_optics
from eyefem.eye.parts import SurgeryParts, drained, snug_scale
from eyefem.eye.presets import SEED_MATERIALS
from eyefem.eye.rigid_buckle import buckle_term, rigid_design_params, suture_term
from eyefem.eye.sponge import (
    SPONGE_PARK,
    fit_sponge,
    sponge_contact_term,
    sponge_mesh,
    sponge_spring_term,
    sponge_suture_term,
)
from eyefem.fem.cavity import cavity_pressures, close_cavity
from eyefem.fem.loop_solid import ShortenedLoopSolid
from eyefem.fem.mesh import Mesh
from eyefem.fem.terms import DofForce, Term, host_kernel
from eyefem.solve.model import Model, node_dofs
from eyefem.solve.solver import Stage

log = logging.getLogger(__name__)

BASE_TERMS = ("solid", "zonule", "lens_springs", "orbit")
"""The terms active in every stage of the surgery."""


@dataclasses.dataclass(frozen=True)
class LoadPath:
    """What the stages of every buckle share.

    Attributes:
      fixed: (k,) the dofs held at zero throughout (the optic nerve's end).
      extra_dof: the rigid buckle's radial motion (held unless it is an unknown).
      p_iop: the pre-operative IOP the eye is pressurised to, MPa.
    """

    fixed: np.ndarray
    extra_dof: int
    p_iop: float

    @property
    def held(self) -> tuple[np.ndarray, np.ndarray]:
        """The nerve's end and the buckle's radial motion held: (dofs, values)."""
        return np.r_[self.fixed, self.extra_dof], np.zeros(len(self.fixed) + 1)

    def pressurise(self, steps: int, prescribed) -> Stage:
        """Stage 1: the surface pressure raised to the IOP, the cavity open."""
        return Stage("pressurise", steps, prescribed, params={"iop": {"p": self.p_iop}},
                     active=BASE_TERMS + ("iop",))


def tied_lengths(sut) -> Callable:
    """The suture-tying rule, C_2 of the staged adjoint (eyefem.solve.staged.StageMap's
    carry of the stage that the sutures are tied after): (q, theta, data) -> {"L0": (n,)
    the suture bars' lengths at q, mm}; data: (the suture term's data, dofs); ``sut``: a
    suture term of the kind whose data it receives (its methods only). JAX; the forward
    run's hook :func:`tie_sutures` evaluates it, the design gradients differentiate it."""
    def carry(q, theta, data):
        sut_data, sut_dofs = data
        return {"L0": sut.lengths(q[sut_dofs], theta["sutures"], sut_data)}
    return carry


def preop_carry(parts: SurgeryParts, nodes, snug: bool) -> Callable:
    """C_1, what the pressurised eye hands on: (q, theta, data) -> {"volume": the cavity's
    volume at q (mm^3, closed at it), "optics": its eyefem.eye.outcomes.eye_optics (the
    pre-operative eye the changes are measured from)} and, with ``snug``, "scale": the
    buckle's snug radial scale (eyefem.eye.parts.snug_scale at data["node"]); data:
    {"cavity": (the FluidCavity's data, dofs), "node": the snug node}. JAX: the volume and
    scale at which the stage hooks that place a buckle close the cavity and fit it
    (close_cavity, snug_scale), as the design gradients differentiate them."""
    X = parts.eye.mesh.nodes

    def preop(q, theta, data):
        out = {"volume": cavity_pressures(q, theta["cavity"], *data["cavity"])[1][0],
               "optics": eye_optics(X, q, nodes)}
        if snug:
            out["scale"] = snug_scale(parts, q, data["node"])
        return out
    return preop


def tied(sutures: dict, L0) -> dict:
    """The suture term's params ``sutures`` tied at lengths L0 (n,), mm: their rest lengths
    L0 and "tied" = 1 (numpy or JAX; the rule of the suture stage's hook
    :func:`tie_sutures` and of the design simulators' T_3)."""
    return {**sutures, "L0": L0, "tied": np.ones(np.shape(L0))}


def tie_sutures(model, q, theta):
    """Stage hook: the sutures tied at their current lengths (their rest lengths L0, by
    :func:`tied_lengths`)."""
    t = model.term("sutures")
    # tied_lengths' rule, its term method compiled once per term class (host_kernel): one
    # small XLA program, where eager JAX compiles one per operation
    L = np.asarray(host_kernel(t, "lengths")(np.asarray(q)[t.dofs], theta["sutures"], t.data))
    return model, q, {**theta, "sutures": tied(theta["sutures"], L)}


class BuckleBody(abc.ABC):
    """One kind of buckle in the surgery (see the module docstring)."""

    body_set: str | None = None
    """The mesh's node / element set of a deformable buckle (None: a rigid one)."""
    summary_outcomes: tuple[str, ...] = ()
    """Outcomes of the last step copied into the run's summary."""

    def warn(self, p: dict, buckle: Buckle) -> None:
        """Log what is known not to run to the end with these settings (default: nothing)."""

    def with_mesh(self, mesh: Mesh, buckle: Buckle, g: EyeGeometry, p: dict
                  ) -> tuple[Mesh, BandInfo | None]:
        """The eye mesh with the buckle's own elements (default: none) and band node ids."""
        return mesh, None

    @abc.abstractmethod
    def terms(self, parts: SurgeryParts) -> tuple[Term, Term, tuple[Term, ...]]:
        """(contact "buckle", sutures "sutures", the terms that hold the buckle)."""

    def model(self, model: Model, parts: SurgeryParts) -> Model:
        """The assembled model, adapted to the body (default: unchanged)."""
        return model

    @abc.abstractmethod
    def stages(self, parts: SurgeryParts, path: LoadPath) -> list[Stage]:
        """The load path: pressurise, fit and tighten (or place), suture."""

    def outcomes(self, parts: SurgeryParts, model: Model, q, theta) -> dict:
        """The body's own outcomes at state q (default: none)."""
        return {}


class RigidBuckle(BuckleBody):
    """The exact analytic ring or sponge (eyefem.fem.buckle_contact), fitted snug on the
    pressurised eye and moved radially by d = tightening x d_per_mm; a ring with
    band_tension > 0 is pulled by that force instead (its radial motion an unknown)."""

    def terms(self, parts):
        pulled = parts.p["band_tension"] > 0
        pull = (DofForce("band_pull", parts.extra_dof, gain=1.0 / parts.d_per_mm),) if pulled else ()
        return buckle_term(parts, 1.0), suture_term(parts, 1.0), pull

    def stages(self, parts, path):
        p, b = parts.p, parts.buckle
        held, held_eye = path.held, (path.fixed, np.zeros(len(path.fixed)))

        def place_buckle(model, q, theta):
            model, q, theta = close_cavity(model, q, theta, "cavity", "iop")
            scale = float(snug_scale(parts, q))
            sut, new_buckle = suture_term(parts, scale), buckle_term(parts, scale)
            return model.with_terms([new_buckle if t.name == "buckle" else
                                     sut if t.name == "sutures" else t
                                     for t in model.terms]), q, theta

        tighten, suture = rigid_design_params(parts, p)
        motion = {k: np.full(1, v) for k, v in tighten["buckle"].items()}
        ridge = {"ridge": np.full(1, KINDS[b.kind][2])}
        pulled = "band_pull" in tighten
        # a pulled band (force control) moves freely: its radial motion is an unknown
        held_band = held_eye if pulled else held
        pull = {"band_pull": tighten["band_pull"]} if pulled else {}
        return [
            path.pressurise(p["steps_pressurise"], held),
            Stage("tighten" if b.encircling else "place", p["steps_tighten"], held_band,
                  params={"buckle": {**motion, **ridge}, "sutures": motion,
                          "cavity": tighten["cavity"], **pull},
                  active=BASE_TERMS + ("cavity", "buckle") + tuple(pull), before=place_buckle),
            Stage("suture", p["steps_suture"], held_band if b.encircling else held_eye,
                  params={"sutures": {"tightening": np.full(
                      2 * p["n_sutures"], suture["sutures"]["tightening"])}},
                  active=BASE_TERMS + ("cavity", "buckle", "sutures") + tuple(pull),
                  before=tie_sutures),
        ]

    def outcomes(self, parts, model, q, theta):
        motion = float(q[parts.extra_dof])
        return {"buckle_free_motion_mm": motion,
                "band_shortening_mm": (parts.p["tightening"] + motion / parts.d_per_mm
                                       if parts.buckle.encircling else 0.0)}


class DeformableRing(BuckleBody):
    """A hexahedral silicone band, or tire with its band (eyefem.eye.band): parked off the
    sclera while the eye is pressurised, refitted snug (its stress-free state) when the
    cavity closes, tightened by its pulled ends or its shortened rest length, then sewn."""

    body_set = "band"
    summary_outcomes = BAND_OUTPUTS

    def warn(self, p, buckle):
        if p["mesh"] not in ("coarse", "default"):
            log.warning("deformable %s on the %s eye mesh: the deformable band and tires have "
                        "been run to the end on the coarse and default eyes only, with their "
                        "case files' settings (docs/surgery_deformable.md)", buckle.kind, p["mesh"])

    def with_mesh(self, mesh, buckle, g, p):
        # parked BAND_PARK mm off the sclera until stage 2 fits it snug
        n_circ = band_n_circ(mesh, mesh.node_set("eye/sclera_outer"), buckle, g)
        closed = p["deformable_tightening"] == "shortened_loop"
        mesh = with_band(mesh, deformable_band(buckle, g, g.scleral_radius + BAND_PARK, n_circ,
                                               closed=closed))
        return mesh, BandInfo(mesh, n_circ, closed)

    def terms(self, parts):
        return (band_contact_term(parts, SEED_MATERIALS["sclera"]), band_suture_term(parts),
                (band_spring_term(parts),))

    def model(self, model, parts):
        if not parts.band.closed:
            return model
        s = model.term("solid")  # the band's loop tightened by its rest length
        loop = ShortenedLoopSolid(s.name, model.mesh, s.coeffs, s.multiplier_offset,
                                  loop_nodes=parts.band.nodes)
        return model.with_terms([loop] + [t for t in model.terms if t is not s])

    def stages(self, parts, path):
        p, mesh = parts.p, parts.eye.mesh

        def place_band(model, q, theta):
            """Close the cavity; refit the (held, undeformed) band snug on the pressurised
            eye: its stress-free state is the snug fit."""
            model, q, theta = close_cavity(model, q, theta, "cavity", "iop")
            scale = float(snug_scale(parts, q))
            fitted = parts.refitted(fit_band(parts, scale, q), scale)
            contact = band_contact_term(fitted, SEED_MATERIALS["sclera"]).update(q, None)
            return with_refitted_terms(model, fitted.eye.mesh, {
                "buckle": contact, "sutures": band_suture_term(fitted),
                "band_springs": band_spring_term(fitted)}), q, theta

        held, _ = path.held
        band_all = node_dofs(mesh.node_set("band"))
        held = (np.r_[held, band_all], np.zeros(len(held) + len(band_all)))
        tightened = tightened_band(parts, np.r_[path.fixed, path.extra_dof], p["tightening"])
        band_terms = ("cavity", "buckle", "band_springs")
        tighten, suture = self.design_params(parts, {k: p[k] for k in self.VARIABLES})
        return [
            path.pressurise(p["steps_pressurise"], held),
            Stage("tighten", p["steps_tighten"], tuple(tightened), params=tighten,
                  active=BASE_TERMS + band_terms, before=place_band),
            Stage("suture", p["steps_suture"], tuple(tightened), params=suture,
                  active=BASE_TERMS + band_terms + ("sutures",), before=tie_sutures),
        ]

    VARIABLES = ("tightening", "suture_tightening", "drain_volume", "liquid_bulk", "suture_EA")
    """The design variables the ring's stages take as params (the tightening: of a closed
    loop, deformable_tightening = 'shortened_loop'; the pulled ends' is a prescribed
    displacement)."""

    @staticmethod
    def design_params(parts: SurgeryParts, design) -> tuple[dict, dict]:
        """The params (term -> param -> value; numpy or JAX) the design (VARIABLES: name
        -> value) sets in the tightening stage (cavity: the drained volume,
        eyefem.eye.parts.drained, and bulk = liquid_bulk; a closed loop's rest-length
        shortening = tightening) and those the suture stage adds (the sutures' three-bar
        shortenings and EA)."""
        tighten = {"cavity": {**drained(design["drain_volume"]), "bulk": design["liquid_bulk"]}}
        if parts.band.closed:
            tighten["solid"] = {"shortening": design["tightening"]}
        n = parts.p["n_sutures"]
        suture = {"sutures": {"tightening": three_bar_shortening(design["suture_tightening"], n),
                              "EA": np.ones(3 * n) * design["suture_EA"]}}
        return tighten, suture

    def outcomes(self, parts, model, q, theta):
        return band_outcomes(parts, model, q, theta)


class DeformableSponge(BuckleBody):
    """A hexahedral silicone sponge (eyefem.eye.sponge): parked off the sclera while the
    eye is pressurised, refitted snug when the cavity closes, pressed in by its sutures."""

    body_set = "sponge"

    def warn(self, p, buckle):
        if p["mesh"] != "coarse" and (p["buckle_meridian_deg"] % 90 == 0 or
                                      p["contact_normals"] != "nodal" or not p["globe_axial"]):
            log.warning("deformable %s on the %s eye mesh at meridian %g deg, contact_normals "
                        "= '%s', globe_axial = %g: off the coarse eye the deformable sponge has "
                        "run to the end with the settings of cases/surgery/"
                        "deformable_sponge_default.toml (a meridian off the eye mesh's "
                        "symmetry planes, contact_normals = 'nodal', globe_axial = 1); at "
                        "meridian 0 its suture steps were cut until they stopped "
                        "(docs/surgery_deformable.md)", buckle.kind, p["mesh"], p["buckle_meridian_deg"],
                        p["contact_normals"], p["globe_axial"])

    def with_mesh(self, mesh, buckle, g, p):
        # parked SPONGE_PARK mm off the sclera until stage 2 fits it snug
        return with_band(mesh, sponge_mesh(buckle, g, p["mesh"], SPONGE_PARK), "sponge"), None

    def terms(self, parts):
        mesh, b, p = parts.eye.mesh, parts.buckle, parts.p
        sutures, _ = sponge_suture_term(mesh, b, parts.frame, p)
        return (sponge_contact_term(mesh, SEED_MATERIALS["sclera"], p["contact_normals"]),
                sutures, (sponge_spring_term(mesh, b, parts.eye.geometry),))

    def stages(self, parts, path):
        p, b, g, mesh = parts.p, parts.buckle, parts.eye.geometry, parts.eye.mesh

        def place_sponge(model, q, theta):
            """Close the cavity; refit the (held, undeformed) sponge snug on the
            pressurised eye."""
            model, q, theta = close_cavity(model, q, theta, "cavity", "iop")
            scale = float(snug_scale(parts, q))
            new_mesh = fit_sponge(mesh, b, g, p["mesh"], scale, q, p["contact_normals"])
            sut, _ = sponge_suture_term(new_mesh, b, parts.frame, p)
            return with_refitted_terms(model, new_mesh, {
                "buckle": sponge_contact_term(new_mesh, SEED_MATERIALS["sclera"],
                                              p["contact_normals"]).update(q, None),
                "sutures": sut, "sponge_springs": sponge_spring_term(new_mesh, b, g)}), q, theta

        held, _ = path.held
        sponge_all = node_dofs(mesh.node_set("sponge"))
        parked = (np.r_[held, sponge_all], np.zeros(len(held) + len(sponge_all)))
        sponge_terms = ("cavity", "buckle", "sponge_springs")
        return [
            path.pressurise(p["steps_pressurise"], parked),
            Stage("place", 1, parked, params={"cavity": drained(p["drain_volume"])},
                  active=BASE_TERMS + sponge_terms, before=place_sponge),
            Stage("suture", p["steps_suture"], path.held,
                  params={"sutures": {"tightening": three_bar_tightening(p)}},
                  active=BASE_TERMS + sponge_terms + ("sutures",), before=tie_sutures),
        ]


def buckle_body(p: dict, buckle: Buckle) -> BuckleBody:
    """The body of the case's buckle (case fields buckle_body and buckle)."""
    if p.get("buckle_body", "rigid") == "rigid":
        return RigidBuckle()
    return DeformableRing() if buckle.encircling else DeformableSponge()
