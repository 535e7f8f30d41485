"""Hand-coded (numpy) contact forces and tangents, and their tangent-verification checks.

Rigid (frictionless, frozen closest point c and normal n, body moved by d * dir):

    g = (x - c - d dir) . n,   r = alpha g n,   K = alpha n n^T          (g < 0)

Node to quadrilateral, with the seed's D vector of length 15 (hitting node, then the
four face nodes) D = [n, -N_1 n, ..., -N_4 n]:

    sliding:   g = (x_h - x_t) . n(x_1..x_4),   r = alpha g dg,   K = alpha (dg dg^T + g d2g)
    sticking:  d = x_h - x_t(xi_0),             r = alpha Dm^T d,  K = alpha Dm^T Dm

with dg = D + (the normal's variation), Dm = [I, -N_1 I, ..., -N_4 I] (3 x 15). The
normal n = m / |m|, m = t_1 x t_2, t_k = sum_a N_a,k x_a is differentiated in full:
dn = P dm / |m| (P = I - n n^T), d2m[u, v] = dt_1[u] x dt_2[v] + dt_1[v] x dt_2[u].
On a Nagata patch (held nodal normals) the target point and tangents are still linear
in the positions, x_t = sum_a M_a x_a and t_k = sum_a M_a,k x_a with 3 x 3 matrices
(the edges' curvature vectors are linear in the edge vectors): the same formulas with
N_a I -> M_a and N_a,k I -> M_a,k (the matrices from the patch formula, column by column).
"""

from __future__ import annotations

import numpy as np

_C = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)


def quad_shape(xi):
    """Bilinear N (4,) and dN/dxi (4, 2) at xi (2,)."""
    N = 0.25 * (1 + xi[0] * _C[:, 0]) * (1 + xi[1] * _C[:, 1])
    dN = np.stack([0.25 * _C[:, 0] * (1 + xi[1] * _C[:, 1]),
                   0.25 * _C[:, 1] * (1 + xi[0] * _C[:, 0])], -1)
    return N, dN


def rigid_residual_tangent(x, c, n, alpha):
    """Residual (3,) N and tangent (3, 3) N/mm of one node x against a rigid point c, normal n."""
    g = float((x - c) @ n)
    if g >= 0:
        return np.zeros(3), np.zeros((3, 3))
    return alpha * g * n, alpha * np.outer(n, n)


def _linear_maps(xi, n4):
    """(Dm, T1, T2) (3, 15): x_h - x_t = Dm x, t_k = T_k x for the 15 positions x of a
    hitting node and a face: bilinear (n4 None) or the Nagata patch of nodal normals n4
    (4, 3), columns from the patch at unit positions (linear for fixed normals)."""
    if n4 is None:
        N, dN = quad_shape(xi)
        Dm = np.hstack([np.eye(3)] + [-N[a] * np.eye(3) for a in range(4)])
        T = [np.hstack([np.zeros((3, 3))] + [dN[a, k] * np.eye(3) for a in range(4)])
             for k in range(2)]
        return Dm, T[0], T[1]
    from eyefem.fem.contact import nagata_patch

    cols = []
    for j in range(12):
        xf = np.zeros(12)
        xf[j] = 1.0
        p, tan = nagata_patch(xi[None], xf.reshape(1, 4, 3), n4[None])
        cols.append(np.concatenate([np.asarray(p)[0], np.asarray(tan)[0].ravel()]))
    M = np.array(cols).T  # (9, 12): x_t, t_1, t_2 per unit face position
    Dm = np.hstack([np.eye(3), -M[:3]])
    zero = np.zeros((3, 3))
    return Dm, np.hstack([zero, M[3:6]]), np.hstack([zero, M[6:9]])


def node_quad_residual_tangent(x5, xi, alpha, mode="sliding", smoothing=None, n4=None):
    """Residual (15,) and tangent (15, 15) of a hitting node x5[0] against face x5[1:5].

    Args: x5 (5, 3) current positions, mm; xi (2,) parametric point; alpha N/mm;
      smoothing: eps (mm) of the smoothed penetration p = eps softplus(-g / eps) (energy
      1/2 alpha p^2: dE/dg = -alpha p s, d2E/dg2 = alpha (s^2 + p s (1 - s) / eps) with
      s = sigmoid(-g / eps)); None: the plain penalty 1/2 alpha <-g>^2; n4: held nodal
      unit normals (4, 3) (the Nagata patch), None: the flat face.
    """
    Dm, T1, T2 = _linear_maps(np.asarray(xi, float), n4)
    x = x5.ravel()
    r = Dm @ x
    if mode == "sticking":
        return alpha * Dm.T @ r, alpha * Dm.T @ Dm
    t1, t2 = T1 @ x, T2 @ x
    m = np.cross(t1, t2)
    lm = np.linalg.norm(m)
    n = m / lm
    g = float(r @ n)
    if smoothing is None and g >= 0:
        return np.zeros(15), np.zeros((15, 15))
    P = np.eye(3) - np.outer(n, n)
    E = np.eye(15)

    def parts(u):  # variations of r, t1, t2, m, n along a 15-vector u
        dt1, dt2 = T1 @ u, T2 @ u
        dm = np.cross(dt1, t2) + np.cross(t1, dt2)
        return Dm @ u, dt1, dt2, dm, P @ dm / lm

    V = [parts(E[i]) for i in range(15)]
    dg = np.array([dr @ n + r @ dn for dr, _, _, _, dn in V])
    d2g = np.zeros((15, 15))
    for i, (dru, dt1u, dt2u, dmu, dnu) in enumerate(V):
        for j, (drv, dt1v, dt2v, dmv, dnv) in enumerate(V):
            d2m = np.cross(dt1u, dt2v) + np.cross(dt1v, dt2u)
            d2n_r = (-(r @ dnv) * (n @ dmu) / lm - g * (dnv @ dmu) / lm
                     - (n @ dmv) * (r @ P @ dmu) / lm**2 + r @ P @ d2m / lm)
            d2g[i, j] = dru @ dnv + drv @ dnu + d2n_r
    return _penalty(g, dg, d2g, alpha, smoothing)


def _penalty(g, dg, d2g, alpha, smoothing):
    """Residual and tangent of the penalty energy at gap g with its first and second
    derivatives dg (15,), d2g (15, 15)."""
    if smoothing is None:
        if g >= 0:
            return np.zeros(15), np.zeros((15, 15))
        return alpha * g * dg, alpha * (np.outer(dg, dg) + g * d2g)
    sg = 1.0 / (1.0 + np.exp(g / smoothing))  # sigmoid(-g / eps)
    pen = smoothing * np.logaddexp(-g / smoothing, 0.0)
    e1, e2 = -alpha * pen * sg, alpha * (sg * sg + pen * sg * (1 - sg) / smoothing)
    return e1 * dg, e2 * np.outer(dg, dg) + e1 * d2g


def sponge_residual_tangent(x, N, alpha, centre, axis, radius, smoothing, length=np.inf,
                            end_width=0.0):
    """Residual (3m,) N and tangent (3m, 3m) N/mm of a straight rigid sponge's smoothed
    penalty (eyefem.fem.buckle_contact) at the contact points x_q = sum_a N[q, a] x_a of
    the m nodes x (m, 3) mm, each with penalty alpha[q] N/mm: a node (m = 1, N = [[1]]) or
    a face's Gauss points (m = 4). Per point: v = x_q - centre, r = P v with P = I - t t^T
    (t: the unit axis), a = t . v, g = |r| - radius + e(|a|) with the ends' lift e of a
    sponge ``length`` mm long whose ends round off over ``end_width`` mm (0.3 (max(|a| -
    (length / 2 - end_width), 0) / end_width)^3; end_width 0: 10 max(|a| - length / 2,
    0)^2), dg/dx_q = n + e'(|a|) sign(a) t with n = r / |r|, d2g/dx_q^2 = (P - n n^T) / |r|
    + e''(|a|) t t^T; over the nodes dg = N_q (x) dg/dx_q and d2g = N_q N_q^T (x)
    d2g/dx_q^2."""
    m = len(x)
    P = np.eye(3) - np.outer(axis, axis)
    r_tot, K_tot = np.zeros(3 * m), np.zeros((3 * m, 3 * m))
    for Nq, aq in zip(N, alpha):
        v = Nq @ x - centre
        rv = P @ v
        rho = np.linalg.norm(rv)
        n = rv / rho
        a = axis @ v
        if end_width:
            z = max(abs(a) - (length / 2 - end_width), 0.0) / end_width
            e, e1, e2 = 0.3 * z**3, 0.9 * z**2 / end_width, 1.8 * z / end_width**2
        else:
            z = max(abs(a) - length / 2, 0.0)
            e, e1, e2 = 10.0 * z**2, 20.0 * z, 20.0 * (z > 0)
        dg = np.kron(Nq, n + e1 * np.sign(a) * axis)
        d2g = np.kron(np.outer(Nq, Nq), (P - np.outer(n, n)) / rho + e2 * np.outer(axis, axis))
        r_q, K_q = _penalty(rho - radius + e, dg, d2g, aq, smoothing)
        r_tot += r_q
        K_tot += K_q
    return r_tot, K_tot


# --- tangent-verification checks ----------------------------------------------------------------


def _buckle_check(quadrature, end_width=None):
    """A straight rigid sponge (axis y, radius 2.5 mm, 10 mm long) pressing a warped face:
    its four nodes (quadrature 0), or its 2 x 2 Gauss points (quadrature 2), a few
    smoothing lengths deep; with ``end_width`` (mm) the face lies under one of the sponge's
    ends, rounded off over that length."""
    def check(rng):
        import jax
        import jax.numpy as jnp

        from eyefem.fem.buckle_contact import BuckleContact, face_points
        from eyefem.verify.checks import CheckData

        R, rs, L, eps = 10.0, 2.5, 10.0, 0.02
        X = np.array([[10.0, -0.6, -0.5], [10.0, 0.6, -0.5], [10.0, 0.6, 0.5], [10.0, -0.6, 0.5]])
        depth = 0.03
        if end_width is not None:  # under the rounded end (3.9 to 5.1 mm along the axis, its
            X = X + np.array([0.0, 4.5, 0.0])  # Gauss points lifted by 0.001 and 0.18 mm):
            depth = 0.2  # deeper, so that all are in contact
        x = X + np.array([depth, 0.0, 0.0]) + 0.02 * rng.standard_normal((4, 3))
        alpha_node = 30.0
        if quadrature:
            _, N, wJ = face_points(X, np.arange(4)[None], quadrature)
            alpha = alpha_node / (0.25 * wJ.sum()) * wJ  # per unit area: a node's over its area
            data = {"X": np.broadcast_to(X, (len(N), 4, 3)), "N": N}
        else:
            N, alpha = np.eye(4), np.full(4, alpha_node)
            data = {"X": X}
        geo = np.array([R, np.pi / 2, 2.5, 0.0, 0.0, rs, L, 1.0, 0.5])
        frame = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
        data.update({"alpha": alpha, "geo": geo, "frame": frame})
        term = BuckleContact.__new__(BuckleContact)  # the kernel only: no mesh needed
        for k, v in (("shape", "sponge"), ("curved", False), ("extra_dof", -1),
                     ("smoothing", eps), ("end_width", end_width or 0.0)):
            object.__setattr__(term, k, v)
        params = {k: jnp.zeros(1) for k in ("d", "s", "ridge", "dr", "rot")}

        def energy(u):
            uu = u.reshape(4, 3)
            q_loc = jnp.broadcast_to(uu.ravel(), (len(N), 12)) if quadrature else uu
            return jnp.sum(term.local_energy(q_loc, params, data))

        grad = jax.jit(jax.grad(energy))
        u = (x - X).ravel()
        r_h, K_h = sponge_residual_tangent(x, N, alpha, np.array([R + rs, 0.0, 0.0]),
                                           frame[2], rs, eps, L, end_width or 0.0)
        gaps = np.asarray(term.gaps(
            jnp.broadcast_to(jnp.asarray(u), (len(N), 12)) if quadrature
            else jnp.asarray(u.reshape(4, 3)), params, data))
        return CheckData(np.asarray(grad(jnp.asarray(u))), r_h,
                         np.asarray(jax.hessian(energy)(jnp.asarray(u))), K_h,
                         lambda y: np.asarray(grad(jnp.asarray(y))), u,
                         f"sponge on a warped face, gaps {min(gaps):.3f}..{max(gaps):.3f} mm, "
                         + (f"{quadrature}x{quadrature} Gauss points" if quadrature
                            else "its 4 nodes")
                         + (f", under an end rounded over {end_width} mm" if end_width else ""))

    return check


def _rigid_check(rng):
    import jax
    import jax.numpy as jnp

    from eyefem.fem.rigid_contact import RigidContact
    from eyefem.verify.checks import CheckData

    n = rng.standard_normal(3)
    n /= np.linalg.norm(n)
    c = rng.standard_normal(3)
    dirv = rng.standard_normal(3)
    dirv /= np.linalg.norm(dirv)
    d = 0.3
    X = c + d * dirv + 0.1 * rng.standard_normal(3)
    x = X - (((X - c - d * dirv) @ n) + 0.05) * n + 0.02 * rng.standard_normal(3)  # g ~ -0.05
    alpha = 50.0
    data = {"X": X[None], "c": c[None], "n": n[None], "dir": dirv[None], "dir2": np.zeros((1, 3)),
            "body": np.zeros(1, int),
            "w": np.ones(1), "alpha": np.full(1, alpha), "area": np.ones(1)}
    params = {"d": jnp.array([d]), "s": jnp.zeros(1)}

    term = RigidContact.__new__(RigidContact)  # the kernel only: no mesh needed

    def energy(u):
        return jnp.sum(term.local_energy(u.reshape(1, 3), params, data))

    grad = jax.jit(jax.grad(energy))
    u = x - X
    r_h, K_h = rigid_residual_tangent(x, c + d * dirv, n, alpha)
    return CheckData(np.asarray(grad(jnp.asarray(u))), r_h,
                     np.asarray(jax.hessian(energy)(jnp.asarray(u))), K_h,
                     lambda y: np.asarray(grad(jnp.asarray(y))), u,
                     f"gap {float((x - c - d * dirv) @ n):.3f} mm, moving body")


def _surface_check(mode, smoothing=None, nodal=False):
    def check(rng):
        import jax
        import jax.numpy as jnp

        from eyefem.fem.contact import SurfaceContact
        from eyefem.verify.checks import CheckData

        X = np.array([[0.3, 0.4, 0.2], [0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
        x5 = X + 0.08 * rng.standard_normal((5, 3))
        xi = rng.uniform(-0.6, 0.6, 2)
        N, _ = quad_shape(xi)
        # penetrating by ~0.05 mm; smoothed: a gap within a few eps of touching
        depth = 0.05 if smoothing is None else 0.5 * smoothing
        x5[0] = N @ x5[1:] + np.array([0.01, -0.02, -depth])
        alpha = 40.0
        data = {"X": X[None], "xi": xi[None], "w": np.ones(1), "alpha": np.full(1, alpha),
                "area": np.ones(1), "eps": np.full(1, smoothing or 1.0)}
        n4 = None
        if nodal:  # nodal normals tilted off the face's, as on a curved surface
            n4 = (np.array([[-0.2, -0.2, 1.0], [0.2, -0.2, 1.0], [0.2, 0.2, 1.0], [-0.2, 0.2, 1.0]])
                  + 0.05 * rng.standard_normal((4, 3)))
            n4 /= np.linalg.norm(n4, axis=1, keepdims=True)
            data["n4"] = n4[None]
        term = SurfaceContact.__new__(SurfaceContact)  # the kernel only: no mesh needed
        object.__setattr__(term, "mode", mode)
        object.__setattr__(term, "smoothing", smoothing)

        def energy(u):
            return jnp.sum(term.local_energy(u.reshape(1, 15), {"scale": 1.0}, data))

        grad = jax.jit(jax.grad(energy))
        u = (x5 - X).ravel()
        r_h, K_h = node_quad_residual_tangent(x5, xi, alpha, mode, smoothing, n4)
        return CheckData(np.asarray(grad(jnp.asarray(u))), r_h,
                         np.asarray(jax.hessian(energy)(jnp.asarray(u))), K_h,
                         lambda y: np.asarray(grad(jnp.asarray(y))), u,
                         f"node on a warped quad, {mode}"
                         + (f", smoothed (eps {smoothing} mm)" if smoothing else "")
                         + (", Nagata patch of nodal normals" if nodal else ""))

    return check


def contact_checks() -> dict:
    """The contact terms' tangent checks, by name (eyefem.verify.tangents.term_checks)."""
    return {
        "rigid_contact": _rigid_check,
        "surface_contact_sliding": _surface_check("sliding"),
        "surface_contact_sticking": _surface_check("sticking"),
        "surface_contact_smoothed": _surface_check("sliding", smoothing=0.02),
        "surface_contact_nodal_normals": _surface_check("sliding", smoothing=0.02, nodal=True),
        "buckle_contact_nodes": _buckle_check(0),
        "buckle_contact_faces": _buckle_check(2),
        "buckle_contact_sponge_end": _buckle_check(2, end_width=1.0),
    }
