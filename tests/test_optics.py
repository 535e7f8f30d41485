"""The clinical optics (eyefem.eye.optics): the corneal fit against closed forms
(paraboloids of known principal radii), its invariance under rigid motions about the
optical axis, its autodiff derivative against central differences, and the reduced eye's
refraction change."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from eyefem.eye import optics

jax.config.update("jax_enable_x64", True)


def _paraboloid(r1, r2, angle=0.0, n=7, half=1.5):
    """Points (n*n, 3) of z = 3 - (u^2 / (2 r1) + v^2 / (2 r2)) with (u, v) the (x, y)
    turned by ``angle``: principal radii r1, r2 (mm) about the z axis."""
    s = np.linspace(-half, half, n)
    x, y = (a.ravel() for a in np.meshgrid(s, s))
    c, sn = np.cos(angle), np.sin(angle)
    u, v = c * x + sn * y, -sn * x + c * y
    return np.stack([x, y, 3.0 - u**2 / (2 * r1) - v**2 / (2 * r2)], axis=1)


def test_paraboloid_gives_its_keratometric_powers():
    """The quadric holds every paraboloid exactly: its powers are (n_k - 1) / R, 337.5 / R
    D for R in mm, and the astigmatism their difference, to round-off."""
    x = _paraboloid(7.8, 7.5, angle=0.3)
    ids = np.arange(len(x))
    p1, p2 = 337.5 / 7.8, 337.5 / 7.5
    assert float(optics.corneal_power_d(x, ids)) == pytest.approx(0.5 * (p1 + p2), rel=1e-12)
    assert float(optics.corneal_astigmatism_d(x, ids)) == pytest.approx(p2 - p1, rel=1e-9)
    k1, k2 = optics.cornea_curvatures(x, ids)
    assert (float(k1), float(k2)) == pytest.approx((1 / 7.5, 1 / 7.8), rel=1e-12)


def test_fit_is_invariant_under_rotation_about_the_axis_and_translation():
    x = _paraboloid(7.8, 7.2, angle=0.1)
    ids = np.arange(len(x))
    t = 0.7
    rot = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    y = x @ rot.T + np.array([0.0, 0.0, -1.3])
    for f in (optics.corneal_power_d, optics.corneal_astigmatism_d):
        assert float(f(y, ids)) == pytest.approx(float(f(x, ids)), rel=1e-12)


def test_corneal_power_derivative_matches_central_differences():
    """d power / d positions by autodiff (the adjoint's outcome derivative) against
    central differences of step 1e-6 mm (truncation 1e-12, round-off 1e-9 relative)."""
    x = _paraboloid(7.8, 7.4, angle=0.2, n=5)
    ids = np.arange(len(x))
    g = np.asarray(jax.grad(lambda y: optics.corneal_power_d(y, ids))(jnp.asarray(x)))
    rng = np.random.default_rng(0)
    d = rng.standard_normal(x.shape)
    h = 1e-6
    fd = (float(optics.corneal_power_d(x + h * d, ids))
          - float(optics.corneal_power_d(x - h * d, ids))) / (2 * h)
    assert np.sum(g * d) == pytest.approx(fd, rel=1e-6)


def test_reduced_eye_refraction_change():
    """Emsley's reduced eye (n' = 4/3, 60 D): 1 mm of axial elongation makes the eye
    n' 1e-3 / f'^2 = 2.7 D more myopic (f' = n' / 60 D); a cornea 1 D stronger, 1 D."""
    f = (4 / 3) / 60.0
    assert optics.refraction_change_d(1.0, 0.0) == pytest.approx(-(4 / 3) * 1e-3 / f**2,
                                                                rel=1e-14)
    assert optics.refraction_change_d(1.0, 0.0) == pytest.approx(-2.7, rel=1e-12)
    assert optics.refraction_change_d(0.0, 1.0) == -1.0
