"""A patient's eye from the biometry a clinic measures: the case-file fields and the
EyeGeometry they give.

Measured (optical biometry, keratometry, pachymetry): axial length, anterior corneal
radius, central corneal thickness, anterior chamber depth. Scleral thickness is rarely
measured; its defaults are published averages (limbus 0.5, equator 0.4, posterior pole
1.0 mm; eyefem.eye.eyemodel). The globe is scaled with the axial length: the scleral
radius is 11.5 mm x axial length / 24 mm (an eye that is longer is larger, not only
longer: a simplification of axial myopia, which stretches the posterior globe more), and
the lens keeps its size, its anterior pole at the given depth behind the corneal apex.
"""

from __future__ import annotations

import dataclasses

from eyefem.eye.eyemodel import EyeGeometry
from eyefem.io.casefile import Field, positive

REFERENCE = EyeGeometry()
"""The default eye (axial length 24 mm)."""

BIOMETRY_FIELDS = [
    Field("axial_length", float, REFERENCE.axial_length,
          "axial length, corneal apex to the outer posterior pole, mm (the globe is scaled "
          "with it)", positive, "> 0", warn=(20.0, 32.0), refuse=(14.0, 40.0), unit="mm",
          slips=(("cm", 10.0),)),
    Field("corneal_radius", float, REFERENCE.cornea_radius,
          "anterior corneal radius of curvature (keratometry: 337.5 / K in dioptres), mm",
          positive, "> 0", warn=(6.5, 9.5), refuse=(4.0, 14.0), unit="mm"),
    Field("central_corneal_thickness", float, REFERENCE.cornea_thickness,
          "central corneal thickness, mm", positive, "> 0", warn=(0.4, 0.7),
          refuse=(0.1, 1.5), unit="mm", slips=(("um", 1e-3),)),
    Field("anterior_chamber_depth", float,
          REFERENCE.lens_centre_depth - REFERENCE.lens_thickness / 2,
          "anterior chamber depth, corneal apex to the anterior lens pole, mm", positive,
          "> 0", warn=(2.0, 4.5), refuse=(1.0, 6.0), unit="mm"),
    Field("sclera_thickness_limbus", float, REFERENCE.sclera_limbus,
          "scleral thickness at the limbus, mm", positive, "> 0", warn=(0.3, 0.9),
          refuse=(0.1, 2.0), unit="mm", slips=(("um", 1e-3),)),
    Field("sclera_thickness_equator", float, REFERENCE.sclera_equator,
          "scleral thickness at the equator, mm", positive, "> 0", warn=(0.25, 0.8),
          refuse=(0.1, 2.0), unit="mm", slips=(("um", 1e-3),)),
    Field("sclera_thickness_pole", float, REFERENCE.sclera_pole,
          "scleral thickness at the posterior pole, mm", positive, "> 0", warn=(0.6, 1.5),
          refuse=(0.1, 3.0), unit="mm", slips=(("um", 1e-3),)),
    Field("limbus_width", float, 1.5,
          "arc width of the limbus ring (a tissue between cornea and sclera), mm: the wall "
          "elements whose centroid lies within it (1.5: the anatomical limbus); 0: the ring "
          "of elements the corneoscleral junction passes through, one element wide "
          "(narrower on finer meshes; docs/convergence.md, 'The limbus ring')",
          lambda v: v == 0 or 0.5 <= v <= 3, "0 (one element) or 0.5 to 3 mm"),
    Field("zonule_insertion_radius", float, 0.0,
          "radius of the disc of the ciliary body over which each zonule bar pulls, mm; the "
          "bars then share the zonule's cross-section (0.24 mm^2), so the eye's rigidity is "
          "the same on every mesh level; 0: each bar pulls on a point with 0.01 mm^2 (the "
          "recorded results' model, which changes with the mesh; docs/convergence.md, "
          "'The zonule')",
          lambda v: v == 0 or 0.5 <= v <= 3, "0 (point insertions) or 0.5 to 3 mm"),
    Field("lens_support", float, 0.0,
          "the springs that hold the floating lens in place, N/mm in all, shared by its "
          "nodes, so the lens is held alike on every mesh level (0.343: the default level's "
          "sum); 0: 1e-3 N/mm on every lens node (the recorded results' model, whose sum "
          "follows the lens mesh: 0.125 N/mm on the coarse level, 2.2 on finer; "
          "docs/convergence.md, 'The lens's support')",
          lambda v: v == 0 or 1e-4 <= v <= 100, "0 (per node) or 1e-4 to 100 N/mm"),
    Field("tissue_mixing", bool, False,
          "true: a wall element that a tissue boundary cuts (cornea, limbus ring, ciliary "
          "body, optic disc) stores the mixture of the tissues' energies in the proportions "
          "of its volume, so the tissues keep their size and place on every mesh level; "
          "false: each element is wholly the tissue of its centroid (staircase boundaries; "
          "the recorded results' model; docs/convergence.md, 'Tissue boundaries')"),
]
"""Case-file fields of a patient's biometry (the surgery and pressure_volume problems)."""


def eye_geometry(p: dict) -> EyeGeometry:
    """The EyeGeometry of the biometry fields in parameters ``p`` (defaults where absent).

    Raises ValueError (naming the fields) when the measurements do not make an eye: the
    lens would reach the cornea or the corneal and scleral spheres would not meet."""
    b = {f.name: p.get(f.name, f.default) for f in BIOMETRY_FIELDS}
    scale = b["axial_length"] / REFERENCE.axial_length
    if b["anterior_chamber_depth"] <= b["central_corneal_thickness"]:
        raise ValueError(f"anterior_chamber_depth = {b['anterior_chamber_depth']} mm is not "
                         f"beyond the cornea (central_corneal_thickness = "
                         f"{b['central_corneal_thickness']} mm); the depth is measured from "
                         "the corneal apex (epithelium) to the lens")
    g = dataclasses.replace(
        REFERENCE, axial_length=b["axial_length"],
        scleral_radius=REFERENCE.scleral_radius * scale,
        cornea_radius=b["corneal_radius"], cornea_thickness=b["central_corneal_thickness"],
        sclera_limbus=b["sclera_thickness_limbus"], sclera_equator=b["sclera_thickness_equator"],
        sclera_pole=b["sclera_thickness_pole"],
        lens_centre_depth=b["anterior_chamber_depth"] + REFERENCE.lens_thickness / 2,
        limbus_width=b["limbus_width"] or None,
        zonule_insertion_radius=b["zonule_insertion_radius"] or None,
        tissue_mixing=bool(b["tissue_mixing"]), lens_support=b["lens_support"] or None)
    try:
        g.limbus_angle  # noqa: B018 - raises if the corneal and scleral spheres do not meet
    except ValueError as exc:
        raise ValueError(f"axial_length = {b['axial_length']} mm with corneal_radius = "
                         f"{b['corneal_radius']} mm: {exc}") from None
    return g
