"""The wall's elastic law against a published biaxial test of human sclera (compared, not fitted).

    python benchmarks/tissue_tests.py --json results/tissue_tests.json \\
        --plot docs/images/tissue_tests.png                     # + two coarse eye runs
    python benchmarks/tissue_tests.py --no-eye                  # the closed form only

Equibiaxial stretch of an incompressible membrane (plane stress), in-plane stretch
lambda, F = diag(lambda, lambda, lambda^-2), Green strain E = (lambda^2 - 1) / 2:

    I1bar = I1 = 2 lambda^2 + lambda^-4 = 2 (1 + 2E) + (1 + 2E)^-2
    I2bar = I2 = lambda^4 + 2 lambda^-2 = (1 + 2E)^2 + 2 (1 + 2E)^-1

With w(lambda) = W(I1, I2) along this path, the plane-stress Cauchy stress (sigma33 = 0
fixes the pressure) is sigma = (lambda / 2) dw/dlambda, the first Piola-Kirchhoff stress
P = sigma / lambda and the second S = P / lambda = dw/dlambda / (2 lambda); as dlambda/dE
= 1 / lambda,

    S(E) = (1/2) dw/dE,     sigma(E) = (1 + 2E) S(E)                              [MPa]

S and its tangent dS/dE come from jax.grad of the project's own strain energy
(eyefem.fem.materials.strain_energy) composed with the invariants above, not from a
re-typed formula. For W = c10 (I1bar - 3) + c30 (I1bar - 3)^3 (eyefem.eye.presets):
(1 + 2E)^-2 = 1 - 4E + 12 E^2 - 32 E^3 + O(E^4), so I1 - 3 = 12 E^2 - 32 E^3 + O(E^4) and

    w = 12 c10 E^2 - 32 c10 E^3 + 1728 c30 E^6 + O(E^4),
    S = 12 c10 E - 48 c10 E^2 + 5184 c30 E^5 + ...,   dS/dE (E -> 0) = 12 c10,

the tangent rising by about 25920 c30 E^4 (the cubic term), i.e. the small-strain
equibiaxial stiffness is 12 c10 whatever c30 is.

Published: Eilaghi, Flanagan, Tertinegg, Simmons, Brodland, Ethier, "Biaxial mechanical
testing of human sclera", J Biomech 43(9):1696-1701 (2010): 10 eyes of 5 donors (55.4 +-
3.5 y), 6 mm square samples 3-9 mm from the optic nerve head, equibiaxial tests fitted to
W = c (e^Q - 1), Q = c1 E11^2 + c2 E22^2 + 2 c3 E11 E22 (c3 small): c c1 = 2.9 +- 2.0 MPa,
c c2 = 2.8 +- 1.9 MPa. At small strain S11 ~ 2 c c1 E11: a small-strain stiffness
2 c c1 = 5.8 +- 4.0 MPa (mean +- SD). The exponents c1, c2 alone (how fast the tissue
stiffens) are not available to us, so only the small-strain stiffness is compared.

The eye runs (``--mesh coarse``, in-process: eyefem.catalog, eyefem.run.runner.run_setup)
give the strains the law works at: the largest in-plane (largest principal) Green strain of
the sclera's elements (their Gauss points' volume average, SolidQ1P0.fields
"max_principal_strain") at the last step of cases/validation/pressure_volume.toml
(physiological, 100 uL injected: what the calibration sampled) and of
cases/planning/case1_physiological.toml (the buckle tightened and the sutures tied), and
the largest equibiaxial equivalent: the equibiaxial strain with the element's I1bar - 3
(the law's argument; :func:`equivalent_strain`).

Writes a JSON record (``--json``) and a plot (``--plot``): S against E for the seed's and
the physiological sclera, Eilaghi's small-strain line 5.8 E with its +-1 SD band, and
markers at the calibration's and the buckle's largest strains.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

EILAGHI = {"stiffness_MPa": 5.8, "sd_MPa": 4.0, "c_c1_MPa": [2.9, 2.0], "c_c2_MPa": [2.8, 1.9],
           "source": "Eilaghi A, Flanagan JG, Tertinegg I, Simmons CA, Brodland GW, Ethier CR, "
                     "Biaxial mechanical testing of human sclera, J Biomech 43(9):1696-1701 "
                     "(2010): 10 eyes of 5 donors, 55.4 +- 3.5 y, equibiaxial, Fung law; "
                     "small-strain stiffness 2 c c1 (mean +- SD)"}
"""Eilaghi et al. 2010: the small-strain equibiaxial stiffness dS/dE = 2 c c1, MPa."""

PRESET_NAMES = ("seed", "physiological")
TISSUES = ("sclera", "limbus", "cornea")
TANGENT_STRAINS = (0.01, 0.02, 0.04, 0.06)
"""Green strains at which the tangent dS/dE is reported."""
CASES = {"calibration": "cases/validation/pressure_volume.toml",
         "buckle": "cases/planning/case1_physiological.toml"}
"""The eye runs (physiological preset) whose sclera strains are reported."""


def equibiaxial_invariants(E):
    """(I1bar, I2bar) of the incompressible equibiaxial stretch of Green strain E (...)."""
    s = 1.0 + 2.0 * E  # lambda^2
    return 2.0 * s + s ** -2, s * s + 2.0 / s


def equibiaxial_energy(E, coeffs):
    """W along the equibiaxial path, MPa: E scalar Green strain, coeffs (4, 4) c_rs, MPa;
    eyefem.fem.materials.strain_energy (the project's law)."""
    from eyefem.fem.materials import strain_energy

    i1b, i2b = equibiaxial_invariants(E)
    return strain_energy(i1b, i2b, coeffs)


def second_piola(E, coeffs):
    """In-plane second Piola-Kirchhoff stress S = (1/2) dW/dE, MPa, at Green strains E
    (n,) (plane stress, lambda3 = lambda^-2); returns (n,)."""
    import jax
    import jax.numpy as jnp

    s = jax.vmap(jax.grad(equibiaxial_energy), (0, None))
    return 0.5 * s(jnp.atleast_1d(jnp.asarray(E, jnp.float64)), jnp.asarray(coeffs))


def cauchy(E, coeffs):
    """In-plane Cauchy stress sigma = lambda^2 S = (1 + 2E) S, MPa, (n,)."""
    E = np.atleast_1d(np.asarray(E, np.float64))
    return (1.0 + 2.0 * E) * np.asarray(second_piola(E, coeffs))


def tangent(E, coeffs):
    """Tangent dS/dE, MPa, at Green strains E (n,) (autodiff of :func:`second_piola`)."""
    import jax
    import jax.numpy as jnp

    d = jax.vmap(jax.grad(lambda e, c: 0.5 * jax.grad(equibiaxial_energy)(e, c)), (0, None))
    return d(jnp.atleast_1d(jnp.asarray(E, jnp.float64)), jnp.asarray(coeffs))


def preset_coeffs(preset: str, tissue: str) -> np.ndarray:
    """The (4, 4) c_rs table, MPa, of ``tissue`` in the preset ``preset``."""
    from eyefem.eye.presets import preset_materials

    return preset_materials(preset)[tissue].coeffs


def law_record(preset: str, tissue: str, extra_strains=()) -> dict:
    """Small-strain stiffness, tangents and stresses of one tissue of one preset."""
    c = preset_coeffs(preset, tissue)
    k0 = float(tangent([0.0], c)[0])
    strains = sorted(set(TANGENT_STRAINS) | {float(e) for e in extra_strains})
    rec = {"c10_MPa": float(c[1, 0]), "c30_MPa": float(c[3, 0]),
           "small_strain_stiffness_MPa": k0, "twelve_c10_MPa": 12.0 * float(c[1, 0]),
           "ratio_to_eilaghi": k0 / EILAGHI["stiffness_MPa"],
           "eilaghi_sd_from_mean": (k0 - EILAGHI["stiffness_MPa"]) / EILAGHI["sd_MPa"]}
    rec["tangent_MPa"] = {f"{e:.6g}": float(t) for e, t in zip(strains, tangent(strains, c))}
    rec["S_MPa"] = {f"{e:.6g}": float(s) for e, s in zip(strains, second_piola(strains, c))}
    rec["cauchy_MPa"] = {f"{e:.6g}": float(s) for e, s in zip(strains, cauchy(strains, c))}
    return rec


def run_case(path: str, preset: str, mesh: str, out_dir: Path):
    """Run a case file in-process (as ``eyefem run CASE --mesh MESH --materials PRESET
    --no-vtu``) into ``out_dir``; returns (solution, seconds)."""
    from eyefem.api import load_case, with_material_preset
    from eyefem.io.casefile import with_mesh
    from eyefem.catalog import problems
    from eyefem.run.runner import run_setup

    case = load_case(ROOT / path)
    case = with_mesh(case, mesh)
    case = with_material_preset(case, preset)
    setup = problems()[case.problem][1](case.parameters, case.materials)
    tic = time.perf_counter()
    res = run_setup(setup, out_dir, case.solver, vtu=False, plots=False)
    return res.solution, time.perf_counter() - tic


def sclera_strains(solution) -> dict:
    """The sclera's element strains at a solution's final state: the largest principal
    Green strain of each sclera element (Gauss points' volume average), its maximum, 99th
    and 50th percentiles, the element and its centroid (mm)."""
    model, q, theta = solution.model, solution.q, solution.theta
    term = model.term("solid")
    mesh = model.mesh
    f = term.fields(np.asarray(q), theta["solid"])
    els = np.asarray(term.elements)
    mask = mesh.material_ids[els] == mesh.materials.index("sclera")
    e = f["max_principal_strain"][mask]
    C = 2.0 * f["green_lagrange"][mask] + np.eye(3)
    a = np.trace(C, axis1=1, axis2=2) * f["J"][mask] ** (-2.0 / 3.0) - 3.0  # I1bar - 3
    vm = f["von_mises"][mask]
    i, k = int(np.argmax(e)), int(np.argmax(a))
    el = int(els[mask][i])
    return {"max": float(e[i]), "p99": float(np.percentile(e, 99)),
            "median": float(np.median(e)), "elements": int(mask.sum()), "element": el,
            "centroid_mm": mesh.nodes[mesh.hexes[el]].mean(axis=0).round(3).tolist(),
            "von_mises_at_max_MPa": float(vm[i]),
            "i1bar_minus_3_at_max": float(a[i]), "max_i1bar_minus_3": float(a[k]),
            "equibiaxial_equivalent_at_max": equivalent_strain(a[i]),
            "max_equibiaxial_equivalent": equivalent_strain(a[k]),
            "max_von_mises_MPa": float(vm.max())}


def equivalent_strain(a: float) -> float:
    """The equibiaxial Green strain E >= 0 whose I1bar - 3 = 2 (1 + 2E) + (1 + 2E)^-2 - 3
    equals ``a`` >= 0: the strain of the closed-form curve at which the law's argument is
    the element's (an element's largest principal strain overstates it where the state is
    not equibiaxial: uniaxial, bending)."""
    from scipy.optimize import brentq

    if a <= 0.0:
        return 0.0
    return float(brentq(lambda E: equibiaxial_invariants(E)[0] - 3 - a, 0.0, 1.0, xtol=1e-14))


def eye_strains(mesh: str, runs_dir: Path | None) -> dict:
    """Largest sclera strains of the calibration's and the buckle's runs (physiological)."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(runs_dir) if runs_dir else Path(tmp)
        for name, path in CASES.items():
            sol, secs = run_case(path, "physiological", mesh, base / name)
            out[name] = {"case": path, "mesh": mesh, "preset": "physiological",
                         "wall_s": round(secs, 1), **sclera_strains(sol)}
            r = out[name]
            print(f"{name}: {path} ({mesh}, {secs:.0f} s): largest sclera strain "
                  f"{r['max']:.5f} (99th percentile {r['p99']:.5f}; equibiaxial equivalent "
                  f"{r['equibiaxial_equivalent_at_max']:.5f}); largest equibiaxial "
                  f"equivalent {r['max_equibiaxial_equivalent']:.5f}; von Mises there "
                  f"{r['von_mises_at_max_MPa']:.3g} MPa, largest {r['max_von_mises_MPa']:.3g} MPa")
    return out


def plot(path: Path, record: dict) -> None:
    """S against E, 0-8 %, seed and physiological sclera, Eilaghi's line and band, strain
    markers: linear axes (left) and logarithmic stress (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    E = np.linspace(0.0, 0.08, 401)
    k, sd = EILAGHI["stiffness_MPa"], EILAGHI["sd_MPa"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, log in zip(axes, (False, True)):
        x = E[1:] if log else E
        ax.fill_between(100 * x, (k - sd) * x, (k + sd) * x, color="0.85",
                        label=f"Eilaghi 2010: small-strain line 2 c c1 E, {k} +- {sd} MPa")
        ax.plot(100 * x, k * x, "k--", lw=1)
        for preset, style in (("seed", "C0-"), ("physiological", "C3-")):
            c = preset_coeffs(preset, "sclera")
            k0 = record["laws"][preset]["sclera"]["small_strain_stiffness_MPa"]
            ax.plot(100 * x, np.asarray(second_piola(x, c)), style,
                    label=f"{preset} sclera (dS/dE at 0: {k0:.2f} MPa)")
        for name, style in (("calibration", "C2:"), ("buckle", "C1-.")):
            s = record.get("eye_strains", {}).get(name)
            if s:
                ax.axvline(100 * s["max"], color=style[:2], ls=style[2:],
                           label=f"largest sclera strain, {name} run ({100 * s['max']:.2f} %)")
                q = s["max_equibiaxial_equivalent"]
                ax.axvline(100 * q, color=style[:2], ls=style[2:], lw=0.6,
                           label=f"  its largest equibiaxial equivalent ({100 * q:.2f} %)")
        ax.set_xlabel("equibiaxial Green strain E, %")
        ax.set_ylabel("second Piola-Kirchhoff stress S, MPa")
        ax.set_xlim(0, 8)
        if log:
            ax.set_yscale("log")
            ax.set_ylim(1e-4, 1e4)
            ax.set_title("logarithmic stress")
        else:
            ax.set_ylim(0, 1.0)
            ax.set_title("linear (the physiological curve leaves the axes)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle("Equibiaxial response of the sclera's law against Eilaghi et al. 2010 "
                 "(compared, not fitted)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, help="write the record here")
    ap.add_argument("--plot", type=Path, help="write the plot here (PNG)")
    ap.add_argument("--mesh", default="coarse", help="eye mesh level of the runs (coarse)")
    ap.add_argument("--no-eye", action="store_true", help="skip the two eye runs")
    ap.add_argument("--runs-dir", type=Path, help="keep the eye runs' folders here "
                    "(default: a temporary folder)")
    a = ap.parse_args(argv)
    tic = time.perf_counter()
    record = {"eilaghi_2010": EILAGHI,
              "note": "only the small-strain stiffness 2 c c1 is compared: the Fung exponents "
                      "c1, c2 alone (the tissue's stiffening) were not available",
              "loading": "incompressible equibiaxial plane stress, F = diag(l, l, l^-2), "
                         "E = (l^2 - 1) / 2, S = (1/2) dW/dE, sigma = (1 + 2E) S"}
    if not a.no_eye:
        record["eye_strains"] = eye_strains(a.mesh, a.runs_dir)
    extra = [s[k] for s in record.get("eye_strains", {}).values()
             for k in ("max", "max_equibiaxial_equivalent")]
    record["laws"] = {p: {t: law_record(p, t, extra) for t in TISSUES} for p in PRESET_NAMES}
    print(f"Eilaghi 2010: small-strain equibiaxial stiffness {EILAGHI['stiffness_MPa']} +- "
          f"{EILAGHI['sd_MPa']} MPa")
    print(f"{'preset':14s}{'tissue':8s}{'dS/dE(0)':>10s}{'ratio':>7s}"
          + "".join(f"{f'@{100 * e:g}%':>10s}" for e in TANGENT_STRAINS) + "  (MPa)")
    for p, tissues in record["laws"].items():
        for t, r in tissues.items():
            print(f"{p:14s}{t:8s}{r['small_strain_stiffness_MPa']:10.4g}"
                  f"{r['ratio_to_eilaghi']:7.3f}"
                  + "".join(f"{r['tangent_MPa']['%.6g' % e]:10.4g}" for e in TANGENT_STRAINS))
    for name, s in record.get("eye_strains", {}).items():
        t = record["laws"]["physiological"]["sclera"]["tangent_MPa"]["%.6g" % s["max"]]
        t2 = record["laws"]["physiological"]["sclera"]["tangent_MPa"][
            "%.6g" % s["max_equibiaxial_equivalent"]]
        print(f"{name}: physiological sclera tangent at its largest strain "
              f"{s['max']:.5f}: {t:.4g} MPa; at its largest equibiaxial equivalent "
              f"{s['max_equibiaxial_equivalent']:.5f}: {t2:.4g} MPa")
    record["wall_s"] = round(time.perf_counter() - tic, 1)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(record, indent=2) + "\n")
    if a.plot:
        plot(a.plot, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
