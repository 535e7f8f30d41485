"""The seed's liquid-container examples: pipes squeezed between rigid plates, and a
cylindrical container tightened by a deformable band.

Both couple closed fluid cavities (one per pipe / container) to the solid and load it
through contact. Each writes the per-step history (cavity pressures and volumes, contact
counts and penetrations, forces), a VTU series with von Mises stress, contact pressure
and the cavity pressure on the wetted faces, and a PNG plot of the cavity pressures.

Both models carry only constraints that their symmetry planes impose (zero normal
displacement on a plane of mirror symmetry of geometry and load), so the supports
transmit no force; the summaries report the largest support reaction to show it.
"""

from __future__ import annotations

import numpy as np

from eyefem.fem import vessels
from eyefem.fem.cavity import WATER_BULK, FluidCavity
from eyefem.fem.contact import SurfaceContact
from eyefem.fem.materials import mooney_rivlin
from eyefem.fem.mesh import merge
from eyefem.fem.rigid import plane
from eyefem.fem.rigid_contact import RigidContact
from eyefem.fem.units import MMHG
from eyefem.io.casefile import Field, positive
from eyefem.io.output import plot_curves
from eyefem.solve.problem import Setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage

_KPA = 1e-3  # MPa


def _materials(materials, defaults):
    """Materials by name: the case's, else the defaults; every case material must be used."""
    out = dict(defaults)
    for name, m in (materials or {}).items():
        if name not in defaults:
            raise ValueError(f"unknown material '{name}' for this problem; it uses {sorted(defaults)}")
        out[name] = m
    return out


def _supports(mesh, spec):
    """Zero displacements: dofs (n,) of (node set, components) pairs, unique."""
    return np.unique(np.concatenate([node_dofs(mesh.node_set(s), c) for s, c in spec]))


def _section(path, model, state, normal, axes, title, offset):
    """Section of the deformed mesh by the plane normal . x = offset (mm; off the node
    layers, which a cut through nodes would miss), coloured by von Mises stress (kPa), PNG."""
    from eyefem.io.pictures import plot_section

    q, theta = state["q"], state["theta"]
    mesh = model.mesh
    x = mesh.nodes + q[: 3 * mesh.n_nodes].reshape(-1, 3) - offset * np.asarray(normal)
    vm = model.terms[0].fields(q, theta["solid"])["von_mises"] / _KPA
    plot_section(path, x, mesh.hexes, vm, normal=normal, axes=axes, title=title,
                 label="von Mises stress, kPa")


def _young(mat):
    """Small-strain Young's modulus of an incompressible Mooney-Rivlin material, MPa."""
    return 6.0 * float(mat.coeffs[1, 0] + mat.coeffs[0, 1])


# --- several liquid-filled pipes squeezed between rigid plates ------------------------------
PIPES_FIELDS = [
    Field("n_pipes", int, 3, "number of pipes, side by side along x", positive, "> 0"),
    Field("inner_radius", float, 2.5, "pipe inner radius, mm", positive, "> 0"),
    Field("thickness", float, 0.5, "pipe wall and end-cap thickness, mm", positive, "> 0"),
    Field("length", float, 10.0, "inner length of each pipe (axis y), mm", positive, "> 0"),
    Field("squeeze_min", float, 0.4, "gap closure of the first pipe's plates, mm", positive, "> 0"),
    Field("squeeze_max", float, 1.2, "gap closure of the last pipe's plates, mm", positive, "> 0"),
    Field("bulk_modulus", float, WATER_BULK, "liquid bulk modulus K, MPa", positive, "> 0"),
    Field("n_circ", int, 16, "elements around a pipe (multiple of 8)", positive, "> 0"),
    Field("n_len", int, 8, "elements along a pipe (even)", positive, "> 0"),
    Field("steps", int, 6, "load steps", positive, "> 0"),
]


def compressed_pipes(p, materials):
    """Liquid-filled closed pipes, each pressed between its own pair of rigid plates.

    Pipe k (axis y, centred at x = k * spacing) sits between a plate above and one below,
    initially touching it; each plate moves toward the pipe by half of the pipe's
    squeeze (linear from squeeze_min to squeeze_max over the pipes), so each cavity ends
    at its own pressure. Supports: the pipe's three mirror planes.
    """
    mats = _materials(materials, {"wall": mooney_rivlin("wall", 0.2, 0.05)})
    ri, h, L = p["inner_radius"], p["thickness"], p["length"]
    ro = ri + h
    n = p["n_pipes"]
    one = vessels.closed_cylinder(ri, h, L, p["n_circ"], 1, p["n_len"], material="wall")
    rot = one.nodes @ np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # (x, y, z) -> (x, z, -y)
    size = L + 2 * h + 2.0
    spacing = size + 1.0
    parts = []
    for k in range(n):
        x = rot + [k * spacing, -0.5 * L, 0.0]
        parts.append((f"pipe{k}", one.replace(nodes=x)))
    mesh = merge(*parts)
    mesh = mesh.replace(node_sets={**mesh.node_sets, "outer": np.concatenate(
        [mesh.node_set(f"pipe{k}/outer") for k in range(n)])})
    squeeze = np.linspace(p["squeeze_min"], p["squeeze_max"], n)
    bodies = []
    for k in range(n):
        c = np.array([k * spacing, 0.0, 0.0])
        bodies.append(plane(f"top{k}", c + [0, 0, ro], (0, 0, -1), size, n=4, direction=(0, 0, -1)))
        bodies.append(plane(f"bottom{k}", c - [0, 0, ro], (0, 0, 1), size, n=4, direction=(0, 0, 1)))
    contact = RigidContact("plates", mesh, "outer", tuple(bodies), modulus=_young(mats["wall"]))
    liquid = FluidCavity("liquid", mesh, [f"pipe{k}/cavity" for k in range(n)],
                         bulk=p["bulk_modulus"])
    model = solid_model(mesh, mats, (contact, liquid))
    # mirror planes of pipe k: z = 0 ("y0" before the rotation), x = x_k ("x0"), y = 0 ("mid")
    fixed = _supports(mesh, [(f"pipe{k}/{s}", c) for k in range(n)
                             for s, c in (("y0", "z"), ("x0", "x"), ("mid", "y"))])
    travel = np.repeat(0.5 * squeeze, 2)
    stages = [Stage("squeeze", p["steps"], (fixed, np.zeros(len(fixed))),
                    params={"plates": {"d": travel}})]

    last = {}

    def probe(model, q, theta):
        last.update(q=q, theta=theta)
        P, V = liquid.pressures(q, theta["liquid"])
        f = model.gradient(q, theta)[fixed]
        row = {"squeeze_fraction": float(theta["plates"]["d"][0] / travel[0]),
               "max_support_reaction_N": float(np.abs(f).max())}
        for k in range(n):
            row[f"pipe{k}_squeeze_mm"] = float(2 * theta["plates"]["d"][2 * k])
            row[f"pipe{k}_pressure_kPa"] = float(P[k] / _KPA)
        return row

    def finish(rows, out_dir, plots):
        s = np.array([r["squeeze_fraction"] for r in rows])
        if plots:
            plot_curves(out_dir / "pipes_pressure.png", s,
                        {f"pipe {k} (squeeze {squeeze[k]:.2f} mm)":
                         (np.array([r[f"pipe{k}_pressure_kPa"] for r in rows]), "o-")
                         for k in range(n)},
                        xlabel="load fraction", ylabel="cavity pressure, kPa",
                        title="Liquid-filled pipes squeezed between rigid plates")
            _section(out_dir / "pipes_section_von_mises.png", model, last, (0.0, 1.0, 0.0),
                     (0, 2), "pipes near mid-length", 0.25 * L / p["n_len"])
        end = rows[-1]
        out = {f"pipe{k}_pressure_kPa": end[f"pipe{k}_pressure_kPa"] for k in range(n)}
        out.update({f"pipe{k}_squeeze_mm": float(squeeze[k]) for k in range(n)})
        out["max_support_reaction_N"] = max(r["max_support_reaction_N"] for r in rows)
        out["n_elem"] = mesh.n_elem
        return out

    return Setup("pipes", model, stages, probe, finish)


# --- a liquid-filled cylinder tightened by a band --------------------------------------------
CONTAINER_FIELDS = [
    Field("inner_radius", float, 5.0, "container inner radius, mm", positive, "> 0"),
    Field("thickness", float, 0.5, "container wall and end-cap thickness, mm", positive, "> 0"),
    Field("length", float, 10.0, "container inner height (axis z), mm", positive, "> 0"),
    Field("band_width", float, 2.5, "band width, mm", positive, "> 0"),
    Field("band_thickness", float, 0.6, "band thickness, mm", positive, "> 0"),
    Field("shortening", float, 2.0, "band circumference shortening, mm", positive, "> 0"),
    Field("bulk_modulus", float, WATER_BULK, "liquid bulk modulus K, MPa", positive, "> 0"),
    Field("n_circ", int, 32, "elements around (multiple of 8)", positive, "> 0"),
    Field("n_len", int, 8, "container elements along the axis (even)", positive, "> 0"),
    Field("steps", int, 8, "load steps", positive, "> 0"),
]


def banded_container(p, materials):
    """A closed liquid-filled cylinder squeezed at mid-height by a deformable band.

    The band (cut at the +y meridian) is wrapped around the container with a snug fit
    (inner radius 1e-4 smaller than the container's outer radius) and tightened by pulling
    its two ends along x past each other by half the shortening each; the ends are free
    to move radially and the band slides without friction (node-to-segment contact of
    the band's inner surface on the container's mantle). Supports on mirror planes:
    z = length / 2 (container and band), x = 0 (container); the container's y
    translation is held at the two mid-plane nodes on y = 0.
    """
    mats = _materials(materials, {"wall": mooney_rivlin("wall", 0.1, 0.0),
                                  "band": mooney_rivlin("band", 1.0, 0.0)})
    ri, h, L = p["inner_radius"], p["thickness"], p["length"]
    ro = ri + h
    box = vessels.closed_cylinder(ri, h, L, p["n_circ"], 1, p["n_len"], material="wall")
    band = vessels.slit_band(ro * (1 - 1e-4), p["band_thickness"], p["band_width"], p["n_circ"],
                             1, 2, z_centre=0.5 * L, slit_angle=90.0, material="band")
    mesh = merge(("container", box), ("band", band))
    contact = SurfaceContact("contact", mesh, "band/inner", "container/mantle",
                             modulus=_young(mats["wall"]))
    liquid = FluidCavity("liquid", mesh, "container/cavity", bulk=p["bulk_modulus"])
    model = solid_model(mesh, mats, (contact, liquid))
    fixed = _supports(mesh, [("container/mid", "z"), ("container/x0", "x"),
                             ("container/rim_y0", "y"), ("band/mid", "z")])
    end0, end1 = (node_dofs(mesh.node_set(f"band/{e}"), "x") for e in ("end0", "end1"))
    pulled = np.concatenate([end0, end1])
    half = 0.5 * p["shortening"]
    dofs = np.concatenate([fixed, pulled])
    vals = np.concatenate([np.zeros(len(fixed)), np.full(len(end0), half), np.full(len(end1), -half)])
    _, first = np.unique(dofs, return_index=True)
    stages = [Stage("tighten", p["steps"], (dofs[first], vals[first]))]
    X = mesh.nodes
    rim = mesh.node_set("container/outer")
    r0 = np.hypot(X[rim, 0], X[rim, 1])
    at_band = rim[(np.abs(r0 - ro) < 1e-9 * ro) & (np.abs(X[rim, 2] - 0.5 * L) < 1e-9 * L)]
    at_quarter = rim[(np.abs(r0 - ro) < 1e-9 * ro)
                     & (np.abs(X[rim, 2] - 0.25 * L) < 0.5 * L / p["n_len"] + 1e-9)]

    def radius(q, nodes):
        x = X[nodes] + q[: 3 * mesh.n_nodes].reshape(-1, 3)[nodes]
        return float(np.hypot(x[:, 0], x[:, 1]).mean())

    last = {}

    def probe(model, q, theta):
        last.update(q=q, theta=theta)
        P, V = liquid.pressures(q, theta["liquid"])
        g = model.gradient(q, theta)
        t = float(g[end0].sum())  # the pull on end 0 (+x): the band tension, N
        return {"shortening_mm": float(q[end0].mean() - q[end1].mean()),
                "pressure_kPa": float(P[0] / _KPA), "pressure_mmHg": float(P[0] / MMHG),
                "band_tension_N": t, "radius_at_band_mm": radius(q, at_band),
                "radius_at_quarter_mm": radius(q, at_quarter),
                "max_support_reaction_N": float(np.abs(g[fixed]).max())}

    def finish(rows, out_dir, plots):
        s = np.array([r["shortening_mm"] for r in rows])
        if plots:
            plot_curves(out_dir / "container_pressure.png", s,
                        {"cavity pressure, kPa": (np.array([r["pressure_kPa"] for r in rows]), "o-"),
                         "band tension x 10, N": (10 * np.array([r["band_tension_N"] for r in rows]),
                                                  "s--")},
                        xlabel="band shortening, mm", ylabel="kPa  /  N x 10",
                        title="Liquid-filled cylinder tightened by a band")
            _section(out_dir / "container_section_von_mises.png", model, last, (1.0, 0.0, 0.0),
                     (1, 2), "container and band (section near x = 0)",
                     np.pi * ro / p["n_circ"])
        end = rows[-1]
        keys = ("shortening_mm", "pressure_kPa", "band_tension_N", "radius_at_band_mm",
                "radius_at_quarter_mm")
        out = {k: end[k] for k in keys}
        out["initial_outer_radius_mm"] = ro
        out["max_support_reaction_N"] = max(r["max_support_reaction_N"] for r in rows)
        out["n_elem"] = mesh.n_elem
        return out

    return Setup("container", model, stages, probe, finish)


PROBLEMS = {
    "compressed_pipes": (PIPES_FIELDS, compressed_pipes),
    "banded_container": (CONTAINER_FIELDS, banded_container),
}
