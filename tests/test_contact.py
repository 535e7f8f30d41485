"""Penalty contact: closest points, rigid plates and bodies, the contact patch test,
sliding on a curved surface, sticking vs sliding, many pairs, bad input."""

import numpy as np
import pytest

from eyefem.fem import generators
from eyefem.fem.contact import SurfaceContact
from eyefem.fem.materials import invariant_derivatives, mooney_rivlin
from eyefem.fem.mesh import merge
from eyefem.fem.rigid import (
    RigidBody,
    closest_point_triangle,
    cylinder,
    plane,
    ring_segment,
    sphere,
)
from eyefem.fem.rigid_contact import RigidContact
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage, solve
from eyefem.verify.checks import row_hessians

MAT = mooney_rivlin("r", 1.0, 0.2)


def test_closest_point_matches_brute_force():
    rng = np.random.default_rng(0)
    a, b, c = (rng.standard_normal((200, 3)) for _ in range(3))
    p = 2 * rng.standard_normal((200, 3))
    got = closest_point_triangle(p, a, b, c)
    s, t = np.meshgrid(np.linspace(0, 1, 401), np.linspace(0, 1, 401))
    keep = s + t <= 1
    s, t = s[keep], t[keep]
    for i in range(0, 200, 7):
        cloud = a[i] + s[:, None] * (b[i] - a[i]) + t[:, None] * (c[i] - a[i])
        best = np.linalg.norm(cloud - p[i], axis=1).min()
        assert np.linalg.norm(got[i] - p[i]) <= best + 1e-9
        assert np.linalg.norm(got[i] - p[i]) >= best - 5e-3  # the cloud spacing


def test_rigid_body_bad_input():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    with pytest.raises(ValueError, match=r"triangles \[1\] have zero area"):
        RigidBody("b", pts, [[0, 1, 2], [0, 1, 1]])
    with pytest.raises(ValueError, match="inconsistent orientation"):
        RigidBody("b", pts, [[0, 1, 2], [0, 1, 3]])
    with pytest.raises(ValueError, match="direction is the zero vector"):
        RigidBody("b", pts, [[0, 1, 2]], direction=(0, 0, 0))


def _report(sol, term):
    """The report of one term: {quantity: value}."""
    rep = sol.model.report(sol.q, sol.theta)
    return {k.split("/", 1)[1]: v for k, v in rep.items() if k.startswith(term + "/")}


def test_generated_rigid_normals_point_the_documented_way():
    for body, sign in ((cylinder("c", (1, 2, 3), (0, 1, 1), 5.0, 4.0), 1),
                       (cylinder("t", (1, 2, 3), (0, 1, 1), 5.0, 4.0, inward=True), -1),
                       (ring_segment("r", (1, 2, 3), (0, 1, 1), 5.0, 2.0, 0.0, 1.0), -1),
                       (sphere("s", (1, 2, 3), 5.0), 1)):
        centroid = body.points[body.triangles].mean(axis=1) - np.array([1.0, 2.0, 3.0])
        assert np.all(sign * np.einsum("ti,ti->t", body.normals, centroid) > 0), body.name


def _block():
    return generators.box(1, 1, 1, 3, 3, 3, material="r")


def _symmetry_dofs(m):
    return np.concatenate([node_dofs(m.node_set("x0"), "x"), node_dofs(m.node_set("y0"), "y"),
                           node_dofs(m.node_set("z0"), "z")])


def _press_block(penalty):
    m = _block()
    plate = plane("plate", (0.5, 0.5, 1.0), (0, 0, -1), 3.0, direction=(0, 0, -1))
    contact = RigidContact("contact", m, "z1", (plate,), penalty=penalty)
    model = solid_model(m, {"r": MAT}, (contact,))
    d = _symmetry_dofs(m)
    sol = solve(model, [Stage("press", 4, (d, np.zeros(len(d))),
                              params={"contact": {"d": np.array([0.2])}})])
    z1 = node_dofs(m.node_set("z1"), "z")
    lam = 1 + sol.q[z1].mean()
    w1, w2 = invariant_derivatives(lam**2 + 2 / lam, 2 * lam + lam**-2, MAT.coeffs)
    force_theory = 2 * (lam - lam**-2) * (w1 + w2 / lam)  # uniaxial, area 1 mm^2
    reaction = sol.model.gradient(sol.q, sol.theta)[node_dofs(m.node_set("z0"), "z")].sum()
    rep = _report(sol, "contact")
    return lam, force_theory, reaction, rep


def test_rigid_plate_force_matches_uniaxial_theory_and_penetration_drops():
    lam_lo, f_lo, r_lo, rep_lo = _press_block(1e2)
    lam_hi, f_hi, r_hi, rep_hi = _press_block(1e4)
    for lam, f, r, rep in ((lam_lo, f_lo, r_lo, rep_lo), (lam_hi, f_hi, r_hi, rep_hi)):
        assert lam < 0.85  # compressed
        assert rep["active"] == 16  # every top node touches the plate
        assert rep["force_N"] == pytest.approx(abs(r), rel=1e-9)  # equilibrium
    # the top is uniformly displaced when the penalty is large (each node has the same
    # alpha, so with a soft penalty the edge nodes sink less: a 0.2% error at alpha = 100)
    assert abs(r_hi) == pytest.approx(abs(f_hi), rel=1e-4)
    assert abs(r_lo) == pytest.approx(abs(f_lo), rel=5e-3)
    # the plate moved 0.2 mm: the top sinks 0.2 minus the penetration
    assert abs((1 - lam_hi) - 0.2) <= rep_hi["max_penetration_mm"] + 1e-12
    assert rep_hi["max_penetration_mm"] < 0.02 * rep_lo["max_penetration_mm"]
    assert rep_lo["max_penetration_mm"] > 1e-3


def test_fifty_rigid_bodies():
    """50 small plates pressed into a slab, each by its own amount."""
    m = generators.box(10, 5, 1, 20, 10, 2, material="r")
    bodies = []
    for k in range(50):
        cx, cy = 0.5 + (k % 10), 0.5 + (k // 10)
        bodies.append(plane(f"p{k}", (cx, cy, 1.0), (0, 0, -1), 0.7, n=2, direction=(0, 0, -1)))
    contact = RigidContact("contact", m, "z1", tuple(bodies), modulus=6 * 1.2)
    model = solid_model(m, {"r": MAT}, (contact,))
    d = node_dofs(m.node_set("z0"))
    push = 0.02 * (1 + np.arange(50) / 50)
    sol = solve(model, [Stage("press", 2, (d, np.zeros(len(d))),
                              params={"contact": {"d": push}})])
    term = sol.model.term("contact")
    g, node, _ = term._state(sol.q, sol.theta["contact"])
    body = term.data["body"][term.data["w"] > 0]
    touching = np.unique(body[g < 0])
    assert len(touching) == 50
    uz = sol.q[: 3 * m.n_nodes].reshape(-1, 3)[:, 2]
    for k in (0, 17, 49):  # the node under each plate centre follows the plate
        j = node[(body == k) & (g < 0)]
        assert uz[j].min() == pytest.approx(-push[k], rel=0.2)
    assert _report(sol, "contact")["max_penetration_mm"] < 0.1 * push.min()


def test_block_slides_on_curved_rigid_surface():
    """A block pressed on a rigid cylinder (radius 10) and carried 20 degrees around it:
    frictionless, so it stays in contact and the tangential reaction vanishes."""
    m = generators.box(1, 1, 0.5, 4, 4, 2, origin=(-0.5, -0.5, 10.0), material="r")
    cyl = cylinder("cyl", (0, 0, 0), (0, 1, 0), 10.0, 4.0, n_circ=360, n_len=4)
    contact = RigidContact("contact", m, "z0", (cyl,), modulus=6.0, penalty=1e4)
    model = solid_model(m, {"r": MAT}, (contact,))
    top = m.node_set("z1")
    X = m.nodes[top]
    side = np.setdiff1d(m.node_set("y0"), top)
    dofs = np.concatenate([node_dofs(top), node_dofs(side, "y")])
    stages = []
    for k, ang in enumerate(np.radians([0.0, 5.0, 10.0, 15.0, 20.0])):
        c, s = np.cos(ang), np.sin(ang)
        Xp = X * [1, 1, 1]
        Xp[:, 2] -= 0.02  # pressed 0.02 mm
        x = np.stack([c * Xp[:, 0] + s * Xp[:, 2], Xp[:, 1], -s * Xp[:, 0] + c * Xp[:, 2]], 1)
        vals = np.concatenate([(x - X).ravel(), np.zeros(len(side))])
        stages.append(Stage(f"slide{k}", 2, (dofs, vals)))
    sol = solve(model, stages)
    g, node, _ = sol.model.term("contact")._state(sol.q, sol.theta["contact"])
    bottom = m.node_set("z0")
    assert np.isin(bottom, node[g < 0]).all()  # all bottom nodes still touch
    assert -g.min() < 1e-3  # penetration below 1e-3 mm with alpha = 1e4
    r = sol.model.gradient(sol.q, sol.theta)[: 3 * m.n_nodes].reshape(-1, 3)[top].sum(axis=0)
    ang = np.radians(20.0)
    t = np.array([np.cos(ang), 0, -np.sin(ang)])  # tangent of the arc at the block
    nrm = np.array([np.sin(ang), 0, np.cos(ang)])
    assert abs(r @ nrm) > 0.01  # it is pressed
    assert abs(r @ t) < 1e-2 * abs(r @ nrm)  # no friction (0.3%: the 1-degree facets)


def _stack(mode, shear, two_pass):
    """A 3x3x2 block under a 4x4x2 block (non-matching), pressed 0.05 mm from the top, then
    (shear) the top dragged 0.05 mm in x with the upper block free in x.

    Returns: mesh, solution, mean x-displacement of the lower block's top after each stage.
    """
    lo = generators.box(1, 1, 0.5, 3, 3, 2, material="r")
    hi = generators.box(1, 1, 0.5, 4, 4, 2, origin=(0, 0, 0.5), material="r")
    m = merge(("lo", lo), ("hi", hi))
    terms = (SurfaceContact("c1", m, "hi/z0", "lo/z1", mode=mode, penalty=1e4),)
    if two_pass:
        terms += (SurfaceContact("c2", m, "lo/z1", "hi/z0", mode=mode, penalty=1e4),)
    model = solid_model(m, {"r": MAT}, terms)
    fix = [node_dofs(m.node_set(s), "x") for s in ("lo/x0", "hi/x0")]
    fix += [node_dofs(m.node_set(s), "y") for s in ("lo/y0", "hi/y0")]
    fix += [node_dofs(m.node_set("lo/z0"), "z")]
    d = np.unique(np.concatenate(fix))
    top = node_dofs(m.node_set("hi/z1"), "z")
    d1 = np.concatenate([d, top])
    v1 = np.concatenate([np.zeros(len(d)), np.full(len(top), -0.05)])
    stages = [Stage("press", 2, (d1, v1))]
    if shear:  # free the upper block in x, drag its top by 0.05 mm
        topx = node_dofs(m.node_set("hi/z1"), "x")
        keep = ~np.isin(d1, node_dofs(m.node_set("hi/x0"), "x"))
        d2 = np.concatenate([d1[keep], topx])
        stages.append(Stage("shear", 2, (d2, np.concatenate([v1[keep], np.full(len(topx), 0.05)]))))
    lo_top_x = node_dofs(m.node_set("lo/z1"), "x")
    ux = {}

    def on_step(rec, model, q, theta):
        ux[rec.stage] = q[lo_top_x].mean()

    return m, solve(model, stages, on_step=on_step), ux


def test_contact_patch_test_two_pass_transmits_uniform_stress():
    m, sol, _ = _stack("sliding", shear=False, two_pass=True)
    szz = sol.model.terms[0].fields(sol.q, sol.theta["solid"])["cauchy"][:, 2, 2]
    assert szz.max() < -0.1
    assert np.ptp(szz) < 1e-3 * abs(szz.mean())
    assert _report(sol, "c1")["active"] > 0 and _report(sol, "c2")["active"] > 0


def test_one_pass_patch_test_is_not_uniform():
    """Why the patch test needs two passes: one pass lets master nodes penetrate."""
    m, sol, _ = _stack("sliding", shear=False, two_pass=False)
    szz = sol.model.terms[0].fields(sol.q, sol.theta["solid"])["cauchy"][:, 2, 2]
    assert np.ptp(szz) > 0.05 * abs(szz.mean())


def test_sticking_transmits_shear_sliding_does_not():
    drag = {}
    for mode in ("sliding", "sticking"):
        m, sol, ux = _stack(mode, shear=True, two_pass=False)
        drag[mode] = ux["shear"] - ux["press"]  # the lower block's top, moved by the shear
    # frictionless: only the normal forces on the slightly tilted faces act (< 2%)
    assert abs(drag["sliding"]) < 2e-2 * 0.05
    assert drag["sticking"] > 0.1 * 0.05  # stuck: dragged along
    assert drag["sticking"] > 20 * abs(drag["sliding"])


def test_one_hundred_contact_pairs():
    """50 stacks of non-matching blocks, two-pass contact each: 100 contact terms."""
    parts = []
    for k in range(50):
        o = (2.0 * (k % 10), 2.0 * (k // 10), 0.0)
        parts.append((f"lo{k}", generators.box(1, 1, 0.5, 1, 1, 1, origin=o, material="r")))
        parts.append((f"hi{k}", generators.box(1, 1, 0.5, 2, 2, 1, origin=(o[0], o[1], 0.5),
                                               material="r")))
    m = merge(*parts)
    terms = []
    for k in range(50):
        terms.append(SurfaceContact(f"a{k}", m, f"hi{k}/z0", f"lo{k}/z1", penalty=1e4))
        terms.append(SurfaceContact(f"b{k}", m, f"lo{k}/z1", f"hi{k}/z0", penalty=1e4))
    model = solid_model(m, {"r": MAT}, tuple(terms))
    d, v = [], []
    for k in range(50):
        for s, comp in ((f"lo{k}/x0", "x"), (f"hi{k}/x0", "x"), (f"lo{k}/y0", "y"),
                        (f"hi{k}/y0", "y"), (f"lo{k}/z0", "z")):
            d.append(node_dofs(m.node_set(s), comp))
            v.append(np.zeros(len(d[-1])))
        d.append(node_dofs(m.node_set(f"hi{k}/z1"), "z"))
        v.append(np.full(len(d[-1]), -0.01 * (1 + k / 50)))
    sol = solve(model, [Stage("press", 1, (np.concatenate(d), np.concatenate(v)))])
    rep = sol.model.report(sol.q, sol.theta)
    assert all(rep[f"a{k}/active"] + rep[f"b{k}/active"] > 0 for k in range(50))
    szz = sol.model.terms[0].fields(sol.q, sol.theta["solid"])["cauchy"][:, 2, 2]
    lo = szz[0::5]  # the one-element lower block of each stack (merge keeps the order)
    assert np.all(np.diff(lo) < 0)  # more compression stack by stack


def test_contact_bad_input():
    m = merge(("lo", generators.box(1, 1, 0.5, 2, 2, 1, material="r")),
              ("hi", generators.box(1, 1, 0.5, 3, 3, 1, origin=(0, 0, 0.3), material="r")))
    with pytest.raises(KeyError, match="no face set 'lo/top'"):
        SurfaceContact("c", m, "hi/z0", "lo/top")
    with pytest.raises(ValueError, match=r"node \d+ starts 0.2 mm inside face set 'lo/z1'"):
        SurfaceContact("c", m, "hi/z0", "lo/z1")
    with pytest.raises(ValueError, match="mode 'glued'"):
        SurfaceContact("c", m, "hi/z0", "lo/z1", mode="glued", max_initial_penetration=1.0)
    plate = plane("plate", (0.5, 0.5, 0.1), (0, 0, -1), 3.0)
    with pytest.raises(ValueError, match=r"nodes start inside rigid bodies .* depth 0.4 mm in 'plate'"):
        RigidContact("c", m, "lo/z1", (plate,))


def test_smoothed_sliding_contact_closed_form():
    """Node over a flat unit face at gap g, smoothing eps: energy 1/2 alpha (eps
    softplus(-g / eps))^2: the plain penalty 1/2 alpha g^2 for -g >> eps, 1/2 alpha
    (eps ln 2)^2 at touching, and nothing left for g >> eps; unchanged by a rigid motion."""
    import jax.numpy as jnp

    from eyefem.fem.contact import SurfaceContact

    X = np.array([[0.3, 0.4, 0.0], [0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    alpha, eps = 40.0, 0.01
    data = {"X": X[None], "xi": np.zeros((1, 2)), "w": np.ones(1), "alpha": np.full(1, alpha),
            "area": np.ones(1), "eps": np.full(1, eps)}
    term = SurfaceContact.__new__(SurfaceContact)
    object.__setattr__(term, "mode", "sliding")
    object.__setattr__(term, "smoothing", eps)

    def energy(x5):
        return float(term.local_energy(jnp.asarray((x5 - X).reshape(1, 15)), {"scale": 1.0}, data)[0])

    def at_gap(g):
        x5 = X.copy()
        x5[0] = [0.5, 0.5, g]  # over the face centre (xi = 0), normal +z
        return x5

    assert energy(at_gap(-0.5)) == pytest.approx(0.5 * alpha * 0.5**2, rel=1e-12)
    assert energy(at_gap(0.0)) == pytest.approx(0.5 * alpha * (eps * np.log(2)) ** 2, rel=1e-12)
    assert energy(at_gap(0.5)) < 1e-30
    rng = np.random.default_rng(0)
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))
    x5 = at_gap(-0.003)
    assert energy(x5 @ Q.T + [1.0, -2.0, 0.5]) == pytest.approx(energy(x5), rel=1e-10)


@pytest.mark.parametrize("smoothing", [None, 0.01])
def test_surface_contact_gauss_newton_tangent_is_the_exact_one_less_the_gap_curvature(smoothing):
    """The solver's modified tangent of node-to-segment contact (contact_curvature): the
    energy's gradient, Hessian = exact Hessian - a p p' hess(g) (the gap's curvature
    term, from autodiff of the gaps alone), positive semidefinite."""
    import jax
    import jax.numpy as jnp
    from scipy.special import expit

    lo = generators.box(1, 1, 0.5, 3, 3, 1, material="r")
    hi = generators.box(1, 1, 0.5, 4, 4, 1, origin=(0, 0, 0.5), material="r")
    m = merge(("lo", lo), ("hi", hi))
    rng = np.random.default_rng(4)
    q = 0.03 * rng.standard_normal(3 * m.n_nodes)
    q[2::3][m.node_set("hi")] -= 0.02  # the upper block sunk into the lower one
    t = SurfaceContact("c", m, "hi/z0", "lo/z1", penalty=1e3, smoothing=smoothing).update(q, None)
    params = {"scale": 1.0}
    q_loc = jnp.asarray(q[t.dofs])
    gauss_newton, exact = jax.jit(t.grad_hess_gauss_newton), jax.jit(t.local_grad_hess)
    g_gn, H_gn = (np.asarray(a) for a in gauss_newton(jnp.asarray(q), params, t.data, t.dofs))
    g_ex, H_ex = (np.asarray(a) for a in exact(q_loc, params, t.data))
    np.testing.assert_allclose(g_gn, g_ex, rtol=1e-12, atol=1e-12 * np.abs(g_ex).max())
    gaps = np.asarray(t.local_gaps(q_loc, t.data))
    a = t.data["w"] * t.data["alpha"]
    assert (gaps[a > 0] < 0).sum() >= 5 and (gaps[a > 0] > 0).sum() >= 1
    if smoothing is None:
        c = a * np.minimum(gaps, 0.0)
    else:
        c = -a * smoothing * np.logaddexp(-gaps / smoothing, 0.0) * expit(-gaps / smoothing)
    # pair i's gap depends on row i only: the Hessian of sum_i c_i g_i is block diagonal
    curv = row_hessians(lambda x: jnp.sum(c * t.local_gaps(x, t.data)), q_loc)
    np.testing.assert_allclose(H_gn + curv, H_ex, rtol=1e-9, atol=1e-9 * np.abs(H_ex).max())
    assert np.abs(curv).max() > 1e-3 * np.abs(H_ex).max()  # the dropped term is not negligible
    assert np.linalg.eigvalsh(H_gn).min() > -1e-9 * np.abs(H_gn).max()


def _arc_force(normals, x, depth=0.01, alpha=1e3, theta=0.1, radius=10.0):
    """Force (3,) N on a node pressed depth mm below the top of a faceted cylinder (four
    faces over 0.4 rad of a 10 mm radius about the y axis, top node row at x = 2, z = 0.5)
    at x; the pair's forces must sum to zero."""
    import jax

    lo = generators.box(4, 1, 0.5, 4, 1, 1, material="r")
    hi = generators.box(0.2, 0.2, 0.2, 1, 1, 1, origin=(1.9, 0.4, 0.8), material="r")
    m = merge(("lo", lo), ("hi", hi))
    X = m.nodes
    q = np.zeros(3 * m.n_nodes)
    top = np.flatnonzero(np.isclose(X[:, 2], 0.5) & np.isin(np.arange(len(X)), m.node_set("lo")))
    phi = (X[top, 0] - 2.0) * theta
    arc = np.stack([2.0 + radius * np.sin(phi), X[top, 1], 0.5 - radius * (1 - np.cos(phi))], 1)
    q.reshape(-1, 3)[top] = arc - X[top]
    z0 = m.node_set("hi/z0")
    node = int(z0[np.argmin(np.linalg.norm(X[z0] - [1.9, 0.4, 0.8], axis=1))])
    top_z = 0.5 - radius * (1 - np.sqrt(1 - ((x - 2.0) / radius) ** 2))
    q[3 * node: 3 * node + 3] = np.array([x, 0.5, top_z - depth]) - X[node]
    t = SurfaceContact("c", m, "hi/z0", "lo/z1", penalty=alpha, normals=normals).update(q, None)
    g = np.asarray(jax.grad(lambda y: t.energy(y, t.params, t.data, t.dofs))(q))
    assert np.abs(g).max() > 0 and np.abs(g.reshape(-1, 3).sum(axis=0)).max() < 1e-12 * np.abs(g).max()
    return -g[3 * node: 3 * node + 3]


@pytest.mark.parametrize("normals", ["facet", "nodal"])
def test_nodal_normals_carry_the_force_continuously_over_a_facet_edge(normals):
    """A node pressed 0.01 mm into a faceted cylinder (faces 0.1 rad apart) just either
    side of the edge on its top: with flat faces its force turns by 0.1 rad across the
    edge (x component -+sin(0.05) of it); on the Nagata patches of the nodal normals
    it is continuous and vertical there (the edge nodes' normal), and its size is that
    of the penalty at the depth below the cylinder (the patches follow the arc, where
    the faces lie up to 3 um inside it at their middles)."""
    left, right = _arc_force(normals, 2.0 - 1e-4), _arc_force(normals, 2.0 + 1e-4)
    size = np.linalg.norm(left)
    assert size == pytest.approx(1e3 * 0.01, rel=2e-3)
    if normals == "nodal":
        np.testing.assert_allclose(right, left, atol=1e-4 * size)
        assert abs(left[0]) < 1e-4 * size and left[2] > 0
    else:
        np.testing.assert_allclose([left[0], right[0]], [-np.sin(0.05) * size, np.sin(0.05) * size],
                                   rtol=1e-3)


def test_nagata_patch_follows_the_arc_the_faces_cut_across():
    """Between the edges of the faceted cylinder the flat faces lie up to R (1 - cos 0.05)
    = 12.5 um inside it; on the Nagata patches a node pressed 0.02 mm below the cylinder
    over a face's middle feels the penalty of 0.02 mm (flat faces: of 0.0075 mm)."""
    on_patch, on_face = (np.linalg.norm(_arc_force(n, 2.5, depth=0.02)) for n in ("nodal", "facet"))
    assert on_patch == pytest.approx(1e3 * 0.02, rel=1e-3)
    assert on_face == pytest.approx(1e3 * (0.02 - 10.0 * (1 - np.cos(0.05))), rel=2e-2)


def test_nagata_patch_stays_near_its_face_when_a_node_leaves_its_held_normals():
    """Nodal normals 0.02 rad apart (a fine mesh of a sphere) are held while a node moves
    0.1 mm along them (one Newton step indenting the sclera): the patch bends by the
    normals' angle times the edge, not by the step over the angle squared."""
    from eyefem.fem.contact import nagata_patch

    h, ang = 0.5, 0.02
    xf = np.array([[0, 0, 0], [h, 0, 0], [h, h, 0], [0, h, 0]], float)[None]
    tilt = lambda a: np.array([np.sin(a), 0.0, np.cos(a)])
    n4 = np.stack([tilt(-ang / 2), tilt(ang / 2), tilt(ang / 2), tilt(-ang / 2)])[None]
    xi = np.stack(np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 9)), -1).reshape(-1, 2)
    dev = []
    for lift in (0.0, 0.1):
        x = xf.copy()
        x[0, 1, 2] += lift
        p, _ = nagata_patch(xi, np.repeat(x, len(xi), 0), np.repeat(n4, len(xi), 0))
        N = 0.25 * (1 + xi[:, :1] * [-1, 1, 1, -1]) * (1 + xi[:, 1:] * [-1, -1, 1, 1])
        dev.append(np.abs(np.asarray(p) - N @ x[0]).max())
    assert dev[0] == pytest.approx(h * ang / 8, rel=0.05)  # the arc's sag at mid-edge
    assert dev[1] < 2 * h * ang


def test_nodal_normals_need_sliding_contact():
    m = merge(("lo", generators.box(1, 1, 0.5, 2, 2, 1, material="r")),
              ("hi", generators.box(1, 1, 0.5, 3, 3, 1, origin=(0, 0, 0.6), material="r")))
    with pytest.raises(ValueError, match="normals 'nodal' needs mode 'sliding'"):
        SurfaceContact("c", m, "hi/z0", "lo/z1", mode="sticking", normals="nodal")
    with pytest.raises(ValueError, match="normals 'smooth'; use 'facet' or 'nodal'"):
        SurfaceContact("c", m, "hi/z0", "lo/z1", normals="smooth")
