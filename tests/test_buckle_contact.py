"""Analytic buckle contact and anchored suture bars: closed-form gaps, invariance, and
autodiff residual/tangent against central finite differences (smoothed penalties)."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from eyefem.fem import generators
from eyefem.fem.bars import AnchoredBars
from eyefem.fem.buckle_contact import (BuckleContact, ring_profile, smooth_penetration,
                                       sponge_end_lift)
from eyefem.verify.checks import row_hessians

R = 10.0


@pytest.fixture(scope="module")
def shell():
    return generators.spherical_shell(R - 0.5, 0.5, 4, 1)


def _ring(shell, **kw):
    return BuckleContact("b", shell, "outer", "ring", R, theta_b=np.pi / 2, width=7.0, ridge=0.75,
                         ridge_width=3.0, modulus=0.5, **kw)


def test_ring_gap_is_the_closed_form_radial_distance(shell):
    t = _ring(shell)
    X = t.data["X"]
    params = {**t.params, "d": np.array([0.2]), "s": np.array([0.0]), "ridge": np.array([0.0])}
    g = np.asarray(t.gaps(np.zeros_like(X), params, t.data))
    tau = np.arccos(X[:, 2] / np.linalg.norm(X, axis=1))
    a = R * (tau - np.pi / 2)
    flat = np.abs(a) < 3.0  # on the flat base, away from the lifted edges
    np.testing.assert_allclose(g[flat], R - 0.2 - np.linalg.norm(X[flat], axis=1), atol=1e-12)
    # the ridge protrudes by its height on its crest and not at all beyond its flanks
    assert float(ring_profile(0.0, 7.0, 0.75, 3.0)) == pytest.approx(-0.75)
    assert float(ring_profile(2.0, 7.0, 0.75, 3.0)) == pytest.approx(0.0)


@pytest.mark.parametrize("flank", [0.5, 1.0])
def test_ridge_flank_sets_the_shoulders_width_and_curvature(flank):
    """The ridge falls over ``flank`` mm inside its 3 mm base, half way at its middle, and
    its shoulders' curvature peaks at the quintic smoothstep's 10 / sqrt(3) x ridge /
    flank^2 (what makes narrow flanks a negative tangential stiffness)."""
    prof = lambda a: float(ring_profile(a, 7.0, 0.75, 3.0, flank))  # noqa: E731
    assert prof(1.5 - flank - 1e-9) == pytest.approx(-0.75)
    assert prof(1.5 - flank / 2) == pytest.approx(-0.375, rel=1e-12)
    assert prof(1.5 + 1e-9) == pytest.approx(0.0, abs=1e-12)
    a = np.linspace(1.5 - flank, 1.5, 20001)
    h = a[1] - a[0]
    p = np.asarray(ring_profile(a, 7.0, 0.75, 3.0, flank))
    curvature = np.abs(np.diff(p, 2)) / h**2
    assert curvature.max() == pytest.approx(10 / np.sqrt(3) * 0.75 / flank**2, rel=1e-4)


@pytest.mark.parametrize("edge", [0.5, 1.0])
def test_buckle_edge_sets_the_lifts_width_and_curvature(shell, edge):
    """Each edge of a ring lifts 0.3 mm over its last ``edge`` mm, cubically: flat and
    without a kink where the lift starts (value, slope and curvature 0), 0.3 mm at the
    edge, where the curvature peaks at 1.8 / edge^2 per mm (7.2 per mm with the 0.5 mm of
    the recorded results); the gap of a node over the lift follows it."""
    prof = lambda a: float(ring_profile(a, 7.0, 0.0, 0.0, 1.0, edge))  # noqa: E731
    assert prof(3.5 - edge - 1e-9) == 0.0
    assert prof(3.5) == pytest.approx(0.3, rel=1e-12)
    assert prof(3.5 - edge / 2) == pytest.approx(0.3 / 8, rel=1e-12)
    a = np.linspace(3.5 - edge, 3.5, 20001)
    h = a[1] - a[0]
    p = np.asarray(ring_profile(a, 7.0, 0.0, 0.0, 1.0, edge))
    curvature = np.diff(p, 2) / h**2
    assert curvature.max() == pytest.approx(1.8 / edge**2, rel=1e-3)
    assert abs(curvature[0]) < 1e-3 * curvature.max()
    t = BuckleContact("b", shell, "outer", "ring", R, theta_b=np.pi / 2, width=7.0,
                      modulus=0.5, edge_width=edge)
    X = t.data["X"]
    params = {**t.params, "d": np.array([0.2])}
    g = np.asarray(t.gaps(np.zeros_like(X), params, t.data))
    tau = np.arccos(X[:, 2] / np.linalg.norm(X, axis=1))
    a = R * (tau - np.pi / 2)
    expected = R + np.asarray(ring_profile(a, 7.0, 0.0, 0.0, 1.0, edge)) - 0.2 \
        - np.linalg.norm(X, axis=1)
    np.testing.assert_allclose(g, expected, atol=1e-12)
    with pytest.raises(ValueError, match="edge_width = 3.5 mm"):
        BuckleContact("b", shell, "outer", "ring", R, width=7.0, edge_width=3.5)


@pytest.mark.parametrize("end", [0.5, 1.0])
def test_sponge_end_rounds_off_over_its_width(shell, end):
    """A sponge's ends (``end_width``) lift 0.3 mm over their last ``end`` mm, cubically:
    no kink where the lift starts (value, slope and curvature 0), 0.3 mm at the end, the
    curvature peaking there at 1.8 / end^2 per mm; the earlier ends (0) are 10 (a - L/2)^2
    beyond the end only. The gap of a point is its distance from the axis less the
    sponge's radius plus the lift at its distance along the axis."""
    lift = lambda a, w=end: np.asarray(sponge_end_lift(np.asarray(a), 10.0, w))  # noqa: E731
    assert float(lift(5.0 - end - 1e-9)) == 0.0
    assert float(lift(5.0)) == pytest.approx(0.3, rel=1e-12)
    assert float(lift(5.0 - end / 2)) == pytest.approx(0.3 / 8, rel=1e-12)
    assert float(lift(5.5, 0.0)) == pytest.approx(10 * 0.25, rel=1e-12)
    assert float(lift(5.0, 0.0)) == 0.0
    a = np.linspace(5.0 - end, 5.0, 20001)
    h = a[1] - a[0]
    curvature = np.diff(lift(a), 2) / h**2
    assert curvature.max() == pytest.approx(1.8 / end**2, rel=1e-3)
    assert abs(curvature[0]) < 1e-3 * curvature.max()
    # 8 mm long, so that some of this coarse shell's nodes lie under the rounded ends
    t = BuckleContact("b", shell, "outer", "sponge", R, n0=(1.0, 0, 0), m0=(0, 0, -1.0),
                      axis=(0, 0, -1.0), sponge_radius=2.5, sponge_length=8.0, modulus=0.5,
                      end_width=end)
    X = t.data["X"]
    params = {**t.params, "d": np.array([0.2]), "s": np.array([0.3])}
    g = np.asarray(t.gaps(np.zeros_like(X), params, t.data))
    C = np.array([R + 2.5 - 0.2, 0.0, 0.0]) + 0.3 * np.array([0, 0, -1.0])
    along = (X - C) @ np.array([0, 0, -1.0])
    dist = np.linalg.norm((X - C)[:, :2], axis=1)
    ends = np.asarray(sponge_end_lift(np.abs(along), 8.0, end))
    np.testing.assert_allclose(g, dist - 2.5 + ends, atol=1e-12)
    assert ((ends > 0) & (np.abs(along) < 4.0)).any()  # some nodes under the rounded ends
    with pytest.raises(ValueError, match="end_width = 5.0 mm"):
        BuckleContact("b", shell, "outer", "sponge", R, sponge_length=10.0, end_width=5.0)


def test_report_counts_the_points_that_carry_the_contact(shell):
    """With the smoothed penetration a pressed point can sit at a small positive gap and
    still carry force: 'active' counts the gaps below the smoothing width eps (each point
    there carries at least 24 % of its force at zero gap), 'penetrating' the negative
    gaps; 'force_N' sums every point's force."""
    t = BuckleContact("b", shell, "outer", "sponge", R, n0=(1.0, 0, 0), m0=(0, 0, -1.0),
                      axis=(0, 0, -1.0), sponge_radius=2.5, sponge_length=8.0, modulus=0.5,
                      smoothing=0.1)
    # pressed 0.72 mm in: this coarse shell's nearest node 0.72 mm deep, the next two at
    # +0.04 mm, within eps = 0.1 mm
    params = {**t.params, "d": np.array([0.72]), "s": np.array([0.0])}
    q = np.zeros(int(t.dofs.max()) + 1)
    g = np.asarray(t.gaps(q[t.dofs], params, t.data))
    rep = t.report(q, params)
    assert rep["active"] == np.sum(g < 0.1) and rep["penetrating"] == np.sum(g < 0)
    assert (rep["active"], rep["penetrating"]) == (3, 1)
    assert rep["max_penetration_mm"] == pytest.approx(-g.min(), rel=1e-12)
    assert rep["force_N"] == pytest.approx(t.contact_forces(g).sum(), rel=1e-12)
    force = lambda gap: float(smooth_penetration(gap, 0.1)) / (1 + np.exp(gap / 0.1))  # noqa: E731
    assert force(0.1) / force(0.0) == pytest.approx(0.2431, abs=1e-4)


def test_ring_gap_is_invariant_under_rotation_about_the_axis(shell):
    t = _ring(shell)
    rng = np.random.default_rng(0)
    u = 0.05 * rng.standard_normal(t.data["X"].shape)
    params = {**t.params, "d": np.array([0.3]), "s": np.array([0.1]), "ridge": np.array([0.5])}
    c, s = np.cos(0.7), np.sin(0.7)
    Q = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    x = t.data["X"] + u
    rot = {**t.data, "X": t.data["X"] @ Q.T}
    g1 = np.asarray(t.gaps(u, params, t.data))
    g2 = np.asarray(t.gaps(x @ Q.T - rot["X"], params, rot))
    np.testing.assert_allclose(g1, g2, atol=1e-12)


def test_faces_integrate_a_uniform_penetration_to_a_uniform_pressure():
    """A sphere of radius R pressed uniformly by d = 0.5 mm (a ring wider than the sphere,
    plain penalty): integrated over the faces, the total contact force is the penalty per
    unit area k_A times d times the area 4 pi R^2, less the bilinear faces' chord (each point
    of a face lies inside the sphere by at most its sagitta s: the force lies between
    k_A (d - s) A and k_A d A, A the faces' area, within 1 % of the sphere's), and the nodes'
    contact pressure is uniform to the same chord; lumped at the nodes, the pressure follows
    the nodes' tributary areas (+-30 % on the cubed sphere)."""
    mesh = generators.spherical_shell(R - 0.5, 0.5, 16, 1)
    d = 0.5
    out = {}
    for quadrature in (0, 2):
        t = BuckleContact("b", mesh, "outer", "ring", R, theta_b=np.pi / 2, width=4 * R,
                          modulus=0.5, smoothing=1e-6, quadrature=quadrature)
        q, params = np.zeros(3 * mesh.n_nodes), {**t.params, "d": np.array([d])}
        force = t.contact_forces(t._gap_np(q, params)).sum()
        pres = t.point_fields(q, params, mesh.n_nodes)["b_pressure_MPa"][t.nodes]
        out[quadrature] = (t, force, pres)
    t, force, pres = out[2]
    k_A = t.alpha / np.mean(t.node_area)
    A = 4 * np.pi * R**2
    assert t.data["area"].sum() == pytest.approx(A, rel=1e-2)
    diag = np.linalg.norm(mesh.nodes[t.faces[:, 0]] - mesh.nodes[t.faces[:, 2]], axis=1).max()
    s = R - np.sqrt(R**2 - (diag / 2) ** 2)  # the largest face's sagitta, mm
    assert k_A * (d - s) * 0.99 * A < force < k_A * d * A
    assert pres.max() / pres.min() < 1 + 2 * s / d
    assert pres.min() > k_A * (d - s) * 0.98
    _, force_nodes, pres_nodes = out[0]
    assert force_nodes == pytest.approx(k_A * d * A, rel=1e-2)
    assert pres_nodes.max() / pres_nodes.min() > 1.5


@pytest.mark.parametrize("shape", ["ring", "sponge"])
def test_face_contact_energy_is_invariant_under_a_rotation_of_eye_and_buckle(shell, shape):
    """The eye's mesh, its displacement and the buckle's frame turned together about an
    arbitrary axis through the globe centre (a sponge) or about the eye axis (a ring, whose
    axis is z): the same energy of every contact point."""
    from scipy.spatial.transform import Rotation

    Q = (Rotation.from_rotvec([0.3, -0.5, 0.8]) if shape == "sponge"
         else Rotation.from_rotvec([0.0, 0.0, 0.9])).as_matrix()
    frame = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 0, -1.0]])
    turned = shell.replace(nodes=shell.nodes @ Q.T)
    rng = np.random.default_rng(7)
    u = 0.05 * rng.standard_normal(shell.nodes.shape)
    energies = []
    for mesh, F, v in ((shell, frame, u), (turned, frame @ Q.T, u @ Q.T)):
        if shape == "sponge":
            t = BuckleContact("b", mesh, "outer", "sponge", R, n0=tuple(F[0]), m0=tuple(F[1]),
                              axis=tuple(F[2]), sponge_radius=2.5, modulus=0.5, curved=True,
                              quadrature=2)
        else:
            t = _ring(mesh, quadrature=2)
        params = {**t.params, "d": np.array([0.45]), "ridge": np.array([0.3])}
        energies.append(np.asarray(t.local_energy(jnp.asarray(v.ravel()[t.dofs]), params, t.data)))
    assert energies[0].max() > 1e-4  # some points in contact
    np.testing.assert_allclose(energies[1], energies[0], rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("quadrature", [0, 2])
@pytest.mark.parametrize("shape", ["ring", "sponge"])
def test_energy_derivatives_in_the_buckles_params_match_finite_differences(shell, shape,
                                                                            quadrature):
    """The design gradients move the buckle through its params (inward motion d, fit dr;
    a ring's shift s along the meridians and ridge; a sponge's turn rot about the eye
    axis): autodiff derivatives of the contact energy in each against central differences,
    at the nodes and over the faces."""
    import jax

    if shape == "ring":
        t, names = _ring(shell, quadrature=quadrature), ("d", "s", "dr", "ridge")
    else:
        t, names = BuckleContact(
            "b", shell, "outer", "sponge", R, n0=(1.0, 0, 0), m0=(0, 0, -1.0),
            axis=(0, 0, -1.0), sponge_radius=2.5, sponge_length=10.0, modulus=0.5, curved=True,
            quadrature=quadrature), ("d", "dr", "rot")
    rng = np.random.default_rng(8)
    q_loc = jnp.asarray(0.03 * rng.standard_normal(t.dofs.shape))
    base = {**t.params, "d": np.array([0.6]), "s": np.array([0.3]), "dr": np.array([0.02]),
            "ridge": np.array([0.4]), "rot": np.array([0.01])}

    def energy(p):
        return jnp.sum(t.local_energy(q_loc, p, t.data))

    grads = jax.grad(energy)(jax.tree_util.tree_map(jnp.asarray, base))
    h = 1e-6
    for name in names:
        up = {**base, name: base[name] + h}
        down = {**base, name: base[name] - h}
        fd = (float(energy(up)) - float(energy(down))) / (2 * h)
        assert abs(float(grads[name][0])) > 1e-3, name  # the param moves the contact
        assert float(grads[name][0]) == pytest.approx(fd, rel=1e-6), name


def test_quadrature_outside_1_to_4_is_refused(shell):
    with pytest.raises(ValueError, match="quadrature = 5"):
        _ring(shell, quadrature=5)


def test_smoothed_penetration_is_the_penalty_deep_in_and_vanishes_outside():
    eps = 2e-3
    assert float(smooth_penetration(jnp.asarray(-0.1), eps)) == pytest.approx(0.1, rel=1e-12)
    assert float(smooth_penetration(jnp.asarray(0.05), eps)) < 1e-12
    assert float(smooth_penetration(jnp.asarray(0.0), eps)) == pytest.approx(eps * np.log(2))


def _fd_check(term, q_loc, params):
    """Autodiff local gradient and Hessian against central differences of the energy."""
    import jax

    kernel, energy = jax.jit(term.local_grad_hess), jax.jit(term.local_energy)  # not eager
    g, H = kernel(jnp.asarray(q_loc), params, term.data)
    g, H = np.asarray(g), np.asarray(H)
    e = lambda ql: np.asarray(energy(jnp.asarray(ql), params, term.data))  # noqa: E731
    grad = lambda ql: np.asarray(kernel(jnp.asarray(ql), params, term.data)[0])  # noqa: E731
    h = 1e-6
    k = q_loc.shape[1]
    for j in range(k):
        dq = np.zeros_like(q_loc)
        dq[:, j] = h
        fd_g = (e(q_loc + dq) - e(q_loc - dq)) / (2 * h)
        fd_H = (grad(q_loc + dq) - grad(q_loc - dq)) / (2 * h)
        np.testing.assert_allclose(g[:, j], fd_g, rtol=1e-6, atol=1e-9 * max(1, np.abs(g).max()))
        np.testing.assert_allclose(H[:, :, j], fd_H, rtol=1e-5, atol=1e-7 * max(1, np.abs(H).max()))


def _local_state(t, rng, amplitude=0.05, sunk=0.2):
    """Random local dofs of every contact point, the free radial dof (last column) sunk by
    ``sunk`` mm (the same value in every row, as the global dof it is)."""
    n, k = t.dofs.shape
    return np.concatenate([amplitude * rng.standard_normal((n, k - 1)), np.full((n, 1), sunk)],
                          axis=1)


@pytest.mark.parametrize("quadrature", [0, 2])
@pytest.mark.parametrize("shape", ["ring", "ring with 1.5 mm edges", "sponge", "curved sponge",
                                   "curved sponge with 2 mm ends"])
def test_buckle_contact_gradient_and_tangent_match_finite_differences(shell, shape, quadrature):
    if shape.startswith("ring"):
        edge = {"edge_width": 1.5} if "edges" in shape else {}
        t = _ring(shell, extra_dof=3 * shell.n_nodes, quadrature=quadrature, **edge)
    else:
        t = BuckleContact("b", shell, "outer", "sponge", R, n0=(1.0, 0, 0), m0=(0, 0, -1.0),
                          axis=(0, 0, -1.0), sponge_radius=2.5, sponge_length=10.0, modulus=0.5,
                          extra_dof=3 * shell.n_nodes, curved=shape.startswith("curved"),
                          quadrature=quadrature, end_width=2.0 if "ends" in shape else 0.0)
    rng = np.random.default_rng(1)
    q_loc = _local_state(t, rng)
    # the faces' points lie up to 0.3 mm inside this coarse shell's sphere: press deeper
    params = {**t.params, "d": np.array([0.4 if quadrature else 0.1]), "s": np.array([0.2]),
              "ridge": np.array([0.4]), "dr": np.array([0.05]), "rot": np.array([0.03])}
    pen = -np.asarray(t.gaps(q_loc, params, t.data))
    assert (pen > 0.01).any() and (pen < -0.01).any()  # some nodes in contact, some clear
    if "ends" in shape:  # some points in contact lie under the rounded ends
        sharp = dataclasses.replace(t, end_width=0.0)
        assert ((pen > 0) & (pen != -np.asarray(sharp.gaps(q_loc, params, sharp.data)))).any()
    _fd_check(t, q_loc, params)


@pytest.mark.parametrize("quadrature", [0, 2])
def test_gauss_newton_tangent_is_the_exact_one_less_the_surface_curvature_term(shell, quadrature):
    """The solver's modified tangent of the buckle contact: same gradient as the energy's,
    Hessian = exact Hessian - alpha p p' hess(g) (the curvature term, from autodiff of the
    gaps alone), and positive semidefinite where the exact one is not."""
    import jax
    from scipy.special import expit

    t = _ring(shell, extra_dof=3 * shell.n_nodes, quadrature=quadrature)
    rng = np.random.default_rng(3)
    n = t.n_points
    q = np.zeros(3 * shell.n_nodes + 1)
    q[:3 * shell.n_nodes] = 0.05 * rng.standard_normal(3 * shell.n_nodes)
    q[-1] = 0.2
    params = {**t.params, "d": np.array([0.1]), "s": np.array([0.2]), "ridge": np.array([0.4])}
    gauss_newton, exact = jax.jit(t.grad_hess_gauss_newton), jax.jit(t.local_grad_hess)
    g_gn, H_gn = (np.asarray(a) for a in gauss_newton(jnp.asarray(q), params, t.data, t.dofs))
    g_ex, H_ex = (np.asarray(a) for a in exact(jnp.asarray(q[t.dofs]), params, t.data))
    np.testing.assert_allclose(g_gn, g_ex, rtol=1e-12, atol=1e-15)
    q_loc = jnp.asarray(q[t.dofs])
    gaps = np.asarray(t.gaps(q_loc, params, t.data))
    eps = t.smoothing
    c = t.data["alpha"] * np.asarray(smooth_penetration(jnp.asarray(gaps), eps)) * -expit(-gaps / eps)
    # item i's gap depends on row i only: the Hessian of sum_i c_i g_i is block diagonal
    curv = row_hessians(lambda x: jnp.sum(c * t.gaps(x, params, t.data)), q_loc)
    assert curv.shape == (n, q_loc.shape[1], q_loc.shape[1])
    np.testing.assert_allclose(H_gn + curv, H_ex, rtol=1e-9, atol=1e-9 * np.abs(H_ex).max())
    assert np.abs(curv).max() > 1e-3 * np.abs(H_ex).max()  # the dropped term is not negligible
    assert np.linalg.eigvalsh(H_gn).min() > -1e-9 * np.abs(H_gn).max()
    assert np.linalg.eigvalsh(H_ex).min() < -1e-6 * np.abs(H_ex).max()


def _sponge(shell, radius=R):
    return BuckleContact("b", shell, "outer", "sponge", radius, n0=(1.0, 0, 0), m0=(0, 0, -1.0),
                         axis=(0, 0, -1.0), sponge_radius=2.5, sponge_length=10.0, modulus=0.5,
                         curved=True)


def test_fit_and_turn_params_equal_a_buckle_built_there(shell):
    """Param dr equals a buckle fitted at R + dr; param rot equals the nodes turned back by
    rot about the z axis (so a design can move the buckle without rebuilding it)."""
    from eyefem.fem.bars import rotate_z

    t, t2 = _sponge(shell), _sponge(shell, R + 0.3)
    X = t.data["X"]
    rng = np.random.default_rng(4)
    q = 0.05 * rng.standard_normal(X.shape)
    p = {**t.params, "d": np.array([0.2])}
    g_fit = np.asarray(t.gaps(q, {**p, "dr": np.array([0.3])}, t.data))
    np.testing.assert_allclose(g_fit, np.asarray(t2.gaps(q, p, t2.data)), atol=1e-12)
    ang = 0.4
    x_turned = np.asarray(rotate_z(X + q, ang))
    g_rot = np.asarray(t.gaps(x_turned - X, {**p, "rot": np.array([ang])}, t.data))
    np.testing.assert_allclose(g_rot, np.asarray(t.gaps(q, p, t.data)), atol=1e-12)
    assert np.abs(np.asarray(t.gaps(x_turned - X, p, t.data)) - g_rot).max() > 0.1  # it matters


def test_anchored_bar_anchor_follows_fit_and_turn_params(shell):
    """An anchor moved by dr along dir3 and turned by rot about z (closed form)."""
    faces = shell.face_set("outer")[:2]
    anchors = np.array([[11.0, 0.0, 1.0], [0.0, 11.0, -1.0]])
    d3 = anchors / np.linalg.norm(anchors, axis=1, keepdims=True)
    t = AnchoredBars("s", faces, np.zeros((2, 2)), anchors, np.zeros(2, int), np.zeros((2, 3)),
                     np.zeros((2, 3)), 1, shell.nodes, L0=np.ones(2), dirs3=d3)
    xa = shell.nodes[faces].mean(axis=1)  # xi = 0: the face centre
    a = 0.3
    p = {**t.params, "dr": np.array([0.5]), "rot": np.array([a])}
    xb = anchors + 0.5 * d3
    xb = np.stack([np.cos(a) * xb[:, 0] - np.sin(a) * xb[:, 1],
                   np.sin(a) * xb[:, 0] + np.cos(a) * xb[:, 1], xb[:, 2]], axis=1)
    np.testing.assert_allclose(np.asarray(t.lengths(np.zeros((2, 12)), p, t.data)),
                               np.linalg.norm(xb - xa, axis=1), rtol=1e-13)


def test_anchored_sutures_gradient_tangent_and_force(shell):
    faces = shell.face_set("outer")[:3]
    rng = np.random.default_rng(2)
    n = len(faces)
    xi = rng.uniform(-0.8, 0.8, (n, 2))
    anchors = shell.nodes[faces].mean(axis=1) * 1.1
    dirs = -anchors / np.linalg.norm(anchors, axis=1, keepdims=True)
    t = AnchoredBars("s", faces, xi, anchors, np.zeros(n, int), dirs, np.tile([0, 0, 1.0], (n, 1)),
                     1, shell.nodes, L0=np.ones(n), EA=40.0, extra_dof=3 * shell.n_nodes,
                     dirs3=np.tile([1.0, 0, 0], (n, 1)))
    q_loc = np.concatenate([0.05 * rng.standard_normal((n, 12)), np.full((n, 1), 0.1)], axis=1)
    base = {**t.params, "dr": np.array([0.1]), "rot": np.array([0.05])}
    params = {**base, "L0": np.asarray(t.lengths(q_loc, base, t.data)) - np.r_[0.02, 0.0, -0.02],
              "tightening": np.zeros(n)}
    _fd_check(t, q_loc, params)
    # the force is dE/dl: taut bar ~ EA/L0 * stretch, slack bar ~ 0
    f = np.asarray(t.axial_forces(jnp.asarray(q_loc), params, t.data))
    k = 40.0 / params["L0"]
    assert f[0] == pytest.approx(k[0] * 0.02, rel=1e-3)
    assert f[2] < 1e-12 and f[1] == pytest.approx(k[1] * 2e-4 * np.log(2) * 0.5, rel=1e-9)


@pytest.mark.parametrize("quadrature", [0, 2])
def test_gap_linearisation_is_the_directional_derivative_of_the_gaps(shell, quadrature):
    """The solver's contact look-ahead uses the gaps, their first-order change along a step,
    their gradients and the gaps at the step's end: checked against the gaps and central
    differences."""
    t = _ring(shell, extra_dof=3 * shell.n_nodes, quadrature=quadrature)
    rng = np.random.default_rng(5)
    q_loc = _local_state(t, rng)
    dq = 0.1 * rng.standard_normal(q_loc.shape)
    params = {**t.params, "d": np.array([0.1]), "ridge": np.array([0.4])}
    g, dg, G, g_end = (np.asarray(a) for a in t.gap_linearisation(
        jnp.asarray(q_loc), jnp.asarray(dq), params, t.data))
    gaps = lambda x: np.asarray(t.gaps(jnp.asarray(x), params, t.data))  # noqa: E731
    np.testing.assert_array_equal(g, gaps(q_loc))
    h = 1e-5  # gaps beyond the ring's edges reach 10^3 mm: round-off ~ 1e-16 |g| / h
    np.testing.assert_allclose(dg, (gaps(q_loc + h * dq) - gaps(q_loc - h * dq)) / (2 * h),
                               rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(np.einsum("nk,nk->n", G, dq), dg, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(g_end, gaps(q_loc + dq))


@pytest.fixture(scope="module")
def inflated_against_a_ring():
    """Octant of a thin sphere (outer radius R) inflated in one step by 30 mmHg, which
    alone would grow it by about 0.4 mm, against a rigid ring 0.1 mm (50 eps) outside its
    equator: the first Newton step runs the equator's nodes deep into the ring."""
    from eyefem.fem.materials import neo_hookean
    from eyefem.fem.surface import PressureLoad
    from eyefem.fem.units import MMHG
    from eyefem.solve.model import node_dofs, solid_model
    from eyefem.solve.solver import NewtonOptions, Stage, solve

    mesh = generators.spherical_shell(R - 0.5, 0.5, 8, 1, octant=True, material="sclera")
    ring = BuckleContact("ring", mesh, "outer", "ring", R + 0.1, theta_b=np.pi / 2, width=7.0,
                         modulus=0.5)
    model = solid_model(mesh, {"sclera": neo_hookean("sclera", 0.0833)},
                        (PressureLoad("p", mesh, "inner", 0.0), ring))
    d = np.concatenate([node_dofs(mesh.node_set(f"sym_{c}"), c) for c in "xyz"])
    stage = Stage("inflate", 1, (d, np.zeros(len(d))), params={"p": {"p": 30 * MMHG}})
    out = {k: solve(model, [stage], options=NewtonOptions(contact_lookahead=k))
           for k in (True, False)}
    out["problem"] = (model, stage)
    return out


def test_contact_lookahead_reaches_the_same_state_in_fewer_iterations(inflated_against_a_ring):
    on, off = inflated_against_a_ring[True], inflated_against_a_ring[False]
    assert [r.t for r in on.history] == [1.0]  # no cut
    np.testing.assert_allclose(on.q, off.q, atol=1e-7)
    ring = on.model.term("ring")
    g = np.asarray(ring.gaps(on.q[ring.dofs], on.theta["ring"], ring.data))
    assert g.min() < ring.smoothing  # the equator is held by the ring, the pole is not
    x = on.model.mesh.nodes + on.q[:3 * on.model.mesh.n_nodes].reshape(-1, 3)
    r = np.linalg.norm(x[ring.nodes], axis=1)
    assert r[np.abs(x[ring.nodes, 2]) < 0.1].max() < R + 0.1
    assert r[x[ring.nodes, 2] > R - 0.1].min() > R + 0.2
    its = lambda s: sum(r.iterations for r in s.history)  # noqa: E731
    assert its(on) < its(off)  # 7 against 11 when written


def test_lookahead_with_its_stiffness_factorised_anew_reaches_the_same_state(
        inflated_against_a_ring, monkeypatch):
    """Beyond LOOKAHEAD_DENSE_BYTES the look-ahead nodes' stiffness is added to the sparse
    tangent and factorised anew instead of a Woodbury update (whose dense columns grew a
    finer-eye run by 18 GB): with the bound at 0 the run takes the same iterations to the
    same state."""
    from eyefem.solve import contact_strategy
    from eyefem.solve.solver import NewtonOptions, solve

    on = inflated_against_a_ring[True]
    monkeypatch.setattr(contact_strategy, "LOOKAHEAD_DENSE_BYTES", 0)
    model, stage = inflated_against_a_ring["problem"]
    fresh = solve(model, [stage], options=NewtonOptions(contact_lookahead=True))
    np.testing.assert_allclose(fresh.q, on.q, atol=1e-9)
    its = lambda s: sum(r.iterations for r in s.history)  # noqa: E731
    assert its(fresh) == its(on)


def test_a_wrong_lookahead_step_falls_back_to_the_plain_newton_step(inflated_against_a_ring, monkeypatch):
    """When no trial of the look-ahead's step lowers the residual (its model of a node is
    wrong), the plain Newton step is taken: a look-ahead that always returns the reversed
    step changes neither the converged state nor the iteration count of the run
    without look-ahead."""
    from eyefem.solve import globalisation
    from eyefem.solve.solver import NewtonOptions, solve

    off = inflated_against_a_ring[False]
    calls = []

    def reversed_step(model, asm, q, theta, active, solver, rf, rm, x, y, rounds=4, **kw):
        calls.append(1)
        return -x, -y, solver, 1

    monkeypatch.setattr(globalisation, "lookahead", reversed_step)
    model, stage = inflated_against_a_ring["problem"]
    fresh = solve(model, [stage], options=NewtonOptions(contact_lookahead=True))
    assert calls
    np.testing.assert_allclose(fresh.q, off.q, atol=1e-9)
    its = lambda s: sum(r.iterations for r in s.history)  # noqa: E731
    assert its(fresh) == its(off)
