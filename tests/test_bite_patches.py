"""Suture bites of physical size (eyefem.fem.bars.EndPatches): closed forms of the
kernel's moments, invariance, the tangent against the hand-coded chain rule and finite
differences, the derivative in the bite's position, and clear errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from eyefem.fem.bars import (
    AnchoredBars,
    TiedBars,
    end_patches,
    patch_weights,
    reference_end_positions,
)
from eyefem.solve.model import Model
from eyefem.verify.handcoded import smoothed_bar_residual_tangent

R = 1.5


def plate(n, L=6.0, sphere=None):
    """An n x n grid of quadrilaterals over [-L/2, L/2]^2 (z = 0), or mapped onto a sphere
    of radius ``sphere`` about (0, 0, -sphere) (a cap of the outer sclera)."""
    x = np.linspace(-L / 2, L / 2, n + 1)
    X, Y = np.meshgrid(x, x, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    if sphere:
        d = nodes + [0.0, 0.0, sphere]
        nodes = sphere * d / np.linalg.norm(d, axis=1, keepdims=True) - [0.0, 0.0, sphere]
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    faces = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    return nodes, faces


def bite(n, p=(0.1, -0.05), sphere=None):
    """(nodes, faces, face holding p (1, 4), its xi (1, 2)) on :func:`plate`."""
    X, F = plate(n, sphere=sphere)
    h = 6.0 / n
    i, j = int((p[0] + 3.0) // h), int((p[1] + 3.0) // h)
    f = i * n + j
    c = np.array([-3.0 + (i + 0.5) * h, -3.0 + (j + 0.5) * h])
    return X, F, F[f][None], ((np.asarray(p) - c) / (h / 2))[None]


def weights(X, P, xi):
    return np.asarray(patch_weights(jnp.asarray(X[P.nodes]), jnp.asarray(xi), P.data()))


@pytest.mark.parametrize("n", [16, 32, 64])
def test_kernel_moments_on_a_flat_plate(n):
    """On a flat grid of spacing h the weights sum to 1, their centroid is the bite point
    (a linear field is reproduced), and their second moment about it is the kernel's
    R^2/4 (int r^2 phi dA / int phi dA for phi = (1 - r^2/R^2)^2) plus the bilinear
    interpolant's h^2/6 per direction: a closed form to 1e-4."""
    X, F, f4, xi = bite(n)
    P = end_patches(X, F, f4, xi, True, R)
    w = weights(X, P, xi)[0]
    x = X[P.nodes[0]]
    p = np.array([0.1, -0.05, 0.0])
    h = 6.0 / n
    assert w.sum() == pytest.approx(1.0, abs=1e-14)
    assert np.all(w >= 0)
    np.testing.assert_allclose(w @ x, p, atol=2e-5)
    m2 = w @ np.sum((x - p) ** 2, axis=1)
    assert m2 == pytest.approx(R**2 / 4 + h**2 / 3, rel=1e-4)
    # no weight beyond the patch's radius plus one element (nodal lumping)
    assert np.all(w[np.linalg.norm(x - p, axis=1) > R + np.sqrt(2) * h] == 0)


@pytest.mark.parametrize("n", [32, 64])
def test_elliptic_patch_moments_on_a_flat_plate(n):
    """An elliptic patch (half-width R across, half-length A along t) is the disc's kernel
    stretched along t: its second moments about the bite point are A^2/8 along t and
    R^2/8 across (each plus the bilinear interpolant's h^2/6), closed forms to 1e-4; its
    long axis is the surface tangent normal to the bar, whichever way the bar points."""
    X, F, f4, xi = bite(n)
    p = np.array([0.1, -0.05, 0.0])
    h, A, Rw = 6.0 / n, 2.0, 0.5
    c, s_ = np.cos(0.3), np.sin(0.3)
    toward = p + [3.0 * c, 3.0 * s_, 1.0]  # the bar pulls across the axis t = (-s, c, 0)
    P = end_patches(X, F, f4, xi, True, Rw, half_length=A, toward=toward[None])
    t = np.array([-s_, c, 0.0])
    assert P.elongated and abs(abs(P.along[0] @ t) - 1.0) < 1e-12
    w = weights(X, P, xi)[0]
    x = X[P.nodes[0]] - p
    assert w.sum() == pytest.approx(1.0, abs=1e-14) and np.all(w >= 0)
    np.testing.assert_allclose(w @ x, 0.0, atol=2e-5)
    across = np.cross([0.0, 0.0, 1.0], t)
    assert w @ (x @ t) ** 2 == pytest.approx(A**2 / 8 + h**2 / 6, rel=1e-4)
    assert w @ (x @ across) ** 2 == pytest.approx(Rw**2 / 8 + h**2 / 6, rel=1e-4)
    # no weight outside the ellipse's bounding box grown by one element (nodal lumping)
    outside = (np.abs(x @ t) > A + np.sqrt(2) * h) | (np.abs(x @ across) > Rw + np.sqrt(2) * h)
    assert outside.sum() > 10
    assert np.all(w[outside] == 0)


def test_a_disc_is_an_ellipse_of_equal_axes():
    """half_length = R gives the disc's weights bit for bit (no axis is needed)."""
    X, F, f4, xi = bite(16)
    w0 = weights(X, end_patches(X, F, f4, xi, True, R), xi)
    P = end_patches(X, F, f4, xi, True, R, half_length=R)
    assert not P.elongated
    np.testing.assert_array_equal(weights(X, P, xi), w0)


def test_a_point_end_keeps_its_bilinear_weights():
    X, F, f4, xi = bite(8)
    P = end_patches(X, F, np.repeat(f4, 2, 0), np.repeat(xi, 2, 0), [False, True], R)
    w = weights(X, P, np.repeat(xi, 2, 0))
    c = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    N = 0.25 * (1 + xi[0, 0] * c[:, 0]) * (1 + xi[0, 1] * c[:, 1])
    np.testing.assert_allclose(w[0, :4], N, rtol=1e-14)
    assert np.all(w[0, 4:] == 0) and np.count_nonzero(w[1]) > 20


@pytest.fixture(scope="module", params=["disc", "ellipse"])
def curved_bar(request):
    """A tied suture bar from a bite spread over a cap of a 12 mm sphere (a disc of radius
    R, or an ellipse 0.5 mm across and 4 mm long) to a node above it, and its model."""
    X, F, f4, xi = bite(8, p=(0.4, 0.2), sphere=12.0)
    far = [2.5, 0.3, 1.0] if request.param == "ellipse" else [0.5, 0.3, 2.0]
    top = np.vstack([X, [far] * 4])
    k = len(X)
    P = (end_patches(top, F, f4, xi, True, R) if request.param == "disc" else
         end_patches(top, F, f4, xi, True, 0.5, half_length=2.0, toward=[far]))
    bar = TiedBars("sutures", f4, [[k, k + 1, k + 2, k + 3]], xi, [[0.0, 0.0]], top, EA=3.0,
                   smoothing=0.01, patch_a=P)
    return bar, Model(None, (bar,), 3 * len(top)), top, P


def test_energy_invariant_under_rigid_motion(curved_bar):
    """The bite is a weighted mean of material points, so a rigid motion of the whole
    (the sclera with the anchor) leaves the suture's length and energy unchanged."""
    bar, model, X, _ = curved_bar
    rng = np.random.default_rng(1)
    u = 0.02 * rng.standard_normal(X.shape)
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))
    u2 = (X + u) @ Q.T + [0.3, -0.2, 0.5] - X
    p = {**bar.params, "tightening": np.array([0.05])}
    th = {"sutures": p}
    e1, e2 = model.energy(u.ravel(), th), model.energy(u2.ravel(), th)
    assert e1 > 1e-5 and e2 == pytest.approx(e1, rel=1e-11)


def test_tangent_matches_hand_coded_chain_rule_and_fd(curved_bar):
    """Autodiff residual and tangent of the spread bite against the hand-coded smoothed bar
    mapped by the patch weights (x_a = sum w_j x_j: T = w (x) I3), and the tangent against
    central differences of the residual."""
    bar, model, X, P = curved_bar
    rng = np.random.default_rng(2)
    u = 0.02 * rng.standard_normal(X.shape)
    L = float(bar.lengths(jnp.asarray(u.ravel())[bar.dofs], bar.params, bar.data)[0])
    p = {**bar.params, "tightening": np.array([bar.params["L0"][0] - L + 0.005])}
    th = {"sutures": p}
    g, H = model.local_grad_hess(bar, u.ravel(), th)
    w = weights(X, P, p["xi"][:, 0])[0]
    wb = 0.25 * np.ones(4)  # the far end: the face's centre (xi = 0)
    T = np.zeros((6, bar.dofs.shape[1]))
    m = len(w)
    T[:3, :3 * m] = np.kron(w[None], np.eye(3))
    T[3:, 3 * m:] = np.kron(wb[None], np.eye(3))
    x = (bar.data["X"][0] + u[bar.dofs[0, ::3] // 3]).ravel()
    L0 = p["L0"][0]
    f, k = smoothed_bar_residual_tangent(T[:3] @ x, T[3:] @ x, 3.0, L0, L0 - p["tightening"][0], 0.01)
    np.testing.assert_allclose(g[0], T.T @ f, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(H[0], T.T @ k @ T, rtol=1e-9, atol=1e-11)
    v = rng.standard_normal(u.size)
    h = 1e-6
    fd = (model.gradient(u.ravel() + h * v, th) - model.gradient(u.ravel() - h * v, th)) / (2 * h)
    np.testing.assert_allclose(model.hvp(u.ravel(), v, th), fd, rtol=1e-6, atol=1e-8)


def test_bite_moves_smoothly_with_its_position(curved_bar):
    """d energy / d xi (the bite's place in its face, a design param moved by the suture
    width) by autodiff through the kernel weights, against central differences."""
    bar, _, X, _ = curved_bar
    u = 0.01 * np.random.default_rng(3).standard_normal(X.shape)
    ql = jnp.asarray(u.ravel())[bar.dofs]

    def energy(xi_a):
        xi = jnp.stack([xi_a[None], jnp.zeros((1, 2))], axis=1)
        p = {**bar.params, "xi": xi, "tightening": jnp.array([0.02])}
        return jnp.sum(bar.local_energy(ql, p, bar.data))

    xi0 = jnp.asarray(bar.params["xi"][0, 0])
    ad = np.asarray(jax.grad(energy)(xi0))
    h = 1e-6
    fd = [(energy(xi0.at[i].add(h)) - energy(xi0.at[i].add(-h))) / (2 * h) for i in range(2)]
    assert np.abs(ad).max() > 1e-5
    np.testing.assert_allclose(ad, fd, rtol=1e-6)


def test_anchored_bars_with_patches_match_tied_bars():
    """A rigid buckle's suture (AnchoredBars) with a spread bite has the length of the
    same bar as TiedBars, and its tied length is measured from the patch's centroid."""
    X, F, f4, xi = bite(8, sphere=12.0)
    P = end_patches(X, F, f4, xi, True, R)
    anchor = np.array([[0.5, 0.3, 2.0]])
    x0 = reference_end_positions(X, f4, xi, P)
    L0 = np.linalg.norm(anchor - x0, axis=1)
    bars = AnchoredBars("s", f4, xi, anchor, [0], [[0, 0, 1.0]], [[1.0, 0, 0]], 1, X, L0,
                        patch=P)
    u = 0.01 * np.random.default_rng(4).standard_normal(X.shape)
    ql = jnp.asarray(u.ravel())[bars.dofs]
    l = float(bars.lengths(ql, bars.params, bars.data)[0])
    xa = weights(X, P, xi)[0] @ (X + u)[P.nodes[0]]
    assert l == pytest.approx(np.linalg.norm(anchor[0] - xa), rel=1e-12)
    # the centroid of a spread bite lies below the curved surface (about R^2 / (8 rho))
    depth = 12.0 - np.linalg.norm(x0[0] - [0.0, 0.0, -12.0])
    assert 0.5 * R**2 / (8 * 12.0) < depth < 2 * R**2 / (8 * 12.0)


def test_bad_patches_are_reported():
    X, F, f4, xi = bite(4)
    with pytest.raises(ValueError, match="bite patch radius = 0.0 mm; must be > 0"):
        end_patches(X, F, f4, xi, True, 0.0)
    with pytest.raises(ValueError, match="half-length = -1.0 mm; must be > 0"):
        end_patches(X, F, f4, xi, True, R, half_length=-1.0)
    with pytest.raises(ValueError, match="needs the point each bar pulls toward"):
        end_patches(X, F, f4, xi, True, 0.5, half_length=2.0)
    p = np.einsum("a,ai->i", 0.25 * np.ones(4), X[f4[0]])  # not the bite, but on its normal
    with pytest.raises(ValueError, match="bar end 0: the bar is normal to the surface"):
        end_patches(X, F, f4, np.zeros((1, 2)), True, 0.5, half_length=2.0,
                    toward=[p + [0.0, 0.0, 2.0]])
    P = end_patches(X, F, f4, xi, True, R)
    with pytest.raises(ValueError, match="does not start with the faces of its ends"):
        TiedBars("s", f4[:, ::-1], [[0] * 4], xi, [[0, 0]], X, patch_a=P)


def test_padding_carries_no_weight(monkeypatch):
    """A patch's node and face counts are padded up to a multiple of PATCH_PADDING (so
    that bites a few faces larger or smaller, as another suture width gives, keep the
    arrays' shapes and the kernels compiled for them): the padding carries no weight (the
    weights of the real nodes equal those of the unpadded patch to 1e-15, the padded
    columns' are 0)."""
    from eyefem.fem import bars

    X, F, f4, xi = bite(16)
    pad = bars.PATCH_PADDING
    padded = end_patches(X, F, f4, xi, True, R)
    monkeypatch.setattr(bars, "PATCH_PADDING", 1)
    tight = end_patches(X, F, f4, xi, True, R)
    m, f = tight.nodes.shape[1], tight.faces.shape[1]
    assert padded.nodes.shape[1] == -(-m // pad) * pad > m - pad
    assert padded.faces.shape[1] == -(-f // pad) * pad
    assert (padded.nodes.shape[1], padded.faces.shape[1]) != (m, f)  # the test pads something
    w_pad, w_tight = weights(X, padded, xi)[0], weights(X, tight, xi)[0]
    np.testing.assert_allclose(w_pad[:m], w_tight, rtol=0, atol=1e-15)
    assert np.all(w_pad[m:] == 0.0)
