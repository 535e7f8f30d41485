"""The design variables of a surgery case and the outcomes the adjoint differentiates."""

from __future__ import annotations

from eyefem.eye.presets import SEED_MATERIALS
from eyefem.eye.surgery import SURGERY_FIELDS

TIMELINE_VARIABLES = {
    "paracentesis_volume": "aqueous removed by the anterior chamber paracentesis, uL (= mm^3; "
                           "cases on the timeline, volume_regulation = true)",
    "paracentesis_delay_minutes": "when the paracentesis is done, minutes after the end of the "
                                  "tightening (cases on the timeline; the outcomes are smooth "
                                  "in it: eyefem.eye.timeline.timed_stages)",
}
"""The surgical variables of the surgery's timeline (eyefem.eye.timeline): they vary only
in cases with volume_regulation = true (eyefem.eye.simulators.TimelineSimulator)."""
SURGICAL_VARIABLES = {
    "tightening": "band circumference shortening (segmental: radial push x 2 pi), mm",
    "buckle_shift": "posterior shift of the fitted buckle along the meridian, mm",
    "buckle_meridian_deg": "meridian of a segmental buckle, degrees",
    "suture_width": "bite span across the buckle, mm",
    "suture_tightening": "shortening of each suture loop when tied, mm",
    "drain_volume": "fluid drained during stage 2, mm^3",
    "band_tension": "tension of a pulled encircling band (cases with band_tension > 0), N",
    **TIMELINE_VARIABLES,
}
MATERIAL_VARIABLES = {
    **{f"c10_{m}": f"neo-Hookean c10 of the {m.replace('_', ' ')}, MPa" for m in SEED_MATERIALS},
    "zonule_E": "Young's modulus of the zonule, MPa",
    "liquid_bulk": "bulk modulus of the cavity liquid, MPa",
    "suture_EA": "axial stiffness of the sutures, N",
}
DESIGN_VARIABLES = {**SURGICAL_VARIABLES, **MATERIAL_VARIABLES}
STAGE1_VARIABLES = tuple(f"c10_{m}" for m in SEED_MATERIALS) + ("zonule_E",)
"""The design variables that change the pre-operative (pressurised) eye."""
OUTCOMES = {
    "iop_mmhg": "post-operative IOP (cavity pressure), mmHg",
    "indentation_mm": "buckle indentation height, mm",
    "axial_length_change_mm": "axial length change since the pre-operative state, mm",
    "max_suture_force_N": "force in the most loaded suture bar, N",
    "refraction_change_D": "refraction change in the reduced eye, dioptres (negative: myopic)",
    "corneal_power_change_D": "change of the mean keratometric power, dioptres",
    "corneal_astigmatism_D": "corneal astigmatism (difference of principal powers), dioptres",
    "anterior_chamber_depth_change_mm": "anterior chamber depth change, mm",
}
OPTICAL_CHANGES = ("axial_length_change_mm", "refraction_change_D", "corneal_power_change_D",
                   "anterior_chamber_depth_change_mm")
"""Outcomes measured from the pre-operative eye (eyefem.eye.outcomes.changes): their
gradients have a stage-1 part through the pre-operative state."""


def default_parameters(**overrides) -> dict:
    """Surgery case parameters with defaults (see eyefem.eye.surgery)."""
    p = {f.name: f.default for f in SURGERY_FIELDS}
    unknown = set(overrides) - set(p)
    if unknown:
        raise ValueError(f"unknown surgery parameters {sorted(unknown)}; known: {sorted(p)}")
    p.update(overrides)
    return p

MATERIAL_PARAMS = (("solid", "coeffs"), ("zonule", "EA"))
"""The params of the design's material constants that stage 1 (the pre-operative eye) sees."""
STAGE_PARAMS = {
    1: MATERIAL_PARAMS,
    2: MATERIAL_PARAMS + (("cavity", "bulk"), ("cavity", "dv"), ("band_pull", "f"))
    + tuple((t, k) for t in ("buckle", "sutures") for k in ("d", "s", "rot"))
    + (("sutures", "EA"), ("sutures", "xi")),
}
STAGE_PARAMS[3] = STAGE_PARAMS[2] + (("sutures", "tightening"),)
"""(term, param) pairs each stage takes from the design (design_map); the suture
tightening only once the sutures are tied (stage 3)."""
