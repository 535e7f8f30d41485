"""What the surgery problem is built from: the eye, the buckle, the case parameters."""

from __future__ import annotations

import dataclasses

import numpy as np

from eyefem.eye.buckles import Buckle


@dataclasses.dataclass
class SurgeryParts:
    """What the surgery problem is built from (kept for outputs and planning)."""

    eye: object
    buckle: Buckle
    p: dict
    sclera_nodes: np.ndarray
    frame: tuple
    layout: object = None
    scale: float = 1.0
    d_per_mm: float = 0.0
    extra_dof: int = -1
    band: object = None  # BandInfo of a deformable band
    sponge: bool = False  # a deformable sponge (node set "sponge" of the mesh)
