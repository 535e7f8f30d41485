"""Hand-coded (numpy) residual and tangent of a closed fluid cavity, and its tangent check."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.cavity import FluidCavity
from eyefem.fem.mesh import HEX_CORNERS, HEX_FACES, Mesh, quad_gauss_points, quad_shape
from eyefem.fem.surface import face_cone_volume
from eyefem.fem.units import MMHG
from eyefem.verify.checks import CheckData, random_deformation
from eyefem.verify.handcoded import pressure_face_residual_tangent


def cavity_residual_tangent(x, faces, p_ini, v_ini, bulk, dv=0.0, c_out=0.0):
    """Hand-coded residual (3 n,) and dense tangent (3 n, 3 n) of one closed cavity.

    Classical formulas, no autodiff (x: (n, 3) current node positions, mm; faces
    (n_f, 4), normals into the liquid):

        V = -sum_f 1/3 int x . (x_xi x x_eta) dxi deta          (2x2 Gauss, exact)
        g = dV/dx = -sum_f int N_a (x_xi x x_eta)               (closed surface)
        H = d2V/dx2 = -sum_f int N_a [N_b,eta skew(x_xi) - N_b,xi skew(x_eta)]
        r = -P g,   K = -P H + K_eff / V_ini g g^T

    Returns: (r, K, P (MPa), V (mm^3)).
    """
    xg, wg = quad_gauss_points()
    N, dN = quad_shape(xg)
    n = len(x)
    g = np.zeros(3 * n)
    H = np.zeros((3 * n, 3 * n))
    V = 0.0
    for f in faces:
        xf = x[f]
        for k in range(4):
            V -= wg[k] * (N[k] @ xf) @ np.cross(dN[k, :, 0] @ xf, dN[k, :, 1] @ xf) / 3.0
        rf, kf = pressure_face_residual_tangent(xf, -1.0)
        d = (3 * f[:, None] + np.arange(3)).ravel()
        g[d] += rf
        H[np.ix_(d, d)] += kf
    keff = bulk / (1.0 + bulk * c_out / v_ini)
    P = p_ini - keff * (V - v_ini - dv) / v_ini
    return -P * g, -P * H + keff / v_ini * np.outer(g, g), P, V


def cavity_check(rng):
    """Cavity term on the boundary of a deformed hexahedron (liquid inside), with injected
    volume and outflow compliance: hand-coded vs autodiff vs finite differences."""
    X = HEX_CORNERS * 0.5
    x = (X @ random_deformation(rng, 0.3).T + 0.05 * rng.standard_normal((8, 3))).ravel()
    faces = HEX_FACES[:, ::-1]  # normals into the enclosed region
    mesh = Mesh(X, np.arange(8)[None], [0], face_sets={"c": faces})
    u = x - X.ravel()
    v_def = -float(np.sum(face_cone_volume(jnp.asarray(x.reshape(8, 3)[faces]), jnp.zeros(3))))
    # V_ini above the deformed volume, some liquid drained: a pressure rise of tens of mmHg
    term = FluidCavity("cav", mesh, "c", p_ini=0.002, bulk=2.0, v_ini=1.005 * v_def,
                       outflow_compliance=0.1)
    p = {**term.params, "dv": -0.002 * v_def}
    E = jax.jit(lambda y: term.energy(y, p, term.data, term.dofs))
    grad = jax.jit(jax.grad(E))
    # the term's own split: sparse face blocks + rank-one part
    gl, Hl = term.grad_hess(jnp.asarray(u), p, term.data, term.dofs)
    dofs = term.dofs
    r_ad = np.bincount(dofs.ravel(), np.asarray(gl).ravel(), minlength=24)
    K_ad = np.zeros((24, 24))
    np.add.at(K_ad, (dofs[:, :, None], dofs[:, None, :]), np.asarray(Hl))
    for al, v in term.low_rank(u, p, term.data, dofs):
        K_ad += al * np.outer(v, v)
    H_full = np.asarray(jax.hessian(E)(jnp.asarray(u)))
    if not np.allclose(K_ad, H_full, rtol=0, atol=1e-12 * np.abs(H_full).max()):
        raise AssertionError("cavity: face blocks + low rank differ from the autodiff Hessian")
    r, K, P, V = cavity_residual_tangent(x.reshape(8, 3), faces, p["p_ini"], p["v_ini"],
                                         p["bulk"], p["dv"], p["c_out"])
    return CheckData(r_ad, r, K_ad, K, lambda y: np.asarray(grad(jnp.asarray(y))), u,
                     f"P = {P / MMHG:.2f} mmHg, V/V0 = {V / p['v_ini']:.3f}")
