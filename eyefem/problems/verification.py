"""Verification problems with closed-form answers (seed section 5, plus patch and uniaxial tests).

Each builder takes validated case parameters and materials and returns a Setup whose
``finish`` compares the computed curve with theory, writes ``<name>_curve.csv`` and a
PNG plot, and returns the largest relative error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from eyefem.fem import generators
from eyefem.fem.materials import MooneyRivlin, invariant_derivatives, mooney_rivlin
from eyefem.fem.surface import PressureLoad
from eyefem.fem.terms import OrbitSpring
from eyefem.fem.units import MMHG
from eyefem.io.casefile import Field, positive
from eyefem.io.output import plot_curves, write_csv
from eyefem.solve.problem import Setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage


def _material(materials, default):
    if not materials:
        return default
    if len(materials) != 1:
        raise ValueError(f"this problem uses one material; the case defines {sorted(materials)}")
    return next(iter(materials.values()))


def _w12(mat: MooneyRivlin, i1, i2):
    """dW/dI1, dW/dI2 at (reduced = full, J = 1) invariants."""
    return invariant_derivatives(np.asarray(i1), np.asarray(i2), mat.coeffs)


def _prescribe(mesh, spec):
    """Stack (node set, components, value) triples into (dofs, values)."""
    dofs, vals = [], []
    for name, comps, v in spec:
        d = node_dofs(mesh.node_set(name), comps)
        dofs.append(d)
        vals.append(np.full(d.shape, float(v)))
    d, v = np.concatenate(dofs), np.concatenate(vals)
    _, first = np.unique(d, return_index=True)  # a dof in two sets keeps its first value
    return d[np.sort(first)], v[np.sort(first)]


def _rel_err(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.abs(a - b) / np.maximum(np.abs(b), 1e-300)


def _finish_curve(name, x, cols, theory_key, computed_key, xlabel, ylabel, out_dir: Path, plots,
                  title):
    rows = [dict(zip(cols, vals)) for vals in zip(*cols.values())]
    write_csv(out_dir / f"{name}_curve.csv", rows)
    if plots:
        plot_curves(out_dir / f"{name}.png", x,
                    {"eyefem": (np.asarray(cols[computed_key]), "o"),
                     "theory": (np.asarray(cols[theory_key]), "-")},
                    xlabel=xlabel, ylabel=ylabel, title=title)
    err = _rel_err(cols[computed_key], cols[theory_key])
    return float(err.max())


# --- seed problem 1: equibiaxial sheet -----------------------------------------------------
SHEET_FIELDS = [
    Field("side", float, 20.0, "full sheet side length, mm (the model is its 1/4)", positive, "> 0"),
    Field("thickness", float, 1.0, "sheet thickness, mm", positive, "> 0"),
    Field("n_side", int, 20, "elements along each in-plane edge of the 1/4 model", positive, "> 0"),
    Field("n_thick", int, 2, "elements through the thickness", positive, "> 0"),
    Field("stretch", float, 5.8, "final stretch ratio", lambda v: v > 1, "> 1"),
    Field("steps", int, 40, "load steps", positive, "> 0"),
]


def equibiaxial_sheet(p, materials):
    """Seed problem 1: 1/4 model of a thin square sheet stretched equibiaxially.

    Theory: F = 2 A (l - l^-5)(W1 + l^2 W2) per edge of the quarter (A its initial
    cross-section), true stress sigma = 2 (l^2 - l^-4)(W1 + l^2 W2).
    """
    mat = _material(materials, mooney_rivlin("rubber", 25.0, 5.0))
    a, h = p["side"] / 2, p["thickness"]
    mesh = generators.box(a, a, h, p["n_side"], p["n_side"], p["n_thick"], material=mat.name)
    model = solid_model(mesh, {mat.name: mat})
    d = (p["stretch"] - 1.0) * a
    stages = [Stage("stretch", p["steps"], _prescribe(
        mesh, [("x0", "x", 0), ("y0", "y", 0), ("z0", "z", 0), ("x1", "x", d), ("y1", "y", d)]))]
    x1 = node_dofs(mesh.node_set("x1"), "x")
    area = a * h

    def probe(model, q, theta):
        r = model.gradient(q, theta)
        lam = 1.0 + q[x1].mean() / a
        force = float(r[x1].sum())
        return {"stretch": lam, "force_N": force, "true_stress_MPa": force * lam / area}

    def finish(rows, out_dir, plots):
        lam = np.array([r["stretch"] for r in rows])
        i1, i2 = 2 * lam**2 + lam**-4, lam**4 + 2 * lam**-2
        w1, w2 = _w12(mat, i1, i2)
        f_th = 2 * area * (lam - lam**-5) * (w1 + lam**2 * w2)
        s_th = 2 * (lam**2 - lam**-4) * (w1 + lam**2 * w2)
        f = np.array([r["force_N"] for r in rows])
        s = np.array([r["true_stress_MPa"] for r in rows])
        cols = {"stretch": lam, "force_N": f, "force_theory_N": f_th,
                "true_stress_MPa": s, "true_stress_theory_MPa": s_th}
        ef = _finish_curve("sheet", lam, cols, "force_theory_N", "force_N", "stretch ratio",
                           "edge force of the 1/4 model, N", out_dir, plots,
                           "Equibiaxial tension, Mooney-Rivlin")
        es = float(_rel_err(s, s_th).max())
        return {"max_rel_error_force": ef, "max_rel_error_stress": es,
                "final_stretch": float(lam[-1]), "final_force_N": float(f[-1])}

    return Setup("sheet", model, stages, probe, finish)


# --- uniaxial and patch tests ---------------------------------------------------------------
UNIAXIAL_FIELDS = [
    Field("stretch", float, 3.0, "final stretch (< 1 for compression)", positive, "> 0"),
    Field("n", int, 2, "elements per edge of the unit cube", positive, "> 0"),
    Field("steps", int, 10, "load steps", positive, "> 0"),
]


def uniaxial(p, materials):
    """Uniaxial tension of a unit cube: F = 2 A (l - l^-2)(W1 + W2 / l), exact for Q1P0."""
    mat = _material(materials, mooney_rivlin("rubber", 25.0, 5.0))
    n = p["n"]
    mesh = generators.box(1.0, 1.0, 1.0, n, n, n, material=mat.name)
    model = solid_model(mesh, {mat.name: mat})
    stages = [Stage("pull", p["steps"], _prescribe(
        mesh, [("x0", "x", 0), ("y0", "y", 0), ("z0", "z", 0), ("x1", "x", p["stretch"] - 1)]))]
    x1 = node_dofs(mesh.node_set("x1"), "x")

    def probe(model, q, theta):
        r = model.gradient(q, theta)
        return {"stretch": 1.0 + q[x1].mean(), "force_N": float(r[x1].sum())}

    def finish(rows, out_dir, plots):
        lam = np.array([r["stretch"] for r in rows])
        w1, w2 = _w12(mat, lam**2 + 2 / lam, 2 * lam + lam**-2)
        f_th = 2 * (lam - lam**-2) * (w1 + w2 / lam)
        cols = {"stretch": lam, "force_N": np.array([r["force_N"] for r in rows]),
                "force_theory_N": f_th}
        e = _finish_curve("uniaxial", lam, cols, "force_theory_N", "force_N", "stretch ratio",
                          "force, N", out_dir, plots, "Uniaxial tension of a unit cube")
        return {"max_rel_error_force": e}

    return Setup("uniaxial", model, stages, probe, finish)


PATCH_FIELDS = [
    Field("stretch_x", float, 1.3, "stretch along x", positive, "> 0"),
    Field("stretch_y", float, 0.9, "stretch along y", positive, "> 0"),
    Field("n", int, 3, "elements per edge", lambda v: v >= 2, ">= 2"),
    Field("distortion", float, 0.2, "random node shift, fraction of the element size",
          lambda v: 0 <= v < 0.3, "in [0, 0.3)"),
    Field("seed", int, 0, "random seed of the distortion"),
    Field("steps", int, 4, "load steps", positive, "> 0"),
]


def patch_test(p, materials):
    """Patch test: a distorted mesh under homogeneous biaxial stretch reproduces it exactly.

    Symmetry on x0, y0, z0, stretches prescribed on x1, y1, z1 traction-free. Every node
    must follow u = (F - I) X with F = diag(a, b, 1/(ab)) and the stress must be uniform:
    sigma_zz = 0, sigma_xx = 2 W1 (a^2 - c^2) - 2 W2 (a^-2 - c^-2), c = 1/(ab).
    """
    mat = _material(materials, mooney_rivlin("rubber", 25.0, 5.0))
    n = p["n"]
    base = generators.box(1.0, 1.0, 1.0, n, n, n, material=mat.name)
    rng = np.random.default_rng(p["seed"])
    X = base.nodes.copy()
    shift = rng.uniform(-1, 1, X.shape) * p["distortion"] / n
    on_plane = (np.isclose(X, 0) | np.isclose(X, 1))
    shift[on_plane] = 0.0  # boundary nodes stay on their planes
    mesh = base.replace(nodes=X + shift)
    model = solid_model(mesh, {mat.name: mat})
    a, b = p["stretch_x"], p["stretch_y"]
    stages = [Stage("stretch", p["steps"], _prescribe(
        mesh, [("x0", "x", 0), ("y0", "y", 0), ("z0", "z", 0), ("x1", "x", a - 1),
               ("y1", "y", b - 1)]))]
    solid = model.terms[0]

    x1, y1 = node_dofs(mesh.node_set("x1"), "x"), node_dofs(mesh.node_set("y1"), "y")

    def probe(model, q, theta):
        at, bt = 1 + q[x1].mean(), 1 + q[y1].mean()
        Ft = np.diag([at, bt, 1 / (at * bt)])
        u = q[: 3 * mesh.n_nodes].reshape(-1, 3)
        u_exact = mesh.nodes @ (Ft - np.eye(3)).T
        s = solid.fields(q, theta["solid"])["cauchy"]
        return {"max_node_error_mm": float(np.abs(u - u_exact).max()),
                "sigma_xx_MPa": float(s[:, 0, 0].mean()),
                "sigma_xx_spread_MPa": float(np.ptp(s[:, 0, 0])),
                "sigma_zz_max_MPa": float(np.abs(s[:, 2, 2]).max()),
                "sigma_xx_theory_MPa": _patch_sigma(mat, Ft[0, 0], Ft[1, 1])}

    def finish(rows, out_dir, plots):
        last = rows[-1]
        write_csv(out_dir / "patch_curve.csv", rows)
        return {"max_node_error_mm": max(r["max_node_error_mm"] for r in rows),
                "sigma_xx_rel_error": float(_rel_err(last["sigma_xx_MPa"],
                                                     last["sigma_xx_theory_MPa"])),
                "sigma_xx_spread_MPa": last["sigma_xx_spread_MPa"],
                "sigma_zz_max_MPa": last["sigma_zz_max_MPa"]}

    return Setup("patch", model, stages, probe, finish)


def _patch_sigma(mat, a, b):
    c = 1 / (a * b)
    i1, i2 = a * a + b * b + c * c, a**-2 + b**-2 + c**-2
    w1, w2 = _w12(mat, i1, i2)
    return float(2 * w1 * (a * a - c * c) - 2 * w2 * (a**-2 - c**-2))


# --- seed problem 2: inflated disk ----------------------------------------------------------
DISK_FIELDS = [
    Field("radius", float, 10.0, "disk radius, mm", positive, "> 0"),
    Field("thickness", float, 0.1, "disk thickness, mm", positive, "> 0"),
    Field("n_radial", int, 52, "elements across the outer ring of the O-grid", positive, "> 0"),
    Field("n_circ", int, 50, "elements around the quarter circle (even)",
          lambda v: v > 0 and v % 2 == 0, "even, > 0"),
    Field("n_thick", int, 1, "elements through the thickness", positive, "> 0"),
    Field("pressure", float, 0.8, "final pressure, MPa", positive, "> 0"),
    Field("steps", int, 16, "load steps", positive, "> 0"),
    Field("fit_radius", float, 0.25, "pole-curvature fit region, fraction of the radius",
          lambda v: 0 < v < 1, "in (0, 1)"),
]


def inflated_disk(p, materials):
    """Seed problem 2: 1/4 model of a clamped thin disk inflated by pressure.

    Thin-membrane theory at the pole: P = (4h/r)(1 - l^-6)(W1 + l^2 W2),
    sigma = P r l^2 / (2h), with l the pole stretch (from the thickness: l = sqrt(h/h_c))
    and r the pole's radius of curvature (least-squares fit of the mid-surface).
    """
    mat = _material(materials, mooney_rivlin("rubber", 25.0, 5.0))
    R, h = p["radius"], p["thickness"]
    mesh = generators.quarter_disk(R, h, p["n_radial"], p["n_circ"], p["n_thick"],
                                   material=mat.name)
    press = PressureLoad("pressure", mesh, "bottom", 0.0)
    model = solid_model(mesh, {mat.name: mat}, (press,))
    stages = [Stage("inflate", p["steps"], _prescribe(
        mesh, [("rim", "xyz", 0), ("sym_x", "x", 0), ("sym_y", "y", 0)]),
        params={"pressure": {"p": p["pressure"]}})]
    pb, pt = mesh.node_set("pole_bottom")[0], mesh.node_set("pole_top")[0]
    X = mesh.nodes
    bottom = mesh.node_set("sym_y")
    bottom = bottom[np.isclose(X[bottom, 2], 0.0)]
    top_of = {tuple(np.round(X[i, :2], 9)): i for i in mesh.node_set("sym_y")
              if np.isclose(X[i, 2], h)}
    pairs = np.array([(i, top_of[tuple(np.round(X[i, :2], 9))]) for i in bottom])
    solid = model.terms[0]
    pole_elems = np.nonzero(np.any(mesh.hexes == pb, axis=1))[0]

    def probe(model, q, theta):
        x = X + q[: 3 * mesh.n_nodes].reshape(-1, 3)
        hc = x[pt, 2] - x[pb, 2]
        lam = np.sqrt(h / hc)
        mid = 0.5 * (x[pairs[:, 0]] + x[pairs[:, 1]])
        rho = np.hypot(mid[:, 0], mid[:, 1])
        sel = rho <= p["fit_radius"] * R * lam
        A = np.stack([np.ones(sel.sum()), rho[sel] ** 2, rho[sel] ** 4], 1)
        coef = np.linalg.lstsq(A, mid[sel, 2], rcond=None)[0]
        r = -1.0 / (2 * coef[1]) if coef[1] < 0 else np.inf
        s = solid.fields(q, theta["solid"])["cauchy"][pole_elems]
        return {"pressure_MPa": float(theta["pressure"]["p"]), "pole_stretch": float(lam),
                "pole_radius_mm": float(r), "pole_height_mm": float(mid[np.argmin(rho), 2]),
                "pole_stress_MPa": float(0.5 * (s[:, 0, 0] + s[:, 1, 1]).mean())}

    def finish(rows, out_dir, plots):
        P = np.array([r["pressure_MPa"] for r in rows])
        lam = np.array([r["pole_stretch"] for r in rows])
        rr = np.array([r["pole_radius_mm"] for r in rows])
        w1, w2 = _w12(mat, 2 * lam**2 + lam**-4, lam**4 + 2 * lam**-2)
        p_th = 4 * h / rr * (1 - lam**-6) * (w1 + lam**2 * w2)
        s_th = P * rr * lam**2 / (2 * h)
        s = np.array([r["pole_stress_MPa"] for r in rows])
        cols = {"pressure_MPa": P, "pole_stretch": lam, "pole_radius_mm": rr,
                "pressure_theory_MPa": p_th, "pole_stress_MPa": s, "pole_stress_theory_MPa": s_th}
        rows_c = [dict(zip(cols, v)) for v in zip(*cols.values())]
        write_csv(out_dir / "disk_curve.csv", rows_c)
        if plots:
            plot_curves(out_dir / "disk.png", lam, {"eyefem (applied)": (P, "o"),
                                                    "membrane theory": (p_th, "-")},
                        xlabel="pole stretch", ylabel="pressure, MPa",
                        title="Inflated disk: pressure vs pole stretch")
            plot_curves(out_dir / "disk_stress.png", lam, {"eyefem": (s, "o"),
                                                           "membrane theory": (s_th, "-")},
                        xlabel="pole stretch", ylabel="pole Cauchy stress, MPa",
                        title="Inflated disk: pole stress")
        last = slice(len(rows) // 2, None)  # membrane theory holds once the disk has bulged
        return {"max_rel_error_pressure": float(_rel_err(P, p_th)[last].max()),
                "max_rel_error_stress": float(_rel_err(s, s_th)[last].max()),
                "final_pole_stretch": float(lam[-1]), "final_pole_radius_mm": float(rr[-1]),
                "final_pressure_theory_MPa": float(p_th[-1]), "n_elem": mesh.n_elem}

    return Setup("disk", model, stages, probe, finish)


# --- benchmark shell -------------------------------------------------------------------------
SHELL_FIELDS = [
    Field("inner_radius", float, 11.0, "inner radius, mm", positive, "> 0"),
    Field("thickness", float, 1.0, "wall thickness, mm", positive, "> 0"),
    Field("n_per_edge", int, 12, "elements per cube-sphere patch edge (odd: the rigid "
          "motions are held by springs, shell_rigid_spring)", positive, "> 0"),
    Field("n_thick", int, 2, "elements through the thickness", positive, "> 0"),
    Field("pressure_mmHg", float, 15.0, "final internal pressure, mmHg", positive, "> 0"),
    Field("steps", int, 10, "load steps", positive, "> 0"),
]


def shell_rigid_constraints(mesh):
    """Six dofs that remove the rigid motions of a body symmetric about the origin: the
    outer nodes furthest along +x, -x (y, z held) and +y (x, z held). They let a symmetric
    expansion be only when those nodes lie on the axes: an even ``n_per_edge`` of a
    cube-sphere shell. With an odd one they lie off the axes and hold part of their radial
    motion (measured at n_per_edge 5: outer radial displacements scatter by 57% against 7%
    at 6, tangential drift 0.03 mm against 3e-4 mm): use :func:`shell_rigid_spring`."""
    X = mesh.nodes
    out = mesh.node_set("outer")
    px, mx, py = (out[np.argmax(X[out] @ d)] for d in np.eye(3)[[0, 0, 1]] * [[1], [-1], [1]])
    return np.concatenate([node_dofs([px, mx], "yz"), node_dofs([py], "xz")])


def shell_rigid_spring(mesh, k=1.0) -> OrbitSpring:
    """Springs on the mean translation and the best-fit rotation of the outer nodes nearest
    the six axis directions (four around each axis at an odd ``n_per_edge``, one on it at
    an even one): stiffness k N/mm, k R^2 N mm/rad (R: their radius). The node set is as
    symmetric as the shell, so a symmetric expansion has no net translation or rotation
    on it and the springs carry no force, whatever n_per_edge; and since the loads of a
    closed pressurised surface have no net force or moment, at equilibrium the springs'
    force is zero too: they remove the rigid motions and hold nothing else
    (eyefem.fem.terms.OrbitSpring; its ``force_N`` and ``moment_Nmm`` report it)."""
    X = mesh.nodes
    out = mesh.node_set("outer")
    e = X[out] / np.linalg.norm(X[out], axis=1)[:, None]
    picked = []
    for d in np.vstack([np.eye(3), -np.eye(3)]):
        c = e @ d
        picked.append(out[c >= c.max() - 1e-9])
    nodes = np.unique(np.concatenate(picked))
    r = float(np.linalg.norm(X[nodes], axis=1).mean())
    return OrbitSpring("rigid_motion", nodes, X[nodes], k_rot=(k * r * r,) * 3, k_trans=k,
                       k_axial=k)


def inflated_shell(p, materials):
    """Thin spherical shell inflated by internal pressure (the benchmark problem).

    Theory (thin incompressible neo-Hookean / Mooney-Rivlin membrane):
    P = (2 H / R) (l^-1 - l^-7)(2 W1 + 2 l^2 W2) with H, R the initial mid-surface
    thickness and radius and l the mid-surface stretch.
    """
    mat = _material(materials, mooney_rivlin("sclera", 0.0833, 0.0))
    mesh = generators.spherical_shell(p["inner_radius"], p["thickness"], p["n_per_edge"],
                                      p["n_thick"], material=mat.name)
    press = PressureLoad("pressure", mesh, "inner", 0.0)
    if p["n_per_edge"] % 2:  # no node on the axes: springs on the rigid motions
        model = solid_model(mesh, {mat.name: mat}, (press, shell_rigid_spring(mesh)))
        d = np.zeros(0, np.int64)
    else:  # six dofs of nodes on the axes (the FEBio comparison's supports)
        model = solid_model(mesh, {mat.name: mat}, (press,))
        d = shell_rigid_constraints(mesh)
    stages = [Stage("inflate", p["steps"], (d, np.zeros(len(d))),
                    params={"pressure": {"p": p["pressure_mmHg"] * MMHG}})]
    outer = mesh.node_set("outer")
    Ro = p["inner_radius"] + p["thickness"]

    def probe(model, q, theta):
        x = mesh.nodes[outer] + q[: 3 * mesh.n_nodes].reshape(-1, 3)[outer]
        return {"pressure_mmHg": float(theta["pressure"]["p"] / MMHG),
                "outer_radius_mm": float(np.linalg.norm(x, axis=1).mean())}

    def finish(rows, out_dir, plots):
        write_csv(out_dir / "shell_curve.csv", rows)
        ro = rows[-1]["outer_radius_mm"]
        ri = (ro**3 - Ro**3 + p["inner_radius"] ** 3) ** (1 / 3)  # incompressible
        return {"final_outer_radius_mm": ro, "final_inner_radius_mm": ri, "n_elem": mesh.n_elem}

    return Setup("shell", model, stages, probe, finish)


DISK_SOLVER = {"beta": 100.0, "line_search": False}
"""The inflated disk's ``[solver]`` defaults. The flat disk resists the pressure only by
bending (h = 0.1 mm across R = 10 mm): the first Newton direction is the linear bending
response, hundreds of mm long, where the membrane answer is about 1 mm. Without a line
search a step longer than ``max_step`` (0.5 mm) is scaled to it (the line search's
trials of that direction fail and the Levenberg-Marquardt shifts after them barely move
it: every step is cut until it stops); and the saddle point of the flat, one element
thick disk, augmented with beta = 1e4, solves only to a residual of 3e-6 (the solver
refuses above 1e-6), with beta = 100 to 1e-8. The seed's mesh (3,225 hexahedra) then runs
its 16 steps uncut, within 0.06 % (pressure) and 0.6 % (pole stress) of membrane theory."""


def disk_solver_settings(values: dict) -> dict:
    """The ``[solver]`` settings of an inflated disk (DISK_SOLVER, whatever the
    parameters ``values``); a case file's own ``[solver]`` entries take precedence."""
    return dict(DISK_SOLVER)


inflated_disk.solver_settings = disk_solver_settings

PROBLEMS = {
    "equibiaxial_sheet": (SHEET_FIELDS, equibiaxial_sheet),
    "inflated_disk": (DISK_FIELDS, inflated_disk),
    "uniaxial": (UNIAXIAL_FIELDS, uniaxial),
    "patch_test": (PATCH_FIELDS, patch_test),
    "inflated_shell": (SHELL_FIELDS, inflated_shell),
}


def cantilever_bending_stiffness(element_length: float, layers: int, *, length: float = 8.0,
                                 thickness: float = 0.4, c10: float = 0.0833) -> dict:
    """Tip stiffness of a clamped plane-strain strip of Q1P0 hexahedra against beam theory.

    The linear (small-strain) stiffness of the neo-Hookean strip (length x thickness x
    thickness, mm; one element across, y held on every node: plane strain; the root face
    clamped; the tip face given a transverse displacement, free to rotate) against
    Timoshenko's k = 1 / (L^3 / (3 E' I) + L / (kappa G A)) with E' = E / (1 - nu^2) = 8 c10
    (nu = 1/2), G = 2 c10, kappa = 5/6. Fully integrated trilinear hexahedra carry a
    parasitic shear in bending that grows with (element_length / thickness)^2 ("shear
    locking"); the constant pressure of Q1P0 removes volumetric locking, not this.

    Args:
      element_length: hexahedron length along the strip, mm (length / element_length
        elements, rounded).
      layers: elements through the thickness.
    Returns:
      {"aspect": element_length / thickness, "ratio": k_FE / k_beam, "k_fe_N_per_mm",
       "k_beam_N_per_mm"}.
    """
    n_x = max(1, int(round(length / element_length)))
    mesh = generators.box(length, thickness, thickness, n_x, 1, layers, material="wall")
    model = solid_model(mesh, {"wall": mooney_rivlin("wall", c10, 0.0)})
    n = model.n_dof
    K = np.asarray(model.hvp_many(np.zeros(n), np.eye(n), model.theta0()))
    fixed = np.zeros(n, bool)
    fixed[node_dofs(mesh.node_set("x0"), "xyz")] = True
    fixed[node_dofs(mesh.node_set("all"), "y")] = True
    tip = node_dofs(mesh.node_set("x1"), "z")
    fixed[tip] = True
    u = np.zeros(n)
    u[tip] = 1e-3
    free = ~fixed
    u[free] = np.linalg.solve(K[np.ix_(free, free)], -K[np.ix_(free, fixed)] @ u[fixed])
    k_fe = float((K @ u)[tip].sum() / 1e-3)
    area, inertia = thickness**2, thickness**4 / 12
    k_beam = 1.0 / (length**3 / (3 * 8 * c10 * inertia) + length / (5 / 6 * 2 * c10 * area))
    return {"aspect": length / n_x / thickness, "ratio": k_fe / k_beam, "k_fe_N_per_mm": k_fe,
            "k_beam_N_per_mm": k_beam}
