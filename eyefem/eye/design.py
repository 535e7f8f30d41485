"""The design of a surgery case: its variables, and where its simulators live.

The design variables (DESIGN_VARIABLES: the surgical ones and the material constants;
SURGICAL_VARIABLES, MATERIAL_VARIABLES, TIMELINE_VARIABLES), the outcomes (OUTCOMES) and
the stages' params are declared in eyefem.eye.variables; the simulators of designs and
their adjoint gradients (SurgerySimulator, TimelineSimulator, RingSimulator) are in
eyefem.eye.simulators; the stages they differentiate, with what each hands on
(preop_carry, tied_lengths), are the buckle bodies' (eyefem.eye.bodies). This module
re-exports them under one name (``eyefem.eye.design.SurgerySimulator`` is
eyefem.eye.simulators.SurgerySimulator; the docs name the defining modules); it defines
nothing.
"""

from eyefem.eye.bodies import preop_carry, tied_lengths
from eyefem.eye.simulators import (
    Preop,
    Result,
    RingResult,
    RingSimulator,
    StagedSimulator,
    SurgerySimulator,
    TimelineResult,
    TimelineSimulator,
    term_kind,
    whole_eye,
)
from eyefem.eye.variables import (
    DESIGN_VARIABLES,
    MATERIAL_PARAMS,
    MATERIAL_VARIABLES,
    OPTICAL_CHANGES,
    OUTCOMES,
    STAGE1_VARIABLES,
    STAGE_PARAMS,
    SURGICAL_VARIABLES,
    TIMELINE_VARIABLES,
    default_parameters,
)

__all__ = [
    "DESIGN_VARIABLES",
    "MATERIAL_PARAMS",
    "MATERIAL_VARIABLES",
    "OPTICAL_CHANGES",
    "OUTCOMES",
    "Preop",
    "Result",
    "RingResult",
    "RingSimulator",
    "STAGE1_VARIABLES",
    "STAGE_PARAMS",
    "SURGICAL_VARIABLES",
    "StagedSimulator",
    "SurgerySimulator",
    "TIMELINE_VARIABLES",
    "TimelineResult",
    "TimelineSimulator",
    "default_parameters",
    "preop_carry",
    "term_kind",
    "tied_lengths",
    "whole_eye",
]
