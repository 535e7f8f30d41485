"""Hand-coded (classical, non-autodiff) residuals and tangents, to verify the autodiff ones.

Q1P0 element (Total Lagrangian, 2x2x2 Gauss), per Gauss point with G = dN/dX (8, 3):

    F = I + u^T G,   C = F^T F,   J = det F
    a = dI1bar/dC = J^(-2/3) (I - I1/3 C^-1)
    b = dI2bar/dC = J^(-4/3) (I1 I - C - 2/3 I2 C^-1)
    S = 2 (W1 a + W2 b) + 2 lambda J C^-1                      (second Piola-Kirchhoff, MPa)
    CC = 2 dS/dC                                                (material tangent, MPa)
    r_ai = int (F S)_iL G_aL dV0                                (internal force, N)
    K_ab,ik = int [ G_aJ F_iI CC_IJKL F_kK G_bL + delta_ik G_aJ S_JL G_bL ] dV0
    K_lambda,ai = int 2 J (F^-T)_iJ G_aJ dV0,   r_lambda = int 2 (J - 1) dV0

Follower pressure on one bilinear face (seed 4.2), x_xi, x_eta the surface tangents:

    r_a = p int N_a (x_xi x x_eta) dxi deta
    K_ab = p int N_a [ N_b,eta skew(x_xi) - N_b,xi skew(x_eta) ] dxi deta

(skew(v) w = v x w). Per face, r differs from the gradient of the cone-volume potential
by boundary-line terms that cancel over a closed surface.
"""

from __future__ import annotations

import numpy as np

from eyefem.fem.mesh import hex_geometry, quad_gauss_points, quad_shape

_I = np.eye(3)
_ISYM = 0.5 * (np.einsum("ik,jl->ijkl", _I, _I) + np.einsum("il,jk->ijkl", _I, _I))


def _powers(x):
    """x^k and its first two derivatives for k = 0..3: three (4,) arrays."""
    p = np.array([1.0, x, x * x, x**3])
    dp = np.array([0.0, 1.0, 2 * x, 3 * x * x])
    ddp = np.array([0.0, 0.0, 2.0, 6 * x])
    return p, dp, ddp


def invariant_derivatives2(i1b, i2b, c):
    """W1, W2, W11, W12, W22 of W = sum c_rs (I1bar-3)^r (I2bar-3)^s at one point."""
    pa, dpa, ddpa = _powers(i1b - 3.0)
    pb, dpb, ddpb = _powers(i2b - 3.0)
    return (dpa @ c @ pb, pa @ c @ dpb, ddpa @ c @ pb, dpa @ c @ dpb, pa @ c @ ddpb)


def _dcinv(ci):
    """d(C^-1)_IJ / dC_KL, symmetrised: (3, 3, 3, 3)."""
    return -0.5 * (np.einsum("ik,lj->ijkl", ci, ci) + np.einsum("il,kj->ijkl", ci, ci))


def stress_and_tangent(F, lam, c):
    """S (3, 3) and CC (3, 3, 3, 3) at one point from F (3, 3), lambda (MPa), c (4, 4)."""
    C = F.T @ F
    J = np.linalg.det(F)
    ci = np.linalg.inv(C)
    i1 = np.trace(C)
    i2 = 0.5 * (i1 * i1 - np.sum(C * C))
    j23, j43 = J ** (-2.0 / 3.0), J ** (-4.0 / 3.0)
    i1b, i2b = j23 * i1, j43 * i2
    w1, w2, w11, w12, w22 = invariant_derivatives2(i1b, i2b, c)
    a = j23 * (_I - i1 / 3.0 * ci)
    bb = j43 * (i1 * _I - C - 2.0 / 3.0 * i2 * ci)
    S = 2.0 * (w1 * a + w2 * bb) + 2.0 * lam * J * ci
    dci = _dcinv(ci)
    da = (-1.0 / 3.0 * np.einsum("ij,kl->ijkl", a, ci)
          + j23 * (-1.0 / 3.0 * np.einsum("ij,kl->ijkl", ci, _I) - i1 / 3.0 * dci))
    db = (-2.0 / 3.0 * np.einsum("ij,kl->ijkl", bb, ci)
          + j43 * (np.einsum("ij,kl->ijkl", _I, _I) - _ISYM
                   - 2.0 / 3.0 * np.einsum("ij,kl->ijkl", ci, i1 * _I - C)
                   - 2.0 / 3.0 * i2 * dci))
    djci = 0.5 * J * np.einsum("ij,kl->ijkl", ci, ci) + J * dci
    dS = 2.0 * (w11 * np.einsum("ij,kl->ijkl", a, a)
                + w12 * (np.einsum("ij,kl->ijkl", a, bb) + np.einsum("ij,kl->ijkl", bb, a))
                + w22 * np.einsum("ij,kl->ijkl", bb, bb) + w1 * da + w2 * db) + 2.0 * lam * djci
    return S, 2.0 * dS


def q1p0_residual_tangent(X, u, lam, coeffs):
    """Residual (25,) and tangent (25, 25) of one Q1P0 element, local dofs u[a, i] then lambda.

    Args: X (8, 3) reference coordinates, mm; u (8, 3) displacements, mm; lam, MPa;
    coeffs (4, 4) c_rs, MPa.
    """
    grad_n, dv, _ = hex_geometry(np.asarray(X, float), np.arange(8)[None])
    r = np.zeros(25)
    K = np.zeros((25, 25))
    for g in range(8):
        G, w = grad_n[0, g], dv[0, g]
        F = _I + u.T @ G
        J = np.linalg.det(F)
        S, CC = stress_and_tangent(F, lam, coeffs)
        P = F @ S
        r[:24] += w * (G @ P.T).ravel()
        r[24] += w * 2.0 * (J - 1.0)
        mat = np.einsum("aJ,iI,IJKL,kK,bL->aibk", G, F, CC, F, G)
        geo = np.einsum("aJ,JL,bL->ab", G, S, G)
        K[:24, :24] += w * (mat + np.einsum("ab,ik->aibk", geo, _I)).reshape(24, 24)
        kl = 2.0 * J * (G @ np.linalg.inv(F)).ravel()
        K[:24, 24] += w * kl
        K[24, :24] += w * kl
    return r, K


def _skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def pressure_face_residual_tangent(x, p):
    """Follower-pressure residual (12,) and load stiffness (12, 12) of one face.

    Args: x (4, 3) current node positions, mm (normal by the node order); p, MPa.
    """
    xg, wg = quad_gauss_points()
    N, dN = quad_shape(xg)
    r = np.zeros((4, 3))
    K = np.zeros((4, 3, 4, 3))
    for g in range(4):
        t1, t2 = dN[g, :, 0] @ x, dN[g, :, 1] @ x
        n = np.cross(t1, t2)
        r += wg[g] * p * N[g][:, None] * n
        for b in range(4):
            kb = dN[g, b, 1] * _skew(t1) - dN[g, b, 0] * _skew(t2)
            K[:, :, b, :] += wg[g] * p * N[g][:, None, None] * kb
    return r.ravel(), K.reshape(12, 12)


def smoothed_bar_residual_tangent(xa, xb, EA, L0, L_rest, eps):
    """Force (6,) and tangent (6, 6) of a tension-only bar with the smoothed stretch
    p = eps softplus((l - L_rest) / eps), energy EA / (2 L0) p^2.

    N = EA / L0 p s (N) with s = sigmoid((l - L_rest) / eps), dN/dl = EA / L0 (s^2 +
    p s (1 - s) / eps); f = [-N n, N n]; k = dN/dl n n^T + N / l (I - n n^T).
    """
    d = np.asarray(xb) - np.asarray(xa)
    l = np.linalg.norm(d)
    n = d / l
    z = (l - L_rest) / eps
    s = 1.0 / (1.0 + np.exp(-z))
    p = eps * np.logaddexp(z, 0.0)
    N = EA / L0 * p * s
    k = EA / L0 * (s * s + p * s * (1 - s) / eps) * np.outer(n, n) + N / l * (_I - np.outer(n, n))
    return np.concatenate([-N * n, N * n]), np.block([[k, -k], [-k, k]])


def bar_residual_tangent(xa, xb, EA, L0, L_rest):
    """Force (6,) and tangent (6, 6) of a bar between points xa, xb (3,), mm.

    N = EA / L0 (l - L_rest) (N), n = (xb - xa) / l;
    f = [-N n, N n];  k = EA / L0 n n^T + N / l (I - n n^T);  K = [[k, -k], [-k, k]].
    """
    d = np.asarray(xb) - np.asarray(xa)
    l = np.linalg.norm(d)
    n = d / l
    N = EA / L0 * (l - L_rest)
    k = EA / L0 * np.outer(n, n) + N / l * (_I - np.outer(n, n))
    return np.concatenate([-N * n, N * n]), np.block([[k, -k], [-k, k]])
