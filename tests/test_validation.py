"""The pressure-volume validation case and the material presets (docs/validation.md).

Pinned numbers are from the coarse eye (2470 hexahedra) with 5 injection steps of 20 uL;
the calibration's own solves (one step per injected volume instead of a ramp) reproduce
them to 1e-5 relative, so they are pinned to 1e-4 relative.
"""

import numpy as np
import pytest

from eyefem.eye.presets import (
    PHYSIOLOGICAL_SCLERA,
    PRESETS,
    SEED_MATERIALS,
    WALL_RATIOS,
    preset_materials,
    preset_terms,
)
from eyefem.eye.validation import PALLIKARIS_K, PV_FIELDS, pressure_volume, rigidity
from eyefem.run.runner import run_setup

SEED_K_COARSE = 0.0019290178795776465  # recorded: coarse eye, seed preset, 5 steps
PHYS_K_COARSE = 0.01261495934527887  # recorded: coarse eye, physiological preset, 5 steps
SPREAD_ZONULE_K_COARSE = 0.0019814652909238128  # recorded: the seed's, zonule discs of 1.5 mm


def _params(preset, **kw):
    p = {f.name: f.default for f in PV_FIELDS}
    p.update(mesh="coarse", materials_preset=preset, steps=5, **kw)
    return p


def test_seed_preset_keeps_the_seed_constants():
    seed = {"cornea": 0.0333, "limbus": 0.0583, "sclera": 0.0833, "ciliary_body": 0.01,
            "choroid": 0.0083, "retina": 0.0008, "optic_nerve": 0.05, "lens": 10.0}
    assert SEED_MATERIALS == seed
    assert preset_terms("seed") == {t: {"c10": c} for t, c in seed.items()}
    for t, m in preset_materials("seed").items():
        c = np.zeros((4, 4))
        c[1, 0] = seed[t]
        np.testing.assert_array_equal(m.coeffs, c)


def test_surgery_cases_default_to_the_seed_preset():
    from eyefem.eye.surgery import SEED_MATERIALS as surgery_seed
    from eyefem.eye.surgery import SURGERY_FIELDS

    assert surgery_seed is SEED_MATERIALS
    assert {f.name: f.default for f in SURGERY_FIELDS}["materials_preset"] == "seed"


def test_physiological_preset_scales_the_wall_and_keeps_the_rest():
    terms = preset_terms("physiological")
    for t, r in WALL_RATIOS.items():
        assert terms[t] == pytest.approx({k: r * v for k, v in PHYSIOLOGICAL_SCLERA.items()})
    for t in set(SEED_MATERIALS) - set(WALL_RATIOS):
        assert terms[t] == {"c10": SEED_MATERIALS[t]}
    assert set(PRESETS) == {"seed", "physiological"}


def test_unknown_preset_names_the_choices():
    with pytest.raises(ValueError, match="physiological"):
        preset_terms("human")


def test_rigidity_fit_recovers_an_exponential():
    dv = np.arange(1, 11) * 10.0
    k, k_free, p0 = rigidity(dv, 15.0 * np.exp(0.0126 * dv), 15.0)
    assert k == pytest.approx(0.0126, rel=1e-12)
    assert k_free == pytest.approx(0.0126, rel=1e-10)
    assert p0 == pytest.approx(15.0, rel=1e-10)


@pytest.fixture(scope="module")
def physiological_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("pv_phys")
    return run_setup(pressure_volume(_params("physiological"), None), out, vtu=False)


def test_physiological_eye_matches_living_rigidity(physiological_run):
    s = physiological_run.summary
    assert s["materials_preset"] == "physiological"
    assert len(s["pv_table"]) == 6 and s["pv_table"][0] == [0.0, pytest.approx(15.0)]
    assert abs(s["rigidity_K_per_uL"] / PALLIKARIS_K - 1) < 0.15
    assert s["rigidity_K_per_uL"] == pytest.approx(PHYS_K_COARSE, rel=1e-4)
    assert (physiological_run.out_dir / "pressure_volume.png").exists()


@pytest.mark.slow
def test_tighter_tolerance_moves_no_outcome(physiological_run, tmp_path):
    """rtol 100x tighter (1e-10) moves the P-V table and K by less than 1e-6 relative (the
    issue's bound), here held to 1e-8: the tolerance is relative to the load the state
    carries, so every step, volume-controlled ones included, is tightened (measured
    2026-11-26: 8.2e-10 on the pressures, 8.2e-11 on K; with the old reference, the step's
    first residual, 5.8e-7 and 1.7e-7)."""
    import dataclasses

    from eyefem.solve.options import NewtonOptions

    tight = dataclasses.replace(NewtonOptions(), rtol=NewtonOptions().rtol / 100)
    s = run_setup(pressure_volume(_params("physiological"), None), tmp_path, tight, vtu=False,
                  plots=False).summary
    ref = physiological_run.summary
    np.testing.assert_allclose(s["pv_table"], ref["pv_table"], rtol=1e-8)
    assert s["rigidity_K_per_uL"] == pytest.approx(ref["rigidity_K_per_uL"], rel=1e-8)


@pytest.mark.slow
def test_seed_eye_rigidity_is_the_recorded_one(tmp_path):
    s = run_setup(pressure_volume(_params("seed"), None), tmp_path, vtu=False, plots=False).summary
    assert s["rigidity_K_per_uL"] == pytest.approx(SEED_K_COARSE, rel=1e-4)
    assert s["rigidity_K_per_uL"] < 0.2 * PALLIKARIS_K  # the seed eye is far too compliant


@pytest.mark.slow
def test_adjoint_gradient_of_rigidity_matches_central_differences():
    """dK/dc10 and dK/dc30 at the physiological constants (coarse eye, 3 injections)
    against central differences with h = 1e-3 c. The solves are tightened (rtol 1e-11):
    when the tolerance was relative to a step's first residual, the default rtol 1e-8
    left the first injection step's pressure converged to about 1e-5 relative, which was
    the whole difference the h = 1e-4 c quotient saw (measured
    2026-11-26: adjoint -0.0059188775 per uL per MPa; central differences at h = 1e-2,
    1e-3, 1e-4 c10: -0.00592041, -0.00591894, -0.00591806 tightened, against -0.00575114
    at h = 1e-4 with the default tolerance; the 1e-3 quotient's truncation error is
    about 1e-5, the test's 1e-4 leaves a margin of 10). At rtol 1e-11 the injection steps
    stall on roundoff just above the tolerance (1.1e-11 N against 2e-12 N), so the solves
    are held to 1e-10: the pressures' error is then 1e-10 relative, far below the
    quotient's."""
    from eyefem.solve.solver import NewtonOptions
    from optimize.calibrate import PressureVolumeFit, rigidity_of

    tight = NewtonOptions(rtol=1e-10, vtol=1e-13, atol=1e-13, cg_rtol=1e-11)
    fit = PressureVolumeFit("coarse", 100.0, 3, names=("c10", "c30"), options=tight)
    x = np.array([PHYSIOLOGICAL_SCLERA["c10"], PHYSIOLOGICAL_SCLERA["c30"]])
    w = fit.dv / (fit.dv @ fit.dv)
    g = w @ fit.gradients(x)[0]  # dK/dc (1/uL/MPa)
    for j in range(2):
        h = 1e-3 * x[j]
        k = [rigidity_of(fit.dv, fit.solve(x + s * h * np.eye(2)[j])[0], fit.p0) for s in (1, -1)]
        assert g[j] == pytest.approx((k[0] - k[1]) / (2 * h), rel=1e-4)


@pytest.mark.slow
def test_spread_zonule_rigidity_is_the_recorded_one(tmp_path):
    """The zonule's bars sharing 0.24 mm^2 and pulling on discs of 1.5 mm
    (``zonule_insertion_radius``; docs/convergence.md, "The zonule") stiffen the coarse
    seed eye by 2.7 % against its 16 point insertions of 0.01 mm^2 each (0.16 mm^2)."""
    s = run_setup(pressure_volume(_params("seed", zonule_insertion_radius=1.5), None), tmp_path,
                  vtu=False, plots=False).summary
    assert s["rigidity_K_per_uL"] == pytest.approx(SPREAD_ZONULE_K_COARSE, rel=1e-4)
    assert 1.01 < s["rigidity_K_per_uL"] / SEED_K_COARSE < 1.05
