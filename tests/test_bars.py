"""Suture / zonule bars: closed form, invariance, hand-coded tangent vs autodiff vs FD."""

import jax.numpy as jnp
import numpy as np
import pytest

from eyefem.fem.bars import Bars, bilinear
from eyefem.solve.model import Model
from eyefem.verify.handcoded import bar_residual_tangent


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (10, 3))
    X[:4] = [[0, 0, 0], [1, 0, 0], [1, 1, 0.1], [0, 1, 0]]
    na = np.array([[0, 1, 2, 3], [5, 5, 5, 5]])
    nb = np.array([[6, 6, 6, 6], [7, 7, 7, 7]])
    xi_a = np.array([[0.3, -0.4], [0.0, 0.0]])
    bars = Bars("b", na, nb, xi_a, np.zeros((2, 2)), X, EA=[2.0, 3.0])
    model = Model(None, (bars,), 30)  # bars alone need no hexahedral mesh
    return bars, model, X, rng


def test_closed_form_force_and_tightening(setup):
    bars, model, X, rng = setup
    q = np.zeros(30)
    q[3 * 7: 3 * 7 + 3] = 0.1 * (X[7] - X[5]) / np.linalg.norm(X[7] - X[5])  # stretch bar 1 by 0.1
    p = dict(bars.params)
    f = bars.forces(q, p)
    assert f[1] == pytest.approx(3.0 / np.linalg.norm(X[7] - X[5]) * 0.1, rel=1e-12)
    p["shortening"] = np.array([0.0, 0.05])
    L0 = np.linalg.norm(X[7] - X[5])
    assert bars.forces(q, p)[1] == pytest.approx(3.0 / L0 * (0.1 + 0.05 * L0), rel=1e-12)
    slack = Bars("s", [[5] * 4], [[7] * 4], [[0, 0]], [[0, 0]], X, EA=1.0, tension_only=True)
    qs = np.zeros(30)
    qs[21:24] = -0.1 * (X[7] - X[5]) / L0
    assert slack.forces(qs, slack.params)[0] == 0.0


def test_energy_invariant_under_rotation(setup):
    bars, model, X, rng = setup
    u = 0.1 * rng.standard_normal((10, 3))
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    u2 = (X + u) @ Q.T + 0.7 - X
    th = {"b": bars.params}
    assert model.energy(u.ravel(), th) == pytest.approx(model.energy(u2.ravel(), th), rel=1e-12)


def test_tangent_matches_hand_coded_and_fd(setup):
    bars, model, X, rng = setup
    u = 0.1 * rng.standard_normal((10, 3))
    p = dict(bars.params)
    p["shortening"] = np.array([0.02, 0.1])
    th = {"b": p}
    g, H = model.local_grad_hess(bars, u.ravel(), th)
    for i in range(2):
        Ta = np.kron(bilinear(p["xi"][i, 0])[None], np.eye(3))  # (3, 12)
        Tb = np.kron(bilinear(p["xi"][i, 1])[None], np.eye(3))
        T = np.block([[Ta, np.zeros((3, 12))], [np.zeros((3, 12)), Tb]])  # (6, 24)
        x = (bars.data["X"][i] + u[bars.dofs[i, ::3] // 3]).ravel()
        xa, xb = Ta @ x[:12], Tb @ x[12:]
        L0 = bars.data["L0"][i]
        f, k = bar_residual_tangent(xa, xb, p["EA"][i], L0, L0 * (1 - p["shortening"][i]))
        np.testing.assert_allclose(g[i], T.T @ f, rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(H[i], T.T @ k @ T, rtol=1e-9, atol=1e-12)
    # finite differences of the global gradient
    v = rng.standard_normal(30)
    h = 1e-6
    fd = (model.gradient(u.ravel() + h * v, th) - model.gradient(u.ravel() - h * v, th)) / (2 * h)
    np.testing.assert_allclose(model.hvp(u.ravel(), v, th), fd, rtol=1e-6, atol=1e-8)


def test_bad_bars_are_reported():
    X = np.eye(3)
    with pytest.raises(ValueError, match="bar 0 has an end outside its face"):
        Bars("s", [[0, 1, 2, 0]], [[1] * 4], [[1.5, 0]], [[0, 0]], X)
    with pytest.raises(ValueError, match="zero initial length"):
        Bars("s", [[0] * 4], [[0] * 4], [[0, 0]], [[0, 0]], X)
    with pytest.raises(ValueError, match="EA must be > 0"):
        Bars("s", [[0] * 4], [[1] * 4], [[0, 0]], [[0, 0]], X, EA=-1.0)


def test_bilinear_partition_of_unity():
    xi = jnp.array([[0.2, -0.7], [1.0, 1.0]])
    N = np.asarray(bilinear(xi))
    np.testing.assert_allclose(N.sum(1), 1.0)
    np.testing.assert_allclose(N[1], [0, 0, 1, 0])


def test_tied_bar_closed_form_smoothing_and_rotation_invariance():
    """A tied bar between the centres of two parallel unit faces 2 mm apart, shortened by
    0.1 mm: force EA / L0 x 0.1 (to exp(-0.1 / eps)), energy EA / (2 L0) 0.1^2; slack by
    10 eps: force below 1e-4 of that; a rigid rotation of the deformed state changes
    neither energy nor length."""
    from eyefem.fem.bars import TiedBars

    sq = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    X = np.vstack([sq, sq + [0, 0, 2.0]])
    bar = TiedBars("t", [[0, 1, 2, 3]], [[4, 5, 6, 7]], [[0, 0]], [[0, 0]], X, EA=40.0,
                   smoothing=2e-4)
    assert bar.params["L0"][0] == pytest.approx(2.0)
    q = np.zeros(24)
    p = {**bar.params, "tightening": np.array([0.1])}
    assert float(bar.forces(q, p)[0]) == pytest.approx(40.0 / 2.0 * 0.1, rel=1e-9)
    e = float(bar.energy(q, p, bar.data, bar.dofs))
    assert e == pytest.approx(0.5 * 40.0 / 2.0 * 0.1**2, rel=1e-9)
    slack = {**bar.params, "tightening": np.array([-10 * 2e-4])}
    assert float(bar.forces(q, slack)[0]) < 1e-4 * 2.0
    rng = np.random.default_rng(3)
    u = 0.05 * rng.standard_normal((8, 3))
    Qr = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Qr *= np.sign(np.linalg.det(Qr))
    u_rot = (X + u) @ Qr.T - X
    assert float(bar.energy(u_rot.ravel(), p, bar.data, bar.dofs)) == pytest.approx(
        float(bar.energy(u.ravel(), p, bar.data, bar.dofs)), rel=1e-12)


def test_host_side_forces_run_one_compiled_program(setup, monkeypatch):
    """Forces at a state on the host are one compiled program, shared by every term of the
    class and static key (eyefem.fem.terms.host_kernel), with the traced forces' values:
    eager JAX compiled one XLA program per operation (about 20 for a bar's forces), which
    a machine's first run of a case paid for at every output."""
    import jax
    import jax.monitoring

    from eyefem.fem import terms
    from eyefem.solve.heap import COMPILE_EVENT

    bars, model, X, rng = setup
    q = 0.05 * rng.standard_normal(30)
    p = {**bars.params, "shortening": np.array([0.01, 0.02])}
    twin = Bars("twin", [[1, 2, 3, 4], [8, 8, 8, 8]], [[9, 9, 9, 9], [0, 0, 0, 0]],
                [[0.1, 0.2], [0.0, 0.0]], np.zeros((2, 2)), X, EA=[1.0, 4.0])
    recorded, listening = [], [True]  # a listener cannot be removed: it stops recording
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **kw: recorded.append(event)
        if event == COMPILE_EVENT and listening[0] else None)
    monkeypatch.setattr(terms, "_HOST_KERNELS", {})
    jax.clear_caches()
    jax.config.update("jax_enable_compilation_cache", False)  # count compilations, not loads
    try:
        f = bars.forces(q, p)
        first = len(recorded)
        f_twin = twin.forces(q, twin.params)
    finally:
        jax.config.update("jax_enable_compilation_cache", True)
    assert first <= 1 and len(recorded) == first  # the twin reuses the compiled program
    ref = bars.axial_forces(jnp.asarray(q)[bars.dofs], p, bars.data)
    np.testing.assert_allclose(f, ref, rtol=1e-14, atol=0.0)
    np.testing.assert_allclose(
        f_twin, twin.axial_forces(jnp.asarray(q)[twin.dofs], twin.params, twin.data),
        rtol=1e-14, atol=0.0)
    listening[0] = False
