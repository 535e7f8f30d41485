"""The eye wall's element: Q1P0 bricks, or the same with assumed transverse shear strains
in the load-bearing wall (case field ``wall_element`` of the surgery and pressure_volume
problems; docs/convergence.md, "Shear locking")."""

from __future__ import annotations

from eyefem.fem.solid_ans import SolidQ1P0ANS
from eyefem.io.casefile import Field
from eyefem.solve.model import Model

WALL_ELEMENTS = ("q1p0", "ans")
"""The eye wall's elements (case field ``wall_element``)."""

ANS_TISSUES = ("cornea", "limbus", "sclera")
"""The tissues whose elements take the assumed shear strains with ``wall_element = 'ans'``:
the load-bearing wall (the retina and choroid, single soft layers, stay plain bricks)."""

WALL_ELEMENT_FIELD = Field(
    "wall_element", str, "q1p0", "the eye wall's element: 'q1p0' (the trilinear brick with a "
    "constant pressure; the recorded results' model) or 'ans' (the same with assumed "
    "transverse shear strains in the cornea, limbus and sclera: free of the bricks' shear "
    "locking in bending, about four times the cost; surgery: a rigid buckle only; "
    "docs/convergence.md, 'Shear locking')", lambda v: v in WALL_ELEMENTS,
    f"one of {list(WALL_ELEMENTS)}")


def with_wall_element(model: Model, kind: str) -> Model:
    """The model with its solid's ANS_TISSUES elements as
    :class:`eyefem.fem.solid_ans.SolidQ1P0ANS` (assumed transverse shears) for ``kind``
    'ans'; unchanged for 'q1p0'."""
    if kind == "q1p0":
        return model
    if kind != "ans":
        raise ValueError(f"wall_element = {kind!r}; must be one of {list(WALL_ELEMENTS)}")
    s = model.term("solid")
    ans = SolidQ1P0ANS(s.name, s.mesh, s.coeffs, s.multiplier_offset,
                       ans_materials=tuple(t for t in ANS_TISSUES if t in s.mesh.materials))
    return model.with_terms([ans if t is s else t for t in model.terms])
