"""Validation problem ``pressure_volume``: the eye's pressure-volume curve by injection.

Stage 1 (``pressurise``) loads the wetted surface (wall inside and lens) with the IOP,
the cavity open; stage 2 (``inject``) closes the cavity at that pressure and volume
(eyefem.fem.cavity.close_cavity) and injects ``inject_ul`` uL of liquid in ``steps``
equal steps by volume control (the cavity param ``dv``), as an intracameral injection
in a living eye (Pallikaris et al. 2005, IOVS 46:409).

The summary's ocular rigidity is the least-squares slope of ln P against the injected
volume over the injected points, P0 fixed at the closing pressure (the baseline IOP):

    K = sum_i dV_i ln(P_i / P0) / sum_i dV_i^2                       [1/uL]

(``rigidity_K_free_P0_per_uL``: the same fit with ln P0 free).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from eyefem.eye.biometry import BIOMETRY_FIELDS, eye_geometry
from eyefem.eye.eyemodel import LEVEL_EXPECTED, LEVEL_HELP, build_eye, is_level
from eyefem.eye.presets import PRESETS, with_overrides
from eyefem.eye.wall import WALL_ELEMENT_FIELD, with_wall_element
from eyefem.fem.cavity import WATER_BULK, FluidCavity, closing_hook
from eyefem.fem.surface import PressureLoad
from eyefem.fem.units import MMHG
from eyefem.io.casefile import Field, positive
from eyefem.io.output import plot_curves, write_csv
from eyefem.solve.problem import Setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage

log = logging.getLogger(__name__)

PALLIKARIS_K = 0.0126
"""Ocular rigidity of living human eyes, 1/uL, in P = P0 exp(K dV) (Pallikaris et al. 2005)."""

PV_FIELDS = [
    Field("mesh", str, "default", LEVEL_HELP, is_level, LEVEL_EXPECTED),
    Field("materials_preset", str, "physiological", f"tissue constants: {', '.join(PRESETS)} "
          "(eyefem.eye.presets; [materials] tables override single tissues)",
          lambda v: v in PRESETS, f"one of {list(PRESETS)}"),
    Field("iop_mmhg", float, 15.0, "pressure at which the cavity is closed, mmHg", positive,
          "> 0"),
    Field("inject_ul", float, 100.0, "liquid injected after closing, uL (mm^3)", positive, "> 0"),
    Field("steps", int, 10, "injection steps (P recorded after each)", lambda v: v >= 2, ">= 2"),
    Field("steps_pressurise", int, 2, "load steps to the IOP", positive, ">= 1"),
    Field("liquid_bulk", float, WATER_BULK, "liquid bulk modulus, MPa", positive, "> 0"),
    Field("zonule_E", float, 100.0, "zonule Young's modulus, MPa", positive, "> 0"),
    WALL_ELEMENT_FIELD,
] + BIOMETRY_FIELDS


def rigidity(dv_ul, p_mmhg, p0_mmhg) -> tuple[float, float, float]:
    """Fits of ln P = ln P0 + K dV over the injected points dv_ul (n,) > 0, p_mmhg (n,).

    Returns (K with P0 fixed at p0_mmhg, K with P0 free, the free fit's P0 (mmHg))."""
    dv, y = np.asarray(dv_ul, float), np.log(np.asarray(p_mmhg, float))
    k_fixed = float(dv @ (y - np.log(p0_mmhg)) / (dv @ dv))
    k_free, ln_p0 = np.polyfit(dv, y, 1)
    return k_fixed, float(k_free), float(np.exp(ln_p0))


def pv_parts(p, materials=None):
    """The model and load path pieces: (model, pressurise Stage, held (dofs, values),
    active terms of the injection stage). ``materials``: overrides of single tissues."""
    eye = build_eye(eye_geometry(p), p["mesh"])
    mesh = eye.mesh
    faces = np.concatenate([mesh.face_set("eye/inner"), mesh.face_set("lens/surface")])
    mesh = mesh.replace(face_sets={**mesh.face_sets, "wetted": faces})
    mats = with_overrides(p["materials_preset"], materials, log)
    unknown = sorted(set(materials or {}) - set(mesh.materials))
    if unknown:
        raise ValueError(f"materials {unknown} are not tissues of the eye mesh; it has "
                         f"{list(mesh.materials)}")
    zonule = eye.zonule_bars(p["zonule_E"])
    iop = PressureLoad("iop", mesh, "wetted", 0.0)
    cavity = FluidCavity("cavity", mesh, [("wetted",)], bulk=p["liquid_bulk"])
    lens_hold = eye.lens_springs()
    model = with_wall_element(solid_model(mesh, {m: mats[m] for m in mesh.materials},
                                          (zonule, iop, cavity, lens_hold)),
                              p.get("wall_element", "q1p0"))
    fix = node_dofs(mesh.node_set("eye/nerve_end"))
    held = (fix, np.zeros(len(fix)))
    base = ("solid", "zonule", "lens_springs")
    stage1 = Stage("pressurise", p["steps_pressurise"], held,
                   params={"iop": {"p": p["iop_mmhg"] * MMHG}}, active=base + ("iop",))
    return model, stage1, held, base + ("cavity",)


def pressure_volume(p, materials):
    """Build the pressure_volume Setup (see PV_FIELDS)."""
    model, stage1, held, active = pv_parts(p, materials)
    inject = Stage("inject", p["steps"], held, params={"cavity": {"dv": p["inject_ul"]}},
                   active=active, before=closing_hook("cavity", "iop"))
    cav = model.term("cavity")

    def probe(model, q, theta):
        P, V = cav.pressures(q, theta["cavity"])
        closed = theta["iop"]["p"] == 0.0  # close_cavity releases the surface load
        return {"iop_mmhg": (float(P[0]) if closed else float(theta["iop"]["p"])) / MMHG,
                "injected_ul": float(np.asarray(theta["cavity"]["dv"]).ravel()[0]),
                "volume_mm3": float(V[0])}

    def finish(rows, out_dir, plots):
        out_dir = Path(out_dir)
        first = [r for r in rows if r["stage"] == "pressurise"][-1:]
        table = [[r["injected_ul"], r["iop_mmhg"]] for r in first + [r for r in rows
                                                                   if r["stage"] == "inject"]]
        dv, P = np.array(table).T
        k, k_free, p0_free = rigidity(dv[1:], P[1:], P[0])
        write_csv(out_dir / "pv.csv", [{"injected_ul": a, "iop_mmhg": b} for a, b in table])
        if plots:
            s = np.linspace(0.0, dv[-1], 101)
            living = P[0] * np.exp(PALLIKARIS_K * s)
            plot_curves(out_dir / "pressure_volume.png", s,
                        {"model eye": ((dv, P), "o"),
                         f"fit P0 exp(K dV), K = {k:.4g}/uL": (P[0] * np.exp(k * s), "-"),
                         f"Pallikaris 2005, K = {PALLIKARIS_K}/uL": (living, "--")},
                        xlabel="injected volume, uL", ylabel="IOP, mmHg",
                        title=f"pressure-volume, {p['mesh']} mesh, {p['materials_preset']} "
                        "materials")
        summary = {"rigidity_K_per_uL": k, "rigidity_fit": "ln P = ln P0 + K dV, least squares "
                   "over the injected points, P0 fixed at the closing pressure",
                   "rigidity_K_free_P0_per_uL": k_free, "fit_free_P0_mmhg": p0_free,
                   "target_K_per_uL": PALLIKARIS_K,
                   "relative_error_K": k / PALLIKARIS_K - 1.0,
                   "pv_table": [[float(a), float(b)] for a, b in table],
                   "materials_preset": p["materials_preset"], "mesh": p["mesh"],
                   "elements": int(model.mesh.n_elem)}
        return summary

    return Setup("pressure_volume", model, [stage1, inject], probe, finish)


PROBLEMS = {"pressure_volume": (PV_FIELDS, pressure_volume)}
